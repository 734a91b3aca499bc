"""Convex-hull volume (qhull through scipy): the paper's upper-bound estimate (§II.E)."""

from __future__ import annotations

import numpy as np

from canopy_kit.volume.base import VolumeEstimator


def hull_volume(xyz: np.ndarray) -> float:
    """Volume of the convex hull of (N, 3) points; raises scipy's QhullError when degenerate."""
    from scipy.spatial import ConvexHull

    # Centring first keeps qhull's precision independent of where the tree stands.
    return float(ConvexHull(xyz - xyz.mean(axis=0)).volume)


def hull_mesh(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The convex hull as a small triangle mesh: its corner points (V, 3) and triangles
    (F, 3) indexing them, e.g. for a 3-D view that should not carry every input point."""
    from scipy.spatial import ConvexHull

    centre = xyz.mean(axis=0)
    hull = ConvexHull(xyz - centre)
    corners = hull.vertices
    index = np.full(len(xyz), -1, dtype=np.int64)
    index[corners] = np.arange(len(corners))
    return xyz[corners], index[hull.simplices]


class ConvexHullVolume(VolumeEstimator):
    """Volume of the smallest convex polyhedron around the points (an upper bound).

    Takes no parameters: the hull is defined by the points alone.
    """

    name = "convex_hull"
    convex_rtol = 1e-6

    def __init__(self) -> None:
        pass

    def _volume(self, xyz: np.ndarray) -> float | tuple[float, dict]:
        from scipy.spatial import QhullError

        try:
            return hull_volume(xyz)
        except QhullError as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else "QhullError"
            return 0.0, {"reason": f"qhull could not build a hull: {first}"}
