"""Where the simulated sensors sit on the vehicle, and what the bag's ``/tf_static`` says of it.

The vehicle frame (the rig's ``base_frame``, REP 105's ``base_link``) has its origin on
the ground midway between the wheels and turns with the vehicle's roll and pitch. A rig
(``[rig] name``: a preset of ``canopy_kit/presets/rigs`` or a rig file, the format of
:mod:`canopy_kit.config.rig`) places the LiDAR, the IMU and the GNSS antenna on it. The default
``identity`` is the simulator's first rig: every sensor in the LiDAR's frame at
``lidar.mount_height`` (pitched ``lidar.mount_pitch_deg``) and no ``/tf_static``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from canopy_kit.config.rig import parse_rig, rig_data
from canopy_kit.core.frames import FrameGraph, FrameTransform, from_rpy, rigid
from canopy_kit.errors import ConfigError

IDENTITY = "identity"


@dataclass
class SensorMounts:
    """The sensors' poses on the vehicle and the transforms the bag records."""

    base_from_lidar: np.ndarray
    base_from_imu: np.ndarray
    base_from_antenna: np.ndarray
    base_frame: str
    lidar_frame: str
    imu_frame: str
    gnss_frame: str
    tf_static: list[FrameTransform] = field(default_factory=list)  # empty: no /tf_static written
    imu_time_offset: float = 0.0  # s: the IMU's stamps run this far ahead of the true time

    @property
    def identity(self) -> bool:
        """True when every sensor shares the LiDAR's frame."""
        return self.lidar_frame == self.imu_frame == self.gnss_frame

    def to_dict(self) -> dict:
        """For truth/frame.json."""

        def pose(m: np.ndarray) -> dict:
            return {
                "translation": m[:3, 3].round(6).tolist(),
                "rpy_deg": Rotation.from_matrix(m[:3, :3])
                .as_euler("xyz", degrees=True)
                .round(6)
                .tolist(),
            }

        return {
            "base_frame": self.base_frame,
            "lidar_frame": self.lidar_frame,
            "imu_frame": self.imu_frame,
            "gnss_frame": self.gnss_frame,
            "base_from_lidar": pose(self.base_from_lidar),
            "base_from_imu": pose(self.base_from_imu),
            "base_from_antenna": pose(self.base_from_antenna),
            "tf_static_written": bool(self.tf_static),
            "imu_time_offset_s": self.imu_time_offset,
        }


def legacy_lidar_mount(mount_height: float, mount_pitch_deg: float) -> np.ndarray:
    """The identity rig's LiDAR: ``mount_height`` above the ground point, pitched about y."""
    return rigid(Rotation.from_euler("y", mount_pitch_deg, degrees=True), [0.0, 0.0, mount_height])


def sensor_mounts(config) -> SensorMounts:
    """The :class:`SensorMounts` a simulator config asks for."""
    spec = config.rig
    if spec.name == IDENTITY:
        lidar = legacy_lidar_mount(config.lidar.mount_height, config.lidar.mount_pitch_deg)
        frame = config.lidar.frame_id
        return SensorMounts(
            lidar,
            lidar.copy(),
            lidar.copy(),
            "base_link",
            frame,
            frame,
            frame,
            imu_time_offset=spec.imu_time_offset,
        )
    data, where = rig_data(spec.name)
    rig = parse_rig(data, where)
    for key in ("lidar_frame", "imu_frame", "gnss_frame"):
        if not getattr(rig, key):
            raise ConfigError(f"{where}: a simulator rig must name rig.{key}")
    graph = FrameGraph(rig.transforms)

    def mount(frame: str) -> np.ndarray:
        out = graph.try_transform(rig.base_frame, frame)
        if out is None:
            raise ConfigError(
                f"{where}: frame {frame!r} is not connected to the base frame {rig.base_frame!r}"
            )
        return out

    mounts = SensorMounts(
        mount(rig.lidar_frame),
        mount(rig.imu_frame),
        mount(rig.gnss_frame),
        rig.base_frame,
        rig.lidar_frame,
        rig.imu_frame,
        rig.gnss_frame,
        imu_time_offset=spec.imu_time_offset,
    )
    if spec.write_tf_static:
        mounts.tf_static = _recorded(rig.transforms, rig.imu_frame, spec.tf_imu_error_rpy_deg)
    return mounts


def _recorded(
    transforms: list[FrameTransform], imu_frame: str, error_rpy_deg: list[float]
) -> list[FrameTransform]:
    """The rig's transforms as /tf_static records them, the IMU's turned by ``error_rpy_deg``."""
    out = []
    for t in transforms:
        matrix = t.matrix
        if t.child == imu_frame and any(error_rpy_deg):
            matrix = matrix @ from_rpy([0.0, 0.0, 0.0], error_rpy_deg)
        out.append(FrameTransform(t.parent, t.child, matrix, "tf_static"))
    return out
