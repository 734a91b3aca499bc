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
            rows = family_rows(family, seed, REAL_CLOUDS if family == "real" else ())
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    scan = sub.add_parser("scan", help="drive every row and cache the scans")
    scan.add_argument("--families", nargs="+", default=FAMILIES, choices=FAMILIES)
    scan.add_argument("--seeds", nargs="+", type=int, default=None)
    scan.add_argument("--sensors", nargs="+", default=SENSORS)
    scan.add_argument("--mount", type=float, default=1.8)
    scan.add_argument("--cache", type=Path, default=DEFAULT_CACHE)
    args = parser.parse_args()
    if args.command == "scan":
        for family in args.families:
            seeds = args.seeds or (REAL_SEEDS if family == "real" else TUNE_SEEDS + HELD_OUT_SEEDS)
            for seed in seeds:
                scans(args.cache, family, seed, args.sensors, args.mount)


if __name__ == "__main__":
    main()
