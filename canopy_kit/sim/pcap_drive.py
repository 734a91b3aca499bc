"""A simulated VLP-16 drive written as a real capture would be: a libpcap file of the sensor's
UDP packets and a GNSS track file beside it.

The packets are the simulator's own (``lidar.output = "velodyne_packets"``, a session's
``velodyne_msgs/VelodyneScan`` topic); each is framed as Ethernet/IPv4/UDP to port 2368 and
captured at its first firing's time. A position packet (512 bytes, port 8308; the $GPRMC
sentence at byte 206 and the counter at byte 198, VLP-16 manual §9.3) goes out every
``POSITION_EVERY_S``. The track is the session's GNSS fixes: ``mtls`` (the LFuji-air text
layout: hhmmss.ss time of day, an unused column, easting, northing, height in UTM, an unused
column), ``csv`` (header time,lat,lon,height, Unix seconds), ``nmea`` ($GPGGA + $GPRMC) or
``gpx``. The session folder keeps its truth, so a run of the pcap is judged with ``--truth``.
"""

from __future__ import annotations

import struct
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from canopy_kit.core.atomic import atomic_write_text
from canopy_kit.errors import InputError
from canopy_kit.io.bag import VELODYNE_SCAN, GnssSeries, open_bag

POSITION_EVERY_S = 0.1
DATA_PORT, POSITION_PORT = 2368, 8308
TRACK_FORMATS = ("mtls", "csv", "nmea", "gpx")


def _udp_frame(payload: bytes, port: int) -> bytes:
    """Ethernet/IPv4/UDP frame from 192.168.1.201:port to 255.255.255.255:port."""
    udp = struct.pack(">HHHH", port, port, 8 + len(payload), 0) + payload
    total = 20 + len(udp)
    ip = struct.pack(
        ">BBHHHBBH4s4s",
        0x45,
        0,
        total,
        0,
        0x4000,
        64,
        17,
        0,
        bytes([192, 168, 1, 201]),
        b"\xff" * 4,
    )
    words = struct.unpack(">10H", ip)
    checksum = sum(words)
    checksum = (checksum & 0xFFFF) + (checksum >> 16)
    ip = ip[:10] + struct.pack(">H", ~checksum & 0xFFFF) + ip[12:]
    ether = b"\xff" * 6 + bytes([0x60, 0x76, 0x88, 0x00, 0x00, 0x00]) + b"\x08\x00"
    return ether + ip + udp


def _record(t: float, frame: bytes) -> bytes:
    sec = int(np.floor(t))
    usec = min(int(round((t - sec) * 1e6)), 999_999)
    return struct.pack("<IIII", sec, usec, len(frame), len(frame)) + frame


def _nmea(body: str) -> str:
    value = 0
    for ch in body:
        value ^= ord(ch)
    return f"${body}*{value:02X}"


def _dm(value: float, lat: bool) -> tuple[str, str]:
    hemi = ("N" if value >= 0 else "S") if lat else ("E" if value >= 0 else "W")
    value = abs(value)
    deg = int(value)
    minutes = (value - deg) * 60.0
    return (f"{deg:02d}{minutes:07.4f}" if lat else f"{deg:03d}{minutes:07.4f}"), hemi


def gprmc(t: float, lat: float, lon: float) -> str:
    """A $GPRMC sentence (status A) for UTC epoch second ``t`` at (lat, lon)."""
    d = datetime.fromtimestamp(t, UTC)
    la, lh = _dm(lat, True)
    lo, oh = _dm(lon, False)
    return _nmea(
        f"GPRMC,{d:%H%M%S}.{d.microsecond // 10000:02d},A,{la},{lh},{lo},{oh},0.0,0.0,"
        f"{d:%d%m%y},,,A"
    )


def gpgga(t: float, lat: float, lon: float, height: float) -> str:
    """A $GPGGA sentence (fix quality 1, geoid separation 0) for UTC epoch second ``t``."""
    d = datetime.fromtimestamp(t, UTC)
    la, lh = _dm(lat, True)
    lo, oh = _dm(lon, False)
    return _nmea(
        f"GPGGA,{d:%H%M%S}.{d.microsecond // 10000:02d},{la},{lh},{lo},{oh},1,12,0.8,"
        f"{height:.3f},M,0.0,M,,"
    )


def _position_packet(t: float, lat: float, lon: float) -> bytes:
    payload = bytearray(512)
    counter = int(round((t - np.floor(t / 3600.0) * 3600.0) * 1e6))
    payload[198:202] = struct.pack("<I", counter)
    payload[202] = 2  # PPS locked
    sentence = (gprmc(t, lat, lon) + "\r\n").encode("ascii")
    payload[206 : 206 + len(sentence)] = sentence
    return bytes(payload)


def _read_session(bag_path: Path) -> tuple[list[tuple[float, bytes]], GnssSeries | None]:
    packets: list[tuple[float, bytes]] = []
    with open_bag(bag_path) as bag:
        topic = bag.find_topic(VELODYNE_SCAN)
        assert topic is not None
        for _, msg in bag._messages(topic):
            for p in msg.packets:
                nanos = getattr(p.stamp, "nanosec", getattr(p.stamp, "nsec", 0))
                stamp = p.stamp.sec + nanos * 1e-9
                packets.append((stamp, bytes(np.asarray(p.data, np.uint8))))
        gnss = bag.gnss()
    return packets, gnss


def write_pcap(
    path: str | Path, packets: list[tuple[float, bytes]], gnss: GnssSeries | None
) -> Path:
    """A classic libpcap file (µs, Ethernet) of the data packets and position packets."""
    path = Path(path)
    if not packets:
        raise InputError(f"{path}: no packets to write")
    t0, t1 = packets[0][0], packets[-1][0]
    records: list[tuple[float, int, bytes]] = [(t, DATA_PORT, p) for t, p in packets]
    if gnss is not None and len(gnss.t):
        ok = np.isfinite(gnss.latitude)
        for t in np.arange(t0, t1, POSITION_EVERY_S):
            i = int(np.clip(np.searchsorted(gnss.t[ok], t), 0, ok.sum() - 1))
            lat, lon = gnss.latitude[ok][i], gnss.longitude[ok][i]
            records.append((float(t), POSITION_PORT, _position_packet(float(t), lat, lon)))
    records.sort(key=lambda r: r[0])
    header = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)
    tmp = path.with_name(f".{path.name}.partial")
    with tmp.open("wb") as fh:
        fh.write(header)
        for t, port, payload in records:
            fh.write(_record(t, _udp_frame(payload, port)))
    tmp.replace(path)
    return path


def write_track(
    path: str | Path, gnss: GnssSeries, fmt: str = "mtls", time_scale: str = "utc"
) -> Path:
    """The fixes as a track file of ``fmt`` (see the module docstring); ``time_scale`` gps
    writes the mtls time of day on GPS time (UTC + leap seconds)."""
    from canopy_kit.core.geo import LocalFrame
    from canopy_kit.io.gnss_track import leap_seconds

    if fmt not in TRACK_FORMATS:
        raise InputError(f"track format {fmt!r} is not one of {', '.join(TRACK_FORMATS)}")
    ok = np.isfinite(gnss.latitude) & (gnss.status >= 0)
    t, lat, lon, h = gnss.t[ok], gnss.latitude[ok], gnss.longitude[ok], gnss.altitude[ok]
    lines: list[str] = []
    if fmt == "mtls":
        frame = LocalFrame.at(float(lat[0]), float(lon[0]))
        enu = frame.to_local(lat, lon, h) + frame.origin
        shift = leap_seconds(float(t[0])) if time_scale == "gps" else 0
        for ti, (e, n, z) in zip(t, enu, strict=True):
            d = datetime.fromtimestamp(ti + shift, UTC)
            tod = d.hour * 10000 + d.minute * 100 + d.second + d.microsecond * 1e-6
            lines.append(f"{tod:.8f}\t{tod:.8f}\t{e:.8f}\t{n:.8f}\t{z:.8f}\t{tod:.8f}")
    elif fmt == "csv":
        lines.append("time,lat,lon,height")
        lines += [f"{a:.6f},{b:.9f},{c:.9f},{d:.4f}" for a, b, c, d in zip(t, lat, lon, h)]
    elif fmt == "nmea":
        for a, b, c, d in zip(t, lat, lon, h):
            lines += [gpgga(a, b, c, d), gprmc(a, b, c)]
    else:
        lines.append('<?xml version="1.0" encoding="UTF-8"?>')
        lines.append(
            '<gpx version="1.1" creator="canopy-kit" xmlns="http://www.topografix.com/GPX/1/1">'
        )
        lines.append("<trk><trkseg>")
        for a, b, c, d in zip(t, lat, lon, h):
            when = datetime.fromtimestamp(a, UTC).isoformat(timespec="microseconds")
            lines.append(
                f'<trkpt lat="{b:.9f}" lon="{c:.9f}"><ele>{d:.4f}</ele><time>{when}</time></trkpt>'
            )
        lines.append("</trkseg></trk></gpx>")
    return atomic_write_text(Path(path), "\n".join(lines) + "\n")


def export_pcap_drive(
    session_bag: str | Path,
    out_dir: str | Path,
    track_formats: tuple[str, ...] = ("mtls",),
    time_scale: str = "utc",
) -> dict[str, Path]:
    """Write a simulated session (raw VLP-16 packets + GNSS) as ``drive.pcap`` and its track
    files (``track.txt`` mtls, ``track.csv``, ``track.nmea``, ``track.gpx``) in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    packets, gnss = _read_session(Path(session_bag))
    files = {"pcap": write_pcap(out / "drive.pcap", packets, gnss)}
    names = {"mtls": "track.txt", "csv": "track.csv", "nmea": "track.nmea", "gpx": "track.gpx"}
    if gnss is not None:
        for fmt in track_formats:
            files[fmt] = write_track(out / names[fmt], gnss, fmt, time_scale)
    return files
