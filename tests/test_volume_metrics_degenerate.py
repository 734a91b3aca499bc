"""Crown extents on any point set, in memory linear in the points.

Truth: the largest pairwise distance from scipy's ``pdist`` on small sets, hand-computed
values on lines, circles and single points. The memory bound is measured with tracemalloc
on a tree whose points all lie in one vertical plane (the case that asked 13 GiB).
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from canopy_kit.volume.metrics import horizontal_hull, tree_metrics, widest_extents


@pytest.mark.parametrize("kind", ["gaussian", "ellipse", "grid", "uniform"])
def test_widest_extent_is_the_largest_pairwise_distance(kind):
    rng = np.random.default_rng(len(kind))
    for _ in range(40):
        n = int(rng.integers(3, 300))
        if kind == "gaussian":
            xy = rng.normal(size=(n, 2)) * [3.0, 1.0]
        elif kind == "ellipse":
            a = rng.uniform(0, 2 * np.pi, n)
            xy = np.c_[2 * np.cos(a), np.sin(a)]
        elif kind == "grid":  # many collinear hull edges and ties
            xy = rng.integers(0, 4, (n, 2)).astype(float)
        else:
            xy = rng.uniform(size=(n, 2))
        widest, across = widest_extents(xy)
        assert widest == pytest.approx(pdist(xy).max(), abs=1e-9)
        assert 0.0 <= across <= widest + 1e-9


def test_degenerate_sets_give_their_extents():
    t = np.linspace(0.0, 5.0, 1000)
    line = np.c_[t, 0.5 * t]
    assert widest_extents(line) == pytest.approx((np.hypot(5.0, 2.5), 0.0), abs=1e-9)
    assert len(horizontal_hull(line)) == 2
    assert widest_extents(np.ones((50, 2))) == (0.0, 0.0)
    assert widest_extents(np.zeros((1, 2))) == (0.0, 0.0)
    assert widest_extents(np.zeros((0, 2))) == (0.0, 0.0)


def test_a_tree_in_one_vertical_plane_is_measured_in_linear_memory():
    rng = np.random.default_rng(3)
    n = 30_000
    x = rng.uniform(0.0, 4.0, n)
    xyz = np.c_[x, 0.5 * x, rng.uniform(0.0, 3.0, n)]
    tracemalloc.start()
    try:
        m = tree_metrics(xyz, volume_m3=1.0)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert m.crown_diameter_max_m == pytest.approx(
        np.hypot(x.max() - x.min(), 0.5 * (x.max() - x.min()))
    )
    assert m.height_m == pytest.approx(xyz[:, 2].max() - xyz[:, 2].min())
    assert peak < 64 * 2**20, f"{peak / 2**20:.0f} MiB for {n} points"  # the points are 0.7 MiB


def test_a_round_hull_of_many_vertices_stays_linear():
    a = np.linspace(0.0, 2 * np.pi, 20_000, endpoint=False)
    xy = np.c_[np.cos(a), np.sin(a)] * 3.0
    tracemalloc.start()
    try:
        widest, across = widest_extents(xy)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert widest == pytest.approx(6.0, abs=1e-6) and across == pytest.approx(6.0, abs=1e-3)
    assert peak < 64 * 2**20
