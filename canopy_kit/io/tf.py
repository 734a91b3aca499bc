"""Transforms recorded in a bag: ``/tf_static`` and the rigid part of ``/tf`` (tf2_msgs/TFMessage).

``/tf_static`` is latched: one message near the start lists every fixed sensor mount.
Some robots publish their mounts on ``/tf`` instead (a robot_state_publisher without
static joints); a ``/tf`` transform that does not change over the first seconds and does
not hang off a world frame (``odom``, ``map``...) is taken as static too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from canopy_kit.core.frames import FrameTransform, from_quaternion, rotation_angle_deg
from canopy_kit.errors import InputError

TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_MESSAGE_DEF = "geometry_msgs/TransformStamped[] transforms"
# REP 105 frames that move with the robot's motion, never part of a sensor mount.
WORLD_FRAMES = {"odom", "map", "world", "earth", "utm", "enu", "gps_origin"}
DYNAMIC_WINDOW_S = 10.0  # how much of /tf is read to find its static-in-practice transforms
STATIC_TOLERANCE_M = 1e-3
STATIC_TOLERANCE_DEG = 0.01


@dataclass
class RecordedTransforms:
    """What a bag says about its frames."""

    transforms: list[FrameTransform] = field(default_factory=list)
    topics: list[str] = field(default_factory=list)  # the tf topics read
    notes: list[str] = field(default_factory=list)


def ensure_tf_types(typestore: Any) -> None:
    """Register ``tf2_msgs/msg/TFMessage`` in a typestore that lacks it (ROS1 noetic's)."""
    if TF_MESSAGE not in typestore.types:
        from rosbags.typesys import get_types_from_msg

        typestore.register(get_types_from_msg(TF_MESSAGE_DEF, TF_MESSAGE))


def _strip(frame: str) -> str:
    """Frame ids without tf1's leading slash (``/velodyne`` and ``velodyne`` are one frame)."""
    return frame.removeprefix("/")


def _edges(msg: Any) -> list[tuple[str, str, np.ndarray]]:
    out = []
    for ts in msg.transforms:
        tr, q = ts.transform.translation, ts.transform.rotation
        try:
            matrix = from_quaternion((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w))
        except ValueError:
            continue
        if np.all(np.isfinite(matrix)):
            out.append((_strip(ts.header.frame_id), _strip(ts.child_frame_id), matrix))
    return out


def read_transforms(bag: Any, dynamic_window: float = DYNAMIC_WINDOW_S) -> RecordedTransforms:
    """The bag's static transforms (``BagSession``): every ``*tf_static`` message, plus the
    ``/tf`` transforms that stay put over the first ``dynamic_window`` seconds."""
    reader = bag.reader
    tf_conns = [c for c in reader.connections if c.msgtype == TF_MESSAGE]
    out = RecordedTransforms()
    static = [c for c in tf_conns if c.topic.rstrip("/").endswith("tf_static")]
    dynamic = [c for c in tf_conns if c not in static]
    out.topics = sorted({c.topic for c in tf_conns})
    found: dict[str, FrameTransform] = {}
    for _conn, msg in _read(bag, static):
        for parent, child, matrix in _edges(msg):
            found[child] = FrameTransform(parent, child, matrix, "tf_static")
    if dynamic:
        seen: dict[tuple[str, str], list[np.ndarray]] = {}
        stop = int(reader.start_time + dynamic_window * 1e9)
        for _, msg in _read(bag, dynamic, stop):
            for parent, child, matrix in _edges(msg):
                seen.setdefault((parent, child), []).append(matrix)
        moving = []
        for (parent, child), mats in seen.items():
            if child in found or parent in WORLD_FRAMES or child in WORLD_FRAMES:
                continue
            first = mats[0]
            still = all(
                np.linalg.norm(m[:3, 3] - first[:3, 3]) <= STATIC_TOLERANCE_M
                and rotation_angle_deg(m, first) <= STATIC_TOLERANCE_DEG
                for m in mats
            )
            if still:
                found[child] = FrameTransform(parent, child, first, "tf")
            else:
                moving.append(f"{parent} -> {child}")
        if moving:
            out.notes.append(
                f"/tf transforms that move were not used as mounts: {', '.join(sorted(moving))}"
            )
    out.transforms = [found[k] for k in sorted(found)]
    return out


def _read(bag: Any, conns: list, stop_ns: int | None = None):
    if not conns:
        return
    reader = bag.reader
    try:
        for conn, timestamp, raw in reader.messages(connections=conns):
            if stop_ns is not None and timestamp > stop_ns:
                return
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:  # rosbags raises several unrelated types
                raise InputError(
                    f"{bag.path}: topic {conn.topic!r}: cannot decode a {conn.msgtype} "
                    f"message at t={timestamp * 1e-9:.3f} s ({type(exc).__name__}: {exc})"
                ) from None
            yield conn, msg
    except InputError:
        raise
    except Exception as exc:
        raise InputError(
            f"{bag.path}: reading the tf topics failed ({type(exc).__name__}: {exc})"
        ) from None


def first_frame_id(bag: Any, topic: str | None) -> str | None:
    """``header.frame_id`` of the first message on ``topic`` (None: no topic or no message)."""
    if not topic:
        return None
    reader = bag.reader
    conns = [c for c in reader.connections if c.topic == topic]
    for _conn, msg in _read(bag, conns):
        return _strip(str(msg.header.frame_id))
    return None
