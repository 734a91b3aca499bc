"""``canopy_kit.volume.convexity``: is a thin sample of a crown a sample of a convex body?
Checked on bodies whose convexity is known by construction: a ball, a flat cross of four
arms (its convex hull is twice its volume) and a skeleton of branches."""

from __future__ import annotations

import numpy as np
import pytest
from test_volume_sample_hull import uniform_in_ball

from canopy_kit.volume import estimate_volume
from canopy_kit.volume.convexity import HOLLOW_Z, is_hollowed_body, sample_convexity
from canopy_kit.volume.hull import hull_volume, sample_corrected_hull, thin_to_distance

ARM, WIDTH = 3.0, 0.8  # the cross: arms reaching 3 m from the centre, 0.8 m square section
CROSS_M3 = (2 * (2 * ARM * WIDTH) - WIDTH**2) * WIDTH


def in_cross(p: np.ndarray) -> np.ndarray:
    a = np.abs(p)
    flat = a[:, 2] <= WIDTH / 2
    along_x = (a[:, 0] <= ARM) & (a[:, 1] <= WIDTH / 2)
    along_y = (a[:, 1] <= ARM) & (a[:, 0] <= WIDTH / 2)
    return flat & (along_x | along_y)


def cross_scan_lines(step: float = 0.02, gap: float = 0.2) -> np.ndarray:
    """Returns along straight lines over the cross's surface, ``gap`` apart, ``step`` apart
    along each line (as a spinning LiDAR's rings cross a small crown): they fill the hull's
    surface thinly (fill < 1.2) though they outline the body."""
    along = np.arange(-ARM, ARM + 1e-9, step)
    cap = np.arange(-WIDTH / 2, WIDTH / 2 + 1e-9, step)
    lines = []
    for z in np.arange(-WIDTH / 2, WIDTH / 2 + 1e-9, gap):
        face = abs(z) > WIDTH / 2 - 1e-9  # top and bottom: lines across the face
        for c in np.arange(-WIDTH / 2, WIDTH / 2 + 1e-9, gap if face else WIDTH):
            ones = np.ones_like(along)
            lines += [np.c_[along, c * ones, z * ones], np.c_[c * ones, along, z * ones]]
        for end in (-ARM, ARM):  # the arms' end faces
            ones = np.ones_like(cap)
            lines += [np.c_[end * ones, cap, z * ones], np.c_[cap, end * ones, z * ones]]
    pts = np.vstack(lines)
    return pts[in_cross(pts * (1 - 1e-9))]


@pytest.mark.parametrize("n", [30, 100, 300])
def test_a_uniform_sample_of_a_ball_is_not_called_hollowed(n: int) -> None:
    """A convex body's sample lies within the spread of the uniform samples of its own hull:
    |z| well under the threshold, at every sample size."""
    test = sample_convexity(uniform_in_ball(n, np.random.default_rng(n), radius=1.5))
    assert test.n_points == n
    assert abs(test.z) < 3.0 < -HOLLOW_Z, test


def test_a_sample_of_the_cross_is_far_from_convex_and_deterministic() -> None:
    rng = np.random.default_rng(1)
    box = rng.uniform([-ARM, -ARM, -WIDTH / 2], [ARM, ARM, WIDTH / 2], (40_000, 3))
    pts = box[in_cross(box)][:250]
    pts = pts[thin_to_distance(pts, 0.2)]
    test = sample_convexity(pts)
    assert test.z <= HOLLOW_Z and test.share < test.null_share
    assert sample_convexity(pts) == test  # same seed, same answer


def test_a_thinly_scanned_cross_keeps_its_alpha_hull_and_the_mixed_interval() -> None:
    """The scan lines fill the hull's surface as thinly as a sparse crown's; Efron's corrected
    hull would measure the cross's convex hull (about 2.5 × the body), the α-hull follows
    the arms."""
    from canopy_kit.volume.uncertainty import SPARSE_FILL, volume_interval

    xyz = cross_scan_lines()
    result = estimate_volume(xyz, "adaptive_alpha")
    extra = result.extra
    assert extra["surface_fill"] < SPARSE_FILL
    assert extra["estimate"] == "alpha_hull" and extra["crown_kind"] == "mixed"
    assert abs(result.volume_m3 / CROSS_M3 - 1) < 0.25  # measured +16.5 %
    assert sample_corrected_hull(xyz, 0.2).volume_m3 > 2 * CROSS_M3  # measured 2.47 ×
    interval = volume_interval(
        xyz, result.volume_m3, "adaptive_alpha", fill=extra["surface_fill"], kind="mixed"
    )
    assert any(flag.startswith("deeply lobed crown") for flag in interval.flags)


def test_a_skeleton_of_branches_is_not_a_hollowed_body() -> None:
    """Bare branches are far from convex too, but the α-hull of their points is thin tubes:
    the corrected hull stays (as on the real leafless broadleaf archi_tree_1)."""
    rng = np.random.default_rng(2)
    branches = []
    for _ in range(12):
        direction = rng.normal(size=3)
        direction[2] = abs(direction[2])
        direction /= np.linalg.norm(direction)
        t = np.linspace(0, 3, 300)[:, None]
        branches.append(t * direction + rng.normal(0, 0.02, (300, 3)))
    xyz = np.vstack(branches)
    test = sample_convexity(xyz[thin_to_distance(xyz, 0.2)])
    alpha_hull = estimate_volume(xyz, "adaptive_alpha", sparse_fill=None).volume_m3
    assert test.z <= HOLLOW_Z  # not convex ...
    assert alpha_hull < 0.1 * hull_volume(xyz)  # ... but no body: measured 2 %
    assert not is_hollowed_body(test, alpha_hull, hull_volume(xyz))
    assert estimate_volume(xyz, "adaptive_alpha").extra["estimate"] == "sample_corrected_hull"


def test_points_drawn_in_the_hull_are_scipys_points_inside_it_and_uniform() -> None:
    """Every point drawn lies in the hull by scipy's own point location (a Delaunay
    triangulation of the hull's corners), and none of the bounding box's points that scipy
    places inside is rejected: the same batch, the same points. Drawn in a cube's hull, their
    mean and spread are a uniform cube's (centre 0.5, variance 1/12 per axis)."""
    from scipy.spatial import ConvexHull, Delaunay

    from canopy_kit.volume.convexity import uniform_in_hull

    rng = np.random.default_rng(11)
    points = rng.normal(size=(300, 3)) * [2.0, 1.0, 0.5]
    drawn = uniform_in_hull(points, 2000, np.random.default_rng(3))
    located = Delaunay(points[ConvexHull(points).vertices])
    assert drawn.shape == (2000, 3) and (located.find_simplex(drawn) >= 0).all()
    # the same generator's first batch, located by scipy: the draw keeps exactly those points
    batch = np.random.default_rng(3).uniform(points.min(axis=0), points.max(axis=0), (8000, 3))
    kept = batch[located.find_simplex(batch) >= 0]
    assert len(kept) >= 2000 and np.array_equal(drawn, kept[:2000])

    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    cube = uniform_in_hull(corners, 20_000, np.random.default_rng(4))
    assert np.allclose(cube.mean(axis=0), 0.5, atol=0.01)
    assert np.allclose(cube.var(axis=0), 1 / 12, rtol=0.03)
