"""Ground model: RANSAC planes on overlapping cells, joined into a smooth height grid.

One plane cannot follow an orchard's slope changes and bumps, so the ground is fitted
piecewise: the lowest point of each small cell is a ground candidate, a RANSAC plane is
fitted to the candidates of every ``cell_size`` cell (with half a cell of overlap), and
the planes' heights at the cell centres form a grid that is interpolated bilinearly.
Cells without enough candidates (under dense canopy, outside the scan) are filled from
their nearest fitted neighbours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from canopy_kit.core.cloud import column_max, column_min
from canopy_kit.core.voxel import first_minimum
from canopy_kit.errors import InputError, ProcessingError


@dataclass(frozen=True)
class GroundModel:
    """Ground heights on a regular grid of cell centres; ``height(xy)`` interpolates."""

    origin: np.ndarray  # xy of the centre of cell (0, 0)
    cell_size: float
    heights: np.ndarray  # (nx, ny) ground height at the cell centres
    fitted: np.ndarray  # (nx, ny) True where a plane was fitted, False where filled

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height at points ``xy`` (N, 2); bilinear inside, clamped outside the grid."""
        xy = np.asarray(xy, dtype=np.float64)
        g = (xy[:, :2] - self.origin) / self.cell_size
        nx, ny = self.heights.shape
        gx = np.clip(g[:, 0], 0, nx - 1)
        gy = np.clip(g[:, 1], 0, ny - 1)
        return ndimage.map_coordinates(self.heights, [gx, gy], order=1, mode="nearest")

    def above(self, xyz: np.ndarray) -> np.ndarray:
        """Height of points above the ground model."""
        xyz = np.asarray(xyz, dtype=np.float64)
        return xyz[:, 2] - self.height(xyz[:, :2])


def lowest_per_cell(xyz: np.ndarray, cell: float) -> np.ndarray:
    """The lowest point of every occupied ``cell`` x ``cell`` column: ground candidates."""
    keys = np.floor((xyz[:, :2] - column_min(xyz[:, :2])) / cell).astype(np.int64)
    lin = keys[:, 0] * (keys[:, 1].max() + 1) + keys[:, 1]
    return xyz[first_minimum(lin, xyz[:, 2])]


def ransac_plane(
    points: np.ndarray,
    threshold: float,
    rng: np.random.Generator,
    iterations: int = 64,
    max_slope: float = 0.6,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Plane ``z = a x + b y + c`` with most inliers within ``threshold``; (coef, inliers).

    Candidate planes steeper than ``max_slope`` (rise over run) are rejected: ground in an
    orchard is gentle, a steep plane through candidates is a crown or a trunk.
    """
    n = len(points)
    if n < 3:
        return None
    idx = rng.integers(0, n, (iterations, 3))
    p0, p1, p2 = points[idx[:, 0]], points[idx[:, 1]], points[idx[:, 2]]
    normal = np.cross(p1 - p0, p2 - p0)
    nz = normal[:, 2]
    ok = np.abs(nz) > 1e-9
    if not ok.any():
        return None
    coef = np.zeros((iterations, 3))
    coef[ok, 0] = -normal[ok, 0] / nz[ok]
    coef[ok, 1] = -normal[ok, 1] / nz[ok]
    coef[ok, 2] = p0[ok, 2] - coef[ok, 0] * p0[ok, 0] - coef[ok, 1] * p0[ok, 1]
    ok &= np.hypot(coef[:, 0], coef[:, 1]) <= max_slope
    if not ok.any():
        return None
    pred = coef[ok] @ np.column_stack([points[:, 0], points[:, 1], np.ones(n)]).T
    resid = np.abs(points[:, 2][None, :] - pred)
    # Vertical residual scaled to the perpendicular distance of the plane.
    dist = resid / np.sqrt(1.0 + coef[ok, 0] ** 2 + coef[ok, 1] ** 2)[:, None]
    counts = (dist <= threshold).sum(axis=1)
    # Ties go to the lower plane: crowns seen from below sit above the ground.
    score = counts - 1e-6 * coef[ok, 2]
    best = int(np.argmax(score))
    inliers = dist[best] <= threshold
    if inliers.sum() < 3:
        return None
    design = np.column_stack([points[inliers, 0], points[inliers, 1], np.ones(inliers.sum())])
    refined, *_ = np.linalg.lstsq(design, points[inliers, 2], rcond=None)
    return refined, inliers


def fit_ground(
    xyz: np.ndarray,
    cell_size: float = 4.0,
    threshold: float = 0.15,
    candidate_cell: float = 0.5,
    min_candidates: int = 8,
    seed: int = 0,
) -> GroundModel:
    """Fit the piecewise RANSAC ground model to a map's points (local metric frame)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if len(xyz) == 0:
        raise InputError("ground model: the map has no points")
    if not cell_size > 0 or not threshold > 0 or not candidate_cell > 0:
        raise InputError(
            f"ground model: cell_size ({cell_size}), ground_ransac_threshold ({threshold}) and "
            f"candidate cell ({candidate_cell}) must be positive"
        )
    rng = np.random.default_rng(seed)
    cand = lowest_per_cell(xyz, candidate_cell)
    lo = column_min(xyz[:, :2])
    hi = column_max(xyz[:, :2])
    shape = np.maximum(np.ceil((hi - lo) / cell_size).astype(int), 1)
    origin = lo + 0.5 * cell_size
    heights = np.full(tuple(shape), np.nan)
    cell_of = np.floor((cand[:, :2] - lo) / cell_size).astype(int)
    cell_of = np.minimum(cell_of, shape - 1)
    # Candidates of each cell plus a half-cell margin, via a sort on the cell index.
    lin = cell_of[:, 0] * shape[1] + cell_of[:, 1]
    order = np.argsort(lin, kind="stable")
    bounds = np.searchsorted(lin[order], np.arange(shape[0] * shape[1] + 1))
    for i in range(shape[0]):
        for j in range(shape[1]):
            block = [
                order[bounds[a * shape[1] + b] : bounds[a * shape[1] + b + 1]]
                for a in range(max(i - 1, 0), min(i + 2, shape[0]))
                for b in range(max(j - 1, 0), min(j + 2, shape[1]))
            ]
            members = np.concatenate(block) if block else np.zeros(0, int)
            centre = origin + np.array([i, j]) * cell_size
            near = np.all(np.abs(cand[members, :2] - centre) <= 0.75 * cell_size, axis=1)
            pts = cand[members[near]]
            if len(pts) < min_candidates:
                continue
            fit = ransac_plane(pts - np.array([centre[0], centre[1], 0.0]), threshold, rng)
            if fit is None or fit[1].sum() < min_candidates:
                continue
            heights[i, j] = fit[0][2]  # the plane's height at the cell centre
    fitted = np.isfinite(heights)
    fitted &= ~_raised_cells(heights, fitted, cell_size)
    if not fitted.any():
        raise ProcessingError(
            f"ground model: no {cell_size} m cell had {min_candidates} ground candidates on a "
            "plane; is there ground in the map?"
        )
    if not fitted.all():
        _, (ii, jj) = ndimage.distance_transform_edt(~fitted, return_indices=True)
        heights = heights[ii, jj]
    return GroundModel(origin, float(cell_size), heights, fitted)


def _raised_cells(
    heights: np.ndarray,
    fitted: np.ndarray,
    cell_size: float,
    max_step: float = 0.5,
    max_slope: float = 0.3,
) -> np.ndarray:
    """Cells whose plane sits far above all fitted neighbours: a crown bottom taken for ground."""
    h = np.where(fitted, heights, np.inf)
    padded = np.pad(h, 1, constant_values=np.inf)
    nx, ny = h.shape
    lowest = np.full(h.shape, np.inf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                lowest = np.minimum(lowest, padded[1 + di : 1 + di + nx, 1 + dj : 1 + dj + ny])
    allowed = max_step + max_slope * cell_size * np.sqrt(2)
    ok = fitted & np.isfinite(lowest)
    raised = np.zeros_like(fitted)
    raised[ok] = h[ok] - lowest[ok] > allowed
    return raised
