"""The surface of the solid an estimator measured, as a triangle mesh (for the report's 3-D
view): :class:`Surface`, and the boundary of a set of tetrahedra (the alpha complex's).

Estimators that can draw their solid return it from ``with_surface(xyz)`` together with the
volume, from the same triangulation: the convex hull (qhull's facets) and the alpha shape
(the triangles of its tetrahedra that belong to exactly one of them).
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


def compact_surface(name: str, xyz: np.ndarray, faces: np.ndarray, volume: float) -> Surface:
    """A surface of the triangles ``faces`` (indices into ``xyz``), keeping only the vertices
    they use, re-indexed."""
    used, inverse = np.unique(faces.ravel(), return_inverse=True)
    return Surface(name, xyz[used], inverse.reshape(-1, 3).astype(np.int64), float(volume))


def boundary_triangles(
    simplices: np.ndarray, n_points: int, xyz: np.ndarray | None = None
) -> np.ndarray:
    """The triangles (F, 3) that belong to exactly one of the tetrahedra ``simplices`` (M, 4)
    of points indexed below ``n_points``: the boundary of their union. Each triangle's
    vertex indices are in ascending order, or, given the points ``xyz``, wound so that its
    normal points out of the solid (away from its tetrahedron's fourth vertex; into a cavity
    for a cavity's wall), which mesh tools need.

    Each triangle is one int64 key (its sorted indices in base ``n_points``); the keys are
    sorted and those without an equal neighbour kept: 18x faster than ``np.unique`` on
    triangle rows for a 150k-tetrahedron crown.
    """
    s = np.sort(np.asarray(simplices, dtype=np.int64), axis=1)  # sorts every face too
    if not len(s):
        return np.empty((0, 3), np.int64)
    a, b, c, d = s.T
    opposite = np.concatenate([d, c, b, a])  # the vertex each face below leaves out
    if n_points >= 2_000_000:  # the key would overflow (n³ ≥ 2⁶³): compare rows instead
        faces = np.concatenate([s[:, [0, 1, 2]], s[:, [0, 1, 3]], s[:, [0, 2, 3]], s[:, [1, 2, 3]]])
        unique, first_seen, counts = np.unique(faces, axis=0, return_index=True, return_counts=True)
        out, owner = unique[counts == 1], first_seen[counts == 1]
    else:
        n = np.int64(n_points)
        key = np.concatenate([(a * n + b) * n + c, (a * n + b) * n + d, (a * n + c) * n + d])
        key = np.concatenate([key, (b * n + c) * n + d])
        order = np.argsort(key, kind="stable") if xyz is not None else None
        key = key[order] if order is not None else np.sort(key)
        single = np.ones(len(key), bool)
        repeated = key[1:] == key[:-1]
        single[1:] &= ~repeated
        single[:-1] &= ~repeated
        owner = order[single] if order is not None else None
        first_two, third = np.divmod(key[single], n)
        first, second = np.divmod(first_two, n)
        out = np.column_stack([first, second, third])
    if xyz is None:
        return out
    xyz = np.asarray(xyz, dtype=np.float64)
    return wound_away_from(out, xyz, xyz[opposite[owner]])


def wound_away_from(faces: np.ndarray, xyz: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """``faces`` (indices into ``xyz``) with each triangle's winding (right-hand normal)
    turned away from ``inside``: a point on the solid's side of it, one per triangle (F, 3)
    or one for all (3,), e.g. a convex solid's centroid."""
    p0, p1, p2 = (xyz[faces[:, k]] for k in range(3))
    normal = np.cross(p1 - p0, p2 - p0)
    flip = np.einsum("ij,ij->i", normal, np.broadcast_to(inside, p0.shape) - p0) > 0
    out = faces.copy()
    out[flip, 1], out[flip, 2] = faces[flip, 2], faces[flip, 1]
    return out
