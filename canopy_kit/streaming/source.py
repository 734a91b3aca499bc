"""Sweeps of a bag in the odometry frame, read causally, and a running georeference.

The map is kept in the odometry frame (gravity-aligned, origin at the first sweep): it is
locally consistent, so crowns seen from two alleys a minute apart still line up. The GNSS
is used only to place finished trees on the globe. (``mapping.stream_map`` applies its
per-second GNSS refit to every sweep instead; on a tiny simulated session that moved the
map frame by up to 0.9 m in height between refits and blurred the crowns, so its map
cannot be segmented as the batch map is.)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.core.geo import LocalFrame
from canopy_kit.errors import InputError

Progress = Callable[[str, float, float], None]


@dataclass
class OdometrySweep:
    """One registered sweep: its pose and kept points in the odometry frame."""

    index: int
    time: float
    pose: np.ndarray  # (4, 4) odometry_from_sensor
    points: PointCloud  # every scan field plus ``gps_time``


@dataclass
class SweepSource:
    """Iterate a bag's sweeps causally; GNSS fixes met on the way are kept for georeferencing."""

    bag: Path
    config: MappingConfig
    progress: Progress | None = None
    gnss: object | None = None  # mapping.sensors.GnssBuffer once reading has started
    gnss_lever_arm: np.ndarray = field(
        default_factory=lambda: np.zeros(3)
    )  # antenna in the LiDAR frame
    n_scans: int = 0
    warnings: list[str] = field(default_factory=list)
    topics: object | None = None  # mapping.sensors.SensorTopics once the bag is open

    def __iter__(self) -> Iterator[OdometrySweep]:
        from canopy_kit.errors import InputError
        from canopy_kit.io.bag import open_bag
        from canopy_kit.mapping.assemble import point_fields
        from canopy_kit.mapping.extrinsics import resolve_rig
        from canopy_kit.mapping.filters import map_range
        from canopy_kit.mapping.frontend import LidarFrontend, map_points, require_sweeps
        from canopy_kit.mapping.sensors import (
            GnssBuffer,
            ImuBuffer,
            sensor_messages,
            topics_for,
        )

        cfg = self.config
        n_sweeps = 0
        with open_bag(self.bag, self.config.ouster_metadata or None) as bag:
            topics = topics_for(bag, cfg)
            rig = resolve_rig(bag, topics, cfg)
            if rig.calibrate:
                raise InputError(
                    f"{self.bag}: --calibrate-extrinsics (mapping.extrinsics = 'calibrate') needs "
                    "the whole drive before the first sweep; it does not stream. Estimate the mount "
                    "with `canopy-kit map BAG --calibrate-extrinsics` and stream with the rig.toml it "
                    "writes (--rig)"
                )
            self.topics = topics
            self.warnings.extend(rig.warnings + topics.notes)
            self.gnss_lever_arm = rig.gnss_lever_arm
            imu = (
                ImuBuffer(mounting=rig.imu_mounting(), source=f"{bag.path}: topic {topics.imu!r}")
                if topics.imu
                else None
            )
            self.gnss = GnssBuffer() if topics.gnss else None
            if topics.gnss is None:
                self.warnings.append(
                    f"{self.bag}: no GNSS topic: tree positions stay in the "
                    "odometry frame (no latitude/longitude)"
                )
            where = f"{bag.path}: topic {topics.scans!r}"
            frontend = LidarFrontend(
                cfg, imu, where=where, keep_all_points=True, lidar_from_base=rig.lidar_from_base
            )
            total = next((t.count for t in bag.topics() if t.name == topics.scans), 0)

            def sweeps() -> Iterator:
                for scan in sensor_messages(bag, topics, imu, self.gnss):  # type: ignore[arg-type]
                    self.n_scans += 1
                    yield from frontend.feed(scan)
                    if self.progress:
                        self.progress("streaming: sweeps", self.n_scans, total)
                yield from frontend.finish()

            far = map_range(cfg)
            for sweep in sweeps():
                pose = sweep.pose
                local, kept, _ = map_points(sweep, far)
                xyz = local @ pose[:3, :3].T + pose[:3, 3]
                scan = sweep.scan
                fields = point_fields(scan.fields, kept, scan.times, scan.stamp, len(xyz))
                n_sweeps += 1
                yield OdometrySweep(scan.index, sweep.t_ref, pose, PointCloud(xyz, fields))
            require_sweeps(n_sweeps, where)
            self.warnings.extend(frontend.state.warnings + bag.log.warnings())
            self.warnings.extend(imu.warnings if imu is not None else [])  # e.g. IMU in g


class RunningGeoreference:
    """Yaw + translation from the odometry frame to the local UTM frame, fitted to the GNSS.

    ``fit(now)`` uses the fixes seen so far (recent ones weighted more, as the odometry
    drifts); ``fit(None)`` weighs the whole drive equally (the final placement).
    """

    MIN_BASELINE = 15.0  # m of travel before the heading is trusted
    RECENCY = 120.0  # s

    def __init__(self, epoch: float = 1.0) -> None:
        self.epoch = epoch
        self.frame: LocalFrame | None = None
        self._t: list[float] = []
        self._xyz: list[np.ndarray] = []

    def add_pose(self, t: float, position: np.ndarray) -> None:
        """Record where the odometry put the sensor at time ``t``."""
        self._t.append(float(t))
        self._xyz.append(np.asarray(position, float)[:3].copy())

    def fit(self, gnss: object | None, now: float | None = None) -> np.ndarray | None:
        """The (4, 4) local_from_odometry transform, or None while it cannot be known."""
        from canopy_kit.mapping.fusion import heading_alignment
        from canopy_kit.mapping.gnss import gnss_epochs, local_frame_for

        if gnss is None or len(gnss) == 0 or len(self._t) < 2:  # type: ignore[arg-type]
            return None
        series = gnss.series()  # type: ignore[attr-defined]
        try:
            if self.frame is None:
                self.frame = local_frame_for(series)
            epochs = gnss_epochs(series, self.frame, self.epoch)
        except InputError:
            return None
        t, odo = np.asarray(self._t), np.asarray(self._xyz)
        inside = (epochs.t >= t[0]) & (epochs.t <= t[-1])
        if inside.sum() < 3:
            return None
        p_odo = np.column_stack([np.interp(epochs.t[inside], t, odo[:, k]) for k in range(3)])
        if np.ptp(p_odo[:, :2], axis=0).max() < self.MIN_BASELINE:
            return None
        weights = None if now is None else np.exp(-(now - epochs.t[inside]) / self.RECENCY)
        yaw, shift = heading_alignment(p_odo, epochs.xyz[inside], weights)
        out = np.eye(4)
        out[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0, 0, 1]]
        out[:3, 3] = shift
        return out

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Times and odometry-frame positions recorded so far."""
        return np.asarray(self._t), np.asarray(self._xyz).reshape(-1, 3)
