"""Volume accuracy matrix: estimator × crown form × sensor × scan side, on trees the pipeline
segmented (issue 25).

Per sensor model and crown form, simulates a 2-row × 4-tree pistachio session on held-out
seeds (never used to tune anything; cached under ``--cache``), builds the map with the true
poses (odometry error left out: docs/MAPPING.md measures it), segments it with the
``adaptive`` preset's segmenter exactly as ``canopy-kit run`` does, matches segments to the
simulator's trees (IoU ≥ 0.5 of the points) and measures every matched tree with the
volume stage of the pipeline (the same code and settings as trees.csv):

- ``both``: the tree's segment as the pipeline cut it (the crown seen from both alleys);
- ``one-sided``: the same segment as a drive along one alley alone would have mapped it:
  the map of that alley's sweeps only (``canopy_kit.evaluate.truth_map.alley_maps``), with the
  segment's labels carried over (each side counted once). Until 2026-12-04 this was a split
  of the whole map by the alley of each kept point, which gave the alley driven first every
  voxel both alleys saw (docs/history/VOLUMES_LOG.md).

Signed bias, MAPE and p90 of |error| against the simulator's exact envelope volume, and
how often the recommended estimator's interval holds the truth, per cell and overall.

    .venv/bin/python benchmarks/bench_volume_matrix.py [--sensors vlp16 os1-128] [--forms lobed]
        [--seeds 431] [--csv out/volume_matrix.csv]

The summary is what docs/history/VOLUMES_LOG.md "Accuracy matrix" quotes and what the report states as
the recommended estimator's measured bias (canopy_kit/volume/data/accuracy.csv).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

SENSORS = ["vlp16", "hdl32", "os1-64", "os1-128"]
FORMS = ["ellipsoid", "lobed", "vase", "hedged", "sparse"]
HELD_OUT_SEEDS = [431]
ESTIMATORS = ["convex_hull", "alpha_shape", "adaptive_alpha", "foliage_envelope"]
RECOMMENDED = "foliage_envelope"  # the adaptive preset's [volume] recommended


def session(cache: Path, sensor: str, form: str, seed: int, orchard: dict | None = None) -> Path:
    """A simulated session (cached): 2 rows × 4 trees, no IMU/GNSS (true poses map it);
    ``orchard`` adds ``[orchard]`` settings (e.g. deeper lobes, a leaf depth)."""
    from canopy_kit.sim import load_sim_config, simulate_session

    variant = "".join(f"_{k}={v}" for k, v in sorted((orchard or {}).items())).replace(" ", "")
    root = cache / f"{sensor}_{form}_s{seed}{variant}"
    if not (root / "truth").exists():
        overrides = {
            "seed": seed,
            "orchard": {"rows": 2, "trees_per_row": 4, "crown_form": form, **(orchard or {})},
            "imu": {"enabled": False},
            "gnss": {"enabled": False},
        }
        print(f"simulating {root.name} ...", file=sys.stderr, flush=True)
        simulate_session(
            root, load_sim_config("pistachio", overrides, sensor=sensor), fmt="ros1", overwrite=True
        )
    return root


def evaluate_session(
    root: Path,
    sensor: str,
    form: str,
    seed: int,
    extra: tuple[str, ...] = (),
    reference: str = "envelope",
) -> pd.DataFrame:
    """One row per matched tree, scan (both, left, right) and method, plus interval rows;
    ``extra`` estimators are measured beside the preset's; ``reference``: ``envelope`` (the
    simulator's crown volume) or ``foliage`` (each method on the tree's complete foliage)."""
    from dataclasses import replace

    from canopy_kit.config import load_preset
    from canopy_kit.evaluate.volume_accuracy import segmented_volume_errors

    config = load_preset("adaptive")
    methods = list(dict.fromkeys([*ESTIMATORS, *extra]))
    volume = replace(config.volume, methods=list(dict.fromkeys([*config.volume.methods, *extra])))
    t0 = time.perf_counter()
    errors, score = segmented_volume_errors(
        root, replace(config, volume=volume), methods, reference=reference
    )
    print(
        f"  {root.name}: {score.n_correct}/{score.n_truth} trees segmented one-to-one, "
        f"{time.perf_counter() - t0:.1f} s",
        file=sys.stderr,
        flush=True,
    )
    errors = errors.assign(sensor=sensor, form=form, seed=seed)
    errors.attrs["segmented"] = (score.n_correct, score.n_truth)
    return errors


def summarise(errors: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    """Signed bias, MAPE, p90 |error| per group and method; interval coverage per group."""
    scan = np.where(errors["scan"] == "both", "both", "one-sided")
    df = errors.assign(scan=scan)
    est = df[df["method"] != "interval"].assign(abs_error=lambda d: d["error"].abs())
    table = (
        est.groupby([*by, "method"], sort=False)
        .agg(
            n=("error", "size"),
            bias=("error", "mean"),
            mape=("abs_error", "mean"),
            p90=("abs_error", lambda a: float(np.quantile(a, 0.9))),
        )
        .reset_index()
    )
    cover = df[df["method"] == "interval"].groupby(by, sort=False)["covered"].mean()
    table = table.join(cover.rename("interval_covers"), on=by)
    # the interval columns bound the preset's recommended estimator only
    table.loc[table["method"] != RECOMMENDED, "interval_covers"] = np.nan
    return table


def calibrate(errors: pd.DataFrame) -> dict[str, dict[str, tuple[float, float]]]:
    """Per estimator in the rows (``--extra-estimators`` too): ``uncertainty.calibrate_ratios``
    (per kind of crown, from the interval rows' surface fill), what uncertainty.CALIBRATIONS
    holds."""
    from canopy_kit.volume.uncertainty import calibrate_ratios

    key = ["sensor", "form", "seed", "scan", "tree"]
    if "variant" in errors:
        key.insert(0, "variant")
    interval = errors[errors["method"] == "interval"].set_index(key)
    tree = pd.DataFrame({"tree_fill": interval["fill"]})
    # the interval's own kind (CSVs written before 2026-12-05 have none: the fill's)
    tree["tree_kind"] = interval["kind"] if "kind" in interval else None
    out = {}
    for method in dict.fromkeys(errors.loc[errors["method"] != "interval", "method"]):
        est = errors[errors["method"] == method].join(tree, on=key)
        ratio = est["true_volume_m3"] / est["volume_m3"]
        # the interval rows' kind is the recommended estimator's; the others go by the fill
        kinds = est["tree_kind"] if method == RECOMMENDED else None
        out[method] = calibrate_ratios(ratio, est["tree_fill"], kinds)
    return out


def write_summary(errors: pd.DataFrame, path: Path) -> None:
    """The accuracy table the report quotes: per scan over every form (``all``), over the
    forms whose foliage outlines the envelope (``dense``: all but ``sparse``), and per form;
    the preset's estimators only (not ``--extra-estimators``)."""
    errors = errors[errors["method"].isin([*ESTIMATORS, "interval"])]
    overall = summarise(errors, ["scan"]).assign(form="all")
    dense = summarise(errors[errors["form"] != "sparse"], ["scan"]).assign(form="dense")
    table = pd.concat([overall, dense, summarise(errors, ["scan", "form"])], ignore_index=True)
    table["sensors"] = " ".join(sorted(errors["sensor"].unique()))
    table["seeds"] = " ".join(str(s) for s in sorted(errors["seed"].unique()))
    columns = [
        "scan",
        "form",
        "method",
        "n",
        "bias",
        "mape",
        "p90",
        "interval_covers",
        "sensors",
        "seeds",
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    table[columns].to_csv(path, index=False, float_format="%.4f")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sensors", nargs="+", default=SENSORS)
    parser.add_argument("--forms", nargs="+", default=FORMS)
    parser.add_argument("--seeds", nargs="+", type=int, default=HELD_OUT_SEEDS)
    parser.add_argument("--cache", type=Path, default=Path("out/bench_volume_matrix"))
    parser.add_argument("--csv", type=Path, default=None, help="write every tree's row here")
    parser.add_argument(
        "--summary",
        type=Path,
        default=None,
        help="write the per-scan and per-form summary the report quotes here "
        "(canopy_kit/volume/data/accuracy.csv)",
    )
    parser.add_argument(
        "--orchard-set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="[orchard] settings for harsher crowns, values as TOML, e.g. "
        "'lobe_hollow_range=[0.25, 0.35]' leaf_penetration_m=0.3",
    )
    parser.add_argument(
        "--extra-estimators",
        nargs="+",
        default=[],
        metavar="NAME",
        help="estimators measured beside the preset's on the same trees (e.g. "
        "enclosing_ellipsoid); they do not enter --summary's report table",
    )
    parser.add_argument(
        "--reference",
        choices=["envelope", "foliage"],
        default="envelope",
        help="the truth each volume is compared with: the simulator's crown envelope, or the "
        "same estimator on the tree's complete foliage (what the drive and the segmentation "
        "lost; the recommended estimator's interval is meant to hold it)",
    )
    parser.add_argument(
        "--calibrate",
        action="store_true",
        help="print the interval's calibration (uncertainty.CALIBRATIONS) from these rows: run "
        "it on the tuning seeds (401 402) only",
    )
    parser.add_argument(
        "--from-csv",
        type=Path,
        nargs="+",
        default=None,
        help="summarise the rows previous runs wrote with --csv (no simulation)",
    )
    args = parser.parse_args()
    if args.from_csv:
        errors = pd.concat([pd.read_csv(path) for path in args.from_csv], ignore_index=True)
        print(f"rows of {' '.join(map(str, args.from_csv))}")
        _report(errors, args)
        return
    import tomllib

    orchard = tomllib.loads("\n".join(args.orchard_set)) if args.orchard_set else None
    variant = " ".join(args.orchard_set) or "default"
    parts = []
    segmented = [0, 0]
    for sensor in args.sensors:
        for form in args.forms:
            for seed in args.seeds:
                root = session(args.cache, sensor, form, seed, orchard)
                part = evaluate_session(
                    root, sensor, form, seed, tuple(args.extra_estimators), args.reference
                )
                segmented = [a + b for a, b in zip(segmented, part.attrs["segmented"], strict=True)]
                parts.append(part.assign(variant=variant))
    errors = pd.concat(parts, ignore_index=True)
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        errors.to_csv(args.csv, index=False)
    print(f"trees segmented correctly: {segmented[0]}/{segmented[1]} (adaptive preset, IoU ≥ 0.5)")
    _report(errors, args)


def _report(errors: pd.DataFrame, args: argparse.Namespace) -> None:
    if args.calibrate:
        print("calibration (uncertainty.CALIBRATIONS):")
        for method, ratios in calibrate(errors).items():
            print(f"  {method}: {ratios}")
    if args.summary:
        write_summary(errors, args.summary)
    pd.set_option("display.width", 200)
    pct = {
        "bias": "{:+.1%}".format,
        "mape": "{:.1%}".format,
        "p90": "{:.1%}".format,
        "interval_covers": "{:.0%}".format,
    }
    for by in (["scan"], ["scan", "form"], ["scan", "sensor"]):
        print(f"\nby {' × '.join(by)}:")
        print(summarise(errors, by).to_string(index=False, formatters=pct))


if __name__ == "__main__":
    main()
