"""The gimbal attitude and altitudes a DJI drone writes into a photo's XMP packet.

Read from the ``drone-dji`` namespace (attributes of ``rdf:Description`` as DJI writes them,
or elements as some editing tools rewrite them): ``GimbalYawDegree``, ``GimbalPitchDegree``,
``GimbalRollDegree`` (degrees; :mod:`canopy_kit.core.gimbal` gives the camera rotation),
``FlightYawDegree`` and ``RelativeAltitude`` (metres above take-off). A photo without them
(another camera, an edited file) has none; a tag that is there but not a number, or an
angle out of range, is an error naming the photo and the tag.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from canopy_kit.core.gimbal import is_oblique
from canopy_kit.errors import InputError

_TAG = r"drone-dji:{name}\s*(?:=\s*[\"']([^\"']*)[\"']|>\s*([^<]*)<)"
_RANGES = {  # tag: (lowest, highest) accepted value
    "GimbalYawDegree": (-360.0, 360.0),
    "GimbalPitchDegree": (-180.0, 180.0),
    "GimbalRollDegree": (-180.0, 180.0),
    "FlightYawDegree": (-360.0, 360.0),
    "RelativeAltitude": (-1000.0, 10000.0),
}


@dataclass(frozen=True)
class DroneAttitude:
    """A photo's gimbal (yaw, pitch, roll) in degrees, the aircraft's heading and its height
    above take-off (None where the photo does not say)."""

    gimbal_yaw_deg: float
    gimbal_pitch_deg: float
    gimbal_roll_deg: float
    flight_yaw_deg: float | None
    relative_altitude_m: float | None

    @property
    def oblique(self) -> bool:
        """Whether the gimbal is pitched above ``core.gimbal.OBLIQUE_PITCH_DEG`` (more than 15 degrees
        away from straight down)."""
        return is_oblique(self.gimbal_pitch_deg)


def _value(text: str, name: str, path: Path) -> float | None:
    found = re.search(_TAG.format(name=name), text)
    if found is None:
        return None
    raw = (found.group(1) if found.group(1) is not None else found.group(2)).strip()
    try:
        value = float(raw)
    except ValueError:
        raise InputError(f"{path}: XMP drone-dji:{name} is {raw!r}, not a number") from None
    lo, hi = _RANGES[name]
    if not (math.isfinite(value) and lo <= value <= hi):
        raise InputError(f"{path}: XMP drone-dji:{name} = {value} is outside [{lo:g}, {hi:g}]")
    return value


def read_drone_attitude(xmp: bytes | str | None, path: str | Path) -> DroneAttitude | None:
    """The attitude in an XMP packet, or None when it holds no gimbal pitch and yaw."""
    if not xmp:
        return None
    text = xmp.decode("utf-8", "replace") if isinstance(xmp, bytes) else xmp
    path = Path(path)
    values = {name: _value(text, name, path) for name in _RANGES}
    if values["GimbalPitchDegree"] is None or values["GimbalYawDegree"] is None:
        return None
    return DroneAttitude(
        values["GimbalYawDegree"],
        values["GimbalPitchDegree"],
        values["GimbalRollDegree"] or 0.0,
        values["FlightYawDegree"],
        values["RelativeAltitude"],
    )
