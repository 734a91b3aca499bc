"""The minimum-volume enclosing ellipsoid against shapes whose answer is known by hand."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from canopy_kit.errors import ConfigError
from canopy_kit.volume.ellipsoid import EnclosingEllipsoidVolume, enclosing_ellipsoid
from canopy_kit.volume.hull import hull_volume


def ellipsoid_surface(axes, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points on the surface of an ellipsoid of semi-axes ``axes``, turned and moved."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rot = Rotation.random(random_state=seed).as_matrix()
    centre = rng.uniform(-50, 50, 3)
    return (u * np.asarray(axes)) @ rot.T + centre, rot, centre


@pytest.mark.parametrize("axes, n", [((2.0, 1.5, 1.0), 30), ((3.0, 3.0, 0.5), 500)])
def test_points_on_an_ellipsoid_give_that_ellipsoid(axes, n):
    pts, _, centre = ellipsoid_surface(axes, n, seed=n)
    ell = enclosing_ellipsoid(pts, tol=1e-9)
    assert ell.converged
    assert ell.volume == pytest.approx(4 / 3 * np.pi * np.prod(axes), rel=1e-5)
    assert ell.semi_axes == pytest.approx(sorted(axes, reverse=True), rel=1e-4)
    assert ell.center == pytest.approx(centre, abs=1e-4)


def test_the_cube_is_enclosed_by_its_circumscribed_sphere():
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    cloud = np.concatenate([corners, np.random.default_rng(1).uniform(-1, 1, (200, 3))])
    ell = enclosing_ellipsoid(cloud, tol=1e-9)
    assert ell.volume == pytest.approx(4 / 3 * np.pi * 3**1.5, rel=1e-6)  # radius √3
    assert ell.semi_axes == pytest.approx([3**0.5] * 3, rel=1e-6)


def test_encloses_every_point_and_follows_affine_maps():
    rng = np.random.default_rng(7)
    cloud = rng.normal(size=(400, 3)) * [2.0, 1.0, 0.5]
    ell = enclosing_ellipsoid(cloud, tol=1e-8)
    assert ell.contains(cloud).all()
    assert ell.volume >= hull_volume(cloud)
    # The minimum-volume ellipsoid of A x + b is A applied to x's: volume times |det A|.
    a = np.array([[1.5, 0.3, 0.0], [0.0, 0.7, 0.2], [0.1, 0.0, 2.0]])
    moved = enclosing_ellipsoid(cloud @ a.T + [10.0, -4.0, 3.0], tol=1e-8)
    assert moved.volume == pytest.approx(ell.volume * abs(np.linalg.det(a)), rel=1e-4)


def test_the_estimator_measures_and_reports():
    pts, _, _ = ellipsoid_surface((2.0, 1.5, 1.0), 200, seed=3)
    res = EnclosingEllipsoidVolume()(pts)
    assert res.valid and res.method == "enclosing_ellipsoid"
    assert res.volume_m3 == pytest.approx(4 / 3 * np.pi * 3.0, rel=3e-4)
    assert res.extra["semi_axes_m"] == pytest.approx([2.0, 1.5, 1.0], rel=1e-3)


def test_an_unfinished_iteration_is_not_passed_off_as_a_result():
    cloud = np.random.default_rng(2).normal(size=(300, 3))
    res = EnclosingEllipsoidVolume(max_iterations=2)(cloud)
    assert not res.valid and "did not converge in 2 iterations" in res.reason
    # what it gives is still an enclosing ellipsoid: no smaller than the optimum
    assert res.volume_m3 >= EnclosingEllipsoidVolume()(cloud).volume_m3


@pytest.mark.parametrize(
    "params, name", [({"tol": 0.0}, "tol"), ({"max_iterations": 0}, "max_iterations")]
)
def test_bad_parameters_are_named(params, name):
    with pytest.raises(ConfigError, match=f"enclosing_ellipsoid: {name}"):
        EnclosingEllipsoidVolume(**params)(np.random.default_rng(0).normal(size=(20, 3)))
