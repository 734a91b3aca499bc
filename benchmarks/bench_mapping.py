"""Mapping throughput, memory and accuracy: canopy-kit's mapping vs KISS-ICP's own pipeline.

    .venv/bin/python benchmarks/bench_mapping.py [--session DIR] [--keep] [--repeat N [--against DIR]]

Without ``--session`` a 4-row pistachio session with the default 32-ring sensor is
simulated into a temporary folder (about 1 GB; deleted afterwards unless ``--keep``).
Each pipeline runs in its own process, so peak memory (max RSS) is its own:

- ``canopy-kit build_map``: the default MappingConfig (IMU + GNSS fusion, every third
  sweep registered or sooner in tight turns, ICP convergence 1e-3, the odometry in time
  chunks on one process per core, the map pass in one stretch per core (the first in the
  parent process, the others in forked workers), each reading its
  own stretch of the bag, KISS-ICP on 1 thread so runs are bit-reproducible);
- the most accurate and slowest: every sweep registered, KISS-ICP's own convergence
  criterion, everything in one process (``workers = 1, odometry_every = 1,
  kiss_convergence = 1e-4``, the defaults of two sessions before);
- ``KISS-ICP (Python API, unfiltered)``: ``kiss_icp.kiss_icp.KissICP`` with its default
  config (voxel = max_range / 100, all cores), every scan as is (ground kept), per-point
  times normalised to [0, 1] for its own deskew - what ``kiss_icp_pipeline`` does. It
  yields poses only (no map is accumulated, no IMU or GNSS).

Real-time factor = seconds of driving per second of compute: wall clock on this machine
(2 cores, shared: the load average is printed) and CPU time (all processes; the figure an
otherwise idle single core would give). Prints a Markdown table for docs/BENCHMARKS.md
("## Mapping").
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from canopy_kit.parallel import cpu_seconds

DEFAULT = ("canopy-kit build_map (defaults: IMU + GNSS, every 3rd sweep registered, odometry in "
           "2 time chunks, map pass in 2 stretches: the parent and 1 worker)")


def _peak_mb() -> tuple[float, float]:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return own, children


def run_canopy_kit(session: Path, overrides: dict) -> dict:
    from canopy_kit.config import MappingConfig
    from canopy_kit.mapping import build_map
    from canopy_kit.mapping.evaluate import evaluate_against_simulation
    from canopy_kit.sim.session import find_bag

    cpu0, wall0 = cpu_seconds(), time.perf_counter()
    result = build_map(find_bag(session), MappingConfig(**overrides))
    wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    own, children = _peak_mb()
    ev = evaluate_against_simulation(result, session)
    d = result.diagnostics
    return {"duration_s": d["duration_s"], "wall_s": wall, "cpu_s": cpu, "peak_mb": own,
            "worker_peak_mb": children, "ate_m": ev["ate_rmse_m"], "drift_pct": ev["drift_percent"],
            "map_median_m": ev["map_aligned"]["median_m"], "map_p90_m": ev["map_aligned"]["p90_m"],
            "map_points": d["map_points"],
            "stages": d["timing"]}


def run_kiss_icp(session: Path) -> dict:
    import numpy as np
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    from canopy_kit.io.bag import open_bag
    from canopy_kit.mapping.evaluate import trajectory_errors
    from canopy_kit.mapping.trajectory import pose_table
    from canopy_kit.sim.session import find_bag
    from canopy_kit.sim.truth import load_truth

    cpu0, wall0 = cpu_seconds(), time.perf_counter()
    odometry = KissICP(load_config(None))
    times, poses = [], []
    first = last = None
    with open_bag(find_bag(session)) as bag:
        for scan in bag.scans():
            t = scan.times
            lo, hi = float(t.min()), float(t.max())
            odometry.register_frame(scan.xyz, (t - lo) / max(hi - lo, 1e-9))
            times.append(0.5 * (lo + hi))  # KISS-ICP deskews to the middle of the sweep
            poses.append(odometry.last_pose.copy())
            first = scan.stamp if first is None else first
            last = scan.stamp
    wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    own, _ = _peak_mb()
    err = trajectory_errors(pose_table(np.array(times), np.array(poses)), load_truth(session).trajectory)
    return {"duration_s": last - first + 0.1, "wall_s": wall, "cpu_s": cpu, "peak_mb": own,
            "worker_peak_mb": 0.0, "ate_m": err["ate_rmse_m"], "drift_pct": err["drift_percent"],
            "map_median_m": None, "map_p90_m": None, "map_points": None, "stages": {}}


def _cm(metres: float | None) -> str:
    return "-" if metres is None else f"{100 * metres:.1f}"


def _child(mode: str, session: Path, code: Path | None = None) -> dict:
    load = os.getloadavg()[0]
    env = None
    if code:  # that checkout's canopy_kit first on the path (before the editable install)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(code), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([sys.executable, __file__, "--child", mode, "--session", str(session)],
                         capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"{mode} failed:\n{out.stderr[-3000:]}")
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["load"] = 0.5 * (load + os.getloadavg()[0])
    return result


def _simulate(folder: Path) -> Path:
    from canopy_kit.sim import load_sim_config, simulate_session

    cfg = load_sim_config("pistachio", {"seed": 0, "orchard": {"rows": 4, "trees_per_row": 10}})
    return simulate_session(folder / "bench_pistachio", cfg).root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--session", type=Path, help="Simulated session folder (default: simulate one)")
    parser.add_argument("--keep", action="store_true", help="Keep the simulated session")
    parser.add_argument("--repeat", type=int, default=0,
                        help="Then run the default pipeline this many more times and print the median "
                             "(the machine's speed varies by up to 40 %% between identical runs)")
    parser.add_argument("--against", type=Path,
                        help="With --repeat: a checkout of other canopy-kit code (e.g. `git worktree add "
                             "/tmp/old REV`), run alternately with this code under the same conditions")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.against and not args.repeat:
        parser.error("--against needs --repeat N (the number of alternating runs)")
    if args.child:
        result = (run_kiss_icp(args.session) if args.child == "kiss"
                  else run_canopy_kit(args.session, json.loads(args.child)))
        print(json.dumps(result))
        return
    tmp = None
    session = args.session
    if session is None:
        tmp = Path(tempfile.mkdtemp(prefix="bench_mapping_", dir="/tmp"))
        session = _simulate(tmp)
    try:
        runs = {
            DEFAULT: _child("{}", session),
            "canopy-kit build_map, one process, every sweep registered, ICP convergence 1e-4 "
            "(workers = 1, odometry_every = 1)": _child(
                '{"workers": 1, "odometry_every": 1, "kiss_convergence": 0.0001}', session),
            "KISS-ICP (Python API, unfiltered, all cores)": _child("kiss", session),
        }
        duration = next(iter(runs.values()))["duration_s"]
        _print_table(session, runs, duration)
        if args.repeat:
            _repeat(session, args.repeat, args.against, duration)
    finally:
        if tmp is not None and not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)


def _print_table(session: Path, runs: dict[str, dict], duration: float) -> None:
    print(f"session: {session} ({duration:.0f} s of driving, 32 rings x 1024 columns, 10 Hz)")
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the end\n")
    print("| pipeline | real-time factor, wall | real-time factor, CPU | wall s | CPU s | load avg "
          "| peak RSS MB | ATE m | drift % | map to true surfaces, median / 90 % (cm) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, r in runs.items():
        peak = f"{r['peak_mb']:.0f}" + (f" + {r['worker_peak_mb']:.0f}/worker" if r["worker_peak_mb"] else "")
        print(f"| {name} | {r['duration_s'] / r['wall_s']:.1f}x | {r['duration_s'] / r['cpu_s']:.1f}x | "
              f"{r['wall_s']:.0f} | {r['cpu_s']:.0f} | {r['load']:.1f} | {peak} | {r['ate_m']:.3f} | "
              f"{r['drift_pct']:.2f} | {_cm(r['map_median_m'])} / {_cm(r['map_p90_m'])} |")
    stages = runs[DEFAULT]["stages"]
    print("\nstages (default run): " + ", ".join(f"{k} {v:.1f}" for k, v in stages.items()), flush=True)


def _repeat(session: Path, n: int, against: Path | None, duration: float) -> None:
    """The default pipeline ``n`` times (alternating with the code at ``against``): medians."""
    import statistics

    codes = {"this code": None} | ({f"code at {against}": against} if against else {})
    walls: dict[str, list[float]] = {name: [] for name in codes}
    print(f"\nthe default pipeline {n} times" + (", alternating with the code at " + str(against)
                                                  if against else "") + ": wall s (load average)")
    for i in range(n):
        line = []
        order = list(codes.items()) if i % 2 == 0 else list(codes.items())[::-1]  # neither always first
        for name, code in order:
            r = _child("{}", session, code)
            walls[name].append(r["wall_s"])
            line.append(f"{name} {r['wall_s']:.1f} ({r['load']:.1f})")
        print(f"  run {i + 1}: " + ", ".join(line), flush=True)
    for name, w in walls.items():
        print(f"{name}: median {statistics.median(w):.1f} s = {duration / statistics.median(w):.1f}x wall "
              f"(best {duration / min(w):.1f}x, worst {duration / max(w):.1f}x, {n} runs)")


if __name__ == "__main__":
    main()
