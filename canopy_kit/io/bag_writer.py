"""Write ROS1 / ROS2 (sqlite3 or mcap) bags message by message, through rosbags' writers.

Used by the simulator and the tests; messages are built from plain numpy values so the
caller never touches ROS types.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np

from canopy_kit.errors import InputError
from canopy_kit.io import pointcloud2 as pc2

BagFormat = Literal["ros1", "ros2-sqlite3", "ros2-mcap"]
BAG_FORMATS: tuple[str, ...] = ("ros1", "ros2-sqlite3", "ros2-mcap")


def bag_path_for(out: Path, fmt: str) -> Path:
    """Where a bag of ``fmt`` named ``out`` lives (ROS1: a ``.bag`` file; ROS2: a folder)."""
    if fmt == "ros1":
        return out if out.suffix == ".bag" else out.with_suffix(".bag")
    return out


class BagWriter:
    """Streaming bag writer. ``with BagWriter(path, "ros2-mcap") as w: w.write_imu(...)``.

    The bag is written under a temporary name and renamed on a clean close, so a crash
    never leaves a bag that looks complete.
    """

    def __init__(self, path: str | Path, fmt: str = "ros2-mcap") -> None:
        if fmt not in BAG_FORMATS:
            raise InputError(f"bag format {fmt!r} is not one of {', '.join(BAG_FORMATS)}")
        self.fmt = fmt
        self.path = bag_path_for(Path(path), fmt)
        self.ros1 = fmt == "ros1"
        self._tmp = self.path.with_name(f".{self.path.name}.partial")
        self._writer: Any = None
        self._conns: dict[str, Any] = {}
        self._seq: dict[str, int] = {}
        from rosbags.typesys import Stores, get_typestore

        self.typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)

    def __enter__(self) -> BagWriter:
        if self.path.exists():
            raise InputError(f"{self.path}: already exists; remove it or choose another name")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self._tmp.exists():
            shutil.rmtree(self._tmp) if self._tmp.is_dir() else self._tmp.unlink()
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self._writer = Writer(self._tmp)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if self.fmt == "ros2-mcap" else StoragePlugin.SQLITE3
            self._writer = Writer(self._tmp, version=9, storage_plugin=plugin)
        self._writer.open()
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        self._writer.close()
        if exc_type is None:
            if not self.ros1:
                self._rename_ros2_storage()
            self._tmp.rename(self.path)
        else:
            shutil.rmtree(
                self._tmp, ignore_errors=True
            ) if self._tmp.is_dir() else self._tmp.unlink(missing_ok=True)

    def _rename_ros2_storage(self) -> None:
        """Storage files inside a ROS2 bag are named after the folder; keep them consistent."""
        import yaml

        meta_path = self._tmp / "metadata.yaml"
        meta = yaml.safe_load(meta_path.read_text())
        info = meta["rosbag2_bagfile_information"]
        renamed = []
        for rel in info["relative_file_paths"]:
            new = rel.replace(self._tmp.name, self.path.name)
            (self._tmp / rel).rename(self._tmp / new)
            renamed.append(new)
        info["relative_file_paths"] = renamed
        for f in info.get("files", []):
            f["path"] = f["path"].replace(self._tmp.name, self.path.name)
        meta_path.write_text(yaml.safe_dump(meta, sort_keys=False))

    def _connect(self, topic: str, msgtype: str, latched: bool = False) -> None:
        """Open a connection; ``latched`` as /tf_static is (ROS1 latching, ROS2 transient local)."""
        if not latched:
            self._conns[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore
            )
        elif self.ros1:
            self._conns[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore, latching=1
            )
        else:
            from rosbags.interfaces import (
                Qos,
                QosDurability,
                QosHistory,
                QosLiveliness,
                QosReliability,
                QosTime,
            )

            never = QosTime(0x7FFFFFFF, 0xFFFFFFFF)
            qos = Qos(
                QosHistory.KEEP_LAST,
                1,
                QosReliability.RELIABLE,
                QosDurability.TRANSIENT_LOCAL,
                never,
                never,
                QosLiveliness.AUTOMATIC,
                never,
                False,
            )
            self._conns[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore, offered_qos_profiles=[qos]
            )

    def _write(self, topic: str, msgtype: str, msg: Any, stamp: float) -> None:
        if topic not in self._conns:
            self._connect(topic, msgtype)
        if self.ros1:
            data = self.typestore.serialize_ros1(msg, msgtype)
        else:
            data = self.typestore.serialize_cdr(msg, msgtype)
        self._writer.write(self._conns[topic], int(round(stamp * 1e9)), data)

    def _header(self, topic: str, stamp: float, frame_id: str) -> Any:
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        return pc2.make_header(self.typestore, stamp, frame_id, self.ros1, seq)

    def _vec3(self, v: Any) -> Any:
        return self.typestore.types["geometry_msgs/msg/Vector3"](
            x=float(v[0]), y=float(v[1]), z=float(v[2])
        )

    def _quat(self, q: Any) -> Any:
        return self.typestore.types["geometry_msgs/msg/Quaternion"](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        )

    def write_points(
        self,
        topic: str,
        stamp: float,
        columns: Mapping[str, np.ndarray],
        frame_id: str = "lidar",
        height: int = 1,
    ) -> None:
        """One PointCloud2 from named columns (x, y, z, then any fields)."""
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        msg = pc2.build_message(self.typestore, columns, stamp, frame_id, self.ros1, seq, height)
        self._write(topic, "sensor_msgs/msg/PointCloud2", msg, stamp)

    def write_velodyne_scan(
        self,
        topic: str,
        packet_stamps: Any,
        packets: Any,
        frame_id: str = "velodyne",
        stamp: float | None = None,
    ) -> None:
        """One velodyne_msgs/VelodyneScan: per-packet stamps (s) and the packets, a (P, 1206)
        uint8 array or P byte strings. The header stamp (and the log time) is ``stamp``, by
        default the first packet's.
        """
        from canopy_kit.io.velodyne_ros import VELODYNE_PACKET, register_velodyne_types

        register_velodyne_types(self.typestore)
        t = self.typestore.types
        if isinstance(packets, list | tuple):
            data = [np.frombuffer(bytes(p), np.uint8) for p in packets]
        else:
            data = list(np.asarray(packets, np.uint8).reshape(len(packet_stamps), -1))
        stamps = [float(s) for s in packet_stamps]
        header_stamp = stamps[0] if stamp is None else float(stamp)
        msg = t["velodyne_msgs/msg/VelodyneScan"](
            header=self._header(topic, header_stamp, frame_id),
            packets=[
                t[VELODYNE_PACKET](
                    stamp=pc2.make_header(self.typestore, s, "", self.ros1).stamp, data=row
                )
                for s, row in zip(stamps, data, strict=True)
            ],
        )
        self._write(topic, "velodyne_msgs/msg/VelodyneScan", msg, header_stamp)

    def write_livox_custom(
        self,
        topic: str,
        timebase_ns: int,
        points: np.ndarray,
        frame_id: str = "livox_frame",
        msgtype: str = "livox_ros_driver2/msg/CustomMsg",
        point_num: int | None = None,
    ) -> None:
        """One Livox CustomMsg (driver2, or ``livox_ros_driver/msg/CustomMsg``) of ``points``
        (fields of :data:`canopy_kit.io.livox.POINT_RECORD`), serialised with numpy."""
        from canopy_kit.io.livox import register_livox_types, serialize_custom_msg

        register_livox_types(self.typestore)
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        data = serialize_custom_msg(
            timebase_ns, points, frame_id, not self.ros1, seq, point_num=point_num
        )
        if topic not in self._conns:
            self._connect(topic, msgtype)
        self._writer.write(self._conns[topic], int(timebase_ns), data)

    def write_ouster_packets(
        self,
        topic: str,
        packet_stamps: Any,
        packets: Any,
        metadata: str | None = None,
        metadata_topic: str = "/ouster/metadata",
        msgtype: str = "ouster_sensor_msgs/msg/PacketMsg",
    ) -> None:
        """Ouster lidar packets, one ``PacketMsg`` each (``msgtype``: older drivers'
        ``ouster_ros/msg/PacketMsg``), logged at ``packet_stamps`` (s); ``metadata`` (the
        sensor's JSON) goes once on ``metadata_topic`` as a latched std_msgs/String first."""
        from canopy_kit.io.ouster_bag import register_ouster_types

        register_ouster_types(self.typestore)
        t = self.typestore.types
        if metadata is not None and metadata_topic not in self._conns:
            self._connect(metadata_topic, "std_msgs/msg/String", latched=True)
            msg = t["std_msgs/msg/String"](data=metadata)
            self._write(metadata_topic, "std_msgs/msg/String", msg, float(packet_stamps[0]))
        rows = np.asarray(packets, np.uint8).reshape(len(packet_stamps), -1)
        for stamp, row in zip(packet_stamps, rows, strict=True):
            self._write(topic, msgtype, t[msgtype](buf=row), float(stamp))

    def write_imu(
        self,
        topic: str,
        stamp: float,
        angular_velocity: Any,
        linear_acceleration: Any,
        orientation: Any | None = None,
        frame_id: str = "lidar",
    ) -> None:
        """One sensor_msgs/Imu; orientation xyzw or None (covariance[0] = -1, per REP-145).

        ``frame_id`` defaults to the LiDAR's (``write_points``): without /tf_static a bag
        maps only when its sensors share a frame."""
        t = self.typestore.types
        ocov = np.zeros(9)
        if orientation is None:
            orientation, ocov[0] = (0.0, 0.0, 0.0, 1.0), -1.0
        msg = t["sensor_msgs/msg/Imu"](
            header=self._header(topic, stamp, frame_id),
            orientation=self._quat(orientation),
            orientation_covariance=ocov,
            angular_velocity=self._vec3(angular_velocity),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=self._vec3(linear_acceleration),
            linear_acceleration_covariance=np.zeros(9),
        )
        self._write(topic, "sensor_msgs/msg/Imu", msg, stamp)

    def write_fix(
        self,
        topic: str,
        stamp: float,
        lat: float,
        lon: float,
        alt: float,
        sigma_h: float = 1.0,
        sigma_v: float = 2.0,
        status: int = 0,
        frame_id: str = "lidar",
        covariance_type: int = 2,
    ) -> None:
        """One sensor_msgs/NavSatFix with a diagonal covariance.

        ``covariance_type`` 0 (COVARIANCE_TYPE_UNKNOWN) writes an all-zero covariance, as
        receivers that do not know their accuracy do; NaN positions are written as they are."""
        t = self.typestore.types
        status_msg = t["sensor_msgs/msg/NavSatStatus"](status=int(status), service=1)
        cov = (
            np.zeros(9)
            if covariance_type == 0
            else np.diag([sigma_h**2, sigma_h**2, sigma_v**2]).ravel().astype(float)
        )
        msg = t["sensor_msgs/msg/NavSatFix"](
            header=self._header(topic, stamp, frame_id),
            status=status_msg,
            latitude=float(lat),
            longitude=float(lon),
            altitude=float(alt),
            position_covariance=cov,
            position_covariance_type=int(covariance_type),
        )
        self._write(topic, "sensor_msgs/msg/NavSatFix", msg, stamp)

    def write_tf_static(
        self, stamp: float, transforms: list[tuple[str, str, np.ndarray]], topic: str = "/tf_static"
    ) -> None:
        """One tf2_msgs/TFMessage of ``(parent, child, parent_from_child 4x4)`` transforms
        (latched on a ``*tf_static`` topic, as robots record it)."""
        from scipy.spatial.transform import Rotation

        from canopy_kit.io.tf import TF_MESSAGE, ensure_tf_types

        ensure_tf_types(self.typestore)
        t = self.typestore.types
        items = []
        for parent, child, matrix in transforms:
            m = np.asarray(matrix, float)
            items.append(
                t["geometry_msgs/msg/TransformStamped"](
                    header=self._header(topic, stamp, parent),
                    child_frame_id=child,
                    transform=t["geometry_msgs/msg/Transform"](
                        translation=self._vec3(m[:3, 3]),
                        rotation=self._quat(Rotation.from_matrix(m[:3, :3]).as_quat()),
                    ),
                )
            )
        if topic not in self._conns:
            self._connect(topic, TF_MESSAGE, latched=topic.rstrip("/").endswith("tf_static"))
        self._write(topic, TF_MESSAGE, t[TF_MESSAGE](transforms=items), stamp)

    def write_odometry(
        self,
        topic: str,
        stamp: float,
        position: Any,
        orientation: Any,
        frame_id: str = "map",
        child_frame_id: str = "lidar",
    ) -> None:
        """One nav_msgs/Odometry pose (twist left zero)."""
        t = self.typestore.types
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](
                x=float(position[0]), y=float(position[1]), z=float(position[2])
            ),
            orientation=self._quat(orientation),
        )
        twist = t["geometry_msgs/msg/Twist"](
            linear=self._vec3((0, 0, 0)), angular=self._vec3((0, 0, 0))
        )
        msg = t["nav_msgs/msg/Odometry"](
            header=self._header(topic, stamp, frame_id),
            child_frame_id=child_frame_id,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
        )
        self._write(topic, "nav_msgs/msg/Odometry", msg, stamp)
