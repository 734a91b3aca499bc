"""Typed configuration: one dataclass per concern, loaded from TOML presets.

Unknown keys and wrong types are errors that name the key; the config actually used is
written next to every result (:func:`write_config`) so each number can be reproduced.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

from canopy_kit.errors import ConfigError, InputError
from canopy_kit.plugins.params import check_choice

T = TypeVar("T")


@dataclass
class MappingConfig:
    """LiDAR(-inertial) odometry and map building (``canopy_kit.mapping``, docs/MAPPING.md)."""

    # Map
    map_voxel_size: float = 0.05
    min_range: float = 1.0
    max_range: float = 60.0
    # The map keeps returns up to this range (the odometry uses them up to ``max_range``):
    # far returns help the registration but map as clutter, and a small attitude error moves
    # them most (0.3 deg at 50 m is 0.26 m): a LiDAR pitched 12 deg saw the headland's far
    # ground as 1.1 m "trees" (docs/MAPPING.md, "Measured on robot rigs").
    map_max_range: float = 30.0
    # Odometry front end (KISS-ICP on deskewed sweeps with the ground removed)
    deskew: bool = True
    use_imu: bool = True
    use_gnss: bool = True
    odometry_ground_band: float = 0.15
    odometry_ground_refine: bool = True
    odometry_point_stride: int = 1
    # Register every n-th sweep (build_map), or sooner where the vehicle turns or moves fast;
    # the sweeps between are placed by the fused continuous trajectory (odometry
    # interpolated, gyro rotation) in the map pass.
    odometry_every: int = 3
    # The sweeps left unregistered still go into KISS-ICP's local map, at their predicted
    # pose, so the map does not lag the sensor by the sweeps between registrations (a lag
    # that made the odometry under-measure the distance driven, docs/MAPPING.md "Livox
    # Mid-360 trajectory error"): +14-19 % of the mapping's CPU, ATE -0.1 to -0.5 cm on the
    # spinning sensors, 5.4 -> 3.8-4.4 cm on a Livox Mid-360. "auto": on when the LiDAR sees
    # no ground beside the robot, read from the first scans (the lowest returns above -11 deg,
    # mapping.ground_view); true / false: always / never. The decision is in the mapping
    # diagnostics (metrics.json "mapping" > "odometry_map_skipped").
    odometry_map_skipped: bool | Literal["auto"] = "auto"
    # Long drives: the odometry runs in consecutive chunks of at least this many scans on
    # ``workers`` processes (mapping.chunks), tied together where they overlap.
    odometry_chunk_sweeps: int = 600
    kiss_voxel_size: float = 0.5
    kiss_max_points_per_voxel: int = 20
    # KISS-ICP's ICP stops when an iteration moves the pose by less than this (its own default
    # 1e-4; 1e-3 saved 18 % of the odometry at the same trajectory error, docs/history/BENCHMARKS_LOG.md).
    kiss_convergence: float = 1e-3
    min_points_per_scan: int = 500
    odometry_max_correction: float = 0.15
    odometry_max_correction_deg: float = 1.5
    # KISS-ICP threads. 1 keeps runs bit-reproducible; 0 (all cores) is faster but its
    # parallel sums change the last bits of poses from run to run, and so of trees.csv.
    threads: int = 1
    # Processes for the odometry chunks and the map pass (0: one per core; 1: no workers).
    workers: int = 0
    # Pose graph: keyframes and the odometry error model (jitter plus drift)
    keyframe_every: int = 5
    odometry_jitter_rotation: float = 0.002
    odometry_jitter_translation: float = 0.015
    odometry_drift_rotation: float = 0.0002
    odometry_drift_translation: float = 0.003
    # IMU noise (datasheet values; per sqrt(Hz))
    gyro_noise_density: float = 0.005
    accel_noise_density: float = 0.05
    gyro_bias_walk: float = 5e-5
    accel_bias_walk: float = 1e-3
    # GNSS: epochs, error model, and the antenna lever arm in the LiDAR frame (used only
    # when neither /tf_static nor the rig relates the receiver's frame to the LiDAR's)
    gnss_epoch: float = 1.0
    gnss_correlation_time: float = 30.0
    gnss_white_fraction: float = 0.3
    gnss_default_sigma_horizontal: float = 1.5
    gnss_default_sigma_vertical: float = 3.0
    gnss_lever_arm: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # Topics (empty: the busiest topic of the type)
    pointcloud_topic: str = ""
    # Ouster packet bags: the sensor's metadata JSON when the bag has no /ouster/metadata topic
    ouster_metadata: str = ""
    imu_topic: str = ""
    gnss_topic: str = ""
    # Sensor rig (docs/MAPPING.md, "Sensor rigs"): extrinsics from the bag's /tf_static,
    # given or overridden by ``rig`` (a rig file's tables; ``--rig FILE`` puts them here and
    # its path in ``rig_name``). ``extrinsics``: "auto" stops when the LiDAR and the IMU
    # stamp different frames and nothing relates them; "identity" takes them for one frame;
    # "calibrate" estimates the IMU's rotation from the drive (one more odometry pass).
    # The rotation is always checked against the data: a warning past ``extrinsic_tolerance_deg``.
    rig: dict[str, Any] = field(default_factory=dict)
    rig_name: str = ""
    extrinsics: Literal["auto", "identity", "calibrate"] = "auto"
    base_frame: str = (
        ""  # the frame the trajectory is reported in (default: base_link, else the LiDAR's)
    )
    extrinsic_tolerance_deg: float = 2.0

    def __post_init__(self) -> None:
        value = self.odometry_map_skipped
        if not (isinstance(value, bool) or (isinstance(value, str) and value == "auto")):
            raise ConfigError(
                f'mapping.odometry_map_skipped: expected true, false or "auto", got {value!r}'
            )


@dataclass
class PreprocessConfig:
    """Ground, trunk and low-vegetation removal and the voxel grid (``canopy_kit.segment``).

    Heights are above the piecewise RANSAC ground model. ``stem_band`` is where trunks are
    looked for; canopy is ``min_canopy_height``..``max_canopy_height``; an unset
    ``max_canopy_height`` follows the trees (the top of the map's height distribution below
    its first empty band, ``segment.preprocess.canopy_ceiling``), a set one is a fixed
    limit and crowns reaching it are named in a warning. ``voxelize`` orders
    the voxel grid and the clustering (the paper's text and Fig. 3 disagree);
    ``weight_by_density`` makes each voxel count as the map points it holds.
    """

    ground_cell_size: float = 4.0
    ground_ransac_threshold: float = 0.15
    ground_candidate_cell: float = 0.5
    min_canopy_height: float = 0.8
    max_canopy_height: float | None = None  # None: from the data
    stem_band: list[float] = field(default_factory=lambda: [0.3, 0.8])
    voxel_size: float = 0.1
    voxelize: Literal["before_clustering", "after_clustering"] = "before_clustering"
    weight_by_density: bool = True


@dataclass
class SegmentConfig:
    """Which segmenter plugin to use and its keyword arguments."""

    method: str = "adaptive"
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class RowsConfig:
    """Grouping tree centroids into rows and labelling them (L0.., R0..).

    ``driving_direction`` is the bearing in degrees (clockwise from north, the map's +y)
    of the first pass along the rows; ``None`` takes it from a trajectory when one is
    given, else uses the row direction pointing north of east-west (see ``segment.rows``).
    """

    max_distance_to_row: float = 1.5
    min_trees_per_row: int = 2
    curved_rows: bool = True
    driving_direction: float | None = None


@dataclass
class VolumeConfig:
    """Volume estimator plugins to run per tree and their keyword arguments.

    ``voxel_size``: volumes are measured on each tree's points thinned to this voxel grid
    (the paper measures its 0.1 m voxel grid; docs/VOLUMES.md's accuracy figures are on it
    too); 0 measures every map point. Height and crown metrics always use every point.

    ``recommended``: the estimator whose volume the table's interval columns
    (``volume_low_m3``, ``volume_high_m3``, ``canopy_kit.volume.uncertainty``) bound; it is
    run even when not in ``methods``. Default the paper's ``alpha_shape``; the ``adaptive``
    preset recommends ``foliage_envelope`` (docs/VOLUMES.md, "Tree families").

    ``interval_kind``: the kind of tree whose calibrated ratios the interval takes for every
    tree ("": each tree's own kind of crown, from its points); ``"wall"`` for trees cut from
    a fruiting wall at their trunks (the ``wall`` preset: a slab of the wall, whatever its
    surface fill says).
    """

    methods: list[str] = field(default_factory=lambda: ["convex_hull", "alpha_shape"])
    params: dict[str, dict[str, Any]] = field(default_factory=dict)
    voxel_size: float = 0.1
    workers: int = 0  # processes measuring trees (0: one per core; 1: this process only)
    recommended: str = "alpha_shape"
    interval_kind: str = ""

    def __post_init__(self) -> None:
        if not (isinstance(self.workers, int) and self.workers >= 0):
            raise ConfigError(
                f"volume.workers: must be an integer >= 0 (0: one per core), got {self.workers!r}"
            )
        if not (isinstance(self.voxel_size, (int, float)) and self.voxel_size >= 0):
            raise ConfigError(
                f"volume.voxel_size: must be a number >= 0 (0: every map point), "
                f"got {self.voxel_size!r}"
            )
        if not (isinstance(self.recommended, str) and self.recommended):
            raise ConfigError(
                f"volume.recommended: must be the name of a volume method, got {self.recommended!r}"
            )
        if self.interval_kind not in ("", "wall"):
            raise ConfigError(
                "volume.interval_kind: must be '' (each tree's own kind of crown) or 'wall' "
                f"(trees cut from a fruiting wall at their trunks), got {self.interval_kind!r}"
            )


# How crowns are found without seed trees (``ground_truth.crowns.delineate_crowns``).
CROWN_SEEDINGS = ("rows", "chm_maxima")


@dataclass
class GroundTruthConfig:
    """Drone photogrammetry ground truth (``ground_truth.process_flight``, docs/GROUND_TRUTH.md).

    The one set of settings of the drone pipeline: a preset's ``[ground_truth]`` table fills
    it, ``canopy-kit run`` and ``canopy-kit ground-truth`` pass it to ``process_flight``, and it
    is written next to the results. Every key changes the result
    (tests/test_ground_truth_config.py).
    """

    # Longest side (px) of the photos pycolmap extracts SIFT features from.
    max_image_size: int = 1600
    # Longest side (px) of the photos the surface models and the orthomosaic are made from.
    work_image_size: int = 2000
    # Orthomosaic cell size (m); unset: the ground sampling distance, at least 2 cm.
    ortho_resolution: float | None = None
    # Highest canopy (m above ground) the surface matching searches; unset: from the flight's
    # sparse points (ground_truth.dsm.search_height: the trees' own height, plus 2 m).
    max_canopy_height: float | None = None
    # A crown farther than this from a tree is not that tree's crown (seeded or not).
    match_distance_m: float = 1.5
    # Seed the crowns with the given trees' positions (the LiDAR's in a run); false: find them
    # from the imagery alone (crown_seeds) and only match them to the trees.
    crowns_from_seeds: bool = True
    # Crowns without seed trees: "rows" (one seed per tree along the rows seen in the
    # canopy, for touching crowns) or "chm_maxima" (local maxima of the canopy height model).
    crown_seeds: str = "rows"
    # Planting distance along the row (m) for "rows"; unset: the crowns' width across the row.
    tree_spacing_m: float | None = None
    # The rows' bearing from north (degrees, 0-180) for the rows seeding and the along/across
    # extents; unset: found in the imagery (the canopy's rows, else the crowns' neighbours).
    row_bearing_deg: float | None = None
    # Move the seed trees by their measured offset from the crowns and delineate again.
    register_seeds: bool = True
    # An aerial crown whose diameter is outside this ratio of the LiDAR crown diameter is a
    # fragment or a merge of neighbours: kept in the table, flagged, left out of the statistics.
    min_diameter_ratio: float = 0.6
    max_diameter_ratio: float = 1.6
    # Carve each crown's visual hull from its silhouettes in every registered photo
    # (hull_volume_m3; the recommended aerial volume of an oblique flight); false: skip it.
    hull_volume: bool = True
    # Grow a crown's outline by this much (m, never into a neighbour's) before carving its
    # hull, when its oblique views come from bearings all round (the silhouettes then bound
    # its sides; outlines run narrow on porous crowns); 0: never.
    hull_outline_margin_m: float = 0.6

    def __post_init__(self) -> None:
        if not isinstance(self.hull_volume, bool):
            raise ConfigError(
                f"ground_truth.hull_volume: expected true or false, got {self.hull_volume!r}"
            )
        value = self.hull_outline_margin_m
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not 0 <= value <= 5
            or value != value
        ):
            raise ConfigError(
                "ground_truth.hull_outline_margin_m: expected a distance in metres from 0 "
                f"(never grow the crown outlines) to 5, got {value!r}"
            )
        for name in ("max_image_size", "work_image_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 64:
                raise ConfigError(
                    f"ground_truth.{name}: expected an integer >= 64 (px), got {value!r}"
                )
        value = self.match_distance_m
        if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
            raise ConfigError(
                f"ground_truth.match_distance_m: expected a number > 0, got {value!r}"
            )
        check_choice(self.crown_seeds, "ground_truth.crown_seeds", None, CROWN_SEEDINGS)
        bearing = self.row_bearing_deg
        if bearing is not None and (
            isinstance(bearing, bool)
            or not isinstance(bearing, int | float)
            or not 0 <= bearing < 360
        ):
            raise ConfigError(
                "ground_truth.row_bearing_deg: expected a bearing from north in degrees "
                f"(0 <= value < 360) or no value (found in the imagery), got {bearing!r}"
            )
        for name, unset in (
            ("ortho_resolution", "the ground sampling distance"),
            ("tree_spacing_m", "the crowns' width across the row"),
            ("max_canopy_height", "from the flight's sparse points"),
        ):
            value = getattr(self, name)
            if value is not None and (
                isinstance(value, bool) or not isinstance(value, int | float) or value <= 0
            ):
                raise ConfigError(
                    f"ground_truth.{name}: expected a number > 0 (m) or no value ({unset}), "
                    f"got {value!r}"
                )
        if not 0 <= self.min_diameter_ratio < self.max_diameter_ratio:
            raise ConfigError(
                "ground_truth.min_diameter_ratio/max_diameter_ratio: expected "
                f"0 <= min < max, got {self.min_diameter_ratio} and {self.max_diameter_ratio}"
            )


@dataclass
class ChecksConfig:
    """Thresholds of the checks that need no truth (``canopy_kit.results.checks``, docs/VALIDATION.md).

    Each pair is (warn, fail): a value beyond ``*_warn`` warns, beyond ``*_fail`` fails the
    run (``run --strict`` exits 4). Ratios are crown diameter over a spacing measured on
    the same map; shares are fractions of the segmented trees; the aerial MAPE is the
    alpha-shape volume against the drone's height-aware ellipsoid (the paper's sphere is
    itself biased by +28 % to +85 %, docs/GROUND_TRUTH.md, so it never fails a run).
    """

    crown_row_spacing_warn: float = 1.0
    crown_row_spacing_fail: float = 1.75
    crown_tree_spacing_warn: float = 2.0
    crown_tree_spacing_fail: float = 3.0
    trunks_per_segment_warn: int = 2
    trunks_per_segment_fail: int = 3
    # Segments on no trunk of their own, closer to a neighbour than this share of the tree
    # spacing: pieces of a split crown (counted; any fails by default).
    trunkless_neighbour_ratio: float = 0.7
    split_crowns_warn: int = 0
    split_crowns_fail: int = 0
    # Share of trees whose crown reaches the map's outline (it may end inside them).
    crowns_at_map_edge_share_warn: float = 0.0
    crowns_at_map_edge_share_fail: float = 0.25
    # Trees whose tops a set preprocess.max_canopy_height cut (counted; any fails).
    crowns_cut_at_ceiling_warn: int = 0
    crowns_cut_at_ceiling_fail: int = 0
    crown_outlier_share_warn: float = 0.0
    crown_outlier_share_fail: float = 0.10
    flagged_volume_share_warn: float = 0.0
    flagged_volume_share_fail: float = 0.10
    rejected_registrations_share_warn: float = 0.02
    rejected_registrations_share_fail: float = 0.10
    gnss_rejected_share_warn: float = 0.10
    gnss_rejected_share_fail: float = 0.50
    gnss_bias_rms_warn_m: float = 3.0
    gnss_bias_rms_fail_m: float = 10.0
    aerial_matched_share_warn: float = 0.95
    aerial_matched_share_fail: float = 0.90
    aerial_mape_warn_pct: float = 40.0
    aerial_mape_fail_pct: float = 60.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if not f.name.endswith("_warn") and "_warn_" not in f.name:
                continue
            fail_name = f.name.replace("_warn", "_fail")
            warn, fail = getattr(self, f.name), getattr(self, fail_name)
            if isinstance(warn, bool) or not isinstance(warn, int | float) or warn < 0:
                raise ConfigError(f"checks.{f.name}: expected a number >= 0, got {warn!r}")
            lower_is_worse = f.name.startswith("aerial_matched")
            if (warn < fail) if lower_is_worse else (warn > fail):
                raise ConfigError(
                    f"checks.{f.name}/{fail_name}: the warning threshold must come "
                    f"before the failure threshold, got {warn} and {fail}"
                )


@dataclass
class PipelineConfig:
    """Everything one run needs; a preset fills it, the CLI overrides parts."""

    name: str = "custom"
    orchard: str = "generic"
    seed: int = 0
    mapping: MappingConfig = field(default_factory=MappingConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    segment: SegmentConfig = field(default_factory=SegmentConfig)
    rows: RowsConfig = field(default_factory=RowsConfig)
    volume: VolumeConfig = field(default_factory=VolumeConfig)
    ground_truth: GroundTruthConfig = field(default_factory=GroundTruthConfig)
    checks: ChecksConfig = field(default_factory=ChecksConfig)

    def __post_init__(self) -> None:
        if isinstance(self.seed, int) and self.seed < 0:  # numpy seeds are non-negative
            raise ConfigError(f"config.seed: expected a non-negative integer, got {self.seed}")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _choices(tp: Any) -> str:
    """'true, false or "auto"' for a union of ``bool`` and literals (empty for other types)."""
    values: list[str] = []
    for arg in get_args(tp):
        if arg is bool:
            values += ["true", "false"]
        elif get_origin(arg) is Literal:
            values += [f'"{v}"' if isinstance(v, str) else repr(v) for v in get_args(arg)]
        else:
            return ""
    return ", ".join(values[:-1]) + f" or {values[-1]}" if len(values) > 1 else ""


def _convert(value: Any, tp: Any, where: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and convert it (ints to floats etc.)."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table, got {type(value).__name__}")
        return from_dict(tp, value, where)
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(f"{where}: {value!r} is not one of {list(get_args(tp))}")
        return value
    if origin in (typing.Union, types.UnionType):
        errors = []
        for arg in get_args(tp):
            if arg is type(None) and value is None:
                return None
            try:
                return _convert(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        choices = _choices(tp)
        if choices:
            raise ConfigError(f"{where}: expected {choices}, got {value!r}")
        raise ConfigError(f"{where}: {value!r} does not match {_type_name(tp)}")
    if origin is list:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected a list, got {type(value).__name__}")
        (item,) = get_args(tp) or (Any,)
        return [_convert(v, item, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table, got {type(value).__name__}")
        _, val_tp = get_args(tp) or (str, Any)
        return {str(k): _convert(v, val_tp, f"{where}.{k}") for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if isinstance(tp, type) and not isinstance(value, tp):
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
    return value


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = "config") -> T:
    """Build dataclass ``cls`` from a mapping; unknown keys and wrong types are errors."""
    hints = get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key {unknown[0]!r} (known keys: {', '.join(sorted(known))})"
        )
    kwargs = {k: _convert(v, hints[k], f"{where}.{k}") for k, v in data.items()}
    return cls(**kwargs)


def to_dict(obj: Any) -> dict[str, Any]:
    """Plain-dict form of a config dataclass, ready for TOML or JSON."""
    return dataclasses.asdict(obj)


def merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Deep-merge ``override`` into ``base`` (tables merge, other values replace)."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def read_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file, naming the file in any error."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: file does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def preset_names() -> list[str]:
    """Names of the presets shipped in ``canopy_kit/presets``."""
    files = resources.files("canopy_kit") / "presets"
    return sorted(p.name[:-5] for p in files.iterdir() if p.name.endswith(".toml"))


def load_preset(
    name_or_path: str | Path, overrides: Mapping[str, Any] | None = None
) -> PipelineConfig:
    """Load a shipped preset by name (``pistachio``, ``almond``) or a TOML file by path."""
    text_name = str(name_or_path)
    if text_name in preset_names():
        data = tomllib.loads(
            (resources.files("canopy_kit") / "presets" / f"{text_name}.toml").read_text()
        )
        where = f"preset {text_name!r}"
    else:
        path = Path(name_or_path)
        if not path.exists():
            raise ConfigError(
                f"preset {text_name!r} is neither a shipped preset "
                f"({', '.join(preset_names())}) nor an existing TOML file"
            )
        data = read_toml(path)
        where = str(path)
    if overrides:
        data = apply_overrides(data, overrides)
    config = from_dict(PipelineConfig, data, where)
    check_plugin_param_types(config, where)
    return config


def check_plugin_param_types(config: PipelineConfig, where: str = "config") -> None:
    """ConfigError naming the key when a plugin parameter of ``config`` misfits the type the
    plugin's ``__init__`` annotates (a string for a float...). Plugins that are not
    registered are left to ``pipeline.check_settings``, which names them."""
    from canopy_kit import plugins
    from canopy_kit.errors import PluginError
    from canopy_kit.plugins.params import check_types

    tables = [
        ("segmenters", config.segment.method, config.segment.params, f"{where}.segment.params")
    ]
    tables += [
        ("volumes", method, params, f"{where}.volume.params.{method}")
        for method, params in config.volume.params.items()
    ]
    for kind, name, params, at in tables:
        try:
            target = plugins.load(kind, name)
        except PluginError:
            continue
        if isinstance(target, type):
            check_types(params, target, at)


def parse_settings(items: Iterable[str], where: str = "--set") -> dict[str, Any]:
    """``["orchard.rows=3", "lidar.rings=16"]`` to a nested dict; values parsed as TOML (text
    that is not TOML stays text). ``where`` starts the error for an item without ``=``."""
    flat: dict[str, Any] = {}
    for item in (part.strip() for part in items):
        if not item:
            continue
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{where} {item!r}: expected section.key=value")
        try:
            flat[key.strip()] = tomllib.loads(f"v = {raw.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            flat[key.strip()] = raw.strip()
    return nested_settings(flat)


def nested_settings(settings: Mapping[str, Any]) -> dict[str, Any]:
    """``{"mapping.threads": 1}`` and ``{"mapping": {"threads": 1}}`` both become the latter."""
    out: dict[str, Any] = {}
    for key, value in settings.items():
        node = out
        parts = str(key).split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = nested_settings(value) if isinstance(value, Mapping) else value
    return out


def apply_overrides(data: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """A preset's tables with ``overrides`` merged in (:func:`merge`), as a run uses them.

    The preset's ``segment.params`` belong to its own ``segment.method``: an override naming
    another method starts from that method's defaults (plus any ``segment.params`` it gives).
    """
    base = dict(data)
    seg_over, seg_base = overrides.get("segment"), base.get("segment")
    if (
        isinstance(seg_over, Mapping)
        and isinstance(seg_base, Mapping)
        and "method" in seg_over
        and seg_over["method"] != seg_base.get("method", SegmentConfig.method)
    ):
        base["segment"] = {k: v for k, v in seg_base.items() if k != "params"}
    return merge(base, overrides)


def config_toml(config: Any) -> str:
    """A config dataclass as TOML text (None values left out: TOML has no null)."""
    import tomlkit

    return tomlkit.dumps(_drop_none(to_dict(config)))


def write_config(config: Any, path: str | Path) -> Path:
    """Write a config dataclass as TOML, atomically."""
    from canopy_kit.core.atomic import atomic_write_text

    return atomic_write_text(path, config_toml(config))


def _drop_none(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _drop_none(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [_drop_none(v) for v in value]
    return value
