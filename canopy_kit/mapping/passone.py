"""Pass 1 of :func:`~canopy_kit.mapping.build_map`: the odometry front end over the bag.

:class:`PassOne` feeds a bag's scans (all, or one range of them) through the
:class:`~canopy_kit.mapping.frontend.LidarFrontend` while it collects the IMU and GNSS;
:class:`OdometryPass` is what the rest of the mapping needs from it, whether it came from
one process (:func:`odometry_pass`) or from time chunks stitched together
(:mod:`canopy_kit.mapping.chunks`). The warnings and quality flags are worded here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.core.geo import LocalFrame
from canopy_kit.io.bag import BagSession, stray_times_warning
from canopy_kit.io.message_log import MessageLog
from canopy_kit.mapping.extrinsics import SensorRig, resolve_rig
from canopy_kit.mapping.frontend import (
    DROPOUT_S,
    STANDSTILL_M,
    FrontendState,
    FrontendSweep,
    LidarFrontend,
)
from canopy_kit.mapping.ground import refinement_points
from canopy_kit.mapping.imu import ImuSeries
from canopy_kit.mapping.sensors import (
    GnssBuffer,
    ImuBuffer,
    SensorTopics,
    sensor_messages,
    topics_for,
)

Progress = Callable[[str, float, float], None]


class SweepRecord(NamedTuple):
    """What the pose graph and the map pass need of one sweep."""

    index: int  # scan index in the bag
    t_ref: float  # the instant ``pose`` refers to
    pose: np.ndarray  # (4, 4) odometry frame
    uncertainty: float
    deskewed: bool
    registered: bool  # False: a prediction only (``mapping.odometry_every``)
    # The ground points its height correction used (sensor frame, float32, thinned), kept for
    # a time chunk's sweeps with ``chunks.REGROUND_CHUNKS`` on (:func:`~.ground.regrounded_poses`).
    ground: np.ndarray | None = None


@dataclass
class OdometryPass:
    """The front end's output over a whole bag, with what it noticed on the way."""

    bag_path: str
    topics: SensorTopics
    records: list[SweepRecord]
    state: FrontendState
    imu: ImuSeries | None  # None: mapped without the IMU
    gnss: GnssBuffer | None
    n_scans: int = 0
    n_without_time: int = 0
    first_stamp: float = np.inf
    last_stamp: float = -np.inf
    bag_warnings: list[str] = field(default_factory=list)  # but the corrupt-times one: ``stray``
    recovered: bool = False
    workers: int = 1
    stray: list[tuple[int, int]] = field(default_factory=list)  # (scan, points with corrupt times)
    # The bag's log time (ns) of scan 0, 1, ... as far as they were read (the map pass seeks with it).
    scan_log_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    rig: SensorRig | None = None  # the frames the pass ran with
    # What the reader met on each topic: messages used, dropped or trimmed, time spans, frames.
    log: MessageLog | None = None


def scan_count(bag: BagSession, topic: str) -> int:
    """Messages on ``topic`` according to the bag's index."""
    return next((t.count for t in bag.topics() if t.name == topic), 0)


class PassOne:
    """Front end over the bag: sweeps, IMU and GNSS, with running counts for diagnostics.

    ``scan_range = (first, end)`` processes scans ``first <= index < end`` only (IMU and GNSS
    are collected from the start of the bag); scans before ``count_from`` are left out of
    the counts (a chunk's overlap with the chunk before it).
    """

    def __init__(
        self,
        bag: BagSession,
        config: MappingConfig,
        progress: Progress | None,
        keep_all_points: bool,
        scan_range: tuple[int, int | None] = (0, None),
        count_from: int = 0,
        rig: SensorRig | None = None,
        lidar_only: bool = False,
    ) -> None:
        self.bag = bag
        self.config = config
        self.topics = topics_for(bag, config)
        self.rig = rig if rig is not None else resolve_rig(bag, self.topics, config)
        # ``lidar_only``: the IMU is collected (as recorded) but the front end does not use it.
        self.lidar_only = lidar_only
        self.imu = (
            ImuBuffer(
                mounting=self.rig.imu_mounting(), source=f"{bag.path}: topic {self.topics.imu!r}"
            )
            if self.topics.imu
            else None
        )
        self.gnss = GnssBuffer() if self.topics.gnss else None
        self.frontend = LidarFrontend(
            config,
            None if lidar_only else self.imu,
            where=f"{bag.path}: topic {self.topics.scans!r}",
            keep_all_points=keep_all_points,
            lidar_from_base=self.rig.lidar_from_base,
        )
        self.total = scan_count(bag, self.topics.scans)
        self.progress = progress
        self.scan_range = scan_range
        self.count_from = count_from
        self.n_scans = 0
        self.n_without_time = 0
        self.first_stamp = np.inf
        self.last_stamp = -np.inf
        self.scan_log_ns: list[int] = []

    def sweeps(self) -> Iterator[FrontendSweep]:
        """Registered (and, with ``odometry_every`` > 1, predicted) sweeps in bag order."""
        for scan in sensor_messages(
            self.bag, self.topics, self.imu, self.gnss, *self.scan_range, log_times=self.scan_log_ns
        ):
            if scan.index >= self.count_from:
                self.n_scans += 1
                self.first_stamp = min(self.first_stamp, scan.stamp)
                self.last_stamp = max(self.last_stamp, scan.stamp)
                if scan.times is None:
                    self.n_without_time += 1
            yield from self.frontend.feed(scan)
            if self.progress:
                self.progress("mapping: odometry", self.n_scans, self.total)
        yield from self.frontend.finish()

    def result(self, records: list[SweepRecord]) -> OdometryPass:
        """The pass's output once :meth:`sweeps` is exhausted."""
        imu = self.imu.series() if self.imu is not None and len(self.imu) >= 20 else None
        if self.frontend.imu is None and not self.lidar_only:
            imu = None
        skip = self.bag.stray_warning_index
        bag_warnings = [w for i, w in enumerate(self.bag.warnings) if i != skip]
        bag_warnings += self.imu.warnings if self.imu is not None else []  # e.g. IMU in g
        stray = [(i, n) for i, n in self.bag.stray_time_scans if i >= self.count_from]
        return OdometryPass(
            str(self.bag.path),
            self.topics,
            records,
            self.frontend.state,
            imu,
            self.gnss,
            self.n_scans,
            self.n_without_time,
            self.first_stamp,
            self.last_stamp,
            bag_warnings,
            self.bag.recovered,
            stray=stray,
            scan_log_ns=np.asarray(self.scan_log_ns, np.int64),
            rig=self.rig,
            log=self.bag.log,
        )


GROUND_KEPT = 1000  # ground points kept per sweep for the re-correction of chunks


def record(sweep: FrontendSweep, keep_ground: bool = False) -> SweepRecord:
    """The :class:`SweepRecord` of a front-end sweep (with its ground points if ``keep_ground``)."""
    ground = None
    if keep_ground and sweep.registered:
        ground = refinement_points(sweep.xyz[sweep.ground], GROUND_KEPT).astype(np.float32)
    return SweepRecord(
        sweep.scan.index,
        sweep.t_ref,
        sweep.pose,
        sweep.uncertainty,
        sweep.deskewed,
        sweep.registered,
        ground,
    )


def odometry_pass(
    bag: BagSession,
    config: MappingConfig,
    progress: Progress | None = None,
    scan_range: tuple[int, int | None] = (0, None),
    count_from: int = 0,
    rig: SensorRig | None = None,
    lidar_only: bool = False,
    keep_ground: bool = False,
) -> OdometryPass:
    """Run the front end over the bag (or a range of its scans) in this process.

    ``keep_ground``: the records keep their ground points (a time chunk's, for stitching)."""
    one = PassOne(
        bag,
        config,
        progress,
        keep_all_points=False,
        scan_range=scan_range,
        count_from=count_from,
        rig=rig,
        lidar_only=lidar_only,
    )
    return one.result([record(s, keep_ground) for s in one.sweeps()])


def _input_warnings(topics: SensorTopics, config: MappingConfig, bag_path: str) -> list[str]:
    out = []
    if config.use_imu and topics.imu is None:
        out.append(
            f"{bag_path}: no IMU topic (sensor_msgs/msg/Imu): mapped with LiDAR only "
            "(no gravity alignment, no gyro deskew or rotation prior)"
        )
    if config.use_gnss and topics.gnss is None:
        out.append(
            f"{bag_path}: no GNSS topic (sensor_msgs/msg/NavSatFix): the map is not "
            "georeferenced (local frame at the first sweep) and drift is not bounded"
        )
    return out


def pass_warnings(p: OdometryPass, config: MappingConfig) -> list[str]:
    """Everything about the input and the odometry a user should hear of, one line each."""
    out = (
        list(p.bag_warnings) + list(p.topics.notes) + _input_warnings(p.topics, config, p.bag_path)
    )
    if p.log is not None:
        out += p.log.warnings()
    if p.stray:
        out.append(stray_times_warning(p.bag_path, p.topics.scans, p.stray))
    st = p.state
    scans = p.topics.scans
    if p.n_without_time:
        out.append(
            f"{p.bag_path}: topic {scans!r}: {p.n_without_time} of "
            f"{p.n_scans} scans have no per-point time field (t, time, timestamp...); "
            "those were mapped without deskew"
        )
    elif st.not_deskewed and config.deskew:
        out.append(
            f"{st.not_deskewed} sweeps had unusable per-point times (constant or "
            "non-finite) and were mapped without deskew"
        )
    if st.skipped_sparse:
        out.append(
            f"{len(st.skipped_sparse)} scans had fewer than "
            f"{config.min_points_per_scan} points in range and were skipped "
            f"(first: scan {st.skipped_sparse[0]})"
        )
    if st.rejected_registrations:
        out.append(
            f"{st.rejected_registrations} of {st.sweeps} sweeps: ICP moved the motion "
            f"prediction by more than {config.odometry_max_correction} m or "
            f"{config.odometry_max_correction_deg} deg; the prediction was kept "
            "(little structure in view?)"
        )
    if st.out_of_order:
        out.append(
            f"{p.bag_path}: topic {scans!r}: {len(st.out_of_order)} scans "
            "stamped at or before the scan before them (repeated or backwards time) were "
            f"skipped (first: scan {st.out_of_order[0]})"
        )
    if st.gaps:
        start, length = max(st.gaps, key=lambda g: g[1])
        out.append(
            f"{p.bag_path}: topic {scans!r}: no scan for {length:.1f} s "
            f"after t={start:.3f} s ({len(st.gaps)} gap(s) over {DROPOUT_S:.0f} s): sensor "
            "dropout, the map has a hole there"
        )
    if st.sweeps >= 2 and st.max_displacement < STANDSTILL_M:
        out.append(
            f"the robot moved at most {st.max_displacement:.2f} m from its start: the map "
            "shows what one spot sees (one-sided crowns, trees out of range missing)"
        )
    if st.ground_fallbacks:
        out.append(
            f"{st.ground_fallbacks} sweeps had almost no points above the ground; their "
            "odometry used the ground points (flat-ground trap possible)"
        )
    return out + list(st.warnings)


def quality_flags(p: OdometryPass, frame: LocalFrame | None, imu: object) -> list[str]:
    """Short names of what makes the map less trustworthy than a clean drive's (metrics.json)."""
    st = p.state
    flags = {
        "bag_recovered": p.recovered,
        "scan_gaps": bool(st.gaps),
        "scans_out_of_order": bool(st.out_of_order),
        "scans_skipped": bool(st.skipped_sparse),
        "point_times_dropped": bool(p.stray),
        "standing_still": st.max_displacement < STANDSTILL_M,
        "no_imu": imu is None,
        "not_georeferenced": frame is None,
    }
    return [name for name, raised in flags.items() if raised] + (
        p.log.flags() if p.log is not None else []
    )
