"""Which frame each sensor of a bag stamps, and how those frames sit on the robot.

:func:`resolve_rig` reads the frame ids the LiDAR, IMU and GNSS messages carry, the
bag's ``/tf_static`` (and the static part of ``/tf``), and the rig file of the config
(which overrides the bag, frame by frame), and returns a :class:`SensorRig`: the IMU and
the antenna in the LiDAR frame (the frame the odometry runs in) and the base frame the
trajectory is reported in. When the LiDAR and the IMU stamp different frames that
nothing relates, it stops with an :class:`~canopy_kit.errors.InputError` naming both,
unless the config says to assume one frame or to estimate the rotation from the drive.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.config.rig import RigSpec, parse_rig, rig_tables
from canopy_kit.core.frames import FrameGraph, FrameTransform, invert, rigid, rpy_deg
from canopy_kit.errors import InputError
from canopy_kit.io.tf import first_frame_id, read_transforms
from canopy_kit.mapping.imu_mounting import ImuMounting

DEFAULT_BASE_FRAME = "base_link"
SAME_FRAME = "same frame"
ASSUMED = "assumed identity (--assume-identity-extrinsics)"
ESTIMATED = "estimated from the drive"
LEVER_ARM_SETTING = "mapping.gnss_lever_arm"


@dataclass
class SensorRig:
    """The sensors of one bag in the LiDAR frame, where each transform came from."""

    lidar_frame: str
    imu_frame: str | None = None
    gnss_frame: str | None = None
    base_frame: str = ""
    lidar_from_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    lidar_from_gnss: np.ndarray = field(default_factory=lambda: np.eye(4))
    lidar_from_base: np.ndarray = field(default_factory=lambda: np.eye(4))
    sources: dict[str, str] = field(default_factory=dict)  # "imu", "gnss", "base" -> where from
    imu_time_offset: float = 0.0
    calibrate: bool = False  # the IMU rotation is to be estimated from the drive
    transforms: list[FrameTransform] = field(default_factory=list)  # every mount known
    tf_topics: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def base_name(self) -> str:
        """The frame the trajectory is reported in."""
        return self.base_frame or self.lidar_frame

    @property
    def gnss_lever_arm(self) -> np.ndarray:
        """The antenna's position in the LiDAR frame (m)."""
        return self.lidar_from_gnss[:3, 3].copy()

    def imu_mounting(self) -> ImuMounting | None:
        """How to move IMU samples into the LiDAR frame (None: nothing to do).

        While the mount is still to be estimated (``calibrate``) the samples stay in the IMU's
        axes; only the clock offset, if one is known, is applied."""
        if self.imu_frame is None:
            return None
        if self.calibrate:
            m = ImuMounting(np.eye(3), np.zeros(3), self.imu_time_offset)
        else:
            m = ImuMounting(
                self.lidar_from_imu[:3, :3].copy(),
                self.lidar_from_imu[:3, 3].copy(),
                self.imu_time_offset,
            )
        return None if m.is_identity else m

    def with_imu_rotation(
        self, rotation: np.ndarray, source: str = ESTIMATED, time_offset: float | None = None
    ) -> SensorRig:
        """The same rig with the IMU turned by ``rotation`` (lidar_from_imu, 3x3)."""
        t = self.lidar_from_imu.copy()
        t[:3, :3] = rotation
        sources = dict(self.sources, imu=source)
        offset = self.imu_time_offset if time_offset is None else time_offset
        return replace(
            self, lidar_from_imu=t, sources=sources, calibrate=False, imu_time_offset=offset
        )

    def to_dict(self) -> dict[str, Any]:
        """Frames, the IMU/antenna/base transforms and their sources (mapping.json, report)."""

        def pose(m: np.ndarray) -> dict[str, list[float]]:
            return {
                "translation": [round(float(v), 4) for v in m[:3, 3]],
                "rpy_deg": [round(v, 3) for v in rpy_deg(m)],
            }

        out: dict[str, Any] = {
            "lidar_frame": self.lidar_frame,
            "imu_frame": self.imu_frame,
            "gnss_frame": self.gnss_frame,
            "base_frame": self.base_name,
            "tf_topics": self.tf_topics,
            "sources": dict(self.sources),
        }
        if self.imu_frame is not None:
            out["lidar_from_imu"] = pose(self.lidar_from_imu)
            out["imu_time_offset_s"] = self.imu_time_offset
        if self.gnss_frame is not None:
            out["gnss_lever_arm_m"] = [round(float(v), 4) for v in self.gnss_lever_arm]
        out["lidar_from_base"] = pose(self.lidar_from_base)
        # The mounts on the vehicle, as a rig file gives them.
        base_from_lidar = invert(self.lidar_from_base)
        out["mounts_in_base"] = {"lidar": pose(base_from_lidar)}
        if self.imu_frame is not None:
            out["mounts_in_base"]["imu"] = pose(base_from_lidar @ self.lidar_from_imu)
        if self.gnss_frame is not None:
            out["mounts_in_base"]["gnss"] = pose(base_from_lidar @ self.lidar_from_gnss)
        out["transforms"] = [t.to_dict() for t in self.transforms]
        return out

    def rig_file_tables(self) -> dict[str, Any]:
        """The rig as a rig file (rig.toml next to the results): every mount, sensors in the base frame."""
        graph = FrameGraph(self.transforms)
        base = self.base_name
        edges = list(self.transforms)
        # Mounts the run knows only relative to the LiDAR (estimated, assumed, the lever-arm setting).
        base_from_lidar = invert(self.lidar_from_base)
        for key, frame, lidar_from in (
            ("imu", self.imu_frame, self.lidar_from_imu),
            ("gnss", self.gnss_frame, self.lidar_from_gnss),
        ):
            if (
                frame
                and frame != self.lidar_frame
                and (
                    graph.try_transform(self.lidar_frame, frame) is None
                    or self.sources.get(key) in (ESTIMATED, ASSUMED)
                )
            ):
                edges = [e for e in edges if e.child != frame]
                parent = base if base != frame else self.lidar_frame
                matrix = base_from_lidar @ lidar_from if parent == base else lidar_from
                edges.append(FrameTransform(parent, frame, matrix, self.sources.get(key, "")))
        names = {
            "lidar_frame": self.lidar_frame,
            "imu_frame": self.imu_frame or "",
            "gnss_frame": self.gnss_frame or "",
            "imu_time_offset_s": self.imu_time_offset or None,
        }
        return rig_tables(base, edges, **names)  # type: ignore[arg-type]


def _config_rig(config: MappingConfig) -> RigSpec | None:
    if not config.rig:
        return None
    return parse_rig(config.rig, config.rig_name or "mapping.rig")


def _sensor_frame(rig: RigSpec | None, key: str, stamped: str | None) -> str | None:
    """The frame a sensor's data are in: the rig file's name for it, else what its messages stamp."""
    named = getattr(rig, key) if rig is not None else ""
    return named or stamped


def resolve_rig(bag: Any, topics: Any, config: MappingConfig) -> SensorRig:
    """The :class:`SensorRig` of a bag (``BagSession``) and its sensor ``topics``."""
    rig_file = _config_rig(config)
    recorded = read_transforms(bag)
    graph = FrameGraph(recorded.transforms)
    for t in rig_file.transforms if rig_file is not None else []:
        graph.add(t)  # the rig file wins over the bag, frame by frame
    warnings = list(recorded.notes)
    lidar = _sensor_frame(rig_file, "lidar_frame", first_frame_id(bag, topics.scans))
    if not lidar:
        lidar = "lidar"
        warnings.append(
            f"{bag.path}: topic {topics.scans!r}: the scans stamp no frame_id; "
            "taken as the frame 'lidar'"
        )
    imu = (
        _sensor_frame(rig_file, "imu_frame", first_frame_id(bag, topics.imu))
        if topics.imu
        else None
    )
    gnss = (
        _sensor_frame(rig_file, "gnss_frame", first_frame_id(bag, topics.gnss))
        if topics.gnss
        else None
    )
    out = SensorRig(
        lidar,
        imu,
        gnss,
        tf_topics=recorded.topics,
        warnings=warnings,
        imu_time_offset=rig_file.imu_time_offset_s if rig_file is not None else 0.0,
    )
    out.base_frame = _base_frame(config, rig_file, graph, lidar)
    out.lidar_from_base = (
        graph.try_transform(lidar, out.base_frame) if out.base_frame != lidar else np.eye(4)
    )
    if out.lidar_from_base is None:
        raise InputError(
            f"{bag.path}: base frame {out.base_frame!r} (mapping.base_frame) is not connected "
            f"to the LiDAR's frame {lidar!r} by /tf_static or the rig "
            f"(frames known: {', '.join(sorted(graph.frames)) or 'none'})"
        )
    out.sources["base"] = _source(graph, lidar, out.base_frame)
    if imu is not None:
        _resolve_imu(out, graph, config, bag, topics)
    if gnss is not None:
        _resolve_gnss(out, graph, config, bag, topics)
    out.transforms = graph.edges
    return out


def _base_frame(
    config: MappingConfig, rig_file: RigSpec | None, graph: FrameGraph, lidar: str
) -> str:
    if config.base_frame:
        return config.base_frame
    if rig_file is not None and rig_file.base_frame in graph.frames:
        return rig_file.base_frame
    if (
        DEFAULT_BASE_FRAME in graph.frames
        and graph.try_transform(lidar, DEFAULT_BASE_FRAME) is not None
    ):
        return DEFAULT_BASE_FRAME
    return lidar


def _source(graph: FrameGraph, target: str, source: str) -> str:
    return " + ".join(graph.sources(target, source)) or SAME_FRAME


def _resolve_imu(
    out: SensorRig, graph: FrameGraph, config: MappingConfig, bag: Any, topics: Any
) -> None:
    imu = out.imu_frame
    assert imu is not None
    if not imu or imu == out.lidar_frame:
        out.imu_frame = out.lidar_frame
        out.sources["imu"] = SAME_FRAME
        if config.extrinsics == "calibrate":
            out.calibrate = True
        return
    known = graph.try_transform(out.lidar_frame, imu)
    if known is not None:
        out.lidar_from_imu = known
        out.sources["imu"] = _source(graph, out.lidar_frame, imu)
        out.calibrate = config.extrinsics == "calibrate"
        return
    if config.extrinsics == "calibrate":
        out.calibrate = True
        out.sources["imu"] = ESTIMATED
        return
    if config.extrinsics == "identity":
        out.sources["imu"] = ASSUMED
        out.warnings.append(
            f"the LiDAR's frame {out.lidar_frame!r} and the IMU's frame {imu!r} differ and "
            "nothing relates them; mapped as if they were one frame (as asked)"
        )
        return
    raise InputError(
        f"{bag.path}: the LiDAR (topic {topics.scans!r}, frame {out.lidar_frame!r}) and the IMU (topic "
        f"{topics.imu!r}, frame {imu!r}) stamp different frames, and neither the bag's /tf_static "
        f"{'nor ' + repr(config.rig_name or 'the rig') if config.rig else 'nor a rig file'} relates them. "
        "Give the mounting with --rig FILE (docs/MAPPING.md, 'Sensor rigs'), estimate the rotation from the "
        "drive with --calibrate-extrinsics, or, if the two frames really are one, --assume-identity-extrinsics"
    )


def _resolve_gnss(
    out: SensorRig, graph: FrameGraph, config: MappingConfig, bag: Any, topics: Any
) -> None:
    gnss = out.gnss_frame
    assert gnss is not None
    setting = rigid(translation=[float(v) for v in config.gnss_lever_arm])
    if not gnss or gnss == out.lidar_frame:
        out.gnss_frame = out.lidar_frame
        out.lidar_from_gnss = setting
        out.sources["gnss"] = LEVER_ARM_SETTING if np.any(setting[:3, 3]) else SAME_FRAME
        return
    known = graph.try_transform(out.lidar_frame, gnss)
    if known is not None:
        out.lidar_from_gnss = known
        out.sources["gnss"] = _source(graph, out.lidar_frame, gnss)
        return
    out.lidar_from_gnss = setting
    out.sources["gnss"] = LEVER_ARM_SETTING
    out.warnings.append(
        f"{bag.path}: topic {topics.gnss!r}: no transform from the GNSS frame {gnss!r} to "
        f"the LiDAR's {out.lidar_frame!r}; the antenna lever arm is {LEVER_ARM_SETTING} "
        f"= {[float(v) for v in config.gnss_lever_arm]} m (give the antenna in a rig file)"
    )
