"""Convex-hull volumes (qhull through scipy): the paper's upper-bound estimate (§II.E), and
the hull corrected for how thinly the points sample the crown (Efron's identity).

A convex hull of points drawn from inside a solid falls short of the solid by the caps
between its vertices, and the shortfall grows as the sample thins: on sparse young trees the
hull of the LiDAR returns is about half the crown envelope. For n points drawn uniformly
from a convex body K, Efron (1965) showed E[V(hull of n)] = V(K) · (1 − E[f(n + 1)] / (n + 1)),
f the number of hull vertices, so ``V(hull) · (n + 1) / (n + 1 − f)`` estimates V(K) from
the sample itself (the same correction as Ripley and Rasson's 1977 estimate of a support).
LiDAR returns are clustered on leaves, not independent, so the points are first thinned so
that no two kept points are nearer than ``cell`` (:func:`thin_to_distance`): a cluster of
returns on one leaf or shoot counts once, wherever the voxel grid would have cut it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.plugins.params import AtLeastOne, Positive
from canopy_kit.volume.base import VolumeEstimator
from canopy_kit.volume.surface import Surface, compact_surface, wound_away_from


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


def qhull_reason(exc: Exception) -> str:
    """The first line of a QhullError's message (its name when it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else "QhullError"


MAX_SAMPLE_FACTOR = 3.0  # the correction is capped: past it the sample says too little


@dataclass(frozen=True)
class SampleCorrectedHull:
    """The thinned points' hull volume, its correction factor and the counts behind it."""

    volume_m3: float  # hull volume × factor
    hull_m3: float
    factor: float  # (n + 1) / (n + 1 − vertices), at most MAX_SAMPLE_FACTOR
    n_points: int  # points after thinning to at least a cell apart
    n_vertices: int


def thin_to_distance(xyz: np.ndarray, distance: float) -> np.ndarray:
    """Indices of points no two of which are nearer than ``distance``: a greedy pass in
    voxel order over one point per ``distance`` voxel (each kept point removes its
    neighbours), so that the result does not depend on the order of the input."""
    from scipy.spatial import cKDTree

    from canopy_kit.core.voxel import voxel_representatives

    reps = voxel_representatives(xyz, distance)[0]  # in the order of the voxels' keys
    pts = xyz[reps]
    neighbours = cKDTree(pts).query_ball_point(pts, distance * (1 - 1e-9))
    removed = np.zeros(len(pts), bool)
    keep = []
    for i, near in enumerate(neighbours):
        if not removed[i]:
            keep.append(i)
            removed[near] = True
    return reps[np.asarray(keep, np.int64)]


def sample_corrected_hull(
    xyz: np.ndarray, cell: float, max_factor: float = MAX_SAMPLE_FACTOR
) -> SampleCorrectedHull:
    """Efron's sampling correction of the convex hull of ``xyz`` thinned to points at least
    ``cell`` apart (module docstring); raises scipy's QhullError when degenerate."""
    return efron_corrected_hull(xyz[thin_to_distance(xyz, cell)], max_factor)


def efron_corrected_hull(
    pts: np.ndarray, max_factor: float = MAX_SAMPLE_FACTOR
) -> SampleCorrectedHull:
    """Efron's correction of the convex hull of points already thinned (module docstring);
    raises scipy's QhullError when degenerate."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(pts - pts.mean(axis=0))
    n, f = len(pts), len(hull.vertices)
    factor = min((n + 1) / (n + 1 - f), max_factor)
    return SampleCorrectedHull(float(hull.volume * factor), float(hull.volume), factor, n, f)


class ConvexHullVolume(VolumeEstimator):
    """Volume of the smallest convex polyhedron around the points (an upper bound).

    Takes no parameters: the hull is defined by the points alone.
    """

    name = "convex_hull"
    measures = (
        "the convex hull of the points: every hollow and concavity filled; an upper bound of "
        "any envelope of the same points"
    )
    convex_rtol = 1e-6

    def __init__(self) -> None:
        pass

    def _volume(self, xyz: np.ndarray) -> float | tuple[float, dict]:
        from scipy.spatial import QhullError

        try:
            return hull_volume(xyz)
        except QhullError as exc:
            return 0.0, {"reason": _hull_failure(exc)}

    def _volume_and_surface(
        self, xyz: np.ndarray
    ) -> tuple[float | tuple[float, dict], Surface | None]:
        from scipy.spatial import ConvexHull, QhullError

        try:
            hull = ConvexHull(xyz - xyz.mean(axis=0))  # centred: as hull_volume
        except QhullError as exc:
            return (0.0, {"reason": _hull_failure(exc)}), None
        volume = float(hull.volume)
        faces = wound_away_from(hull.simplices, xyz, xyz.mean(axis=0))  # outwards: convex
        return volume, compact_surface("convex hull", xyz, faces, volume)


def _hull_failure(exc: Exception) -> str:
    return f"qhull could not build a hull: {qhull_reason(exc)}"


class SampleCorrectedHullVolume(VolumeEstimator):
    """Convex hull scaled by Efron's sampling correction ``(n + 1) / (n + 1 − f)`` of the
    points thinned to at least ``cell`` apart (n points, f of them hull vertices).

    The factor is 1.2-1.35 on simulated crowns whose foliage fills the envelope (their points
    lie in a shell, so it overshoots there: adaptive_alpha uses it only for sparse crowns)
    and 1.7 up to ``max_factor`` on sparse young trees. Assumes a convex crown: on lobed or
    vase crowns it overshoots as the hull does. Made for random samples (Efron's identity is
    about them): on a regular lattice finer than ``cell`` the thinning drops the corners (a
    9³ lattice of the unit cube gives 0.75 m³), so it promises no ``convex_rtol``.

    Parameters
    ----------
    cell : float, default 0.2
        Smallest distance (m) between the points kept for the hull, so that a cluster of
        returns on one leaf or shoot counts once.
    max_factor : float, default 3.0
        Largest correction applied.
    """

    name = "sample_corrected_hull"
    measures = (
        "the convex hull times Efron's sampling correction: the hull of the body a thin "
        "sample was drawn from"
    )

    def __init__(self, cell: Positive = 0.2, max_factor: AtLeastOne = MAX_SAMPLE_FACTOR) -> None:
        self.cell = cell
        self.max_factor = max_factor

    def _volume(self, xyz: np.ndarray) -> tuple[float, dict]:
        from scipy.spatial import QhullError

        try:
            est = sample_corrected_hull(xyz, self.cell, self.max_factor)
        except QhullError as exc:
            reason = f"qhull could not build a hull of the thinned points: {qhull_reason(exc)}"
            return 0.0, {"reason": reason}
        return est.volume_m3, {
            "hull_m3": est.hull_m3,
            "sample_factor": est.factor,
            "thinned_points": est.n_points,
            "hull_vertices": est.n_vertices,
        }
