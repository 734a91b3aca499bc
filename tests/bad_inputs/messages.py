"""Faults inside a bag's messages: a copy of a bag with chosen messages edited.

:func:`rewrite_bag` copies every message of a bag (ROS1 or ROS2) into a new ROS2 MCAP bag,
passing each through an ``edit`` hook that may change it, drop it or add messages (on other
topics too). The hooks below build the catalogue's message faults: a non-finite IMU sample,
PointCloud2 headers that lie about their data, a sensor clock that jumps back, a second
point-cloud topic.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
# (topic, index on that topic, log time ns, message) -> [(topic, msgtype, log time ns, message)]
Edit = Callable[[str, int, int, Any], list[tuple[str, str, int, Any]] | None]


def rewrite_bag(src: str | Path, dst: str | Path, edit: Edit) -> Path:
    """Copy ``src`` to the ROS2 MCAP bag ``dst`` through ``edit`` (None from it: keep the
    message as it is). Connections appear as messages need them."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    dst = Path(dst)
    with AnyReader([Path(src)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        store = reader.typestore
        writer = Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        conns: dict[str, Any] = {}
        seen: dict[str, int] = {}
        try:
            for conn, log_ns, raw in reader.messages():
                index = seen.get(conn.topic, 0)
                seen[conn.topic] = index + 1
                msg = reader.deserialize(raw, conn.msgtype)
                out = edit(conn.topic, index, log_ns, msg)
                for topic, msgtype, t_ns, m in (
                    [(conn.topic, conn.msgtype, log_ns, msg)] if out is None else out
                ):
                    if topic not in conns:
                        conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
                    writer.write(conns[topic], int(t_ns), store.serialize_cdr(m, msgtype))
        finally:
            writer.close()
    return dst


def _keep(topic: str, msgtype: str, log_ns: int, msg: Any) -> list[tuple[str, str, int, Any]]:
    return [(topic, msgtype, log_ns, msg)]


def imu_sample(
    index: int,
    angular_velocity: tuple[float, float, float] | None = None,
    linear_acceleration: tuple[float, float, float] | None = None,
    topic: str = "/imu/data",
) -> Edit:
    """IMU message ``index`` of ``topic`` (or every ``index``-th when negative) carries these values."""

    def edit(t: str, i: int, log_ns: int, msg: Any) -> list | None:
        if t != topic or not (i == index or (index < 0 and i % -index == 0)):
            return None
        vec = type(msg.angular_velocity)
        if angular_velocity is not None:
            msg = dataclasses.replace(msg, angular_velocity=vec(*map(float, angular_velocity)))
        if linear_acceleration is not None:
            msg = dataclasses.replace(
                msg, linear_acceleration=vec(*map(float, linear_acceleration))
            )
        return _keep(t, IMU, log_ns, msg)

    return edit


def gnss_fix(indices: tuple[int, ...], topic: str = "/gps/fix", **values: float) -> Edit:
    """NavSatFix messages ``indices`` of ``topic`` with ``latitude``, ``longitude`` or
    ``altitude`` replaced (their status left as it is: they still claim a fix)."""

    def edit(t: str, i: int, log_ns: int, msg: Any) -> list | None:
        if t != topic or i not in indices:
            return None
        return _keep(t, "sensor_msgs/msg/NavSatFix", log_ns, dataclasses.replace(msg, **values))

    return edit


def cloud_header(topic: str = "/points", every: int = 1, **changes: Any) -> Edit:
    """Every ``every``-th PointCloud2 of ``topic`` with header fields replaced: ``width``,
    ``height``, ``point_step``, ``row_step`` as numbers, ``fields`` as a function of the
    message's fields (returning new ``PointField`` objects)."""

    def edit(t: str, i: int, log_ns: int, msg: Any) -> list | None:
        if t != topic or i % every:
            return None
        new = {}
        for key, value in changes.items():
            if key == "fields":
                new[key] = value(msg.fields, type(msg.fields[0]))
            elif callable(value):
                new[key] = int(value(getattr(msg, key)))
            else:
                new[key] = int(value)
        return _keep(t, POINTCLOUD2, log_ns, dataclasses.replace(msg, **new))

    return edit


def padded_data(topic: str = "/points", n_bytes: int = 48, every: int = 1) -> Edit:
    """Every ``every``-th PointCloud2 of ``topic`` with ``n_bytes`` of zeros after its data
    (the header unchanged: more data than it describes)."""

    def edit(t: str, i: int, log_ns: int, msg: Any) -> list | None:
        if t != topic or i % every:
            return None
        data = np.concatenate([np.asarray(msg.data, np.uint8), np.zeros(n_bytes, np.uint8)])
        return _keep(t, POINTCLOUD2, log_ns, dataclasses.replace(msg, data=data))

    return edit


def data_cut(topic: str = "/points", keep: float = 0.0) -> Edit:
    """Every PointCloud2 of ``topic`` with only the first ``keep`` of its data (header unchanged)."""

    def edit(t: str, i: int, log_ns: int, msg: Any) -> list | None:
        if t != topic:
            return None
        data = np.asarray(msg.data, np.uint8)
        return _keep(
            t,
            POINTCLOUD2,
            log_ns,
            dataclasses.replace(msg, data=data[: int(keep * len(data))].copy()),
        )

    return edit


def field_changed(name: str, **changes: int) -> Callable[[list, type], list]:
    """A ``fields`` edit for :func:`cloud_header`: the field ``name`` with ``offset``,
    ``datatype`` or ``count`` changed."""

    def fields(items: list, cls: type) -> list:
        return [dataclasses.replace(f, **changes) if f.name == name else f for f in items]

    return fields


def clock_jump(after_s: float, by_s: float, topics: tuple[str, ...] | None = None) -> Edit:
    """Header stamps of every message from ``after_s`` s into the bag on shifted by ``by_s``
    (negative: the sensor clock jumped back), on ``topics`` (None: every topic with a header);
    log times stay as recorded."""
    state: dict[str, int] = {}

    def edit(t: str, i: int, log_ns: int, msg: Any) -> list | None:
        state.setdefault("t0", log_ns)
        header = getattr(msg, "header", None)
        if (
            header is None
            or (topics is not None and t not in topics)
            or log_ns - state["t0"] < after_s * 1e9
        ):
            return None
        stamp = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec + int(round(by_s * 1e9))
        new_stamp = dataclasses.replace(
            header.stamp, sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000
        )
        msgtype = getattr(msg, "__msgtype__", None) or _msgtype_of(msg)
        return _keep(
            t,
            msgtype,
            log_ns,
            dataclasses.replace(msg, header=dataclasses.replace(header, stamp=new_stamp)),
        )

    return edit


def _msgtype_of(msg: Any) -> str:
    """``sensor_msgs/msg/Imu`` from a rosbags message class named ``sensor_msgs__msg__Imu``."""
    return type(msg).__name__.replace("__", "/")


def second_cloud(
    topic: str = "/points_raw", source: str = "/points", keep: float = 0.5, seed: int = 0
) -> Edit:
    """A second PointCloud2 topic with ``keep`` of each scan's points (a filtered copy that
    the busiest-topic rule would not choose) next to ``source``."""
    rng = np.random.default_rng(seed)

    def edit(t: str, i: int, log_ns: int, msg: Any) -> list | None:
        if t != source:
            return None
        n = int(msg.width) * int(msg.height)
        rows = np.frombuffer(bytes(msg.data), np.uint8).reshape(n, int(msg.point_step))
        picked = rows[np.sort(rng.choice(n, int(keep * n), replace=False))]
        copy = dataclasses.replace(
            msg,
            width=len(picked),
            height=1,
            row_step=len(picked) * int(msg.point_step),
            data=picked.ravel().copy(),
        )
        return [(t, POINTCLOUD2, log_ns, msg), (topic, POINTCLOUD2, log_ns + 1000, copy)]

    return edit


def chain(*edits: Edit) -> Edit:
    """Edits applied one after the other to each message (the first that changes it wins)."""

    def edit(t: str, i: int, log_ns: int, msg: Any) -> list | None:
        for e in edits:
            out = e(t, i, log_ns, msg)
            if out is not None:
                return out
        return None

    return edit
