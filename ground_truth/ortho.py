"""Orthomosaic: every cell takes its colour from the most nadir photo that sees it.

Each cell is placed at its surface height (DSM), projected into its candidate photos,
nearest to nadir first, and the first photo whose line of sight clears the surface
(checked by marching along the ray over the DSM) gives the colour, so crowns do not
smear over the ground beside them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ground_truth.camera import PosedCamera
from ground_truth.dsm import nadir_views
from ground_truth.raster import Grid, sample_bilinear

Progress = Callable[[str, float, float], None]


@dataclass
class Orthomosaic:
    """RGB orthomosaic (uint8, alpha 0 where no photo sees the cell) and its source photo."""

    grid: Grid
    rgba: np.ndarray  # (rows, cols, 4) uint8
    source: np.ndarray  # (rows, cols) index into ``camera_names``, -1 for none
    camera_names: list[str]

    @property
    def rgb(self) -> np.ndarray:
        return self.rgba[..., :3]

    @property
    def valid(self) -> np.ndarray:
        return self.rgba[..., 3] > 0


def _line_of_sight_clear(
    points: np.ndarray,
    camera: PosedCamera,
    dsm_grid: Grid,
    dsm: np.ndarray,
    top: float,
    step: float,
) -> np.ndarray:
    """True where the ray from each point towards the camera stays above the DSM."""
    from ground_truth.kernels import rays_clear  # numba: compiled on first use

    c = camera.center
    d = c - points
    horizontal = np.hypot(d[:, 0], d[:, 1])
    # Rise needed to clear everything: march until the ray is above ``top``.
    rise = np.maximum(top - points[:, 2], 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(d[:, 2] > 0, rise / d[:, 2] * horizontal, 0.0)
    return rays_clear(
        np.ascontiguousarray(points, np.float64),
        np.asarray(c, np.float64),
        reach,
        float(step),
        np.asarray(dsm, np.float64),
        dsm_grid.x0,
        dsm_grid.y0,
        dsm_grid.resolution,
        0.15,
    )


def _max_reach(cameras: Sequence[PosedCamera], relief: float) -> float:
    """How far (horizontally) an obstacle ``relief`` m high can hide the ground from any view."""
    tan_half_diagonal = max(np.hypot(c.width, c.height) / 2 / c.focal for c in cameras)
    return 1.1 * relief * tan_half_diagonal


def crown_region_sources(
    cameras: Sequence[PosedCamera],
    grid: Grid,
    regions: np.ndarray,
    heights: np.ndarray,
    margin_px: float = 8.0,
) -> np.ndarray:
    """One source photo per crown region: the most nadir photo that sees all of it (-1: none).

    Taking a whole crown from one photo keeps its outline consistent: both edges move
    the same way when the surface height there is off, so the diameter hardly changes.
    """
    from scipy.ndimage import find_objects

    x, y = grid.centers()
    source = np.full(grid.shape, -1, np.int32)
    for k, sl in enumerate(find_objects(regions)):
        if sl is None:
            continue
        inside = regions[sl] == k + 1
        pts = np.column_stack([x[sl][inside], y[sl][inside], heights[sl][inside]])
        centre = pts[:, :2].mean(axis=0)
        best, best_d = -1, np.inf
        for i, cam in enumerate(cameras):
            d = float(np.hypot(*(cam.center[:2] - centre)))
            if d >= best_d:
                continue
            uv, depth = cam.project(pts)
            if (
                (depth > 0).all()
                and (uv[:, 0] >= margin_px).all()
                and (uv[:, 1] >= margin_px).all()
                and (uv[:, 0] < cam.width - margin_px).all()
                and (uv[:, 1] < cam.height - margin_px).all()
            ):
                best, best_d = i, d
        source[sl][inside] = best
    return source


def orthomosaic(
    cameras: Sequence[PosedCamera],
    images: Sequence[np.ndarray],
    dsm_grid: Grid,
    dsm: np.ndarray,
    resolution: float,
    views: int = 4,
    regions: np.ndarray | None = None,
    region_heights: np.ndarray | None = None,
    progress: Progress | None = None,
) -> Orthomosaic:
    """Orthomosaic at ``resolution`` over the DSM's extent; ``images`` are RGB uint8 arrays.

    ``regions`` (labels on the orthomosaic grid) are crowns taken whole from one photo each,
    placed at ``region_heights`` (same grid) instead of the DSM.
    """
    from scipy.ndimage import map_coordinates, maximum_filter

    report = progress or (lambda *_: None)
    grid = dsm_grid.resampled(resolution)
    x, y = grid.centers()
    z = sample_bilinear(dsm_grid, dsm, x, y)
    z = np.where(np.isfinite(z), z, np.nanmedian(dsm))
    if regions is not None and region_heights is not None:
        z = np.where(regions > 0, region_heights, z)
    candidates = nadir_views(cameras, grid, z, views).reshape(-1, views)
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    source = np.full(len(pts), -1, np.int32)
    top = float(np.nanmax(dsm))
    pending = np.ones(len(pts), bool)
    if regions is not None:
        forced = crown_region_sources(cameras, grid, regions, z).ravel()
        source[forced >= 0] = forced[forced >= 0]
        pending &= forced < 0
    # Only cells with something higher nearby can be hidden: march rays for those alone.
    reach_cells = int(
        np.ceil(_max_reach(cameras, top - float(np.nanmin(dsm))) / dsm_grid.resolution)
    )
    nearby_top = maximum_filter(np.nan_to_num(dsm, nan=-np.inf), size=2 * reach_cells + 1)
    exposed = sample_bilinear(dsm_grid, nearby_top, x, y).ravel() <= pts[:, 2] + 0.15
    for slot in range(views):
        for i in np.unique(candidates[pending, slot]):
            if i < 0:
                continue
            sel = np.flatnonzero(pending & (candidates[:, slot] == i))
            clear = exposed[sel].copy()
            hidden = ~clear
            clear[hidden] = _line_of_sight_clear(
                pts[sel[hidden]], cameras[i], dsm_grid, dsm, top, resolution * 2
            )
            source[sel[clear]] = i
            pending[sel[clear]] = False
        report("Orthomosaic", slot + 1, views)
    # Cells no candidate sees clearly still take the most nadir photo.
    fallback = pending & (candidates[:, 0] >= 0)
    source[fallback] = candidates[fallback, 0]
    rgba = np.zeros((len(pts), 4), np.uint8)
    for i in np.unique(source):
        if i < 0:
            continue
        sel = np.flatnonzero(source == i)
        uv, _ = cameras[i].project(pts[sel])
        img = images[i]
        for band in range(3):
            rgba[sel, band] = np.clip(
                np.round(
                    map_coordinates(
                        img[..., band].astype(np.float32),
                        [uv[:, 1] - 0.5, uv[:, 0] - 0.5],
                        order=1,
                        mode="nearest",
                    )
                ),
                0,
                255,
            )
        rgba[sel, 3] = 255
    return Orthomosaic(
        grid,
        rgba.reshape(grid.rows, grid.cols, 4),
        source.reshape(grid.shape),
        [c.name for c in cameras],
    )
