"""``process_flight``: drone photos in, orthomosaic, surface models and per-crown table out."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.config import GroundTruthConfig
from canopy_kit.core.atomic import atomic_write_bytes, atomic_write_text
from canopy_kit.core.geo import LocalFrame
from canopy_kit.core.gimbal import is_oblique
from canopy_kit.errors import ConfigError, ProcessingError
from ground_truth.camera import PosedCamera
from ground_truth.crown_flags import (
    FLAG_COLUMN,
    crown_rows,
    flag_crowns,
    flag_spacing,
    flag_summary,
)
from ground_truth.crowns import (
    CrownOptions,
    CrownSegmentation,
    delineate_crowns,
    measure_crowns,
    vegetation_images,
)
from ground_truth.dsm import (
    SurfaceModel,
    SurfaceOptions,
    canopy_top,
    clean_surface,
    dense_surface,
    ground_from_surface,
    ground_model,
    reliable_points,
    search_height,
)
from ground_truth.exif import Flight, read_flight
from ground_truth.match import crown_tree_ids, match_crowns, read_trees, seed_offset, tree_positions
from ground_truth.multiview import camera_pitch_deg, multiview_stage
from ground_truth.ortho import Orthomosaic, orthomosaic
from ground_truth.raster import Grid, colorize, png_bytes, sample_bilinear, write_geotiff
from ground_truth.rows import RowDirection
from ground_truth.sfm import SfmOptions, SparseModel, run_sfm

Progress = Callable[[str, float, float], None]


@dataclass
class GroundTruthResult:
    """Everything one flight produced, in memory and on disk (``paths``)."""

    out_dir: Path
    frame: LocalFrame
    model: SparseModel | None  # None when loaded back from disk
    surface: SurfaceModel
    ortho: Orthomosaic
    segmentation: CrownSegmentation
    crowns: pd.DataFrame
    trees: pd.DataFrame | None
    report: dict
    paths: dict[str, Path]
    config: GroundTruthConfig | None = None  # None when loaded back from disk


# The settings of SfM, surface and orthomosaic: a result reused (``process_flight(reuse=)``)
# must have been made with the same, or the new values would do nothing.
RECONSTRUCTION_KEYS = ("max_image_size", "work_image_size", "ortho_resolution", "max_canopy_height")


def check_threads(threads: object, name: str = "threads") -> int:
    """SfM's thread count as given (0: every core; 1: one thread, which makes COLMAP's result
    repeatable bit for bit); a ConfigError naming ``name`` for anything else."""
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 0:
        raise ConfigError(f"{name}: expected an integer >= 0 (0: every core), got {threads!r}")
    return threads


def sfm_options(config: GroundTruthConfig, seed: int = 0, threads: int = 0) -> SfmOptions:
    """The structure-from-motion settings of ``config``, the run's ``seed`` and its
    ``threads`` (:func:`check_threads`), the rest at their defaults."""
    check_threads(threads)
    return SfmOptions(
        max_image_size=config.max_image_size, seed=seed, num_threads=threads if threads else -1
    )


def ortho_resolution(gsd: float, config: GroundTruthConfig) -> float:
    """Orthomosaic cell size (m): ``config.ortho_resolution``, else the GSD, at least 2 cm."""
    return config.ortho_resolution or max(round(gsd, 2), 0.02)


def load_work_images(
    flight: Flight, cameras: list[PosedCamera], max_size: int
) -> tuple[list[PosedCamera], list[np.ndarray]]:
    """The photos downscaled to ``max_size`` px on their longest side, with their cameras."""
    from PIL import Image

    width, height = flight.size
    factor = min(1.0, max_size / max(width, height))
    scaled, rgbs = [], []
    for cam in cameras:
        with Image.open(flight.folder / cam.name) as im:
            im = im.convert("RGB")
            if factor < 1.0:
                im = im.resize(
                    (round(width * factor), round(height * factor)), Image.Resampling.LANCZOS
                )
            rgbs.append(np.asarray(im))
        scaled.append(cam.scaled(factor) if factor < 1.0 else cam)
    return scaled, rgbs


def _grey(rgb: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    grey = (rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)) / 255.0
    return gaussian_filter(grey, sigma) if sigma > 0 else grey


AIMED_AREA_PAD_M = 2.0  # beyond the centre rays' ground points: the crowns at the area's edge


def _survey_grid(model: SparseModel, resolution: float) -> Grid:
    """The area the sparse points cover (2nd to 98th percentile, padded a little); for an
    oblique flight cut to the area its photos are aimed at (:func:`looked_at_area`)."""
    xy = model.points[:, :2]
    if len(xy) < 10:
        raise ProcessingError(f"only {len(xy)} sparse points: the reconstruction is too thin")
    lo, hi = np.percentile(xy, 2, axis=0), np.percentile(xy, 98, axis=0)
    pad = 0.02 * float(np.max(hi - lo))
    lo, hi = lo - pad, hi + pad
    area = looked_at_area(list(model.cameras.values()), float(np.median(model.points[:, 2])))
    if area is not None:
        cut_lo, cut_hi = np.maximum(lo, area[0]), np.minimum(hi, area[1])
        if (cut_hi > cut_lo).all():
            lo, hi = cut_lo, cut_hi
    return Grid.covering(lo, hi, resolution)


def looked_at_area(
    cameras: list[PosedCamera], ground_z: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) corners of the ground an oblique flight's photos are aimed at: where the
    centre rays meet the ground at ``ground_z`` (a planned flight sweeps them over its
    area), padded by ``AIMED_AREA_PAD_M``. None for a nadir flight (no photo
    :func:`~canopy_kit.core.gimbal.is_oblique`): its sparse points bound its area."""
    hits, oblique = [], False
    for cam in cameras:
        forward = cam.rotation[2]  # the viewing direction in the world (world-to-camera rows)
        height = float(cam.center[2] - ground_z)
        if forward[2] > -0.2 or height <= 0:  # looking near the horizon: no defined aim
            continue
        # an oblique photo also sees ground far ahead, at grazing angles, where the surface
        # is noise
        oblique |= is_oblique(camera_pitch_deg(cam))
        hits.append(cam.center[:2] + forward[:2] * (height / -forward[2]))
    if not hits or not oblique:
        return None
    hits_xy = np.asarray(hits)
    return hits_xy.min(axis=0) - AIMED_AREA_PAD_M, hits_xy.max(axis=0) + AIMED_AREA_PAD_M


def _reconstruct(
    flight: Flight,
    out: Path,
    frame: LocalFrame,
    opts: GroundTruthConfig,
    report: Progress,
    timings: dict[str, float],
    seed: int = 0,
    threads: int = 0,
) -> tuple[SparseModel, SurfaceModel, Orthomosaic, float, float, float]:
    """SfM, surface models and orthomosaic of a flight."""
    t0 = time.perf_counter()
    model = run_sfm(flight, out / "sfm", frame, sfm_options(opts, seed, threads), report)
    timings["sfm"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    names = sorted(model.cameras)
    cameras, rgbs = load_work_images(
        flight, [model.cameras[n] for n in names], opts.work_image_size
    )
    heights = np.array([c.center[2] for c in cameras]) - np.median(model.points[:, 2])
    gsd = float(np.median(heights) / np.median([c.focal for c in cameras]))
    ortho_res = ortho_resolution(gsd, opts)
    surface_opts = SurfaceOptions()
    grid = _survey_grid(model, max(surface_opts.resolution, 2 * ortho_res))
    points = reliable_points(model.points, model.track_lengths, model.point_errors)
    ground = ground_model(
        points, grid, surface_opts.ground_window_m, surface_opts.ground_resolution
    )
    greys = [
        _grey(rgb, 0.35 * grid.resolution / gsd) for rgb in rgbs
    ]  # anti-alias to the cell size
    classes = vegetation_images(rgbs, 0.35 * grid.resolution / gsd)
    limit = opts.max_canopy_height
    if limit is None:  # unset: the trees' own height, as the sparse points show it
        limit, _ = search_height(points, grid, ground)
    top = canopy_top(cameras, greys, grid, ground, limit, surface_opts)
    raw = dense_surface(
        cameras, greys, grid, ground, top, surface_opts, classes=classes, progress=report
    )
    dsm = clean_surface(raw.dsm, ground)
    # The dense surface sees far more ground than the sparse points: refine the ground from it.
    ground = np.minimum(ground_from_surface(dsm, grid, surface_opts.ground_window_m), dsm)
    surface = SurfaceModel(grid, dsm, ground, raw.score, raw.view_index, raw.camera_names)
    timings["surface"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    mosaic = orthomosaic(cameras, rgbs, grid, surface.dsm, ortho_res, progress=report)
    timings["orthomosaic"] = time.perf_counter() - t0
    return model, surface, mosaic, gsd, ortho_res, top


def process_flight(
    images_dir: str | Path,
    out_dir: str | Path,
    frame: LocalFrame | None = None,
    seeds: str | Path | pd.DataFrame | None = None,
    progress: Progress | None = None,
    config: GroundTruthConfig | None = None,
    reuse: GroundTruthResult | None = None,
    seed: int = 0,
    threads: int = 0,
) -> GroundTruthResult:
    """Drone photos → georeferenced orthomosaic, DSM/DTM/CHM, crowns and (with seeds) per-tree table.

    ``frame`` is the local metric frame of the LiDAR map (default: UTM at the flight);
    ``seeds`` are tree positions (CSV path or table with lat/lon or x/y) that seed the
    crown watershed and receive one matched crown each. ``reuse``, an earlier result for
    the same photos and frame, skips SfM, surface and orthomosaic (other seeds or crown and
    matching settings only). ``config`` is the ``[ground_truth]`` table of a preset
    (default: its defaults); it is written next to the results as ``ground_truth_config.json``.
    ``seed`` (the preset's ``seed``) seeds SfM's random sampling; the report keeps it.
    ``threads`` are SfM's threads (0: every core). COLMAP's mapping and bundle adjustment
    on several threads do not repeat bit for bit, so two runs can place a crown differently;
    ``threads=1`` repeats exactly (and is slower).
    """
    opts = config or GroundTruthConfig()
    sfm_options(opts, seed, threads)  # settings checked before anything is written
    report = progress or (lambda *_: None)
    out = Path(out_dir)
    timings: dict[str, float] = {}

    flight = read_flight(images_dir)  # checked before anything is written
    out.mkdir(parents=True, exist_ok=True)
    frame = frame or (reuse.frame if reuse is not None else flight.default_frame())
    if reuse is not None:
        if reuse.model is None:
            raise ProcessingError(
                "a result loaded from disk has no SfM model to reuse; process the photos again"
            )
        if reuse.frame != frame or sorted(reuse.model.cameras) != sorted(
            n for n in flight.names if n not in reuse.model.unregistered
        ):
            raise ProcessingError(
                f"{images_dir}: the result to reuse comes from other photos or another frame"
            )
        made_with = reuse.config or GroundTruthConfig()
        changed = [k for k in RECONSTRUCTION_KEYS if getattr(made_with, k) != getattr(opts, k)]
        if changed:
            key = changed[0]
            raise ProcessingError(
                f"ground_truth.{key}: the result to reuse was made with "
                f"{getattr(made_with, key)!r}, not {getattr(opts, key)!r}; "
                "process the photos again"
            )
        made_seed = reuse.report.get("sfm_seed", 0)
        if made_seed != seed:
            raise ProcessingError(
                f"seed: the result to reuse was reconstructed with seed {made_seed}, "
                f"not {seed}; process the photos again"
            )
        model, surface, mosaic = reuse.model, reuse.surface, reuse.ortho
        timings.update(
            {
                k: v
                for k, v in reuse.report["timings_s"].items()
                if k in ("sfm", "surface", "orthomosaic")
            }
        )
        gsd, ortho_res, top = (
            reuse.report["ground_sampling_distance_m"],
            reuse.report["orthomosaic_resolution_m"],
            reuse.report["canopy_search_height_m"],
        )
    else:
        fresh = not (out / "sfm").exists()
        try:
            model, surface, mosaic, gsd, ortho_res, top = _reconstruct(
                flight, out, frame, opts, report, timings, seed, threads
            )
        except BaseException:
            if fresh:  # no half-made reconstruction left behind under --out
                shutil.rmtree(out / "sfm", ignore_errors=True)
            raise
    grid = surface.grid

    t0 = time.perf_counter()
    trees = None
    if seeds is not None:
        trees = (
            read_trees(seeds, frame)
            if not isinstance(seeds, pd.DataFrame)
            else tree_positions(seeds, frame)
        )
    seg, crowns, matched, offset = crowns_stage(mosaic, surface, trees, frame, opts)
    timings["crowns"] = time.perf_counter() - t0

    cameras = [model.cameras[n] for n in sorted(model.cameras)]
    multiview = multiview_stage(flight, cameras, seg, crowns, matched, surface, opts, report)
    if multiview["hull_s"] is not None:
        timings["hull"] = multiview["hull_s"]

    summary = {
        "images": str(Path(images_dir)),
        "frame": frame.to_dict(),
        "sfm": model.report(),
        "sfm_seed": seed,
        "sfm_threads": threads,
        "ground_sampling_distance_m": gsd,
        "orthomosaic_resolution_m": ortho_res,
        "surface_resolution_m": grid.resolution,
        "canopy_search_height_m": top,
        "crowns": int(len(crowns)),
        "trees_matched": int(matched["matched"].sum()) if matched is not None else None,
        "trees": int(len(matched)) if matched is not None else None,
        "sphere_diameter": "diameter_max_m (widest extent)",
        "flight_views": multiview["flight_views"],
        "aerial_volume_model": multiview["aerial_volume_model"],
        "hull_outlines": multiview["hull_outlines"],
        "timings_s": timings,
    }
    summary["crown_seeding"] = seg.seeding
    if seg.row_layout is not None:
        summary["crown_rows"] = seg.row_layout.to_dict()
    summary["crown_flags"] = crowns.attrs.get("crown_flags")
    row_dir = crowns.attrs.get("row_direction")
    if row_dir is not None:
        summary["row_direction"] = row_dir.to_dict()
    if offset is not None:
        summary["seed_offset"] = offset
    paths = _write_outputs(out, frame, model, surface, mosaic, seg, crowns, matched, summary, opts)
    return GroundTruthResult(
        out, frame, model, surface, mosaic, seg, crowns, matched, summary, paths, opts
    )


def crowns_stage(
    mosaic: Orthomosaic,
    surface: SurfaceModel,
    trees: pd.DataFrame | None,
    frame: LocalFrame,
    opts: GroundTruthConfig,
) -> tuple[CrownSegmentation, pd.DataFrame, pd.DataFrame | None, dict | None]:
    """Crowns on the orthomosaic, measured and (with ``trees``) matched to the trees.

    With seed trees, the offset of the crowns from their seeds is measured (``seed_offset``:
    the seeds' georeferencing against the photos', e.g. a LiDAR map on standalone GNSS
    against an RTK drone); when it is significant and ``register_seeds`` is set, the
    crowns are delineated once more from seeds moved by that offset, so each seed starts
    on its own crown. The trees' positions and ``aerial_distance_m`` stay as given.
    """
    ox, oy = mosaic.grid.centers()
    chm = sample_bilinear(surface.grid, surface.chm, ox, oy)
    seeded = trees is not None and opts.crowns_from_seeds
    seeds_xy = trees[["tree_x", "tree_y"]].to_numpy() if seeded else None
    crown_opts = CrownOptions(
        unseeded=opts.crown_seeds,
        tree_spacing_m=opts.tree_spacing_m,
        row_bearing_deg=opts.row_bearing_deg,
    )
    given = opts.row_bearing_deg
    row_direction = RowDirection.from_bearing(given) if given is not None else None
    offset = None
    for attempt in range(2):
        seg = delineate_crowns(mosaic.rgb, mosaic.valid, chm, mosaic.grid, seeds_xy, crown_opts)
        crowns = measure_crowns(seg, chm, row_direction)
        spacing, source = flag_spacing(crowns, seg.row_layout, opts.tree_spacing_m)
        rows = crown_rows(crowns[["x", "y"]].to_numpy(), seg.row_layout)
        crowns[FLAG_COLUMN] = flag_crowns(crowns, spacing, rows)
        crowns.attrs["crown_flags"] = flag_summary(crowns[FLAG_COLUMN], spacing, source)
        lat, lon, _ = frame.to_wgs84(crowns[["x", "y"]].to_numpy()) if len(crowns) else ([], [], [])
        crowns.insert(3, "lat", lat)
        crowns.insert(4, "lon", lon)
        matched = match_crowns(trees, crowns, opts.match_distance_m) if trees is not None else None
        if matched is None:
            break
        if attempt == 0:
            offset = {**seed_offset(matched), "seeds_shifted": False}
            if not (seeded and opts.register_seeds and offset["significant"]):
                break
            seeds_xy = seeds_xy + np.array([offset["east_m"], offset["north_m"]])
            offset["seeds_shifted"] = True
        else:  # what remains after the shift (the crowns, not the seeds, set their centres)
            after = seed_offset(matched)
            offset.update({"east_after_m": after["east_m"], "north_after_m": after["north_m"]})
    if matched is not None and "tree_id" in matched:  # the seeds' ids name their crowns
        crowns["tree_id"] = crown_tree_ids(crowns, matched)
    return seg, crowns, matched, offset


def cameras_table(model: SparseModel) -> pd.DataFrame:
    """Registered cameras: centre in the local frame, camera-to-world quaternion, GPS residual."""
    from scipy.spatial.transform import Rotation

    res = model.gps_residuals.set_index("image")
    rows = []
    for name, cam in sorted(model.cameras.items()):
        q = Rotation.from_matrix(cam.rotation.T).as_quat()
        c = cam.center
        rows.append(
            {
                "image": name,
                "x": c[0],
                "y": c[1],
                "z": c[2],
                "qw": q[3],
                "qx": q[0],
                "qy": q[1],
                "qz": q[2],
                "focal_px": cam.focal,
                "gps_dx": res.loc[name, "dx"],
                "gps_dy": res.loc[name, "dy"],
                "gps_dz": res.loc[name, "dz"],
            }
        )
    return pd.DataFrame(rows)


def table_csv(table: pd.DataFrame) -> str:
    """A crowns or trees table as CSV, floats to 9 decimals (1e-9 deg: 0.1 mm of lat/lon)."""
    return table.to_csv(index=False, float_format="%.9f")


def _write_outputs(
    out: Path,
    frame: LocalFrame,
    model: SparseModel,
    surface: SurfaceModel,
    mosaic: Orthomosaic,
    seg: CrownSegmentation,
    crowns: pd.DataFrame,
    trees: pd.DataFrame | None,
    summary: dict,
    opts: GroundTruthConfig,
) -> dict[str, Path]:
    from ground_truth.plots import overlay_crowns_rgb

    paths = {
        "orthomosaic_tif": write_geotiff(out / "orthomosaic.tif", mosaic.rgba, mosaic.grid, frame),
        "orthomosaic_png": atomic_write_bytes(out / "orthomosaic.png", png_bytes(mosaic.rgba)),
        "dsm_tif": write_geotiff(
            out / "dsm.tif",
            (surface.dsm + frame.origin_height).astype(np.float32),
            surface.grid,
            frame,
            nodata=float("nan"),
        ),
        "dtm_tif": write_geotiff(
            out / "dtm.tif",
            (surface.dtm + frame.origin_height).astype(np.float32),
            surface.grid,
            frame,
            nodata=float("nan"),
        ),
        "chm_tif": write_geotiff(
            out / "chm.tif",
            surface.chm.astype(np.float32),
            surface.grid,
            frame,
            nodata=float("nan"),
        ),
        "chm_png": atomic_write_bytes(out / "chm.png", png_bytes(colorize(surface.chm, 0.0, None))),
        "crown_labels_tif": write_geotiff(
            out / "crown_labels.tif", seg.labels.astype(np.int32), mosaic.grid, frame, nodata=0
        ),
        "crowns_png": atomic_write_bytes(
            out / "crowns.png", png_bytes(overlay_crowns_rgb(mosaic, seg))
        ),
        "crowns_csv": atomic_write_text(out / "crowns.csv", table_csv(crowns)),
    }
    paths["cameras_csv"] = atomic_write_text(
        out / "cameras.csv", cameras_table(model).to_csv(index=False, float_format="%.6f")
    )
    if trees is not None:
        paths["trees_csv"] = atomic_write_text(out / "trees.csv", table_csv(trees))
    paths["report_json"] = atomic_write_text(
        out / "report.json", json.dumps(summary, indent=2, default=str)
    )
    paths["config_json"] = atomic_write_text(
        out / "ground_truth_config.json", json.dumps(asdict(opts), indent=2, default=str)
    )
    return paths


def _grid_of(geo: dict, shape: tuple[int, ...], frame: LocalFrame) -> Grid:
    res = float(geo["pixel_scale"][0])
    return Grid(
        float(geo["tiepoint"][3]) - frame.origin_easting,
        float(geo["tiepoint"][4]) - frame.origin_northing,
        res,
        int(shape[0]),
        int(shape[1]),
    )


def load_result(out_dir: str | Path) -> GroundTruthResult:
    """A processed flight read back from ``out_dir`` (rasters, tables, report; no SfM model)."""
    from canopy_kit.errors import InputError
    from ground_truth.crowns import vegetation_mask
    from ground_truth.raster import read_geotiff

    out = Path(out_dir)
    if not (out / "report.json").exists():
        raise InputError(f"{out}: not a ground-truth output folder (no report.json)")
    report = json.loads((out / "report.json").read_text())
    frame = LocalFrame.from_dict(report["frame"])
    rgba, geo = read_geotiff(out / "orthomosaic.tif")
    ogrid = _grid_of(geo, rgba.shape, frame)
    dsm, geo_s = read_geotiff(out / "dsm.tif")
    dtm, _ = read_geotiff(out / "dtm.tif")
    sgrid = _grid_of(geo_s, dsm.shape, frame)
    surface = SurfaceModel(
        sgrid,
        dsm.astype(float) - frame.origin_height,
        dtm.astype(float) - frame.origin_height,
        np.full(dsm.shape, np.nan),
        np.zeros(dsm.shape + (0,), int),
        [],
    )
    mosaic = Orthomosaic(ogrid, rgba, np.full(rgba.shape[:2], -1, np.int32), [])
    labels, _ = read_geotiff(out / "crown_labels.tif")
    crowns = pd.read_csv(out / "crowns.csv")
    vegetation, threshold = vegetation_mask(mosaic.rgb, mosaic.valid)
    seg = CrownSegmentation(
        ogrid,
        labels.astype(np.int32),
        labels > 0,
        vegetation,
        threshold,
        crowns[["x", "y"]].to_numpy(),
        crowns["seed_id"].to_numpy(),
        report.get("crown_seeding", "tree_positions"),
    )
    trees = pd.read_csv(out / "trees.csv") if (out / "trees.csv").exists() else None
    paths = {p.stem + "_" + p.suffix[1:]: p for p in out.iterdir() if p.is_file()}
    return GroundTruthResult(out, frame, None, surface, mosaic, seg, crowns, trees, report, paths)
