"""Rig files: where a robot's sensors sit, for bags whose ``/tf_static`` is missing or wrong.

A rig file is TOML::

    [rig]
    base_frame = "base_link"      # the vehicle frame the trajectory is reported in
    lidar_frame = "velodyne"      # optional: the frames the sensors stamp, when a driver
    imu_frame = "imu_link"        #   leaves frame_id empty or it is to be overridden
    gnss_frame = "gps"
    imu_time_offset_s = 0.0       # optional: IMU clock minus LiDAR clock

    [frames.velodyne]             # one table per frame: its pose in its parent
    parent = "base_link"          # default: base_frame
    translation = [0.3, 0.0, 1.9] # metres
    rpy_deg = [0.0, 12.0, 180.0]  # roll, pitch, yaw (ROS fixed axes), or
    # quaternion = [x, y, z, w]

The same format describes the simulator's rigs (``canopy_kit/presets/rigs/``) and the rig a
mapping run used (written next to its results as ``rig.toml``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.core.frames import FrameTransform, from_quaternion, from_rpy, rpy_deg
from canopy_kit.errors import ConfigError

RIG_KEYS = {"base_frame", "lidar_frame", "imu_frame", "gnss_frame", "imu_time_offset_s"}
FRAME_KEYS = {"parent", "translation", "rpy_deg", "quaternion"}
RIG_FILE_SOURCE = "rig file"


@dataclass
class RigSpec:
    """A rig file's content: frame names and the transforms it gives."""

    base_frame: str = "base_link"
    lidar_frame: str = ""
    imu_frame: str = ""
    gnss_frame: str = ""
    imu_time_offset_s: float = 0.0
    transforms: list[FrameTransform] = field(default_factory=list)
    where: str = "rig"

    def frame(self, name: str) -> FrameTransform | None:
        """The transform whose child is ``name``, if the rig gives one."""
        return next((t for t in self.transforms if t.child == name), None)


def _vector(value: Any, n: int, where: str) -> list[float]:
    if not isinstance(value, list | tuple) or len(value) != n:
        raise ConfigError(f"{where}: expected a list of {n} numbers, got {value!r}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            raise ConfigError(f"{where}: expected a list of {n} finite numbers, got {value!r}")
        out.append(float(v))
    return out


def _string(value: Any, where: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"{where}: expected a frame name (string), got {value!r}")
    return value


def parse_rig(data: Mapping[str, Any], where: str = "rig") -> RigSpec:
    """A :class:`RigSpec` from a rig file's tables; errors name ``where`` and the key."""
    unknown = sorted(set(data) - {"rig", "frames"})
    if unknown:
        raise ConfigError(
            f"{where}: unknown table {unknown[0]!r} (a rig file has [rig] and [frames.NAME])"
        )
    head = data.get("rig", {})
    if not isinstance(head, Mapping):
        raise ConfigError(f"{where}: [rig] must be a table")
    bad = sorted(set(head) - RIG_KEYS)
    if bad:
        raise ConfigError(
            f"{where}: rig.{bad[0]} is not a rig setting (known: {', '.join(sorted(RIG_KEYS))})"
        )
    spec = RigSpec(where=where)
    for key in ("base_frame", "lidar_frame", "imu_frame", "gnss_frame"):
        if key in head:
            setattr(spec, key, _string(head[key], f"{where}: rig.{key}"))
    if not spec.base_frame:
        raise ConfigError(f"{where}: rig.base_frame must not be empty")
    if "imu_time_offset_s" in head:
        offset = head["imu_time_offset_s"]
        if isinstance(offset, bool) or not isinstance(offset, int | float) or not abs(offset) < 10:
            raise ConfigError(
                f"{where}: rig.imu_time_offset_s: expected seconds (|offset| < 10), got {offset!r}"
            )
        spec.imu_time_offset_s = float(offset)
    frames = data.get("frames", {})
    if not isinstance(frames, Mapping):
        raise ConfigError(f"{where}: [frames] must hold one table per frame ([frames.NAME])")
    for name, table in frames.items():
        spec.transforms.append(_frame(str(name), table, spec.base_frame, f"{where}: frames.{name}"))
    return spec


def _frame(name: str, table: Any, base_frame: str, where: str) -> FrameTransform:
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where}: expected a table (parent, translation, rpy_deg or quaternion)")
    bad = sorted(set(table) - FRAME_KEYS)
    if bad:
        raise ConfigError(f"{where}.{bad[0]}: unknown key (known: {', '.join(sorted(FRAME_KEYS))})")
    parent = _string(table.get("parent", base_frame), f"{where}.parent")
    if parent == name:
        raise ConfigError(f"{where}.parent: a frame cannot be its own parent")
    translation = _vector(table.get("translation", [0.0, 0.0, 0.0]), 3, f"{where}.translation")
    if "rpy_deg" in table and "quaternion" in table:
        raise ConfigError(f"{where}: give rpy_deg or quaternion, not both")
    if "quaternion" in table:
        q = _vector(table["quaternion"], 4, f"{where}.quaternion")
        try:
            matrix = from_quaternion(translation, q)
        except ValueError as exc:
            raise ConfigError(f"{where}.quaternion: {exc}") from None
    else:
        matrix = from_rpy(
            translation, _vector(table.get("rpy_deg", [0.0, 0.0, 0.0]), 3, f"{where}.rpy_deg")
        )
    return FrameTransform(parent, name, matrix, RIG_FILE_SOURCE)


def load_rig(path: str | Path) -> RigSpec:
    """Read and check a rig file (TOML)."""
    from canopy_kit.config import read_toml

    return parse_rig(read_toml(path), str(path))


def rig_preset_names() -> list[str]:
    """The rigs shipped in ``canopy_kit/presets/rigs`` (the simulator's, usable as examples)."""
    folder = resources.files("canopy_kit") / "presets" / "rigs"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def rig_data(name_or_path: str | Path) -> tuple[dict[str, Any], str]:
    """A shipped rig preset's or a rig file's tables, and where they came from."""
    import tomllib

    from canopy_kit.config import read_toml

    name = str(name_or_path)
    if name in rig_preset_names():
        text = (resources.files("canopy_kit") / "presets" / "rigs" / f"{name}.toml").read_text()
        return tomllib.loads(text), f"rig preset {name!r}"
    path = Path(name_or_path)
    if not path.exists():
        raise ConfigError(
            f"rig {name!r} is neither a shipped rig ({', '.join(rig_preset_names())}) "
            "nor an existing TOML file"
        )
    return read_toml(path), str(path)


def rig_tables(
    base_frame: str, transforms: list[FrameTransform], **names: str | float
) -> dict[str, Any]:
    """Rig-file tables (as :func:`parse_rig` reads them) for frames and transforms."""
    head: dict[str, Any] = {"base_frame": base_frame}
    head.update({k: v for k, v in names.items() if v not in ("", None)})
    frames = {
        t.child: {
            "parent": t.parent,
            "translation": [round(float(v), 6) for v in t.matrix[:3, 3]],
            "rpy_deg": [round(v, 6) for v in rpy_deg(t.matrix)],
        }
        for t in transforms
    }
    return {"rig": head, "frames": frames}


def rig_overrides(rig: str | Path | None = None, extrinsics: str | None = None) -> dict[str, Any]:
    """Config overrides (``mapping.rig``, ``rig_name``, ``extrinsics``) for a rig file and a mode.

    The rig file is read and checked here, so that the config written next to the results
    holds the rig itself, not only its path."""
    mapping: dict[str, Any] = {}
    if rig is not None:
        data, where = rig_data(rig)
        parse_rig(data, where)
        mapping.update(rig=data, rig_name=str(rig))
    if extrinsics is not None:
        mapping["extrinsics"] = extrinsics
    return {"mapping": mapping} if mapping else {}


def extrinsics_mode(assume_identity: bool, calibrate: bool) -> str | None:
    """``mapping.extrinsics`` from the two command-line flags (None: neither given)."""
    if assume_identity and calibrate:
        raise ConfigError(
            "--assume-identity-extrinsics and --calibrate-extrinsics exclude each other"
        )
    return "identity" if assume_identity else "calibrate" if calibrate else None
