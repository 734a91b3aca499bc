"""Mapping throughput, memory and accuracy: canopy-kit's mapping vs KISS-ICP and rko_lio.

    .venv/bin/python benchmarks/bench_mapping.py [--session DIR | --rig NAME [--sensor NAME] [--seed N]]
        [--keep] [--rko-lio PATH] [--repeat N [--against DIR]] [--map-skipped {auto,on,off} ...]

Without ``--session`` a 4-row pistachio session (10 trees a row) is simulated into a
temporary folder (about 1 GB; deleted afterwards unless ``--keep``): the default 32-ring
sensor and seed 0, or the given ones, with every sensor in the LiDAR's frame or on the robot
rig ``--rig`` (``canopy_kit/presets/rigs``: the bag's /tf_static says where they sit).
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
- ``rko_lio`` (PRBonn's LiDAR-inertial odometry, its ``rko_lio`` command from a virtual
  environment of its own, ``--rko-lio``): its default config, LiDAR + IMU (no GNSS), the
  extrinsics from the bag's /tf_static and poses of the rig's base frame (base_link); on a
  bag without /tf_static (the identity rig) the extrinsics from truth/frame.json in a config
  file and poses of the LiDAR's frame. Evaluated against the truth of the frame it reports;
  wall time, CPU time and max RSS are those of its process (``os.wait4``). Printed as "not
  installed" (with the command to install it) when that command is missing.

``--map-skipped off auto`` (any of auto, on, off) runs only the default pipeline, once per
value of ``mapping.odometry_map_skipped``, and prints its decision (and the lowest returns'
elevation it was read from), the ATE, drift and CPU time: the Livox table of docs/MAPPING.md.

Real-time factor = seconds of driving per second of compute: wall clock on this machine
(2 cores, shared: the load average is printed) and CPU time (all processes; the figure an
otherwise idle single core would give). Prints a Markdown table for docs/BENCHMARKS.md
("## Mapping", and "## Mapping on robot rigs" for ``--rig``), with what each pipeline reads
and the frame whose poses it reports (the truth it is compared with).
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

from _checkout import child_json

from canopy_kit.core.parallel import cpu_seconds

DEFAULT = (
    "canopy-kit build_map (defaults: IMU + GNSS, every 3rd sweep registered, odometry in "
    "one time chunk per core unless the LiDAR is tilted over 5 deg, map pass in 2 stretches: "
    "the parent and 1 worker)"
)
RKO_LIO = Path(os.environ.get("RKO_LIO", "/work/rko_venv/bin/rko_lio"))
RKO_INSTALL = "python3 -m venv /work/rko_venv && /work/rko_venv/bin/pip install rko_lio rosbags"
# --map-skipped: the values of mapping.odometry_map_skipped
MAP_SKIPPED: dict[str, bool | str] = {"auto": "auto", "on": True, "off": False}
TUM = ["time", "x", "y", "z", "qx", "qy", "qz", "qw"]
# Runs a command and writes its exit code, CPU s and max RSS (kB) to argv[1]. A child's max RSS
# starts at its parent's peak (exec keeps the high-water mark of the memory it replaces), so
# rko_lio is started from this small process rather than from the benchmark's.
WAIT4 = (
    "import os, subprocess, sys; p = subprocess.Popen(sys.argv[2:]); _, s, r = os.wait4(p.pid, 0); "
    "open(sys.argv[1], 'w').write("
    "f'{os.waitstatus_to_exitcode(s)} {r.ru_utime + r.ru_stime} {r.ru_maxrss}')"
)


def _peak_mb() -> tuple[float, float]:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return own, children


def _result(
    duration_s: float,
    wall_s: float,
    cpu_s: float,
    peak_mb: float,
    errors: dict,
    frame: str,
    **extra: object,
) -> dict:
    """One pipeline's row: timing, memory, trajectory errors (and, with ``extra``, its map)."""
    row = {
        "duration_s": duration_s,
        "wall_s": wall_s,
        "cpu_s": cpu_s,
        "peak_mb": peak_mb,
        "worker_peak_mb": 0.0,
        "ate_m": errors["ate_rmse_m"],
        "drift_pct": errors["drift_percent"],
        "frame": frame,
        "map_median_m": None,
        "map_p90_m": None,
        "map_points": None,
        "stages": {},
    }
    return row | extra


def run_canopy_kit(session: Path, overrides: dict) -> dict:
    from canopy_kit.config import MappingConfig
    from canopy_kit.evaluate.trajectory_error import evaluate_against_simulation
    from canopy_kit.mapping import build_map
    from canopy_kit.sim.session import find_bag

    cpu0, wall0 = cpu_seconds(), time.perf_counter()
    result = build_map(find_bag(session), MappingConfig(**overrides))
    wall, cpu = time.perf_counter() - wall0, cpu_seconds() - cpu0
    own, children = _peak_mb()
    ev = evaluate_against_simulation(result, session)
    d = result.diagnostics
    return _result(
        d["duration_s"],
        wall,
        cpu,
        own,
        ev,
        ev["trajectory_frame"],
        worker_peak_mb=children,
        map_median_m=ev["map_aligned"]["median_m"],
        map_p90_m=ev["map_aligned"]["p90_m"],
        map_points=d["map_points"],
        stages=d["timing"],
        odometry_processes=d["odometry_workers"],
        map_skipped=d.get("odometry_map_skipped"),
    )


def run_kiss_icp(session: Path) -> dict:
    import numpy as np
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    from canopy_kit.evaluate.trajectory_error import trajectory_errors
    from canopy_kit.io.bag import open_bag
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
    truth = load_truth(session)
    err = trajectory_errors(pose_table(np.array(times), np.array(poses)), truth.trajectory)
    return _result(last - first + 0.1, wall, cpu, own, err, truth.info.get("sensor_frame", ""))


def run_rko_lio(session: Path, exe: Path) -> dict:
    """rko_lio's command on the session's bag; wall, CPU and max RSS of its process."""
    import pandas as pd

    from canopy_kit.evaluate.trajectory_error import trajectory_errors
    from canopy_kit.sim.session import find_bag
    from canopy_kit.sim.truth import load_truth

    truth = load_truth(session)
    rig = truth.info.get("rig", {})
    bag = find_bag(session)
    out = Path(tempfile.mkdtemp(prefix="rko_lio_", dir="/tmp"))
    # It reads a folder: the ROS2 bag's own, or the one that holds the ROS1 *.bag.
    cmd = [str(exe), str(bag if bag.is_dir() else bag.parent), "-o", str(out), "-n", "run"]
    if rig.get("tf_static_written"):  # it reads the extrinsics from /tf_static; poses of base_link
        frame = rig["base_frame"]
        cmd += ["--base_frame", frame]
    else:  # it refuses a bag without /tf_static: the rig's extrinsics, the LiDAR as its base
        frame = truth.info["sensor_frame"]
        (out / "extrinsics.yaml").write_text(_rko_extrinsics(rig))
        cmd += ["--config", str(out / "extrinsics.yaml")]
    load, wall0 = os.getloadavg()[0], time.perf_counter()
    with open(out / "log.txt", "w") as log:
        subprocess.run(
            [sys.executable, "-c", WAIT4, str(out / "usage.txt"), *cmd],
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=out,
            check=False,
        )
    wall = time.perf_counter() - wall0
    usage = out / "usage.txt"  # missing: the command did not start (the log says why)
    code, cpu, max_rss_kb = (
        (float(v) for v in usage.read_text().split()) if usage.exists() else (1, 0, 0)
    )
    poses = sorted(out.glob("run_*/*_tum.txt"))  # TUM: time x y z qx qy qz qw, time = sweep end
    if code != 0 or not poses:
        tail = (out / "log.txt").read_text()[-3000:]
        raise RuntimeError(f"rko_lio failed ({' '.join(cmd)}):\n{tail}")
    table = pd.read_csv(poses[0], sep=" ", header=None, names=TUM)
    t = table["time"].to_numpy()
    print(f"rko_lio: {' '.join(cmd)}\n  poses: {poses[0]}", file=sys.stderr)
    errors = trajectory_errors(table, truth.trajectory_of(frame))
    duration = t[-1] - t[0] + float(pd.Series(t).diff().median())  # stamps at the sweeps' ends
    return _result(
        duration,
        wall,
        cpu,
        max_rss_kb / 1024.0,
        errors,
        frame,
        load=0.5 * (load + os.getloadavg()[0]),
    )


def _rko_extrinsics(rig: dict) -> str:
    """rko_lio's config: the IMU's and the LiDAR's poses in the LiDAR's frame (truth/frame.json)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from canopy_kit.core.frames import from_rpy

    def mount(key: str) -> np.ndarray:
        m = rig.get(key, {"translation": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]})
        return from_rpy(m["translation"], m["rpy_deg"])

    imu = np.linalg.inv(mount("base_from_lidar")) @ mount("base_from_imu")
    values = [
        round(float(v), 9) for v in [*Rotation.from_matrix(imu[:3, :3]).as_quat(), *imu[:3, 3]]
    ]
    return (
        f"extrinsic_imu2base_quat_xyzw_xyz: {values}\n"
        "extrinsic_lidar2base_quat_xyzw_xyz: [0, 0, 0, 1, 0, 0, 0]\n"
    )


def _rko_version(exe: Path) -> str | None:
    """rko_lio's and rosbags' versions in the environment of ``exe`` (None: not installed there)."""
    if not exe.exists():
        return None
    code = (
        "import importlib.metadata as m; "
        "print(f\"rko_lio {m.version('rko_lio')}, rosbags {m.version('rosbags')}\")"
    )
    out = subprocess.run(
        [str(exe.parent / "python"), "-c", code], capture_output=True, text=True, check=False
    )
    return out.stdout.strip() if out.returncode == 0 else None


def _cm(metres: float | None) -> str:
    return "-" if metres is None else f"{100 * metres:.1f}"


def _child(mode: str, session: Path, code: Path | None = None, *args: str) -> dict:
    argv = [__file__, "--child", mode, "--session", str(session), *args]
    return child_json(argv, code, mode)


def _simulate(folder: Path, rig: str, sensor: str | None, seed: int) -> dict:
    from canopy_kit.sim import load_sim_config, simulate_session

    cfg = load_sim_config(
        "pistachio",
        {"seed": seed, "orchard": {"rows": 4, "trees_per_row": 10}, "rig": {"name": rig}},
        sensor=sensor,
    )
    return {"session": str(simulate_session(folder / f"bench_pistachio_{rig}", cfg).root)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--session", type=Path, help="Simulated session folder (default: simulate one)"
    )
    parser.add_argument(
        "--rig",
        help="Simulate the session on this sensor rig (identity, the default, "
        "tower, imu-flipped, yawed-lever, side-tilt)",
    )
    parser.add_argument(
        "--sensor", help="Simulated sensor model, e.g. vlp16 (default: the 32-ring one)"
    )
    parser.add_argument("--seed", type=int, default=0, help="Simulation seed")
    parser.add_argument("--keep", action="store_true", help="Keep the simulated session")
    parser.add_argument(
        "--rko-lio",
        type=Path,
        default=RKO_LIO,
        help="rko_lio's command, in its own virtual environment (default: $RKO_LIO or %(default)s)",
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=0,
        help="Then run the default pipeline this many more times and print the median "
        "(the machine's speed varies by up to 40 %% between identical runs)",
    )
    parser.add_argument(
        "--against",
        type=Path,
        help="With --repeat: a checkout of other canopy-kit code (e.g. `git worktree add "
        "/tmp/old REV`), run alternately with this code under the same conditions",
    )
    parser.add_argument(
        "--map-skipped",
        nargs="+",
        choices=list(MAP_SKIPPED),
        help="Only the default pipeline, once with each of these mapping.odometry_map_skipped "
        "(auto: decided from the data; on/off: true/false): a table of the decision, ATE "
        "and CPU (docs/MAPPING.md, 'Livox Mid-360 trajectory error')",
    )
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.against and not args.repeat:
        parser.error("--against needs --repeat N (the number of alternating runs)")
    if args.session and (args.rig or args.sensor) and not args.child:
        parser.error(
            "--rig and --sensor simulate a session: not with --session (its rig is its own)"
        )
    args.rig = args.rig or "identity"
    if args.child:
        result = (
            run_kiss_icp(args.session)
            if args.child == "kiss"
            else _simulate(args.session, args.rig, args.sensor, args.seed)
            if args.child == "simulate"
            else run_canopy_kit(args.session, json.loads(args.child))
        )
        print(json.dumps(result))
        return
    print(
        f"load average at the start: {', '.join(f'{v:.2f}' for v in os.getloadavg())} (1, 5, 15 min)"
    )
    tmp = None
    session = args.session
    if session is None:
        tmp = Path(tempfile.mkdtemp(prefix="bench_mapping_", dir="/tmp"))
        # in a child too: the simulator's peak memory would count in every later child's max RSS
        sim_args = ["--rig", args.rig, "--seed", str(args.seed)]
        sim_args += ["--sensor", args.sensor] if args.sensor else []
        session = Path(_child("simulate", tmp, None, *sim_args)["session"])
    if args.map_skipped:
        try:
            _map_skipped_table(session, args.map_skipped)
        finally:
            if tmp is not None and not args.keep:
                shutil.rmtree(tmp, ignore_errors=True)
        return
    rko_version = _rko_version(args.rko_lio)
    try:
        runs = {
            DEFAULT: _child("{}", session),
            "canopy-kit build_map, one process, every sweep registered, ICP convergence 1e-4 "
            "(workers = 1, odometry_every = 1)": _child(
                '{"workers": 1, "odometry_every": 1, "kiss_convergence": 0.0001}', session
            ),
            "KISS-ICP (Python API, unfiltered, all cores)": _child("kiss", session),
            "rko_lio (its CLI, default config, all cores)": (
                run_rko_lio(session, args.rko_lio) if rko_version else None
            ),
        }
        duration = next(iter(runs.values()))["duration_s"]
        _print_table(session, runs, duration, rko_version)
        if args.repeat:
            _repeat(session, args.repeat, args.against, duration)
    finally:
        if tmp is not None and not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)


def _inputs(session: Path) -> dict[str, str]:
    """What each pipeline reads of this session's bag, by the first word of its name."""
    from canopy_kit.sim.truth import load_truth

    if load_truth(session).info.get("rig", {}).get("tf_static_written", False):
        ours = theirs = "extrinsics from /tf_static"
    else:
        ours = "no /tf_static: every sensor in the LiDAR's frame"
        theirs = "no /tf_static: extrinsics from truth/frame.json in --config"
    return {
        "canopy-kit": f"LiDAR + IMU + GNSS; {ours}",
        "KISS-ICP": "LiDAR",
        "rko_lio": f"LiDAR + IMU; {theirs}",
    }


def _print_table(
    session: Path, runs: dict[str, dict | None], duration: float, rko_version: str | None
) -> None:
    from importlib.metadata import version

    import canopy_kit
    from canopy_kit.sim.session import load_sim_config_of

    cfg = load_sim_config_of(session)
    lidar = cfg.lidar
    print(
        f"session: {session} ({duration:.0f} s of driving, {lidar.rings} rings x {lidar.columns} "
        f"columns, {lidar.rate_hz:g} Hz, rig {cfg.rig.name}, seed {cfg.seed})"
    )
    print(
        f"versions: canopy-kit {canopy_kit.__version__}, kiss-icp {version('kiss-icp')}, "
        f"{rko_version or 'rko_lio not installed'}"
    )
    print(
        f"machine: {os.cpu_count()} cores, load average at the end "
        f"{', '.join(f'{v:.2f}' for v in os.getloadavg())} (1, 5, 15 min)\n"
    )
    print(
        "| pipeline | inputs | poses of | real-time factor, wall | real-time factor, CPU | wall s | CPU s "
        "| load avg | peak RSS MB | ATE m | drift % | map to true surfaces, median / 90 % (cm) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    inputs = _inputs(session)
    for name, r in runs.items():
        what = inputs[name.split()[0]]
        if r is None:
            print(
                f"| {name} | {what} | not installed: `{RKO_INSTALL}` (or --rko-lio PATH) |"
                + " - |" * 9
            )
            continue
        peak = f"{r['peak_mb']:.0f}" + (
            f" + {r['worker_peak_mb']:.0f}/worker" if r["worker_peak_mb"] else ""
        )
        print(
            f"| {name} | {what} | {r['frame']} | {r['duration_s'] / r['wall_s']:.1f}x | "
            f"{r['duration_s'] / r['cpu_s']:.1f}x | {r['wall_s']:.0f} | {r['cpu_s']:.0f} | "
            f"{r['load']:.1f} | {peak} | {r['ate_m']:.3f} | {r['drift_pct']:.2f} | "
            f"{_cm(r['map_median_m'])} / {_cm(r['map_p90_m'])} |"
        )
    stages = runs[DEFAULT]["stages"]
    print(
        f"\nstages (default run, odometry in {runs[DEFAULT]['odometry_processes']} process(es)): "
        + ", ".join(f"{k} {v:.1f}" for k, v in stages.items()),
        flush=True,
    )


def _map_skipped_table(session: Path, modes: list[str]) -> None:
    """The default pipeline once per ``mapping.odometry_map_skipped`` mode: its decision,
    trajectory error and CPU time (each run in a child process of its own)."""
    print(
        f"session: {session}\n\n| odometry_map_skipped | decision (lowest returns, deg) | "
        "ATE cm | drift % | CPU s | wall s | load avg |\n|---|---|---|---|---|---|---|"
    )
    for mode in modes:
        r = _child(json.dumps({"odometry_map_skipped": MAP_SKIPPED[mode]}), session)
        decision = r["map_skipped"] or {}
        low = decision.get("lowest_elevation_deg")
        print(
            f"| {mode} | {'on' if decision.get('on') else 'off'}"
            f"{'' if low is None else f' ({low:.1f})'} | {100 * r['ate_m']:.2f} | "
            f"{r['drift_pct']:.3f} | {r['cpu_s']:.1f} | {r['wall_s']:.1f} | {r['load']:.1f} |",
            flush=True,
        )


def _repeat(session: Path, n: int, against: Path | None, duration: float) -> None:
    """The default pipeline ``n`` times (alternating with the code at ``against``): medians."""
    import statistics

    codes = {"this code": None} | ({f"code at {against}": against} if against else {})
    walls: dict[str, list[float]] = {name: [] for name in codes}
    print(
        f"\nthe default pipeline {n} times"
        + (", alternating with the code at " + str(against) if against else "")
        + ": wall s (load average)"
    )
    for i in range(n):
        line = []
        order = (
            list(codes.items()) if i % 2 == 0 else list(codes.items())[::-1]
        )  # neither always first
        for name, code in order:
            r = _child("{}", session, code)
            walls[name].append(r["wall_s"])
            line.append(f"{name} {r['wall_s']:.1f} ({r['load']:.1f})")
        print(f"  run {i + 1}: " + ", ".join(line), flush=True)
    for name, w in walls.items():
        print(
            f"{name}: median {statistics.median(w):.1f} s = {duration / statistics.median(w):.1f}x wall "
            f"(best {duration / min(w):.1f}x, worst {duration / max(w):.1f}x, {n} runs)"
        )


if __name__ == "__main__":
    main()
