"""Simulator settings: one dataclass per concern, loaded from ``presets/sim/*.toml``."""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from canopy_kit.config import from_dict, merge, read_toml
from canopy_kit.errors import ConfigError
from canopy_kit.sim.config_fields import check_fields


@dataclass
class OrchardSpec:
    """Orchard geometry. Lengths in metres, angles in degrees, densities per m² or m³."""

    kind: str = "pistachio"
    rows: int = 4
    trees_per_row: int = 10
    spacing_range: list[float] = field(default_factory=lambda: [5.0, 5.0])
    position_jitter: float = 0.1
    row_spacing: float = 6.0
    row_bearing_deg: float = 0.0
    row_bow: float = 0.0
    missing_probability: float = 0.0
    double_probability: float = 0.0
    double_offset_range: list[float] = field(default_factory=lambda: [1.5, 2.2])
    crown_diameter_range: list[float] = field(default_factory=lambda: [3.0, 4.5])
    crown_across_ratio_range: list[float] = field(default_factory=lambda: [0.85, 1.0])
    crown_height_ratio_range: list[float] = field(default_factory=lambda: [0.75, 0.95])
    crown_base_height_range: list[float] = field(default_factory=lambda: [0.8, 1.2])
    crown_squareness_range: list[float] = field(default_factory=lambda: [2.0, 2.5])
    crown_irregularity: float = 0.08
    crown_lobes: int = 6
    # Crown forms (canopy_kit.sim.crown_forms): ellipsoid (the superellipsoid above), lobed,
    # vase (open centre), hedged (flat pruned sides and top), sparse (young), or mix (per tree).
    crown_form: str = "ellipsoid"
    lobe_hollow_range: list[float] = field(
        default_factory=lambda: [0.45, 0.6]
    )  # radius between lobes
    hedge_cut: float = 0.75  # pruning planes at this fraction of the across and upper semi-axes
    sparse_crown_scale: float = 0.45
    sparse_foliage_scale: float = 0.3
    # Leaves reach at most this far (m, along the ray from the centre) below the envelope;
    # inf: through the whole crown (6 -> 60 clusters/m³ from centre to shell).
    leaf_penetration_m: float = float("inf")
    lean_max: float = 0.0
    separate_crowns: bool = True
    min_crown_gap: float = 0.3
    alley_clearance: float = 1.0
    trunk_radius_range: list[float] = field(default_factory=lambda: [0.08, 0.14])
    branches_range: list[int] = field(default_factory=lambda: [3, 5])
    foliage_density_shell: float = 60.0
    foliage_density_core: float = 6.0
    leaf_cluster_size_range: list[float] = field(default_factory=lambda: [0.10, 0.22])
    headland: float = 8.0
    margin: float = 6.0
    terrain_slope_deg: float = 0.0
    terrain_cross_slope_deg: float = 0.0
    terrain_bump_amplitude: float = 0.08
    terrain_bump_wavelength: float = 14.0
    grass_height: float = 0.25
    grass_density: float = 1.5
    origin_lat: float = 37.2810
    origin_lon: float = -120.4200
    origin_height: float = 50.0
    # Revisits of the same orchard (same seed, same layout): crown growth, removed trees and
    # young trees replanted in place of old ones (tree ids of the full layout).
    crown_scale: float = 1.0
    removed_trees: list[int] = field(default_factory=list)
    replanted_trees: list[int] = field(default_factory=list)
    replanted_crown_scale: float = 0.5
    # Young trees among the old (e.g. replants in a hedgerow): drawn per tree with this
    # probability (no draw at 0, so other layouts stay as they were), crowns scaled so.
    young_probability: float = 0.0
    young_crown_scale: float = 0.5
    # Trellis of a fruiting wall (canopy_kit.sim.trellis), none when post_spacing is 0: posts
    # (height above the ground, radius) along each row's line every ``trellis_post_spacing``
    # m and at both ends, wires at ``trellis_wire_heights`` (m above the ground) from end
    # post to end post, a drip irrigation line at ``drip_line_height`` (0: none). The LiDAR
    # hits them; their per-point truth label is ``TRELLIS_ID`` (-2), never a tree.
    trellis_post_spacing: float = 0.0
    trellis_post_height: float = 3.6
    trellis_post_radius: float = 0.05
    trellis_end_overhang: float = 0.6  # end posts this far beyond the first and last tree
    trellis_end_post_lean_deg: float = 0.0  # end posts lean outward along the row (0: upright)
    trellis_wire_heights: list[float] = field(default_factory=list)
    trellis_wire_radius: float = 0.0015
    drip_line_height: float = 0.0
    drip_line_radius: float = 0.008
    # What a tree's true volume is (trees.csv): ``crown`` (its own envelope) or
    # ``trunk-midpoint`` (a continuous wall: the union of the row's crowns between the
    # midpoints to its neighbours' trunks, canopy_kit.sim.wall_truth; adds cut_volume_m3).
    tree_volume_truth: Literal["crown", "trunk-midpoint"] = "crown"


@dataclass
class LidarSpec:
    """Spinning LiDAR; ``vertical_fov`` is [lowest, highest] beam elevation in degrees.

    ``firing``: ``columns`` (``columns`` evenly spaced columns, every ring at once) or
    ``vlp16`` (a VLP-16's firing sequence and laser table; ``rings``, ``vertical_fov``,
    ``columns`` and ``time_field`` are then unused). ``output``: ``points``
    (sensor_msgs/PointCloud2) or ``velodyne_packets`` (velodyne_msgs/VelodyneScan, the raw
    packets; fires as a VLP-16) or ``ouster_packets`` (ouster_ros PacketMsg of lidar mode
    ``columns`` x ``rate_hz`` and UDP profile ``ouster_profile``; see canopy_kit.sim.ouster).
    ``firing`` ``livox-mid360`` / ``livox-avia``: a Livox non-repetitive pattern
    (:mod:`canopy_kit.sim.livox`; ``output`` ``livox_custom`` writes livox_ros_driver2
    CustomMsg, ``points`` the driver2 PointCloud2 layout).
    """

    rings: int = 32
    vertical_fov: list[float] = field(default_factory=lambda: [-45.0, 45.0])
    columns: int = 1024
    rate_hz: float = 10.0
    min_range: float = 0.5
    max_range: float = 60.0
    range_noise: float = 0.01
    dropout: float = 0.01
    mount_height: float = 1.8
    mount_pitch_deg: float = 0.0
    time_field: Literal["t", "time", "timestamp"] = "t"
    frame_id: str = "lidar"
    topic: str = "/points"
    firing: Literal["columns", "vlp16", "livox-mid360", "livox-avia"] = "columns"
    output: Literal["points", "velodyne_packets", "livox_custom", "ouster_packets"] = "points"
    ouster_profile: Literal["RNG19_RFL8_SIG16_NIR16", "LEGACY", "RNG15_RFL8_NIR8"] = (
        "RNG19_RFL8_SIG16_NIR16"
    )


@dataclass
class DriveSpec:
    """Robot motion through the alleys, with U-turns at the headlands."""

    cruise_speed: float = 1.5
    speed_variation: float = 0.12
    turn_speed: float = 0.8
    acceleration: float = 0.35
    start_still: float = 2.0
    end_still: float = 1.0
    alleys: Literal["all", "inner"] = "all"
    reverse: bool = False  # drive the serpentine backwards, from the far end of the last alley
    lead_in: float = 0.0  # metres of straight approach before the first alley (a farther start)
    wheelbase: float = 1.2
    track: float = 1.0
    vibration_deg: float = 0.1
    odometry_rate_hz: float = 50.0
    odometry_topic: str = "/ground_truth/odom"


@dataclass
class ImuSpec:
    """IMU at the LiDAR (identity extrinsic); noise densities per √Hz. ``output``: ``imu``
    (sensor_msgs/Imu) or ``ouster_packets`` (the Ouster's own IMU packets; needs
    ``lidar.output = "ouster_packets"``, see canopy_kit.sim.ouster)."""

    enabled: bool = True
    rate_hz: float = 200.0
    gyro_noise: float = 0.0005
    accel_noise: float = 0.002
    gyro_bias_sigma: float = 0.002
    accel_bias_sigma: float = 0.05
    topic: str = "/imu/data"
    frame_id: str = "lidar"
    acceleration_unit: Literal["m/s2", "g"] = "m/s2"  # g: as Livox drivers publish it
    output: Literal["imu", "ouster_packets"] = "imu"


@dataclass
class GnssSpec:
    """GNSS antenna at the LiDAR; ``mode`` standard (metre level) or rtk (centimetre).

    The receiver's behaviour under canopy is off by default. Times are seconds from the
    drive start; intervals are ``[start_s, duration_s]``. Outages write NO_FIX messages
    (``outage_fill``: NaN or the last known position, or no message at all); jumps offset
    the fixes horizontally by ``offset_m`` in a random direction (multipath), with the
    reported covariance unchanged; ``rtk_intervals`` (mode standard) give RTK fixes
    (status 2, RTK sigmas) inside and standalone fixes (``standalone_status``) outside.
    ``covariance_type`` 0 (unknown) writes a zero covariance, as cheap receivers do.
    """

    enabled: bool = True
    rate_hz: float = 10.0
    mode: Literal["standard", "rtk"] = "standard"
    sigma_horizontal: float = 0.6
    sigma_vertical: float = 1.2
    correlation_time: float = 20.0
    rtk_sigma_horizontal: float = 0.02
    rtk_sigma_vertical: float = 0.04
    topic: str = "/gps/fix"
    frame_id: str = "gnss"
    outages: list[list[float]] = field(default_factory=list)
    outage_count: int = 0  # random outages besides the listed ones
    outage_duration_range: list[float] = field(default_factory=lambda: [3.0, 6.0])
    outage_fill: Literal["nan", "last", "none"] = "nan"
    outage_status: int = -1  # status written during an outage (-1 NO_FIX; 0: a receiver that lies)
    jumps: list[list[float]] = field(default_factory=list)  # [start_s, duration_s, offset_m]
    jump_count: int = 0
    jump_duration_range: list[float] = field(default_factory=lambda: [2.0, 4.0])
    jump_offset_range: list[float] = field(default_factory=lambda: [1.0, 4.0])
    rtk_intervals: list[list[float]] = field(default_factory=list)
    standalone_status: int = 0  # 0 FIX or 1 SBAS
    covariance_type: int = 2  # 0 unknown, 1 approximated, 2 diagonal known, 3 known


@dataclass
class DroneSpec:
    """Photo flight over the orchard (lengths in m, angles in degrees).

    ``pattern``: ``nadir`` (a lawn-mower survey, lines along the rows, the image's long side
    across the track), ``double-grid`` (two grids, along and across the rows, the camera
    pitched to ``gimbal_pitch_deg``), ``single-grid`` (the grid along the rows alone) or
    ``orbit`` (a racetrack round each row, the camera at that pitch aimed at the row); see
    :mod:`canopy_kit.sim.drone_patterns`.
    ``gps_sigma_*`` is the per-photo GNSS noise written to EXIF (defaults: an RTK drone);
    ``gps_offset_sigma_*`` a constant offset shared by the whole flight (metre-level for a
    drone without RTK). ``position_jitter_*`` and ``attitude_sigma_deg``/``yaw_sigma_deg``
    are how far the true camera strays from the plan.
    """

    enabled: bool = False
    pattern: Literal["nadir", "double-grid", "single-grid", "orbit"] = "nadir"
    gimbal_pitch_deg: float = -60.0  # oblique patterns only; -90 looks straight down
    altitude: float = 35.0
    forward_overlap: float = 0.8
    side_overlap: float = 0.75
    image_width: int = 1200
    image_height: int = 900
    focal_length_mm: float = 8.8
    sensor_width_mm: float = 13.2
    gps_sigma_horizontal: float = 0.02
    gps_sigma_vertical: float = 0.05
    gps_offset_sigma_horizontal: float = 0.0
    gps_offset_sigma_vertical: float = 0.0
    position_jitter_horizontal: float = 0.3
    position_jitter_vertical: float = 0.15
    attitude_sigma_deg: float = 0.8
    yaw_sigma_deg: float = 1.5
    area_margin: float = 4.0
    flight_speed: float = 5.0
    sun_elevation_deg: float = 55.0
    sun_azimuth_deg: float = 135.0
    jpeg_quality: int = 92


@dataclass
class RigSimSpec:
    """Where the sensors sit on the vehicle (``canopy_kit.sim.rig``).

    ``name``: ``identity`` (every sensor in the LiDAR's frame at ``lidar.mount_height``, no
    /tf_static), a rig preset (``canopy_kit/presets/rigs``: tower, imu-flipped, yawed-lever,
    side-tilt) or a rig file. ``write_tf_static = false`` leaves the mounts out of the bag;
    ``tf_imu_error_rpy_deg`` makes /tf_static wrong about the IMU by that rotation;
    ``imu_time_offset`` stamps the IMU this many seconds late against the LiDAR.
    """

    name: str = "identity"
    write_tf_static: bool = True
    tf_imu_error_rpy_deg: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    imu_time_offset: float = 0.0


@dataclass
class SimConfig:
    """A whole field session: orchard, sensors, drive and optional drone flight.

    ``seed`` makes the orchard and the scene; ``session_seed``, when set, makes the drive
    and the sensor noise instead, so one orchard can be visited on several days.
    """

    seed: int = 0
    session_seed: int | None = None
    orchard: OrchardSpec = field(default_factory=OrchardSpec)
    lidar: LidarSpec = field(default_factory=LidarSpec)
    drive: DriveSpec = field(default_factory=DriveSpec)
    imu: ImuSpec = field(default_factory=ImuSpec)
    gnss: GnssSpec = field(default_factory=GnssSpec)
    drone: DroneSpec = field(default_factory=DroneSpec)
    rig: RigSimSpec = field(default_factory=RigSimSpec)


SENSOR_MODELS: dict[str, dict[str, Any]] = {
    "vlp16": {
        "rings": 16,
        "vertical_fov": [-15.0, 15.0],
        "columns": 1800,
        "time_field": "time",
        "max_range": 100.0,
    },
    "hdl32": {
        "rings": 32,
        "vertical_fov": [-30.67, 10.67],
        "columns": 1800,
        "time_field": "time",
        "max_range": 100.0,
    },
    "os0-32": {
        "rings": 32,
        "vertical_fov": [-45.0, 45.0],
        "columns": 1024,
        "time_field": "t",
        "max_range": 50.0,
    },
    "os1-64": {
        "rings": 64,
        "vertical_fov": [-22.5, 22.5],
        "columns": 1024,
        "time_field": "t",
        "max_range": 120.0,
    },
    "os1-128": {
        "rings": 128,
        "vertical_fov": [-22.5, 22.5],
        "columns": 1024,
        "time_field": "t",
        "max_range": 120.0,
    },
}


# Livox sensors (canopy_kit.sim.livox): their driver's topics and frame, the built-in IMU in g.
SENSOR_MODELS["livox-mid360"] = {
    "rings": 4,
    "vertical_fov": [-7.0, 52.0],
    "firing": "livox-mid360",
    "output": "livox_custom",
    "time_field": "timestamp",
    "min_range": 0.1,
    "max_range": 40.0,
    "range_noise": 0.02,
    "topic": "/livox/lidar",
    "frame_id": "livox_frame",
}
SENSOR_MODELS["livox-avia"] = {
    **SENSOR_MODELS["livox-mid360"],
    "rings": 6,
    "vertical_fov": [-35.2, 35.2],
    "firing": "livox-avia",
    "min_range": 1.0,
    "max_range": 190.0,
}
SENSOR_IMU: dict[str, dict[str, Any]] = {
    name: {"topic": "/livox/imu", "acceleration_unit": "g"}
    for name in ("livox-mid360", "livox-avia")
}


def sim_preset_names() -> list[str]:
    """Orchard presets shipped for the simulator."""
    files = resources.files("canopy_kit") / "presets" / "sim"
    return sorted(p.name[:-5] for p in files.iterdir() if p.name.endswith(".toml"))


def load_sim_config(
    orchard: str | Path = "pistachio",
    overrides: Mapping[str, Any] | None = None,
    sensor: str | None = None,
) -> SimConfig:
    """Simulator config from a shipped orchard preset (or TOML path), a sensor model and overrides.

    A preset or TOML file may start from another preset with ``extends = "<preset>"`` and
    then list only what differs.
    """
    name = str(orchard)
    if name in sim_preset_names():
        data, where = _preset_data(name), f"simulator preset {name!r}"
    else:
        path = Path(orchard)
        if not path.exists():
            raise ConfigError(
                f"orchard {name!r} is neither a simulator preset ({', '.join(sim_preset_names())}) "
                "nor an existing TOML file"
            )
        data, where = _resolve_extends(read_toml(path), str(path)), str(path)
    if sensor is not None:
        if sensor not in SENSOR_MODELS:
            raise ConfigError(f"sensor {sensor!r} is not one of {', '.join(SENSOR_MODELS)}")
        data = merge(data, {"lidar": SENSOR_MODELS[sensor], "imu": SENSOR_IMU.get(sensor, {})})
    if overrides:
        data = merge(data, overrides)
    config = from_dict(SimConfig, data, where)
    validate(config)
    return config


def _preset_data(name: str) -> dict[str, Any]:
    text = (resources.files("canopy_kit") / "presets" / "sim" / f"{name}.toml").read_text()
    return _resolve_extends(tomllib.loads(text), f"simulator preset {name!r}")


def _resolve_extends(data: dict[str, Any], where: str) -> dict[str, Any]:
    """``data`` merged onto the preset its ``extends`` key names (if any)."""
    if "extends" not in data:
        return data
    data = dict(data)
    base = data.pop("extends")
    if base not in sim_preset_names():
        raise ConfigError(
            f"{where}: extends {base!r}, which is not a simulator preset "
            f"({', '.join(sim_preset_names())})"
        )
    return merge(_preset_data(base), data)


def _check(ok: bool, name: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"simulator parameter {name}: {message}")


def _check_range(values: list[float], name: str, low: float = 0.0, strict: bool = True) -> None:
    _check(len(values) == 2, name, f"expected [min, max], got {values}")
    _check(values[0] <= values[1], name, f"min {values[0]} is larger than max {values[1]}")
    _check(
        values[0] > low if strict else values[0] >= low,
        name,
        f"values must be {'>' if strict else '>='} {low}, got {values}",
    )


def validate(c: SimConfig) -> None:
    """Reject impossible parameters with an error naming the parameter (the first found, in
    the order of the sections: orchard, lidar, drive, imu/gnss, rig, drone), after each
    number alone (finite, sign: :mod:`canopy_kit.sim.config_fields`)."""
    check_fields(c)
    _validate_orchard_grid(c.orchard)
    _validate_trees(c.orchard)
    _validate_orchard_room(c.orchard)
    _validate_lidar(c.lidar, c.imu)
    _validate_drive(c.drive)
    _check(c.imu.rate_hz > 0, "imu.rate_hz", f"must be positive, got {c.imu.rate_hz}")
    _check(c.gnss.rate_hz > 0, "gnss.rate_hz", f"must be positive, got {c.gnss.rate_hz}")
    _validate_gnss(c.gnss)
    _validate_rig(c)
    _validate_drone(c.drone)


def _validate_orchard_grid(o: OrchardSpec) -> None:
    """Rows, trees per row and their spacings."""
    _check(o.rows >= 1, "orchard.rows", f"must be at least 1, got {o.rows}")
    _check(
        o.trees_per_row >= 1, "orchard.trees_per_row", f"must be at least 1, got {o.trees_per_row}"
    )
    _check_range(o.spacing_range, "orchard.spacing_range")
    _check(o.row_spacing > 0, "orchard.row_spacing", f"must be positive, got {o.row_spacing}")


def _validate_trees(o: OrchardSpec) -> None:
    """The trees: crown, trunk and branch sizes, missing and double trees, crown forms and
    foliage."""
    _check_range(o.crown_diameter_range, "orchard.crown_diameter_range")
    _check_range(o.crown_across_ratio_range, "orchard.crown_across_ratio_range")
    _check_range(o.crown_height_ratio_range, "orchard.crown_height_ratio_range")
    _check_range(o.crown_base_height_range, "orchard.crown_base_height_range", strict=False)
    _check_range(o.crown_squareness_range, "orchard.crown_squareness_range", low=1.0, strict=False)
    _check_range(o.trunk_radius_range, "orchard.trunk_radius_range")
    _check_range(o.leaf_cluster_size_range, "orchard.leaf_cluster_size_range")
    _check_range([float(v) for v in o.branches_range], "orchard.branches_range", strict=False)
    _check_range(o.double_offset_range, "orchard.double_offset_range")
    for name in ("missing_probability", "double_probability"):
        p = getattr(o, name)
        _check(0.0 <= p < 1.0, f"orchard.{name}", f"must be in [0, 1), got {p}")
    _check(
        0.0 <= o.young_probability < 1.0,
        "orchard.young_probability",
        f"must be in [0, 1), got {o.young_probability}",
    )
    _validate_trellis(o)
    for name in ("crown_scale", "replanted_crown_scale", "young_crown_scale"):
        _check(getattr(o, name) > 0, f"orchard.{name}", f"must be positive, got {getattr(o, name)}")
    _check(
        0 <= o.crown_irregularity < 0.5,
        "orchard.crown_irregularity",
        f"must be in [0, 0.5), got {o.crown_irregularity}",
    )
    from canopy_kit.sim.crown_forms import CROWN_FORMS

    _check(
        o.crown_form in CROWN_FORMS,
        "orchard.crown_form",
        f"must be one of {', '.join(CROWN_FORMS)}, got {o.crown_form!r}",
    )
    _check_range(o.lobe_hollow_range, "orchard.lobe_hollow_range")
    _check(
        o.lobe_hollow_range[1] < 1.0,
        "orchard.lobe_hollow_range",
        f"the radius between lobes must be below the lobes' (1), got {o.lobe_hollow_range}",
    )
    _check(
        0.2 <= o.hedge_cut <= 1.0, "orchard.hedge_cut", f"must be in [0.2, 1], got {o.hedge_cut}"
    )
    for name in ("sparse_crown_scale", "sparse_foliage_scale"):
        _check(
            0 < getattr(o, name) <= 1,
            f"orchard.{name}",
            f"must be in (0, 1], got {getattr(o, name)}",
        )
    _check(
        o.leaf_penetration_m > 0,
        "orchard.leaf_penetration_m",
        f"must be positive (inf: leaves through the whole crown), got {o.leaf_penetration_m}",
    )
    _check(
        o.foliage_density_shell > 0,
        "orchard.foliage_density_shell",
        f"must be positive, got {o.foliage_density_shell}",
    )
    _check(
        o.foliage_density_core >= 0,
        "orchard.foliage_density_core",
        f"must not be negative, got {o.foliage_density_core}",
    )


def _validate_orchard_room(o: OrchardSpec) -> None:
    """Headlands and margins, and room in the alleys and the orchard for the crowns."""
    for name in ("headland", "margin"):
        _check(
            getattr(o, name) >= 0,
            f"orchard.{name}",
            f"must not be negative, got {getattr(o, name)}",
        )
    lane = o.row_spacing - 2 * o.alley_clearance
    _check(
        lane > 0.5,
        "orchard.alley_clearance",
        f"a {o.alley_clearance} m half-corridor leaves no room for crowns between rows "
        f"{o.row_spacing} m apart",
    )
    max_extent = max(o.rows * o.row_spacing, o.trees_per_row * o.spacing_range[1])
    _check(
        o.crown_diameter_range[1] * o.crown_across_ratio_range[0] <= max_extent + lane,
        "orchard.crown_diameter_range",
        f"crowns up to {o.crown_diameter_range[1]} m are larger than the orchard",
    )


def _validate_lidar(li: LidarSpec, imu: ImuSpec) -> None:
    """The LiDAR: beams, rate, ranges, mount, and the firing and output formats that go
    together (Velodyne, Livox and Ouster limits)."""
    _check(li.rings >= 1, "lidar.rings", f"must be at least 1, got {li.rings}")
    _check(li.columns >= 16, "lidar.columns", f"must be at least 16, got {li.columns}")
    _check(
        len(li.vertical_fov) == 2,
        "lidar.vertical_fov",
        f"expected [lowest, highest] beam elevation, got {li.vertical_fov}",
    )
    _check(
        li.vertical_fov[0] < li.vertical_fov[1] or li.rings == 1,
        "lidar.vertical_fov",
        f"lowest beam {li.vertical_fov[0]} must be below highest {li.vertical_fov[1]}",
    )
    _check(
        -90 <= li.vertical_fov[0] and li.vertical_fov[1] <= 90,
        "lidar.vertical_fov",
        "elevations must be within [-90, 90] degrees",
    )
    _check(li.rate_hz > 0, "lidar.rate_hz", f"must be positive, got {li.rate_hz}")
    _check(
        0 < li.min_range < li.max_range,
        "lidar.min_range/max_range",
        f"need 0 < min_range < max_range, got {li.min_range}, {li.max_range}",
    )
    _check(li.range_noise >= 0, "lidar.range_noise", f"must not be negative, got {li.range_noise}")
    _check(0 <= li.dropout < 1, "lidar.dropout", f"must be in [0, 1), got {li.dropout}")
    _check(li.mount_height > 0, "lidar.mount_height", f"must be positive, got {li.mount_height}")
    if li.firing == "vlp16" or li.output == "velodyne_packets":  # canopy_kit.sim.velodyne
        _check(
            5.0 <= li.rate_hz <= 20.0,
            "lidar.rate_hz",
            f"a VLP-16 turns at 5-20 Hz (300-1200 rpm), got {li.rate_hz}",
        )
        _check(
            li.max_range <= 131.07,
            "lidar.max_range",
            f"a VLP-16 packet holds ranges up to 131.07 m, got {li.max_range}",
        )
    livox = li.firing.startswith("livox")
    _check(
        livox == (li.output == "livox_custom") or (livox and li.output == "points"),
        "lidar.output",
        f"{li.output!r} does not go with firing {li.firing!r} (livox_custom needs a Livox "
        "firing; a Livox firing writes livox_custom or points)",
    )
    _check(
        imu.output != "ouster_packets" or li.output == "ouster_packets",
        "imu.output",
        "Ouster IMU packets need the Ouster's lidar packets (lidar.output = 'ouster_packets')",
    )
    if li.output == "ouster_packets":
        from canopy_kit.sim.ouster import check_spec

        for name, problem in check_spec(li):
            _check(False, name, problem)


def _validate_drive(d: DriveSpec) -> None:
    """The robot's speeds and acceleration."""
    for name in ("cruise_speed", "turn_speed"):
        _check(getattr(d, name) > 0, f"drive.{name}", f"must be positive, got {getattr(d, name)}")
    _check(d.lead_in >= 0, "drive.lead_in", f"must not be negative, got {d.lead_in}")
    _check(d.acceleration > 0, "drive.acceleration", f"must be positive, got {d.acceleration}")
    _check(
        0 <= d.speed_variation < d.cruise_speed,
        "drive.speed_variation",
        "must be below cruise_speed",
    )


def _validate_rig(c: SimConfig) -> None:
    """The sensors' rig: the IMU's mounting error and clock offset, and a named rig that
    exists."""
    _check(
        len(c.rig.tf_imu_error_rpy_deg) == 3,
        "rig.tf_imu_error_rpy_deg",
        f"expected [roll, pitch, yaw], got {c.rig.tf_imu_error_rpy_deg}",
    )
    _check(
        abs(c.rig.imu_time_offset) < 1.0,
        "rig.imu_time_offset",
        f"must be below 1 s in magnitude, got {c.rig.imu_time_offset}",
    )
    if c.rig.name != "identity":
        from canopy_kit.sim.rig import sensor_mounts

        sensor_mounts(c)  # the rig exists and names its frames


def _validate_drone(dr: DroneSpec) -> None:
    """The drone flight: overlaps, altitude, camera and photos, speed."""
    for name in ("forward_overlap", "side_overlap"):
        _check(
            0 < getattr(dr, name) < 1,
            f"drone.{name}",
            f"must be in (0, 1), got {getattr(dr, name)}",
        )
    _check(dr.altitude > 0, "drone.altitude", f"must be positive, got {dr.altitude}")
    _check(
        dr.image_width >= 64 and dr.image_height >= 64,
        "drone.image_width/image_height",
        f"must be at least 64 px, got {dr.image_width}x{dr.image_height}",
    )
    for name in ("focal_length_mm", "sensor_width_mm"):
        _check(getattr(dr, name) > 0, f"drone.{name}", f"must be positive, got {getattr(dr, name)}")
    _check(
        1 <= dr.jpeg_quality <= 100,
        "drone.jpeg_quality",
        f"must be in [1, 100], got {dr.jpeg_quality}",
    )
    _check(
        dr.flight_speed > 0,
        "drone.flight_speed",
        f"must be positive, got {dr.flight_speed}",
    )
    _validate_drone_pattern(dr)


def _validate_drone_pattern(d: DroneSpec) -> None:
    """The flight pattern and an oblique camera that sees the ground across its whole frame."""
    _check(
        d.pattern in ("nadir", "double-grid", "single-grid", "orbit"),
        "drone.pattern",
        f"must be nadir, double-grid, single-grid or orbit, got {d.pattern!r}",
    )
    half_fov = math.degrees(
        math.atan(d.image_height / 2 * d.sensor_width_mm / d.image_width / d.focal_length_mm)
    )
    _check(
        -90.0 <= d.gimbal_pitch_deg <= -20.0 and d.gimbal_pitch_deg + half_fov <= -5.0,
        "drone.gimbal_pitch_deg",
        f"must be between -90 and -20 with the image's top edge at least 5 deg below the "
        f"horizon (half the vertical field of view is {half_fov:.1f} deg), got "
        f"{d.gimbal_pitch_deg}",
    )


def _validate_trellis(o: OrchardSpec) -> None:
    """The trellis settings of ``[orchard]``."""
    _check(
        o.trellis_post_spacing >= 0,
        "orchard.trellis_post_spacing",
        f"must not be negative (0: no trellis), got {o.trellis_post_spacing}",
    )
    for name in ("trellis_post_height", "trellis_post_radius", "trellis_wire_radius"):
        _check(getattr(o, name) > 0, f"orchard.{name}", f"must be positive, got {getattr(o, name)}")
    _check(
        o.trellis_end_overhang >= 0,
        "orchard.trellis_end_overhang",
        f"must not be negative, got {o.trellis_end_overhang}",
    )
    _check(
        0 <= o.trellis_end_post_lean_deg < 60,
        "orchard.trellis_end_post_lean_deg",
        f"must be at least 0 and below 60 degrees, got {o.trellis_end_post_lean_deg}",
    )
    _check(
        all(0 < h < o.trellis_post_height for h in o.trellis_wire_heights),
        "orchard.trellis_wire_heights",
        f"wires hang between the ground and the post tops ({o.trellis_post_height} m), "
        f"got {o.trellis_wire_heights}",
    )
    _check(
        o.drip_line_height >= 0 and o.drip_line_radius > 0,
        "orchard.drip_line_height/drip_line_radius",
        f"height must not be negative and radius positive, got {o.drip_line_height}, "
        f"{o.drip_line_radius}",
    )


def _validate_gnss(g: GnssSpec) -> None:
    """The receiver-behaviour settings of ``[gnss]``."""
    for name, width in (("outages", 2), ("jumps", 3), ("rtk_intervals", 2)):
        for i, item in enumerate(getattr(g, name)):
            _check(
                len(item) == width,
                f"gnss.{name}[{i}]",
                f"expected [{'start_s, duration_s' + (', offset_m' if width == 3 else '')}], got {item}",
            )
            _check(
                item[0] >= 0 and item[1] > 0,
                f"gnss.{name}[{i}]",
                f"start must be >= 0 and duration positive, got {item}",
            )
    _check_range(g.outage_duration_range, "gnss.outage_duration_range")
    _check_range(g.jump_duration_range, "gnss.jump_duration_range")
    _check_range(g.jump_offset_range, "gnss.jump_offset_range", strict=False)
    _check(
        g.outage_status in (-1, 0, 1, 2),
        "gnss.outage_status",
        f"must be -1, 0, 1 or 2, got {g.outage_status}",
    )
    _check(
        g.standalone_status in (0, 1),
        "gnss.standalone_status",
        f"must be 0 (FIX) or 1 (SBAS), got {g.standalone_status}",
    )
    _check(
        g.covariance_type in (0, 1, 2, 3),
        "gnss.covariance_type",
        f"must be 0, 1, 2 or 3 (NavSatFix COVARIANCE_TYPE_*), got {g.covariance_type}",
    )
    _check(
        not (g.rtk_intervals and g.mode == "rtk"),
        "gnss.rtk_intervals",
        "mode 'rtk' is RTK for the whole drive; rtk_intervals need mode 'standard'",
    )
