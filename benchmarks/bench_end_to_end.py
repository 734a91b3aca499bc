"""End-to-end speed: seconds of driving per second of compute, per stage and per sensor.

    .venv/bin/python benchmarks/bench_end_to_end.py [--sensors vlp16 hdl32 os1-64 os1-128]
        [--orchard pistachio] [--rows 4] [--trees-per-row 10] [--seed 11] [--preset adaptive]
        [--repeats 5] [--against DIR] [--peers] [--work DIR] [--session SIM_DIR]
        [--rigs identity tower imu-flipped side-tilt]

For each sensor a session is simulated (not timed; kept in ``--work`` and reused when it is
already there), or ``--session`` names one already simulated; its bag is read once, untimed,
before the first run (the first run of a pair had paid for the disk: 42 against 33-35 s on
the 4.8 GB OS1-128 bag). Each run of the whole pipeline
(mapping, segmentation, volumes, report; no drone stage; the stage cache off) is a fresh
process, so its peak memory (max RSS of that process and, separately, of its largest worker)
is its own. With ``--against DIR`` (another checkout, e.g. ``git worktree add /tmp/old
<rev>``) that code runs alternately with this one on the same sessions, the order within a
pair alternating too, so both see the same spells of the machine, and the benchmark prints
how far the two disagree: ATE, segmentation success against the simulator's truth and the
recommended estimator's per-tree volumes. ``--peers``: KISS-ICP's own pipeline and rko_lio
(``bench_mapping.py``'s runs of them) on the same bags, beside canopy-kit's map stage.

Prints one row per run and one Markdown table per code: median wall, real-time factor (wall
and CPU, all processes), the median stage times, peak memory, ATE and success. The issue's
targets: ≥ 5x real time end to end for every sensor on sessions of at least 4 rows.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path

from _checkout import child_json

DEFAULT_SENSORS = ["vlp16", "hdl32", "os1-64", "os1-128"]


def run_once(session: Path, preset: str) -> dict:
    """One timed ``run`` of ``preset`` on the session's bag, then its errors against truth."""
    import numpy as np
    import pandas as pd

    from canopy_kit.config import load_preset
    from canopy_kit.core.parallel import cpu_seconds
    from canopy_kit.evaluate.segmentation_score import evaluate_run
    from canopy_kit.evaluate.trajectory_error import trajectory_errors
    from canopy_kit.evaluate.truth import load_truth
    from canopy_kit.pipeline import run
    from canopy_kit.sim.session import find_bag
    from canopy_kit.volume.verb import volume_column

    config = load_preset(preset)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        wall, cpu = time.perf_counter(), cpu_seconds()
        result = run(config, find_bag(session), out, use_cache=False)
        wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
        own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        workers = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
        truth = load_truth(session)
        frame = result.metrics["mapping"].get("trajectory_frame", "")
        reference = truth.trajectory_of(frame)
        if reference is None:
            reference = truth.trajectory
        errors = trajectory_errors(pd.read_csv(out / "trajectory.csv"), reference)
        score = evaluate_run(out, session)
        trees = result.trees
        column = volume_column(config.volume.recommended)
    times = truth.trajectory["time"]
    return {
        "driving_s": float(times.iloc[-1] - times.iloc[0]),
        "wall_s": wall,
        "cpu_s": cpu,
        "peak_mb": own,
        "worker_peak_mb": workers,
        "stages": result.metrics["stage_timings"],
        "ate_m": errors["ate_rmse_m"],
        "n_trees": int(len(trees)),
        "n_truth": score.n_truth,
        "n_correct": score.n_correct,
        "volumes": {
            str(k): float(v)
            for k, v in zip(trees["tree_id"], trees[column])
            if np.isfinite(v)  # a tree without a volume is compared by its absence
        },
    }


def _child(session: Path, preset: str, code: Path | None) -> dict:
    """:func:`run_once` in a fresh process, with ``code``'s canopy_kit first on the path."""
    argv = [__file__, "--child", str(session), "--preset", preset]
    return child_json(argv, code, f"the run on {session}")


def peer_odometry(session: Path) -> dict[str, dict]:
    """KISS-ICP's own pipeline (a fresh process) and rko_lio (its command, when installed)
    on the session's bag, as bench_mapping.py runs them: the odometry part only."""
    import bench_mapping

    peers = {"KISS-ICP (Python API, all cores)": bench_mapping._child("kiss", session)}
    if bench_mapping.RKO_LIO.exists():
        peers["rko_lio (LiDAR + IMU)"] = bench_mapping.run_rko_lio(session, bench_mapping.RKO_LIO)
    else:
        print(f"rko_lio not installed: {bench_mapping.RKO_INSTALL}")
    return peers


def _peer_rows(sensor: str, ours: list[dict], peers: dict[str, dict]) -> None:
    """Markdown rows: canopy-kit's map stage (median of its runs) beside the peers."""
    med = statistics.median
    driving = ours[0]["driving_s"]
    wall = med(r["stages"]["map"]["wall_s"] for r in ours)
    cpu = med(r["stages"]["map"]["cpu_s"] for r in ours)
    print(
        f"| {sensor} | canopy-kit map stage (odometry + map) | {driving / wall:.1f}x | "
        f"{cpu:.0f} ({driving / cpu:.1f}x) | {ours[0]['peak_mb']:.0f} | {100 * ours[0]['ate_m']:.1f} |"
    )
    for name, r in peers.items():
        print(
            f"| {sensor} | {name} | {r['duration_s'] / r['wall_s']:.1f}x | "
            f"{r['cpu_s']:.0f} ({r['duration_s'] / r['cpu_s']:.1f}x) | {r['peak_mb']:.0f} | "
            f"{100 * r['ate_m']:.1f} |"
        )


def simulated(
    work: Path, orchard: str, sensor: str, rows: int, per_row: int, seed: int, rig: str = "identity"
) -> Path:
    """The session of these settings in ``work``, simulated unless it is already there
    (``rig``: where the sensors sit on the robot, ``canopy_kit/presets/rigs``)."""
    from canopy_kit.sim import load_sim_config, simulate_session

    on_rig = "" if rig == "identity" else f"-{rig}"
    folder = work / f"{orchard}-{sensor}{on_rig}-{rows}x{per_row}-seed{seed}"
    if not folder.is_dir():
        overrides = {"seed": seed, "orchard": {"rows": rows, "trees_per_row": per_row}}
        if rig != "identity":
            overrides["rig"] = {"name": rig}
        cfg = load_sim_config(orchard, overrides, sensor=sensor)
        print(f"simulating {folder.name} ...", flush=True)
        simulate_session(folder, cfg)
    return folder


def warm_read(session: Path) -> None:
    """Read the session's bag once, untimed, so that no run (the first of a pair most of
    all) pays for reading it from disk while the others find it in the page cache."""
    from canopy_kit.sim.session import find_bag

    bag = Path(find_bag(session))
    for path in [bag] if bag.is_file() else sorted(bag.rglob("*")):
        if path.is_file():
            with path.open("rb") as f:
                while f.read(1 << 24):
                    pass


def _volume_change(a: dict, b: dict) -> tuple[float, int]:
    """Largest relative per-tree volume difference of the trees both runs found, and how
    many trees only one of them has."""
    common = a.keys() & b.keys()
    worst = max((abs(a[k] - b[k]) / max(b[k], 1e-9) for k in common), default=0.0)
    return worst, len(a.keys() ^ b.keys())


def _summary(name: str, runs: list[dict]) -> None:
    """One Markdown row of medians for this sensor's runs of one code."""
    med = statistics.median
    driving = runs[0]["driving_s"]
    wall = med(r["wall_s"] for r in runs)
    cpu = med(r["cpu_s"] for r in runs)
    stages = {k: med(r["stages"][k]["wall_s"] for r in runs) for k in runs[0]["stages"]}
    rest = wall - sum(stages.values())
    r0 = runs[0]
    print(
        f"| {name} | {driving:.0f} | {len(runs)} | {wall:.1f} | **{driving / wall:.1f}x** "
        f"({driving / max(r['wall_s'] for r in runs):.1f}-{driving / min(r['wall_s'] for r in runs):.1f}x) | "
        f"{cpu:.0f} ({driving / cpu:.1f}x) | "
        + " | ".join(f"{stages.get(k, float('nan')):.1f}" for k in ("map", "segment", "volumes"))
        + f" | {rest:.1f} | {driving / stages.get('map', float('nan')):.1f}x | "
        f"{max(r['peak_mb'] for r in runs):.0f} + {max(r['worker_peak_mb'] for r in runs):.0f} | "
        f"{100 * r0['ate_m']:.1f} | {r0['n_correct']}/{r0['n_truth']} ({r0['n_trees']} found) |"
    )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sensors", nargs="+", default=None, help=f"default: {DEFAULT_SENSORS}")
    parser.add_argument(
        "--rigs",
        nargs="+",
        default=["identity"],
        help="robot rigs each sensor is simulated on (canopy_kit/presets/rigs: identity, tower, "
        "imu-flipped, side-tilt, ...); one session per sensor and rig",
    )
    parser.add_argument("--orchard", default="pistachio")
    parser.add_argument("--rows", type=int, default=4)
    parser.add_argument("--trees-per-row", type=int, default=10)
    parser.add_argument("--preset", default="adaptive")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--against", type=Path, help="Another checkout to run alternately")
    parser.add_argument("--work", type=Path, help="Folder for the simulated sessions (kept)")
    parser.add_argument("--session", type=Path, help="An already simulated session folder")
    parser.add_argument(
        "--peers",
        action="store_true",
        help="Also run KISS-ICP's own pipeline and rko_lio (when installed) on each session",
    )
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(json.dumps(run_once(args.child, args.preset)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        if args.session is not None:
            sessions = {args.session.name: args.session}
        else:
            sessions = {
                s if rig == "identity" else f"{s} on {rig}": simulated(
                    work, args.orchard, s, args.rows, args.trees_per_row, args.seed, rig
                )
                for s in args.sensors or DEFAULT_SENSORS
                for rig in args.rigs
            }
        codes = {"this code": None} | (
            {f"code at {args.against}": args.against} if args.against else {}
        )
        print(
            f"preset {args.preset}, {args.repeats} run(s) per session and code, each in a fresh "
            f"process; load average {os.getloadavg()[0]:.1f} at start on {os.cpu_count()} cores"
        )
        runs: dict[tuple[str, str], list[dict]] = {}
        for sensor, session in sessions.items():
            warm_read(session)
            for i in range(args.repeats):
                order = list(codes.items())
                for name, code in order if i % 2 == 0 else order[::-1]:  # neither always first
                    r = _child(session, args.preset, code)
                    runs.setdefault((sensor, name), []).append(r)
                    print(
                        f"  {sensor} run {i + 1}, {name}: {r['wall_s']:.1f} s wall "
                        f"({r['driving_s'] / r['wall_s']:.1f}x), {r['cpu_s']:.0f} CPU s, "
                        f"load {r['load']:.1f}",
                        flush=True,
                    )
        for name in codes:
            print(f"\n{name}:")
            print(
                "| sensor | driving s | runs | wall s (median) | real-time factor, wall (range) | "
                "CPU s (RTF) | map s | segment s | volumes s | outputs s | mapping RTF | "
                "peak MB (process + worker) | ATE cm | trees correct |"
            )
            print("|---|" + "---|" * 13)
            for sensor in sessions:
                _summary(sensor, runs[(sensor, name)])
        if args.peers:
            print("\nodometry beside the peers (real-time factor wall; CPU s and its factor):")
            print(
                "| sensor | pipeline | RTF wall | CPU s (RTF) | "
                "peak MB (canopy-kit: its whole run's process) | ATE cm |"
            )
            print("|---|---|---|---|---|---|")
            for sensor, session in sessions.items():
                _peer_rows(sensor, runs[(sensor, "this code")], peer_odometry(session))
        if args.against:
            this, other = list(codes)
            print("\nthis code against the other, first runs:")
            for sensor in sessions:
                a, b = runs[(sensor, this)][0], runs[(sensor, other)][0]
                worst, unmatched = _volume_change(a["volumes"], b["volumes"])
                print(
                    f"  {sensor}: ATE {100 * (a['ate_m'] - b['ate_m']):+.2f} cm, correct trees "
                    f"{a['n_correct'] - b['n_correct']:+d}, largest per-tree volume change "
                    f"{100 * worst:.2f} % ({unmatched} trees in one run only)"
                )


if __name__ == "__main__":
    main()
