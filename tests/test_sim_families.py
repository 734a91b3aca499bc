"""Tree families beyond the envelope crowns (issue 46): lobe unions, grown trees, real splats,
and a row of them driven past by the simulator's LiDAR.

Truths: closed-form volumes of ellipsoids and of two overlapping balls, the pipe model by hand,
the surfaces the sensors were cast against (every return lies on the tree's own leaves or
branches), and the real cloud itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from canopy_kit.sim.alley import drive_row
from canopy_kit.sim.grown import GROWN_FORMS, Colonisation, colonise, grown_tree, pipe_radii
from canopy_kit.sim.lobe_union import LobeUnion, lobe_union_tree
from canopy_kit.sim.real_tree import splatted
from canopy_kit.sim.specimen import sample_mesh


def test_lobe_union_volume_of_one_turned_ellipsoid() -> None:
    union = LobeUnion(np.zeros((1, 3)), np.array([[1.0, 0.7, 0.5]]), np.array([0.3]))
    assert union.volume == pytest.approx(4 / 3 * np.pi * 0.35, rel=1e-3)


def test_lobe_union_volume_of_two_overlapping_balls() -> None:
    """Two unit balls with centres 1 m apart: 2 · 4π/3 minus the lens π/12 (4r + d)(2r - d)²."""
    union = LobeUnion(np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.ones((2, 3)), np.zeros(2))
    assert union.volume == pytest.approx(8 / 3 * np.pi - np.pi / 12 * 5.0, rel=1e-3)


def test_lobe_union_tree_leaves_lie_inside_the_union_and_hollows_open() -> None:
    from scipy.spatial import ConvexHull

    tree = lobe_union_tree(np.random.default_rng(3))
    lobes = tree.info["lobes"]
    assert 4 <= lobes <= 9
    union = tree.info["union"]
    assert union.volume == pytest.approx(tree.envelope_m3)
    assert (union.norms(tree.leaves).min(axis=1) <= 1.0 + 1e-9).all()
    # the lobes leave hollows: the union's convex hull is well above its volume
    assert ConvexHull(tree.leaves).volume > 1.1 * tree.envelope_m3


def test_pipe_model_radii_by_hand() -> None:
    # 0 -> 1 -> {2, 3}; 3 -> 4: tips 2 and 4
    parent = np.array([-1, 0, 1, 1, 3])
    r = pipe_radii(parent, tip=0.01, exponent=2.0)
    assert r[2] == pytest.approx(0.01) and r[4] == pytest.approx(0.01)
    assert r[3] == pytest.approx(0.01)
    assert r[1] == pytest.approx(np.sqrt(2) * 0.01)
    assert r[0] == pytest.approx(r[1])


def test_colonisation_reaches_every_attraction_point_it_can() -> None:
    rng = np.random.default_rng(0)
    attractors = rng.uniform([-1, -1, 1], [1, 1, 2], (300, 3))
    nodes = np.array([[0.0, 0, 0], [0, 0, 0.5], [0, 0, 1.0]])
    skeleton = colonise(attractors, nodes, np.array([-1, 0, 1]), Colonisation())
    reach = cKDTree(skeleton.nodes).query(attractors)[0]
    assert (reach <= Colonisation().kill + 1e-9).mean() > 0.95
    assert (skeleton.parent[1:] < np.arange(1, len(skeleton.parent))).all()  # a tree
    seg = np.linalg.norm(skeleton.nodes[3:] - skeleton.nodes[skeleton.parent[3:]], axis=1)
    assert np.allclose(seg, Colonisation().step)


@pytest.mark.parametrize("form", GROWN_FORMS)
def test_grown_trees_carry_leaves_on_shoots(form: str) -> None:
    old = grown_tree(np.random.default_rng(1), form)
    young = grown_tree(np.random.default_rng(1), form, young=True)
    assert old.envelope_m3 is None and old.family == "grown"
    assert old.n_leaf_clusters > 3 * young.n_leaf_clusters > 0
    assert np.ptp(old.leaves[:, 2]) > np.ptp(young.leaves[:, 2])
    assert len(old.wood[1]) > 0 and len(old.trunk[1]) > 0
    if form == "vase":  # the open centre: few leaves near the axis high in the crown
        centres = old.leaves.reshape(-1, 6, 3).mean(axis=1)
        top = centres[:, 2] > np.quantile(centres[:, 2], 0.7)
        near_axis = np.hypot(centres[top, 0], centres[top, 1]) < 0.4
        assert near_axis.mean() < 0.1


def test_sample_mesh_density_matches_the_area() -> None:
    verts = np.array([[0.0, 0, 0], [2.0, 0, 0], [0.0, 1.0, 0]])  # area 1 m²
    pts = sample_mesh(verts, np.array([[0, 1, 2]]), 5000.0, np.random.default_rng(0))
    assert abs(len(pts) - 3 - 5000) < 4 * np.sqrt(5000)
    assert np.allclose(pts[:, 2], 0.0) and (pts[:, 0] / 2 + pts[:, 1] <= 1 + 1e-12).all()


def test_real_splats_keep_the_cloud_as_reference() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.normal([10, 20, 105], [1, 1, 2], (3000, 3))
    spec = splatted(xyz, cell=0.05)
    ref = spec.complete_foliage()
    assert len(ref) == len(xyz)
    assert ref[:, 2].min() == pytest.approx(0.0)
    assert np.allclose(ref - ref.mean(axis=0), xyz - xyz.mean(axis=0))
    centres = spec.leaves.reshape(-1, 6, 3).mean(axis=1)
    assert cKDTree(ref).query(centres)[0].max() < 1e-9  # a splat on every thinned point


def test_a_drive_returns_points_on_each_trees_own_surfaces() -> None:
    """Every labelled return lies on (within the range noise of) its tree's leaves or branches;
    the union of both alleys holds each side's points."""
    rng = np.random.default_rng(5)
    row = [lobe_union_tree(rng), grown_tree(rng, "vase")]
    scan = drive_row(row, 5.0, "vlp16", speed=2.5, lead=3.0)
    for k, tree in enumerate(row):
        both = scan.tree_points(k)
        left, right = scan.tree_points(k, ["left"]), scan.tree_points(k, ["right"])
        assert len(left) > 1000 and len(right) > 1000 and len(both) == len(left) + len(right)
        dist = cKDTree(tree.complete_foliage(density=20000)).query(both)[0]
        assert np.quantile(dist, 0.99) < 0.05  # 1 cm range noise, 7 mm sample spacing
        # the left alley (y > 0) sees the tree's left side better than its right
        assert (left[:, 1] > 0).mean() > (right[:, 1] > 0).mean()
