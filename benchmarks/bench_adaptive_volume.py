"""The adaptive-α estimator and its per-tree interval on each crown form: calibration and check.

Per crown form and seed, simulates a 1-row × 3-tree pistachio session (16 rings, 512
columns; cached under ``--cache``), builds the reference map with the true poses, cuts each
tree by the simulator's ``tree_id`` (truth-labelled points: no segmentation or odometry
error), thins it to 0.1 m voxels as the pipeline does, and measures every tree, complete and
one-sided, with the paper's alpha shape, the convex hull and ``adaptive_alpha`` with its
interval. Tuning seeds (401, 402) and held-out seeds (411-413) are reported apart.

    .venv/bin/python benchmarks/bench_adaptive_volume.py [--forms lobed vase] [--seeds 411 412]
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

FORMS = ["ellipsoid", "lobed", "vase", "hedged", "sparse"]
TUNE_SEEDS = [401, 402]
CHECK_SEEDS = [411, 412, 413]


def trees_of(cache: Path, form: str, seed: int) -> list:
    """The session's SimulatedTree list (complete and one-sided clouds, 0.1 m voxels), cached."""
    from canopy_kit.sim import load_sim_config, simulate_session
    from canopy_kit.sim.truth_map import truth_map
    from canopy_kit.volume.evaluate import simulated_trees

    root = cache / f"{form}_s{seed}"
    done = root / "trees.pkl"
    if not done.exists():
        overrides = {"seed": seed, "orchard": {"rows": 1, "trees_per_row": 3, "crown_form": form},
                     "lidar": {"columns": 512, "rings": 16},
                     "imu": {"enabled": False}, "gnss": {"enabled": False}}
        print(f"simulating {root} ...", file=sys.stderr, flush=True)
        simulate_session(root, load_sim_config("pistachio", overrides), fmt="ros1", overwrite=True)
        cloud = truth_map(root, voxel_size=0.05)
        trees = simulated_trees(root, reference_map=cloud)
        done.write_bytes(pickle.dumps(trees))
    return pickle.loads(done.read_bytes())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--forms", nargs="+", default=FORMS)
    parser.add_argument("--seeds", nargs="+", type=int, default=TUNE_SEEDS + CHECK_SEEDS)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/canopy_kit_bench_adaptive"))
    parser.add_argument("--simulate-only", action="store_true")
    args = parser.parse_args()
    for seed in args.seeds:
        for form in args.forms:
            t0 = time.perf_counter()
            trees = trees_of(args.cache, form, seed)
            print(f"{form} s{seed}: {len(trees)} trees, {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr, flush=True)
    if args.simulate_only:
        return


if __name__ == "__main__":
    main()
