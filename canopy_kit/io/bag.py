"""ROS1 (.bag) and ROS2 (sqlite3 / mcap) bags through rosbags' ``AnyReader``.

Scans stream out one at a time (:meth:`BagSession.scans`); IMU, GNSS and odometry are
small and come out as whole arrays. Topics are found by message type when not named. The
LiDAR is a PointCloud2 topic or, in a bag without one, the raw packets of the Velodyne
driver (``velodyne_msgs/VelodyneScan``, decoded by :mod:`canopy_kit.io.velodyne_ros`), a
Livox driver's ``CustomMsg`` (:mod:`canopy_kit.io.livox`) or ouster_ros's ``PacketMsg``
(grouped into rotations by :mod:`canopy_kit.io.ouster_bag`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.errors import InputError, MessageError
from canopy_kit.io import pointcloud2 as pc2
from canopy_kit.io.imu_units import acceleration_scale, g_units_warning
from canopy_kit.io.livox import CUSTOM_MSG_TYPES as LIVOX_TYPES
from canopy_kit.io.message_log import MessageLog, imu_sample_fault
from canopy_kit.io.ouster_bag import OUSTER_LIDAR

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
ODOMETRY = "nav_msgs/msg/Odometry"
VELODYNE_SCAN = "velodyne_msgs/msg/VelodyneScan"
LIDAR_TYPES = (POINTCLOUD2, VELODYNE_SCAN, *LIVOX_TYPES, OUSTER_LIDAR)  # in order of preference
KNOWN_TYPES = (POINTCLOUD2, IMU, NAVSATFIX, ODOMETRY, VELODYNE_SCAN, *LIVOX_TYPES, OUSTER_LIDAR)
TOPIC_ROLES = {
    POINTCLOUD2: "lidar",
    VELODYNE_SCAN: "lidar",
    **dict.fromkeys(LIVOX_TYPES, "lidar"),
    OUSTER_LIDAR: "lidar",
    IMU: "imu",
    NAVSATFIX: "gnss",
    ODOMETRY: "odometry",
}
# A point timed this far from the rest of its sweep is corrupt (a sweep lasts 0.05-0.2 s):
# one such time stretched its sweep's deskew window and moved the pose by metres.
MAX_POINT_TIME_OFFSET_S = 1.0


@dataclass
class TopicInfo:
    """One topic of a bag."""

    name: str
    msgtype: str
    count: int


@dataclass
class Scan:
    """One LiDAR sweep: coordinates in the sensor frame plus every other field."""

    stamp: float
    xyz: np.ndarray
    fields: dict[str, np.ndarray]
    times: np.ndarray | None
    frame_id: str
    index: int

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class ImuSeries:
    """IMU samples: time (s), angular velocity (rad/s), linear acceleration (m/s²), orientation xyzw."""

    t: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray
    orientation: np.ndarray
    frame_id: str = ""


@dataclass
class GnssSeries:
    """GNSS fixes: time (s), latitude, longitude (deg), altitude (m), status and covariance.

    ``covariance_type`` is NavSatFix's ``position_covariance_type`` per fix (0 unknown,
    1 approximated, 2 diagonal known, 3 known); empty when the source did not say.
    """

    t: np.ndarray
    latitude: np.ndarray
    longitude: np.ndarray
    altitude: np.ndarray
    status: np.ndarray
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 9)))
    covariance_type: np.ndarray = field(default_factory=lambda: np.zeros(0, int))


@dataclass
class OdometrySeries:
    """Poses: time (s), position (N, 3), orientation quaternions xyzw (N, 4)."""

    t: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    frame_id: str = ""
    child_frame_id: str = ""


def require_bag(bag: str | Path) -> Path:
    """``bag`` as a Path; an InputError when it does not exist, naming the bags beside it
    that its name may have meant (``session`` for ``session.bag``, ``session.mcap``...)."""
    bag = Path(bag)
    if bag.exists():
        return bag
    siblings = bag.parent.iterdir() if bag.parent.is_dir() else ()
    near = sorted(
        p.name for p in siblings if p.name.startswith(bag.name) and bag_kind(p) is not None
    )
    hint = f"; did you mean {', '.join(near)} in {bag.parent}?" if near else ""
    raise InputError(f"{bag}: bag does not exist{hint}")


def bag_kind(path: Path) -> str | None:
    """``ros1``, ``ros2`` or None, from the path's shape and magic bytes."""
    if path.is_dir():
        if (path / "metadata.yaml").exists() or any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return "ros2"
        return None
    if path.suffix == ".bag":
        return "ros1"
    if path.suffix in (".db3", ".mcap"):
        return "ros2"
    try:
        with path.open("rb") as fh:
            head = fh.read(13)
    except OSError:
        return None
    if head.startswith(b"#ROSBAG V2.0"):
        return "ros1"
    if head.startswith(b"\x89MCAP"):
        return "ros2"
    return None


def stray_times_warning(path: str, topic: str, stray: list[tuple[int, int]]) -> str:
    """The one warning that counts the points dropped for corrupt per-point times."""
    return (
        f"{path}: topic {topic!r}: {sum(n for _, n in stray)} points in "
        f"{len(stray)} scans had per-point times more than {MAX_POINT_TIME_OFFSET_S:g} s "
        f"from the rest of their scan or not finite (corrupt data) and were dropped (first: scan "
        f"{min(i for i, _ in stray)})"
    )


class BagSession:
    """An open bag. Use as a context manager: ``with open_bag(path) as bag: ...``."""

    def __init__(self, path: str | Path, ouster_metadata: str | Path | None = None) -> None:
        self.path = require_bag(path)
        self.ouster_metadata = ouster_metadata  # metadata JSON for Ouster packets (io.ouster_bag)
        if self.path.is_file() and self.path.stat().st_size == 0:
            raise InputError(f"{self.path}: file is empty, not a ROS bag")
        if bag_kind(self.path) is None:
            raise InputError(f"{self.path}: not a ROS1 .bag file or a ROS2 bag folder")
        self._reader: Any = None
        self.warnings: list[str] = []
        self.recovered = False  # read in file order after rosbags refused the bag (cut short?)
        self._stray: list[tuple[int, int]] = []  # (scan, points dropped for corrupt times)
        self._stray_warning: int | None = None
        self.log = MessageLog(str(self.path))  # messages met, dropped or trimmed per topic

    def __enter__(self) -> BagSession:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        target = self.path
        if self.path.is_file() and self.path.suffix in (".db3", ".mcap"):
            target = self.path.parent
        from canopy_kit.io.bag_recovery import sqlite_cut_short
        from canopy_kit.io.livox import register_livox_types
        from canopy_kit.io.velodyne_ros import register_velodyne_types

        if sqlite_cut_short(self.path):
            self._recover("the sqlite3 file is shorter than its header says")
            self._wrap_lidar_readers()
            return self
        default = get_typestore(Stores.ROS2_HUMBLE)
        register_velodyne_types(default)  # for bags that carry no message definitions
        register_livox_types(default)
        try:
            self._reader = AnyReader([target], default_typestore=default)
            self._reader.open()
        except Exception as exc:  # rosbags raises several unrelated types for bad files
            self._reader = None
            self._recover(f"{type(exc).__name__}: {exc}")
        else:
            from canopy_kit.io.mcap_messages import fast_mcap_reader

            self._reader = fast_mcap_reader(self._reader, target)
        self._wrap_lidar_readers()
        return self

    def _wrap_lidar_readers(self) -> None:
        """The LiDAR types rosbags lacks registered (for bags that define their other types
        but not these, and for recovered bags); Livox CustomMsgs read with numpy and Ouster
        packets grouped into rotations, where the bag holds them."""
        from canopy_kit.io.livox import wrap_livox_reader
        from canopy_kit.io.ouster_bag import wrap_ouster_reader
        from canopy_kit.io.velodyne_ros import register_velodyne_types

        register_velodyne_types(self._reader.typestore)
        self._reader = wrap_livox_reader(self._reader)
        self._reader = wrap_ouster_reader(self._reader, self.path, self.ouster_metadata)

    def _recover(self, reason: str) -> None:
        """Fall back to reading the complete records of a damaged bag (partial data)."""
        from canopy_kit.io.bag_recovery import recover_bag

        try:
            self._reader = recover_bag(self.path)
        except Exception as exc:  # InputError, or whatever the damaged bytes provoke
            detail = str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
            raise InputError(
                f"{self.path}: cannot open bag ({reason}); reading it record by "
                f"record failed too: {detail}"
            ) from None
        self.recovered = True
        self.warnings.append(
            f"{self.path}: damaged or cut short ({reason}); recovered "
            f"{self._reader.message_count} messages up to "
            f"t={self._reader.end_time * 1e-9:.3f} s, the rest is lost ({self._reader.stopped})"
        )

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    @property
    def reader(self) -> Any:
        if self._reader is None:
            raise RuntimeError("BagSession used outside its 'with' block")
        return self._reader

    def topics(self) -> list[TopicInfo]:
        """Topics with message types and message counts."""
        counts: dict[str, TopicInfo] = {}
        for c in self.reader.connections:
            info = counts.setdefault(c.topic, TopicInfo(c.topic, c.msgtype, 0))
            info.count += c.msgcount
        return sorted(counts.values(), key=lambda t: t.name)

    @property
    def start_time(self) -> float:
        return self.reader.start_time * 1e-9

    @property
    def end_time(self) -> float:
        return self.reader.end_time * 1e-9

    def find_topic(
        self, msgtype: str | tuple[str, ...], topic: str | None = None, required: bool = True
    ) -> str | None:
        """The topic to read for ``msgtype``: the named one (checked) or the busiest of that type.

        ``msgtype`` may list several types in order of preference (e.g. :data:`LIDAR_TYPES`): the
        named topic may carry any of them; otherwise the first type the bag has is chosen.
        """
        types = (msgtype,) if isinstance(msgtype, str) else tuple(msgtype)
        others = f" (or {', '.join(types[1:])})" if len(types) > 1 else ""
        topics = self.topics()
        if topic:
            match = [t for t in topics if t.name == topic]
            if not match:
                raise InputError(
                    f"{self.path}: no topic {topic!r} (topics: {', '.join(t.name for t in topics)})"
                )
            if match[0].msgtype not in types:
                raise InputError(
                    f"{self.path}: topic {topic!r} carries {match[0].msgtype}, "
                    f"expected {types[0]}{others}"
                )
            return topic
        candidates: list[TopicInfo] = []
        for wanted in types:
            candidates = candidates or [t for t in topics if t.msgtype == wanted and t.count > 0]
        if not candidates:
            if required:
                part = " part recovered from the damaged" if self.recovered else ""
                raise InputError(f"{self.path}: no {types[0]} topic{others} in the{part} bag")
            return None
        # Prefer names that do not look like ground truth or debug output.
        candidates.sort(key=lambda t: ("ground_truth" in t.name or "truth" in t.name, -t.count))
        return candidates[0].name

    def _messages(self, topic: str) -> Iterator[tuple[int, Any]]:
        conns = [c for c in self.reader.connections if c.topic == topic]
        try:
            for conn, timestamp, raw in self.reader.messages(connections=conns):
                try:
                    msg = self.reader.deserialize(raw, conn.msgtype)
                except Exception as exc:
                    raise InputError(
                        f"{self.path}: topic {topic!r}: cannot decode a {conn.msgtype} message "
                        f"at t={timestamp * 1e-9:.3f} s ({type(exc).__name__}: {exc})"
                    ) from None
                yield timestamp, msg
        except InputError:
            raise
        except Exception as exc:
            raise InputError(
                f"{self.path}: topic {topic!r}: reading failed ({type(exc).__name__}: {exc})"
            ) from None

    def scans(self, topic: str | None = None) -> Iterator[Scan]:
        """Stream the scans of ``topic`` (auto-detected when None: a PointCloud2 topic, else
        another of :data:`LIDAR_TYPES`); malformed ones are left out and counted
        (:attr:`log`), and too many of them are an error."""
        name = self.find_topic(LIDAR_TYPES, topic)
        assert name is not None
        for index, (_, msg) in enumerate(self._messages(name)):
            scan = self.decode_scan(name, msg, index)
            if scan is not None:
                yield scan
        self.log.topic(name, "scans").check()

    def decode_scan(self, topic: str, msg: Any, index: int) -> Scan | None:
        """Message ``index`` of ``topic``, a PointCloud2 or a VelodyneScan of raw packets
        (:mod:`canopy_kit.io.velodyne_ros`), as a :class:`Scan`; None when it is malformed
        (dropped and counted in :attr:`log`, with the field that does not fit)."""
        log = self.log.topic(topic, "scans")
        where = f"message {index}"
        try:
            if getattr(msg, "__msgtype__", "") == VELODYNE_SCAN:
                from canopy_kit.io.velodyne_ros import scan_from_message

                scan = scan_from_message(msg, where, index)
                stamp, xyz, fields, times, unused = scan.stamp, scan.xyz, scan.fields, scan.times, 0
            elif getattr(msg, "__msgtype__", "") in LIVOX_TYPES:
                from canopy_kit.io.livox import scan_fields

                stamp, xyz, fields, times = scan_fields(
                    msg, f"{self.path}: topic {topic!r}: {where}"
                )
                unused = 0
            elif getattr(msg, "__msgtype__", "") == OUSTER_LIDAR:
                from canopy_kit.io.ouster_bag import scan_from_rotation

                scan = scan_from_rotation(msg, where, index, str(self.path))
                stamp, xyz, fields, times, unused = scan.stamp, scan.xyz, scan.fields, scan.times, 0
            else:
                points, unused = pc2.decode_checked(msg, where)
                xyz = pc2.xyz_from(points, where)
                stamp = pc2.stamp_seconds(msg.header)
                names = points.dtype.names or ()
                time_name = pc2.time_field_name(names)
                times = (
                    pc2.point_times(points[time_name], stamp)
                    if time_name and points[time_name].ndim == 1
                    else None
                )
                fields = {k: np.array(points[k]) for k in names if k not in ("x", "y", "z")}
        except MessageError as exc:
            log.drop(index, "malformed", str(exc))
            return None
        log.use(index, stamp, msg.header.frame_id)
        if unused:
            described = int(msg.width) * int(msg.height) * int(msg.point_step)
            log.trim(
                index,
                unused,
                described,
                (
                    f"{where}: data holds {len(msg.data)} bytes, {unused} more than the "
                    f"width x height x point_step = {msg.width} x {msg.height} x {msg.point_step} = "
                    f"{described} its points take (row_step {msg.row_step})"
                ),
            )
        xyz, fields, times = self.drop_stray_times(topic, index, xyz, fields, times)
        return Scan(stamp, xyz, fields, times, msg.header.frame_id, index)

    def drop_stray_times(
        self,
        topic: str,
        index: int,
        xyz: np.ndarray,
        fields: dict[str, np.ndarray],
        times: np.ndarray | None,
    ) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray | None]:
        """A scan without its points of corrupt per-point time (see :func:`_stray_times`);
        one warning in :attr:`warnings` counts them over the bag."""
        stray = _stray_times(times)
        if stray is None:
            return xyz, fields, times
        keep = ~stray
        self._stray.append((index, int(stray.sum())))
        text = stray_times_warning(str(self.path), topic, self._stray)
        if self._stray_warning is None:
            self._stray_warning = len(self.warnings)
            self.warnings.append(text)
        else:
            self.warnings[self._stray_warning] = text
        return xyz[keep], {k: v[keep] for k, v in fields.items()}, times[keep]  # type: ignore[index]

    @property
    def stray_time_scans(self) -> list[tuple[int, int]]:
        """(scan index, points dropped) of every scan that lost points to corrupt times so far."""
        return list(self._stray)

    @property
    def stray_warning_index(self) -> int | None:
        """Position in :attr:`warnings` of the corrupt-times warning (None: no such warning)."""
        return self._stray_warning

    def imu(self, topic: str | None = None) -> ImuSeries | None:
        """All IMU samples of ``topic`` (auto-detected), or None when the bag has no IMU."""
        name = self.find_topic(IMU, topic, required=bool(topic))
        if name is None:
            return None
        t, gyro, acc, quat, frame = [], [], [], [], ""
        log = self.log.topic(name, "IMU samples")
        for index, (_, msg) in enumerate(self._messages(name)):
            w, a = msg.angular_velocity, msg.linear_acceleration
            if not self.imu_sample_ok(
                log,
                index,
                pc2.stamp_seconds(msg.header),
                (w.x, w.y, w.z),
                (a.x, a.y, a.z),
                msg.header.frame_id,
            ):
                continue
            t.append(pc2.stamp_seconds(msg.header))
            gyro.append((w.x, w.y, w.z))
            acc.append((a.x, a.y, a.z))
            quat.append(
                (msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w)
            )
            frame = msg.header.frame_id
        log.check()
        acc_array = np.array(acc).reshape(-1, 3)
        scale = acceleration_scale(acc_array)
        if scale != 1.0:
            self.warnings.append(g_units_warning(f"{self.path}: topic {name!r}", acc_array))
        return ImuSeries(
            np.array(t),
            np.array(gyro).reshape(-1, 3),
            acc_array * scale,
            np.array(quat).reshape(-1, 4),
            frame,
        )

    @staticmethod
    def imu_sample_ok(
        log: Any,
        index: int,
        stamp: float,
        gyro: tuple[float, float, float],
        acc: tuple[float, float, float],
        frame_id: str,
    ) -> bool:
        """Is IMU message ``index`` usable (finite, possible values)? Counted in ``log`` either way."""
        fault = imu_sample_fault(gyro, acc)
        if fault is None:
            log.use(index, stamp, frame_id)
            return True
        log.drop(
            index,
            fault,
            f"message {index} at t={stamp:.3f} s: {fault} (angular velocity "
            f"{gyro}, linear acceleration {acc})",
        )
        return False

    def gnss(self, topic: str | None = None) -> GnssSeries | None:
        """All NavSatFix messages of ``topic`` (auto-detected), or None when absent."""
        name = self.find_topic(NAVSATFIX, topic, required=bool(topic))
        if name is None:
            return None
        rows, cov = [], []
        for _, msg in self._messages(name):
            rows.append(
                (
                    pc2.stamp_seconds(msg.header),
                    msg.latitude,
                    msg.longitude,
                    msg.altitude,
                    msg.status.status,
                    msg.position_covariance_type,
                )
            )
            cov.append(np.asarray(msg.position_covariance, dtype=float))
        a = np.array(rows, dtype=float).reshape(-1, 6)
        return GnssSeries(
            a[:, 0],
            a[:, 1],
            a[:, 2],
            a[:, 3],
            a[:, 4].astype(int),
            np.array(cov).reshape(-1, 9),
            a[:, 5].astype(int),
        )

    def odometry(self, topic: str | None = None) -> OdometrySeries | None:
        """All Odometry poses of ``topic`` (auto-detected), or None when absent."""
        name = topic or self._truth_odometry_topic()
        if name is None:
            return None
        self.find_topic(ODOMETRY, name)
        t, pos, quat, frame, child = [], [], [], "", ""
        for _, msg in self._messages(name):
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            t.append(pc2.stamp_seconds(msg.header))
            pos.append((p.x, p.y, p.z))
            quat.append((q.x, q.y, q.z, q.w))
            frame, child = msg.header.frame_id, msg.child_frame_id
        return OdometrySeries(
            np.array(t), np.array(pos).reshape(-1, 3), np.array(quat).reshape(-1, 4), frame, child
        )

    def _truth_odometry_topic(self) -> str | None:
        odoms = [t for t in self.topics() if t.msgtype == ODOMETRY and t.count > 0]
        if not odoms:
            return None
        odoms.sort(key=lambda t: ("truth" not in t.name, -t.count))
        return odoms[0].name


def _stray_times(times: np.ndarray | None) -> np.ndarray | None:
    """Mask of the points whose time is not finite or lies far from their sweep's, or None
    when there are none.

    Only a handful (at most 1 %) of far times count as corrupt; a scan whose times spread
    widely throughout is left alone (another convention, handled downstream), and so is a
    scan without a single finite time (mapped without deskew).
    """
    if times is None or len(times) == 0:
        return None
    finite = np.isfinite(times)
    if not finite.any():
        return None
    far = np.zeros(len(times), bool)
    if (
        np.ptp(times[finite]) > MAX_POINT_TIME_OFFSET_S
    ):  # else no point can be that far from the median
        far[finite] = np.abs(times[finite] - np.median(times[finite])) > MAX_POINT_TIME_OFFSET_S
        if far.sum() > 0.01 * len(times):
            far[:] = False
    stray = far | ~finite
    return stray if stray.any() else None


def read_scan(path: str | Path, index: int, topic: str | None = None) -> Scan:
    """The ``index``-th scan of a bag (streams up to it; negative counts from the end)."""
    with open_bag(path) as bag:
        name = bag.find_topic(LIDAR_TYPES, topic)
        count = next(t.count for t in bag.topics() if t.name == name)
        wanted = index + count if index < 0 else index
        if not 0 <= wanted < count:
            raise InputError(f"{path}: topic {name!r} has {count} scans, no scan {index}")
        for scan in bag.scans(name):
            if scan.index == wanted:
                return scan
    raise InputError(f"{path}: scan {index} could not be read")


def open_bag(path: str | Path, ouster_metadata: str | Path | None = None) -> BagSession:
    """Open a ROS1 or ROS2 bag for reading (use with ``with``); ``ouster_metadata``: the
    sensor's metadata JSON for a bag of Ouster packets without a metadata topic."""
    return BagSession(path, ouster_metadata)


class RosbagReader:
    """Reader plugin for ROS1/ROS2 bags (``canopy_kit.readers`` entry point ``rosbag``)."""

    name = "rosbag"
    kind = "bag"
    suffixes = (".bag", ".db3", ".mcap")

    def sniff(self, path: Path) -> bool:
        """A bag folder, or a file that starts with a ROS1, MCAP or SQLite (db3) signature
        (the suffix alone routes a damaged bag to recovery; it does not make a bag)."""
        path = Path(path)
        if path.is_dir():
            return bag_kind(path) is not None
        try:
            with path.open("rb") as fh:
                head = fh.read(16)
        except OSError:
            return False
        return head.startswith((b"#ROSBAG V2.0", b"\x89MCAP", b"SQLite format 3\x00"))

    def describe(self, path: Path) -> dict[str, Any]:
        with open_bag(path) as bag:
            topics = bag.topics()
            return {
                "path": str(path),
                "format": "ros1 bag" if bag_kind(Path(path)) == "ros1" else "ros2 bag",
                "start_time": bag.start_time,
                "end_time": bag.end_time,
                "duration_s": bag.end_time - bag.start_time,
                # the LiDAR topic mapping would read (None: no PointCloud2 or VelodyneScan topic)
                "lidar_topic": bag.find_topic(LIDAR_TYPES, required=False),
                "topics": [
                    {
                        "name": t.name,
                        "type": t.msgtype,
                        "count": t.count,
                        "role": TOPIC_ROLES.get(t.msgtype, ""),
                    }
                    for t in topics
                ],
            }
