"""Livox LiDARs: the drivers' ``CustomMsg`` (livox_ros_driver and livox_ros_driver2) as
:class:`~canopy_kit.io.bag.Scan`\\ s.

A ``CustomMsg`` holds one frame (0.1 s by default) of a non-repetitive scan: ``timebase``
(ns, the first point's time, which driver2 also writes into the header stamp) and, per
point, ``offset_time`` (ns after ``timebase``), x/y/z (m, sensor frame), ``reflectivity``,
``tag`` and ``line`` (the beam; there are no rings). Point times become
``timebase + offset_time`` on the bag's clock, so deskewing uses them.

rosbags deserialises a ``CustomPoint[]`` into one Python object per point (20,000 a frame of
a Mid-360); :class:`LivoxAwareReader` reads the serialised bytes instead, as one numpy
structured array over the point records (ROS1: packed 19-byte records; CDR: each record
aligned to 4 bytes, 20 apart), and falls back to rosbags for anything else.

The driver2 PointCloud2 mode (x, y, z, intensity float32, tag, line uint8, ``timestamp``
float64 absolute ns, 26 bytes a point) needs nothing here: :mod:`canopy_kit.io.pointcloud2`
reads it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from canopy_kit.errors import InputError, MessageError
from canopy_kit.io.ros_types import register_missing

CUSTOM_MSG = "livox_ros_driver2/msg/CustomMsg"
CUSTOM_MSG_V1 = "livox_ros_driver/msg/CustomMsg"
CUSTOM_MSG_TYPES = (CUSTOM_MSG, CUSTOM_MSG_V1)
_CUSTOM_MSG_BODY = (
    "std_msgs/Header header\nuint64 timebase\nuint32 point_num\nuint8 lidar_id\n"
    "uint8[3] rsvd\n{package}/CustomPoint[] points\n"
)
_CUSTOM_POINT = (
    "uint32 offset_time\nfloat32 x\nfloat32 y\nfloat32 z\nuint8 reflectivity\nuint8 tag\n"
    "uint8 line\n"
)
# The message definitions of both drivers (identical fields, different packages).
MESSAGE_DEFINITIONS = {
    f"{package}/msg/CustomPoint": _CUSTOM_POINT
    for package in ("livox_ros_driver", "livox_ros_driver2")
} | {
    f"{package}/msg/CustomMsg": _CUSTOM_MSG_BODY.format(package=package)
    for package in ("livox_ros_driver", "livox_ros_driver2")
}
POINT_FIELDS = [
    ("offset_time", "<u4"),
    ("x", "<f4"),
    ("y", "<f4"),
    ("z", "<f4"),
    ("reflectivity", "u1"),
    ("tag", "u1"),
    ("line", "u1"),
]
POINT_RECORD = np.dtype(POINT_FIELDS)  # ROS1: packed, 19 bytes
POINT_RECORD_CDR = np.dtype(  # CDR: the next record's uint32 starts on a multiple of 4
    {
        "names": [n for n, _ in POINT_FIELDS],
        "formats": [f for _, f in POINT_FIELDS],
        "offsets": [0, 4, 8, 12, 16, 17, 18],
        "itemsize": 20,
    }
)


def register_livox_types(typestore: Any) -> None:
    """Add the livox_ros_driver(2) types a rosbags typestore lacks (rosbags ships none)."""
    register_missing(typestore, MESSAGE_DEFINITIONS)


@dataclass
class _Time:
    sec: int
    nanosec: int


@dataclass
class _Header:
    stamp: _Time
    frame_id: str
    seq: int = 0


@dataclass
class LivoxFrame:
    """A CustomMsg read straight from its bytes: the points as one structured array."""

    header: _Header
    timebase: int
    point_num: int
    lidar_id: int
    points: np.ndarray  # fields of POINT_RECORD
    __msgtype__: str = CUSTOM_MSG


class _Cut(Exception):
    """The bytes end before the message does."""


def parse_custom_msg(raw: bytes | memoryview, ros2: bool, msgtype: str = CUSTOM_MSG) -> LivoxFrame:
    """A serialised CustomMsg (ROS1, or little-endian CDR) as a :class:`LivoxFrame`; a
    :class:`MessageError` when the bytes are too short for what they declare, a ValueError
    for a byte order it does not read (the caller then asks rosbags)."""
    buf = memoryview(raw).cast("B")
    try:
        if ros2:
            if bytes(buf[:2]) != b"\x00\x01":
                raise ValueError("not little-endian CDR")
            body = buf[4:]
            sec, nanosec, n = _unpack("<iII", body, 0)
            frame = bytes(body[12 : 12 + n]).rstrip(b"\x00")
            if 12 + n > len(body):
                raise _Cut
            pos = (12 + n + 7) & ~7
            seq = 0
        else:
            body = buf
            seq, sec, nanosec, n = _unpack("<IIII", body, 0)
            frame = bytes(body[16 : 16 + n])
            if 16 + n > len(body):
                raise _Cut
            pos = 16 + n
        timebase, point_num, lidar_id = _unpack("<QIB", body, pos)
        (count,) = _unpack("<I", body, pos + 16)
        start = pos + 20
        record = POINT_RECORD_CDR if ros2 else POINT_RECORD
        need = count * record.itemsize - (1 if ros2 and count else 0)  # no padding after the last
        if start + need > len(body):
            raise _Cut
        data = np.frombuffer(body, np.uint8, count=len(body) - start, offset=start)[:need]
        if ros2 and count:
            data = np.concatenate([data, np.zeros(1, np.uint8)])
        points = np.frombuffer(data.tobytes(), record, count=count)
    except (_Cut, struct.error):
        raise MessageError(
            f"{msgtype}: {len(buf)} bytes end before the message does (cut or corrupt)"
        ) from None
    points = points.astype(POINT_RECORD) if ros2 else points
    header = _Header(_Time(int(sec), int(nanosec)), frame.decode(errors="replace"), int(seq))
    return LivoxFrame(header, int(timebase), int(point_num), int(lidar_id), points, msgtype)


def _unpack(fmt: str, buf: memoryview, offset: int) -> tuple:
    return struct.unpack_from(fmt, buf, offset)


def points_of(msg: Any) -> np.ndarray:
    """The points of a CustomMsg as a POINT_RECORD array, whether read by
    :func:`parse_custom_msg` or deserialised by rosbags (one object per point)."""
    if isinstance(msg.points, np.ndarray):
        return msg.points
    out = np.zeros(len(msg.points), POINT_RECORD)
    for name, _ in POINT_FIELDS:
        out[name] = [getattr(p, name) for p in msg.points]
    return out


def scan_fields(
    msg: Any, where: str
) -> tuple[float, np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """Stamp (s), coordinates (N, 3), fields and absolute point times (s) of a CustomMsg.

    ``where`` (bag, topic, message) starts the :class:`InputError` raised when ``point_num``
    disagrees with the points the message holds: a driver or recording fault that leaves
    the frame's contents in doubt, so the run stops rather than map it.
    """
    points = points_of(msg)
    header_stamp = float(msg.header.stamp.sec) + float(msg.header.stamp.nanosec) * 1e-9
    if int(msg.point_num) != len(points):
        raise InputError(
            f"{where} at t={header_stamp:.3f} s: point_num says {msg.point_num} points but the "
            f"CustomMsg holds {len(points)} (corrupt or cut message)"
        )
    timebase = int(msg.timebase)
    # timebase is ns since the epoch: split off whole seconds before the float conversion.
    base_s = float(timebase // 1_000_000_000) + (timebase % 1_000_000_000) * 1e-9
    times = base_s + points["offset_time"].astype(np.float64) * 1e-9
    stamp = base_s if timebase else header_stamp
    xyz = np.empty((len(points), 3))
    with np.errstate(invalid="ignore"):
        for i, c in enumerate(("x", "y", "z")):
            xyz[:, i] = points[c]
    fields = {
        "intensity": points["reflectivity"].astype(np.float32),
        "tag": points["tag"].copy(),
        "line": points["line"].copy(),
        "offset_time": points["offset_time"].copy(),
    }
    return stamp, xyz, fields, times


def wrap_livox_reader(reader: Any) -> Any:
    """``reader`` with the Livox types registered, wrapped in a :class:`LivoxAwareReader` when
    it holds CustomMsg topics (else returned as it is: other bags keep their own reader)."""
    register_livox_types(reader.typestore)
    if not any(c.msgtype in CUSTOM_MSG_TYPES for c in reader.connections):
        return reader
    return LivoxAwareReader(reader)


class LivoxAwareReader:
    """An open bag reader whose ``deserialize`` reads Livox CustomMsgs with numpy
    (:func:`parse_custom_msg`); everything else is the wrapped reader's."""

    def __init__(self, reader: Any) -> None:
        self._reader = reader
        is2 = getattr(reader, "is2", None)
        self._ros2 = bool(is2) if is2 is not None else not getattr(reader, "ros1", False)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._reader, name)

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        """The message in ``raw``: a :class:`LivoxFrame` for a CustomMsg, else rosbags'."""
        if msgtype in CUSTOM_MSG_TYPES:
            try:
                return parse_custom_msg(raw, self._ros2, msgtype)
            except ValueError:  # a byte order read only by rosbags
                pass
        return self._reader.deserialize(raw, msgtype)

    def close(self) -> None:
        self._reader.close()


def serialize_custom_msg(
    timebase_ns: int,
    points: np.ndarray,
    frame_id: str,
    ros2: bool,
    seq: int = 0,
    lidar_id: int = 0,
    point_num: int | None = None,
) -> bytes:
    """The bytes of a CustomMsg (ROS1, or little-endian CDR) of ``points`` (POINT_RECORD
    fields), its header stamped ``timebase_ns`` as driver2 does; ``point_num`` other than
    ``len(points)`` only to make corrupt test messages."""
    points = np.asarray(points, POINT_RECORD)
    count = len(points)
    sec, nanosec = divmod(int(timebase_ns), 1_000_000_000)
    name = frame_id.encode()
    declared = count if point_num is None else int(point_num)
    if ros2:
        head = struct.pack("<iII", sec, nanosec, len(name) + 1) + name + b"\x00"
        head += b"\x00" * (-len(head) % 8)
        body = np.zeros(count, POINT_RECORD_CDR)
        for field in POINT_RECORD.names:
            body[field] = points[field]
        records = body.tobytes()[:-1] if count else b""  # no padding after the last record
        prefix = b"\x00\x01\x00\x00"
    else:
        head = struct.pack("<IIII", seq, sec, nanosec, len(name)) + name
        records, prefix = points.tobytes(), b""
    fixed = struct.pack("<QIB3xI", int(timebase_ns), declared, lidar_id, count)
    return prefix + head + fixed + records
