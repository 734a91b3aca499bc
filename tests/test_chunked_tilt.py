"""Chunked odometry and tilted LiDARs: the ground re-correction after stitching
(``ground.regrounded_poses``, off by default: ``chunks.REGROUND_CHUNKS``) and the rule that
keeps a tilted LiDAR's odometry in one process (``chunks.MAX_CHUNKED_TILT_DEG``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from canopy_kit.mapping.ground import refinement_points, regrounded_poses

SENSOR_HEIGHT = 2.0


def _pose(x: float, z: float, pitch_deg: float = 12.0) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("y", pitch_deg, degrees=True).as_matrix()
    out[:3, 3] = [x, 0.0, z]
    return out


def _ground_seen(true_pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Flat ground (z = 0, 5 mm noise) behind the sensor only (one-sided, as a pitched LiDAR
    sees it), in the sensor frame of ``true_pose``."""
    n = 1500
    world = np.column_stack(
        [
            true_pose[0, 3] - rng.uniform(3.0, 15.0, n),
            rng.uniform(-6.0, 6.0, n),
            rng.normal(0.0, 0.005, n),
        ]
    )
    return (world - true_pose[:3, 3]) @ true_pose[:3, :3]


def test_refinement_points_keep_2_to_20_m_and_thin_evenly() -> None:
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-30, 30, (10_000, 2)), rng.normal(-2, 0.01, 10_000)])
    out = refinement_points(pts, max_points=1000)
    r = np.hypot(out[:, 0], out[:, 1])
    assert np.all((r >= 2.0) & (r <= 20.0))
    inside = np.hypot(pts[:, 0], pts[:, 1])
    n_inside = int(np.sum((inside >= 2.0) & (inside <= 20.0)))
    assert n_inside // int(np.ceil(n_inside / 1000)) <= len(out) <= 1000


def test_a_later_chunk_raised_above_the_ground_seen_before_is_lowered_onto_it() -> None:
    """A drive out and back over the same ground: the first half (a first chunk) is right; the
    second half (a later chunk, placed from a ground grid of its own) sits 6 cm high. Against
    the ground of the whole drive each later sweep comes back to the true height."""
    rng = np.random.default_rng(7)
    xs = np.r_[np.arange(0.0, 30.0, 0.5), np.arange(30.0, 0.0, -0.5)]
    fixed = 60
    true = [_pose(x, SENSOR_HEIGHT) for x in xs]
    grounds: list[np.ndarray | None] = [_ground_seen(p, rng) for p in true]
    grounds[fixed + 5] = None  # an unregistered sweep: no ground, pose kept
    raised = [p.copy() for p in true]
    for p in raised[fixed:]:
        p[2, 3] += 0.06
    out, corrected = regrounded_poses(raised, grounds, fixed)
    z = np.array([p[2, 3] for p in out])
    assert np.array_equal(z[:fixed], np.full(fixed, SENSOR_HEIGHT))  # only fill the grid
    assert z[fixed + 5] == pytest.approx(SENSOR_HEIGHT + 0.06)
    later = np.delete(np.arange(fixed, len(xs)), 5)
    assert corrected >= len(later) - 5  # a few need the grid to fill first
    assert np.abs(z[later[5:]] - SENSOR_HEIGHT).max() < 0.01
    # x, y and yaw stay as they were; the tilt is not touched along the one-sided axis
    moved = np.array([p[:2, 3] for p in out]) - np.array([p[:2, 3] for p in raised])
    assert np.abs(moved).max() < 1e-9


def test_ground_never_seen_before_leaves_the_later_poses_as_they_are() -> None:
    rng = np.random.default_rng(8)
    true = [_pose(x, SENSOR_HEIGHT) for x in np.arange(0.0, 20.0, 0.5)]
    later = [_pose(x, SENSOR_HEIGHT + 0.06) for x in np.arange(100.0, 120.0, 0.5)]
    grounds = [_ground_seen(p, rng) for p in true + later]
    out, _ = regrounded_poses(true + later, grounds, len(true))
    # The later sweeps' own ground fills the grid as they go: they agree with it, and nothing
    # pulls them towards ground they never saw.
    z = np.array([p[2, 3] for p in out[len(true) :]])
    assert np.abs(z - (SENSOR_HEIGHT + 0.06)).max() < 0.005
