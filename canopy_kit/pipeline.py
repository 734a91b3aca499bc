"""The whole chain for one field session: bag → map → trees → volumes → checks → report.

``run(config, bag, out)`` is the public entry point; each stage is a small function below and
its result is cached by a hash of its inputs and settings (``canopy_kit.cache``), so changing
a segmentation parameter re-runs segmentation and what follows, not the mapping.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.cache import StageCache, fingerprint, stage_key
from canopy_kit.config import GroundTruthConfig, PipelineConfig, write_config
from canopy_kit.errors import InputError
from canopy_kit.io.atomic import atomic_path, atomic_write_json, atomic_write_text

Progress = Callable[[str, float, float], None]


@dataclass
class Results:
    """What a run produced: the per-tree table, metrics and where the files are."""

    out_dir: Path
    trees: pd.DataFrame
    metrics: dict[str, Any]
    files: dict[str, Path]
    warnings: list[str] = field(default_factory=list)
    cache_hits: list[str] = field(default_factory=list)


@dataclass
class RunContext:
    """Intermediate results handed between stages (also what notebooks explore)."""

    config: PipelineConfig
    mapping: Any = None
    segmentation: Any = None
    trees: pd.DataFrame | None = None
    aerial: Any = None
    table: pd.DataFrame | None = None  # the final per-tree table
    evaluation: dict[str, Any] = field(default_factory=dict)
    truth_matches: pd.DataFrame | None = None  # per true tree: status and matched segment
    truth_dir: Path | None = None  # simulated session the run was checked against
    layout: Any = None  # row and tree spacing, trunks per segment (segment.layout.Layout)


def run(config: PipelineConfig, bag: str | Path, out: str | Path,
        drone_images: str | Path | None = None, truth: str | Path | None = None,
        use_cache: bool = True, progress: Progress | None = None,
        orchard: str | None = None, export_trees: bool = False) -> Results:
    """Run every stage on ``bag`` and write the outputs (all atomically) into ``out``.

    ``orchard`` names the orchard or block in the provenance (default: the bag's stem);
    ``export_trees`` also writes each tree's points as ``trees/<tree_id>.laz``.
    """
    from canopy_kit.provenance import provenance

    out = Path(out)
    report = progress or (lambda *_: None)
    started, t0 = time.time(), time.perf_counter()
    ctx, cache = compute(config, bag, out, drone_images, truth, use_cache, report)
    metrics = run_metrics(ctx, ctx.table)
    metrics["stage_timings"] = cache.timings
    metrics["cached_stages"] = list(cache.hits)
    metrics["provenance"] = provenance(bag, config.name, started, time.perf_counter() - t0,
                                       orchard, drone_images)
    exported = {}
    if export_trees:  # before the outputs: metrics.json and report.html come last
        from canopy_kit.segment.tree_export import export_trees as write_tree_clouds

        exported = write_tree_clouds(out / "trees", ctx.mapping.map, ctx.segmentation)
    files = write_outputs(ctx, ctx.table, metrics, out, report) | exported
    return Results(out, ctx.table, metrics, files, list(metrics.get("warnings", [])), cache.hits)


def compute(config: PipelineConfig, bag: str | Path, out: str | Path,
            drone_images: str | Path | None = None, truth: str | Path | None = None,
            use_cache: bool = True, progress: Progress | None = None
            ) -> tuple[RunContext, StageCache]:
    """Every stage's result (from the cache in ``out/.cache`` when unchanged), no outputs.

    Notebooks call this to explore a run; :func:`run` adds the output files.
    """
    bag, out = Path(bag), Path(out)
    if not bag.exists():
        raise InputError(f"{bag}: bag does not exist")
    if drone_images is not None and not Path(drone_images).is_dir():
        raise InputError(f"{drone_images}: drone image folder does not exist")
    if truth is not None and not Path(truth).is_dir():
        raise InputError(f"{truth}: simulated session folder does not exist")
    check_settings(config)
    if drone_images is not None:
        from ground_truth.exif import read_flight

        read_flight(drone_images)  # bad photos reported now, not after the LiDAR stages
    out.mkdir(parents=True, exist_ok=True)
    cache = StageCache(out / ".cache", enabled=use_cache)
    report = progress or (lambda *_: None)
    ctx = RunContext(config)
    map_key = stage_key("map", fingerprint(bag), config.mapping)
    ctx.mapping = cache.get_or_compute("map", map_key, lambda: map_stage(bag, config, report))
    seg_key = stage_key("segment", map_key, config.preprocess, config.segment, config.rows, config.seed)
    ctx.segmentation = cache.get_or_compute("segment", seg_key,
                                            lambda: segment_stage(ctx, report))
    vol_key = stage_key("volumes", seg_key, config.volume)
    ctx.trees = cache.get_or_compute("volumes", vol_key, lambda: volume_stage(ctx, report))
    if drone_images is not None:
        gt_key = stage_key("aerial", fingerprint(drone_images), config.ground_truth, vol_key)
        ctx.aerial = cache.get_or_compute(
            "aerial", gt_key, lambda: aerial_stage(ctx, Path(drone_images), out / "aerial", report))
    ctx.layout = layout_stage(ctx)
    ctx.table = tree_table(ctx)
    if truth is not None:
        from canopy_kit.validation import evaluate_against_truth

        ctx.truth_dir = Path(truth)
        ctx.evaluation = evaluate_against_truth(ctx, ctx.table, ctx.truth_dir)
        ctx.table = ctx.evaluation.pop("trees")
        ctx.truth_matches = ctx.evaluation.pop("segmentation_trees")
    return ctx, cache


def check_settings(config: PipelineConfig) -> None:
    """Plugins, their parameters and the preprocessing ranges, checked before any stage runs
    (a typo in a preset must not cost a mapping run first)."""
    from canopy_kit import plugins
    from canopy_kit.segment.preprocess import check_preprocess_config

    check_preprocess_config(config.preprocess)
    plugins.create("segmenters", config.segment.method, config.segment.params,
                   where="segment.params")
    for method in dict.fromkeys([*config.volume.methods, config.volume.recommended]):
        plugins.create("volumes", method, config.volume.params.get(method, {}),
                       where=f"volume.params.{method}")


# -- stages ---------------------------------------------------------------------------------
def map_stage(bag: Path, config: PipelineConfig, progress: Progress) -> Any:
    """LiDAR(-inertial) odometry and mapping (``canopy_kit.mapping.build_map``)."""
    from canopy_kit.mapping import build_map

    return build_map(bag, config.mapping, progress=progress)


def driving_direction(trajectory: pd.DataFrame) -> np.ndarray | None:
    """Direction of the first pass, from the start of the estimated trajectory."""
    from canopy_kit.segment.rows import driving_direction_from_trajectory

    if trajectory is None or len(trajectory) < 2:
        return None
    return driving_direction_from_trajectory(trajectory[["x", "y"]].to_numpy())


def segment_stage(ctx: RunContext, progress: Progress) -> Any:
    """Ground/trunk removal, the configured segmenter, rows and labels."""
    from canopy_kit.segment.verb import make_segmenter, segment

    cfg = ctx.config
    segmenter = make_segmenter(cfg.segment.method, cfg.segment.params)
    direction = driving_direction(ctx.mapping.trajectory)
    return segment(ctx.mapping.map, segmenter, cfg.preprocess, cfg.rows,
                   driving_direction=direction,
                   direction_source="trajectory" if direction is not None else None,
                   seed=cfg.seed, progress=progress)


def volume_stage(ctx: RunContext, progress: Progress) -> pd.DataFrame:
    """Metrics and every configured volume estimator per segmented tree, on the map's points
    as map.laz stores them (1 mm): a tree's points read back from it give the same numbers."""
    from canopy_kit.io.las_write import on_las_grid
    from canopy_kit.trees import measure_trees

    seg = ctx.segmentation
    table = measure_trees(on_las_grid(ctx.mapping.map), seg.labels, ctx.config.volume,
                          ground_height=seg.ground.height, progress=progress)
    records = seg.table().set_index("segment_id")
    table = table.join(records[["tree_id", "row", "label", "index_in_row"]], on="segment")
    return table


def layout_stage(ctx: RunContext) -> Any:
    """Row and tree spacing and the trunks under each segment, measured on the map."""
    from canopy_kit.segment.layout import measure_layout

    seg = ctx.segmentation
    return measure_layout(ctx.mapping.map.xyz, seg.height, seg, tuple(ctx.config.preprocess.stem_band))


def aerial_stage(ctx: RunContext, images: Path, out: Path, progress: Progress) -> Any:
    """Drone photogrammetry ground truth, seeded with the LiDAR tree positions."""
    from ground_truth import process_flight

    shift = ctx.mapping.map.origin[:2] - _frame_origin(ctx)[:2]
    seeds = pd.DataFrame({"segment": ctx.trees["segment"].to_numpy(),
                          "tree_id": ctx.trees["tree_id"].astype(str).to_numpy(),
                          "x": ctx.trees["x"].to_numpy() + shift[0],
                          "y": ctx.trees["y"].to_numpy() + shift[1]})
    return process_flight(images, out, frame=ctx.mapping.frame, seeds=seeds, progress=progress,
                          config=ctx.config.ground_truth)


def _frame_origin(ctx: RunContext) -> np.ndarray:
    frame = getattr(ctx.mapping, "frame", None)
    return frame.origin if frame is not None else np.zeros(3)


# -- the per-tree table ---------------------------------------------------------------------
FIRST_COLUMNS = ["tree_id", "label", "row", "x", "y", "lat", "lon", "n_points", "height_m",
                 "crown_diameter_m", "volume_convex_hull_m3", "volume_alpha_m3"]


def tree_table(ctx: RunContext) -> pd.DataFrame:
    """The final per-tree table: LiDAR results, positions in WGS84, crowns unlike the others
    (``segment_flags``) and aerial truth if any."""
    from canopy_kit.segment.qa import crown_outliers

    trees = ctx.trees.copy()
    trees["segment_flags"] = crown_outliers(trees)
    if ctx.layout is not None:
        trees["n_trunks"] = ctx.layout.trunks_per_segment(trees["segment"].to_numpy())
    frame = getattr(ctx.mapping, "frame", None)
    if frame is not None and len(trees):
        xyz = np.column_stack([trees["x"], trees["y"], np.zeros(len(trees))])
        xyz = xyz + ctx.mapping.map.origin - frame.origin
        lat, lon, _ = frame.to_wgs84(xyz)
        trees["lat"], trees["lon"] = lat, lon
    else:
        trees["lat"], trees["lon"] = np.nan, np.nan
    if ctx.aerial is not None:
        trees = join_aerial(trees, ctx.aerial, ctx.config.ground_truth)
    rest = [c for c in trees.columns if c not in FIRST_COLUMNS]
    return trees[[c for c in FIRST_COLUMNS if c in trees.columns] + rest].reset_index(drop=True)


AERIAL_COLUMNS = {  # ground_truth's per-tree columns -> the names of the per-tree table
    "aerial_diameter_max_m": "aerial_diameter_m",
    "aerial_diameter_mean_m": "aerial_diameter_mean_m",
    "aerial_diameter_across_row_m": "aerial_diameter_across_row_m",
    "aerial_diameter_along_row_m": "aerial_diameter_along_row_m",
    "aerial_sphere_volume_m3": "aerial_sphere_volume_m3",
    "aerial_ellipsoid_volume_m3": "aerial_ellipsoid_volume_m3",
    "aerial_chm_volume_m3": "aerial_chm_volume_m3",
    "aerial_envelope_volume_m3": "aerial_envelope_volume_m3",
    "aerial_height_m": "aerial_height_m",
    "aerial_distance_m": "aerial_match_distance_m",
}


def join_aerial(trees: pd.DataFrame, aerial: Any,
                settings: GroundTruthConfig | None = None) -> pd.DataFrame:
    """Add the matched aerial crown diameter and sphere volume, and the LiDAR-vs-aerial errors.

    ``aerial_flag`` names an aerial crown that cannot be the same tree's crown (its diameter
    far from the LiDAR crown's: a fragment, or neighbours merged); such trees keep their
    aerial columns but get no error and stay out of the agreement statistics.
    """
    st = settings or GroundTruthConfig()
    # A result made before a column existed (reused, read back from disk) lacks it.
    present = [c for c in AERIAL_COLUMNS if c in aerial.trees]
    matched = aerial.trees[["segment", *present]].rename(columns=AERIAL_COLUMNS)
    matched = matched[aerial.trees["matched"].to_numpy(bool)]
    out = trees.merge(matched, on="segment", how="left")
    ratio = out["aerial_diameter_m"] / out["crown_diameter_m"]
    out["aerial_flag"] = np.select(
        [ratio < st.min_diameter_ratio, ratio > st.max_diameter_ratio],
        [f"aerial crown a fragment (diameter below {st.min_diameter_ratio:g}x the LiDAR crown's)",
         f"aerial crown merged with neighbours (diameter above {st.max_diameter_ratio:g}x "
         "the LiDAR crown's)"], default="")
    usable = comparable_aerial_sphere(out)
    for col in ("volume_convex_hull_m3", "volume_alpha_m3"):
        if col in out:
            name = col.replace("volume_", "").replace("_m3", "")
            out[f"error_{name}_vs_aerial_pct"] = 100.0 * (out[col] - usable) / usable
    return out


def comparable_aerial_sphere(trees: pd.DataFrame) -> pd.Series:
    """The aerial sphere volume of each tree whose aerial crown is not flagged (NaN otherwise)."""
    flag = trees["aerial_flag"].fillna("") if "aerial_flag" in trees else ""
    return trees["aerial_sphere_volume_m3"].where(flag == "")


def flagged(trees: pd.DataFrame, column: str) -> pd.Series:
    """Trees with a note in ``column`` (``volume_flags``, ``segment_flags``); none without it."""
    if column not in trees:
        return pd.Series(False, index=trees.index)
    return trees[column].fillna("").astype(str).str.len() > 0  # a missing note (NaN) is no note


def run_metrics(ctx: RunContext, trees: pd.DataFrame) -> dict[str, Any]:
    """Summary numbers of the run (mapping diagnostics, counts, agreement, evaluation)."""
    from canopy_kit import stats
    from canopy_kit.checks import Check, run_checks
    from canopy_kit.checks import summary as checks_summary

    m: dict[str, Any] = {"n_trees": int(len(trees)), "preset": ctx.config.name,
                         "segmenter": ctx.config.segment.method}
    warnings = list(getattr(ctx.mapping, "warnings", []))
    warnings += list(getattr(ctx.segmentation, "warnings", []))
    m["mapping"] = dict(getattr(ctx.mapping, "diagnostics", {}))
    m["segmentation"] = ctx.segmentation.summary()
    m["flagged_volumes"] = int(flagged(trees, "volume_flags").sum())
    m["flagged_segments"] = int(flagged(trees, "segment_flags").sum())
    if ctx.aerial is not None and "aerial_sphere_volume_m3" in trees:
        matched = trees["aerial_sphere_volume_m3"].notna()
        ok = comparable_aerial_sphere(trees).notna()
        m["aerial"] = {"matched_trees": int(matched.sum()), "compared_trees": int(ok.sum()),
                       "implausible_crowns": int((matched & ~ok).sum()),
                       **dict(getattr(ctx.aerial, "diagnostics", {}))}
        offset = (getattr(ctx.aerial, "report", None) or {}).get("seed_offset")
        if offset:  # the LiDAR map's georeferencing against the drone's (docs/GROUND_TRUTH.md)
            m["aerial"]["seed_offset"] = offset  # crowns minus LiDAR trees
        for col in ("volume_convex_hull_m3", "volume_alpha_m3"):
            if col in trees and ok.any():
                good = ok & trees[col].notna()
                m["aerial"][col] = stats.agreement(trees.loc[good, col].to_numpy(),
                                                   trees.loc[good, "aerial_sphere_volume_m3"].to_numpy()).as_dict()
    if ctx.layout is not None:
        m["layout"] = ctx.layout.as_dict()
    if ctx.evaluation:
        m["evaluation"] = ctx.evaluation
    m["warnings"] = warnings
    m["checks"] = [c.as_dict() for c in run_checks(m, trees, ctx.config.checks)]
    m["checks_summary"] = checks_summary([Check(**c) for c in m["checks"]])
    return m


# -- outputs --------------------------------------------------------------------------------
def write_outputs(ctx: RunContext, trees: pd.DataFrame, metrics: dict[str, Any], out: Path,
                  progress: Progress) -> dict[str, Path]:
    """Every output file, each written under a temporary name and renamed.

    ``map.laz`` (the longest, compressed by lazrs outside the GIL) is written on a thread
    while the tables and the report's page are made; ``metrics.json`` and ``report.html``
    are written last, once every other file is, so a run that failed leaves no report
    (an error of the writer thread is raised, or noted on the main thread's error).
    """
    from concurrent.futures import ThreadPoolExecutor

    from canopy_kit.io.las import las_ready, write_las
    from canopy_kit.report.html import write_report
    from canopy_kit.report.session import session_report_page
    from canopy_kit.segment.labelled import labelled_map

    cloud = labelled_map(ctx.mapping.map, ctx.segmentation)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="map.laz") as pool:
        laz = pool.submit(lambda: write_las(out / "map.laz", las_ready(cloud)))
        try:
            files = _write_tables(ctx, trees, out, metrics.get("provenance"))
            progress("report", 0, 1)
            page = session_report_page(ctx, trees, metrics)
        except BaseException as exc:
            if laz.exception() is not None:  # waits for the writer
                exc.add_note(f"writing {out / 'map.laz'} failed too: {laz.exception()!r}")
            raise
        laz.result()  # raises here what the writer raised
    files["map.laz"] = out / "map.laz"
    files["metrics.json"] = atomic_write_json(out / "metrics.json", metrics)
    files["report.html"] = write_report(out / "report.html", page)
    progress("report", 1, 1)
    return files


def config_used(ctx: RunContext) -> PipelineConfig:
    """The run's config with what the mapping resolved filled in (the topics it read): written
    as config.toml and shown in the report, so a run with that file reads the same topics."""
    from dataclasses import replace

    from canopy_kit.config import MappingConfig

    mapping = getattr(ctx.mapping, "config", None)
    return replace(ctx.config, mapping=mapping) if isinstance(mapping, MappingConfig) else ctx.config


def write_tree_tables(ctx: RunContext, trees: pd.DataFrame, out: Path,
                      provenance: dict[str, Any] | None = None) -> dict[str, Path]:
    """trees.csv, trees.parquet, trees.geojson, config.toml and what ``canopy-kit evaluate``
    needs besides them (segmentation.json, crowns, rows, trees.gpkg): the outputs of every
    run, batch ones included."""
    from canopy_kit.segment.export import write_segmentation_summary

    files = write_trees(trees, out, provenance)
    files["config.toml"] = write_config(config_used(ctx), out / "config.toml")
    rig = getattr(ctx.mapping, "rig", None)
    if rig is not None:
        from canopy_kit.mapping.outputs import RIG_TOML, write_rig

        files[RIG_TOML] = write_rig(rig, out / RIG_TOML)
    files.update({p.name: p for p in write_segmentation_summary(
        out, ctx.segmentation, trees=trees, provenance=provenance).values()})
    return files


def write_trees(trees: pd.DataFrame, out: Path,
                provenance: dict[str, Any] | None = None) -> dict[str, Path]:
    """The per-tree table as trees.csv (full precision), trees.parquet (``provenance`` in its
    schema metadata) and trees.geojson (none when no tree has a WGS84 position)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from canopy_kit.segment.export import write_geojson

    files: dict[str, Path] = {}
    files["trees.csv"] = atomic_write_text(out / "trees.csv", trees.to_csv(index=False))
    table = pa.Table.from_pandas(trees, preserve_index=False)
    if provenance:
        meta = dict(table.schema.metadata or {})
        meta[b"provenance"] = json.dumps(provenance).encode()
        table = table.replace_schema_metadata(meta)
    with atomic_path(out / "trees.parquet") as tmp:
        pq.write_table(table, tmp)
    files["trees.parquet"] = out / "trees.parquet"
    written = write_geojson(out, {"trees.geojson": trees_geojson(trees, provenance)})
    files.update({p.name: p for p in written.values()})
    return files


def _write_tables(ctx: RunContext, trees: pd.DataFrame, out: Path,
                  provenance: dict[str, Any] | None = None) -> dict[str, Path]:
    files = write_tree_tables(ctx, trees, out, provenance)
    files["trajectory.csv"] = atomic_write_text(
        out / "trajectory.csv", ctx.mapping.trajectory.to_csv(index=False, float_format="%.6f"))
    return files


def trees_geojson(trees: pd.DataFrame, provenance: dict[str, Any] | None = None) -> str | None:
    """Tree positions as an RFC 7946 FeatureCollection (WGS84 ``[lon, lat]``, the table's
    columns as properties); None when no tree has a position (a map without a CRS)."""
    from canopy_kit import geojson

    if "lat" not in trees or "lon" not in trees or not trees["lat"].notna().any():
        return None
    features = [geojson.feature(geojson.point(rec["lon"], rec["lat"]), rec)
                for rec in trees.to_dict(orient="records")
                if pd.notna(rec["lon"]) and pd.notna(rec["lat"])]
    return geojson.feature_collection(features, provenance)
