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
    height_step: float = 0.15
    views_per_cell: int = 4
    window_cells: int = 3
    min_score: float = 0.3
    class_weight: float = 1.0
    all_pairs: bool = True
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


def reliable_points(
    points: np.ndarray,
    track_lengths: np.ndarray,
    errors: np.ndarray,
    min_track: int = 3,
    max_error_px: float = 1.0,
) -> np.ndarray:
    """Sparse points seen in at least ``min_track`` photos with a small reprojection error.

    Two-view points include rare gross outliers (one was 200 m below the ground).
    """
    keep = (np.asarray(track_lengths) >= min_track) & (np.asarray(errors) <= max_error_px)
    return np.asarray(points)[keep]


def ground_model(
    points: np.ndarray, grid: Grid, window_m: float = 10.0, resolution: float = 1.0
) -> np.ndarray:
    """Ground heights on ``grid``: lowest point per coarse cell, opened by ``window_m``.

    The opening (minimum then maximum filter) removes anything narrower than the window
    (crowns) while following slopes better than a plain minimum would. ``points`` should
    be reliable (see ``reliable_points``): one gross outlier pulls a whole window down.
    """
    from scipy.ndimage import gaussian_filter, maximum_filter, minimum_filter, zoom

    points = np.asarray(points, float)
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
    opened = maximum_filter(
        minimum_filter(filled, size=size, mode="nearest"), size=size, mode="nearest"
    )
    smooth = gaussian_filter(opened, sigma=max(size / 4.0, 1.0), mode="nearest")
    # Back to the fine grid (bilinear).
    fine = zoom(smooth, (grid.rows / coarse.rows, grid.cols / coarse.cols), order=1, mode="nearest")
    out = np.empty(grid.shape)
    out[: fine.shape[0], : fine.shape[1]] = fine[: grid.rows, : grid.cols]
    if fine.shape[0] < grid.rows:
        out[fine.shape[0] :, :] = out[fine.shape[0] - 1 : fine.shape[0], :]
    if fine.shape[1] < grid.cols:
        out[:, fine.shape[1] :] = out[:, fine.shape[1] - 1 : fine.shape[1]]
    return out


def nadir_views(
    cameras: Sequence[PosedCamera],
    grid: Grid,
    heights: np.ndarray,
    k: int,
    margin_px: float = 8.0,
    block_m: float = 0.25,
) -> np.ndarray:
    """(rows, cols, k) indices of the cameras seeing each cell nearest to nadir (-1: none).

    Decided per block of about ``block_m`` (the choice changes slowly across the ground),
    with the image margin widened by the block size so every cell of a block is inside.
    """
    step = max(int(block_m / grid.resolution), 1)
    rows, cols = -(-grid.rows // step), -(-grid.cols // step)
    x, y = grid.centers()
    h = np.asarray(heights, float)
    # Block centres (clipped to the grid) and the block's highest surface.
    rc = np.minimum(np.arange(rows) * step + step // 2, grid.rows - 1)
    cc = np.minimum(np.arange(cols) * step + step // 2, grid.cols - 1)
    bx, by = x[np.ix_(rc, cc)].ravel(), y[np.ix_(rc, cc)].ravel()
    bz = h[np.ix_(rc, cc)].ravel()
    pts = np.column_stack([bx, by, bz])
    dist = np.full((len(pts), len(cameras)), np.inf, np.float32)
    for i, cam in enumerate(cameras):
        uv, depth = cam.project(pts)
        pad = margin_px + step * grid.resolution * cam.focal / max(float(np.median(depth)), 1e-6)
        inside = (
            (depth > 0)
            & (uv[:, 0] >= pad)
            & (uv[:, 0] < cam.width - pad)
            & (uv[:, 1] >= pad)
            & (uv[:, 1] < cam.height - pad)
        )
        centre = cam.center
        dist[inside, i] = np.hypot(bx[inside] - centre[0], by[inside] - centre[1])
    kk = min(k, len(cameras))
    order = (
        np.argpartition(dist, kk - 1, axis=1)[:, :kk]
        if kk < len(cameras)
        else np.tile(np.arange(len(cameras)), (len(pts), 1))
    )
    chosen = np.take_along_axis(dist, order, axis=1)
    sort = np.argsort(chosen, axis=1)
    order = np.take_along_axis(order, sort, axis=1)
    order[~np.isfinite(np.take_along_axis(chosen, sort, axis=1))] = -1
    if order.shape[1] < k:
        order = np.pad(order, ((0, 0), (0, k - order.shape[1])), constant_values=-1)
    blocks = order.reshape(rows, cols, k)
    return blocks[np.arange(grid.rows)[:, None] // step, np.arange(grid.cols)[None, :] // step]


class _ViewSampler:
    """Grey values (and vegetation classes) of every cell at any height in its assigned photo
    (one photo per cell).

    The projection is split once into a height-independent part and the camera's third
    rotation column, so each height costs one division and one bilinear lookup per cell and
    image (``ground_truth.kernels.project_bilinear``).
    """

    def __init__(
        self,
        cameras: Sequence[PosedCamera],
        images: Sequence[np.ndarray],
        views: np.ndarray,
        xy: np.ndarray,
        ground: np.ndarray,
        classes: Sequence[np.ndarray] | None = None,
    ) -> None:
        self.n = len(views)
        self.with_classes = classes is not None
        no_classes = np.empty((0, 0), np.float32)
        self.groups = []
        for i in np.unique(views):
            if i < 0:
                continue
            idx = np.flatnonzero(views == i)
            cam = cameras[i]
            pts = np.column_stack([xy[idx], ground[idx]])
            base = (pts @ cam.rotation.T + cam.translation).astype(np.float32)
            intrinsics = np.asarray(cam.intrinsics(), np.float64)
            axis = cam.rotation[:, 2].astype(np.float32)
            image = np.asarray(images[i], np.float32)
            cls = no_classes if classes is None else np.asarray(classes[i], np.float32)
            self.groups.append((idx, base, axis, intrinsics, image, cls))

    def sample(self, height: float) -> tuple[np.ndarray, np.ndarray | None]:
        """(grey values, classes or None) of every cell at ``height`` above the ground."""
        from ground_truth.kernels import project_bilinear

        out = np.full(self.n, np.nan, np.float32)
        out_classes = np.full(self.n if self.with_classes else 0, np.nan, np.float32)
        h = float(np.float32(height))
        for idx, base, axis, intrinsics, image, cls in self.groups:
            project_bilinear(base, axis, h, intrinsics, image, idx, out, cls, out_classes)
        return out, (out_classes if self.with_classes else None)


def dense_surface(
    cameras: Sequence[PosedCamera],
    images: Sequence[np.ndarray],
    grid: Grid,
    ground: np.ndarray,
    max_height: float,
    options: SurfaceOptions | None = None,
    classes: Sequence[np.ndarray] | None = None,
    progress: Progress | None = None,
) -> SurfaceModel:
    """DSM by multi-view height matching above ``ground`` up to ``max_height`` (m).

    ``images`` are grey float32 arrays matching ``cameras`` (same size as each camera);
    ``classes`` optional float32 arrays of the same size, 1 for vegetation, 0 otherwise:
    views that disagree on vegetation within the window are penalised. NCC alone lets the
    most textured part of a window decide, so crowns swell over their dark shadows; the
    class term counts cells, whatever their contrast.
    """
    from ground_truth.kernels import pair_score  # numba: compiled on first use, not on import

    opts = options or SurfaceOptions()
    report = progress or (lambda *_: None)
    k = max(opts.views_per_cell, 2)
    levels = np.arange(-0.5, max_height + opts.height_step, opts.height_step)
    views = nadir_views(cameras, grid, ground + 0.5 * max_height, k)
    flat_views = views.reshape(-1, k)
    x, y = grid.centers()
    xy = np.column_stack([x.ravel(), y.ravel()])
    g = ground.ravel()
    samplers = [_ViewSampler(cameras, images, flat_views[:, j], xy, g, classes) for j in range(k)]
    best = np.full(len(g), -np.inf, np.float32)
    best_level = np.zeros(len(g), np.int32)
    before = np.full(len(g), np.nan, np.float32)
    after = np.full(len(g), np.nan, np.float32)
    previous = np.full(len(g), np.nan, np.float32)
    if opts.all_pairs:
        pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
        keep = max(len(pairs) - (k - 1), 1)  # drop as many pairs as one occluded view spoils
    else:
        pairs = [(0, j) for j in range(1, k)]
        keep = len(pairs) - 1 if k > 2 else len(pairs)
    for li, h in enumerate(levels):
        sampled = [s.sample(h) for s in samplers]
        grey = [values.reshape(grid.shape) for values, _ in sampled]
        cls = None if classes is None else [c.reshape(grid.shape) for _, c in sampled]
        weight = opts.class_weight if cls is not None else 0.0
        scores = [
            pair_score(
                grey[i],
                grey[j],
                grey[i] if cls is None else cls[i],
                grey[j] if cls is None else cls[j],
                opts.window_cells,
                0.8,
                weight,
            )
            for i, j in pairs
        ]
        stack = np.stack(scores)
        # Robust to one view that sees something else (occlusion): average the best pairs.
        stack = np.sort(np.where(np.isfinite(stack), stack, -np.inf), axis=0)[len(pairs) - keep :]
        stack[~np.isfinite(stack)] = np.nan
        finite = np.isfinite(stack)
        count = finite.sum(axis=0)
        score = (
            np.where(
                count > 0, np.where(finite, stack, 0.0).sum(axis=0) / np.maximum(count, 1), -np.inf
            )
            .ravel()
            .astype(np.float32)
        )
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


SEARCH_HEIGHT_WITHOUT_DATA_M = 8.0  # the coarse pass's range when the sparse points tell nothing
SEARCH_MARGIN_M = 2.0  # above the sparse points' canopy: the coarse pass finds the real top
MIN_CANOPY_POINTS = 30  # sparse points above the floor that show where the canopy ends


def search_height(
    points: np.ndarray, grid: Grid, ground: np.ndarray, floor: float = 0.5
) -> tuple[float, str]:
    """The highest canopy (m above ground) the surface matching searches, from the flight's own
    sparse points (no fixed limit): the top of their height distribution below its first
    empty 2 m band (``canopy_kit.segment.preprocess.canopy_ceiling``: trees of any height,
    not a stray point high above them) plus ``SEARCH_MARGIN_M``; with too few points above
    ``floor``, ``SEARCH_HEIGHT_WITHOUT_DATA_M``. Returns the height and where it came from."""
    from canopy_kit.segment.preprocess import canopy_ceiling
    from ground_truth.raster import sample_bilinear

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts):
        height = pts[:, 2] - sample_bilinear(grid, ground, pts[:, 0], pts[:, 1])
        height = height[np.isfinite(height)]
        if int((height >= floor).sum()) >= MIN_CANOPY_POINTS:
            top = canopy_ceiling(height, floor) + SEARCH_MARGIN_M
            return float(top), "the flight's sparse points"
    return SEARCH_HEIGHT_WITHOUT_DATA_M, "too few sparse points above the ground: a default"


def canopy_top(
    cameras: Sequence[PosedCamera],
    images: Sequence[np.ndarray],
    grid: Grid,
    ground: np.ndarray,
    max_height: float,
    options: SurfaceOptions | None = None,
) -> float:
    """Height above ground of the highest canopy (m), from a quick coarse matching pass.

    Sets the search range of the fine pass: most orchards stay well below ``max_height``.
    """
    from scipy.ndimage import zoom

    opts = options or SurfaceOptions()
    factor = 4
    coarse = grid.resampled(grid.resolution * factor)
    g = zoom(ground, (coarse.rows / grid.rows, coarse.cols / grid.cols), order=1)[
        : coarse.rows, : coarse.cols
    ]
    g = np.pad(g, ((0, coarse.rows - g.shape[0]), (0, coarse.cols - g.shape[1])), mode="edge")
    rough = SurfaceOptions(
        resolution=coarse.resolution,
        height_step=max(2 * opts.height_step, 0.25),
        views_per_cell=opts.views_per_cell,
        window_cells=5,
        min_score=0.5,
    )
    model = dense_surface(cameras, images, coarse, g, max_height, rough)
    chm = clean_surface(model.dsm, g) - g  # median filter: isolated false matches go
    return float(min(max(np.nanmax(chm) + 1.0, 2.0), max_height))


def ground_from_surface(dsm: np.ndarray, grid: Grid, window_m: float) -> np.ndarray:
    """Ground heights as the morphological opening of a dense surface (crowns removed)."""
    from scipy.ndimage import gaussian_filter, maximum_filter, minimum_filter

    size = max(int(round(window_m / grid.resolution)) | 1, 3)
    opened = maximum_filter(
        minimum_filter(dsm, size=size, mode="nearest"), size=size, mode="nearest"
    )
    return gaussian_filter(opened, sigma=size / 4.0, mode="nearest")


def clean_surface(dsm: np.ndarray, ground: np.ndarray, median_cells: int = 3) -> np.ndarray:
    """Median-filter the matched surface, fill unmatched cells, never below the ground."""
    from scipy.ndimage import median_filter

    filled = _fill_nans(dsm)
    smooth = median_filter(filled, size=median_cells, mode="nearest")
    return np.maximum(smooth, ground - 0.2)
