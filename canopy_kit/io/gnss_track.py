"""GNSS tracks kept beside a capture rather than in a bag: column text, NMEA and GPX files.

:func:`read_gnss_track` returns the :class:`~canopy_kit.io.bag.GnssSeries` the mapping stage
takes from a bag's NavSatFix topic (times in UTC epoch seconds, WGS84 latitude/longitude,
height in the track's own datum, status 0 FIX, covariance unknown). Formats, by content:

- **column text** without a header (whitespace or commas): the MTLS / LFuji-air layout,
  column 1 GPS time of day as hhmmss.ss, columns 3-5 easting, northing, height in the
  projected CRS ``crs`` (an EPSG code; the file does not say which);
- **CSV with a header** naming a time column (``time``, ``t``, ``timestamp``, ``gps_time``,
  ``utc``) and either ``easting``/``northing`` (or ``e``/``n``, ``x``/``y``; with ``crs``)
  or ``lat``/``lon`` columns, plus an optional height (``height``, ``h``, ``z``, ``alt``,
  ``altitude``, ``ele``);
- **NMEA** sentences ``$GPGGA``/``$GNGGA`` (positions) and ``$GPRMC``/``$GNRMC`` (positions
  and the date);
- **GPX** ``<trkpt lat lon><ele/><time/></trkpt>`` (stdlib ElementTree).

Time rule: NMEA and GPX times are UTC. A time of day needs a date: it is taken as the day
that puts the first fix nearest ``reference_time`` (UTC epoch s, e.g. the capture's
$GPRMC), and later fixes count on across midnight. The column formats' times of day (a
numeric time column below 1e8 is read as hhmmss.ss, above as Unix epoch seconds, an ISO
8601 text column as UTC) are on the scale ``time_scale``: ``"utc"``, or ``"gps"``, which runs
ahead of UTC by the leap seconds since 1980 (:data:`GPS_UTC_LEAP_SECONDS`: 18 s from
2017-01-01): UTC = GPS - leap. The default is UTC because the one real MTLS sample says so:
its VLP-16 (clock set by the receiver's UTC $GPRMC) stands still to 6 mm over the whole
capture, as the track read as UTC does (motion starts 0.1 s after the capture ends), while
read as GPS time the track would have it moving at 0.25 m/s (docs/DATASETS.md, "Velodyne pcap drives").

Checks, each an :class:`InputError` naming the file and line: no fixes; times that go
back; a gap longer than :data:`GAP_FACTOR` × the median interval (and over 1 s); points
that the CRS puts outside its area of use (e.g. an easting beyond the zone's range).
"""

from __future__ import annotations

import csv
import io
import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from canopy_kit.errors import InputError
from canopy_kit.io.bag import GnssSeries
from canopy_kit.io.csv_table import is_number_text
from canopy_kit.io.nmea import (
    NMEA_POSITION,
    hhmmss_seconds,
    nmea_checksum_ok,
    parse_gga,
    parse_rmc,
)

__all__ = ["GnssTrack", "hhmmss_seconds", "leap_seconds", "parse_rmc", "read_gnss_track"]

# (first UTC day in force, GPS - UTC seconds): IERS Bulletin C; none announced after 2017.
GPS_UTC_LEAP_SECONDS = (
    (datetime(2006, 1, 1, tzinfo=UTC).timestamp(), 14),
    (datetime(2009, 1, 1, tzinfo=UTC).timestamp(), 15),
    (datetime(2012, 7, 1, tzinfo=UTC).timestamp(), 16),
    (datetime(2015, 7, 1, tzinfo=UTC).timestamp(), 17),
    (datetime(2017, 1, 1, tzinfo=UTC).timestamp(), 18),
)
GAP_FACTOR = 5.0
MIN_GAP_S = 1.0
DAY = 86400.0
TIME_NAMES = ("time", "t", "timestamp", "gps_time", "utc", "time_s")
EAST_NAMES = ("easting", "east", "e", "x")
NORTH_NAMES = ("northing", "north", "n", "y")
HEIGHT_NAMES = ("height", "h", "z", "alt", "altitude", "ele", "elevation")
LAT_NAMES = ("lat", "latitude")
LON_NAMES = ("lon", "lng", "long", "longitude")


@dataclass
class GnssTrack:
    """A track's fixes, what format it was read as, and the source line of each fix."""

    path: Path
    format: str  # "columns", "csv", "nmea" or "gpx"
    fixes: GnssSeries
    lines: np.ndarray  # 1-based line of each fix in the file (0 for GPX)
    crs: str  # the CRS its coordinates were given in ("EPSG:4326" for lat/lon)


def leap_seconds(utc: float) -> int:
    """GPS - UTC in seconds on the UTC epoch second ``utc`` (18 from 2017-01-01)."""
    offset = 13
    for start, leap in GPS_UTC_LEAP_SECONDS:
        if utc >= start:
            offset = leap
    return offset


def times_of_day_to_utc(
    seconds_of_day: np.ndarray, reference_time: float, gps: bool, where: str
) -> np.ndarray:
    """UTC epoch seconds of times of day, the first put on the day nearest ``reference_time``
    and later ones counted on across midnight; ``gps`` subtracts the GPS-UTC leap seconds."""
    tod = np.asarray(seconds_of_day, float)
    if len(tod) == 0:
        return tod
    unwrapped = tod + DAY * np.cumsum(np.diff(tod, prepend=tod[0]) < -DAY / 2)
    leap = leap_seconds(reference_time) if gps else 0
    midnight = np.floor(reference_time / DAY) * DAY
    first = midnight + unwrapped[0] - leap
    first += DAY * np.round((reference_time - first) / DAY)
    if not np.isfinite(first):
        raise InputError(f"{where}: time of day cannot be placed on a date")
    return first + (unwrapped - unwrapped[0])


def _need_reference(reference_time: float | None, path: Path, what: str) -> float:
    if reference_time is None:
        raise InputError(
            f"{path}: the track gives {what} without a date; its date must come from the "
            "capture (a pcap's $GPRMC or capture time)"
        )
    return float(reference_time)


def read_gnss_track(
    path: str | Path,
    crs: int | str | None = None,
    reference_time: float | None = None,
    time_scale: str = "utc",
) -> GnssTrack:
    """Read a GNSS track file (format from its content, see the module docstring)."""
    if time_scale not in ("utc", "gps"):
        raise InputError(f"--gnss-time {time_scale!r}: expected utc or gps")
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: GNSS track file does not exist")
    text = path.read_text(encoding="utf-8", errors="replace")
    head = text.lstrip()[:400]
    if head.startswith("<"):
        track = _read_gpx(path, text)
    elif head.startswith("$"):
        track = _read_nmea(path, text, reference_time)
    else:
        track = _read_columns(path, text, crs, reference_time, time_scale == "gps")
    check_track(track)
    return track


# -- formats ----------------------------------------------------------------------------------
def _rows(text: str) -> list[tuple[int, list[str]]]:
    out = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            fields = [f for f in re.split(r"[,;\s]+", line) if f]
            out.append((number, fields))
    return out


def _read_columns(
    path: Path, text: str, crs: int | str | None, reference_time: float | None, gps: bool
) -> GnssTrack:
    rows = _rows(text)
    if not rows:
        raise InputError(f"{path}: GNSS track has no rows")
    if not all(is_number_text(f) for f in rows[0][1]):
        return _read_csv(path, text, crs, reference_time, gps)
    lines, values = [], []
    for number, fields in rows:
        if len(fields) < 5:
            raise InputError(
                f"{path}, line {number}: expected time and easting, northing, height in "
                f"columns 1 and 3-5 (the MTLS track layout), got {len(fields)} columns"
            )
        try:
            values.append([float(fields[i]) for i in (0, 2, 3, 4)])
        except ValueError as exc:
            raise InputError(f"{path}, line {number}: not a number ({exc})") from None
        lines.append(number)
    arr = np.asarray(values)
    ref = _need_reference(reference_time, path, "times of day (hhmmss.ss)")
    tod = np.array([hhmmss_seconds(v) for v in arr[:, 0]])
    t = times_of_day_to_utc(tod, ref, gps=gps, where=str(path))
    return _projected(path, "columns", t, arr[:, 1], arr[:, 2], arr[:, 3], np.array(lines), crs)


def _column(names: list[str], choices: tuple[str, ...]) -> int | None:
    for choice in choices:
        if choice in names:
            return names.index(choice)
    return None


def _read_csv(
    path: Path, text: str, crs: int | str | None, reference_time: float | None, gps: bool
) -> GnssTrack:
    sample = text[:4096]
    delimiter = "," if sample.count(",") >= sample.count(";") else ";"
    if sample.count(",") == 0 and sample.count(";") == 0:
        delimiter = "\t" if "\t" in sample else " "
    reader = csv.reader(io.StringIO(text), delimiter=delimiter, skipinitialspace=True)
    header_line, names = 0, []
    body: list[tuple[int, list[str]]] = []
    for number, row in enumerate(reader, start=1):
        row = [c.strip() for c in row if c.strip() != "" or delimiter != " "]
        if not row or row[0].startswith("#"):
            continue
        if not names:
            header_line, names = number, [c.strip().lower() for c in row]
        else:
            body.append((number, row))
    it = _column(names, TIME_NAMES)
    if it is None:
        raise InputError(
            f"{path}, line {header_line}: no time column (one of {', '.join(TIME_NAMES)}) "
            f"in the header {names}"
        )
    ilat, ilon = _column(names, LAT_NAMES), _column(names, LON_NAMES)
    ie, in_ = _column(names, EAST_NAMES), _column(names, NORTH_NAMES)
    ih = _column(names, HEIGHT_NAMES)
    if (ilat is None or ilon is None) and (ie is None or in_ is None):
        raise InputError(
            f"{path}, line {header_line}: the header names neither lat/lon nor "
            f"easting/northing columns ({names})"
        )
    geographic = ilat is not None and ilon is not None
    a, b = (ilat, ilon) if geographic else (ie, in_)
    lines, times, xs, ys, hs = [], [], [], [], []
    for number, row in body:
        try:
            xs.append(float(row[a]))
            ys.append(float(row[b]))
            hs.append(float(row[ih]) if ih is not None and row[ih] != "" else 0.0)
        except (ValueError, IndexError):
            raise InputError(
                f"{path}, line {number}: a coordinate is missing or not a number"
            ) from None
        times.append(row[it] if it < len(row) else "")
        lines.append(number)
    if not lines:
        raise InputError(f"{path}: GNSS track has a header but no rows")
    t = _csv_times(path, times, lines, reference_time, gps)
    if geographic:
        return _geographic(path, "csv", t, np.array(xs), np.array(ys), np.array(hs), lines)
    return _projected(path, "csv", t, np.array(xs), np.array(ys), np.array(hs), lines, crs)


def _csv_times(
    path: Path, values: list[str], lines: list[int], reference_time: float | None, gps: bool
) -> np.ndarray:
    if all(is_number_text(v) for v in values):
        numbers = np.array([float(v) for v in values])
        if np.nanmin(numbers) > 1e8:
            return numbers  # Unix epoch seconds, UTC
        ref = _need_reference(reference_time, path, "times of day (hhmmss.ss)")
        tod = np.array([hhmmss_seconds(v) for v in numbers])
        return times_of_day_to_utc(tod, ref, gps=gps, where=str(path))
    out = []
    for value, number in zip(values, lines, strict=True):
        try:
            stamp = datetime.fromisoformat(value.replace("Z", "+00:00"))
        except ValueError:
            raise InputError(f"{path}, line {number}: time {value!r} is not ISO 8601") from None
        out.append((stamp if stamp.tzinfo else stamp.replace(tzinfo=UTC)).timestamp())
    return np.array(out)


def _read_nmea(path: Path, text: str, reference_time: float | None) -> GnssTrack:
    gga: list[tuple[int, float, float, float, float]] = []  # line, tod, lat, lon, height
    rmc: list[tuple[int, float, float, float]] = []  # line, utc, lat, lon
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        match = NMEA_POSITION.match(line)
        if not match:
            continue
        if not nmea_checksum_ok(line):
            raise InputError(f"{path}, line {number}: NMEA checksum does not match")
        if match.group(2) == "GGA":
            try:
                fix = parse_gga(line)
            except (ValueError, IndexError):
                raise InputError(f"{path}, line {number}: malformed GGA sentence") from None
            if fix is not None:
                gga.append((number, *fix))
        else:
            parsed = parse_rmc(line)
            if parsed is not None:
                rmc.append((number, *parsed))
    if gga:
        ref = rmc[0][1] if rmc else _need_reference(reference_time, path, "GGA times of day")
        # a receiver logging several talkers ($GPGGA and $GNGGA) repeats an epoch: keep its first
        gga = [g for k, g in enumerate(gga) if k == 0 or g[1] != gga[k - 1][1]]
        arr = np.array([g[1:] for g in gga])
        t = times_of_day_to_utc(arr[:, 0], ref, gps=False, where=str(path))
        lines = [g[0] for g in gga]
        return _geographic(path, "nmea", t, arr[:, 1], arr[:, 2], arr[:, 3], lines)
    if rmc:  # RMC has no height
        arr = np.array([r[1:] for r in rmc])
        lines = [r[0] for r in rmc]
        return _geographic(path, "nmea", arr[:, 0], arr[:, 1], arr[:, 2], np.zeros(len(arr)), lines)
    raise InputError(f"{path}: no GGA or RMC sentence with a fix")


def _read_gpx(path: Path, text: str) -> GnssTrack:
    import xml.etree.ElementTree as ET

    if "<!ENTITY" in text:
        raise InputError(f"{path}: GPX with entity declarations is not read")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise InputError(f"{path}: not a readable GPX file ({exc})") from None
    rows = []
    for index, point in enumerate(e for e in root.iter() if e.tag.endswith("trkpt")):
        children = {c.tag.rsplit("}", 1)[-1]: (c.text or "").strip() for c in point}
        try:
            lat, lon = float(point.attrib["lat"]), float(point.attrib["lon"])
            stamp = datetime.fromisoformat(children["time"].replace("Z", "+00:00"))
        except (KeyError, ValueError):
            raise InputError(
                f"{path}: track point {index + 1} needs lat, lon and an ISO 8601 <time>"
            ) from None
        stamp = stamp if stamp.tzinfo else stamp.replace(tzinfo=UTC)
        rows.append((stamp.timestamp(), lat, lon, float(children.get("ele") or 0.0)))
    if not rows:
        raise InputError(f"{path}: GPX file has no <trkpt>")
    arr = np.array(rows)
    return _geographic(path, "gpx", arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], [0] * len(arr))


# -- coordinates and checks -------------------------------------------------------------------
def _series(t: np.ndarray, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> GnssSeries:
    n = len(t)
    return GnssSeries(
        np.asarray(t, float),
        np.asarray(lat, float),
        np.asarray(lon, float),
        np.asarray(h, float),
        np.zeros(n, int),
        np.zeros((n, 9)),
        np.zeros(n, int),
    )


def _geographic(path, fmt, t, lat, lon, h, lines) -> GnssTrack:
    lines = np.asarray(lines, int)
    bad = np.flatnonzero((np.abs(lat) > 90) | (np.abs(lon) > 180) | ~np.isfinite(lat + lon))
    if len(bad):
        raise InputError(
            f"{path}, line {lines[bad[0]]}: latitude/longitude ({lat[bad[0]]}, {lon[bad[0]]}) "
            "out of range"
        )
    return GnssTrack(path, fmt, _series(t, lat, lon, h), lines, "EPSG:4326")


def _projected(path, fmt, t, east, north, h, lines, crs) -> GnssTrack:
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError

    lines = np.asarray(lines, int)
    if crs is None:
        raise InputError(
            f"{path}: easting/northing columns need their CRS (--gnss-crs EPSG code, e.g. "
            "25831 for ETRS89 / UTM 31N)"
        )
    try:
        source = CRS.from_user_input(int(crs) if str(crs).isdigit() else crs)
    except CRSError as exc:
        raise InputError(f"--gnss-crs {crs}: not a known CRS ({exc})") from None
    if not source.is_projected:
        raise InputError(f"--gnss-crs {crs}: {source.name} is not a projected CRS (metres)")
    to_wgs84 = Transformer.from_crs(source, "EPSG:4326", always_xy=True)
    lon, lat = to_wgs84.transform(east, north)
    area = source.area_of_use
    margin = 1.0  # degrees: a track just over a zone's edge is still read
    outside = ~np.isfinite(lon) | ~np.isfinite(lat)
    if area is not None:
        outside |= (lon < area.west - margin) | (lon > area.east + margin)
        outside |= (lat < area.south - margin) | (lat > area.north + margin)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        where = f"({area.west}..{area.east} E, {area.south}..{area.north} N)" if area else ""
        raise InputError(
            f"{path}, line {lines[i]}: easting {east[i]}, northing {north[i]} lie outside "
            f"{source.name}'s area {where}: is the CRS ({source.to_string()}) right?"
        )
    return GnssTrack(path, fmt, _series(t, lat, lon, h), lines, source.to_string())


def check_track(track: GnssTrack) -> None:
    """Times that go forward without long gaps; raise naming the file and line otherwise."""
    t, lines, path = track.fixes.t, track.lines, track.path

    def where(i: int) -> str:
        return f"{path}, line {lines[i]}" if lines[i] else f"{path}, track point {i + 1}"

    if len(t) < 2:
        raise InputError(f"{path}: GNSS track has {len(t)} fix(es); at least 2 are needed")
    dt = np.diff(t)
    back = np.flatnonzero(dt <= 0)
    if len(back):
        i = int(back[0]) + 1
        raise InputError(f"{where(i)}: time does not increase ({t[i - 1]:.3f} then {t[i]:.3f})")
    median = float(np.median(dt))
    limit = max(GAP_FACTOR * median, MIN_GAP_S)
    gaps = np.flatnonzero(dt > limit)
    if len(gaps):
        i = int(gaps[0]) + 1
        raise InputError(
            f"{where(i)}: the track has a gap of {dt[i - 1]:.1f} s before this fix (the "
            f"median interval is {median:.2f} s; gaps over {limit:.1f} s are not bridged)"
        )
