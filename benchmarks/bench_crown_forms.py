"""First look: the volume estimators on each simulator crown form, on truth-labelled points.

Per crown form, simulates a small pistachio session (cached under ``--cache``), builds the
reference map with the true poses, cuts each tree by the simulator's ``tree_id`` (perfect
segmentation, no odometry error), thins it to 0.1 m voxels, and runs convex hull, the
paper's alpha shape (0.9 m), alpha hull (0.9 m) and slices (0.2 m) on the complete tree
and each one-sided scan. Prints signed bias and MAPE per form; docs/history/VOLUMES_LOG.md quotes it.

    .venv/bin/python benchmarks/bench_crown_forms.py [--forms lobed vase] [--rows 2 --trees 3]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.evaluate.volume_errors import (
    MethodSpec,
    error_table,
    simulated_trees,
    volume_errors,
)
from canopy_kit.sim.crown_forms import FORM_NAMES

SPECS = [
    MethodSpec("convex_hull", "convex_hull"),
    MethodSpec("alpha_shape α=0.9", "alpha_shape", {"alpha": 0.9}),
    MethodSpec("alpha_hull α=0.9", "alpha_hull", {"alpha": 0.9}),
    MethodSpec("slices 0.2 hull", "slices", {"thickness": 0.2}),
]


def session(cache: Path, form: str, rows: int, trees: int, seed: int, penetration: float) -> Path:
    """A cached simulated session of one crown form with its reference map (map.npz)."""
    from canopy_kit.evaluate.truth_map import truth_map
    from canopy_kit.sim import load_sim_config, simulate_session

    root = cache / f"{form}_{rows}x{trees}_s{seed}_p{penetration:g}"
    if not (root / "map.npz").exists():
        overrides = {
            "seed": seed,
            "orchard": {
                "rows": rows,
                "trees_per_row": trees,
                "crown_form": form,
                "leaf_penetration_m": penetration,
            },
            "lidar": {"columns": 512},
            "imu": {"enabled": False},
            "gnss": {"enabled": False},
        }
        print(f"simulating {root} ...", file=sys.stderr, flush=True)
        simulate_session(root, load_sim_config("pistachio", overrides), fmt="ros1", overwrite=True)
        cloud = truth_map(root, voxel_size=0.05)
        np.savez(
            root / "map.npz",
            xyz=cloud.xyz,
            tree_id=cloud.fields["tree_id"],
            time=cloud.fields["time"],
        )
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--forms", nargs="+", default=list(FORM_NAMES))
    parser.add_argument("--rows", type=int, default=2)
    parser.add_argument("--trees", type=int, default=3)
    parser.add_argument("--seed", type=int, default=41)
    parser.add_argument(
        "--penetration",
        type=float,
        default=math.inf,
        help="orchard.leaf_penetration_m (default inf: through the whole crown)",
    )
    parser.add_argument("--cache", type=Path, default=Path("/tmp/canopy_kit_bench_crown_forms"))
    args = parser.parse_args()
    from canopy_kit.core.cloud import PointCloud

    tables = []
    for form in args.forms:
        t0 = time.perf_counter()
        root = session(args.cache, form, args.rows, args.trees, args.seed, args.penetration)
        data = np.load(root / "map.npz")
        cloud = PointCloud(data["xyz"], {"tree_id": data["tree_id"], "time": data["time"]})
        trees = simulated_trees(root, reference_map=cloud)
        table = error_table(volume_errors(trees, SPECS))
        table.insert(0, "form", form)
        tables.append(table)
        print(
            f"{form}: {len(trees)} trees, {time.perf_counter() - t0:.0f} s",
            file=sys.stderr,
            flush=True,
        )
    out = pd.concat(tables, ignore_index=True)
    out["bias %"] = (100 * out.pop("bias")).round(1)
    out["MAPE %"] = (100 * out.pop("mape")).round(1)
    with pd.option_context("display.width", 160, "display.max_rows", 200):
        print(out.to_string(index=False))


if __name__ == "__main__":
    main()
