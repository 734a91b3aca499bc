"""A crown's volume from its silhouettes in every calibrated photo (a visual hull).

Each crown's box (its outline in the crown labels, from the ground up to above its top) is
cut into voxels; a voxel stays when every photo that sees it (it projects inside the image,
in front of the camera) shows vegetation there. What stays is the largest shape consistent
with the silhouettes: it holds the whole crown (up to the masks' errors) and is larger than
it where no photo looks between crown and ground. Nadir photos carve only the sides, so the
hull reaches down to the ground under the crown; oblique photos see below the skirt and
carve it away (Laurentini 1994, "The visual hull concept for silhouette-based image
understanding", IEEE PAMI 16(2)).

Photos carry the crown's silhouette against the ground (soil and grass behind a crown seen
obliquely); green grass behind the skirt keeps voxels there, which the ``min_fraction`` rule
(a voxel stays when at least that share of its views are vegetation) does not remove: a
hull over grass is an upper bound.

A crown whose centre (its voxels' mean position at mid-height) fewer than ``min_views``
photos see has no hull (NaN): too few views to carve it. A voxel is dropped as soon as it can
no longer stay, which gives the same volume as carving every voxel in every photo, faster.
``ground_truth.multiview`` runs it in ``process_flight``.

The hull cannot be wider than the crown's outline, and outlines from the surface model run
narrow on porous, lobed crowns. A crown whose oblique views come from bearings all round
(:func:`side_coverage`: they would enclose a round crown within ``max_plan_excess`` of its
plan area) has its outline grown by ``outline_margin_m``, never into a neighbour's, so that
its silhouettes, not the outline, bound its sides; a crown seen from fewer bearings keeps its
outline, which then bounds the hull better than the silhouettes do.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ground_truth.camera import PosedCamera
from ground_truth.raster import Grid


@dataclass(frozen=True)
class HullOptions:
    """Voxel size (m), share of a voxel's views that must show vegetation, fewest views, and
    the longest side (px) of the photos the silhouettes are drawn on."""

    voxel_m: float = 0.1
    min_fraction: float = 0.95
    min_views: int = 3
    headroom_m: float = 0.3  # above the crown's top
    # Crown outlines (the surface model's) grown by this much, never into a neighbour's, so
    # that the silhouettes bound the hull, for the crowns whose views bound their sides:
    # oblique views from bearings all round that would enclose a round crown within
    # ``max_plan_excess`` of its plan area (``side_coverage``). 0: never grown
    # (docs/GROUND_TRUTH.md, issue 51).
    outline_margin_m: float = 0.6
    max_plan_excess: float = 0.025  # a ring of views every 30° gives 2.3 %, every 36° 3.4 %
    oblique_deg: float = 20.0  # a view of a crown this far off straight down is oblique
    image_size: int = 800


def crown_hull_volumes(
    cameras: Sequence[PosedCamera],
    vegetation: Sequence[np.ndarray],
    labels: np.ndarray,
    grid: Grid,
    crowns: pd.DataFrame,
    ground: np.ndarray,
    ground_grid: Grid,
    options: HullOptions | None = None,
    progress: Callable[[str, float, float], None] | None = None,
) -> np.ndarray:
    """Visual-hull volume (m³) of each crown of ``crowns`` (rows in order, ``crown_id``).

    ``vegetation`` are per-photo masks (bool or 0/1, the size of each camera's image);
    ``labels`` the crown label raster on ``grid`` (0: no crown); ``ground`` the terrain
    heights on ``ground_grid``; ``crowns`` needs ``crown_id`` and ``height_m`` (top above
    the ground). NaN for a crown whose centre fewer than ``min_views`` photos see;
    ``progress(stage, done, total)`` after each crown."""
    opts = options or HullOptions()
    report = progress or (lambda *_: None)
    x, y = grid.centers()
    if opts.outline_margin_m > 0:
        labels, _ = grow_bounded_outlines(
            cameras, vegetation, labels, grid, crowns, ground, ground_grid, opts
        )
    out = np.zeros(len(crowns))
    for k, crown in enumerate(crowns.itertuples()):
        report("Visual hull", k, len(crowns))
        cells = labels == crown.crown_id
        if not cells.any():
            out[k] = np.nan
            continue
        # voxel columns on a regular xy lattice over the crown's outline in the labels
        ax = np.arange(x[cells].min(), x[cells].max() + opts.voxel_m, opts.voxel_m)
        ay = np.arange(y[cells].min(), y[cells].max() + opts.voxel_m, opts.voxel_m)
        gx, gy = (a.ravel() for a in np.meshgrid(ax, ay))
        inside = _sample(labels, grid, gx, gy) == crown.crown_id
        cx, cy = gx[inside], gy[inside]
        z0 = _sample(ground, ground_grid, cx, cy)
        z0 = np.where(np.isfinite(z0), z0, np.nanmedian(z0))
        top = float(np.nanmedian(z0)) + float(crown.height_m) + opts.headroom_m
        levels = np.arange(float(z0.min()), top, opts.voxel_m) + opts.voxel_m / 2
        pts = np.column_stack(
            [np.tile(cx, len(levels)), np.tile(cy, len(levels)), np.repeat(levels, len(cx))]
        )
        pts = pts[pts[:, 2] >= np.tile(z0, len(levels))]
        out[k] = _carve(pts, cameras, vegetation, opts) * opts.voxel_m**3
    report("Visual hull", len(crowns), len(crowns))
    return out


@dataclass(frozen=True)
class SideCoverage:
    """How a crown's views surround it: photos that see its centre, those of them looking
    at it at least ``oblique_deg`` off straight down, the widest gap (degrees) between the
    bearings of those oblique views taken as lines (a view from the north bounds the same
    sides as one from the south), and ``plan_excess``: the share by which the polygon those
    bearings circumscribe round a round crown exceeds the crown's plan area (inf with fewer
    than two bearings)."""

    views: int
    oblique_views: int
    bearing_gap_deg: float
    plan_excess: float


def side_coverage(
    cameras: Sequence[PosedCamera],
    shapes: Sequence[tuple[int, ...]],
    centre: np.ndarray,
    oblique_deg: float = 20.0,
) -> SideCoverage:
    """The views round a crown's ``centre`` (x, y, z). A view from bearing b bounds the
    crown across b with its silhouette's two edges, so views from bearings (as lines) that
    leave gaps g_i (summing to 180°) enclose a round crown of radius r in a polygon of area
    2 r² Σ tan(g_i / 2): ``plan_excess`` = 2 Σ tan(g_i / 2) / π - 1 (5.5 % for four bearings
    45° apart, 27 % for two at right angles)."""
    point = np.asarray(centre, float).reshape(1, 3)
    bearings = []
    views = 0
    for cam, shape in zip(cameras, shapes, strict=True):
        if not _visible(cam, shape, point)[0][0]:
            continue
        views += 1
        d = cam.center - point[0]
        if np.degrees(np.arctan2(np.hypot(d[0], d[1]), d[2])) >= oblique_deg:
            bearings.append(np.degrees(np.arctan2(d[1], d[0])) % 180.0)
    b = np.unique(np.round(bearings, 6))
    if len(b) < 2:
        return SideCoverage(views, len(bearings), 180.0, float("inf"))
    gaps = np.diff(np.r_[b, b[0] + 180.0])
    if gaps.max() >= 180.0 - 1e-9:
        return SideCoverage(views, len(bearings), 180.0, float("inf"))
    excess = 2.0 * np.tan(np.radians(gaps) / 2).sum() / np.pi - 1.0
    return SideCoverage(views, len(bearings), float(gaps.max()), float(excess))


def crown_centres(
    labels: np.ndarray,
    grid: Grid,
    crowns: pd.DataFrame,
    ground: np.ndarray,
    ground_grid: Grid,
) -> np.ndarray:
    """Each crown's centre (n x 3; NaN without cells): its outline's mean position, at half
    its height above the ground there."""
    x, y = grid.centers()
    out = np.full((len(crowns), 3), np.nan)
    for k, crown in enumerate(crowns.itertuples()):
        cells = labels == crown.crown_id
        if cells.any():
            cx, cy = float(x[cells].mean()), float(y[cells].mean())
            z0 = _sample(ground, ground_grid, np.array([cx]), np.array([cy]))[0]
            z0 = z0 if np.isfinite(z0) else float(np.nanmedian(ground))
            out[k] = (cx, cy, z0 + float(crown.height_m) / 2)
    return out


def bounded_crowns(
    cameras: Sequence[PosedCamera],
    shapes: Sequence[tuple[int, ...]],
    centres: np.ndarray,
    opts: HullOptions,
) -> np.ndarray:
    """Which crowns (rows of ``centres``) have their sides bounded by the views: at least
    ``min_views`` oblique views whose bearings would enclose a round crown within
    ``max_plan_excess`` of its plan area (:func:`side_coverage`)."""
    out = np.zeros(len(centres), bool)
    for k, c in enumerate(centres):
        if np.isfinite(c).all():
            cov = side_coverage(cameras, shapes, c, opts.oblique_deg)
            out[k] = cov.oblique_views >= opts.min_views and cov.plan_excess <= opts.max_plan_excess
    return out


def grow_bounded_outlines(
    cameras: Sequence[PosedCamera],
    vegetation: Sequence[np.ndarray],
    labels: np.ndarray,
    grid: Grid,
    crowns: pd.DataFrame,
    ground: np.ndarray,
    ground_grid: Grid,
    opts: HullOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """The crown labels with the outlines of the crowns whose sides the views bound
    (:func:`bounded_crowns`) grown by ``outline_margin_m``, never into a neighbour's, and
    which crowns (rows of ``crowns``) those are."""
    from skimage.segmentation import expand_labels

    centres = crown_centres(labels, grid, crowns, ground, ground_grid)
    bounded = bounded_crowns(cameras, [m.shape for m in vegetation], centres, opts)
    grow = crowns["crown_id"].to_numpy()[bounded]
    if not len(grow):
        return labels, bounded
    grown = expand_labels(labels, opts.outline_margin_m / grid.resolution)
    added = (labels == 0) & np.isin(grown, grow)
    return np.where(added, grown, labels), bounded


def _carve(
    pts: np.ndarray,
    cameras: Sequence[PosedCamera],
    vegetation: Sequence[np.ndarray],
    opts: HullOptions,
) -> float:
    """How many voxel centres ``pts`` stay (NaN when fewer than ``min_views`` photos see the
    crown's centre). A voxel stays when at least ``min_views`` photos see it and at least
    ``min_fraction`` of them show vegetation there. Photos whose view misses the crown's box
    are skipped, and a voxel is dropped as soon as more photos showed no vegetation there
    than ``1 - min_fraction`` of every photo that can see the box: it can no longer stay,
    so the result is the same as carving every voxel in every photo, only faster."""
    if len(pts) == 0:
        return float("nan")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    views = [
        (cam, mask)
        for cam, mask in zip(cameras, vegetation, strict=True)
        if _box_in_view(cam, mask.shape, lo, hi)
    ]
    centre = np.array([[*pts[:, :2].mean(axis=0), (lo[2] + hi[2]) / 2]])
    if sum(_visible(cam, mask.shape, centre)[0] for cam, mask in views) < opts.min_views:
        return float("nan")
    limit = (1.0 - opts.min_fraction) * len(views) + 1e-9
    alive = pts
    seen = np.zeros(len(pts), np.int32)
    bare = np.zeros(len(pts), np.int32)  # photos showing no vegetation at the voxel
    for cam, mask in views:
        ok, row, col = _visible(cam, mask.shape, alive, with_pixels=True)
        seen += ok
        bare[ok] += mask[row[ok], col[ok]] <= 0.5
        keep = bare <= limit
        if not keep.all():
            alive, seen, bare = alive[keep], seen[keep], bare[keep]
    green = seen - bare
    return float(((seen >= opts.min_views) & (green >= opts.min_fraction * seen)).sum())


def _visible(
    cam: PosedCamera, shape: tuple[int, ...], pts: np.ndarray, with_pixels: bool = False
) -> tuple[np.ndarray, ...]:
    """Which points project inside the image in front of the camera (and their pixels)."""
    uv, depth = cam.project(pts)
    col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (depth > 0) & (col >= 0) & (row >= 0) & (col < shape[1]) & (row < shape[0])
    return (ok, row, col) if with_pixels else (ok,)


def _box_in_view(cam: PosedCamera, shape: tuple[int, ...], lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether any of an axis-aligned box can project into the image: False only when every
    corner is in front of the camera and their pixel bounds miss the image by a margin (a box
    projects inside the hull of its corners' projections; the margin covers lens distortion)."""
    corners = np.array(np.meshgrid(*zip(lo, hi, strict=True))).reshape(3, -1).T
    uv, depth = cam.project(corners)
    if (depth <= 0).any():
        return True
    margin = 0.05 * max(shape[:2])
    lo_uv, hi_uv = uv.min(axis=0), uv.max(axis=0)
    return bool(
        (hi_uv >= -margin).all() and lo_uv[0] < shape[1] + margin and lo_uv[1] < shape[0] + margin
    )


def _sample(values: np.ndarray, grid: Grid, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Nearest-cell values of a raster at points (NaN outside)."""
    r, c = (np.rint(i).astype(int) for i in grid.index(x, y))
    ok = (r >= 0) & (c >= 0) & (r < values.shape[0]) & (c < values.shape[1])
    out = np.full(len(x), np.nan)
    out[ok] = values[r[ok], c[ok]]
    return out
