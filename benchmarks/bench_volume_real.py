"""Every volume method on the real single-tree clouds in ../shared/data (no truth: a
cross-check of the methods against each other and of the hull against the shipped table).

    .venv/bin/python benchmarks/bench_volume_real.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit import plugins
from canopy_kit.core.voxel import voxel_downsample
from canopy_kit.io.clouds import read_cloud
from canopy_kit.volume import estimate_volume, tree_metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data"
    )
    args = parser.parse_args()
    methods = plugins.names("volumes")

    print(
        "TreeLS terrestrial scans (clipped to a 2.5 m column), 0.1 m voxels: volume m³ (seconds)\n"
    )
    print("| tree | points | height m | " + " | ".join(methods) + " |")
    print("|---|---|---|" + "---|" * len(methods))
    for name in ("pine", "spruce"):
        xyz = voxel_downsample(read_cloud(args.data / "treels" / f"{name}.laz"), 0.1).xyz
        cells = [name, f"{len(xyz):,}", f"{tree_metrics(xyz).height_m:.1f}"]
        for m in methods:
            start = time.perf_counter()
            r = estimate_volume(xyz, m)
            cells.append(
                f"{r.volume_m3:.1f} ({time.perf_counter() - start:.2f})"
                + ("" if r.valid else " invalid")
            )
        print("| " + " | ".join(cells) + " |")

    cloud = read_cloud(args.data / "lidr" / "MixedConifer.laz")
    stats = pd.read_csv(args.data / "lidr" / "MixedConifer_tree_stats.csv")
    ids = cloud.fields["treeID"]
    vols = {m: [] for m in methods}
    invalid = {m: 0 for m in methods}
    for tid in stats["treeID"]:
        xyz = cloud.xyz[ids == tid]
        for m in methods:
            r = estimate_volume(xyz, m)
            vols[m].append(r.volume_m3 if r.valid else np.nan)
            invalid[m] += not r.valid
    ref = stats["hull_volume_3d_all_m3"].to_numpy()
    ours = np.array(vols["convex_hull"])
    both = ~np.isnan(ref) & ~np.isnan(ours)
    print(
        f"\nlidR MixedConifer (airborne, {len(stats)} reference tree IDs, 1-350 points each): "
        f"median volume per tree m³ and trees flagged invalid\n"
    )
    print("| method | median m³ | invalid |")
    print("|---|---|---|")
    for m in methods:
        valid = np.array(vols[m])[~np.isnan(vols[m])]
        median = f"{np.median(valid):.1f}" if len(valid) else "–"
        print(f"| {m} | {median} | {invalid[m]} |")
    print(
        f"\nconvex_hull vs the shipped table: max |difference| "
        f"{np.max(np.abs(ours[both] - ref[both])):.4f} m³ on {both.sum()} trees; the table has "
        f"no hull for {np.isnan(ref).sum()} trees, canopy-kit flags {np.isnan(ours).sum()}"
    )


if __name__ == "__main__":
    main()
