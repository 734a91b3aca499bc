"""The mapping stage's entry points: :func:`build_map` (whole bag) and :func:`stream_map`.

``build_map`` reads the bag twice: pass 1 runs the odometry front end and collects IMU
and GNSS; the pose graph then fuses everything; pass 2 deskews every point with the
fused continuous-time trajectory and accumulates the voxel-thinned map.
``stream_map`` is causal: each sweep comes out registered as soon as it is processed,
placed with the odometry pose georeferenced by a fit to the first GNSS fixes (later,
better fits come with each sweep as an update).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.config import MappingConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.core.geo import LocalFrame
from canopy_kit.core.parallel import cpu_seconds
from canopy_kit.errors import InputError
from canopy_kit.io.bag import GnssSeries, open_bag
from canopy_kit.mapping.assemble import TIME_FIELD, assemble_map, point_fields
from canopy_kit.mapping.calibration import calibrate_rig, check_rig
from canopy_kit.mapping.chunks import run_odometry
from canopy_kit.mapping.extrinsics import SensorRig, resolve_rig
from canopy_kit.mapping.filters import map_range
from canopy_kit.mapping.frontend import FrontendSweep, map_points, require_sweeps
from canopy_kit.mapping.fusion import (
    FusionResult,
    FusionSettings,
    fuse_trajectory,
    heading_alignment,
)
from canopy_kit.mapping.gnss import (
    GnssEpochs,
    fix_report,
    gnss_epochs,
    invalid_fix_warning,
    local_frame_for,
    rejection_reasons,
    report_warning,
    reported_sigmas,
)
from canopy_kit.mapping.gnss_jumps import odometry_outliers
from canopy_kit.mapping.ground_view import ground_view, map_skipped_decision
from canopy_kit.mapping.kernels import warm_up
from canopy_kit.mapping.passone import OdometryPass, PassOne, pass_warnings, quality_flags
from canopy_kit.mapping.sensors import GnssBuffer, SensorTopics, topics_for
from canopy_kit.mapping.trajectory import ContinuousTrajectory, pose_table

Progress = Callable[[str, float, float], None]


@dataclass
class RegisteredScan:
    """One sweep placed in the map frame (what :func:`stream_map` yields)."""

    index: int
    stamp: float
    time: float  # the instant ``pose`` refers to (middle of the sweep)
    pose: np.ndarray  # (4, 4) map_from_sensor
    points: PointCloud  # kept points in the map frame, every field plus ``gps_time``
    ground: np.ndarray  # (N,) points the odometry's ground filter removed
    georeferenced: bool
    # (4, 4) map frame -> local UTM frame by the latest, better GNSS fit (identity until refitted)
    georeference_update: np.ndarray = field(default_factory=lambda: np.eye(4))


@dataclass
class MappingResult:
    """The map, the trajectory and what happened on the way."""

    map: PointCloud
    trajectory: pd.DataFrame  # time, x, y, z, qx, qy, qz, qw (map frame, one row per sweep)
    frame: LocalFrame | None  # None: not georeferenced (no GNSS)
    diagnostics: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    config: MappingConfig = field(default_factory=MappingConfig)
    rig: SensorRig | None = None  # the sensors' frames the map was built with
    # The LiDAR's own poses (``trajectory`` is the base frame's, ``rig.base_name``).
    sensor_trajectory: pd.DataFrame | None = None

    @property
    def trajectory_frame(self) -> str:
        """The frame whose poses ``trajectory`` holds."""
        return self.rig.base_name if self.rig is not None else ""


def fusion_settings(config: MappingConfig, rig: SensorRig | None = None) -> FusionSettings:
    """The pose-graph settings a mapping config asks for (the antenna lever arm from the rig)."""
    lever = rig.gnss_lever_arm if rig is not None else np.asarray(config.gnss_lever_arm, float)
    return FusionSettings(
        keyframe_every=config.keyframe_every,
        odometry_jitter_rotation=config.odometry_jitter_rotation,
        odometry_jitter_translation=config.odometry_jitter_translation,
        odometry_drift_rotation=config.odometry_drift_rotation,
        odometry_drift_translation=config.odometry_drift_translation,
        gyro_noise_density=config.gyro_noise_density,
        accel_noise_density=config.accel_noise_density,
        gyro_bias_walk=config.gyro_bias_walk,
        accel_bias_walk=config.accel_bias_walk,
        gnss_correlation_time=config.gnss_correlation_time,
        gnss_white_fraction=config.gnss_white_fraction,
        gnss_lever_arm=tuple(float(v) for v in lever),  # type: ignore[arg-type]
    )


def _check_config(config: MappingConfig) -> None:
    from canopy_kit.errors import ConfigError

    if not 0 <= config.min_range < config.max_range:
        raise ConfigError(
            f"mapping.min_range/max_range: need 0 <= min_range < max_range, got "
            f"{config.min_range}, {config.max_range}"
        )
    if not config.map_max_range > config.min_range:
        raise ConfigError(
            f"mapping.map_max_range: must be above min_range ({config.min_range} m), got "
            f"{config.map_max_range}"
        )
    for name in (
        "map_voxel_size",
        "kiss_voxel_size",
        "kiss_convergence",
        "gnss_epoch",
        "gnss_correlation_time",
    ):
        if not getattr(config, name) > 0:
            raise ConfigError(f"mapping.{name}: must be positive, got {getattr(config, name)}")
    if len(config.gnss_lever_arm) != 3:
        raise ConfigError(
            f"mapping.gnss_lever_arm: expected [x, y, z], got {config.gnss_lever_arm}"
        )
    if not config.extrinsic_tolerance_deg > 0:
        raise ConfigError(
            f"mapping.extrinsic_tolerance_deg: must be positive, got {config.extrinsic_tolerance_deg}"
        )
    if config.rig:
        from canopy_kit.config.rig import parse_rig

        parse_rig(config.rig, config.rig_name or "mapping.rig")
    for name in (
        "keyframe_every",
        "odometry_point_stride",
        "odometry_every",
        "odometry_chunk_sweeps",
    ):
        if getattr(config, name) < 1:
            raise ConfigError(f"mapping.{name}: must be >= 1, got {getattr(config, name)}")
    if config.workers < 0:
        raise ConfigError(f"mapping.workers: must be >= 0 (0: one per core), got {config.workers}")


def build_map(
    bag_path: str | Path, config: MappingConfig | None = None, progress: Progress | None = None
) -> MappingResult:
    """Map a bag: odometry, pose-graph fusion (IMU, GNSS), deskewed voxel-thinned map."""
    config = config or MappingConfig()
    _check_config(config)
    timing: dict[str, float] = {}
    cpu0, wall0 = cpu_seconds(), time.perf_counter()
    warm_up()  # before the workers fork: they inherit the loaded kernels
    one, rig, extrinsics, warnings, map_skipped = _odometry_pass(bag_path, config, progress)
    timing["odometry_cpu_s"] = cpu_seconds() - cpu0
    timing["odometry_wall_s"] = time.perf_counter() - wall0
    if not extrinsics:
        extrinsics, more = check_rig(one, rig, config)
        warnings += more
    fused, trajectory, frame, gnss_diag = _fuse_drive(one, rig, config, warnings, timing)

    cpu2, wall2 = cpu_seconds(), time.perf_counter()
    xyz, fields, offered = assemble_map(
        str(bag_path),
        one.topics.scans,
        {r.index: r.deskewed for r in one.records},
        trajectory,
        config,
        progress,
        None if one.recovered else one.scan_log_ns,
    )
    timing["map_cpu_s"] = cpu_seconds() - cpu2
    timing["map_wall_s"] = time.perf_counter() - wall2

    cloud = PointCloud(
        xyz,
        fields,
        crs=frame.crs if frame is not None else None,
        origin=frame.origin if frame is not None else np.zeros(3),
    )
    t_ref = np.array([r.t_ref for r in one.records])
    poses = trajectory.matrices(t_ref)  # the LiDAR's
    base_poses = poses @ rig.lidar_from_base
    timing["total_cpu_s"] = cpu_seconds() - cpu0
    timing["total_wall_s"] = time.perf_counter() - wall0
    diagnostics = {
        "bag": str(bag_path),
        **_drive_diagnostics(one, rig, extrinsics, frame, base_poses),
        "odometry_map_skipped": map_skipped,
        "map_points": len(cloud),
        "points_offered": offered,
        **_estimate_diagnostics(one, frame, fused, gnss_diag, timing),
    }
    return MappingResult(
        cloud,
        pose_table(t_ref, base_poses),
        frame,
        diagnostics,
        warnings,
        config_used(config, one.topics),
        rig,
        pose_table(t_ref, poses),
    )


def _odometry_pass(
    bag_path: str | Path, config: MappingConfig, progress: Progress | None
) -> tuple[OdometryPass, SensorRig, dict, list[str], dict]:
    """Pass 1 over the bag: the sensors' rig (calibrated when asked), the odometry front end,
    IMU and GNSS collected; returns the pass, the rig, the calibrated extrinsics (empty when
    not calibrated), the warnings so far and the ``odometry_map_skipped`` decision."""
    extrinsics: dict = {}
    with open_bag(bag_path, config.ouster_metadata or None) as bag:
        topics = topics_for(bag, config)
        rig = resolve_rig(bag, topics, config)
        rig_warnings = list(rig.warnings)
        view = None
        if config.odometry_map_skipped == "auto":
            try:
                view = ground_view(bag.path, topics, rig.lidar_from_base, config)
            except InputError:
                pass  # left off; the odometry reads the same scans and reports why, in its stage
        map_skipped = map_skipped_decision(config.odometry_map_skipped, view)
        config = dataclasses.replace(config, odometry_map_skipped=map_skipped["on"])
        if rig.calibrate:
            rig, extrinsics, more = calibrate_rig(bag, config, rig, progress)
            rig_warnings += more
        one = run_odometry(bag, config, progress, rig)
    registered = sum(1 for r in one.records if r.registered)
    require_sweeps(registered, f"{one.bag_path}: topic {one.topics.scans!r}")
    return one, rig, extrinsics, rig_warnings + pass_warnings(one, config), map_skipped


def _fuse_drive(
    one: OdometryPass,
    rig: SensorRig,
    config: MappingConfig,
    warnings: list[str],
    timing: dict[str, float],
) -> tuple[FusionResult, ContinuousTrajectory, LocalFrame | None, dict]:
    """The pose graph over the registered sweeps with the IMU and the GNSS epochs; returns the
    fused states, the continuous trajectory every sweep is deskewed with, the local frame
    (None: not georeferenced) and the GNSS diagnostics. Adds to ``warnings``, and the graph's
    CPU time (not the GNSS preparation's) to ``timing``."""
    registered = [r for r in one.records if r.registered]
    odo_times = np.array([r.t_ref for r in registered])
    odometry = np.array([r.pose for r in registered])
    antenna = (
        odometry[:, :3, 3] + odometry[:, :3, :3] @ rig.gnss_lever_arm
    )  # where the fixes are taken
    frame, epochs, gnss_diag = _gnss_inputs(
        one.gnss,
        config,
        warnings,
        one.topics.gnss or "",
        (odo_times, antenna),
        (one.first_stamp, one.last_stamp),
    )
    cpu1 = cpu_seconds()
    fused = fuse_trajectory(
        odo_times,
        odometry,
        fusion_settings(config, rig),
        imu=one.imu,
        standstill=one.state.standstill,
        gnss=epochs,
        uncertainty=np.array([r.uncertainty for r in registered]),
    )
    if epochs is not None and "initial_heading_deg" not in fused.diagnostics:
        why = fused.diagnostics.get("no_heading", "GNSS fixes do not overlap the LiDAR sweeps")
        warnings.append(f"{why}; the map is not georeferenced")
        frame = None
    trajectory = ContinuousTrajectory(
        fused.times, fused.poses, odo_times, odometry, one.state.rotations
    )
    timing["fusion_cpu_s"] = cpu_seconds() - cpu1
    return fused, trajectory, frame, gnss_diag


def _drive_diagnostics(
    one: OdometryPass,
    rig: SensorRig,
    extrinsics: dict,
    frame: LocalFrame | None,
    base_poses: np.ndarray,
) -> dict:
    """What was read and mapped: topics, inputs, sweeps, duration, path length and rig."""
    records = one.records
    return {
        "topics": {
            "pointcloud": one.topics.scans,
            "imu": one.topics.imu if one.imu is not None else None,
            "gnss": one.topics.gnss if frame is not None else None,
        },
        "inputs": input_summary(one),
        "scans": one.n_scans,
        "sweeps_mapped": len(records),
        "sweeps_registered": sum(1 for r in records if r.registered),
        "scans_skipped_sparse": len(one.state.skipped_sparse),
        "scans_without_point_time": one.n_without_time,
        "sweeps_deskewed": int(sum({r.index: r.deskewed for r in records}.values())),
        "duration_s": _duration(one),
        "path_length_m": float(
            np.sum(np.linalg.norm(np.diff(base_poses[:, :3, 3], axis=0), axis=1))
        ),
        "trajectory_frame": rig.base_name,
        "rig": rig.to_dict(),
        "extrinsics": extrinsics,
    }


def _duration(one: OdometryPass) -> float:
    """Seconds of drive the scans span (one sweep's worth after the last stamp)."""
    return float(one.last_stamp - one.first_stamp + 0.1) if one.n_scans else 0.0


def _estimate_diagnostics(
    one: OdometryPass,
    frame: LocalFrame | None,
    fused: FusionResult,
    gnss_diag: dict,
    timing: dict[str, float],
) -> dict:
    """How the estimate went: odometry corrections, quality flags, the pose graph, timing and
    real-time factors, then the IMU's and the GNSS's own findings."""
    st = one.state
    duration = _duration(one)
    out = {
        "up_source": st.up_source,
        "registrations_rejected": st.rejected_registrations,
        "ground_corrections": st.ground_corrections,
        "georeferenced": frame is not None,
        "quality_flags": quality_flags(one, frame, one.imu) + gnss_flags(gnss_diag),
        "odometry_workers": one.workers,
        "fusion": fused.diagnostics,
        "timing": timing,
        "real_time_factor": duration / timing["total_wall_s"]
        if timing["total_wall_s"] > 0
        else None,
        "real_time_factor_cpu": duration / timing["total_cpu_s"]
        if timing["total_cpu_s"] > 0
        else None,
    }
    if st.standstill is not None:
        out["imu"] = {
            "standstill_s": st.standstill.duration,
            "standstill_found": st.standstill.found,
            "gyro_bias_start": st.standstill.gyro_bias.tolist(),
        }
        if fused.accel_bias is not None:
            out["imu"]["accel_bias_end"] = fused.accel_bias[-1].tolist()
            out["imu"]["gyro_bias_end"] = fused.gyro_bias[-1].tolist()
    if gnss_diag:
        gnss_diag["mode_changes"] = int(fused.diagnostics.get("gnss_mode_changes", 0))
        if fused.gnss_bias is not None:
            gnss_diag["bias_rms_m"] = float(np.sqrt(np.nanmean(np.sum(fused.gnss_bias**2, axis=1))))
        out["gnss"] = gnss_diag
    return out


def gnss_flags(gnss_diag: dict) -> list[str]:
    """``gnss_fixes_dropped`` when fixes carried non-finite or impossible positions."""
    rejected = gnss_diag.get("rejected", {})
    return (
        ["gnss_fixes_dropped"]
        if rejected.get("non_finite", 0) + rejected.get("out_of_range", 0)
        else []
    )


def config_used(config: MappingConfig, topics: SensorTopics) -> MappingConfig:
    """``config`` with the topics actually read filled in (written next to the results, so a
    run with that config reads the same topics even when the bag offers several)."""
    from dataclasses import replace

    return replace(
        config,
        pointcloud_topic=topics.scans,
        imu_topic=topics.imu or config.imu_topic,
        gnss_topic=topics.gnss or config.gnss_topic,
    )


def input_summary(one: OdometryPass) -> dict:
    """Per role (pointcloud, imu, gnss): the topic read, its frame, messages used and dropped,
    and the time span of the used ones (``mapping.json`` → ``diagnostics.inputs``)."""
    if one.log is None:
        return {}
    return one.log.summary(
        {"pointcloud": one.topics.scans, "imu": one.topics.imu, "gnss": one.topics.gnss}
    )


def _gnss_inputs(
    buffer: GnssBuffer | None,
    config: MappingConfig,
    warnings: list[str],
    topic: str = "",
    odometry: tuple[np.ndarray, np.ndarray] | None = None,
    span: tuple[float, float] | None = None,
) -> tuple[LocalFrame | None, GnssEpochs | None, dict]:
    """The local frame, the epochs for the graph and the GNSS diagnostics of a drive.

    ``odometry`` (times, positions) lets the fixes it contradicts be rejected as jumps;
    ``span`` (first and last sweep) places the outages in time.
    """
    if buffer is None or len(buffer) == 0:
        return None, None, {}
    series = buffer.series()
    reasons = rejection_reasons(series)
    try:
        frame = local_frame_for(series)
        if odometry is not None:
            reasons[_jumps(series, frame, reasons == "", odometry, config)] = "jump"
        epochs = gnss_epochs(
            series,
            frame,
            config.gnss_epoch,
            config.gnss_default_sigma_horizontal,
            config.gnss_default_sigma_vertical,
            exclude=reasons == "jump",
        )
    except InputError as exc:
        warnings.append(f"GNSS topic {topic!r} not used: {exc}")
        return None, None, {}
    diag = fix_report(series, reasons, span)
    diag.update(
        {
            "fixes": epochs.n_fixes,
            "epochs": len(epochs.t),
            "superseded": epochs.n_superseded,
            "sigma_horizontal_median_m": float(np.median(epochs.sigma[:, 0])),
            "crs": frame.crs,
        }
    )
    warnings += [
        line
        for line in (report_warning(topic, diag), invalid_fix_warning(topic, series, reasons))
        if line
    ]
    return frame, epochs, diag


def _jumps(
    series: GnssSeries,
    frame: LocalFrame,
    usable: np.ndarray,
    odometry: tuple[np.ndarray, np.ndarray],
    config: MappingConfig,
) -> np.ndarray:
    """Usable fixes the odometry contradicts (see :func:`odometry_outliers`)."""
    out = np.zeros(len(series.t), bool)
    idx = np.flatnonzero(usable)
    if len(idx) < 3:
        return out
    xyz = frame.to_local(series.latitude[idx], series.longitude[idx], series.altitude[idx])
    sigma = reported_sigmas(
        series, config.gnss_default_sigma_horizontal, config.gnss_default_sigma_vertical
    )[idx]
    out[idx] = odometry_outliers(
        series.t[idx],
        xyz,
        sigma,
        series.status[idx],
        odometry[0],
        odometry[1],
        config.gnss_correlation_time,
        config.gnss_white_fraction,
        config.odometry_jitter_translation,
    )
    return out


def stream_map(
    bag_path: str | Path, config: MappingConfig | None = None, progress: Progress | None = None
) -> Iterator[RegisteredScan]:
    """Yield each sweep registered in the map frame as the drive is processed (causal).

    With GNSS the map frame is the odometry frame placed in the local UTM frame of
    :func:`build_map` by a yaw + translation fit to the fixes of the first ``15 m`` (sweeps
    are held back until then), and it stays so: the streamed map is as consistent as the
    odometry, while its placement on the globe is as good as that first fit. Later fits
    (whenever the drive's extent or duration has doubled) come with each sweep as
    ``georeference_update`` (map frame -> local UTM frame) for placing finished results.
    Without GNSS the frame is the gravity-aligned first sweep. :func:`build_map` smooths
    the whole drive and so places points more accurately.
    """
    config = config or MappingConfig()
    _check_config(config)
    with open_bag(bag_path, config.ouster_metadata or None) as bag:
        one = PassOne(bag, config, progress, keep_all_points=True)
        georef = _RunningGeoreference(config) if one.gnss is not None else None
        pending: list[FrontendSweep] = []
        far = map_range(config)
        for sweep in one.sweeps():
            if georef is None:
                yield _registered(sweep, np.eye(4), False, far)
                continue
            georef.update(one.gnss, sweep)  # type: ignore[arg-type]
            pending.append(sweep)
            if georef.frame_alignment is not None:
                update = georef.alignment @ np.linalg.inv(georef.frame_alignment)  # type: ignore[operator]
                for held in pending:
                    yield _registered(held, georef.frame_alignment, True, far, update)
                pending = []
        for held in pending:  # never georeferenced (too short a drive or no valid fixes)
            yield _registered(held, np.eye(4), False, far)


class _RunningGeoreference:
    """Causal odometry-to-GNSS alignment (yaw + horizontal shift), refitted rarely.

    The first fit comes once the drive spans ``MIN_BASELINE`` metres; it is refitted (to
    every fix so far) only when that span or the time driven has grown by ``REFIT_GROWTH``,
    so the streamed map frame stays put between refits and each refit (averaging more of
    the receiver's slow wander) moves it less than the one before.
    Height is fixed at the first fit: a standalone receiver's height wanders by a metre,
    and refitting it every second moved whole sweeps up and down (blurred crowns).
    ``frame_alignment`` is the first fit and stays fixed: it places the streamed map, so
    the map is as consistent as the odometry (measured: a refit moved the frame by 1.8 m
    after the first 15 m baseline). ``alignment`` is the latest fit.
    """

    MIN_BASELINE = 15.0
    REFIT_GROWTH = 2.0

    def __init__(self, config: MappingConfig) -> None:
        self.config = config
        self.frame: LocalFrame | None = None
        self.alignment: np.ndarray | None = None
        self.frame_alignment: np.ndarray | None = None
        self._t: list[float] = []
        self._odo: list[np.ndarray] = []
        self._last_try = -np.inf
        self._fitted_span = 0.0
        self._fitted_time = 0.0

    def update(self, buffer: GnssBuffer, sweep: FrontendSweep) -> None:
        self._t.append(sweep.t_ref)
        self._odo.append(sweep.pose[:3, 3].copy())
        if len(buffer) == 0 or sweep.t_ref - self._last_try < 1.0:
            return
        self._last_try = sweep.t_ref
        odo = np.array(self._odo)
        span = float(np.ptp(odo[:, :2], axis=0).max())
        elapsed = sweep.t_ref - self._t[0]
        if self.alignment is None:
            if span < self.MIN_BASELINE:
                return
        elif (
            span < self.REFIT_GROWTH * self._fitted_span
            and elapsed < self.REFIT_GROWTH * self._fitted_time
        ):
            return
        series = buffer.series()
        try:
            if self.frame is None:
                self.frame = local_frame_for(series)
            epochs = gnss_epochs(series, self.frame, self.config.gnss_epoch)
        except InputError:
            return
        t = np.array(self._t)
        inside = (epochs.t >= t[0]) & (epochs.t <= t[-1])
        if inside.sum() < 3:
            return
        p_odo = np.column_stack([np.interp(epochs.t[inside], t, odo[:, k]) for k in range(3)])
        if np.ptp(p_odo[:, :2], axis=0).max() < self.MIN_BASELINE:
            return
        yaw, shift = heading_alignment(p_odo, epochs.xyz[inside])
        a = np.eye(4)
        a[:3, :3] = np.array(
            [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        )
        a[:3, 3] = shift
        if self.alignment is not None:
            a[2, 3] = self.alignment[2, 3]
        self.alignment = a
        if self.frame_alignment is None:
            self.frame_alignment = a.copy()
        self._fitted_span, self._fitted_time = span, elapsed


def _registered(
    sweep: FrontendSweep,
    alignment: np.ndarray,
    georeferenced: bool,
    max_range: float,
    update: np.ndarray | None = None,
) -> RegisteredScan:
    pose = alignment @ sweep.pose
    scan = sweep.scan
    xyz, kept, ground = map_points(sweep, max_range)
    world = xyz @ pose[:3, :3].T + pose[:3, 3]
    fields = point_fields(scan.fields, kept, scan.times, scan.stamp, len(world))
    return RegisteredScan(
        scan.index,
        scan.stamp,
        sweep.t_ref,
        pose,
        PointCloud(world, fields),
        ground,
        georeferenced,
        np.eye(4) if update is None else update,
    )


__all__ = [
    "TIME_FIELD",
    "MappingResult",
    "RegisteredScan",
    "build_map",
    "fusion_settings",
    "stream_map",
]
