"""The whole chain for one field session: bag → map → trees → volumes → checks → report.

The per-tree table is assembled in ``canopy_kit.results.tree_table``, metrics and the table's files
written by ``canopy_kit.results.outputs`` (shared with batch and streaming runs); this module runs
the stages in order and writes the report.

``run(config, bag, out)`` is the public entry point; each stage is a small function below and
its result is cached by a hash of its inputs and settings (``canopy_kit.core.cache``), so changing
a segmentation parameter re-runs segmentation and what follows, not the mapping.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from canopy_kit.config import PipelineConfig
from canopy_kit.core.atomic import atomic_write_json, atomic_write_text
from canopy_kit.core.cache import StageCache, fingerprint, stage_key
from canopy_kit.errors import InputError
from canopy_kit.results.outputs import Results, run_metrics, write_tree_tables
from canopy_kit.results.tree_table import tree_table

if TYPE_CHECKING:
    from canopy_kit.volume.surface import Surface
    from canopy_kit.volume.verb import TreeVolumes

Progress = Callable[[str, float, float], None]


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
    row_profiles: Any = None  # per row and metre: height, width, TRV, LWA (segment.row_profile)
    segmenter: Any = None  # the segmenter plugin, built and validated once per run
    estimators: dict[str, Any] | None = None  # the volume estimators, built once per run
    surfaces: dict[int, list[Surface]] = field(default_factory=dict)  # drawn solids per segment


def run(
    config: PipelineConfig,
    bag: str | Path,
    out: str | Path,
    drone_images: str | Path | None = None,
    truth: str | Path | None = None,
    use_cache: bool = True,
    progress: Progress | None = None,
    orchard: str | None = None,
    export_trees: bool = False,
    gnss: Any = None,
    sfm_threads: int = 0,
) -> Results:
    """Run every stage on ``bag`` and write the outputs (all atomically) into ``out``.

    ``orchard`` names the orchard or block in the provenance (default: the bag's stem);
    ``export_trees`` also writes each tree's points as ``trees/<tree_id>.laz``. ``bag`` may
    be a Velodyne pcap, with ``gnss`` a :class:`canopy_kit.io.pcap_drive.GnssTrackOption`.
    ``sfm_threads``: COLMAP's threads for the drone photos (0: every core; 1: repeatable bit
    for bit, slower).
    """
    from canopy_kit.io.pcap_drive import drive_input
    from canopy_kit.mapping.map_source import MapFile, input_path
    from canopy_kit.results.provenance import BagHash, provenance

    out = Path(out)
    report = progress or (lambda *_: None)
    started, t0 = time.time(), time.perf_counter()
    path = source = input_path(bag)  # the bag, the pcap, or the file of a map made elsewhere
    imported: dict[str, Any] = {}
    if not isinstance(bag, MapFile):
        bag, imported = drive_input(source, out / ".cache", gnss)  # a pcap becomes a bag
    # Hashed once the map is made: the mapping keeps both cores busy, segmentation one.
    bag_hash = BagHash(path, start=False)
    try:
        ctx, cache = compute(
            config,
            bag,
            out,
            drone_images,
            truth,
            use_cache,
            report,
            on_mapped=bag_hash.start,
            sfm_threads=sfm_threads,
        )
    except BaseException:
        bag_hash.cancel()
        raise
    metrics = run_metrics(ctx, ctx.table)
    metrics["stage_timings"] = cache.timings
    metrics["cached_stages"] = list(cache.hits)
    metrics["provenance"] = provenance(
        bag if imported else path,  # an imported pcap's bag holds its session date
        config.name,
        started,
        time.perf_counter() - t0,
        orchard,
        drone_images,
        bag_hash,
    )
    if imported:
        metrics["provenance"] |= {"bag": source.name, "orchard": orchard or source.stem}
        metrics["provenance"] |= imported
        # the mapping's warnings name the imported bag: name the capture the user gave
        named = [str(w).replace(str(bag), str(source)) for w in metrics.get("warnings", [])]
        metrics["warnings"] = named
    exported = {}
    if export_trees:  # before the outputs: metrics.json and report.html come last
        from canopy_kit.segment.tree_export import export_trees as write_tree_clouds

        exported = write_tree_clouds(out / "trees", ctx.mapping.map, ctx.segmentation)
    files = write_outputs(ctx, ctx.table, metrics, out, report) | exported
    return Results(out, ctx.table, metrics, files, list(metrics.get("warnings", [])), cache.hits)


def compute(
    config: PipelineConfig,
    bag: str | Path,
    out: str | Path,
    drone_images: str | Path | None = None,
    truth: str | Path | None = None,
    use_cache: bool = True,
    progress: Progress | None = None,
    on_mapped: Callable[[], None] | None = None,
    sfm_threads: int = 0,
) -> tuple[RunContext, StageCache]:
    """Every stage's result (from the cache in ``out/.cache`` when unchanged), no outputs;
    ``on_mapped()`` is called once the map is made or loaded; ``sfm_threads`` as in
    :func:`run` (not part of the aerial stage's cache key: every thread count makes a valid
    reconstruction).

    Notebooks call this to explore a run; :func:`run` adds the output files.
    """
    from canopy_kit.io.bag import require_bag
    from canopy_kit.mapping.map_source import as_map_file, load_finished_map

    out = Path(out)
    finished = as_map_file(bag)  # a map made elsewhere (LAS/LAZ/PCD/PLY): no mapping stage
    bag = finished.path if finished is not None else require_bag(bag)
    if drone_images is not None and not Path(drone_images).is_dir():
        raise InputError(f"{drone_images}: drone image folder does not exist")
    if truth is not None and not Path(truth).is_dir():
        raise InputError(f"{truth}: simulated session folder does not exist")
    segmenter, estimators = check_settings(config)
    if drone_images is not None:
        from ground_truth.exif import read_flight
        from ground_truth.pipeline import check_threads

        check_threads(sfm_threads, "sfm_threads")  # now, not after the LiDAR stages
        read_flight(drone_images)  # bad photos reported now, not after the LiDAR stages
    out.mkdir(parents=True, exist_ok=True)
    cache = StageCache(out / ".cache", enabled=use_cache)
    report = progress or (lambda *_: None)
    ctx = RunContext(config, segmenter=segmenter, estimators=estimators)
    if finished is not None:
        map_key = stage_key("map file", finished.fingerprint())
        ctx.mapping = cache.get_or_compute(
            "map", map_key, lambda: load_finished_map(finished, report)
        )
    else:
        map_key = stage_key("map", fingerprint(bag), config.mapping)
        ctx.mapping = cache.get_or_compute("map", map_key, lambda: map_stage(bag, config, report))
    if on_mapped is not None:
        on_mapped()
    seg_key = stage_key(
        "segment", map_key, config.preprocess, config.segment, config.rows, config.seed
    )
    ctx.segmentation = cache.get_or_compute("segment", seg_key, lambda: segment_stage(ctx, report))
    # "surfaces": the entry holds the drawn solids too (TreeVolumes), not the table alone
    vol_key = stage_key("volumes", seg_key, config.volume, "surfaces")
    volumes = cache.get_or_compute("volumes", vol_key, lambda: volume_stage(ctx, report))
    ctx.trees, ctx.surfaces = volumes.table, volumes.surfaces
    if drone_images is not None:
        gt_key = stage_key("aerial", fingerprint(drone_images), config.ground_truth, vol_key)
        ctx.aerial = cache.get_or_compute(
            "aerial",
            gt_key,
            lambda: aerial_stage(ctx, Path(drone_images), out / "aerial", report, sfm_threads),
        )
    ctx.layout = layout_stage(ctx)
    ctx.row_profiles = row_profile_stage(ctx)
    ctx.table = tree_table(ctx)
    if truth is not None:
        from canopy_kit.evaluate.validation import evaluate_against_truth

        ctx.truth_dir = Path(truth)
        ctx.evaluation = evaluate_against_truth(ctx, ctx.table, ctx.truth_dir)
        ctx.table = ctx.evaluation.pop("trees")
        ctx.truth_matches = ctx.evaluation.pop("segmentation_trees")
    return ctx, cache


def check_settings(config: PipelineConfig) -> tuple[Any, dict[str, Any]]:
    """Plugins, their parameters and the preprocessing ranges, checked before any stage runs
    (a typo in a preset must not cost a mapping run first). The segmenter and the volume
    estimators are built and validated here, once; the stages use these instances."""
    from canopy_kit.segment.preprocess import check_preprocess_config
    from canopy_kit.segment.verb import make_segmenter
    from canopy_kit.volume.verb import build_estimators

    check_preprocess_config(config.preprocess)
    segmenter = make_segmenter(config.segment.method, config.segment.params)
    return segmenter, build_estimators(config.volume)


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
    # the instance check_settings built (a context made by hand builds its own)
    segmenter = ctx.segmenter or make_segmenter(cfg.segment.method, cfg.segment.params)
    direction = driving_direction(ctx.mapping.trajectory)
    return segment(
        ctx.mapping.map,
        segmenter,
        cfg.preprocess,
        cfg.rows,
        driving_direction=direction,
        direction_source="trajectory" if direction is not None else None,
        seed=cfg.seed,
        progress=progress,
    )


def sensor_positions(mapping: Any) -> np.ndarray | None:
    """The sensor's x, y along the drive (map frame), from the mapping's trajectory; None
    when the map came without one (a finished map)."""
    trajectory = getattr(mapping, "trajectory", None)
    if trajectory is None or len(trajectory) == 0 or not {"x", "y"} <= set(trajectory):
        return None
    return trajectory[["x", "y"]].to_numpy(float)


def volume_stage(ctx: RunContext, progress: Progress, surfaces: bool = True) -> TreeVolumes:
    """Metrics and every configured volume estimator per segmented tree, on the map's points
    as map.laz stores them (1 mm): a tree's points read back from it give the same numbers.
    With ``surfaces`` the solids of the drawn estimators come with it, for the report."""
    from dataclasses import replace

    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.io.las_write import on_las_grid
    from canopy_kit.volume.verb import measure_trees_and_surfaces

    seg = ctx.segmentation
    # Only the trees' points (about half of a dense map) are put on the grid and grouped.
    in_trees = np.flatnonzero(seg.labels >= 0)
    trees = PointCloud(ctx.mapping.map.xyz[in_trees], origin=ctx.mapping.map.origin)
    volumes = measure_trees_and_surfaces(
        on_las_grid(trees),
        seg.labels[in_trees],
        ctx.config.volume,
        ground_height=seg.ground.height,
        progress=progress,
        estimators=ctx.estimators,
        draw=surfaces,
        sensor_xy=sensor_positions(ctx.mapping),
    )
    records = seg.table().set_index("segment_id")
    table = volumes.table.join(records[["tree_id", "row", "label", "index_in_row"]], on="segment")
    return replace(volumes, table=table)


def layout_stage(ctx: RunContext) -> Any:
    """Row and tree spacing and the trunks under each segment, measured on the map."""
    from canopy_kit.segment.layout import measure_layout

    seg = ctx.segmentation
    return measure_layout(
        ctx.mapping.map.xyz, seg.height, seg, tuple(ctx.config.preprocess.stem_band)
    )


def row_profile_stage(ctx: RunContext) -> Any:
    """Canopy height, width, cross-section, TRV and LWA per row and metre along it."""
    from canopy_kit.segment.row_profile import segmentation_row_profiles

    return segmentation_row_profiles(ctx.segmentation, ctx.mapping.map.xyz, ctx.layout)


def aerial_stage(
    ctx: RunContext, images: Path, out: Path, progress: Progress, threads: int = 0
) -> Any:
    """Drone photogrammetry ground truth, seeded with the LiDAR tree positions (SfM on
    ``threads`` threads, 0: every core)."""
    from ground_truth import process_flight

    shift = ctx.mapping.map.origin[:2] - _frame_origin(ctx)[:2]
    seeds = pd.DataFrame(
        {
            "segment": ctx.trees["segment"].to_numpy(),
            "tree_id": ctx.trees["tree_id"].astype(str).to_numpy(),
            "x": ctx.trees["x"].to_numpy() + shift[0],
            "y": ctx.trees["y"].to_numpy() + shift[1],
        }
    )
    return process_flight(
        images,
        out,
        frame=ctx.mapping.frame,
        seeds=seeds,
        progress=progress,
        config=ctx.config.ground_truth,
        seed=ctx.config.seed,
        threads=threads,
    )


def _frame_origin(ctx: RunContext) -> np.ndarray:
    frame = getattr(ctx.mapping, "frame", None)
    return frame.origin if frame is not None else np.zeros(3)


# -- outputs --------------------------------------------------------------------------------
def write_outputs(
    ctx: RunContext, trees: pd.DataFrame, metrics: dict[str, Any], out: Path, progress: Progress
) -> dict[str, Path]:
    """Every output file, each written under a temporary name and renamed.

    The report's per-tree drill-down is made first, its surfaces in forked processes (fork
    before any thread is started); then ``map.laz`` (the longest, compressed by lazrs outside
    the GIL) is written on a thread while the tables and the report's page are made;
    ``metrics.json`` and ``report.html`` are written last, once every other file is, so a
    run that failed leaves no report (an error of the writer thread is raised, or noted on
    the main thread's error).
    """
    from concurrent.futures import ThreadPoolExecutor

    from canopy_kit.io.las import las_ready, write_las
    from canopy_kit.report.explorer import tree_details
    from canopy_kit.report.html import write_report
    from canopy_kit.report.session import session_report_page
    from canopy_kit.segment.labelled import labelled_map

    cloud = labelled_map(ctx.mapping.map, ctx.segmentation)
    progress("report", 0, 1)
    details = tree_details(ctx, trees)  # forks its workers: before the thread starts
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="map.laz") as pool:
        laz = pool.submit(lambda: write_las(out / "map.laz", las_ready(cloud)))
        try:
            files = _write_tables(ctx, trees, out, metrics.get("provenance"))
            page = session_report_page(ctx, trees, metrics, details)
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


def _write_tables(
    ctx: RunContext, trees: pd.DataFrame, out: Path, provenance: dict[str, Any] | None = None
) -> dict[str, Path]:
    from canopy_kit.segment.row_profile import write_row_profiles

    files = write_tree_tables(ctx, trees, out, provenance)
    if ctx.row_profiles is not None:
        seg = ctx.segmentation
        files |= write_row_profiles(out, ctx.row_profiles, seg.crs, seg.origin, provenance)
    files["trajectory.csv"] = atomic_write_text(
        out / "trajectory.csv", ctx.mapping.trajectory.to_csv(index=False, float_format="%.6f")
    )
    return files
