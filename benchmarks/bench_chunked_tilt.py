"""Chunked (parallel) odometry against one process on rigs with a tilted LiDAR.

    .venv/bin/python benchmarks/bench_chunked_tilt.py [--rigs identity tower yawed-lever side-tilt]
        [--orchard pistachio] [--rows 4] [--trees-per-row 4] [--seed 701] [--sensor vlp16]
        [--workers 2 3] [--chunk-sweeps 300] [--overlap 150] [--keep DIR]

For every rig the simulator drives the same path (same seed) and ``build_map`` maps the bag
in one process and in ``--workers`` time chunks (``mapping.odometry_chunk_sweeps`` lowered
so a short drive is cut; the tilt rule ``chunks.MAX_CHUNKED_TILT_DEG`` disabled): as shipped
(40 scans of overlap), with ``--overlap`` scans of overlap (a warm local map and ground grid
at each chunk's start), and with that overlap plus the later chunks' ground-height
correction repeated after stitching against the ground of the whole drive before them
(``ground.regrounded_poses``, switched on with ``chunks.REGROUND_CHUNKS``; "regrounded").
Printed per run: ATE of the reported trajectory, the map's median distance to the true
surfaces, and per chunk (the scans each worker owned) the RMS height error of the LiDAR's
poses (what lifts or sinks that chunk's alleys) and the RMS tilt error, both after the
SE(3) alignment of the whole drive; and the mapping's wall time (the machine may be shared).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np


def simulate(folder: Path, rig: str, args: argparse.Namespace) -> Path:
    """The rig's session (the rigs benchmark's, kept across runs in ``folder``)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_rigs import simulate as simulate_rig

    return simulate_rig(folder, args.orchard, rig, args)


@contextmanager
def chunked_as(reground: bool, overlap: int | None) -> Iterator[None]:
    """Chunked odometry with the tilt rule off, the ground re-correction after stitching on
    or off (``chunks.REGROUND_CHUNKS``) and another overlap of the chunks (None: the shipped)."""
    from canopy_kit.mapping import chunks

    saved = (chunks.MAX_CHUNKED_TILT_DEG, chunks.REGROUND_CHUNKS, chunks.OVERLAP_SWEEPS)
    chunks.MAX_CHUNKED_TILT_DEG = 180.0
    chunks.REGROUND_CHUNKS = reground  # the forked workers inherit these
    if overlap is not None:
        chunks.OVERLAP_SWEEPS = overlap
    try:
        yield
    finally:
        chunks.MAX_CHUNKED_TILT_DEG, chunks.REGROUND_CHUNKS, chunks.OVERLAP_SWEEPS = saved


def chunk_errors(result: object, sim: Path, owned: list[int]) -> list[tuple[float, float]]:
    """Per chunk: RMS height error (m) and RMS tilt error (deg) of the LiDAR's aligned poses."""
    from canopy_kit.evaluate.trajectory_error import _poses, interpolate_reference, se3_alignment
    from canopy_kit.evaluate.truth import load_truth

    truth = load_truth(sim).trajectory  # the LiDAR's true poses
    est_table = (
        result.sensor_trajectory if result.sensor_trajectory is not None else result.trajectory
    )
    ref, inside = interpolate_reference(truth, est_table["time"].to_numpy())
    est = _poses(est_table)[inside]
    aligned = se3_alignment(est, ref) @ est
    dz = aligned[:, 2, 3] - ref[:, 2, 3]
    # Tilt error: the angle between the world's "up" seen in the true and the estimated body
    # frame (roll and pitch error, whatever the heading error).
    up_est, up_ref = aligned[:, 2, :3], ref[:, 2, :3]
    tilt = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", up_est, up_ref), -1.0, 1.0)))
    row = np.flatnonzero(inside)  # trajectory row = sweep order; owned = first row of each chunk
    bounds = [*owned, np.inf]
    out = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        sel = (row >= a) & (row < b)
        out.append((float(np.sqrt(np.mean(dz[sel] ** 2))), float(np.sqrt(np.mean(tilt[sel] ** 2)))))
    return out


def run(
    sim: Path, workers: int, chunk_sweeps: int, reground: bool, split: int, overlap: int | None
) -> dict:
    """Map ``sim`` on ``workers``; per-chunk errors over the ``split``-worker plan's chunks."""
    from canopy_kit.config import MappingConfig
    from canopy_kit.evaluate.trajectory_error import evaluate_against_simulation
    from canopy_kit.mapping import build_map
    from canopy_kit.mapping.chunks import chunk_plan
    from canopy_kit.sim.session import find_bag

    cfg = MappingConfig(workers=workers, odometry_chunk_sweeps=chunk_sweeps)
    with chunked_as(reground, overlap):
        t0 = time.perf_counter()
        res = build_map(find_bag(sim), cfg)
        wall = time.perf_counter() - t0
    ev = evaluate_against_simulation(res, sim)
    n = int(res.diagnostics["scans"])
    owned = [
        c.own
        for c in chunk_plan("", n, MappingConfig(workers=split, odometry_chunk_sweeps=chunk_sweeps))
    ]
    return {
        "workers": int(res.diagnostics.get("odometry_workers", 1)),
        "ate_cm": 100 * ev["ate_rmse_m"],
        "map_cm": 100 * ev["map_aligned"]["median_m"],
        "chunks": chunk_errors(res, sim, owned),
        "wall_s": wall,
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument(
        "--rigs", nargs="+", default=["identity", "tower", "yawed-lever", "side-tilt"]
    )
    parser.add_argument("--orchard", default="pistachio")
    parser.add_argument("--rows", type=int, default=4)
    parser.add_argument("--trees-per-row", type=int, default=4)
    parser.add_argument("--seed", type=int, default=701)
    parser.add_argument("--sensor", default="vlp16")
    parser.add_argument("--workers", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--chunk-sweeps", type=int, default=300)
    parser.add_argument("--overlap", type=int, default=150, help="Scans of overlap to try")
    parser.add_argument(
        "--keep", type=Path, help="Keep the sessions in this folder (and reuse them)"
    )
    args = parser.parse_args()
    base = args.keep or Path(tempfile.mkdtemp(prefix="bench_chunked_tilt_"))
    head = "| rig | run | ATE (cm) | map median (cm) | per chunk: height RMS (cm) / tilt RMS (deg) | wall (s) |"
    print(head)
    print("|---|---|---|---|---|---|")
    try:
        for rig in args.rigs:
            sim = simulate(base / f"{args.orchard}-{rig}", rig, args)
            runs = [("one process", 1, False, None)]
            for w in args.workers:
                runs += [
                    (f"{w} chunks, as shipped (overlap 40)", w, False, None),
                    (f"{w} chunks, overlap {args.overlap}", w, False, args.overlap),
                    (f"{w} chunks, overlap {args.overlap}, regrounded", w, True, args.overlap),
                ]
            for name, w, on, overlap in runs:
                split = w if w > 1 else args.workers[0]
                r = run(sim, w, args.chunk_sweeps, on, split, overlap)
                per = ", ".join(f"{100 * z:.1f} / {t:.2f}" for z, t in r["chunks"])
                print(
                    f"| {rig} | {name} ({r['workers']}) | {r['ate_cm']:.1f} | {r['map_cm']:.2f} "
                    f"| {per} | {r['wall_s']:.0f} |",
                    flush=True,
                )
    finally:
        if args.keep is None:
            shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
