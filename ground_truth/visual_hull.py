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
narrow on porous, lobed crowns. So each crown's outline is grown by ``outline_margin_m``,
never into a neighbour's, and its silhouettes, not the outline, bound its sides, unless the
views would not bound them: :func:`outline_excess` carves a round crown of the crown's size
at its centre with exact silhouettes in the flight's cameras and measures how much of it
would reach into the grown ring; above ``max_outline_excess`` of the crown's volume the
outline is kept (views from one line of bearings; docs/GROUND_TRUTH.md).
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
    # that the silhouettes bound the hull, for the crowns whose views bound their sides: a
    # round crown of the crown's size, carved with its exact silhouettes, would let at most
    # ``max_outline_excess`` of its volume into the grown ring (``outline_excess``). 0: never
    # grown (docs/GROUND_TRUTH.md, issue 51).
    outline_margin_m: float = 0.6
    max_outline_excess: float = 0.05  # 17 flights tried: <= 0.64 %; one line of views: 26 %
    image_size: int = 800


@dataclass(frozen=True)
class PhotoMasks:
    """The registered photos and their vegetation masks packed once for the compiled
    carving (:func:`pack_photos`): per photo its camera, world-to-camera rotation and
    translation, pinhole intrinsics (fx, fy, cx, cy, k1, k2), and where its mask (1:
    vegetation, row by row) starts in ``vegetation``, with its width and height."""

    cameras: tuple[PosedCamera, ...]
    rotations: np.ndarray
    translations: np.ndarray
    intrinsics: np.ndarray
    vegetation: np.ndarray
    offsets: np.ndarray
    widths: np.ndarray
    heights: np.ndarray

    @property
    def shapes(self) -> list[tuple[int, int]]:
        """Each mask's (rows, columns)."""
        return list(zip(self.heights.tolist(), self.widths.tolist(), strict=True))


def pack_photos(cameras: Sequence[PosedCamera], vegetation: Sequence[np.ndarray]) -> PhotoMasks:
    """Cameras and per-photo masks (bool or 0/1; > 0.5 is vegetation) as :class:`PhotoMasks`."""
    masks = [np.ravel(~(np.asarray(m) <= 0.5)).astype(np.uint8) for m in vegetation]
    sizes = [m.size for m in masks]
    return PhotoMasks(
        cameras=tuple(cameras),
        rotations=np.array([c.rotation for c in cameras], np.float64).reshape(-1, 3, 3),
        translations=np.array([c.translation for c in cameras], np.float64).reshape(-1, 3),
        intrinsics=np.array([c.intrinsics() for c in cameras], np.float64).reshape(-1, 6),
        vegetation=np.concatenate(masks) if masks else np.zeros(0, np.uint8),
        offsets=np.cumsum([0, *sizes[:-1]]).astype(np.int64)[: len(masks)],
        widths=np.array([np.shape(m)[1] for m in vegetation], np.int64),
        heights=np.array([np.shape(m)[0] for m in vegetation], np.int64),
    )


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
    """Visual-hull volume (m³) of each crown of ``crowns`` (rows in order, ``crown_id``),
    the outlines grown first where the views bound the crowns' sides
    (:func:`grow_bounded_outlines`).

    ``vegetation`` are per-photo masks (bool or 0/1, the size of each camera's image);
    ``labels`` the crown label raster on ``grid`` (0: no crown); ``ground`` the terrain
    heights on ``ground_grid``; ``crowns`` needs ``crown_id`` and ``height_m`` (top above
    the ground). NaN for a crown whose centre fewer than ``min_views`` photos see;
    ``progress(stage, done, total)`` after each crown."""
    photos = pack_photos(cameras, vegetation)
    opts = options or HullOptions()
    return carve_hulls(photos, labels, grid, crowns, ground, ground_grid, opts, progress)[0]


def carve_hulls(
    photos: PhotoMasks,
    labels: np.ndarray,
    grid: Grid,
    crowns: pd.DataFrame,
    ground: np.ndarray,
    ground_grid: Grid,
    opts: HullOptions,
    progress: Callable[[str, float, float], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`crown_hull_volumes` on packed photos, and which crowns (rows of ``crowns``)
    had their outline grown."""
    grown = np.zeros(len(crowns), bool)
    if opts.outline_margin_m > 0:
        labels, grown = grow_bounded_outlines(
            photos, labels, grid, crowns, ground, ground_grid, opts
        )
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
        out[k] = _carve(pts, photos, opts) * opts.voxel_m**3
    report("Visual hull", len(crowns), len(crowns))
    return out, grown


def outline_excess(
    cameras: Sequence[PosedCamera],
    shapes: Sequence[tuple[int, ...]],
    centre: np.ndarray,
    radius: float,
    margin: float,
    opts: HullOptions,
) -> float:
    """How much of a round crown (a sphere of ``radius`` at ``centre``) the views would let
    into a ring ``margin`` wide round its outline, as a share of its volume: the voxels of
    the ring (within the sphere's height) that the hull's rule keeps (``min_views`` photos
    see them, ``min_fraction`` of those on the sphere's exact silhouette: the ray from the
    camera passes within ``radius`` of the centre). 0 where the views bound the sides; a
    view from one bearing bounds only the sides across it."""
    step = min(2 * opts.voxel_m, max(radius / 8, 0.02))  # a tiny crown: bounded work
    reach = radius + margin
    a = np.arange(-reach, reach + step / 2, step)
    gx, gy = np.meshgrid(a, a)
    rho = np.hypot(gx, gy)
    ring = (rho > radius) & (rho <= reach)
    z = np.arange(-radius, radius, step) + step / 2
    n = int(ring.sum())
    pts = np.column_stack(
        [np.tile(gx[ring], len(z)), np.tile(gy[ring], len(z)), np.repeat(z, n)]
    ) + np.asarray(centre, float)
    seen = np.zeros(len(pts), np.int32)
    on = np.zeros(len(pts), np.int32)
    for cam, shape in zip(cameras, shapes, strict=True):
        ok = _visible(cam, shape, pts)
        if ok.any():
            ray = pts[ok] - cam.center
            to_centre = np.asarray(centre, float) - cam.center
            miss = np.linalg.norm(np.cross(to_centre, ray), axis=1) / np.linalg.norm(ray, axis=1)
            seen[ok] += 1
            on[ok] += miss <= radius
    stays = (seen >= opts.min_views) & (on >= opts.min_fraction * seen)
    return float(stays.sum() * step**3 / (4 / 3 * np.pi * radius**3))


def crown_centres(
    labels: np.ndarray,
    grid: Grid,
    crowns: pd.DataFrame,
    ground: np.ndarray,
    ground_grid: Grid,
) -> tuple[np.ndarray, np.ndarray]:
    """Each crown's centre (n x 3; NaN without cells), its outline's mean position at half
    its height above the ground there, and radius (the outline's area as a circle's)."""
    x, y = grid.centers()
    out = np.full((len(crowns), 3), np.nan)
    radii = np.full(len(crowns), np.nan)
    for k, crown in enumerate(crowns.itertuples()):
        cells = labels == crown.crown_id
        if cells.any():
            cx, cy = float(x[cells].mean()), float(y[cells].mean())
            z0 = _sample(ground, ground_grid, np.array([cx]), np.array([cy]))[0]
            z0 = z0 if np.isfinite(z0) else float(np.nanmedian(ground))
            out[k] = (cx, cy, z0 + float(crown.height_m) / 2)
            radii[k] = np.sqrt(cells.sum() * grid.resolution**2 / np.pi)
    return out, radii


def bounded_crowns(
    cameras: Sequence[PosedCamera],
    shapes: Sequence[tuple[int, ...]],
    centres: np.ndarray,
    radii: np.ndarray,
    opts: HullOptions,
) -> np.ndarray:
    """Which crowns (rows of ``centres``, ``radii``) have their sides bounded by the views:
    a round crown of that size there would let at most ``max_outline_excess`` of its
    volume into the grown ring (:func:`outline_excess`)."""
    out = np.zeros(len(centres), bool)
    for k, (c, r) in enumerate(zip(centres, radii, strict=True)):
        if np.isfinite(c).all() and r > 0:
            excess = outline_excess(cameras, shapes, c, r, opts.outline_margin_m, opts)
            out[k] = excess <= opts.max_outline_excess
    return out


def grow_bounded_outlines(
    photos: PhotoMasks,
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

    centres, radii = crown_centres(labels, grid, crowns, ground, ground_grid)
    bounded = bounded_crowns(photos.cameras, photos.shapes, centres, radii, opts)
    grow = crowns["crown_id"].to_numpy()[bounded]
    if not len(grow):
        return labels, bounded
    grown = expand_labels(labels, opts.outline_margin_m / grid.resolution)
    added = (labels == 0) & np.isin(grown, grow)
    return np.where(added, grown, labels), bounded


def _carve(pts: np.ndarray, photos: PhotoMasks, opts: HullOptions) -> float:
    """How many voxel centres ``pts`` stay (NaN when fewer than ``min_views`` photos see the
    crown's centre). A voxel stays when at least ``min_views`` photos see it and at least
    ``min_fraction`` of them show vegetation there. Photos whose view misses the crown's box
    are skipped, and a voxel is dropped as soon as more photos showed no vegetation there
    than ``1 - min_fraction`` of every photo that can see the box: it can no longer stay,
    so the result is the same as carving every voxel in every photo, only faster."""
    if len(pts) == 0:
        return float("nan")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    shapes = photos.shapes
    views = [k for k, cam in enumerate(photos.cameras) if _box_in_view(cam, shapes[k], lo, hi)]
    centre = np.array([[*pts[:, :2].mean(axis=0), (lo[2] + hi[2]) / 2]])
    seen = sum(_visible(photos.cameras[k], shapes[k], centre)[0] for k in views)
    if seen < opts.min_views:
        return float("nan")
    from ground_truth.kernels import carve_count  # numba: compiled on first use

    v = np.array(views, np.int64)
    return float(
        carve_count(
            np.ascontiguousarray(pts, np.float64),
            photos.rotations[v],
            photos.translations[v],
            photos.intrinsics[v],
            photos.vegetation,
            photos.offsets[v],
            photos.widths[v],
            photos.heights[v],
            (1.0 - opts.min_fraction) * len(views) + 1e-9,
            opts.min_views,
            opts.min_fraction,
        )
    )


def _visible(cam: PosedCamera, shape: tuple[int, ...], pts: np.ndarray) -> np.ndarray:
    """Which points project inside the image in front of the camera."""
    uv, depth = cam.project(pts)
    col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
    return (depth > 0) & (col >= 0) & (row >= 0) & (col < shape[1]) & (row < shape[0])


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
