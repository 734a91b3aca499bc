"""Malformed simulator config values (found by fuzzing ``load_sim_config`` over every field
with wrong types, empty and short lists, NaN, infinities and negatives): each is a
ConfigError naming the field, never an IndexError or a value let through."""

from __future__ import annotations

import dataclasses
import math

import pytest

from canopy_kit.errors import ConfigError
from canopy_kit.sim import load_sim_config
from canopy_kit.sim.config import SimConfig
from canopy_kit.sim.config_fields import MAY_BE_INFINITE

SMALL = {"orchard": {"rows": 1, "trees_per_row": 3}}


def _load(section: str, field: str, value: object) -> None:
    overrides = {**SMALL, section: {**SMALL.get(section, {}), field: value}}
    load_sim_config("pistachio", overrides)


def _float_fields() -> list[tuple[str, str, bool]]:
    """(section, field, is a list) of every float or list-of-float field of the config."""
    out = []
    for section in dataclasses.fields(SimConfig):
        spec = getattr(SimConfig(), section.name)
        if not dataclasses.is_dataclass(spec):
            continue
        for f in dataclasses.fields(spec):
            value = getattr(spec, f.name)
            if isinstance(value, float):
                out.append((section.name, f.name, False))
            elif isinstance(value, list) and value and isinstance(value[0], float):
                out.append((section.name, f.name, True))
    return out


FLOAT_FIELDS = _float_fields()


def test_the_sweep_covers_every_section() -> None:
    sections = {s for s, _, _ in FLOAT_FIELDS}
    assert sections == {"orchard", "lidar", "drive", "imu", "gnss", "drone", "rig"}
    assert len(FLOAT_FIELDS) > 80


@pytest.mark.parametrize("bad", [math.nan, -math.inf, math.inf], ids=["nan", "-inf", "inf"])
def test_no_float_field_takes_nan_or_infinity(bad: float) -> None:
    for section, field, is_list in FLOAT_FIELDS:
        name = f"{section}.{field}"
        if bad == math.inf and name in MAY_BE_INFINITE:
            continue
        value = [bad, bad] if is_list else bad
        with pytest.raises(ConfigError, match=rf"simulator parameter {name}: "):
            _load(section, field, value)


@pytest.mark.parametrize(
    ("section", "field", "value", "message"),
    [
        # crashed with IndexError
        ("lidar", "vertical_fov", [], r"lidar.vertical_fov: expected \[lowest, highest\].*\[\]"),
        ("lidar", "vertical_fov", [10.0], r"lidar.vertical_fov: expected .*\[10.0\]"),
        ("lidar", "vertical_fov", [-10.0, 0.0, 10.0], r"lidar.vertical_fov: expected "),
        # accepted, then NaN geometry or a crash inside numpy
        ("orchard", "terrain_slope_deg", math.nan, r"orchard.terrain_slope_deg: .*finite.*nan"),
        ("orchard", "spacing_range", [math.nan, 5.0], r"orchard.spacing_range: .*finite"),
        ("lidar", "range_noise", math.inf, r"lidar.range_noise: must be a finite number"),
        ("gnss", "outages", [[math.nan, 2.0]], r"gnss.outages: must be a finite number"),
        ("drone", "sensor_width_mm", math.inf, r"drone.sensor_width_mm: .*finite"),
        # negative: accepted, then numpy raised on a negative scale or size
        ("seed", None, -1, r"seed: must not be negative, got -1"),
        ("orchard", "position_jitter", -0.1, r"orchard.position_jitter: must not be negative"),
        ("orchard", "crown_lobes", -1, r"orchard.crown_lobes: must not be negative, got -1"),
        ("orchard", "alley_clearance", -1.0, r"orchard.alley_clearance: must not be negative"),
        ("orchard", "removed_trees", [0, -2], r"orchard.removed_trees: must not be negative"),
        ("imu", "gyro_noise", -1.0, r"imu.gyro_noise: must not be negative, got -1.0"),
        ("gnss", "sigma_horizontal", -0.5, r"gnss.sigma_horizontal: must not be negative"),
        ("drone", "yaw_sigma_deg", -1.0, r"drone.yaw_sigma_deg: must not be negative"),
        ("drive", "wheelbase", 0.0, r"drive.wheelbase: must be positive, got 0.0"),
        ("gnss", "correlation_time", -1.0, r"gnss.correlation_time: must be positive"),
        ("orchard", "origin_lat", 91.0, r"orchard.origin_lat: must be in \[-90, 90\], got 91.0"),
        ("drone", "sun_elevation_deg", -5.0, r"drone.sun_elevation_deg: must be in \[1, 90\]"),
        # named a wildcard or two fields instead of the wrong one
        ("orchard", "foliage_density_core", -1.0, r"orchard.foliage_density_core: must not be"),
        ("drone", "side_overlap", 0.0, r"drone.side_overlap: must be in \(0, 1\), got 0.0"),
        ("lidar", "dropout", 1.0, r"lidar.dropout: must be in \[0, 1\), got 1.0"),
        ("drive", "turn_speed", 0.0, r"drive.turn_speed: must be positive, got 0.0"),
        ("gnss", "rate_hz", 0.0, r"gnss.rate_hz: must be positive, got 0.0"),
        # wrong types and empty lists (caught when the config is read)
        ("orchard", "crown_diameter_range", [], r"orchard.crown_diameter_range: expected \[min"),
        ("orchard", "rows", "two", r"orchard.rows: expected an integer, got 'two'"),
        ("lidar", "vertical_fov", "wide", r"lidar.vertical_fov: expected a list, got str"),
        ("gnss", "jumps", [[]], r"gnss.jumps\[0\]: expected \[start_s, duration_s, offset_m\]"),
        ("drone", "altitude", [35.0], r"drone.altitude: expected a number"),
    ],
)
def test_a_malformed_value_names_its_field(
    section: str, field: str | None, value: object, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        if field is None:
            load_sim_config("pistachio", {**SMALL, section: value})
        else:
            _load(section, field, value)


@pytest.mark.parametrize(
    ("section", "field", "value"),
    [
        ("orchard", "leaf_penetration_m", math.inf),  # leaves through the whole crown
        ("orchard", "row_bearing_deg", -30.0),
        ("orchard", "terrain_slope_deg", -4.0),
        ("lidar", "mount_pitch_deg", -10.0),
        ("drone", "sun_azimuth_deg", -45.0),
        ("orchard", "crown_lobes", 0),
    ],
)
def test_values_that_stay_allowed(section: str, field: str, value: object) -> None:
    _load(section, field, value)
