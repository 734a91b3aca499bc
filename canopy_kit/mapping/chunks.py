"""Pass 1 in parallel: the drive cut into consecutive chunks, one odometry per worker process.

KISS-ICP's registration holds the GIL and a sweep needs the one before it, so one
odometry runs on one core. A long drive is therefore cut into ``n`` chunks of consecutive
scans; every chunk after the first starts ``OVERLAP_SWEEPS`` scans early, and each worker
reads the bag from its start (scans before its chunk are skipped undecoded, IMU and GNSS
are collected: the standstill at the start levels every chunk and fixes the gyro bias).
Each chunk's odometry lives in its own frame; chunk ``k`` is tied to chunk ``k - 1`` by
the mean of ``T_prev(i) · T_k(i)⁻¹`` over the overlap sweeps both registered, taken from
the second half of the overlap (chunk ``k``'s local map needs a few sweeps to fill up).
The stitched odometry then goes to the pose graph like a single process's: the seams are
as good as one registration. A LiDAR tilted from the vehicle's vertical keeps its odometry in
one process (``MAX_CHUNKED_TILT_DEG``; what was tried to lift that rule is noted there).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from canopy_kit.config import MappingConfig
from canopy_kit.core.parallel import Tick, run_forked, worker_count
from canopy_kit.io.bag import BagSession, open_bag
from canopy_kit.io.message_log import MessageLog, merged
from canopy_kit.mapping.extrinsics import SensorRig, resolve_rig
from canopy_kit.mapping.ground import regrounded_poses
from canopy_kit.mapping.passone import OdometryPass, SweepRecord, odometry_pass, scan_count
from canopy_kit.mapping.sensors import topics_for

Progress = Callable[[str, float, float], None]
OVERLAP_SWEEPS = 40  # scans each chunk after the first starts early
MIN_TIE_SWEEPS = 5  # overlap sweeps both chunks registered, needed to tie them
# Reading a scan undecoded (to reach a chunk's start) costs this share of processing one
# (measured on a 32-ring MCAP session: 1.1 s for 1185 scans skipped, 12.5 s processed).
SKIP_COST = 0.085
# A LiDAR tilted further than this from the vehicle's vertical sees the ground on one side
# only: the ground then fixes its height but not its tilt, and the height rests on the
# ground grid of the whole drive so far, which a chunk starting mid-drive does not have
# (measured on a LiDAR pitched 12 deg: alleys of the second chunk up to 5 cm high, map 2.3
# against 1.5 cm from the true surfaces, volumes 3.5 against 2.3 % above the true-pose map's).
# Tried to lift the rule (benchmarks/bench_chunked_tilt.py, pistachio, tower rig pitched 12
# deg): 150 scans of overlap (warm local map and ground grid) and, after stitching, the later
# chunks' ground correction repeated against the ground of the whole drive before them
# (ground.regrounded_poses). On 4 x 4 trees, 2 chunks of 300 scans, that brought the map to a
# single process's (1.14 against 1.15 cm from the true surfaces; 1.37 without the repeat),
# and yawed-lever too (1.12 against 1.11), but side-tilt (rolled 20 deg) got worse (1.37
# against 1.26, its second chunk's heights 1.4-1.5 against 0.5-0.6 cm RMS); on 4 x 10 (the
# rigs benchmark's drive, 2 chunks of the default size) tower stayed apart (2.02 against 1.50
# cm; 3.15 without the repeat). So the rule stays, and the repeat is off (REGROUND_CHUNKS).
MAX_CHUNKED_TILT_DEG = 5.0
# Repeat the later chunks' ground-height correction after stitching (see above; the chunks
# then keep a thinned copy of each sweep's ground points). Off: it did not hold on every rig.
REGROUND_CHUNKS = False


@dataclass(frozen=True)
class Chunk:
    """Scans ``first <= index < end`` are processed; those from ``own`` on are this chunk's."""

    bag_path: str
    config: MappingConfig
    first: int
    own: int
    end: int | None  # None: to the end of the bag
    rig: SensorRig | None = None
    lidar_only: bool = False


def chunk_plan(
    bag_path: str,
    n_scans: int,
    config: MappingConfig,
    rig: SensorRig | None = None,
    lidar_only: bool = False,
) -> list[Chunk]:
    """The chunks for ``n_scans`` scans: one per worker (``mapping.workers``, 0: every core)."""
    workers = worker_count(config.workers, n_scans // max(config.odometry_chunk_sweeps, 1))
    bounds = balanced_bounds(n_scans, workers)
    step = max(1, config.odometry_every)

    def start(own: int) -> int:  # early enough for the overlap, in step with the chunk before
        return max(0, (own - OVERLAP_SWEEPS) // step * step)

    return [
        Chunk(
            bag_path,
            config,
            start(int(a)) if k else 0,
            int(a),
            int(b) if k < workers - 1 else None,
            rig,
            lidar_only,
        )
        for k, (a, b) in enumerate(itertools.pairwise(bounds))
    ]


def balanced_bounds(n_scans: int, n_chunks: int) -> np.ndarray:
    """Chunk borders (``n_chunks + 1`` scan indices) that give every worker the same work.

    A chunk after the first also processes ``OVERLAP_SWEEPS`` scans of the one before and
    reads every scan before that undecoded (``SKIP_COST`` of a processed scan each), so
    later chunks own fewer scans.
    """

    def extra(own: float) -> float:  # work of a chunk owning scans from ``own`` on, besides them
        return 0.0 if own == 0 else OVERLAP_SWEEPS + SKIP_COST * max(own - OVERLAP_SWEEPS, 0.0)

    def borders(load: float) -> list[float]:
        out = [0.0]
        for _ in range(n_chunks - 1):
            out.append(out[-1] + max(load - extra(out[-1]), 1.0))
        return out

    lo, hi = 0.0, float(n_scans)
    for _ in range(60):  # the load per chunk for which the last chunk gets as much as the others
        load = 0.5 * (lo + hi)
        last = borders(load)[-1]
        lo, hi = (load, hi) if n_scans - last + extra(last) > load else (lo, load)
    return np.array([*borders(load), n_scans]).round().astype(int)


def _run_chunk(chunk: Chunk, tick: Tick) -> OdometryPass:
    counted = 0

    def progress(_: str, n: float, __: float) -> None:
        nonlocal counted
        while counted < n:
            counted += 1
            tick()

    with open_bag(chunk.bag_path, chunk.config.ouster_metadata or None) as bag:
        return odometry_pass(
            bag,
            chunk.config,
            progress,
            (chunk.first, chunk.end),
            count_from=chunk.own,
            rig=chunk.rig,
            lidar_only=chunk.lidar_only,
            keep_ground=REGROUND_CHUNKS and chunk.config.odometry_ground_refine,
        )


def tie(previous: list[SweepRecord], current: list[SweepRecord], own: int) -> np.ndarray | None:
    """``A`` with ``A · T_current ≈ T_previous`` on the overlap, or None when too few sweeps tie."""
    before = {r.index: r for r in previous if r.registered}
    overlap = [r for r in current if r.index < own and r.index in before]
    overlap = overlap[len(overlap) // 2 :]
    # Sweeps both registered; else the current chunk's predictions (a gyro-and-velocity
    # extrapolation over one sweep: millimetres off) stand in.
    pairs = [(before[r.index].pose, r.pose) for r in overlap if r.registered]
    if len(pairs) < MIN_TIE_SWEEPS:
        pairs = [(before[r.index].pose, r.pose) for r in overlap]
    if len(pairs) < MIN_TIE_SWEEPS:
        return None
    each = np.array([p @ np.linalg.inv(c) for p, c in pairs])
    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(each[:, :3, :3]).mean().as_matrix()
    out[:3, 3] = each[:, :3, 3].mean(axis=0)
    return out


def stitch(chunks: list[Chunk], parts: list[OdometryPass]) -> OdometryPass | None:
    """One :class:`OdometryPass` in the first chunk's frame; None when a seam cannot be tied."""
    first, last = parts[0], parts[-1]
    records = [r for r in first.records if len(chunks) == 1 or r.index < chunks[1].own]
    to_first = np.eye(4)
    for k in range(1, len(parts)):
        a = tie(parts[k - 1].records, parts[k].records, chunks[k].own)
        if a is None:
            return None
        to_first = to_first @ a
        end = chunks[k + 1].own if k + 1 < len(chunks) else np.inf
        records += [
            r._replace(pose=to_first @ r.pose)
            for r in parts[k].records
            if chunks[k].own <= r.index < end
        ]
    records, regrounded = _regrounded(records, chunks)
    states = [p.state for p in parts]
    origin = records[0].pose[:2, 3]
    state = replace(
        first.state,
        rotations=last.state.rotations,  # the last worker integrated the gyro over the whole drive
        sweeps=len(records),
        skipped_sparse=sorted(
            {i for s, c in zip(states, chunks) for i in s.skipped_sparse if i >= c.own}
        ),
        not_deskewed=sum(not r.deskewed for r in records),
        ground_fallbacks=sum(s.ground_fallbacks for s in states),
        ground_corrections=sum(s.ground_corrections for s in states) + regrounded,
        out_of_order=sorted(
            {i for s, c in zip(states, chunks) for i in s.out_of_order if i >= c.own}
        ),
        gaps=sorted({g for s in states for g in s.gaps}),
        max_displacement=float(max(np.hypot(*(r.pose[:2, 3] - origin)) for r in records)),
        rejected_registrations=sum(s.rejected_registrations for s in states),
        warnings=list(dict.fromkeys(w for s in states for w in s.warnings)),
    )
    return OdometryPass(
        first.bag_path,
        first.topics,
        records,
        state,
        last.imu,
        last.gnss,
        n_scans=sum(p.n_scans for p in parts),
        n_without_time=sum(p.n_without_time for p in parts),
        first_stamp=min(p.first_stamp for p in parts),
        last_stamp=max(p.last_stamp for p in parts),
        bag_warnings=list(dict.fromkeys(w for p in parts for w in p.bag_warnings)),
        recovered=first.recovered,
        workers=len(parts),
        stray=sorted({(i, n) for p, c in zip(parts, chunks) for i, n in p.stray if i >= c.own}),
        scan_log_ns=last.scan_log_ns,  # the last chunk read every scan message from the start
        rig=first.rig,
        log=_stitched_log(chunks, parts),
    )


def _regrounded(records: list[SweepRecord], chunks: list[Chunk]) -> tuple[list[SweepRecord], int]:
    """The stitched records with the later chunks' heights and tilts corrected again against
    the ground of the whole drive before them (:func:`regrounded_poses`), their ground points
    dropped; and the number of sweeps corrected."""
    if len(chunks) < 2 or not (REGROUND_CHUNKS and chunks[0].config.odometry_ground_refine):
        return [r._replace(ground=None) for r in records], 0
    fixed = sum(r.index < chunks[1].own for r in records)
    poses, corrected = regrounded_poses(
        [r.pose for r in records], [r.ground for r in records], fixed
    )
    return [r._replace(pose=p, ground=None) for r, p in zip(records, poses, strict=True)], corrected


def _stitched_log(chunks: list[Chunk], parts: list[OdometryPass]) -> MessageLog | None:
    """The scans' log from each chunk's own scans; the IMU's and GNSS's from the last chunk,
    which read them from the start of the bag."""
    if any(p.log is None for p in parts):
        return None
    topic = parts[0].topics.scans
    log = MessageLog(parts[0].bag_path)
    log.topics = dict(parts[-1].log.topics)  # type: ignore[union-attr]
    ends = [c.own for c in chunks[1:]] + [np.inf]
    log.topics[topic] = merged(
        [
            p.log.topic(topic, "scans").restricted(c.own, end)  # type: ignore[union-attr]
            for p, c, end in zip(parts, chunks, ends, strict=True)
        ]
    )
    return log


def lidar_tilt_deg(rig: SensorRig | None) -> float:
    """Angle (deg) between the LiDAR's z axis and the vehicle's (0 without a base frame)."""
    if rig is None:
        return 0.0
    return float(np.degrees(np.arccos(np.clip(abs(rig.lidar_from_base[2, 2]), 0.0, 1.0))))


def run_odometry(
    bag: BagSession,
    config: MappingConfig,
    progress: Progress | None = None,
    rig: SensorRig | None = None,
    lidar_only: bool = False,
) -> OdometryPass:
    """Pass 1 over the whole bag: in chunks on several cores when the drive is long enough.

    ``rig`` (resolved from the bag when None) says how the IMU sits in the LiDAR frame;
    ``lidar_only`` collects the IMU without using it (to estimate that mounting)."""
    topics = topics_for(bag, config)
    if rig is None:
        rig = resolve_rig(bag, topics, config)
    n_scans = scan_count(bag, topics.scans)
    chunks = chunk_plan(str(bag.path), n_scans, config, rig, lidar_only)
    if len(chunks) > 1 and lidar_tilt_deg(rig) > MAX_CHUNKED_TILT_DEG:
        chunks = chunks[:1]  # one process: see MAX_CHUNKED_TILT_DEG
    if len(chunks) > 1 and not bag.recovered:
        parts = run_forked(_run_chunk, chunks, "mapping: odometry", n_scans, progress)
        stitched = stitch(chunks, parts)
        if stitched is not None:
            return stitched
        single = odometry_pass(bag, config, progress, rig=rig, lidar_only=lidar_only)
        single.state.warnings.append(
            f"odometry: the {len(chunks)} parallel chunks of the drive could not be tied together "
            f"(fewer than {MIN_TIE_SWEEPS} sweeps registered in an overlap); ran in one process"
        )
        return single
    return odometry_pass(bag, config, progress, rig=rig, lidar_only=lidar_only)
