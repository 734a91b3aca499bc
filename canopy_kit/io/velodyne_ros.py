"""``velodyne_msgs/VelodyneScan`` messages (the ROS driver's raw packets) as :class:`Scan`\\ s.

The driver puts about one rotation in each message (some 75 packets of a VLP-16 at 10 Hz)
and stamps each packet; the header stamp is the first or the last packet's, depending on the
driver's version, so it is not used. One message becomes one Scan, decoded by
:mod:`canopy_kit.io.velodyne` into what ``velodyne_pointcloud`` would publish for it:

- coordinates in the driver's REP 103 frame (x along azimuth 0, the sensor's front; y left;
  z up), which ``header.frame_id`` and any ``/tf_static`` extrinsic refer to (the pcap reader
  keeps VeloView's frame, rotated 90° from it);
- fields ``intensity`` (float32), ``ring`` (uint16, 0 = lowest beam) and ``time`` (float32 s
  after the scan's stamp, its first point);
- absolute point times on the bag's clock: the sensor's microsecond counter times every
  return precisely, and the median difference between the packets' stamps and their
  counters puts it on the clock the IMU and GNSS messages use (a packet's stamp taken as the
  time of its first firing, as ``velodyne_pointcloud`` does). With a free-running (not GPS
  synchronised) sensor the counter alone would be up to half an hour off.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from canopy_kit.errors import InputError, MessageError
from canopy_kit.io.bag import VELODYNE_SCAN, Scan
from canopy_kit.io.ros_types import register_missing
from canopy_kit.io.velodyne import (
    DATA_PACKET_BYTES,
    HOUR_US,
    decode_array,
    hour_base,
    packet_array,
    xyz_from,
)

VELODYNE_PACKET = "velodyne_msgs/msg/VelodynePacket"
# velodyne_msgs as the ROS 1 and ROS 2 drivers define them (the same fields: ROS 1 md5sums
# 50804fc9... and ae4f90a2..., the ones real bags carry).
MESSAGE_DEFINITIONS = {
    VELODYNE_PACKET: "builtin_interfaces/Time stamp\nuint8[1206] data\n",
    VELODYNE_SCAN: "std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets\n",
}


def register_velodyne_types(typestore: Any) -> None:
    """Add the velodyne_msgs types a rosbags typestore lacks (rosbags ships none of them)."""
    register_missing(typestore, MESSAGE_DEFINITIONS)


def _seconds(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def scan_from_message(msg: Any, where: str, index: int) -> Scan:
    """One VelodyneScan message as a Scan; ``where`` (bag, topic, message) starts any error."""
    packets = list(msg.packets)
    for k, packet in enumerate(packets):
        if len(packet.data) != DATA_PACKET_BYTES:
            raise MessageError(
                f"{where}: packet {k} has {len(packet.data)} bytes; a Velodyne data "
                f"packet has {DATA_PACKET_BYTES}"
            )
    stamps = np.array([_seconds(p.stamp) for p in packets], np.float64)
    data = b"".join(np.asarray(p.data, np.uint8).tobytes() for p in packets)
    try:
        return scan_from_packets(
            stamps, data, msg.header.frame_id, where, index, header_stamp=_seconds(msg.header.stamp)
        )
    except InputError as exc:  # a packet that is not a Velodyne data packet: this message only
        raise MessageError(str(exc)) from None


def scan_from_packets(
    stamps: np.ndarray,
    data: bytes,
    frame_id: str,
    where: str,
    index: int,
    header_stamp: float | None = None,
) -> Scan:
    """A Scan from packet stamps (s, bag clock) and the packets' bytes (see the module notes)."""
    packets = packet_array(data, where)
    if len(packets) == 0:
        stamp = header_stamp if header_stamp is not None else 0.0
        empty = {
            "intensity": np.zeros(0, np.float32),
            "ring": np.zeros(0, np.uint16),
            "time": np.zeros(0, np.float32),
        }
        return Scan(stamp, np.zeros((0, 3)), empty, np.zeros(0), frame_id, index)
    points = decode_array(packets, returns_only=True)
    counter = packets["timestamp"].astype(np.float64)  # µs past the hour
    # the counter restarts every hour: count the restarts within the message
    hours = np.concatenate([[0], np.cumsum(np.diff(counter) < -HOUR_US / 2)]) * float(HOUR_US)
    base = hour_base(float(stamps[0]), float(counter[0]))
    clock_offset = float(np.median(stamps - (base + (counter + hours) * 1e-6)))
    times = base + clock_offset + (points["time_us"] + hours[points["packet"]]) * 1e-6
    xyz = xyz_from(points["azimuth"], points["elevation"], points["distance"], "ros")
    stamp = (
        float(times[0]) if len(times) else base + clock_offset + float(counter[0] + hours[0]) * 1e-6
    )
    fields = {
        "intensity": points["intensity"].astype(np.float32),
        "ring": points["ring"],
        "time": (times - stamp).astype(np.float32),
    }
    return Scan(stamp, xyz, fields, times, frame_id, index)
