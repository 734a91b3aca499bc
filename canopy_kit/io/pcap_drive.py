"""A Velodyne VLP-16 pcap drive (plus an optional GNSS track file) turned into a ROS1 bag
that the normal pipeline maps.

Design: an import step, not a second source type for the mapping stage. The capture's
data packets become ``velodyne_msgs/VelodyneScan`` messages (one per rotation) and the
track's fixes ``sensor_msgs/NavSatFix`` messages, in a ROS1 bag in the run's cache folder
(``out/.cache/pcap_import/``, reused while the pcap, track and settings are unchanged).
Every reader, check, rig and fusion path of the mapping stage then works on a pcap drive as
on a bag, with no second code path to keep in step.

Time: each packet's time is its µs-past-the-hour counter on the UTC hour that the first
position packet's ``$GPRMC`` gives (the sensor takes its clock from that receiver), else the
hour nearest the capture time. Packet stamps are written as exactly those times, so the
bag reader's stamp-to-counter offset is zero. Both sensors are written in one frame
(``velodyne``): give a rig (``--rig``) for a GNSS antenna away from the LiDAR.
"""

from __future__ import annotations

import hashlib
import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.errors import InputError
from canopy_kit.io.clouds import check_input_file
from canopy_kit.io.gnss_track import GnssTrack, read_gnss_track
from canopy_kit.io.nmea import parse_rmc
from canopy_kit.io.velodyne import DATA_PACKET_BYTES, HOUR_US, hour_base
from canopy_kit.io.velodyne_pcap import DATA_PORT, PCAP_MAGICS, POSITION_PORT, _udp_packets

SCAN_TOPIC = "/velodyne_packets"
GNSS_TOPIC = "/gnss/fix"
FRAME = "velodyne"
MIN_DRIVE_S = 10.0  # shorter captures cannot show trees from both sides or close a pass
MIN_TRAVEL_M = 5.0  # a drive must pass at least a tree spacing or two
STILL_M = 0.05  # scans whose points lie this close to another scan's were taken in one place
STILL_SHARE = 0.8  # ... for this share of their points (measured 0.95 on the stationary sample)
CRS_CHECK_M = 500.0  # track vs the capture's $GPRMC position: further means a wrong CRS
IMPORT_VERSION = 1  # bump when the bag layout changes: cached imports are remade


def is_pcap(path: str | Path) -> bool:
    """True for an existing classic libpcap file (by its magic number)."""
    path = Path(path)
    if not path.is_file():
        return False
    with path.open("rb") as fh:
        return fh.read(4) in PCAP_MAGICS


@dataclass
class PcapDrive:
    """A capture's data packets by their UTC times and first azimuths (the payloads stay in
    the file: :meth:`payloads` reads them again, so a drive of hours fits in memory), and
    its $GPRMC fixes."""

    path: Path
    packet_times: np.ndarray  # UTC epoch s of each data packet (its counter on the UTC hour)
    azimuth: np.ndarray  # each data packet's first block azimuth, 0.01 degree
    rmc: np.ndarray  # (K, 3) UTC epoch s, latitude, longitude of the position packets' fixes
    clock: str  # "gprmc" or "capture time"
    capture_start: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def duration(self) -> float:
        return float(self.packet_times[-1] - self.packet_times[0]) if len(self.azimuth) else 0.0

    @property
    def rotation_starts(self) -> np.ndarray:
        """Index of each packet whose first block's azimuth wrapped past 0° (plus 0)."""
        wraps = np.flatnonzero(np.diff(self.azimuth) < -18000.0) + 1
        return np.concatenate([[0], wraps]).astype(int)

    @property
    def rotations(self) -> int:
        return len(self.rotation_starts)

    def payloads(self) -> Iterator[bytes]:
        """The data packets' 1206-byte payloads, in capture order."""
        with self.path.open("rb") as fh:
            for _, port, payload in _udp_packets(fh, self.path):
                if port == DATA_PORT and len(payload) == DATA_PACKET_BYTES:
                    yield bytes(payload)


def _nmea_in(payload: bytes) -> str | None:
    start = payload.find(b"$G")
    if start < 0:
        return None
    end = len(payload)
    for stop in (b"\r", b"\n", b"\x00"):
        k = payload.find(stop, start)
        if k >= 0:
            end = min(end, k)
    return payload[start:end].decode("ascii", errors="replace")


def read_pcap_drive(path: str | Path) -> PcapDrive:
    """Every VLP-16 data packet's UTC time and first azimuth, and the $GPRMC fixes."""
    path = check_input_file(path, "pcap file")
    captures, counters, azimuths, rmc = [], [], [], []
    with path.open("rb") as fh:
        for capture, port, payload in _udp_packets(fh, path):
            if port == DATA_PORT and len(payload) == DATA_PACKET_BYTES:
                captures.append(capture)
                counters.append(struct.unpack("<I", payload[1200:1204])[0])
                azimuths.append(struct.unpack("<H", payload[2:4])[0])
            elif port == POSITION_PORT:
                sentence = _nmea_in(payload)
                fix = parse_rmc(sentence) if sentence and sentence[3:6] == "RMC" else None
                if fix is not None:
                    rmc.append(fix)
    if not counters:
        raise InputError(f"{path}: no VLP-16 data packets (UDP port {DATA_PORT}, 1206 bytes)")
    counter = np.asarray(counters, float)
    # the counter restarts every hour: count on from the first packet's hour
    counter += HOUR_US * np.cumsum(np.diff(counter, prepend=counter[0]) < -HOUR_US / 2)
    clock = "gprmc" if rmc else "capture time"
    reference = rmc[0][0] if rmc else captures[0]
    times = hour_base(reference, counter[0]) + counter * 1e-6
    return PcapDrive(
        path, times, np.asarray(azimuths, float), np.asarray(rmc).reshape(-1, 3), clock, captures[0]
    )


def track_for(
    drive: PcapDrive, track: str | Path, crs: int | str | None, time_scale: str
) -> tuple[GnssTrack, list[str]]:
    """The track read on the capture's date, checked against the capture's time and place."""
    notes = []
    if crs is None and len(drive.rmc):
        from canopy_kit.core.geo import utm_epsg

        crs = utm_epsg(float(drive.rmc[0, 1]), float(drive.rmc[0, 2]))
        notes.append(
            f"--gnss-crs not given: easting/northing (if any) read as EPSG:{crs}, the WGS84 UTM "
            "zone of the capture's $GPRMC position"
        )
    got = read_gnss_track(track, crs, drive.packet_times[0], time_scale)
    t = got.fixes.t
    start, end = drive.packet_times[0], drive.packet_times[-1]
    inside = (t >= start - 1.0) & (t <= end + 1.0)
    if inside.sum() < 2:
        from datetime import UTC, datetime

        def iso(x: float) -> str:
            return datetime.fromtimestamp(x, UTC).isoformat(timespec="seconds")

        raise InputError(
            f"{got.path}: the track ({iso(t[0])} to {iso(t[-1])} UTC, read as {time_scale.upper()}"
            f") does not cover the capture {drive.path.name} ({iso(start)} to {iso(end)} UTC)"
        )
    if len(drive.rmc):
        from canopy_kit.core.geo import LocalFrame

        lat, lon = float(drive.rmc[0, 1]), float(drive.rmc[0, 2])
        i = int(np.argmin(np.abs(t - drive.rmc[0, 0])))
        local = LocalFrame.at(lat, lon).to_local(
            got.fixes.latitude[i : i + 1], got.fixes.longitude[i : i + 1]
        )
        distance = float(np.hypot(*local[0, :2]))
        if distance > CRS_CHECK_M:
            line = f", line {got.lines[i]}" if got.lines[i] else ""
            raise InputError(
                f"{got.path}{line}: this fix lies {distance / 1000:.1f} km from the position "
                f"the capture's $GPRMC gives ({lat:.5f}, {lon:.5f}): is the track's CRS "
                f"({got.crs}) right?"
            )
    return got, notes


def check_drive_length(drive: PcapDrive, track: GnssTrack | None) -> None:
    """Raise when the capture is too short, or the track shows it standing still."""
    duration, rotations = drive.duration, drive.rotations
    travel = None
    if track is not None:
        from canopy_kit.core.geo import LocalFrame

        f = track.fixes
        inside = (f.t >= drive.packet_times[0]) & (f.t <= drive.packet_times[-1])
        if inside.sum() >= 2:
            frame = LocalFrame.at(float(f.latitude[inside][0]), float(f.longitude[inside][0]))
            xy = frame.to_local(f.latitude[inside], f.longitude[inside])[:, :2]
            # the extent, not the path length: a still receiver's noise adds up along a path
            travel = float(np.linalg.norm(xy.max(axis=0) - xy.min(axis=0)))
    moved = f", the GNSS track spans {travel:.2f} m during it" if travel is not None else ""
    if travel is None and duration >= MIN_DRIVE_S and standing_still(drive):
        moved = (
            f"; its first, middle and last rotations coincide ({100 * STILL_SHARE:.0f} % of "
            f"points within {100 * STILL_M:.0f} cm): the sensor stood still"
        )
        travel = 0.0
    if duration < MIN_DRIVE_S or (travel is not None and travel < MIN_TRAVEL_M):
        raise InputError(
            f"{drive.path}: the capture is {duration:.2f} s long ({rotations} rotations){moved}; "
            f"mapping needs a drive of at least {MIN_DRIVE_S:.0f} s covering at least "
            f"{MIN_TRAVEL_M:.0f} m along the rows (this looks like a sample or a stationary "
            "stretch: `canopy-kit info` describes it)"
        )


def standing_still(drive: PcapDrive) -> bool:
    """True when the first, middle and last full rotations were scanned from one place (the
    drive has no track to tell): most of their points within :data:`STILL_M` of the first's."""
    from scipy.spatial import cKDTree

    from canopy_kit.io.velodyne_ros import scan_from_packets

    starts = drive.rotation_starts
    if len(starts) < 4:
        return False
    picks = {1, len(starts) // 2, len(starts) - 2}
    wanted = {k: [] for k in picks}  # rotation -> its payloads
    owner = np.searchsorted(starts, np.arange(len(drive.azimuth)), side="right") - 1
    for i, payload in enumerate(drive.payloads()):
        if owner[i] in wanted:
            wanted[owner[i]].append(payload)

    def rotation(k: int) -> np.ndarray:
        a = starts[k]
        data = wanted[k]
        scan = scan_from_packets(
            drive.packet_times[a : a + len(data)], b"".join(data), FRAME, str(drive.path), k
        )
        near = np.linalg.norm(scan.xyz, axis=1) < 30.0
        return scan.xyz[near]

    first = rotation(1)
    if len(first) < 100:
        return False
    tree = cKDTree(first)
    for k in (len(starts) // 2, len(starts) - 2):
        other = rotation(k)
        if len(other) < 100 or np.mean(tree.query(other)[0] < STILL_M) < STILL_SHARE:
            return False
    return True


def import_key(pcap: Path, track: Path | None, crs: Any, time_scale: str) -> str:
    """A short hash of what the imported bag depends on (files by path, size and mtime, as
    canopy_kit.core.cache fingerprints inputs)."""

    def fingerprint(p: Path) -> list:
        st = p.resolve().stat()
        return [str(p.resolve()), st.st_size, st.st_mtime_ns]

    parts = {
        "pcap": fingerprint(pcap),
        "track": fingerprint(track) if track is not None else None,
        "crs": str(crs),
        "time_scale": time_scale,
        "version": IMPORT_VERSION,
    }
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


def import_pcap_drive(
    pcap: str | Path,
    cache_dir: str | Path,
    track: str | Path | None = None,
    crs: int | str | None = None,
    time_scale: str = "utc",
) -> tuple[Path, dict[str, Any]]:
    """The ROS1 bag of a pcap drive (made in ``cache_dir`` unless already there) and what
    was read: ``{"pcap", "gnss_track", "gnss_crs", "time_scale", "clock", "notes"}``.

    Checks the capture's length and the track before anything is written.
    """
    pcap = Path(pcap)
    drive = read_pcap_drive(pcap)
    got, notes = (None, []) if track is None else track_for(drive, track, crs, time_scale)
    check_drive_length(drive, got)
    info = {
        "pcap": pcap.name,
        "pcap_duration_s": round(drive.duration, 3),
        "clock": drive.clock,
        "gnss_track": Path(track).name if track is not None else "",
        "gnss_track_format": got.format if got is not None else "",
        "gnss_crs": got.crs if got is not None else "",
        "gnss_time_scale": time_scale if got is not None else "",
        "notes": notes,
    }
    key = import_key(pcap, Path(track) if track is not None else None, crs, time_scale)
    bag = Path(cache_dir) / "pcap_import" / f"{pcap.stem}-{key}.bag"
    if not bag.exists():
        write_drive_bag(bag, drive, got)
    return bag, info


def write_drive_bag(bag: Path, drive: PcapDrive, track: GnssTrack | None) -> Path:
    """A ROS1 bag of the drive: one VelodyneScan per rotation, the fixes over the capture."""
    from canopy_kit.io.bag_writer import BagWriter

    starts = set(drive.rotation_starts.tolist())
    fixes: list[int] = []
    if track is not None:
        t = track.fixes.t
        fixes = list(
            np.flatnonzero((t >= drive.packet_times[0] - 1.0) & (t <= drive.packet_times[-1] + 1.0))
        )
    with BagWriter(bag, "ros1") as writer:
        k, first, rotation = 0, 0, []

        def flush(end: int) -> None:
            nonlocal k
            stamp = float(drive.packet_times[first])
            while k < len(fixes) and track.fixes.t[fixes[k]] < stamp:  # type: ignore[union-attr]
                _write_fix(writer, track, fixes[k])
                k += 1
            writer.write_velodyne_scan(SCAN_TOPIC, drive.packet_times[first:end], rotation, FRAME)

        for i, payload in enumerate(drive.payloads()):
            if i in starts and rotation:
                flush(i)
                first, rotation = i, []
            rotation.append(payload)
        if rotation:
            flush(first + len(rotation))
        for i in fixes[k:]:
            _write_fix(writer, track, i)
    return bag


def _write_fix(writer: Any, track: GnssTrack | None, i: int) -> None:
    f = track.fixes  # type: ignore[union-attr]
    writer.write_fix(
        GNSS_TOPIC,
        float(f.t[i]),
        float(f.latitude[i]),
        float(f.longitude[i]),
        float(f.altitude[i]),
        status=int(f.status[i]),
        frame_id=FRAME,
        covariance_type=0,  # a track file states no accuracy
    )


@dataclass(frozen=True)
class GnssTrackOption:
    """``run``'s GNSS track options for a pcap drive: the file, its CRS and time scale."""

    path: Path | None = None
    crs: int | str | None = None
    time_scale: str = "utc"


def drive_input(
    source: Path, cache_dir: Path, gnss: GnssTrackOption | None
) -> tuple[Path, dict[str, Any]]:
    """The bag to map for ``source``: a pcap imported (:func:`import_pcap_drive`) with its
    provenance entries, any other input unchanged with none. A GNSS track or CRS given for
    a bag is an InputError (a bag carries its own GNSS)."""
    gnss = gnss or GnssTrackOption()
    if not is_pcap(source):
        if gnss.path is not None or gnss.crs is not None:
            raise InputError(
                f"--gnss/--gnss-crs: only a pcap capture takes a GNSS track file; {source} is "
                "not one (a bag's GNSS comes from its NavSatFix topic)"
            )
        return source, {}
    bag, info = import_pcap_drive(source, cache_dir, gnss.path, gnss.crs, gnss.time_scale)
    if gnss.path is not None:
        info["gnss_track_sha256"] = hashlib.sha256(Path(gnss.path).read_bytes()).hexdigest()
    return bag, {"pcap_import": info}
