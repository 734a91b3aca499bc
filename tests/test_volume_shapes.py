"""Volume estimators against shapes of known volume, filled and surface-sampled.

Truth is analytic (cube, sphere, ellipsoid, two overlapping spheres with the lens volume
subtracted, an L of two boxes); Open3D is the reference for the exact alpha complex where
its mesh is watertight. Surface samples carry 0.1 mm noise: exactly coplanar or cospherical
points make qhull's Delaunay orders of magnitude slower and no scanner produces them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest

from canopy_kit.volume import estimate_volume

R_SPHERE = 1.5
ELLIPSOID = np.array([2.0, 1.5, 1.0])
UNION_OFFSET = 0.75  # unit spheres centred at (±0.75, 0, 0)


def lens_volume(r: float, d: float) -> float:
    """Volume of the intersection of two spheres of radius r whose centres are d apart."""
    return np.pi * (4 * r + d) * (2 * r - d) ** 2 / 12


@dataclass(frozen=True)
class Shape:
    """A solid with an analytic volume, a membership test and a surface sampler."""

    volume: float
    lower: tuple[float, float, float]
    upper: tuple[float, float, float]
    inside: Callable[[np.ndarray], np.ndarray]
    surface: Callable[[np.random.Generator, int], np.ndarray]
    convex: bool
    alpha_filled: float  # above the point spacing, below the concave features
    alpha_surface: float  # above the largest empty ball inside the surface

    def filled(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """About ``n`` points inside the solid: one uniform point per cell of a cubic grid
        (stratified sampling, so no large random gaps slow the convergence)."""
        cell = (self.volume / n) ** (1 / 3)
        axes = [np.arange(lo, hi, cell) for lo, hi in zip(self.lower, self.upper)]
        corners = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        p = corners + rng.uniform(0.0, cell, corners.shape)
        return p[self.inside(p) & (p <= self.upper).all(axis=1)]

    def surface_points(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` points on the surface with 0.1 mm Gaussian noise."""
        return self.surface(rng, n) + rng.normal(scale=1e-4, size=(n, 3))


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _box_surface(rng: np.random.Generator, n: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    size = hi - lo
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    axis = rng.choice(3, size=n, p=areas / areas.sum())
    p = rng.uniform(lo, hi, (n, 3))
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, lo[axis], hi[axis])
    return p


def _cube_surface(rng: np.random.Generator, n: int) -> np.ndarray:
    return _box_surface(rng, n, np.full(3, -1.0), np.full(3, 1.0))


def _union_surface(rng: np.random.Generator, n: int) -> np.ndarray:
    c = np.array([UNION_OFFSET, 0, 0])
    p = np.concatenate([_unit(rng, 2 * n) - c, _unit(rng, 2 * n) + c])
    keep = (np.linalg.norm(p - c, axis=1) >= 1) & (np.linalg.norm(p + c, axis=1) >= 1)
    p = p[keep]
    return p[rng.permutation(len(p))[:n]]


def _l_surface(rng: np.random.Generator, n: int) -> np.ndarray:
    lo = np.zeros(3)
    p = np.concatenate(
        [
            _box_surface(rng, 2 * n, lo, np.array([3.0, 1, 1])),
            _box_surface(rng, 2 * n, lo, np.array([1.0, 1, 3])),
        ]
    )
    # drop the parts of each box's faces that lie inside the other box
    hidden = ((p[:, 0] < 1) & (np.isclose(p[:, 2], 1))) | ((p[:, 2] < 1) & (np.isclose(p[:, 0], 1)))
    p = p[~hidden]
    return p[rng.permutation(len(p))[:n]]


SHAPES: dict[str, Shape] = {
    "cube": Shape(
        8.0, (-1, -1, -1), (1, 1, 1), lambda p: np.ones(len(p), bool), _cube_surface, True, 0.9, 1.5
    ),
    "sphere": Shape(
        4 / 3 * np.pi * R_SPHERE**3,
        (-R_SPHERE,) * 3,
        (R_SPHERE,) * 3,
        lambda p: np.linalg.norm(p, axis=1) <= R_SPHERE,
        lambda rng, n: R_SPHERE * _unit(rng, n),
        True,
        0.9,
        2.0,
    ),
    "ellipsoid": Shape(
        4 / 3 * np.pi * ELLIPSOID.prod(),
        tuple(-ELLIPSOID),
        tuple(ELLIPSOID),
        lambda p: np.linalg.norm(p / ELLIPSOID, axis=1) <= 1,
        lambda rng, n: ELLIPSOID * _unit(rng, n),
        True,
        0.9,
        3.0,
    ),
    "two_spheres": Shape(
        2 * 4 / 3 * np.pi - lens_volume(1.0, 2 * UNION_OFFSET),
        (-1.75, -1, -1),
        (1.75, 1, 1),
        lambda p: (
            (np.linalg.norm(p - [UNION_OFFSET, 0, 0], axis=1) <= 1)
            | (np.linalg.norm(p + [UNION_OFFSET, 0, 0], axis=1) <= 1)
        ),
        _union_surface,
        False,
        0.7,
        1.05,
    ),
    "l_shape": Shape(
        5.0,
        (0, 0, 0),
        (3, 1, 3),
        lambda p: (p[:, 2] <= 1) | (p[:, 0] <= 1),
        _l_surface,
        False,
        0.7,
        0.6,
    ),
}
DENSITIES = (1000, 4000, 16000)


def relative_errors(shape: Shape, sampling: str, method: str, seed: int = 0) -> list[float]:
    """Relative volume error of ``method`` at each density (one seeded sample per density)."""
    rng = np.random.default_rng(seed)
    alpha = shape.alpha_filled if sampling == "filled" else shape.alpha_surface
    params = {} if method == "convex_hull" else {"alpha": alpha}
    errors = []
    for n in DENSITIES:
        pts = shape.filled(rng, n) if sampling == "filled" else shape.surface_points(rng, n)
        result = estimate_volume(pts, method, **params)
        assert result.valid, result.reason
        errors.append(result.volume_m3 / shape.volume - 1)
    return errors


def test_lens_formula_matches_monte_carlo() -> None:
    shape = SHAPES["two_spheres"]
    rng = np.random.default_rng(1)
    p = rng.uniform(shape.lower, shape.upper, (2_000_000, 3))
    box = np.prod(np.subtract(shape.upper, shape.lower))
    assert shape.inside(p).mean() * box == pytest.approx(shape.volume, rel=0.005)


@pytest.mark.parametrize("method", ["convex_hull", "alpha_shape"])
@pytest.mark.parametrize("name", ["cube", "sphere", "ellipsoid"])
def test_convex_filled_converges_to_the_volume(name: str, method: str) -> None:
    errors = relative_errors(SHAPES[name], "filled", method)
    # a random sample's hull misses a shell that thins as the density grows
    assert all(e < 0.002 for e in errors), errors
    assert abs(errors[-1]) < 0.6 * abs(errors[0]), errors
    assert abs(errors[-1]) < 0.045, errors


@pytest.mark.parametrize("method", ["convex_hull", "alpha_shape"])
@pytest.mark.parametrize("name", ["cube", "sphere", "ellipsoid"])
def test_convex_surface_converges_to_the_volume(name: str, method: str) -> None:
    errors = relative_errors(SHAPES[name], "surface", method)
    assert abs(errors[-1]) <= abs(errors[0]) + 0.005, errors
    assert abs(errors[-1]) < 0.005, errors


@pytest.mark.parametrize("sampling", ["filled", "surface"])
@pytest.mark.parametrize("name", ["two_spheres", "l_shape"])
def test_concave_alpha_converges_and_beats_the_hull(name: str, sampling: str) -> None:
    alpha = relative_errors(SHAPES[name], sampling, "alpha_shape")
    hull = relative_errors(SHAPES[name], sampling, "convex_hull")
    assert hull[-1] > 0.05, hull  # the hull bridges the concavity
    assert abs(alpha[-1]) < abs(hull[-1]), (alpha, hull)
    if sampling == "filled":
        # sampled solids converge at O(spacing): boundary points sit ~half a spacing inside
        assert abs(alpha[-1]) < 0.5 * abs(alpha[0]), alpha
        assert abs(alpha[-1]) < 0.02, alpha
    else:
        # α must exceed the inner radius to fill a surface sample, so it also rounds the
        # concave edges: an over-fill (+4 % on the L, +6 % on the spheres), half the hull's
        assert 0 < alpha[-1] < 0.6 * hull[-1], (alpha, hull)


def test_alpha_below_the_inner_radius_leaves_a_hollow_surface_sample_empty() -> None:
    # The measured trap: α = 0.9 m on a surface-only crown of radius 1.5 m finds almost nothing.
    shape = SHAPES["sphere"]
    pts = shape.surface_points(np.random.default_rng(2), 4000)
    result = estimate_volume(pts, "alpha_shape", alpha=0.9)
    assert result.valid and result.volume_m3 < 0.02 * shape.volume


def test_lattice_cube_is_exact() -> None:
    g = np.linspace(-1.0, 1.0, 9)
    cube = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    assert estimate_volume(cube, "convex_hull").volume_m3 == pytest.approx(8.0, rel=1e-12)
    assert estimate_volume(cube, "alpha_shape", alpha=0.3).volume_m3 == pytest.approx(8.0, rel=1e-9)
    # α below half the diagonal of a lattice cell: no tetrahedron qualifies, flagged
    tiny = estimate_volume(cube, "alpha_shape", alpha=0.1)
    assert not tiny.valid and tiny.volume_m3 == 0.0 and "below the point spacing" in tiny.reason


@pytest.mark.parametrize(("n", "alpha"), [(3000, 0.5), (3000, 0.9), (10000, 0.9)])
def test_exact_alpha_matches_open3d_where_its_mesh_is_watertight(n: int, alpha: float) -> None:
    import open3d as o3d

    pts = SHAPES["sphere"].filled(np.random.default_rng(3), n)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(pc, alpha)
    assert mesh.is_watertight()
    ours = estimate_volume(pts, "alpha_shape", alpha=alpha)
    assert ours.volume_m3 == pytest.approx(mesh.get_volume(), rel=1e-6)


@pytest.mark.parametrize("name", ["sphere", "ellipsoid", "two_spheres", "cube"])
def test_fast_alpha_hull_matches_the_exact_complex_on_solids(name: str) -> None:
    shape = SHAPES[name]
    pts = shape.filled(np.random.default_rng(4), 16000)
    for alpha in (0.5, 0.9):
        exact = estimate_volume(pts, "alpha_shape", alpha=alpha).volume_m3
        fast = estimate_volume(pts, "alpha_hull", alpha=alpha)
        assert fast.valid and fast.extra["grid_step"] <= alpha / 4
        # the α-hull sits slightly inside the complex: empty balls bite between boundary
        # points and round the concave crease of the two spheres
        assert -0.025 < fast.volume_m3 / exact - 1 < 0.005, (name, alpha, fast.volume_m3, exact)


def test_fast_alpha_hull_rounds_concave_edges_differently() -> None:
    # The α-hull fills a concave edge with a round fillet, the complex with straight
    # tetrahedra: on the L it is a few % smaller than the complex, still closer than the hull.
    shape = SHAPES["l_shape"]
    pts = shape.filled(np.random.default_rng(5), 16000)
    exact = estimate_volume(pts, "alpha_shape", alpha=0.9).volume_m3
    fast = estimate_volume(pts, "alpha_hull", alpha=0.9).volume_m3
    hull = estimate_volume(pts, "convex_hull").volume_m3
    assert 0.93 * exact < fast < exact
    assert abs(fast - shape.volume) < abs(hull - shape.volume)


def test_fast_alpha_hull_depends_little_on_the_grid_step() -> None:
    # Finer grids resolve the bites between boundary points (smaller), coarser ones add a
    # curvature bias of about h²/(4ρ²) (larger): a few % across a 3× range of steps.
    pts = SHAPES["ellipsoid"].filled(np.random.default_rng(6), 8000)
    volumes = [
        estimate_volume(pts, "alpha_hull", alpha=0.9, grid_step=h).volume_m3
        for h in (0.3, 0.225, 0.15, 0.1)
    ]
    assert np.ptp(volumes) < 0.035 * np.mean(volumes), volumes


def test_hull_mesh_is_the_hull_by_its_corners() -> None:
    from canopy_kit.volume.hull import hull_mesh, hull_volume

    rng = np.random.default_rng(3)
    cube = np.array([[x, y, z] for x in (0, 2) for y in (0, 3) for z in (0, 1)], float)
    xyz = np.vstack(
        [
            cube + [400000.0, 4000000.0, 0.0],
            rng.uniform(0.1, 0.9, (5000, 3)) * [2, 3, 1] + [400000.0, 4000000.0, 0.0],
        ]
    )
    corners, faces = hull_mesh(xyz)
    assert len(corners) == 8 and faces.min() == 0 and faces.max() == 7
    np.testing.assert_allclose(
        np.sort(corners - corners.min(axis=0), axis=0), np.sort(cube, axis=0)
    )
    # The triangles close the hull: the tetrahedra from its centre to them fill its volume.
    tri = (corners - corners.mean(axis=0))[faces]
    volume = np.abs(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))).sum() / 6
    assert volume == pytest.approx(hull_volume(xyz)) and volume == pytest.approx(6.0)
