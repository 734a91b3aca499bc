"""Each volume method's error against the simulator's exact crown volume.

Simulates a small pistachio and almond session (cached under ``--cache``), builds the
reference map with the true poses, cuts each tree by the simulator's ``tree_id`` (perfect
segmentation, no odometry error), thins it to 0.1 m voxels as the paper does, and runs
every method on the complete tree and on each one-sided scan (points seen from the alley
on one side of its row). Prints MAPE and bias per orchard; docs/history/VOLUMES_LOG.md quotes it.

    .venv/bin/python benchmarks/bench_volume_accuracy.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from canopy_kit.evaluate.volume_errors import (
    MethodSpec,
    error_table,
    simulated_trees,
    volume_errors,
)

SPECS = [
    MethodSpec("convex_hull", "convex_hull"),
    MethodSpec("alpha_shape α=0.9", "alpha_shape", {"alpha": 0.9}),
    MethodSpec("alpha_hull α=0.9", "alpha_hull", {"alpha": 0.9}),
    MethodSpec("alpha_auto", "alpha_auto"),
    MethodSpec("voxel 0.1 filled", "voxel", {"voxel_size": 0.1}),
    MethodSpec("slices 0.2 hull", "slices", {"thickness": 0.2}),
    MethodSpec("mirror (estimated plane)", "mirror"),
    MethodSpec("mirror (trunk + row plane)", "mirror", trunk_plane=True),
]


def session(cache: Path, orchard: str, rows: int, trees: int) -> Path:
    """A cached simulated session folder with its reference map saved as map.npz."""
    from canopy_kit.evaluate.truth_map import truth_map
    from canopy_kit.sim import load_sim_config, simulate_session

    root = cache / f"{orchard}_{rows}x{trees}"
    if not (root / "map.npz").exists():
        overrides = {
            "orchard": {"rows": rows, "trees_per_row": trees},
            "imu": {"enabled": False},
            "gnss": {"enabled": False},
        }
        print(f"simulating {root} ...", file=sys.stderr, flush=True)
        simulate_session(root, load_sim_config(orchard, overrides), fmt="ros1", overwrite=True)
        cloud = truth_map(root, voxel_size=0.05)
        np.savez(
            root / "map.npz",
            xyz=cloud.xyz,
            tree_id=cloud.fields["tree_id"],
            time=cloud.fields["time"],
        )
    return root


def load_map(root: Path):
    """The cached reference map as a PointCloud with tree_id and time."""
    from canopy_kit.core.cloud import PointCloud

    data = np.load(root / "map.npz")
    return PointCloud(data["xyz"], {"tree_id": data["tree_id"], "time": data["time"]})


def open3d_errors(trees: list) -> dict[str, float]:
    """Open3D's alpha-shape volume on every scan: failures and errors where it worked."""
    from bench_volume import open3d_alpha_volume  # the sibling script

    errs, failed, total = [], 0, 0
    for t in trees:
        for xyz in (t.complete, *t.sides.values()):
            total += 1
            try:
                errs.append(open3d_alpha_volume(xyz, 0.9) / t.true_volume_m3 - 1)
            except RuntimeError:
                failed += 1
    e = np.array(errs)
    return {
        "failed": failed,
        "total": total,
        "mape": float(np.abs(e).mean()) if len(e) else np.nan,
        "bias": float(e.mean()) if len(e) else np.nan,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--orchards", nargs="+", default=["pistachio", "almond"])
    parser.add_argument("--rows", type=int, default=2)
    parser.add_argument("--trees-per-row", type=int, default=6)
    parser.add_argument("--cache", type=Path, default=Path("out/bench_volume"))
    parser.add_argument("--csv", type=Path, default=None, help="also write per-tree errors here")
    args = parser.parse_args()

    print(
        "Volume error against the simulator's exact crown volume (reference map from true "
        "poses, trees cut by the simulator's tree_id, 0.1 m voxels)\n"
    )
    for orchard in args.orchards:
        start = time.perf_counter()
        root = session(args.cache, orchard, args.rows, args.trees_per_row)
        trees = simulated_trees(root, voxel_size=0.1, reference_map=load_map(root))
        errors = volume_errors(trees, SPECS)
        if args.csv:
            errors.assign(orchard=orchard).to_csv(
                args.csv.with_name(f"{args.csv.stem}_{orchard}{args.csv.suffix}"), index=False
            )
        table = error_table(errors)
        sizes = [len(t.complete) for t in trees]
        print(
            f"### {orchard}: {len(trees)} trees, {min(sizes):,}-{max(sizes):,} points each "
            f"(complete), true volumes {min(t.true_volume_m3 for t in trees):.1f}-"
            f"{max(t.true_volume_m3 for t in trees):.1f} m³\n"
        )
        print("| method | complete MAPE | complete bias | one-sided MAPE | one-sided bias |")
        print("|---|---|---|---|---|")
        for spec in SPECS:
            cells = [spec.label]
            for scan in ("complete", "one-sided"):
                row = table[(table["scan"] == scan) & (table["method"] == spec.label)].iloc[0]
                flag = f" ({row.invalid} invalid)" if row.invalid else ""
                cells += [f"{row.mape:.1%}{flag}", f"{row.bias:+.1%}"]
            print("| " + " | ".join(cells) + " |")
        o3d = open3d_errors(trees)
        print(
            f"\nOpen3D alpha shape + get_volume (α = 0.9 m) on the same scans: failed on "
            f"{o3d['failed']} of {o3d['total']}; where it worked, MAPE {o3d['mape']:.1%}, "
            f"bias {o3d['bias']:+.1%}."
        )
        seen = [len(t.sides[s]) / len(t.complete) for t in trees for s in t.sides]
        far = [
            np.mean(((t.sides[s][:, :2] - t.trunk_xy) @ t.across_row) * sign < 0)
            for t in trees
            for s, sign in (("left", 1), ("right", -1))
        ]
        print(
            f"\nOne-sided scans hold {min(seen):.0%}-{max(seen):.0%} (mean {np.mean(seen):.0%}) "
            f"of a tree's points; {min(far):.0%}-{max(far):.0%} (mean {np.mean(far):.0%}) of "
            f"them lie beyond the trunk plane, away from the sensor. "
            f"({time.perf_counter() - start:.0f} s)\n"
        )


if __name__ == "__main__":
    main()
