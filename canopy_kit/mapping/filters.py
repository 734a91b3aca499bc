"""Per-scan point filters: range limits and the ground pre-filter for odometry.

Measured trap: KISS-ICP on scans whose ground is a flat plane barely moves, because the
ground points (which travel with the sensor) dominate the point-to-point matching. The
odometry therefore gets the scan with ground removed; the map keeps every point.
"""

from __future__ import annotations

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.errors import InputError


def range_mask(xyz: np.ndarray, min_range: float, max_range: float) -> np.ndarray:
    """Finite points whose distance to the sensor lies in ``[min_range, max_range]``."""
    from canopy_kit.mapping.kernels import in_range

    return in_range(np.ascontiguousarray(xyz, np.float64), min_range**2, max_range**2)


def map_range(config: MappingConfig) -> float:
    """The farthest return the map keeps: ``mapping.map_max_range`` within ``max_range``."""
    return float(min(config.max_range, config.map_max_range))


def map_range_subset(xyz: np.ndarray, keep: np.ndarray, max_range: float) -> np.ndarray:
    """Positions, among the points ``keep`` (a mask) selects of a scan's ``xyz``, of those
    within ``max_range`` of the sensor."""
    return np.flatnonzero(range_mask(xyz[keep], 0.0, max_range))


def first_per_voxel(xyz: np.ndarray, size: float) -> np.ndarray:
    """Indices of the first point in each occupied cubic voxel of edge ``size`` (in order)."""
    from canopy_kit.mapping.kernels import EMPTY, insert_keys, voxel_keys

    if len(xyz) == 0:
        return np.zeros(0, np.int64)
    keys, _ = voxel_keys(np.ascontiguousarray(xyz, np.float64), float(size), 20)
    bits = max(4, int(np.ceil(np.log2(2 * len(keys)))))
    table = np.full(1 << bits, EMPTY, np.int64)
    return np.flatnonzero(insert_keys(keys, table, bits))


def check_point_count(n_points: int, minimum: int, where: str) -> None:
    """Raise an :class:`InputError` naming the scan when it has fewer than ``minimum`` points."""
    if n_points < minimum:
        raise InputError(
            f"{where}: only {n_points} valid points in the scan, at least {minimum} are needed "
            f"for LiDAR odometry (mapping.min_points_per_scan); is the range filter or topic right?"
        )


def fit_ground_plane(
    xyz: np.ndarray,
    cell_size: float = 2.0,
    fit_radius: float = 25.0,
    up: np.ndarray | None = None,
    iterations: int = 3,
    inlier_band: float = 0.25,
    max_points: int = 4000,
) -> np.ndarray | None:
    """Plane ``(n, d)`` with ``n·p + d = 0`` (``n`` pointing up) through the scan's ground.

    The lowest point of each ``cell_size`` cell (along ``up``, default the sensor z axis)
    within ``fit_radius`` is a ground candidate; a least-squares plane is refit to the
    candidates within ``inlier_band`` of the previous fit. Returns None when the scan has
    too few candidates (e.g. no ground in view). At most ``max_points`` evenly strided
    points are used (the cell minima barely change).
    """
    if len(xyz) > max_points:
        xyz = xyz[:: int(np.ceil(len(xyz) / max_points))]
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float) / np.linalg.norm(up)
    # A right-handed basis (e1, e2, up) so heights are measured along ``up``.
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    basis = np.column_stack([e1, e2, up])
    local = xyz @ basis
    near = np.einsum("ij,ij->i", local[:, :2], local[:, :2]) <= fit_radius**2
    local = local[near & (local[:, 2] < 0.0)]  # ground lies below the sensor
    if len(local) < 30:
        return None
    cells = np.floor(local[:, :2] / cell_size).astype(np.int64)
    key = (cells[:, 0] + 100_000) * 200_003 + (cells[:, 1] + 100_000)
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
    # Lowest height per cell, placed at the cell centre (slopes are small over one cell).
    z_min = np.minimum.reduceat(local[order, 2], starts)
    centre = (cells[order[starts]] + 0.5) * cell_size
    cand = np.column_stack([centre, z_min])
    if len(cand) < 6:
        return None
    # Robust start: the lower half of the candidates (cells filled by crowns or trunks sit higher).
    z0 = np.median(cand[:, 2])
    use = cand[:, 2] <= z0 + inlier_band
    coef = None
    for _ in range(iterations):
        if use.sum() < 6:
            break
        a = np.column_stack([cand[use, 0], cand[use, 1], np.ones(use.sum())])
        coef, *_ = np.linalg.lstsq(a, cand[use, 2], rcond=None)
        resid = cand[:, 2] - (coef[0] * cand[:, 0] + coef[1] * cand[:, 1] + coef[2])
        use = np.abs(resid) <= inlier_band
    if coef is None:
        return None
    # z = a x + b y + c in the (e1, e2, up) basis  ->  n·p + d = 0 in the sensor frame.
    n_local = np.array([-coef[0], -coef[1], 1.0])
    scale = np.linalg.norm(n_local)
    return np.concatenate([basis @ (n_local / scale), [-coef[2] / scale]])


def ground_mask(
    xyz: np.ndarray, band: float, plane: np.ndarray | None = None, up: np.ndarray | None = None
) -> np.ndarray:
    """Points within ``band`` metres above (or anywhere below) the scan's ground plane.

    ``plane`` is fitted with :func:`fit_ground_plane` when not given; with no plane found
    no point is called ground.
    """
    if plane is None:
        plane = fit_ground_plane(xyz, up=up)
    if plane is None:
        return np.zeros(len(xyz), bool)
    height = xyz @ plane[:3] + plane[3]
    return height <= band
