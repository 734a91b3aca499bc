"""One pass over a bag's LiDAR, IMU and GNSS topics in log-time order.

Reading the IMU or GNSS topic on its own costs a pass over the whole bag (chunks hold
every topic), about as long as decoding the scans, so the mapping stage reads all three
together and keeps the small IMU/GNSS streams in growable buffers.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.errors import InputError
from canopy_kit.io import pointcloud2 as pc2
from canopy_kit.io.bag import (
    IMU,
    LIDAR_TYPES,
    NAVSATFIX,
    BagSession,
    GnssSeries,
    ImuSeries,
    Scan,
)
from canopy_kit.io.imu_units import MIN_SAMPLES, acceleration_scale, g_units_warning
from canopy_kit.io.message_log import TopicLog
from canopy_kit.mapping.imu_mounting import ImuMounting


@dataclass
class SensorTopics:
    """The topics one mapping run reads (IMU/GNSS None when absent or disabled)."""

    scans: str
    imu: str | None
    gnss: str | None
    notes: list[str] = field(default_factory=list)  # topics chosen among several, one line each


def resolve_topics(
    bag: BagSession,
    scans: str = "",
    imu: str = "",
    gnss: str = "",
    use_imu: bool = True,
    use_gnss: bool = True,
) -> SensorTopics:
    """Named topics (checked) or the busiest topic of each message type; the scans are a
    PointCloud2 topic or, when the bag has none (or it is named), a VelodyneScan topic.
    A topic chosen among several of its type is named in ``notes``."""
    scan_topic = bag.find_topic(LIDAR_TYPES, scans or None)
    assert scan_topic is not None
    imu_topic = bag.find_topic(IMU, imu or None, required=bool(imu)) if use_imu else None
    gnss_topic = bag.find_topic(NAVSATFIX, gnss or None, required=bool(gnss)) if use_gnss else None
    chosen = [
        (scan_topic, scans, "pointcloud_topic"),
        (imu_topic, imu, "imu_topic"),
        (gnss_topic, gnss, "gnss_topic"),
    ]
    notes = [
        _choice_note(bag, topic, setting) for topic, named, setting in chosen if topic and not named
    ]
    return SensorTopics(scan_topic, imu_topic, gnss_topic, [n for n in notes if n])


def topics_for(bag: BagSession, config: MappingConfig) -> SensorTopics:
    """:func:`resolve_topics` with a mapping config's topic names and sensor switches."""
    return resolve_topics(
        bag,
        config.pointcloud_topic,
        config.imu_topic,
        config.gnss_topic,
        config.use_imu,
        config.use_gnss,
    )


def _choice_note(bag: BagSession, topic: str, setting: str) -> str | None:
    """The warning for a topic chosen among several of its type (None: it was the only one)."""
    topics = bag.topics()
    msgtype = next(t.msgtype for t in topics if t.name == topic)
    same = [t for t in topics if t.msgtype == msgtype and t.count > 0]
    if len(same) < 2:
        return None
    listed = ", ".join(f"{t.name!r} ({t.count} messages)" for t in same)
    return (
        f"{bag.path}: {len(same)} {msgtype} topics: {listed}; read {topic!r} (the busiest, the "
        f"first by name among equals; mapping.{setting} chooses another) and wrote it to the "
        "config saved with the results"
    )


class _Growable:
    """Rows appended one at a time into a numpy array that doubles its capacity."""

    def __init__(self, width: int) -> None:
        self._a = np.zeros((256, width))
        self.n = 0

    def append(self, row: tuple[float, ...]) -> None:
        if self.n == len(self._a):
            self._a = np.resize(self._a, (2 * len(self._a), self._a.shape[1]))
        self._a[self.n] = row
        self.n += 1

    @property
    def rows(self) -> np.ndarray:
        return self._a[: self.n]


class ImuBuffer:
    """IMU samples received so far (time, gyro xyz, accel xyz), as recorded.

    With a ``mounting`` the samples come out of :meth:`series` in the LiDAR frame and on
    the LiDAR clock (see :mod:`.imu_mounting`); :attr:`last_time` is on that clock too.
    """

    def __init__(
        self, frame_id: str = "", mounting: ImuMounting | None = None, source: str = ""
    ) -> None:
        self._rows = _Growable(7)
        self.frame_id = frame_id
        self.source = source  # "<bag>: topic '<imu topic>'", to start errors about these samples
        self.mounting = None if mounting is None or mounting.is_identity else mounting
        self.accel_scale: float | None = None  # m/s² per recorded unit, fixed once known
        self.warnings: list[str] = []  # e.g. acceleration recorded in g

    def __len__(self) -> int:
        return self._rows.n

    def append(
        self, t: float, gyro: tuple[float, float, float], acc: tuple[float, float, float]
    ) -> None:
        self._rows.append((t, *gyro, *acc))

    @property
    def last_time(self) -> float:
        if not len(self):
            return -np.inf
        offset = self.mounting.time_offset if self.mounting is not None else 0.0
        return float(self._rows.rows[-1, 0]) - offset

    def series(self, start: int = 0) -> ImuSeries:
        """Samples from index ``start`` on, sorted by time (no orientation).

        With a mounting, the lever-arm terms of a slice are computed from that slice alone
        (their first and last few samples are less smooth than in the whole series)."""
        r = self._rows.rows[start:]
        r = r[np.argsort(r[:, 0], kind="stable")]
        t, gyro, accel = r[:, 0].copy(), r[:, 1:4].copy(), r[:, 4:7].copy()
        accel *= self._accel_scale()
        if self.mounting is not None:
            t, gyro, accel = self.mounting.apply(t, gyro, accel)
        return ImuSeries(t, gyro, accel, np.tile([0.0, 0.0, 0.0, 1.0], (len(r), 1)), self.frame_id)

    def _accel_scale(self) -> float:
        """m/s² per recorded unit, decided once from the first samples (see io.imu_units)."""
        if self.accel_scale is None and len(self) >= MIN_SAMPLES:
            accel = self._rows.rows[:, 4:7]
            readings = accel[np.any(accel != 0, axis=1)]  # not a driver's all-zero start-up
            if len(readings) >= MIN_SAMPLES:
                self.accel_scale = acceleration_scale(readings)
                if self.accel_scale != 1.0:
                    self.warnings.append(g_units_warning(self.source or "IMU", readings))
        return self.accel_scale or 1.0


class GnssBuffer:
    """NavSatFix messages received so far: time, position, status, covariance and its type."""

    def __init__(self) -> None:
        self._rows = _Growable(5 + 9 + 1)

    def __len__(self) -> int:
        return self._rows.n

    def append(
        self,
        t: float,
        lat: float,
        lon: float,
        alt: float,
        status: int,
        covariance: np.ndarray,
        covariance_type: int = 2,
    ) -> None:
        """One fix; ``covariance_type`` is the message's ``position_covariance_type``."""
        cov = np.full(9, np.nan)
        given = np.asarray(covariance, float).ravel()[:9]
        cov[: len(given)] = given
        self._rows.append((t, lat, lon, alt, float(status), *cov, float(covariance_type)))

    def series(self) -> GnssSeries:
        """Every fix so far, sorted by time (NO_FIX and non-finite ones included)."""
        r = self._rows.rows
        r = r[np.argsort(r[:, 0], kind="stable")]
        return GnssSeries(
            r[:, 0].copy(),
            r[:, 1].copy(),
            r[:, 2].copy(),
            r[:, 3].copy(),
            r[:, 4].astype(int),
            r[:, 5:14].copy(),
            r[:, 14].astype(int),
        )


_IMU_SIZE_AFTER_HEADER = 296  # orientation, 3 vectors and 3 covariances: 37 float64
_GYRO, _ACCEL = 104, 200  # their offsets after the header (same in ROS1 and CDR)


def imu_fields(raw: bytes | memoryview, ros2: bool) -> tuple[float, str, tuple, tuple] | None:
    """Stamp, frame id, gyro and accel of a serialized ``sensor_msgs/Imu``, read in place.

    About 50 times cheaper than a full deserialisation (an IMU at 200 Hz sends 20 messages
    per LiDAR sweep). Returns None for anything but a well-formed little-endian message,
    and the caller then deserialises it with rosbags.
    """
    raw = bytes(raw)
    if ros2:
        if raw[:2] != b"\x00\x01" or len(raw) < 16:  # CDR, little endian
            return None
        raw, start = raw[4:], 12  # alignment counts from after the encapsulation header
        sec, nsec, n = struct.unpack_from("<iII", raw, 0)
        if n == 0 or start + n > len(raw) or raw[start + n - 1] != 0:
            return None
        frame = raw[start : start + n - 1]
        body = (start + n + 7) & ~7
    else:
        if len(raw) < 16:
            return None
        _, sec, nsec, n = struct.unpack_from("<IIII", raw, 0)
        start = 16
        frame = raw[start : start + n]
        body = start + n
    if len(raw) < body + _IMU_SIZE_AFTER_HEADER:
        return None
    try:
        frame_id = frame.decode()
    except UnicodeDecodeError:
        return None
    return (
        float(sec) + float(nsec) * 1e-9,
        frame_id,
        struct.unpack_from("<3d", raw, body + _GYRO),
        struct.unpack_from("<3d", raw, body + _ACCEL),
    )


def sensor_messages(
    bag: BagSession,
    topics: SensorTopics,
    imu: ImuBuffer | None = None,
    gnss: GnssBuffer | None = None,
    first_scan: int = 0,
    end_scan: int | None = None,
    log_times: list[int] | None = None,
) -> Iterator[Scan]:
    """Stream the scans; IMU and GNSS messages met on the way are appended to the buffers.

    Only scans ``first_scan <= index < end_scan`` are decoded and yielded (the ones before
    are skipped undecoded; IMU and GNSS before them are still collected); reading stops at
    ``end_scan``. ``log_times`` receives the bag's log time (ns) of every scan message read,
    skipped ones included (the map pass seeks to a scan with it).
    """
    reader = bag.reader
    wanted = (
        {topics.scans}
        | ({topics.imu} if topics.imu and imu is not None else set())
        | ({topics.gnss} if topics.gnss and gnss is not None else set())
    )
    conns = [c for c in reader.connections if c.topic in wanted]
    ros2 = getattr(reader, "is2", None)  # None: a recovered bag's reader; decode fully
    scan_log = bag.log.topic(topics.scans, "scans")
    imu_log = bag.log.topic(topics.imu, "IMU samples") if topics.imu and imu is not None else None
    gnss_log = (
        bag.log.topic(topics.gnss, "GNSS fixes") if topics.gnss and gnss is not None else None
    )
    index = n_imu = n_gnss = 0
    try:
        for conn, timestamp, raw in reader.messages(connections=conns):
            if log_times is not None and conn.topic == topics.scans:
                log_times.append(int(timestamp))
            if index < first_scan and conn.topic == topics.scans:
                index += 1
                continue
            if imu_log is not None and ros2 is not None and conn.topic == topics.imu:
                fields = imu_fields(raw, ros2)
                if fields is not None:
                    _add_imu(bag, imu, imu_log, n_imu, timestamp, *fields)  # type: ignore[arg-type]
                    n_imu += 1
                    continue
            msg = _deserialize(bag, conn, timestamp, raw)
            if conn.topic == topics.scans:
                scan_log.watch_clock(index, pc2.stamp_seconds(msg.header), timestamp)
                scan = bag.decode_scan(conn.topic, msg, index)
                if scan is not None:
                    yield scan
                index += 1
                if end_scan is not None and index >= end_scan:
                    break
            elif imu_log is not None and conn.topic == topics.imu:
                _add_imu_message(bag, imu, imu_log, n_imu, timestamp, msg)  # type: ignore[arg-type]
                n_imu += 1
            elif gnss_log is not None and conn.topic == topics.gnss:
                _add_fix(gnss, gnss_log, n_gnss, timestamp, msg)  # type: ignore[arg-type]
                n_gnss += 1
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{bag.path}: reading failed ({type(exc).__name__}: {exc})") from None
    bag.log.check()


def _deserialize(bag: BagSession, conn: Any, timestamp: int, raw: bytes) -> Any:
    """A message decoded, or an error naming the bag, topic, type and time."""
    try:
        return bag.reader.deserialize(raw, conn.msgtype)
    except Exception as exc:  # rosbags raises several unrelated types
        raise InputError(
            f"{bag.path}: topic {conn.topic!r}: cannot decode a {conn.msgtype} message "
            f"at t={timestamp * 1e-9:.3f} s ({type(exc).__name__}: {exc})"
        ) from None


def _add_imu_message(
    bag: BagSession, imu: ImuBuffer, log: TopicLog, index: int, timestamp: int, msg: Any
) -> None:
    """A decoded sensor_msgs/Imu appended to ``imu`` (the path when reading in place failed)."""
    w, a = msg.angular_velocity, msg.linear_acceleration
    _add_imu(
        bag,
        imu,
        log,
        index,
        timestamp,
        pc2.stamp_seconds(msg.header),  # type: ignore[arg-type]
        msg.header.frame_id,
        (w.x, w.y, w.z),
        (a.x, a.y, a.z),
    )


def _add_fix(gnss: GnssBuffer, log: TopicLog, index: int, timestamp: int, msg: Any) -> None:
    """A decoded NavSatFix appended to ``gnss``, its clock and frame watched by ``log``."""
    stamp = pc2.stamp_seconds(msg.header)
    log.watch_clock(index, stamp, timestamp)
    log.use(index, stamp, msg.header.frame_id)
    gnss.append(
        stamp,
        msg.latitude,
        msg.longitude,
        msg.altitude,  # type: ignore[union-attr]
        int(msg.status.status),
        np.asarray(msg.position_covariance, float),
        int(msg.position_covariance_type),
    )


def _add_imu(
    bag: BagSession,
    imu: ImuBuffer,
    log: TopicLog,
    index: int,
    log_ns: int,
    stamp: float,
    frame_id: str,
    gyro: tuple[float, float, float],
    acc: tuple[float, float, float],
) -> None:
    """One IMU sample into the buffer, unless it is unusable (then dropped and counted)."""
    log.watch_clock(index, stamp, log_ns)
    if bag.imu_sample_ok(log, index, stamp, gyro, acc, frame_id):
        imu.frame_id = frame_id
        imu.append(stamp, gyro, acc)
