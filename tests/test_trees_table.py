"""The per-tree table (``canopy_kit.volume.verb.measure_trees``) on clouds of known shape."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from canopy_kit.config import VolumeConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import ConfigError
from canopy_kit.volume.verb import measure_trees


def _ball_orchard(n_trees: int, seed: int = 0) -> tuple[PointCloud, np.ndarray, np.ndarray]:
    """Solid balls of known radius (a 0.05 m grid with 1 mm of noise: exact grids are
    degenerate for qhull), one per label."""
    rng = np.random.default_rng(seed)
    radii = rng.uniform(0.8, 1.4, n_trees)
    parts, labels = [], []
    grid = np.mgrid[-1.5:1.5:0.05, -1.5:1.5:0.05, -1.5:1.5:0.05].reshape(3, -1).T
    for k, r in enumerate(radii):
        ball = grid[np.linalg.norm(grid, axis=1) <= r] + np.array([6.0 * k, 0.0, 3.0])
        ball += rng.normal(0.0, 0.001, ball.shape)
        parts.append(ball)
        labels.append(np.full(len(ball), k))
    return PointCloud(np.vstack(parts)), np.concatenate(labels), radii


def test_volumes_of_solid_balls_and_the_same_table_on_any_number_of_workers() -> None:
    cloud, labels, radii = _ball_orchard(9)
    config = VolumeConfig(
        methods=["convex_hull", "alpha_shape"],
        params={"alpha_shape": {"alpha": 0.9}},
        voxel_size=0.1,
        workers=1,
    )
    one = measure_trees(cloud, labels, config)
    true = 4 / 3 * np.pi * radii**3
    # Thinned to 0.1 m, the hull of a filled ball of radius r loses about one spacing of radius.
    assert np.all(np.abs(one["volume_convex_hull_m3"] / true - 1) < 0.15)
    assert np.all(one["volume_alpha_m3"] <= one["volume_convex_hull_m3"] + 1e-9)
    config.workers = 2
    two = measure_trees(cloud, labels, config)
    pd.testing.assert_frame_equal(one, two)
    assert list(two["segment"]) == list(range(9))


def test_volume_voxel_size_zero_measures_every_point_and_bad_settings_are_named() -> None:
    cloud, labels, radii = _ball_orchard(2)
    every = measure_trees(
        cloud, labels, VolumeConfig(methods=["convex_hull"], voxel_size=0.0, workers=1)
    )
    thinned = measure_trees(
        cloud, labels, VolumeConfig(methods=["convex_hull"], voxel_size=0.2, workers=1)
    )
    true = 4 / 3 * np.pi * radii**3
    # Every point of the 0.05 m grid: closer to the true ball than the 0.2 m thinning.
    assert np.all(
        np.abs(every["volume_convex_hull_m3"] - true)
        < np.abs(thinned["volume_convex_hull_m3"] - true)
    )
    with pytest.raises(ConfigError, match="volume.voxel_size"):
        VolumeConfig(voxel_size=-1)
    with pytest.raises(ConfigError, match="volume.workers"):
        VolumeConfig(workers=-2)


def test_flagged_counts_trees_with_a_note_and_not_missing_values() -> None:
    from canopy_kit.results.tree_table import flagged

    trees = pd.DataFrame(
        {
            "volume_flags": ["", "hull of fewer than 4 points", None, np.nan],
            "tree_id": ["a", "b", "c", "d"],
        }
    )
    assert flagged(trees, "volume_flags").tolist() == [False, True, False, False]
    assert flagged(trees, "segment_flags").tolist() == [False] * 4  # no such column
