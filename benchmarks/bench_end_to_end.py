"""End-to-end speed: seconds of driving per second of compute, per stage.

    .venv/bin/python benchmarks/bench_end_to_end.py [--rows 4] [--trees-per-row 10] [--orchard pistachio]
                                                    [--session SIM_DIR]

Simulates a session (not timed; or takes an already simulated ``--session``), then runs
the whole pipeline (mapping, segmentation, volumes, report; no drone stage) with the cache
off and prints each stage's wall and CPU time (this process and its worker processes) and
the real-time factor. The issue's target: ≥ 5x real time for a 4-row session.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from canopy_kit.config import load_preset
from canopy_kit.parallel import cpu_seconds
from canopy_kit.pipeline import run
from canopy_kit.sim import load_sim_config, simulate_session
from canopy_kit.sim.session import find_bag
from canopy_kit.sim.truth import load_truth


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--orchard", default="pistachio")
    parser.add_argument("--rows", type=int, default=4)
    parser.add_argument("--trees-per-row", type=int, default=10)
    parser.add_argument("--preset", default="adaptive")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--session", type=Path, help="An already simulated session folder")
    args = parser.parse_args()
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        if args.session is not None:
            bag = find_bag(args.session)
            times = load_truth(args.session).trajectory["time"]
            driving = float(times.iloc[-1] - times.iloc[0])
        else:
            cfg = load_sim_config(
                args.orchard,
                {
                    "seed": args.seed,
                    "orchard": {"rows": args.rows, "trees_per_row": args.trees_per_row},
                },
            )
            session = simulate_session(Path(tmp) / "sim", cfg)
            bag, driving = session.bag, session.trajectory.duration
        wall, cpu = time.perf_counter(), cpu_seconds()
        result = run(load_preset(args.preset), bag, Path(tmp) / "run", use_cache=False)
        wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
    t = result.metrics["stage_timings"]
    print(
        f"{args.orchard}, {args.rows} rows x {args.trees_per_row} trees, {driving:.0f} s of driving, "
        f"{result.metrics['n_trees']} trees, preset {args.preset}"
    )
    print(
        f"load average {load:.1f} at start on {os.cpu_count()} cores: wall times stretch under "
        "load, CPU times much less"
    )
    print("| stage | wall (s) | CPU (s) | real-time factor (wall) | real-time factor (CPU) |")
    print("|---|---|---|---|---|")
    for stage, v in t.items():
        print(
            f"| {stage} | {v['wall_s']:.1f} | {v['cpu_s']:.1f} | {driving / v['wall_s']:.1f}x | "
            f"{driving / v['cpu_s']:.1f}x |"
        )
    rest = wall - sum(v["wall_s"] for v in t.values())
    rest_cpu = cpu - sum(v["cpu_s"] for v in t.values())
    print(f"| outputs and report | {rest:.1f} | {rest_cpu:.1f} | | |")
    print(
        f"| **total** | **{wall:.1f}** | {cpu:.1f} | **{driving / wall:.1f}x** | "
        f"**{driving / cpu:.1f}x** |"
    )


if __name__ == "__main__":
    main()
