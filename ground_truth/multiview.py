"""The multi-view crown volume stage of ``process_flight`` and the flight's recommended model.

A flight's views are **oblique** when at least ``OBLIQUE_SHARE`` of its registered photos
look more than 15° off straight down (``canopy_kit.core.gimbal.is_oblique``; a double grid
with the gimbal at −60° or an orbit), else **nadir**. The visual hull
(``ground_truth.visual_hull``) runs when ``[ground_truth] hull_volume`` is on and at least
``HullOptions.min_views`` photos are registered; a crown whose centre fewer photos see has
no hull (NaN).

The recommended aerial reference (``report.json`` → ``aerial_volume_model``) is the hull
(``hull_volume_m3``) on an oblique flight, where the photos see below the crowns' widest
level; on a nadir flight it is the height-aware ellipsoid (``ellipsoid_volume_m3``), the
least biased nadir model over the crown forms (docs/GROUND_TRUTH.md): a nadir hull cannot
carve below the widest level and reaches the ground there.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from canopy_kit.config import GroundTruthConfig
from canopy_kit.core.gimbal import is_oblique
from canopy_kit.results.aerial_reference import DEFAULT_MODEL as NADIR_COLUMN
from canopy_kit.results.aerial_reference import HULL_MODEL as HULL_COLUMN
from ground_truth.camera import PosedCamera
from ground_truth.crowns import CrownSegmentation
from ground_truth.dsm import SurfaceModel
from ground_truth.exif import Flight
from ground_truth.silhouettes import crown_silhouettes
from ground_truth.visual_hull import HullOptions, carve_hulls, pack_photos

OBLIQUE_SHARE = 0.25  # share of oblique photos that makes a flight oblique


def camera_pitch_deg(camera: PosedCamera) -> float:
    """The camera's pitch in degrees: -90 straight down, 0 at the horizon."""
    forward = camera.rotation[2]  # the viewing direction in the world (world-to-camera rows)
    return float(np.degrees(np.arcsin(np.clip(forward[2], -1.0, 1.0))))


def flight_views(cameras: Sequence[PosedCamera]) -> dict:
    """What the registered photos look at: counts, median pitch, ``oblique`` or ``nadir``."""
    pitch = np.array([camera_pitch_deg(c) for c in cameras])
    oblique = int(sum(is_oblique(float(a)) for a in pitch))
    views = "oblique" if len(pitch) and oblique >= OBLIQUE_SHARE * len(pitch) else "nadir"
    return {
        "views": views,
        "photos": int(len(pitch)),
        "oblique_photos": oblique,
        "median_pitch_deg": round(float(np.median(pitch)), 1) if len(pitch) else None,
    }


def recommended_volume(views: dict, crowns: pd.DataFrame) -> dict:
    """The recommended aerial volume column for a flight of ``views`` (:func:`flight_views`)
    whose ``crowns`` table was measured, and why."""
    hull_ok = HULL_COLUMN in crowns and bool(crowns[HULL_COLUMN].notna().any())
    if views["views"] == "oblique" and hull_ok:
        column, why = HULL_COLUMN, "oblique photos see below the crowns' widest level"
    elif views["views"] == "oblique":
        column, why = NADIR_COLUMN, "oblique flight, but no visual hull was computed"
    else:
        column, why = NADIR_COLUMN, "nadir photos: the hull cannot carve below the widest level"
    return {"recommended": column, "flight_views": views["views"], "why": why}


def hull_options(config: GroundTruthConfig) -> HullOptions:
    """The hull's options from the ``[ground_truth]`` settings."""
    return HullOptions(outline_margin_m=float(config.hull_outline_margin_m))


@dataclass(frozen=True)
class CrownHulls:
    """Each crown's visual-hull volume (m³, NaN: too few views) and how many crowns'
    outlines were grown before carving (the outline rule of ``ground_truth.visual_hull``)."""

    volumes: np.ndarray
    grown: int


def hull_stage(
    flight: Flight,
    cameras: Sequence[PosedCamera],
    seg: CrownSegmentation,
    crowns: pd.DataFrame,
    surface: SurfaceModel,
    options: HullOptions | None = None,
    progress: Callable[[str, float, float], None] | None = None,
) -> CrownHulls:
    """Visual-hull volume (m³) of each crown, carved with silhouettes of the registered
    photos read at ``options.image_size`` px (NaN throughout with fewer than
    ``options.min_views`` photos), and how many outlines the outline rule grew."""
    from ground_truth.pipeline import load_work_images

    opts = options or HullOptions()
    if len(cameras) < opts.min_views or not len(crowns):
        return CrownHulls(np.full(len(crowns), np.nan), 0)
    scaled, rgbs = load_work_images(flight, list(cameras), opts.image_size)
    ground_z = float(np.nanmedian(surface.dtm))
    masks = crown_silhouettes(rgbs, scaled, ground_z)
    del rgbs
    photos = pack_photos(scaled, masks)
    del masks
    volumes, grown = carve_hulls(  # the rule decided once: the count reported is the one carved
        photos, seg.labels, seg.grid, crowns, surface.dtm, surface.grid, opts, progress
    )
    return CrownHulls(volumes, int(grown.sum()))


def multiview_stage(
    flight: Flight,
    cameras: Sequence[PosedCamera],
    seg: CrownSegmentation,
    crowns: pd.DataFrame,
    trees: pd.DataFrame | None,
    surface: SurfaceModel,
    config: GroundTruthConfig,
    progress: Callable[[str, float, float], None] | None = None,
) -> dict:
    """The flight's views and, with ``config.hull_volume``, the hull column added to ``crowns``
    (and ``aerial_hull_volume_m3`` to the matched ``trees``); returns the report's
    ``flight_views``, ``aerial_volume_model``, ``hull_outlines`` (the outline margin and how
    many crowns it was given) and the hull's seconds (None when off)."""
    views = flight_views(cameras)
    seconds, outlines = None, None
    if config.hull_volume:
        t0 = time.perf_counter()
        options = hull_options(config)
        hull = hull_stage(flight, cameras, seg, crowns, surface, options, progress)
        add_hull_column(crowns, trees, hull.volumes)
        outlines = {
            "margin_m": options.outline_margin_m,
            "max_outline_excess": options.max_outline_excess,
            "grown": hull.grown,
            "crowns": len(crowns),
        }
        seconds = time.perf_counter() - t0
    return {
        "flight_views": views,
        "aerial_volume_model": recommended_volume(views, crowns),
        "hull_outlines": outlines,
        "hull_s": seconds,
    }


def add_hull_column(crowns: pd.DataFrame, trees: pd.DataFrame | None, hull: np.ndarray) -> None:
    """Put the hull volumes (one per crown, in order) after the other volumes of ``crowns``
    and, prefixed ``aerial_``, on the matched rows of ``trees``."""
    columns = list(crowns.columns)
    at = columns.index("envelope_volume_m3") + 1 if "envelope_volume_m3" in columns else None
    crowns.insert(len(columns) if at is None else at, HULL_COLUMN, hull)
    if trees is not None and "aerial_crown_id" in trees:
        by_crown = dict(zip(crowns["crown_id"].astype(int), hull, strict=True))
        ids = pd.to_numeric(trees["aerial_crown_id"], errors="coerce")
        trees["aerial_" + HULL_COLUMN] = [
            by_crown.get(int(i), np.nan) if pd.notna(i) else np.nan for i in ids
        ]
