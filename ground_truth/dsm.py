"""Surface (DSM) and ground (DTM) models from posed photos and the sparse SfM points.

pycolmap's CPU wheels have no dense stereo, so the surface comes from object-space
multi-view matching (the photogrammetric "vertical line locus"): for every cell, heights
are tried from the ground up; at each height the cell is projected into its most nadir
views and the height whose image patches agree best (normalised cross-correlation over a
small window) wins. The ground model is the lower envelope of the sparse points, opened
by a window wider than any crown.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from canopy_kit.errors import ProcessingError
from ground_truth.camera import PosedCamera
from ground_truth.raster import Grid

Progress = Callable[[str, float, float], None]


@dataclass
class SurfaceOptions:
    """Dense matching settings: cell size, height step, views per cell and window."""

    resolution: float = 0.1
    height_step: float = 0.1
    views_per_cell: int = 4
    window_cells: int = 5
    min_score: float = 0.3
    max_height: float | None = None  # above ground; default from the sparse points
    ground_window_m: float = 10.0
    ground_resolution: float = 1.0


@dataclass
class SurfaceModel:
    """DSM, DTM and matching score on one grid (heights in the local frame, NaN = unknown)."""

    grid: Grid
    dsm: np.ndarray
    dtm: np.ndarray
    score: np.ndarray
    view_index: np.ndarray  # (rows, cols, K) index into ``camera_names``, -1 for none
    camera_names: list[str]

    @property
    def chm(self) -> np.ndarray:
        """Canopy height model: surface above ground."""
        return self.dsm - self.dtm


def _fill_nans(values: np.ndarray, max_sigma: float = 64.0) -> np.ndarray:
    """Fill NaN cells by normalised convolution with growing Gaussian kernels."""
    from scipy.ndimage import gaussian_filter

    out = np.array(values, float)
    valid = np.isfinite(out)
    if valid.all() or not valid.any():
        return out
    sigma = 1.0
    while not valid.all() and sigma <= max_sigma:
        w = gaussian_filter(valid.astype(float), sigma)
        v = gaussian_filter(np.where(valid, out, 0.0), sigma)
        fill = (~valid) & (w > 1e-3)
        out[fill] = v[fill] / w[fill]
        valid |= fill
        sigma *= 2.0
    out[~valid] = np.nanmedian(out)
    return out


def ground_model(points: np.ndarray, grid: Grid, window_m: float = 10.0,
                 resolution: float = 1.0) -> np.ndarray:
    """Ground heights on ``grid``: lowest sparse point per coarse cell, opened by ``window_m``.

    The opening (minimum then maximum filter) removes anything narrower than the window
    (crowns) while following slopes better than a plain minimum would.
    """
    from scipy.ndimage import gaussian_filter, maximum_filter, minimum_filter, zoom

    if len(points) < 10:
        raise ProcessingError(f"only {len(points)} sparse points: too few for a ground model")
    coarse = grid.resampled(resolution)
    r, c = coarse.index(points[:, 0], points[:, 1])
    r, c = np.round(r).astype(int), np.round(c).astype(int)
    ok = (r >= 0) & (r < coarse.rows) & (c >= 0) & (c < coarse.cols)
    low = np.full(coarse.shape, np.inf)
    np.minimum.at(low, (r[ok], c[ok]), points[ok, 2])
    low[~np.isfinite(low)] = np.nan
    size = max(int(round(window_m / resolution)) | 1, 3)
    filled = _fill_nans(low)
    opened = maximum_filter(minimum_filter(filled, size=size, mode="nearest"), size=size, mode="nearest")
    smooth = gaussian_filter(opened, sigma=max(size / 4.0, 1.0), mode="nearest")
    # Back to the fine grid (bilinear).
    fine = zoom(smooth, (grid.rows / coarse.rows, grid.cols / coarse.cols), order=1, mode="nearest")
    out = np.empty(grid.shape)
    out[: fine.shape[0], : fine.shape[1]] = fine[: grid.rows, : grid.cols]
    if fine.shape[0] < grid.rows:
        out[fine.shape[0]:, :] = out[fine.shape[0] - 1: fine.shape[0], :]
    if fine.shape[1] < grid.cols:
        out[:, fine.shape[1]:] = out[:, fine.shape[1] - 1: fine.shape[1]]
    return out


def nadir_views(cameras: Sequence[PosedCamera], grid: Grid, heights: np.ndarray, k: int,
                margin_px: float = 8.0) -> np.ndarray:
    """(rows, cols, k) indices of the cameras seeing each cell nearest to nadir (-1: none)."""
    x, y = grid.centers()
    pts = np.column_stack([x.ravel(), y.ravel(), heights.ravel()])
    n = len(pts)
    dist = np.full((n, len(cameras)), np.inf, np.float32)
    for i, cam in enumerate(cameras):
        uv, depth = cam.project(pts)
        inside = ((depth > 0) & (uv[:, 0] >= margin_px) & (uv[:, 0] < cam.width - margin_px)
                  & (uv[:, 1] >= margin_px) & (uv[:, 1] < cam.height - margin_px))
        centre = cam.center
        d = np.hypot(pts[:, 0] - centre[0], pts[:, 1] - centre[1])
        dist[inside, i] = d[inside]
    order = np.argsort(dist, axis=1)[:, :k]
    chosen = np.take_along_axis(dist, order, axis=1)
    order[~np.isfinite(chosen)] = -1
    if order.shape[1] < k:
        order = np.pad(order, ((0, 0), (0, k - order.shape[1])), constant_values=-1)
    return order.reshape(grid.rows, grid.cols, k)


def _sample(images: Sequence[np.ndarray], cameras: Sequence[PosedCamera], views: np.ndarray,
            pts: np.ndarray) -> np.ndarray:
    """Grey values of points ``pts`` (N, 3) in camera ``views[n]`` (-1 gives NaN)."""
    from scipy.ndimage import map_coordinates

    out = np.full(len(pts), np.nan, np.float32)
    for i in np.unique(views):
        if i < 0:
            continue
        sel = np.flatnonzero(views == i)
        uv, _ = cameras[i].project(pts[sel])
        # map_coordinates indexes pixel centres at integers: shift by half a pixel.
        out[sel] = map_coordinates(images[i], [uv[:, 1] - 0.5, uv[:, 0] - 0.5], order=1,
                                   mode="constant", cval=np.nan)
    return out


def _ncc(a: np.ndarray, b: np.ndarray, size: int, mask: np.ndarray | None = None,
         min_fraction: float = 0.4) -> np.ndarray:
    """Windowed normalised cross-correlation of two rasters over the cells in ``mask``.

    NaN where either raster is NaN or fewer than ``min_fraction`` of the window counts.
    """
    from scipy.ndimage import uniform_filter

    valid = np.isfinite(a) & np.isfinite(b)
    if mask is not None:
        valid &= mask
    a0, b0 = np.where(valid, a, 0.0), np.where(valid, b, 0.0)
    w = uniform_filter(valid.astype(np.float32), size)
    with np.errstate(invalid="ignore", divide="ignore"):
        ma = uniform_filter(a0, size) / w
        mb = uniform_filter(b0, size) / w
        va = uniform_filter(a0 * a0, size) / w - ma * ma
        vb = uniform_filter(b0 * b0, size) / w - mb * mb
        cov = uniform_filter(a0 * b0, size) / w - ma * mb
        ncc = cov / np.sqrt(np.maximum(va, 1e-6) * np.maximum(vb, 1e-6))
    ncc[(w < min_fraction) | ~valid] = np.nan
    return ncc


def _class_aware_ncc(a: np.ndarray, b: np.ndarray, size: int, classes: np.ndarray | None
                     ) -> np.ndarray:
    """NCC whose window only uses cells of the centre cell's class (vegetation or not).

    Windows that straddle a crown edge otherwise take the height of the more textured
    side, fattening crowns over their dark shadow and thinning them on the sunlit side.
    """
    if classes is None:
        return _ncc(a, b, size, min_fraction=0.8)
    known = np.isfinite(classes)
    green = known & (classes > 0.5)
    return np.where(green, _ncc(a, b, size, green), _ncc(a, b, size, known & ~green))


def dense_surface(cameras: Sequence[PosedCamera], images: Sequence[np.ndarray], grid: Grid,
                  ground: np.ndarray, max_height: float, options: SurfaceOptions | None = None,
                  classes: Sequence[np.ndarray] | None = None,
                  progress: Progress | None = None) -> SurfaceModel:
    """DSM by multi-view height matching above ``ground`` up to ``max_height`` (m).

    ``images`` are grey float32 arrays matching ``cameras`` (same size as each camera);
    ``classes`` optional float32 arrays of the same size, 1 for vegetation, 0 otherwise,
    keep matching windows on one side of crown edges.
    """
    opts = options or SurfaceOptions()
    report = progress or (lambda *_: None)
    k = max(opts.views_per_cell, 2)
    levels = np.arange(-0.5, max_height + opts.height_step, opts.height_step)
    views = nadir_views(cameras, grid, ground + 0.5 * max_height, k)
    flat_views = views.reshape(-1, k)
    x, y = grid.centers()
    xy = np.column_stack([x.ravel(), y.ravel()])
    g = ground.ravel()
    best = np.full(len(g), -np.inf, np.float32)
    best_level = np.zeros(len(g), np.int32)
    before = np.full(len(g), np.nan, np.float32)
    after = np.full(len(g), np.nan, np.float32)
    previous = np.full(len(g), np.nan, np.float32)
    for li, h in enumerate(levels):
        pts = np.column_stack([xy, g + h])
        ref = _sample(images, cameras, flat_views[:, 0], pts).reshape(grid.shape)
        ref_class = (None if classes is None else
                     _sample(classes, cameras, flat_views[:, 0], pts).reshape(grid.shape))
        scores = []
        for j in range(1, k):
            other = _sample(images, cameras, flat_views[:, j], pts).reshape(grid.shape)
            scores.append(_class_aware_ncc(ref, other, opts.window_cells, ref_class))
        stack = np.stack(scores)
        # Robust to one occluded view: average the best k-2 of the k-1 pairs.
        if k > 2:
            stack = np.sort(np.where(np.isfinite(stack), stack, -np.inf), axis=0)[1:]
            stack[~np.isfinite(stack)] = np.nan
        with np.errstate(invalid="ignore"):
            score = np.nanmean(stack, axis=0).ravel().astype(np.float32)
        score[~np.isfinite(score)] = -np.inf
        just_after = best_level == li - 1
        after[just_after] = score[just_after]
        better = score > best
        best[better] = score[better]
        best_level[better] = li
        before[better] = previous[better]
        after[better] = np.nan
        previous = score
        report("Surface matching", li + 1, len(levels))
    # Sub-step refinement: vertex of the parabola through the best score and its neighbours.
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = before - 2 * best + after
        shift = np.where(np.isfinite(denom) & (denom < 0), 0.5 * (before - after) / denom, 0.0)
    shift = np.clip(np.nan_to_num(shift), -0.5, 0.5)
    height = levels[best_level] + shift * opts.height_step
    dsm = (g + height).reshape(grid.shape)
    score = best.reshape(grid.shape)
    dsm[~(score >= opts.min_score)] = np.nan
    return SurfaceModel(grid, dsm, ground, score, views, [c.name for c in cameras])


def clean_surface(dsm: np.ndarray, ground: np.ndarray, median_cells: int = 3) -> np.ndarray:
    """Median-filter the matched surface, fill unmatched cells, never below the ground."""
    from scipy.ndimage import median_filter

    filled = _fill_nans(dsm)
    smooth = median_filter(filled, size=median_cells, mode="nearest")
    return np.maximum(smooth, ground - 0.2)
