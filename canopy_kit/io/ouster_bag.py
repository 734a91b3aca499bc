"""Bags of raw Ouster packets (ouster_ros ``PacketMsg``) read as one Scan per rotation.

ouster_ros records each UDP packet as its own message (``uint8[] buf``, no header) on
``/ouster/lidar_packets`` and ``/ouster/imu_packets``, and the sensor metadata JSON on
``/ouster/metadata`` (``std_msgs/String``, latched; older drivers wrote it to a file
only). :func:`wrap_ouster_reader` wraps an open bag reader so that the mapping sees the
lidar packets as one message per rotation (the packets sharing a ``frame_id``), of the type
:data:`OUSTER_LIDAR`, and everything else unchanged; the rotation is yielded when the next
one's first packet arrives (as the driver publishes a cloud), at its first packet's log
time, so a bag can still be seeked to a scan.

Point times: every column carries its firing time in ns on the sensor's clock (since
boot with ``TIME_FROM_INTERNAL_OSC``, TAI with PTP). A packet is logged once its last column
is measured, so the median over a rotation's packets of (log time − last column's time)
puts the columns on the bag's clock (the IMU's and GNSS's), as :mod:`.velodyne_ros` does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.errors import InputError, MessageError
from canopy_kit.io.ouster import (
    LIDAR_MODES,
    OusterInfo,
    decode_columns,
    frame_ids,
    packet_shape_guess,
    parse_metadata,
    read_metadata,
)
from canopy_kit.io.ros_types import register_missing

# The type the wrapped reader gives a lidar-packets topic (one message per rotation).
OUSTER_LIDAR = "ouster_sensor_msgs/msg/PacketMsg (lidar)"
IMU = "sensor_msgs/msg/Imu"  # the type an IMU-packets topic reads as (one sample a packet)
IMU_PACKET_BYTES = 48  # the LEGACY IMU profile: 3 u64 times, accel (g), gyro (deg/s) f32
STANDARD_GRAVITY = 9.80665
PACKET_TYPES = ("ouster_sensor_msgs/msg/PacketMsg", "ouster_ros/msg/PacketMsg")
STRING = "std_msgs/msg/String"
PACKET_DEFINITION = "uint8[] buf\n"


def register_ouster_types(typestore: Any) -> None:
    """Add the PacketMsg types a rosbags typestore lacks (rosbags ships none of them)."""
    register_missing(typestore, dict.fromkeys(PACKET_TYPES, PACKET_DEFINITION))


@dataclasses.dataclass
class _Stamp:
    sec: int
    nanosec: int


@dataclasses.dataclass
class _Header:
    stamp: _Stamp
    frame_id: str


@dataclasses.dataclass
class OusterRotation:
    """The packets of one rotation: log times (ns), the packets' bytes, the metadata."""

    log_ns: list[int]
    packets: list[bytes]
    info: OusterInfo
    topic: str
    header: _Header
    interior: bool = False  # rotations came before and after it (it is whole, bar packet loss)
    __msgtype__: str = OUSTER_LIDAR


@dataclasses.dataclass
class _Vector:
    x: float
    y: float
    z: float


@dataclasses.dataclass
class _Quaternion:
    x: float
    y: float
    z: float
    w: float


@dataclasses.dataclass
class OusterImuSample:
    """One LEGACY IMU packet as the fields of a ``sensor_msgs/Imu`` the mapping reads."""

    header: _Header
    angular_velocity: _Vector
    linear_acceleration: _Vector
    orientation: _Quaternion
    __msgtype__: str = IMU


class _ImuPacket:
    """An IMU packet and its log time, yielded as a message's raw data (``bytes()`` of it is
    empty, so the mapping's parser of serialized Imu messages leaves it to ``deserialize``)."""

    def __init__(self, buf: bytes, log_ns: int) -> None:
        self.buf, self.log_ns = buf, log_ns

    def __bytes__(self) -> bytes:
        return b""


@dataclasses.dataclass
class _Pending:
    log_ns: list[int]
    packets: list[bytes]
    interior: bool = False


class OusterPacketReader:
    """An open bag reader whose lidar-packet topics read as one message per rotation."""

    def __init__(self, reader: Any, bag: Path, metadata_file: str | Path | None) -> None:
        self._reader = reader
        self._bag = bag
        self._metadata_file = metadata_file
        self._info: OusterInfo | None = None
        self._original: dict[int, Any] = {}
        self._lidar: dict[int, Any] = {}
        self._connections: list[Any] | None = None
        self._imu: dict[int, Any] = {}

    @property
    def connections(self) -> list[Any]:
        """The bag's connections, lidar-packet topics as :data:`OUSTER_LIDAR` with about as
        many messages as rotations (packets over packets per rotation, when the metadata is
        at hand: the mapping plans its chunks by it)."""
        if self._connections is not None:
            return self._connections
        conns = []
        for c in self._reader.connections:
            if c.msgtype in PACKET_TYPES and "imu" in c.topic.lower() and self._legacy_imu(c):
                imu = c._replace(msgtype=IMU)
                self._original[id(imu)] = c
                self._imu[id(c)] = imu
                conns.append(imu)
            elif c.msgtype in PACKET_TYPES and "imu" not in c.topic.lower():
                lidar = c._replace(msgtype=OUSTER_LIDAR, msgcount=self._rotations(c))
                self._original[id(lidar)] = c  # rosbags' Connection: a NamedTuple
                self._lidar[id(c)] = lidar
                conns.append(lidar)
            else:
                conns.append(c)
        self._connections = conns
        return conns

    def _legacy_imu(self, conn: Any) -> bool:
        """Are the IMU packets of ``conn`` in the LEGACY profile (the one read)?"""
        try:
            return self.info(conn.topic).imu_profile == "LEGACY"
        except InputError:
            return False

    def _rotations(self, conn: Any) -> int:
        try:
            info = self.info(conn.topic)
        except InputError:  # no or bad metadata: said when the packets are decoded
            return int(conn.msgcount)
        first, last = info.column_window
        columns = (last - first) % info.columns_per_frame + 1
        per_rotation = -(-columns // info.columns_per_packet)
        return -(-int(conn.msgcount) // per_rotation)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._reader, name)

    def info(self, topic: str) -> OusterInfo:
        """The metadata: the given file, else the bag's ``*metadata`` String topic."""
        if self._info is not None:
            return self._info
        if self._metadata_file:
            self._info = read_metadata(self._metadata_file)
            return self._info
        meta = [
            c
            for c in self._reader.connections
            if c.msgtype == STRING and c.topic.rstrip("/").endswith("metadata")
        ]
        for conn, _, raw in self._reader.messages(connections=meta) if meta else ():
            text = self._reader.deserialize(raw, conn.msgtype).data
            self._info = parse_metadata(text, f"{self._bag}: topic {conn.topic!r}")
            return self._info
        raise InputError(
            f"{self._bag}: topic {topic!r} holds Ouster lidar packets but the bag has no "
            "Ouster metadata topic (std_msgs/String on /ouster/metadata) to decode them; give "
            "the sensor's metadata JSON with --set mapping.ouster_metadata=FILE"
        )

    def messages(
        self, connections: Collection[Any] = (), start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[Any, int, Any]]:
        """Like rosbags' ``messages``; a lidar-packets topic yields one :class:`_Pending` of
        packets per rotation (``deserialize`` makes it an :class:`OusterRotation`)."""
        wanted = list(connections) or list(self.connections)
        _ = self.connections  # maps the lidar connections
        inner = [self._original.get(id(c), c) for c in wanted]
        seek = {k: v for k, v in (("start", start), ("stop", stop)) if v is not None}
        pending: dict[str, tuple[Any, int, _Pending]] = {}
        for conn, log_ns, raw in self._reader.messages(connections=inner, **seek):
            lidar = self._lidar.get(id(conn))
            if lidar is None:
                imu = self._imu.get(id(conn))
                if imu is not None:
                    buf = bytes(self._reader.deserialize(raw, conn.msgtype).buf)
                    yield imu, log_ns, _ImuPacket(buf, int(log_ns))
                else:
                    yield conn, log_ns, raw
                continue
            buf = bytes(self._reader.deserialize(raw, conn.msgtype).buf)
            info = self.info(conn.topic)
            frame = _frame_id(info, buf)
            held = pending.get(conn.topic)
            if held is not None and held[1] != frame:
                yield held[0], held[2].log_ns[0], held[2]
                held = (lidar, frame, _Pending([], [], interior=True))
                pending[conn.topic] = held
            if held is None:  # the first rotation read: it may have started before the bag
                held = (lidar, frame, _Pending([], []))
                pending[conn.topic] = held
            held[2].log_ns.append(int(log_ns))
            held[2].packets.append(buf)
        for lidar, _, group in pending.values():
            group.interior = False  # the bag (or the stretch read) may end within it
            yield lidar, group.log_ns[0], group

    def deserialize(self, raw: Any, msgtype: str) -> Any:
        if isinstance(raw, _ImuPacket):
            return imu_sample(raw.buf, raw.log_ns, self.info(""))
        if isinstance(raw, _Pending):
            topic = next(c.topic for c in self.connections if c.msgtype == msgtype)
            stamp = raw.log_ns[0]
            header = _Header(_Stamp(stamp // 10**9, stamp % 10**9), "os_sensor")
            info = self.info(topic)
            return OusterRotation(raw.log_ns, raw.packets, info, topic, header, raw.interior)
        return self._reader.deserialize(raw, msgtype)


def imu_sample(buf: bytes, log_ns: int, info: OusterInfo) -> OusterImuSample:
    """A LEGACY IMU packet logged at ``log_ns`` as a sample in ``os_sensor`` (rotated by the
    metadata's ``imu_to_sensor_transform``; its 1-2 cm lever arm is left out), stamped on the
    bag's clock: the log time less the time from the gyro's reading to the packet's sending
    (the lidar's points carry the same recording delay). A packet of another size gives NaN
    values, which the mapping drops and counts."""
    if len(buf) == IMU_PACKET_BYTES:
        words = np.frombuffer(buf, np.uint8)
        sys_ts, _, gyro_ts = (int(v) for v in words[:24].view("<u8"))
        values = words[24:48].view("<f4").astype(np.float64)
        stamp = log_ns - (sys_ts - gyro_ts)
    else:
        values, stamp = np.full(6, np.nan), log_ns
    rot = info.imu_to_sensor[:3, :3]
    acc = rot @ values[:3] * STANDARD_GRAVITY
    gyro = rot @ np.deg2rad(values[3:6])
    return OusterImuSample(
        _Header(_Stamp(stamp // 10**9, stamp % 10**9), "os_sensor"),
        _Vector(*(float(v) for v in gyro)),
        _Vector(*(float(v) for v in acc)),
        _Quaternion(0.0, 0.0, 0.0, 1.0),
    )


def _frame_id(info: OusterInfo, buf: bytes) -> int:
    where = 10 if info.profile == "LEGACY" else 2
    if len(buf) < where + 2:
        return -1
    return int.from_bytes(buf[where : where + 2], "little")


def wrap_ouster_reader(reader: Any, bag: Path, metadata_file: str | Path | None = None) -> Any:
    """``reader`` wrapped in an :class:`OusterPacketReader` when it holds Ouster lidar
    packets, else ``reader`` itself."""
    register_ouster_types(reader.typestore)
    if not any(c.msgtype in PACKET_TYPES for c in reader.connections):
        return reader
    return OusterPacketReader(reader, bag, metadata_file)


def check_packets(info: OusterInfo, packets: list[bytes], where: str) -> np.ndarray:
    """The rotation's packets as a (P, bytes) array; an InputError when none has the size the
    metadata's mode and profile give (the metadata belongs to another sensor set-up), a
    MessageError when only some do (damaged packets: the rotation is dropped)."""
    sizes = {len(p) for p in packets}
    if sizes != {info.packet_bytes}:
        if info.packet_bytes not in sizes:
            size = len(packets[0])
            raise InputError(
                f"{where}: lidar packets of {size} bytes ({packet_shape_guess(size, 16)}) do "
                f"not fit the metadata from {info.source}: {info.describe()} packets have "
                f"{info.packet_bytes} bytes; give the metadata recorded with these packets"
            )
        raise MessageError(
            f"{where}: packets of {sorted(sizes)} bytes; {info.describe()} packets have "
            f"{info.packet_bytes}"
        )
    return np.frombuffer(b"".join(packets), np.uint8).reshape(len(packets), -1)


def _check_mode(info: OusterInfo, columns: Any, where: str, interior: bool) -> None:
    """An InputError when the columns' ids or timing belong to another lidar mode: ids past
    the mode's width, columns at another rate, or (a whole rotation) only half the ids."""
    width, fps = info.columns_per_frame, info.fps
    mid, ts = columns.measurement_id, columns.timestamp_ns.astype(np.int64)
    seen = ""
    if mid.max() >= width:
        seen = f"column ids up to {mid.max()}"
    elif interior and mid.max() < width // 2:
        seen = f"rotations of {mid.max() + 1} columns"
    elif len(mid) > 16 and mid[-1] != mid[0]:
        period = (ts[-1] - ts[0]) / (mid[-1] - mid[0]) * 1e-9  # s per column
        expected = 1.0 / (width * fps)
        if abs(period / expected - 1.0) > 0.1:
            seen = f"a column every {period * 1e6:.1f} µs (expected {expected * 1e6:.1f})"
    if seen:
        modes = [m for m in (512, 1024, 2048, 4096) if m > mid.max()]
        if interior:  # a whole rotation: its ids fill the mode's width
            modes = modes[:1]
        guess = ""
        if len(mid) > 16 and mid[-1] != mid[0]:
            rate = 1.0 / ((ts[-1] - ts[0]) / (mid[-1] - mid[0]) * 1e-9)
            fit = [f"{m}x{round(rate / m)}" for m in modes]
            fit = [m for m in fit if m in LIDAR_MODES]
            guess = f" (packets look like {' or '.join(fit)})" if fit else ""
        raise InputError(
            f"{where}: lidar packets with {seen}{guess} do not fit the metadata from "
            f"{info.source}: {info.describe()}; give the metadata recorded with these packets"
        )


def scan_from_rotation(msg: OusterRotation, where: str, index: int, path: str = "") -> Any:
    """One rotation's packets as a Scan in the sensor frame (see the module notes)."""
    from canopy_kit.io.bag import Scan

    info = msg.info
    topic_where = f"{path}: topic {msg.topic!r}, {where}" if path else where
    packets = check_packets(info, msg.packets, topic_where)
    log_ns = np.asarray(msg.log_ns, np.int64)
    columns = decode_columns(info, packets)
    frame_id = "os_sensor"
    if len(columns.measurement_id) == 0:
        empty = {k: np.zeros(0, np.float32) for k in ("intensity", "reflectivity", "time")}
        empty["ring"] = np.zeros(0, np.uint16)
        return Scan(log_ns[0] * 1e-9, np.zeros((0, 3)), empty, np.zeros(0), frame_id, index)
    _check_mode(info, columns, topic_where, msg.interior)
    last = np.zeros(len(packets), np.int64)  # each packet's last valid column time
    np.maximum.at(last, columns.packet, columns.timestamp_ns.astype(np.int64))
    got = np.unique(columns.packet)
    offset_ns = int(np.median(log_ns[got] - last[got]))  # sensor clock -> bag clock
    col_ns = columns.timestamp_ns.astype(np.int64) + offset_ns
    hit = columns.range_m > 0
    c_idx, beam = np.nonzero(hit)
    direction, offset = info.xyz_tables
    m = columns.measurement_id[c_idx]
    r = columns.range_m[c_idx, beam]
    xyz = direction[m, beam] * r[:, None] + offset[m, beam]
    t_ns = col_ns[c_idx]
    stamp_ns = int(col_ns.min())
    times = (t_ns - stamp_ns) * 1e-9
    fields = {
        "intensity": columns.signal[c_idx, beam].astype(np.float32),
        "reflectivity": columns.reflectivity[c_idx, beam].astype(np.float32),
        "ring": beam.astype(np.uint16),  # ouster_ros's ring: 0 = the top beam
        "time": times.astype(np.float32),
    }
    return Scan(stamp_ns * 1e-9, xyz, fields, stamp_ns * 1e-9 + times, frame_id, index)


__all__ = [
    "OUSTER_LIDAR",
    "PACKET_TYPES",
    "OusterRotation",
    "frame_ids",
    "register_ouster_types",
    "scan_from_rotation",
    "wrap_ouster_reader",
]
