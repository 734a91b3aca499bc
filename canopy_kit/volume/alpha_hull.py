"""Fast alpha volume: the alpha hull as a morphological closing of the points by a ball.

The α-hull of a point set P is the complement of the union of all open balls of radius α
that contain no point of P. With ``D = {x : dist(x, P) < α}`` and ``E`` its complement
(the centres of those empty balls), the hull is ``C = {x : dist(x, E) >= α}``: a
dilation followed by an erosion, i.e. a closing by a ball of radius α.

On a grid of step h (α/4 by default, finer for small crowns) the two distance fields come from Euclidean distance
transforms, and both are made exact where it matters, so the result does not drift with h:

1. ``dist(x, P)`` from the occupancy grid is off by at most h·√3/2 (points snapped to
   voxel centres); nodes whose value is that close to α, and the ends of grid edges that
   cross the level α, are recomputed exactly with a k-d tree of the points;
2. the boundary of E is located to sub-voxel precision on every crossing grid edge by
   linear interpolation, and ``dist(x, E)`` near the level α is the exact distance to those
   boundary points (k-d tree);
3. each node near the boundary counts the fraction ``clip((dist - α)/h + 1/2, 0, 1)`` of
   its voxel (exact for a plane), every node further inside counts whole; on a curved
   boundary that over-counts by M h²/12 (M the integrated mean curvature), which is
   measured from the same counts with the boundary shifted by ±h/2 and removed.

It differs from the exact alpha complex (:mod:`canopy_kit.volume.alpha`) in two ways, both
measured in tests/test_volume_alpha_hull.py: its boundary between sparse surface points is
bitten by the empty balls (curved, slightly smaller), and it fills concave edges with a
round fillet of radius α where the complex fills them with straight tetrahedra.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from canopy_kit.plugins.params import Positive
from canopy_kit.volume.alpha import PAPER_ALPHA_M
from canopy_kit.volume.base import VolumeEstimator

DEFAULT_CELLS_PER_ALPHA = 4.0
MAX_CELLS = 8_000_000
# Above this median point spacing / α the hull's bites between points make it more than
# ~5 % smaller than the exact alpha shape (measured on sampled balls): flagged.
MAX_SPACING_RATIO = 0.2  # α/5


def grid_step(
    xyz: np.ndarray, alpha: float, step: float | None = None, max_cells: int = MAX_CELLS
) -> float:
    """The grid step used for ``alpha``: ``step`` if given, else the smallest of α/4, the
    largest extent/12 and the smallest extent/6, enlarged if the padded grid would exceed
    ``max_cells`` cells."""
    extent = np.ptp(xyz, axis=0)
    h = (
        step
        if step is not None
        else min(alpha / DEFAULT_CELLS_PER_ALPHA, float(extent.max()) / 12, float(extent.min()) / 6)
    )
    for _ in range(20):
        cells = np.prod(np.ceil((extent + 2 * alpha + 4 * h) / h) + 1)
        if cells <= max_cells:
            break
        h *= (cells / max_cells) ** (1 / 3) * 1.01
    return float(h)


def _edge_pairs(shape: tuple[int, ...], axis: int) -> tuple[tuple[slice, ...], tuple[slice, ...]]:
    lo = [slice(None)] * 3
    hi = [slice(None)] * 3
    lo[axis], hi[axis] = slice(0, -1), slice(1, None)
    return tuple(lo), tuple(hi)


def _crossing_points(field: np.ndarray, level: float, origin: np.ndarray, h: float) -> np.ndarray:
    """Where ``field`` crosses ``level`` along grid edges (linear interpolation), (M, 3)."""
    out = []
    for axis in range(3):
        lo, hi = _edge_pairs(field.shape, axis)
        a, b = field[lo], field[hi]
        idx = np.nonzero((a >= level) != (b >= level))
        fa, fb = a[idx], b[idx]
        pos = np.column_stack(idx).astype(np.float64) + 0.5
        pos[:, axis] += (level - fa) / (fb - fa)
        out.append(origin + pos * h)
    return np.concatenate(out)


def _crossing_ends(inside: np.ndarray) -> np.ndarray:
    """Nodes at either end of a grid edge whose two ends differ in ``inside``."""
    ends = np.zeros(inside.shape, bool)
    for axis in range(3):
        lo, hi = _edge_pairs(inside.shape, axis)
        cross = inside[lo] != inside[hi]
        ends[lo] |= cross
        ends[hi] |= cross
    return ends


def _node_centres(
    flat: np.ndarray, shape: tuple[int, ...], origin: np.ndarray, h: float
) -> np.ndarray:
    return origin + (np.column_stack(np.unravel_index(flat, shape)) + 0.5) * h


def alpha_hull_volume(
    xyz: np.ndarray,
    alpha: float,
    step: float,
    offset: float = 0.0,
    tree: object = None,
    fill_voids: bool = False,
) -> tuple[float, dict]:
    """Volume of the α-hull (closing of the points by a ball of radius ``alpha``) on a grid.

    ``offset`` (0 <= offset < α) grows the hull outwards by that distance: the solid is
    ``{x : dist(x, E) >= α - offset}``, the closing dilated by ``offset`` (used by
    :mod:`canopy_kit.volume.adaptive` for the envelope that lies outside the outermost points).
    ``tree``: a ``cKDTree`` of ``xyz`` already built by the caller. ``fill_voids`` counts
    closed cavities (empty space no α-ball from outside can reach, e.g. the leafless inside of
    a crown whose leaves form a shell) as solid: the hull of the outer envelope only. A hollow
    open to the outside (a vase's open centre) is not a void and stays empty. ``info["void_m3"]``
    is then the volume those enclosed empty balls would have carved (on the grid's voxels).
    """
    from scipy.spatial import cKDTree

    h = float(step)
    pad = alpha + 2 * h
    origin = xyz.min(axis=0) - pad
    shape = tuple(int(s) for s in np.ceil((xyz.max(axis=0) + pad - origin) / h) + 1)
    if tree is None:
        tree = cKDTree(xyz, balanced_tree=False, compact_nodes=False)
    grid = _Grid(origin, shape, h)
    empty, boundary, info = _empty_ball_centres(xyz, alpha, grid, tree, fill_voids)
    if len(boundary) == 0:
        return 0.0, info
    return _hull_volume(empty, boundary, alpha - offset, grid), info


@dataclass(frozen=True)
class _Grid:
    """The lattice the hull is measured on: corner, nodes per axis, step."""

    origin: np.ndarray
    shape: tuple[int, ...]
    h: float

    def centres(self, flat: np.ndarray) -> np.ndarray:
        return _node_centres(flat, self.shape, self.origin, self.h)


def _empty_ball_centres(
    xyz: np.ndarray, alpha: float, grid: _Grid, tree: Any, fill_voids: bool
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Step 1: the nodes at least ``alpha`` from every point (E, the centres of empty α-balls;
    with ``fill_voids`` only those reachable from outside), the sub-voxel points where the
    distance to the points crosses ``alpha``, and the grid's info. Distances are exact
    (k-d tree) wherever the side of α is uncertain."""
    from scipy import ndimage

    origin, shape, h = grid.origin, grid.shape, grid.h
    ijk = ((xyz - origin) / h).astype(np.intp)
    occupied = np.zeros(shape, bool)
    occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    dist_p = ndimage.distance_transform_edt(~occupied, sampling=h)
    snap = np.sqrt(3.0) / 2.0 * h
    sample = xyz[:: max(1, len(xyz) // 2000)]
    spacing = float(np.median(tree.query(sample, k=2)[0][:, 1]))
    info = {"grid_step": h, "grid_cells": int(np.prod(shape)), "spacing_ratio": spacing / alpha}
    # every node queried below is within α + 2·snap + h of a point: the bound only prunes
    bound = alpha + 2.0 * snap + h
    near = np.flatnonzero(np.abs(dist_p - alpha) <= snap)
    dist_p.flat[near] = tree.query(grid.centres(near), distance_upper_bound=bound)[0]
    exact = np.zeros(shape, bool)
    exact.flat[near] = True
    empty = dist_p >= alpha  # E: centres of empty α-balls
    if fill_voids:  # only the empty balls reachable from outside (26-connected) carve
        voids = empty & ndimage.binary_fill_holes(~empty, structure=np.ones((3, 3, 3), bool))
        info["void_m3"] = 0.0
        if voids.any():
            # what the void's empty balls would carve: within α of their centres (voxels)
            carved = ndimage.distance_transform_edt(~voids, sampling=h) < alpha
            info["void_m3"] = float(np.count_nonzero(carved) * h**3)
            empty &= ~voids
            dist_p[voids] = 0.0  # no α-level crossing on a void's wall
    ends = np.flatnonzero(_crossing_ends(empty) & ~exact)
    dist_p.flat[ends] = tree.query(grid.centres(ends), distance_upper_bound=bound)[0]
    return empty, _crossing_points(dist_p, alpha, origin, h), info


def _hull_volume(empty: np.ndarray, boundary: np.ndarray, level: float, grid: _Grid) -> float:
    """Steps 2 and 3: the volume of the nodes at least ``level`` from E, the distance to E
    exact (to the sub-voxel ``boundary`` points) near that level: whole voxels inside,
    partial voxels along the boundary."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    h = grid.h
    snap = np.sqrt(3.0) / 2.0 * h
    dist_e = ndimage.distance_transform_edt(~empty, sampling=h)
    top = level + h + 2.0 * snap
    band = np.flatnonzero((dist_e >= level - h) & (dist_e < top))
    # depths beyond h count whole under any ±h/2 shift: no need to find them exactly (inf)
    depth = (
        cKDTree(boundary, leafsize=32).query(grid.centres(band), distance_upper_bound=level + h)[0]
        - level
    )
    # The ramp is exact for a plane and over-counts a curved boundary by M h²/12 (M:
    # integrated mean curvature), removed with the second difference of the count under a
    # ±h/2 shift of the boundary.
    inner = np.count_nonzero(dist_e >= top)

    def count(shift: float) -> float:
        return inner + float(np.clip((depth + shift) / h + 0.5, 0.0, 1.0).sum())

    mid = count(0.0)
    cells = mid - (count(0.5 * h) + count(-0.5 * h) - 2.0 * mid) / 6.0
    return float(cells * h**3)


class AlphaHullVolume(VolumeEstimator):
    """Fast α-hull volume (closing by a ball of radius α on a grid), α in metres.

    ``grid_step`` None picks min(α/4, largest extent/12, smallest extent/6), capped at
    8 M cells; the step used is reported in ``result.extra["grid_step"]``. Clouds whose
    median point spacing exceeds α/5 are flagged (the hull then falls well below the
    exact alpha shape); the volume is still returned.

    Parameters
    ----------
    alpha : float, default 0.9
        Radius (m) of the closing ball: concavities narrower than it are filled.
    grid_step : float or None, default None
        Edge (m) of the grid the closing runs on; None picks one from α and the extent.
    """

    name = "alpha_hull"
    measures = (
        "the alpha-hull of the points: closed by a ball of radius alpha (default 0.9 m), "
        "concavities narrower than about 2 alpha filled"
    )
    convex_rtol = 0.03  # the grid's rounding of edges and corners (1.1 % on the unit cube)

    def __init__(self, alpha: Positive = PAPER_ALPHA_M, grid_step: Positive | None = None) -> None:
        self.alpha = alpha
        self.grid_step = grid_step

    def _volume(self, xyz: np.ndarray) -> tuple[float, dict]:
        h = grid_step(xyz, float(self.alpha), self.grid_step)
        volume, extra = alpha_hull_volume(xyz, float(self.alpha), h)
        if volume <= 0.0:
            extra["reason"] = (
                f"alpha = {self.alpha} m is below the point spacing: the alpha hull is empty"
            )
        elif extra["spacing_ratio"] > MAX_SPACING_RATIO:
            extra["reason"] = (
                f"points too sparse for the alpha hull: median spacing "
                f"{extra['spacing_ratio'] * self.alpha:.2f} m exceeds alpha/5 = "
                f"{self.alpha / 5:.2f} m, where the hull falls more than ~5 % "
                f"below the alpha shape; use alpha_shape"
            )
        return volume, extra
