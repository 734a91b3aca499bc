"""Simulator speed and memory: points per second, real-time factor, peak memory.

    .venv/bin/python benchmarks/bench_sim.py [--quick]

Each case runs in a fresh subprocess so its peak resident memory is its own. Cases:
a ~60 s 32-ring session (the issue's target: < 30 s of compute), the same with exact
per-column poses (no pose interpolation: the baseline), and 2-, 6- and 10-row sessions
to show that memory stays flat as the session gets longer.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

CHILD = r"""
import json, resource, sys, time, tempfile, shutil
from pathlib import Path
from canopy_kit.sim import load_sim_config, simulate_session
import canopy_kit.sim.lidar as lidar
case = json.loads(sys.argv[1])
if case.get("exact_poses"):
    original = lidar.SpinningLidar._column_poses
    lidar.SpinningLidar._column_poses = lambda self, stamp, knots=33: original(self, stamp, self.spec.columns)
cfg = load_sim_config(case["orchard"], case["overrides"])
tmp = Path(tempfile.mkdtemp())
t0, c0 = time.perf_counter(), time.process_time()
s = simulate_session(tmp / "s", cfg, fmt=case.get("fmt", "ros2-mcap"))
elapsed = time.perf_counter() - t0
cpu = time.process_time() - c0
size = sum(p.stat().st_size for p in (tmp / "s").rglob("*") if p.is_file())
shutil.rmtree(tmp)
print(json.dumps({"seconds": elapsed, "cpu_s": cpu, "driving_s": s.trajectory.duration, "points": s.n_points,
                  "scans": s.n_scans, "trees": len(s.orchard.trees),
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "bag_mb": size / 1e6}))
"""


def run(case: dict) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(case)], capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="skip the 6- and 10-row sessions")
    args = parser.parse_args()
    sixty = {"orchard": {"rows": 1, "trees_per_row": 13}}  # two alleys and a U-turn
    cases = [
        ("one alley pair, 32 rings x 1024", {"orchard": "pistachio", "overrides": sixty}),
        (
            "same, exact per-column poses (baseline)",
            {"orchard": "pistachio", "overrides": sixty, "exact_poses": True},
        ),
        ("2 rows x 10 trees", {"orchard": "pistachio", "overrides": {"orchard": {"rows": 2}}}),
    ]
    if not args.quick:
        cases += [
            ("6 rows x 10 trees", {"orchard": "pistachio", "overrides": {"orchard": {"rows": 6}}}),
            (
                "10 rows x 10 trees",
                {"orchard": "pistachio", "overrides": {"orchard": {"rows": 10}}},
            ),
        ]
    load = os.getloadavg()[0]
    print(
        f"python {sys.version.split()[0]}, {time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores, "
        f"load average {load:.1f} at start (wall times stretch under load; CPU times less)"
    )
    print(
        "| case | driving (s) | wall (s) | CPU (s) | real-time factor (wall) | points/s | scans | "
        "peak RSS (MB) | bag (MB) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, case in cases:
        r = run(case)
        print(
            f"| {name} | {r['driving_s']:.0f} | {r['seconds']:.1f} | {r['cpu_s']:.1f} | "
            f"{r['driving_s'] / r['seconds']:.2f}x | {r['points'] / r['seconds'] / 1e6:.2f} M | "
            f"{r['scans']} | {r['peak_rss_mb']:.0f} | {r['bag_mb']:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
