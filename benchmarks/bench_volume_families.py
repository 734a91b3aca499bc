"""Volume estimators on tree families built different ways, seen by different sensors.

For every family (``canopy_kit.sim.families``: the simulator's envelope crowns, lobe unions,
space-colonisation trees, real clouds made into splats), seed, sensor and side, drives the
sensor past each row (``canopy_kit.sim.alley``), thins every tree's returns to 0.1 m voxels
as the volume stage does, and measures each estimator on

- the drive's points (``left``, ``right``: one alley; ``both``),
- the tree's complete foliage (every leaf and branch surface, or a real tree's full cloud),

so that each error splits into what the drive lost (**scan-induced**: drive against the same
estimator on complete foliage) and what the definition means (estimators on complete foliage
against each other and against the envelope where a family has one).

Scans are cached under ``--cache`` (one pickle per family, seed, row, sensor and mount).

    .venv/bin/python benchmarks/bench_volume_families.py scan --families envelope lobe_union grown --seeds 1000 1001
    .venv/bin/python benchmarks/bench_volume_families.py report
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
REAL_CLOUDS = [
    SHARED / "real_trees" / "archi_tree_1.las",
    SHARED / "real_trees" / "archi_tree_2.las",
    SHARED / "real_trees" / "pointcloudset_test_tree.las",
    SHARED / "treels" / "pine.laz",
    SHARED / "treels" / "spruce.laz",
]
REAL_PLOTS = [SHARED / "real_trees" / "treeiso_lpine1_demo.laz"]  # 14 red pines, split by stem
FAMILIES = ["envelope", "lobe_union", "grown", "real"]
SENSORS = ["vlp16", "hdl32", "os1-64", "os1-128"]
TUNE_SEEDS = [1000, 1001]  # what any rule or calibration was fitted on
HELD_OUT_SEEDS = [2000, 2001]  # never looked at while tuning
REAL_SEEDS = [0]  # the real family tunes nothing
DEFAULT_CACHE = ROOT / "out" / "bench_families"


def cache_path(cache: Path, family: str, seed: int, row: str, sensor: str, mount: float) -> Path:
    return cache / f"{family}_s{seed}" / f"{row}_{sensor}_h{mount:g}.pkl"


def scans(cache: Path, family: str, seed: int, sensors: list[str], mount: float = 1.8) -> list:
    """Every ScannedTree of ``family`` and ``seed`` for ``sensors``, driven once and cached."""
    from canopy_kit.sim.families import family_rows, scanned_trees

    out, rows = [], None
    complete: dict[str, list] = {}
    for sensor in sensors:
        if rows is None:
            real = family == "real"
            rows = family_rows(
                family, seed, REAL_CLOUDS if real else (), REAL_PLOTS if real else ()
            )
        for row in rows:
            path = cache_path(cache, family, seed, row.name, sensor, mount)
            if not path.exists():
                start = time.perf_counter()
                trees = scanned_trees(
                    row, sensor, mount, seed=seed, complete=complete.get(row.name)
                )
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix(".tmp")
                tmp.write_bytes(pickle.dumps(trees))
                tmp.rename(path)
                print(
                    f"  {family} s{seed} {row.name} {sensor}: {len(trees)} trees, "
                    f"{time.perf_counter() - start:.1f} s",
                    file=sys.stderr,
                    flush=True,
                )
            trees = pickle.loads(path.read_bytes())
            complete.setdefault(row.name, [t.complete for t in trees])
            for t in trees:
                out.append((seed, sensor, mount, t))
    return out


#: The estimators measured: (label, plugin, parameters). ``foliage_envelope`` is the
#: recommended one; its complete-foliage reference takes the measurand its scan took.
METHODS = [
    ("convex_hull", "convex_hull", {}),
    ("alpha_shape", "alpha_shape", {"alpha": 0.9}),
    ("alpha_hull", "alpha_hull", {"alpha": 0.9}),
    ("slices", "slices", {}),
    ("voxel", "voxel", {}),
    ("adaptive_alpha", "adaptive_alpha", {}),
    ("enclosing_ellipsoid", "enclosing_ellipsoid", {}),
    ("foliage_envelope", "foliage_envelope", {}),
]
RECOMMENDED = "foliage_envelope"


def measure_cloud(xyz: np.ndarray, complete: bool = False) -> dict:
    """Every method's volume of ``xyz`` and what the recommended one chose; on ``complete``
    foliage the recommended one is measured as each of its measurands (``envelope`` and
    ``ellipsoid``), since the reference takes the one the scan took."""
    from canopy_kit.volume import estimate_volume
    from canopy_kit.volume.uncertainty import scan_coverage

    out: dict = {"n_points": len(xyz)}
    if len(xyz) < 8:
        return out
    out["coverage"] = scan_coverage(xyz)
    out["height"] = float(np.ptp(xyz[:, 2]))
    for label, method, params in METHODS:
        if label == RECOMMENDED and complete:
            continue
        r = estimate_volume(xyz, method, **params)
        out[label] = r.volume_m3 if r.valid else np.nan
        if label == RECOMMENDED:
            out.update(
                estimate=r.extra.get("estimate"),
                kind=r.extra.get("crown_kind"),
                fill=r.extra.get("surface_fill"),
                spacing=r.extra.get("spacing"),
                void_m3=r.extra.get("void_m3", 0.0),
                without_voids=r.extra.get("volume_without_voids_m3", np.nan),
            )
    if complete:
        for m in ("envelope", "ellipsoid"):
            r = estimate_volume(xyz, RECOMMENDED, measurand=m)
            out[f"{RECOMMENDED}_{m}"] = r.volume_m3 if r.valid else np.nan
            if m == "envelope":
                out["without_voids"] = r.extra.get("volume_without_voids_m3", np.nan)
    return out


def measurements(cache: Path, family: str, seed: int, sensors: list[str]) -> pd.DataFrame:
    """One row per tree and scan (``complete``, ``left``, ``right``, ``both``) of ``family``,
    ``seed`` and each sensor: every method's volume, cached beside the scans."""
    frames = []
    for sensor in sensors:
        path = cache / f"{family}_s{seed}" / f"measured_{sensor}.pkl"
        if not path.exists():
            start = time.perf_counter()
            rows = []
            complete: dict[tuple, dict] = {}
            for _, _, mount, t in scans(cache, family, seed, [sensor]):
                base = {
                    "family": family,
                    "seed": seed,
                    "sensor": sensor,
                    "mount": mount,
                    "row": t.row,
                    "tree": t.name,
                    "form": t.form,
                    "young": t.young,
                    "envelope_m3": t.envelope_m3,
                }
                key = (t.row, t.name)
                if key not in complete:
                    complete[key] = measure_cloud(t.complete, complete=True)
                rows.append({**base, "scan": "complete", **complete[key]})
                for side, xyz in t.scans.items():
                    rows.append({**base, "scan": side, **measure_cloud(xyz)})
                if getattr(t, "surfaces", None) is not None:  # a real tree's splats, complete
                    rows.append({**base, "scan": "splats", **measure_cloud(t.surfaces, True)})
            tmp = path.with_suffix(".tmp")
            pd.DataFrame(rows).to_pickle(tmp)
            tmp.rename(path)
            print(
                f"  measured {family} s{seed} {sensor}: {len(rows)} clouds, "
                f"{time.perf_counter() - start:.0f} s",
                file=sys.stderr,
                flush=True,
            )
        frame = pd.read_pickle(path)
        if "height" not in frame:  # measured before the height was: read it off the scans
            frame = with_heights(frame, scans(cache, family, seed, [sensor]))
        frames.append(frame)
    return pd.concat(frames, ignore_index=True)


def with_heights(frame: pd.DataFrame, scanned: list) -> pd.DataFrame:
    """``frame`` with each cloud's vertical extent (``height``), from its scans."""
    heights = {}
    for _, _, _, t in scanned:
        heights[(t.row, t.name, "complete")] = float(np.ptp(t.complete[:, 2]))
        for side, xyz in t.scans.items():
            heights[(t.row, t.name, side)] = float(np.ptp(xyz[:, 2])) if len(xyz) else np.nan
    keys = zip(frame["row"], frame["tree"], frame["scan"], strict=True)
    return frame.assign(height=[heights.get(k, np.nan) for k in keys])


SIDE = {"left": "one", "right": "one", "both": "both"}


def errors(df: pd.DataFrame) -> pd.DataFrame:
    """One row per scan (left, right, both) with, per method, ``scan:<m>``: the scan's volume
    over the same method's on complete foliage, minus 1 (the recommended method against its
    complete foliage measured as the measurand the scan took), and ``env:<m>``: against the
    envelope where the family has one."""
    key = ["family", "seed", "sensor", "row", "tree"]
    complete = df[df["scan"] == "complete"].set_index(key)
    scans_ = df[df["scan"].isin(list(SIDE))].copy()
    idx = pd.MultiIndex.from_frame(scans_[key])
    labels = [label for label, _, _ in METHODS]
    for label in labels:
        if label == RECOMMENDED:
            env = complete[f"{RECOMMENDED}_envelope"].reindex(idx).to_numpy()
            ell = complete[f"{RECOMMENDED}_ellipsoid"].reindex(idx).to_numpy()
            ref = np.where(scans_["estimate"].to_numpy() == "ellipsoid", ell, env)
            scans_["reference"] = ref
        else:
            ref = complete[label].reindex(idx).to_numpy()
        scans_[f"scan:{label}"] = scans_[label].to_numpy() / ref - 1
        scans_[f"env:{label}"] = scans_[label] / scans_["envelope_m3"] - 1
    # kinds measured before the "small" and "tall" kinds existed: the same rules on the scan
    from canopy_kit.volume.envelope import TALL_HEIGHT_M, YOUNG_MAX_M3

    small = (scans_["kind"] == "dense") & (scans_["convex_hull"] <= YOUNG_MAX_M3)
    scans_.loc[small, "kind"] = "small"
    if "height" in scans_:
        tall = scans_["kind"].isin(["dense", "small", "thin"]) & (scans_["height"] > TALL_HEIGHT_M)
        scans_.loc[tall, "kind"] = "tall"
    scans_["side"] = scans_["scan"].map(SIDE)
    scans_["age"] = np.where(scans_["young"], "young", "old")
    return scans_


def summary(err: pd.DataFrame, by: list[str], kind: str = "scan") -> pd.DataFrame:
    """Bias / MAPE (%) of every method's ``kind`` error (``scan`` or ``env``) per group."""
    labels = [label for label, _, _ in METHODS]
    g = err.groupby(by, sort=False)
    out = pd.DataFrame({"n": g.size()})
    for label in labels:
        col = f"{kind}:{label}"
        bias = 100 * g[col].mean()
        mape = 100 * g[col].apply(lambda e: e.abs().mean())
        out[label] = bias.map("{:+.1f}".format) + " / " + mape.map("{:.1f}".format)
    return out


CALIBRATED_FAMILIES = ["envelope", "lobe_union", "grown"]


def calibrate(err: pd.DataFrame) -> dict[str, tuple[float, float]]:
    """The recommended estimator's interval ratios (complete-foliage reference / estimate) per
    kind of crown, as ``uncertainty.calibrate_ratios`` makes them, on these scans."""
    from canopy_kit.volume.uncertainty import calibrate_ratios

    ok = err[RECOMMENDED].notna() & err["reference"].notna()
    e = err[ok]
    return calibrate_ratios(e["reference"] / e[RECOMMENDED], e["fill"], calibration_kind(e))


def calibration_kind(err: pd.DataFrame) -> np.ndarray:
    """Each scan's calibration kind: the crown kind, ``/one`` when seen from one side."""
    from canopy_kit.volume.uncertainty import ONE_SIDED

    suffix = np.where(err["side"].to_numpy() == "one", ONE_SIDED, "")
    return np.char.add(err["kind"].astype(str).to_numpy(), suffix)


def covered(err: pd.DataFrame, kinds: dict[str, tuple[float, float]]) -> pd.Series:
    """Whether the interval the shipped rules build from ``kinds`` holds each scan's
    complete-foliage reference (a kind not calibrated takes the widest calibrated range)."""
    return intervals(err, kinds)["inside"]


#: The interval's flags that say a tree is outside what the families calibrated.
WARNINGS = ("taller than every tree", "estimators disagree")


def intervals(err: pd.DataFrame, kinds: dict[str, tuple[float, float]]) -> pd.DataFrame:
    """Per scan: whether the interval the shipped rules build from ``kinds`` holds the
    complete-foliage reference (``inside``), and whether the tree is flagged as outside the
    calibrated families (``flagged``: taller than every calibration tree, or estimators that
    disagree beyond them). A kind not calibrated takes the widest calibrated range."""
    from canopy_kit.volume.uncertainty import interval_bounds

    widest = (min(lo for lo, _ in kinds.values()), max(hi for _, hi in kinds.values()))
    rows = []
    for r, kind in zip(err.itertuples(index=False), calibration_kind(err), strict=True):
        v = getattr(r, RECOMMENDED)
        if not (np.isfinite(v) and np.isfinite(r.reference)):
            rows.append((False, False))
            continue
        others = {m: getattr(r, m) for m in ("convex_hull", "alpha_shape")}
        height = getattr(r, "height", np.nan)
        low, high, flags = interval_bounds(
            RECOMMENDED,
            v,
            kinds.get(kind, kinds.get(r.kind, widest)),
            r.kind,
            r.fill,
            r.coverage,
            {"void_m3": r.void_m3},
            others,
            height if np.isfinite(height) else 0.0,
        )
        flagged = any(w in f for f in flags for w in WARNINGS)
        rows.append((low <= r.reference <= high, flagged))
    return pd.DataFrame(rows, columns=["inside", "flagged"], index=err.index)


def shipped_coverage(err: pd.DataFrame) -> pd.DataFrame:
    """The shipped calibration (``uncertainty.CALIBRATIONS``) on every family's held-out
    seeds (the real family: all of it): coverage, flagged share, coverage of the unflagged."""
    from canopy_kit.volume.uncertainty import CALIBRATIONS

    held = err[~err["seed"].isin(TUNE_SEEDS)]
    checked = held.join(intervals(held, CALIBRATIONS[RECOMMENDED].kinds))
    rows = []
    for (family, age, side), g in checked.groupby(["family", "age", "side"]):
        rows.append({"family": family, "age": age, "side": side, **coverage(g)})
    return pd.DataFrame(rows)


def coverage(scans: pd.DataFrame) -> dict[str, float]:
    """Of these scans (``inside``, ``flagged`` per scan): how many, the % whose interval held
    the value, the % flagged, and the % held among the unflagged."""
    clear = scans[~scans["flagged"]]
    return {
        "n": len(scans),
        "covered %": round(100 * scans["inside"].mean(), 1),
        "flagged %": round(100 * scans["flagged"].mean(), 1),
        "covered, unflagged %": round(100 * clear["inside"].mean(), 1) if len(clear) else np.nan,
    }


def leave_one_family_out(err: pd.DataFrame) -> pd.DataFrame:
    """Per held-out family: the interval calibrated on the other families' tuning seeds, its
    coverage on the held-out family's held-out seeds (the real family: on all of it)."""
    tune = err[err["seed"].isin(TUNE_SEEDS)]
    rows = []
    for family in [*CALIBRATED_FAMILIES, "real"]:
        train = tune[tune["family"].isin([f for f in CALIBRATED_FAMILIES if f != family])]
        kinds = calibrate(train) if not train.empty else {}
        test = err[(err["family"] == family) & ~err["seed"].isin(TUNE_SEEDS)]
        if test.empty or not kinds:
            continue
        checked = intervals(test, kinds)
        for (age, side), g in test.join(checked).groupby(["age", "side"]):
            rows.append(
                {
                    "held out": family,
                    "age": age,
                    "side": side,
                    **coverage(g),
                    "calibrated on": "+".join(f for f in CALIBRATED_FAMILIES if f != family),
                }
            )
    return pd.DataFrame(rows)


def write_summary(err: pd.DataFrame, path: Path) -> None:
    """The table the report quotes (canopy_kit/volume/data/family_accuracy.csv): per family,
    age and side, on held-out seeds (the real family: all of it), every method's scan-induced
    bias, MAPE and p90 of |error|; for the recommended method, how often its interval held
    the complete-foliage value (calibrated without that family: leave one family out)."""
    held = err[~err["seed"].isin(TUNE_SEEDS)].copy()
    tune = err[err["seed"].isin(TUNE_SEEDS)]
    held["covered"], held["flagged"] = np.nan, np.nan
    for family in held["family"].unique():
        train = tune[tune["family"].isin([f for f in CALIBRATED_FAMILIES if f != family])]
        mask = held["family"] == family
        if not train.empty:
            checked = intervals(held[mask], calibrate(train)).astype(float)
            held.loc[mask, "covered"] = checked["inside"]
            held.loc[mask, "flagged"] = checked["flagged"]
    rows = []
    for (family, age, side), g in held.groupby(["family", "age", "side"], sort=False):
        for label, _, _ in METHODS:
            e = g[f"scan:{label}"].dropna()
            rows.append(
                {
                    "family": family,
                    "age": age,
                    "side": side,
                    "method": label,
                    "n": len(e),
                    "bias": e.mean(),
                    "mape": e.abs().mean(),
                    "p90": e.abs().quantile(0.9),
                    "interval_covers": g["covered"].mean() if label == RECOMMENDED else np.nan,
                    "flagged": g["flagged"].mean() if label == RECOMMENDED else np.nan,
                    "seeds": " ".join(map(str, sorted(g["seed"].unique()))),
                    "sensors": " ".join(sorted(g["sensor"].unique())),
                }
            )
    path.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows).to_csv(path, index=False, float_format="%.4f")


AGREEMENT_MARGIN = 0.1  # the ranges are widened by this share on either side


def agreement_ranges(err: pd.DataFrame) -> dict[tuple[str, str, str | None], tuple[float, float]]:
    """The widest ratios between estimators of one tree on these scans, ∓ the margin: what
    ``uncertainty.AGREEMENT`` holds (the recommended one per measurand)."""
    out = {}
    measurand = np.where(err["estimate"] == "ellipsoid", "ellipsoid", "envelope")
    for a, b, of in (
        (RECOMMENDED, "convex_hull", "envelope"),
        (RECOMMENDED, "convex_hull", "ellipsoid"),
        ("alpha_shape", "convex_hull", None),
    ):
        rows = err if of is None else err[measurand == of]
        ratio = (rows[a] / rows[b]).replace([np.inf, -np.inf], np.nan).dropna()
        if len(ratio):
            lo = round(float(ratio.min()) * (1 - AGREEMENT_MARGIN), 2)
            hi = round(float(ratio.max()) * (1 + AGREEMENT_MARGIN), 2)
            out[(a, b, of)] = (lo, hi)
    return out


def flagged_share(err: pd.DataFrame) -> pd.DataFrame:
    """Per family, age and side: the share of scans the shipped agreement ranges flag."""
    from canopy_kit.volume.uncertainty import disagreement

    flags = [
        disagreement(
            RECOMMENDED,
            getattr(r, RECOMMENDED),
            {"convex_hull": r.convex_hull, "alpha_shape": r.alpha_shape},
            r.kind,
        )
        is not None
        for r in err.itertuples(index=False)
    ]
    g = err.assign(flagged=flags).groupby(["family", "age", "side"])["flagged"]
    return (100 * g.mean()).round(1).rename("flagged %").reset_index()


def all_measurements(args: argparse.Namespace) -> pd.DataFrame:
    frames = []
    for family in args.families:
        seeds = args.seeds or (REAL_SEEDS if family == "real" else TUNE_SEEDS + HELD_OUT_SEEDS)
        for seed in seeds:
            frames.append(measurements(args.cache, family, seed, args.sensors))
    return pd.concat(frames, ignore_index=True)


def print_report(args: argparse.Namespace) -> None:
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 40)
    pd.set_option("display.max_rows", 500)
    err = errors(all_measurements(args))
    print(
        "scan-induced error (drive against the same estimator on complete foliage), bias / MAPE %"
    )
    print(summary(err, ["family", "age", "side"]).to_string())
    print("\nby sensor, old trees")
    print(summary(err[~err["young"]], ["family", "sensor", "side"]).to_string())
    env = err[err["envelope_m3"].notna()].copy()
    env["variant"] = env["row"].str.split("-").str[-1]
    print("\nagainst the envelope, bias / MAPE %")
    print(summary(env, ["family", "variant", "age", "side"], "env").to_string())
    tune = err[err["seed"].isin(TUNE_SEEDS) & err["family"].isin(CALIBRATED_FAMILIES)]
    if not tune.empty:
        print(f"\ninterval calibration on every family's tuning seeds {TUNE_SEEDS}:")
        print(f"  {RECOMMENDED}: {calibrate(tune)}")
        print("agreement ranges (uncertainty.AGREEMENT) on the same scans:")
        print(f"  {agreement_ranges(tune)}")
        print("\nshare of scans the shipped agreement ranges flag:")
        print(flagged_share(err).to_string(index=False))
        print("\nleave-one-family-out coverage of the interval:")
        print(leave_one_family_out(err).to_string(index=False))
        print("\nthe shipped interval (uncertainty.CALIBRATIONS) on held-out seeds:")
        print(shipped_coverage(err).to_string(index=False))
    if args.summary:
        write_summary(err, args.summary)
        print(f"\nwrote {args.summary}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    scan = sub.add_parser("scan", help="drive every row and cache the scans")
    scan.add_argument("--families", nargs="+", default=FAMILIES, choices=FAMILIES)
    scan.add_argument("--seeds", nargs="+", type=int, default=None)
    scan.add_argument("--sensors", nargs="+", default=SENSORS)
    scan.add_argument("--mount", type=float, default=1.8)
    scan.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    measure = sub.add_parser("measure", help="measure every estimator on the cached scans")
    report = sub.add_parser("report", help="print the tables of docs/VOLUMES.md")
    report.add_argument(
        "--summary",
        type=Path,
        default=None,
        help="write the table the report quotes (canopy_kit/volume/data/family_accuracy.csv)",
    )
    for p in (measure, report):
        p.add_argument("--families", nargs="+", default=FAMILIES, choices=FAMILIES)
        p.add_argument("--seeds", nargs="+", type=int, default=None)
        p.add_argument("--sensors", nargs="+", default=SENSORS)
        p.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    args = parser.parse_args()
    if args.command == "report":
        print_report(args)
        return
    for family in args.families:
        seeds = args.seeds or (REAL_SEEDS if family == "real" else TUNE_SEEDS + HELD_OUT_SEEDS)
        for seed in seeds:
            if args.command == "scan":
                scans(args.cache, family, seed, args.sensors, args.mount)
            else:
                measurements(args.cache, family, seed, args.sensors)


if __name__ == "__main__":
    main()
