"""Segmentation benchmarks: accuracy over simulated sessions, and time/memory per row.

    python benchmarks/bench_segment.py accuracy --orchards pistachio almond --seeds 101 102
    python benchmarks/bench_segment.py speed --rows 1 2 4 10
    python benchmarks/bench_segment.py table --seeds 201 202 203
    python benchmarks/bench_segment.py real      # lidR's labelled MixedConifer scan

``accuracy`` simulates sessions (cached in ``--cache``: the map from the true poses and the
truth folder; the bag is deleted), runs every method on each, scores it (point IoU,
footprint IoU) and the ceiling the exact crown envelopes allow, appends one line per
method and session to ``--csv`` and prints the table method x orchard -> success rate.
``speed`` times the segmenters and Open3D's and scikit-learn's DBSCAN on the same canopy
points of maps with more and more rows (the two rows of one simulated session repeated
across), each run in a fresh process for its peak memory.
``real`` scores every method on the labelled airborne scan in ../shared/data/lidr;
``table`` prints the reproduction table of docs/SEGMENTATION.md from the saved results;
``figures`` draws the top views and failure galleries in docs/figures. ``accuracy``,
``figures`` and ``real`` run DEFAULT_METHODS unless ``--methods`` says otherwise: the
paper's two, ``dbscan_spectral_scaled`` (its almond method with the almond-scaled preset's
settings) and ``adaptive``. The numbers in
docs/SEGMENTATION.md and docs/BENCHMARKS.md come from these commands.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.config import load_preset

PAPER = {
    "dbscan": {"eps": 0.8, "min_samples": 1300},
    "dbscan_spectral": {
        "eps": 0.8,
        "min_samples": 1300,
        "max_cluster_size": 45000,
        "n_neighbors": 10,
    },
    "adaptive": {},
    # the `wall` preset's segmenter (canopy_kit/presets/wall.toml): fruiting walls and hedgerows
    "wall": {"cut": "trunk-midpoints"},
}
# the paper's almond method with its split threshold and graph at our map's scale, as the
# shipped preset sets it (canopy_kit/presets/almond-scaled.toml)
PAPER["dbscan_spectral_scaled"] = dict(load_preset("almond-scaled").segment.params)
# only the graph at our scale, the paper's threshold (an ablation)
PAPER["dbscan_spectral_cells"] = {
    **PAPER["dbscan_spectral_scaled"],
    "max_cluster_size": PAPER["dbscan_spectral"]["max_cluster_size"],
}
#: what the benchmark runs unless told (the ablation only when asked for)
DEFAULT_METHODS = ["dbscan", "dbscan_spectral", "dbscan_spectral_scaled", "adaptive"]
#: method names of this benchmark that run a segmenter under another name
SEGMENTER = {
    "dbscan_spectral_scaled": "dbscan_spectral",
    "dbscan_spectral_cells": "dbscan_spectral",
    "wall": "adaptive",
}


def bench_segmenter(method: str):
    """The segmenter behind a method name of this benchmark, with its settings."""
    from canopy_kit.segment.verb import make_segmenter

    return make_segmenter(SEGMENTER.get(method, method), PAPER[method])


# -- sessions ----------------------------------------------------------------------------
def session_map(
    cache: Path,
    orchard: str,
    rows: int,
    trees: int,
    seed: int,
    overrides: dict | None = None,
    sensor: str | None = None,
    tag: str = "",
):
    """(map PointCloud with tree_id, sim dir): simulated once, then read from the cache."""
    from canopy_kit.config import merge
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.evaluate.truth_map import truth_map
    from canopy_kit.sim import load_sim_config, simulate_session
    from canopy_kit.sim.session import find_bag
    from canopy_kit.sim.truth import load_truth

    name = f"{orchard}_{rows}x{trees}_s{seed}{tag}"
    sim_dir, npz = cache / name, cache / f"{name}.npz"
    if not npz.exists():
        base = {"seed": seed, "orchard": {"rows": rows, "trees_per_row": trees}}
        cfg = load_sim_config(orchard, merge(base, overrides or {}), sensor=sensor)
        simulate_session(sim_dir, cfg, overwrite=True)
        m = truth_map(sim_dir, voxel_size=0.05)
        np.savez(npz, xyz=m.xyz, tree_id=m.fields["tree_id"], intensity=m.fields["intensity"])
        bag = find_bag(sim_dir)
        shutil.rmtree(bag) if bag.is_dir() else bag.unlink()
    d = np.load(npz)
    frame = load_truth(sim_dir).frame
    cloud = PointCloud(
        d["xyz"],
        {"tree_id": d["tree_id"], "intensity": d["intensity"]},
        crs=frame.crs,
        origin=frame.origin,
    )
    return cloud, sim_dir, name


def score_session(cloud, sim_dir: Path, methods: list[str]) -> list[dict]:
    """Every method on one map: success by point and by footprint IoU, plus the ceiling."""
    from canopy_kit.evaluate.segmentation_score import (
        envelope_ceiling,
        score_footprints,
        score_point_labels,
        truth_footprints,
    )
    from canopy_kit.evaluate.wall_cuts import cut_labels, is_wall_truth
    from canopy_kit.segment.rows import driving_direction_from_trajectory
    from canopy_kit.segment.verb import segment
    from canopy_kit.sim.truth import load_truth

    truth = load_truth(sim_dir)
    tl = truth.trees.set_index("tree_id")[["row", "label"]]
    true_ids = cloud.fields["tree_id"]
    if is_wall_truth(truth.trees):  # a wall's tree is its trunk-midpoint cut, as a run scores it
        true_ids = cut_labels(cloud.xyz[:, :2], true_ids, truth.trees)
    direction = driving_direction_from_trajectory(truth.trajectory[["x", "y"]].to_numpy())
    footprints = truth_footprints(sim_dir)
    ceiling = score_point_labels(envelope_ceiling(cloud.xyz, sim_dir), true_ids)
    out = []
    for method in methods:
        t0 = time.perf_counter()
        seg = segment(
            cloud,
            bench_segmenter(method),
            driving_direction=direction,
            direction_source="trajectory",
        )
        elapsed = time.perf_counter() - t0
        pl = seg.table().set_index("segment_id")[["row", "label"]]
        pts = score_point_labels(seg.labels, true_ids, truth_labels=tl, pred_labels=pl)
        fp = score_footprints(seg.footprints, footprints, truth_labels=tl, pred_labels=pl)
        out.append(
            {
                "method": method,
                "n_truth": pts.n_truth,
                "n_predicted": pts.n_predicted,
                "success_points": pts.success_rate,
                "precision_points": pts.precision,
                "success_footprints": fp.success_rate,
                "ceiling_points": ceiling.success_rate,
                "n_merged": pts.n_merged,
                "n_split": pts.n_split,
                "n_other": pts.n_other,
                "f1_points": pts.f1,
                "label_accuracy": pts.label_accuracy,
                "seconds": round(elapsed, 2),
                "warnings": " | ".join(seg.warnings),
            }
        )
    return out


def accuracy(args: argparse.Namespace) -> None:
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    from canopy_kit.cli.common import parse_overrides

    overrides = parse_overrides(args.set) if args.set else {}
    rows = []
    for orchard in args.orchards:
        for seed in args.seeds:
            cloud, sim_dir, name = session_map(
                cache,
                orchard,
                args.rows,
                args.trees_per_row,
                seed,
                overrides,
                args.sensor,
                args.tag,
            )
            for r in score_session(cloud, sim_dir, args.methods):
                r.update(
                    {
                        "orchard": orchard,
                        "seed": seed,
                        "session": name,
                        "variant": args.tag.strip("_") or "default",
                    }
                )
                rows.append(r)
                print(json.dumps(r), file=sys.stderr, flush=True)
    df = pd.DataFrame(rows)
    if args.csv:
        path = Path(args.csv)
        old = pd.read_csv(path) if path.exists() else pd.DataFrame()
        if len(old):
            old = old[
                ~old.set_index(["session", "method"]).index.isin(
                    df.set_index(["session", "method"]).index
                )
            ]
        pd.concat([old, df], ignore_index=True).to_csv(path, index=False, float_format="%.4f")
    from canopy_kit.paper.segmentation_results import success_table

    print(success_table(df).to_string(float_format=lambda v: f"{v:.3f}"))


# -- speed -------------------------------------------------------------------------------
def _rss_mb(field: str) -> float:
    """VmRSS / VmHWM of this process in MB (Linux), NaN elsewhere."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return float(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _measure(job: str, npz: str, queue) -> None:  # runs in a fresh process
    import resource

    d = np.load(npz)
    xyz, w = np.array(d["xyz"]), np.array(d["weight"])
    stems = np.array(d["stems"])
    # ru_maxrss of a spawned child starts at its parent's RSS (Linux keeps the high-water
    # mark across exec): reset the peak (clear_refs 5) and read VmHWM instead.
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    base = _rss_mb("VmRSS")
    t0 = time.perf_counter()
    if job == "open3d":
        import open3d as o3d

        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        # Open3D has no sample weights: N_min in voxels, scaled by the mean map points per voxel.
        labels = np.asarray(pc.cluster_dbscan(0.8, int(round(1300 / w.mean())), False))
    elif job == "sklearn":
        from sklearn.cluster import DBSCAN

        labels = DBSCAN(eps=0.8, min_samples=1300).fit_predict(xyz, sample_weight=w)
    else:
        kwargs = {"sample_weight": w}
        if job == "adaptive":
            kwargs["stem_xyz"] = stems
        labels = bench_segmenter(job).fit_predict(xyz, **kwargs)
    seconds = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    # CPU seconds (all threads): robust to other jobs on a shared machine, unlike wall time.
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    peak = _rss_mb("VmHWM")
    queue.put(
        {
            "seconds": seconds,
            "cpu_s": cpu,
            "peak_mb": peak,
            "base_mb": base,
            "delta_mb": peak - base,
            "n_clusters": int(np.max(labels)) + 1,
        }
    )


def repeated_rows(cloud, sim_dir: Path, n_rows: int):
    """A map of ``n_rows`` rows made by repeating the two rows of a simulated session.

    The block between the middle of the alleys left of row 0 and right of row 1 is copied
    across the rows (same point density, crowns, trunks and ground as simulated); the
    outermost copies keep the scanned margins.
    """
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.sim.truth import load_truth

    info = load_truth(sim_dir).info
    right = np.asarray(info["right_direction"])
    spacing = float(np.diff(info["row_offsets"])[0])
    across = cloud.xyz[:, :2] @ right
    parts = []
    for k in range((n_rows + 1) // 2):
        lo = -np.inf if k == 0 else -0.5 * spacing
        last = k == (n_rows + 1) // 2 - 1
        hi = (0.5 if n_rows % 2 and last else 1.5) * spacing
        hi = np.inf if last and not n_rows % 2 else hi
        m = (across >= lo) & (across < hi)
        xyz = cloud.xyz[m].copy()
        xyz[:, :2] += 2 * k * spacing * right
        parts.append(PointCloud(xyz, {"tree_id": cloud.fields["tree_id"][m]}))
    return PointCloud.concatenate(parts)


def speed(args: argparse.Namespace) -> None:
    import multiprocessing as mp

    from canopy_kit.config import PreprocessConfig
    from canopy_kit.segment.preprocess import prepare

    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    ctx = mp.get_context("spawn")
    rows = []
    base, sim_dir, base_name = session_map(cache, args.orchard, 2, args.trees_per_row, args.seed)
    for n_rows in args.rows:
        cloud = repeated_rows(base, sim_dir, n_rows)
        name = f"{base_name}_rows{n_rows}"
        t0 = time.perf_counter()
        prep = prepare(cloud, PreprocessConfig())
        t_prep = time.perf_counter() - t0
        npz = cache / f"{name}_canopy.npz"
        np.savez(
            npz,
            xyz=prep.normalized(cloud, prep.seen_index),
            weight=prep.seen_weight,
            stems=prep.normalized(cloud, prep.stem_index),
        )
        for job in args.jobs:
            q = ctx.Queue()
            proc = ctx.Process(target=_measure, args=(job, str(npz), q))
            proc.start()
            proc.join()
            res = (
                q.get()
                if proc.exitcode == 0
                else {
                    "seconds": np.nan,
                    "cpu_s": np.nan,
                    "peak_mb": np.nan,
                    "delta_mb": np.nan,
                    "n_clusters": -1,
                }
            )
            res.update(
                {
                    "rows": n_rows,
                    "job": job,
                    "map_points": len(cloud),
                    "canopy_voxels": len(prep.seen_index),
                    "preprocess_s": t_prep,
                }
            )
            rows.append(res)
            print(json.dumps(res), file=sys.stderr, flush=True)
    df = pd.DataFrame(rows)
    table = df.pivot_table(index="rows", columns="job", values=["cpu_s", "seconds", "peak_mb"])
    print(
        df[["rows", "map_points", "canopy_voxels", "preprocess_s"]]
        .drop_duplicates()
        .to_string(index=False, float_format=lambda v: f"{v:.1f}")
    )
    print(table.to_string(float_format=lambda v: f"{v:.1f}"))
    if args.csv:
        df.to_csv(args.csv, index=False, float_format="%.3f")


def figures(args: argparse.Namespace) -> None:
    """Top views and failure galleries of one cached session, for docs/figures."""
    import matplotlib

    matplotlib.use("Agg")
    from canopy_kit.evaluate.segmentation_score import score_point_labels
    from canopy_kit.segment.plots import plot_failure_gallery, plot_top_view
    from canopy_kit.segment.rows import driving_direction_from_trajectory
    from canopy_kit.segment.verb import segment
    from canopy_kit.sim.truth import load_truth

    cache, out = Path(args.cache), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cloud, sim_dir, name = session_map(
        cache, args.orchard, args.rows, args.trees_per_row, args.seed
    )
    traj = load_truth(sim_dir).trajectory[["x", "y"]].to_numpy()
    direction = driving_direction_from_trajectory(traj)
    truth = np.asarray(cloud.fields["tree_id"])
    for method in args.methods:
        seg = segment(cloud, bench_segmenter(method), driving_direction=direction)
        fig = plot_top_view(cloud, seg)
        fig.savefig(out / f"segment_{args.orchard}_{method}_top.png", dpi=110)
        score = score_point_labels(seg.labels, truth)
        gallery = plot_failure_gallery(cloud, seg, score, truth, max_panels=4)
        if gallery is not None:
            gallery.savefig(out / f"segment_{args.orchard}_{method}_failures.png", dpi=90)
        print(f"{name} {method}: {score.n_correct}/{score.n_truth} correct")


def real(args: argparse.Namespace) -> None:
    """Every method on lidR's labelled MixedConifer scan, scored against its treeID."""
    from sklearn.metrics import adjusted_rand_score

    from canopy_kit.config import PreprocessConfig
    from canopy_kit.evaluate.segmentation_score import score_point_labels
    from canopy_kit.io.clouds import read_cloud
    from canopy_kit.segment.verb import segment

    cloud = read_cloud(args.laz)
    tid = np.asarray(cloud.fields["treeID"], dtype=np.float64)
    truth = np.where(np.isfinite(tid) & (tid < 1e300), tid, -1).astype(np.int64)
    truth[cloud.fields["classification"] == 2] = -1  # ground points carry IDs too
    # Conifers are taller than orchard trees: the canopy band is the only change.
    pre = PreprocessConfig(min_canopy_height=2.0, max_canopy_height=40.0)
    print("| method | segments | correct | success | precision | merged | ARI | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    for method in args.methods:
        t0 = time.perf_counter()
        seg = segment(cloud, bench_segmenter(method), pre)
        seconds = time.perf_counter() - t0
        sc = score_point_labels(seg.labels, truth)
        both = (truth >= 0) | (seg.labels >= 0)
        ari = adjusted_rand_score(truth[both], seg.labels[both])
        print(
            f"| {method} | {seg.n_trees} | {sc.n_correct} of {sc.n_truth} | "
            f"{100 * sc.success_rate:.1f} % | {100 * sc.precision:.1f} % | {sc.n_merged} | "
            f"{ari:.3f} | {seconds:.0f} |"
        )
        for w in seg.warnings:
            print(f"  {method}: {w[:120]}", file=sys.stderr)


def table(args: argparse.Namespace) -> None:
    """The reproduction table (markdown) from the saved per-session results."""
    from canopy_kit.paper.segmentation_results import reproduction_results

    t = reproduction_results(args.csv, seeds=args.seeds, variant=args.variant, metric=args.metric)
    if t.empty:
        sys.exit(f"{args.csv}: no sessions for variant {args.variant!r} and seeds {args.seeds}")

    def pct(v: float) -> str:
        return "" if pd.isna(v) else f"{100 * v:.0f} %"

    print(
        "| orchard | method | seeds | trees | correct | success | per-session range | paper | target |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in t.itertuples():
        print(
            f"| {r.orchard} | {r.method} | {r.seeds} | {r.trees} | {r.correct} | "
            f"**{100 * r.success:.1f} %** | {pct(r.min)}-{pct(r.max)} | {pct(r.paper)} | "
            f"{'>= ' + pct(r.target) if not pd.isna(r.target) else ''} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    acc = sub.add_parser("accuracy")
    acc.add_argument("--orchards", nargs="+", default=["pistachio", "almond"])
    acc.add_argument("--seeds", nargs="+", type=int, default=[101, 102, 103, 104, 105])
    acc.add_argument("--rows", type=int, default=3)
    acc.add_argument("--trees-per-row", type=int, default=6)
    acc.add_argument("--methods", nargs="+", default=DEFAULT_METHODS)
    acc.add_argument("--set", nargs="*", default=[], help="simulator overrides section.key=value")
    acc.add_argument("--sensor", default=None)
    acc.add_argument("--tag", default="", help="suffix of the session names (variants)")
    acc.add_argument("--cache", default="out/bench_segment")
    acc.add_argument("--csv", default=None)
    acc.set_defaults(func=accuracy)
    sp = sub.add_parser("speed")
    sp.add_argument("--orchard", default="almond")
    sp.add_argument("--rows", nargs="+", type=int, default=[1, 2, 4, 10])
    sp.add_argument("--trees-per-row", type=int, default=8)
    sp.add_argument("--seed", type=int, default=7)
    sp.add_argument(
        "--jobs", nargs="+", default=["dbscan", "dbscan_spectral", "adaptive", "open3d", "sklearn"]
    )
    sp.add_argument("--cache", default="out/bench_segment")
    sp.add_argument("--csv", default=None)
    sp.set_defaults(func=speed)
    fg = sub.add_parser("figures")
    fg.add_argument("--orchard", default="almond")
    fg.add_argument("--rows", type=int, default=3)
    fg.add_argument("--trees-per-row", type=int, default=6)
    fg.add_argument("--seed", type=int, default=101)
    fg.add_argument("--methods", nargs="+", default=DEFAULT_METHODS)
    fg.add_argument("--cache", default="out/bench_segment")
    fg.add_argument("--out", default="docs/figures")
    fg.set_defaults(func=figures)
    rl = sub.add_parser("real")
    rl.add_argument("--laz", default="../shared/data/lidr/MixedConifer.laz")
    rl.add_argument("--methods", nargs="+", default=DEFAULT_METHODS)
    rl.set_defaults(func=real)
    tb = sub.add_parser("table")
    tb.add_argument("--csv", default="canopy_kit/paper/data/segmentation_results.csv")
    tb.add_argument("--seeds", nargs="*", type=int, default=None)
    tb.add_argument("--variant", default="default")
    tb.add_argument(
        "--metric",
        default="success_points",
        choices=["success_points", "success_footprints", "ceiling_points"],
    )
    tb.set_defaults(func=table)
    args = parser.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
