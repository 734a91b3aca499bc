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

A crown whose voxels are seen by fewer than ``min_views`` photos on the median has no hull
(NaN): too few views to carve it. ``ground_truth.multiview`` runs it in ``process_flight``.
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
    the ground). NaN for a crown seen by too few photos (``min_views``, on the median of its
    voxels); ``progress(stage, done, total)`` after each crown."""
    opts = options or HullOptions()
    report = progress or (lambda *_: None)
    x, y = grid.centers()
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
        green, seen = np.zeros(len(pts), np.int32), np.zeros(len(pts), np.int32)
        for cam, mask in zip(cameras, vegetation, strict=True):
            if not _box_in_view(cam, mask.shape, pts.min(axis=0), pts.max(axis=0)):
                continue
            uv, depth = cam.project(pts)
            col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            ok = (depth > 0) & (col >= 0) & (row >= 0)
            ok &= (col < mask.shape[1]) & (row < mask.shape[0])
            seen += ok
            green[ok] += mask[row[ok], col[ok]] > 0.5
        if len(pts) == 0 or np.median(seen) < opts.min_views:
            out[k] = np.nan
            continue
        kept = (seen >= opts.min_views) & (green >= opts.min_fraction * seen)
        out[k] = kept.sum() * opts.voxel_m**3
    report("Visual hull", len(crowns), len(crowns))
    return out


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
