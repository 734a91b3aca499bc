"""The IMU mount checked against the drive, or estimated from it (``mapping.extrinsics``).

:func:`check_rig` compares the mount the odometry ran with (``/tf_static``, the rig file)
with what the drive says (:mod:`.handeye`) and warns past ``mapping.extrinsic_tolerance_deg``.
:func:`calibrate_rig` runs a LiDAR-only odometry pass (the IMU collected but unused),
estimates the mount from it and returns the rig to map with.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.core.frames import rotation_angle_deg, rpy_deg
from canopy_kit.errors import InputError
from canopy_kit.mapping.extrinsics import ESTIMATED, SensorRig
from canopy_kit.mapping.handeye import RotationEstimate, estimate_imu_rotation
from canopy_kit.mapping.imu import detect_standstill
from canopy_kit.mapping.passone import OdometryPass

Progress = Callable[[str, float, float], None]
MAX_CLOCK_OFFSET_S = 0.1  # searched when calibrating


def _registered(one: OdometryPass) -> tuple[np.ndarray, np.ndarray]:
    recs = [r for r in one.records if r.registered]
    return np.array([r.t_ref for r in recs]), np.array([r.pose for r in recs]).reshape(-1, 4, 4)


def _tilt(
    rig: SensorRig, one: OdometryPass, lidar_from_imu: np.ndarray | None = None
) -> dict[str, float]:
    """The LiDAR's tilt from the vertical: by the IMU's gravity at standstill, and by the rig's base."""
    out: dict[str, float] = {}
    still = one.state.standstill
    if still is None and one.imu is not None:  # a LiDAR-only pass: the IMU was only collected
        still = detect_standstill(one.imu)
    if still is not None and np.linalg.norm(still.gravity_body) > 0:
        up = still.gravity_body / np.linalg.norm(still.gravity_body)
        if lidar_from_imu is not None:  # the standstill was measured in the IMU's own axes
            up = lidar_from_imu[:3, :3] @ up
        out["lidar_tilt_from_gravity_deg"] = float(np.degrees(np.arccos(np.clip(up[2], -1, 1))))
    base_up = rig.lidar_from_base[:3, 2]
    out["lidar_tilt_from_base_deg"] = float(np.degrees(np.arccos(np.clip(base_up[2], -1, 1))))
    return out


def check_rig(
    one: OdometryPass, rig: SensorRig, config: MappingConfig
) -> tuple[dict[str, Any], list[str]]:
    """How far the drive puts the IMU from where the rig says; a warning past the tolerance."""
    diag: dict[str, Any] = {
        "mode": config.extrinsics,
        "tolerance_deg": config.extrinsic_tolerance_deg,
    }
    if one.imu is None or rig.imu_frame is None:
        return diag, []
    times, poses = _registered(one)
    est = estimate_imu_rotation(times, poses, one.imu) if len(times) else None
    diag.update(_tilt(rig, one))
    if est is None:
        diag["check"] = "too few rotation increments to check the IMU mount"
        return diag, []
    # ``one.imu`` is already in the LiDAR frame: the estimate is the residual rotation.
    estimated = est.rotation @ rig.lidar_from_imu[:3, :3]
    angle = rotation_angle_deg(est.rotation)
    diag["given_rpy_deg"] = [round(v, 3) for v in rpy_deg(rig.lidar_from_imu)]
    diag["estimated"] = dict(est.to_dict(), rpy_deg=[round(v, 3) for v in rpy_deg(estimated)])
    diag["difference_deg"] = round(angle, 3)
    warnings = []
    if angle > config.extrinsic_tolerance_deg:
        warnings.append(
            f"extrinsics: the drive puts the IMU (frame {rig.imu_frame!r}) {angle:.1f} deg from where "
            f"{rig.sources.get('imu', 'the rig')} puts it in the LiDAR frame {rig.lidar_frame!r} "
            f"(roll/pitch/yaw given {_rpy(rig.lidar_from_imu)}, estimated {_rpy(estimated)} deg); "
            "check /tf_static or the rig file, or map with --calibrate-extrinsics"
        )
    return diag, warnings


def _rpy(m: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.1f}" for v in rpy_deg(m)) + "]"


def calibrate_rig(
    bag: Any, config: MappingConfig, rig: SensorRig, progress: Progress | None = None
) -> tuple[SensorRig, dict[str, Any], list[str]]:
    """The rig with the IMU rotation (and clock offset) estimated from a LiDAR-only pass."""
    from canopy_kit.mapping.chunks import run_odometry

    if rig.imu_frame is None:
        return rig, {"mode": "calibrate", "check": "no IMU: nothing to calibrate"}, []

    def relabel(_: str, n: float, total: float) -> None:
        if progress:
            progress("mapping: extrinsics (LiDAR-only odometry)", n, total)

    probe = run_odometry(bag, config, relabel, rig, lidar_only=True)
    times, poses = _registered(probe)
    if probe.imu is None:
        raise InputError(
            f"{bag.path}: topic {probe.topics.imu!r}: too few IMU samples to calibrate "
            "the IMU mount (--calibrate-extrinsics)"
        )
    est = estimate_imu_rotation(times, poses, probe.imu, MAX_CLOCK_OFFSET_S) if len(times) else None
    if est is None:
        raise InputError(
            f"{bag.path}: the drive has too few LiDAR rotation increments overlapping the IMU "
            "to estimate the IMU mount (--calibrate-extrinsics); give it with --rig FILE"
        )
    diag = _calibration_diagnostics(rig, est, probe)
    warnings = []
    if not est.observable:
        axes = ", ".join(f"{n} {s:.2f}" for n, s in zip("xyz", est.sigma_deg))
        warnings.append(
            f"extrinsics: the drive turned too little about some axes to fix the IMU mount well "
            f"(1-sigma per LiDAR axis: {axes} deg); prefer a measured rig (--rig FILE)"
        )
    offset = rig.imu_time_offset + est.time_offset_s
    return rig.with_imu_rotation(est.rotation, ESTIMATED, offset), diag, warnings


def _calibration_diagnostics(
    rig: SensorRig, est: RotationEstimate, probe: OdometryPass
) -> dict[str, Any]:
    diag: dict[str, Any] = {"mode": "calibrate", "estimated": est.to_dict()}
    diag.update(_tilt(rig, probe, est.rotation))
    if rig.sources.get("imu") not in (ESTIMATED, None):  # the bag or rig file gave one too
        diag["given_rpy_deg"] = [round(v, 3) for v in rpy_deg(rig.lidar_from_imu)]
        diag["difference_deg"] = round(rotation_angle_deg(est.rotation, rig.lidar_from_imu), 3)
    return diag
