"""NMEA 0183 position sentences: ``$xxGGA`` (time of day, position, height) and ``$xxRMC``
(UTC date and time, position), with their ``*hh`` checksums; talkers GP, GN, GL, GA."""

from __future__ import annotations

import re
from datetime import UTC, datetime


def hhmmss_seconds(value: float) -> float:
    """Seconds of the day of a time written as the number hhmmss.ss (80150.95 -> 08:01:50.95)."""
    hours, rest = divmod(float(value), 10000.0)
    minutes, seconds = divmod(rest, 100.0)
    return hours * 3600.0 + minutes * 60.0 + seconds


NMEA_POSITION = re.compile(r"^\$(GP|GN|GL|GA)(GGA|RMC),")


def nmea_degrees(value: str, hemisphere: str) -> float:
    """Decimal degrees of an NMEA ``dddmm.mmmm`` value and its hemisphere letter."""
    raw = float(value)
    degrees = int(raw // 100)
    out = degrees + (raw - 100 * degrees) / 60.0
    return -out if hemisphere in ("S", "W") else out


def nmea_checksum_ok(sentence: str) -> bool:
    """True when the sentence has no ``*hh`` checksum or its checksum matches."""
    if "*" not in sentence:
        return True
    body, _, given = sentence[1:].partition("*")
    value = 0
    for ch in body:
        value ^= ord(ch)
    return given[:2].upper() == f"{value:02X}"


def parse_rmc(sentence: str) -> tuple[float, float, float] | None:
    """(UTC epoch s, latitude, longitude) of a valid ``$xxRMC`` sentence, else None."""
    fields = sentence.split("*")[0].split(",")
    if len(fields) < 10 or fields[2] != "A" or not fields[1] or len(fields[9]) != 6:
        return None
    try:
        day, month, yy = int(fields[9][:2]), int(fields[9][2:4]), int(fields[9][4:6])
        year = 2000 + yy if yy < 80 else 1900 + yy  # GPS dates begin in 1980
        midnight = datetime(year, month, day, tzinfo=UTC).timestamp()
        t = midnight + hhmmss_seconds(float(fields[1]))
        return t, nmea_degrees(fields[3], fields[4]), nmea_degrees(fields[5], fields[6])
    except ValueError:
        return None


def parse_gga(sentence: str) -> tuple[float, float, float, float] | None:
    """(UTC seconds of the day, latitude, longitude, ellipsoidal height: altitude + geoid
    separation) of a ``$xxGGA`` sentence with a fix, else None; ValueError when malformed."""
    fields = sentence.split("*")[0].split(",")
    if len(fields) < 10 or not fields[2] or fields[6] in ("", "0"):
        return None  # no fix
    separation = float(fields[11]) if len(fields) > 11 and fields[11] != "" else 0.0
    return (
        hhmmss_seconds(float(fields[1])),
        nmea_degrees(fields[2], fields[3]),
        nmea_degrees(fields[4], fields[5]),
        float(fields[9]) + separation,
    )
