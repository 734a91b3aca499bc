"""The surfaces the volume estimators measure, as triangle meshes for the report's 3-D view.

The convex hull is qhull's (as :class:`~canopy_kit.volume.hull.ConvexHullVolume`); the alpha
shape is the boundary of the tetrahedra :class:`~canopy_kit.volume.alpha.AlphaShapeVolume`
sums (those with circumradius below α): the triangles that belong to exactly one of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Surface:
    """A triangle mesh: vertices (V, 3) and triangles (F, 3) of vertex indices, with the
    volume the estimator reports for the solid it bounds."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    volume_m3: float


def _compact(name: str, xyz: np.ndarray, faces: np.ndarray, volume: float) -> Surface:
    """Keep only the vertices the faces use, re-indexed."""
    used, inverse = np.unique(faces.ravel(), return_inverse=True)
    return Surface(name, xyz[used], inverse.reshape(-1, 3).astype(np.int64), float(volume))


def hull_surface(xyz: np.ndarray) -> Surface | None:
    """The convex hull of (N, 3) points; None when qhull cannot build one (flat or too few)."""
    from scipy.spatial import QhullError

    from canopy_kit.volume.hull import hull_mesh, hull_volume

    try:
        corners, faces = hull_mesh(xyz)
        volume = hull_volume(xyz)
    except (QhullError, ValueError):
        return None
    return Surface("convex hull", corners, faces, volume)


def alpha_surface(xyz: np.ndarray, alpha: float) -> Surface | None:
    """The boundary of the alpha complex of (N, 3) points; None when it is empty."""
    from scipy.spatial import QhullError

    from canopy_kit.volume.alpha import alpha_tetrahedra

    try:
        tetra = alpha_tetrahedra(xyz, alpha)
    except (QhullError, ValueError):
        return None
    kept = tetra.simplices[tetra.circumradius < alpha]
    if not len(kept):
        return None
    faces = np.concatenate(
        [kept[:, [0, 1, 2]], kept[:, [0, 1, 3]], kept[:, [0, 2, 3]], kept[:, [1, 2, 3]]]
    )
    boundary = faces[_once(np.sort(faces, axis=1).astype(np.int64), len(xyz))]
    volume = float(tetra.volume[tetra.circumradius < alpha].sum())
    return _compact("alpha shape", xyz, boundary, volume)


def _once(sorted_faces: np.ndarray, n: int) -> np.ndarray:
    """Indices of the triangles (vertex indices sorted per row, all below ``n``) that occur
    exactly once: each as one int64 key, which sorts ten times faster than rows do."""
    if n < 2_000_000:  # n³ < 2⁶³
        key = (sorted_faces[:, 0] * n + sorted_faces[:, 1]) * n + sorted_faces[:, 2]
        _, first, counts = np.unique(key, return_index=True, return_counts=True)
    else:
        _, first, counts = np.unique(sorted_faces, axis=0, return_index=True, return_counts=True)
    return first[counts == 1]
