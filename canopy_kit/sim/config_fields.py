"""Bounds of the simulator config's plain numbers, declared once per field.

:func:`canopy_kit.sim.config.validate` checks the relations between fields (min below max,
a firing with its output); this module checks what each number is alone: every float finite
(NaN compares false with everything, so a check like ``x > 0`` alone would not see it), and
the sign or range of the fields that nothing else bounds. A value outside raises
:class:`~canopy_kit.errors.ConfigError` naming the field (``section.field``) and the value.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from typing import Any

from canopy_kit.errors import ConfigError

#: Fields that may be +inf, and what it means.
MAY_BE_INFINITE = {"orchard.leaf_penetration_m": "leaves through the whole crown"}

#: Fields (or every number in a list field) that must be >= 0.
NON_NEGATIVE = (
    "seed",
    "session_seed",
    "orchard.position_jitter",
    "orchard.min_crown_gap",
    "orchard.lean_max",
    "orchard.alley_clearance",
    "orchard.crown_lobes",
    "orchard.grass_height",
    "orchard.grass_density",
    "orchard.terrain_bump_amplitude",
    "orchard.removed_trees",
    "orchard.replanted_trees",
    "drive.speed_variation",
    "drive.start_still",
    "drive.end_still",
    "drive.vibration_deg",
    "imu.gyro_noise",
    "imu.accel_noise",
    "imu.gyro_bias_sigma",
    "imu.accel_bias_sigma",
    "gnss.sigma_horizontal",
    "gnss.sigma_vertical",
    "gnss.rtk_sigma_horizontal",
    "gnss.rtk_sigma_vertical",
    "gnss.outage_count",
    "gnss.jump_count",
    "drone.gps_sigma_horizontal",
    "drone.gps_sigma_vertical",
    "drone.gps_offset_sigma_horizontal",
    "drone.gps_offset_sigma_vertical",
    "drone.position_jitter_horizontal",
    "drone.position_jitter_vertical",
    "drone.attitude_sigma_deg",
    "drone.yaw_sigma_deg",
    "drone.area_margin",
)

#: Fields that must be > 0.
POSITIVE = (
    "orchard.terrain_bump_wavelength",
    "drive.wheelbase",
    "drive.track",
    "drive.odometry_rate_hz",
    "gnss.correlation_time",
)

#: Fields bounded on both sides (inclusive), in degrees.
RANGES = {
    "orchard.origin_lat": (-90.0, 90.0),
    "orchard.origin_lon": (-180.0, 180.0),
    "orchard.terrain_slope_deg": (-45.0, 45.0),
    "orchard.terrain_cross_slope_deg": (-45.0, 45.0),
    "lidar.mount_pitch_deg": (-90.0, 90.0),
    "drone.sun_elevation_deg": (1.0, 90.0),
}


def _fail(name: str, message: str) -> None:
    raise ConfigError(f"simulator parameter {name}: {message}")


def _fields(config: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(``section.field``, value) of every field of a config dataclass, sections unfolded."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from _fields(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", value


def _numbers(value: Any) -> Iterator[float]:
    """The numbers in a value: itself, or the items of a (nested) list; not booleans."""
    if isinstance(value, list | tuple):
        for item in value:
            yield from _numbers(item)
    elif isinstance(value, int | float) and not isinstance(value, bool):
        yield value


def check_fields(config: Any) -> None:
    """Raise ConfigError for the first number that is not finite or out of its declared bounds."""
    values = dict(_fields(config))
    for name, value in values.items():
        for x in _numbers(value):
            if isinstance(x, float) and not math.isfinite(x):
                if x == math.inf and name in MAY_BE_INFINITE:
                    continue
                _fail(name, f"must be a finite number, got {value}")
    for name in NON_NEGATIVE:
        if any(x < 0 for x in _numbers(values[name])):
            _fail(name, f"must not be negative, got {values[name]}")
    for name in POSITIVE:
        if not values[name] > 0:
            _fail(name, f"must be positive, got {values[name]}")
    for name, (lo, hi) in RANGES.items():
        if not lo <= values[name] <= hi:
            _fail(name, f"must be in [{lo:g}, {hi:g}], got {values[name]}")
