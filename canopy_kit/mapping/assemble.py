"""Pass 2 of :func:`~canopy_kit.mapping.build_map`: every point placed with the fused trajectory.

Each point is moved with the pose at its own time (deskew with the final, smoothed
trajectory) and offered to the voxel map. The sweeps can be split over worker processes
(sweep ``i`` goes to worker ``i % n``); the partial maps are merged so that each voxel
keeps the point that reached it first in acquisition order, as a single process would:
the map does not depend on the number of workers.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.io.bag import BagSession, Scan, open_bag
from canopy_kit.mapping import quaternions as quat
from canopy_kit.mapping.accumulate import MapAccumulator, voxel_hash
from canopy_kit.mapping.filters import range_mask
from canopy_kit.mapping.sensors import decode_scan
from canopy_kit.mapping.trajectory import ContinuousTrajectory
from canopy_kit.parallel import run_jobs, worker_count

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
        world = transform_binned(xyz, bins, quat.to_matrix(q), pos)
    else:
        valid = times is not None and len(times) and np.ptp(times) > 0
        t_ref = 0.5 * (float(times.min()) + float(times.max())) if valid else scan.stamp  # type: ignore[union-attr]
        pos, rot = trajectory.at(np.array([t_ref]))
        world = xyz @ rot[0].T + pos[0]
    return world, fields, keep


def transform_binned(xyz: np.ndarray, bins: np.ndarray, rotations: np.ndarray,
                     translations: np.ndarray) -> np.ndarray:
    """``rotations[b] @ p + translations[b]`` for each point ``p`` of bin ``b``.

    One matrix product per bin over the bin's points; a sweep's points usually come in
    time order, so the bins are contiguous runs and need no sorting.
    """
    order = None
    if len(bins) > 1 and np.any(bins[1:] < bins[:-1]):
        order = np.argsort(bins, kind="stable")
        xyz, bins = xyz[order], bins[order]
    edges = np.searchsorted(bins, np.arange(len(rotations) + 1))
    out = np.empty_like(xyz, dtype=np.float64)
    for b in np.flatnonzero(np.diff(edges)):
        part = slice(edges[b], edges[b + 1])
        out[part] = xyz[part] @ rotations[b].T + translations[b]
    if order is not None:
        placed = np.empty_like(out)
        placed[order] = out
        out = placed
    return out


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


def _accumulate(job: _Job, tick: Callable[[], None] | None = None
                ) -> tuple[np.ndarray, dict[str, np.ndarray], int]:
    acc = MapAccumulator(job.config.map_voxel_size)
    mine = {i: d for i, d in job.sweeps.items() if i % job.n_workers == job.worker}
    with open_bag(job.bag_path) as bag:
        for scan in selected_scans(bag, job.topic, mine.__contains__):
            xyz, fields, keep = world_points(scan, job.trajectory, job.config, mine[scan.index])
            fields[_ORDER] = (np.int64(scan.index) << 24) | keep.astype(np.int64)
            acc.add(xyz, fields)
            if tick:
                tick()
    cloud = acc.cloud()
    return cloud.xyz, cloud.fields, acc.n_offered


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
    n_workers = worker_count(config.workers, len(sweeps) // 50)
    total = len(sweeps)
    jobs = [_Job(str(bag_path), topic, sweeps, trajectory, config, w, n_workers) for w in range(n_workers)]
    parts = run_jobs(_accumulate, jobs, "mapping: map", total, progress)
    if len(parts) == 1:
        xyz, fields, offered = parts[0]
    else:
        xyz, fields = merge_partial_maps([(p[0], p[1]) for p in parts], config.map_voxel_size)
        offered = sum(p[2] for p in parts)
    if progress:
        progress("mapping: map", total, total)
    fields.pop(_ORDER, None)
    return xyz, fields, offered
