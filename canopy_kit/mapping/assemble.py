"""Pass 2 of :func:`~canopy_kit.mapping.build_map`: every point placed with the fused trajectory.

Each point is moved with the pose at its own time (deskew with the final, smoothed
trajectory) and offered to the voxel map. The sweeps can be split over worker processes
(sweep ``i`` goes to worker ``i % n``); the partial maps are merged so that each voxel
keeps the point that reached it first in acquisition order, as a single process would:
the map does not depend on the number of workers.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.errors import ProcessingError
from canopy_kit.io.bag import BagSession, Scan, open_bag
from canopy_kit.mapping import quaternions as quat
from canopy_kit.mapping.accumulate import MapAccumulator, voxel_hash
from canopy_kit.mapping.deskew import rotate_small
from canopy_kit.mapping.filters import range_mask
from canopy_kit.mapping.sensors import decode_scan
from canopy_kit.mapping.trajectory import ContinuousTrajectory

TIME_FIELD = "gps_time"  # absolute per-point time (bag clock, s); LAS's standard time dimension
POSE_BINS = 64  # per-sweep time bins for per-point poses (1.6 ms apart at 10 Hz)
_ORDER = "__order__"  # internal: acquisition order (sweep index << 24 | point index)


def point_fields(scan_fields: dict[str, np.ndarray], keep: np.ndarray | slice,
                 times: np.ndarray | None, stamp: float, n: int) -> dict[str, np.ndarray]:
    """The scan's own fields (untouched) for the kept points plus absolute ``gps_time``."""
    fields = {k: v[keep] for k, v in scan_fields.items()}
    fields[TIME_FIELD] = times[keep] if times is not None else np.full(n, stamp)
    return fields


def world_points(scan: Scan, trajectory: ContinuousTrajectory, config: MappingConfig,
                 deskew: bool) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """A sweep's points in range, moved to the map frame with the pose at each point's time.

    Returns coordinates, fields (the scan's own plus ``gps_time``) and the kept indices.
    """
    keep = np.flatnonzero(range_mask(scan.xyz, config.min_range, config.max_range))
    xyz = scan.xyz[keep]
    times = scan.times
    fields = point_fields(scan.fields, keep, times, scan.stamp, len(xyz))
    if deskew and times is not None and len(keep):
        t = times[keep]
        lo, hi = float(t.min()), float(t.max())
        bins = np.clip(((t - lo) / max(hi - lo, 1e-12) * (POSE_BINS - 1) + 0.5).astype(np.int64),
                       0, POSE_BINS - 1)
        pos, q = trajectory.quaternions_at(lo + (hi - lo) * np.arange(POSE_BINS) / (POSE_BINS - 1))
        # Each bin's pose relative to the middle one is small: rotate with rotation vectors.
        mid = POSE_BINS // 2
        q_mid_inv = quat.conjugate(q[mid])
        rel_rotvec = quat.to_rotvec(quat.multiply(q_mid_inv, q))
        rel_t = quat.rotate(q_mid_inv, pos - pos[mid])
        local = rotate_small(xyz, rel_rotvec[bins]) + rel_t[bins]
        world = local @ quat.to_matrix(q[mid]).T + pos[mid]
    else:
        valid = times is not None and len(times) and np.ptp(times) > 0
        t_ref = 0.5 * (float(times.min()) + float(times.max())) if valid else scan.stamp  # type: ignore[union-attr]
        pos, rot = trajectory.at(np.array([t_ref]))
        world = xyz @ rot[0].T + pos[0]
    return world, fields, keep


def selected_scans(bag: BagSession, topic: str, wanted: Callable[[int], bool]) -> Iterator[Scan]:
    """Scans of ``topic`` whose index ``wanted`` accepts (the others are not decoded)."""
    reader = bag.reader
    conns = [c for c in reader.connections if c.topic == topic]
    for index, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
        if wanted(index):
            yield decode_scan(bag, topic, reader.deserialize(raw, conn.msgtype), index)


@dataclass
class _Job:
    bag_path: str
    topic: str
    sweeps: dict[int, bool]  # scan index -> deskew
    trajectory: ContinuousTrajectory
    config: MappingConfig
    worker: int
    n_workers: int


def _accumulate(job: _Job, progress: Callable[[int], None] | None = None
                ) -> tuple[np.ndarray, dict[str, np.ndarray], int]:
    acc = MapAccumulator(job.config.map_voxel_size)
    mine = {i: d for i, d in job.sweeps.items() if i % job.n_workers == job.worker}
    with open_bag(job.bag_path) as bag:
        for n, scan in enumerate(selected_scans(bag, job.topic, mine.__contains__), 1):
            xyz, fields, keep = world_points(scan, job.trajectory, job.config, mine[scan.index])
            fields[_ORDER] = (np.int64(scan.index) << 24) | keep.astype(np.int64)
            acc.add(xyz, fields)
            if progress:
                progress(n)
    cloud = acc.cloud()
    return cloud.xyz, cloud.fields, acc.n_offered


def _worker(job: _Job, counter, conn) -> None:  # noqa: ANN001
    """Child process body (fork): accumulate, then send the partial map or the error back."""
    def tick(_: int) -> None:
        with counter.get_lock():
            counter.value += 1

    try:
        conn.send(("ok", _accumulate(job, tick)))
    except BaseException as exc:  # report any failure to the parent instead of dying silently
        conn.send(("error", exc))
    finally:
        conn.close()


def _run_parallel(jobs: list[_Job], total: int,
                  progress: Callable[[str, float, float], None] | None) -> list:
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    counter = ctx.Value("i", 0)
    pipes = [ctx.Pipe(duplex=False) for _ in jobs]
    procs = [ctx.Process(target=_worker, args=(job, counter, send), daemon=True)
             for job, (_, send) in zip(jobs, pipes)]
    for proc in procs:
        proc.start()
    results: list = [None] * len(jobs)
    try:
        while any(r is None for r in results):
            for i, (recv, _) in enumerate(pipes):
                if results[i] is None and recv.poll(0.2):
                    results[i] = recv.recv()
            if progress:
                progress("mapping: map", counter.value, total)
            dead = [i for i, p in enumerate(procs) if results[i] is None and not p.is_alive()
                    and not pipes[i][0].poll()]
            if dead:
                raise ProcessingError(f"map assembly worker {dead[0]} ended without a result "
                                      f"(exit code {procs[dead[0]].exitcode})")
    finally:
        for proc in procs:
            proc.join(timeout=5)
            if proc.is_alive():
                proc.terminate()
    for status, value in results:
        if status == "error":
            raise value
    return [value for _, value in results]


def merge_partial_maps(parts: list[tuple[np.ndarray, dict[str, np.ndarray]]],
                       voxel_size: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """One point per voxel over all parts: the one first in acquisition order; sorted by it."""
    xyz = np.concatenate([p[0] for p in parts])
    names = [k for k in parts[0][1]]
    fields = {k: np.concatenate([p[1][k] for p in parts]) for k in names}
    order = fields[_ORDER]
    keys = voxel_hash(xyz, voxel_size)
    idx = np.lexsort((order, keys))
    first = np.r_[True, keys[idx][1:] != keys[idx][:-1]]
    keep = idx[first]
    keep = keep[np.argsort(order[keep], kind="stable")]
    return xyz[keep], {k: v[keep] for k, v in fields.items()}


def assemble_map(bag_path: str, topic: str, sweeps: dict[int, bool], trajectory: ContinuousTrajectory,
                 config: MappingConfig, progress: Callable[[str, float, float], None] | None = None
                 ) -> tuple[np.ndarray, dict[str, np.ndarray], int]:
    """Place every point of the ``sweeps`` (index -> deskew) and voxel-thin them: xyz, fields, offered."""
    n_workers = config.workers if config.workers > 0 else (os.cpu_count() or 1)
    n_workers = max(1, min(n_workers, len(sweeps) // 50 or 1))
    total = len(sweeps)
    jobs = [_Job(str(bag_path), topic, sweeps, trajectory, config, w, n_workers) for w in range(n_workers)]
    if n_workers == 1:
        def tick(n: int) -> None:
            if progress:
                progress("mapping: map", n, total)

        xyz, fields, offered = _accumulate(jobs[0], tick)
    else:
        parts = _run_parallel(jobs, total, progress)
        xyz, fields = merge_partial_maps([(p[0], p[1]) for p in parts], config.map_voxel_size)
        offered = sum(p[2] for p in parts)
    if progress:
        progress("mapping: map", total, total)
    fields.pop(_ORDER, None)
    return xyz, fields, offered
