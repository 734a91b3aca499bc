"""Stacked horizontal slices: the area of each slice's points times the slice thickness.

A common orchard-literature estimator (layer or "slice" method). Each slice's area is the
2-D convex hull of its points (``area="hull"``) or their 2-D alpha shape (``area="alpha"``:
Delaunay triangles whose circumradius is below ``alpha``). Slices with fewer than three
points, or collinear ones, add nothing.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np

from canopy_kit.plugins.params import Positive
from canopy_kit.volume.alpha import PAPER_ALPHA_M
from canopy_kit.volume.base import VolumeEstimator

AreaMethod = Literal["hull", "alpha"]
AREA_METHODS = get_args(AreaMethod)


def hull_area(xy: np.ndarray) -> float:
    """Area of the 2-D convex hull of (N, 2) points; 0 when fewer than 3 or collinear."""
    from scipy.spatial import ConvexHull, QhullError

    if len(xy) < 3:
        return 0.0
    try:
        return float(ConvexHull(xy - xy.mean(axis=0)).volume)
    except QhullError:
        return 0.0


def alpha_area(xy: np.ndarray, alpha: float) -> float:
    """Area of the 2-D alpha shape: Delaunay triangles with circumradius below ``alpha``."""
    from scipy.spatial import Delaunay, QhullError

    if len(xy) < 3:
        return 0.0
    c = xy - xy.mean(axis=0)
    try:
        tri = Delaunay(c).simplices
    except QhullError:
        return 0.0
    a, b, d = c[tri[:, 0]], c[tri[:, 1]], c[tri[:, 2]]
    la = np.linalg.norm(b - d, axis=1)
    lb = np.linalg.norm(a - d, axis=1)
    lc = np.linalg.norm(a - b, axis=1)
    u, v = b - a, d - a
    area = 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = la * lb * lc / (4.0 * area)
    return float(area[np.isfinite(radius) & (radius < alpha)].sum())


def slice_areas(
    xyz: np.ndarray, thickness: float, area: str = "hull", alpha: float = PAPER_ALPHA_M
) -> tuple[np.ndarray, np.ndarray]:
    """Bottom height and area of each horizontal slice of ``thickness`` metres, from min z."""
    z0 = xyz[:, 2].min()
    k = np.floor((xyz[:, 2] - z0) / thickness).astype(np.intp)
    order = np.argsort(k, kind="stable")
    k_sorted = k[order]
    n = int(k_sorted[-1]) + 1
    starts = np.searchsorted(k_sorted, np.arange(n + 1))
    areas = np.zeros(n)
    for i in range(n):
        xy = xyz[order[starts[i] : starts[i + 1]], :2]
        areas[i] = hull_area(xy) if area == "hull" else alpha_area(xy, alpha)
    return z0 + thickness * np.arange(n), areas


class SliceVolume(VolumeEstimator):
    """Σ (slice area × thickness) over horizontal slices; area by 2-D hull or 2-D alpha shape.

    Parameters
    ----------
    thickness : float, default 0.2
        Slice thickness in metres.
    area : str, default "hull"
        Area of a slice: ``hull`` (2-D convex hull) or ``alpha`` (2-D alpha shape).
    alpha : float, default 0.9
        α (m) of the 2-D alpha shape when ``area = "alpha"``.
    """

    name = "slices"
    measures = (
        "the sum over horizontal slices of the slice's 2-D hull (or alpha shape) area times "
        "the thickness"
    )

    def __init__(
        self, thickness: Positive = 0.2, area: AreaMethod = "hull", alpha: Positive = PAPER_ALPHA_M
    ) -> None:
        self.thickness = thickness
        self.area = area
        self.alpha = alpha

    def _volume(self, xyz: np.ndarray) -> float | tuple[float, dict]:
        t = float(self.thickness)
        n = np.ptp(xyz[:, 2]) / t
        if n > 100_000:
            return 0.0, {"reason": f"thickness = {t} m makes {n:.3g} slices; use a thicker slice"}
        _, areas = slice_areas(xyz, t, self.area, float(self.alpha))
        return float(areas.sum() * t), {"n_slices": len(areas)}
