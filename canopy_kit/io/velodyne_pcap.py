"""Velodyne VLP-16 captures (classic libpcap files of the sensor's UDP packets) as scans.

The packets are decoded by :mod:`canopy_kit.io.velodyne` (also VLP-32C and HDL-32E): on a
VLP-16 a point's time is ``packet time + block × 110.592 µs + firing × 55.296 µs + laser ×
2.304 µs`` and its azimuth is interpolated within the block by that time. Point times are
the sensor's clock (µs past the hour, counted on across its hourly restarts) on the hour
nearest the first packet's capture time; coordinates are in Velodyne's (and VeloView's)
frame, azimuth 0 along +y; ``ring`` is the laser id. Scans are full rotations, split where
the azimuth wraps past 0°; zero ranges (no return) are dropped.

Checked against VeloView's export of frame 0 of a real capture (tests/test_velodyne_pcap.py).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from canopy_kit.errors import InputError
from canopy_kit.io.bag import Scan
from canopy_kit.io.clouds import check_input_file
from canopy_kit.io.velodyne import (
    DATA_PACKET_BYTES,
    HOUR_US,
    RETURN_MODES,
    SLOTS,
    decode_packets,
    hour_base,
    xyz_from,
)

PCAP_MAGICS = {  # magic bytes -> (byte order, timestamp fraction unit in seconds)
    b"\xd4\xc3\xb2\xa1": ("<", 1e-6),
    b"\xa1\xb2\xc3\xd4": (">", 1e-6),
    b"\x4d\x3c\xb2\xa1": ("<", 1e-9),
    b"\xa1\xb2\x3c\x4d": (">", 1e-9),
}
LINKTYPE_ETHERNET = 1
DATA_PORT = 2368
POSITION_PORT = 8308
BATCH_PACKETS = 512


def _udp_packets(fh: BinaryIO, path: Path) -> Iterator[tuple[float, int, bytes]]:
    """(capture time s, destination port, UDP payload) of each IPv4/UDP packet in a pcap."""
    head = fh.read(24)
    if len(head) < 24 or head[:4] not in PCAP_MAGICS:
        raise InputError(f"{path}: not a classic pcap file (bad magic number)")
    order, frac = PCAP_MAGICS[head[:4]]
    linktype = struct.unpack(order + "I", head[20:24])[0] & 0x0FFFFFFF
    if linktype != LINKTYPE_ETHERNET:
        raise InputError(f"{path}: pcap link type {linktype} is not Ethernet")
    record = struct.Struct(order + "IIII")
    while True:
        rec = fh.read(16)
        if not rec:
            return
        if len(rec) < 16:
            raise InputError(f"{path}: pcap file is truncated (partial record header)")
        sec, sub, incl, _ = record.unpack(rec)
        frame = fh.read(incl)
        if len(frame) < incl:
            raise InputError(f"{path}: pcap file is truncated (packet of {incl} bytes cut short)")
        payload = _ipv4_udp_payload(frame)
        if payload is not None:
            yield sec + sub * frac, payload[0], payload[1]


def _ipv4_udp_payload(frame: bytes) -> tuple[int, bytes] | None:
    """(destination port, payload) of an Ethernet/IPv4/UDP frame, else None."""
    offset, ethertype = 14, frame[12:14]
    while ethertype == b"\x81\x00" and len(frame) >= offset + 4:  # 802.1Q VLAN tags
        ethertype, offset = frame[offset + 2 : offset + 4], offset + 4
    if ethertype != b"\x08\x00" or len(frame) < offset + 20:
        return None
    ihl = (frame[offset] & 0x0F) * 4
    fragment = struct.unpack(">H", frame[offset + 6 : offset + 8])[0] & 0x3FFF
    if frame[offset + 9] != 17 or fragment:  # not UDP, or an IP fragment
        return None
    udp = offset + ihl
    if len(frame) < udp + 8:
        return None
    port, length = struct.unpack(">HH", frame[udp + 2 : udp + 6])
    return port, frame[udp + 8 : udp + length]


def _points_to_scan(points: dict[str, np.ndarray], base: float, index: int) -> Scan:
    keep = points["distance"] > 0
    d = points["distance"][keep]
    xyz = xyz_from(points["azimuth"][keep], points["elevation"][keep], d, "velodyne")
    times = base + points["time_us"][keep] * 1e-6
    fields = {
        "intensity": points["intensity"][keep],
        "ring": points["laser"][keep],
        "azimuth_deg": points["azimuth"][keep] * 0.01,
        "distance_m": d,
        "timestamp_us": np.mod(points["time_us"][keep], HOUR_US),  # µs past the hour, as counted
    }
    stamp = float(times[0]) if len(times) else base
    return Scan(stamp, xyz, fields, times, "velodyne", index)


def _concat(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: np.concatenate([a[k], b[k]]) for k in b} if a else b


def _take(points: dict[str, np.ndarray], sl: slice) -> dict[str, np.ndarray]:
    return {k: v[sl] for k, v in points.items()}


def scans(path: str | Path) -> Iterator[Scan]:
    """Stream the rotations of a VLP-16 pcap as Scans (sensor frame, absolute UTC times).

    The first and last scans are usually partial rotations (the capture starts and stops
    mid-turn); ``scan.fields['azimuth_deg']`` shows how much of the circle each covers.
    """
    path = check_input_file(path, "pcap file")
    buffer: dict[str, np.ndarray] = {}
    base: float | None = None
    index = decoded = hours = 0
    last_counter: float | None = None  # the previous batch's last packet counter
    with path.open("rb") as fh:
        batch: list[bytes] = []
        packets = _udp_packets(fh, path)
        exhausted = False
        while not exhausted:
            exhausted = True
            for capture, port, payload in packets:
                if port == DATA_PORT and len(payload) == DATA_PACKET_BYTES:
                    if base is None:
                        base = hour_base(capture, struct.unpack("<I", payload[1200:1204])[0])
                    batch.append(payload)
                    if len(batch) > BATCH_PACKETS:
                        exhausted = False
                        break
            if not batch:
                break
            # a batch's last packet waits for the next batch: the block before it steps towards it
            ready, batch = (batch, []) if exhausted else (batch[:-1], batch[-1:])
            following = None if exhausted else struct.unpack("<H", batch[0][2:4])[0]
            points = decode_packets(ready, str(path), decoded, following)
            decoded += len(ready)
            # the sensor's counter restarts every hour: count on from the first packet's hour
            counter = points["time_us"][::SLOTS]
            previous = counter[0] if last_counter is None else last_counter
            restarts = hours + np.cumsum(np.diff(counter, prepend=previous) < -HOUR_US / 2)
            hours, last_counter = int(restarts[-1]), float(counter[-1])
            points["time_us"] = points["time_us"] + float(HOUR_US) * restarts[points["packet"]]
            buffer = _concat(buffer, points)
            wraps = np.flatnonzero(np.diff(buffer["azimuth"]) < -18000.0) + 1
            start = 0
            for cut in wraps:
                yield _points_to_scan(_take(buffer, slice(start, cut)), base or 0.0, index)
                index, start = index + 1, cut
            buffer = _take(buffer, slice(start, None))
    if buffer and len(buffer["azimuth"]):
        yield _points_to_scan(buffer, base or 0.0, index)
    elif base is None:
        raise InputError(f"{path}: no VLP-16 data packets (UDP port {DATA_PORT}, 1206 bytes)")


def describe_pcap(path: str | Path) -> dict[str, Any]:
    """Packet counts, time span, sensor and return mode, rotations and points of a capture."""
    path = check_input_file(path, "pcap file")
    counts = {"data": 0, "position": 0, "other": 0}
    first = last = None
    modes: set[str] = set()
    with path.open("rb") as fh:
        for capture, port, payload in _udp_packets(fh, path):
            first = capture if first is None else first
            last = capture
            if port == DATA_PORT and len(payload) == DATA_PACKET_BYTES:
                counts["data"] += 1
                modes.add(RETURN_MODES.get(payload[1204], hex(payload[1204])))
            elif port == POSITION_PORT:
                counts["position"] += 1
            else:
                counts["other"] += 1
    rotations = points = 0
    sensor_first = sensor_last = None
    for scan in scans(path):
        rotations, points = rotations + 1, points + len(scan)
        if len(scan):
            sensor_first = scan.times[0] if sensor_first is None else sensor_first
            sensor_last = scan.times[-1]

    def iso(t: float | None) -> str | None:
        return None if t is None else datetime.fromtimestamp(t, UTC).isoformat()

    return {
        "path": str(path),
        "format": "Velodyne VLP-16 pcap",
        "start_time": first,
        "end_time": last,
        "start_utc": iso(first),
        "duration_s": (last - first) if first is not None else 0.0,
        # the sensor's own (usually GPS-synchronised) clock, which point times use
        "sensor_start_utc": iso(sensor_first),
        "sensor_end_utc": iso(sensor_last),
        "data_packets": counts["data"],
        "position_packets": counts["position"],
        "other_packets": counts["other"],
        "return_mode": ", ".join(sorted(modes)),
        "scans": rotations,
        "points": points,
    }


class VelodynePcapReader:
    """Reader plugin for VLP-16 pcap captures (``canopy_kit.readers`` entry point ``velodyne_pcap``)."""

    name = "velodyne_pcap"
    kind = "scans"
    suffixes = (".pcap",)

    def sniff(self, path: Path) -> bool:
        """True for a classic pcap file."""
        path = Path(path)
        if not path.is_file():
            return False
        with path.open("rb") as fh:
            return fh.read(4) in PCAP_MAGICS

    def describe(self, path: Path) -> dict[str, Any]:
        """Packet counts, time span, return mode, rotations and points."""
        return describe_pcap(path)

    def scans(self, path: Path) -> Iterator[Scan]:
        """Stream full rotations as Scans."""
        return scans(path)
