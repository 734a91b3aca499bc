"""One-sided scans: the mirror estimator beats the alpha shape (and the hull) on a crown
seen from one alley only, and changes little on a complete scan."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.volume import estimate_volume
from canopy_kit.volume.partial import MirrorPlane, estimate_mirror_plane

SEMI_AXES = np.array([2.0, 1.8, 1.6])  # along the row (x), across (y), up (z)
CENTRE = np.array([0.0, 0.0, 2.6])
TRUE_VOLUME = 4 / 3 * np.pi * SEMI_AXES.prod()


def crown(seed: int = 0, n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """A porous ellipsoidal crown: points denser towards the shell, with 2 cm noise, and
    each point's outward surface normal."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    depth = rng.uniform(0.0, 1.0, n) ** 0.25  # most points near the shell
    pts = CENTRE + d * SEMI_AXES * depth[:, None] + rng.normal(scale=0.02, size=(n, 3))
    normal = d / SEMI_AXES
    return pts, normal / np.linalg.norm(normal, axis=1, keepdims=True)


def one_sided(
    pts: np.ndarray, normal: np.ndarray, alley_y: float = -4.0, sensor_z: float = 1.5
) -> np.ndarray:
    """Points whose surface faces a sensor driving along the line y = alley_y, z = sensor_z."""
    sensor = np.column_stack([pts[:, 0], np.full(len(pts), alley_y), np.full(len(pts), sensor_z)])
    return pts[((sensor - pts) * normal).sum(axis=1) > 0]


def error(pts: np.ndarray, method: str, **params: object) -> float:
    result = estimate_volume(pts, method, **params)
    assert result.valid, result.reason
    return result.volume_m3 / TRUE_VOLUME - 1


def test_mirror_beats_alpha_and_hull_on_a_one_sided_crown() -> None:
    pts, normal = crown()
    seen = one_sided(pts, normal)
    assert 0.3 < len(seen) / len(pts) < 0.55
    alpha = error(seen, "alpha_shape")
    hull = error(seen, "convex_hull")
    mirror = error(seen, "mirror")
    assert alpha < -0.4 and hull < -0.3  # half a crown or less
    assert abs(mirror) < 0.1, mirror
    assert abs(mirror) < abs(hull) < abs(alpha)
    # the fast alpha formulation completes the unseen side just as well
    assert abs(error(seen, "mirror", base="alpha_hull", alpha=1.5)) < 0.15


def test_mirror_about_a_given_trunk_plane() -> None:
    pts, normal = crown(seed=1)
    seen = one_sided(pts, normal)
    given = error(seen, "mirror", plane_point=(0.0, 0.0), plane_normal=(0.0, 1.0))
    # the sensor below the crown centre misses the far top, so its mirror is missing too
    assert -0.15 < given < 0.0
    assert abs(given) < abs(error(seen, "alpha_shape"))


def test_estimated_plane_lies_behind_the_seen_face() -> None:
    pts, normal = crown(seed=2)
    seen = one_sided(pts, normal, alley_y=-4.0)
    plane = estimate_mirror_plane(seen)
    assert abs(plane.normal @ [0.0, 1.0]) > 0.99  # across the row
    offset = float(plane.point @ plane.normal) * np.sign(plane.normal[1])
    # round-crown rule: half the along-row width (2 m) behind the near face (y ≈ -1.8)
    assert offset == pytest.approx(0.2, abs=0.25)
    # seen from the other alley the plane is found on the other side of the points
    other = one_sided(pts, normal, alley_y=4.0)
    assert error(other, "mirror") == pytest.approx(error(seen, "mirror"), abs=0.08)


def test_mirror_on_a_complete_scan_is_close_to_the_hull() -> None:
    pts, _ = crown(seed=3)
    hull = error(pts, "convex_hull")
    assert error(pts, "mirror", plane_point=(0.0, 0.0), plane_normal=(0.0, 1.0)) == pytest.approx(
        hull, abs=0.03
    )
    # the automatic rule assumes a round crown (across = along): this one is 10 % narrower
    assert 0 < error(pts, "mirror") - hull < 0.15


def test_mirror_plane_reflects() -> None:
    plane = MirrorPlane(np.array([1.0, 0.0]), np.array([1.0, 0.0]))
    np.testing.assert_allclose(plane.reflect(np.array([[3.0, 2.0, 5.0]])), [[-1.0, 2.0, 5.0]])
    result = estimate_volume(
        np.random.default_rng(0).uniform(0, 1, (3000, 3)),
        "mirror",
        plane_point=(0.0, 0.0),
        plane_normal=(1.0, 0.0),
    )
    assert result.extra["plane_normal"] == [1.0, 0.0] and result.extra["plane_point"] == [0.0, 0.0]
    # mirrored across x = 0, the unit cube of points becomes a 2 x 1 x 1 box
    assert result.volume_m3 == pytest.approx(2.0, rel=0.05)
