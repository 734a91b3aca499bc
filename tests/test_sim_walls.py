"""Fruiting walls in the simulator (issue 52): the preset's layout, its trellis (posts, wires,
drip line) which the LiDAR hits and labels as no tree, and per-tree truth as the wall
between trunk midpoints."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.errors import ConfigError
from canopy_kit.sim import load_sim_config
from canopy_kit.sim.orchard import generate_orchard
from canopy_kit.sim.session import _streams, build_world
from canopy_kit.sim.trellis import TRELLIS_ID

SEED = 1  # looked at; the preset names its held-out seeds


def _wall(seed: int = SEED, **orchard):
    cfg = load_sim_config("fruiting-wall", {"seed": seed, "orchard": orchard})
    return generate_orchard(cfg.orchard, _streams(seed)["orchard"])


def _along(orchard, xy: np.ndarray) -> np.ndarray:
    return np.asarray(xy)[..., :2] @ orchard.row_direction


def test_fruiting_wall_layout_matches_the_issue() -> None:
    orchard = _wall()
    spec = orchard.spec
    young = np.array([t.young for t in orchard.trees])
    assert young.any() and not young.all()
    assert len(orchard.trees) < spec.rows * spec.trees_per_row  # some missing
    for row in range(spec.rows):
        trees = sorted((t for t in orchard.trees if t.row == row), key=lambda t: t.index_in_row)
        along = _along(orchard, np.array([t.base for t in trees]))
        gaps = np.diff(along)
        # 0.6-1.5 m apart (jittered 4 cm), twice that where a tree is missing
        assert gaps.min() > 0.6 - 0.2 and gaps.max() < 2 * 1.5 + 0.2
        assert np.median(gaps) < 1.5
        # one continuous wall at 1.5 m above the ground: every 5 cm of the row between the
        # first and last trunk lies in some crown
        a = np.arange(along[0], along[-1], 0.05)
        xy = orchard.to_local(a, np.full_like(a, orchard.row_offsets[row]))
        z = orchard.terrain.height(xy[:, 0], xy[:, 1]) + 1.5
        pts = np.column_stack([xy, z])
        inside = np.zeros(len(pts), bool)
        for t in trees:
            inside |= t.crown.contains(pts)
        assert inside.mean() > 0.97
    old = [t for t in orchard.trees if not t.young]
    heights = np.array([t.height for t in old])
    assert heights.min() >= 2.3 and heights.max() <= 3.6
    across = np.array(
        [np.ptp(t.crown.surface_points(4000)[:, :2] @ orchard.right_direction) for t in old]
    )
    assert across.min() >= 0.45 and across.max() <= 1.25  # a wall 0.5-1.2 m thick
    young_heights = [t.height for t in orchard.trees if t.young]
    assert max(young_heights) < heights.min()


def test_trellis_posts_stand_above_the_wall_with_wires_and_a_drip_line() -> None:
    orchard = _wall()
    spec = orchard.spec
    assert len(orchard.trellis) == spec.rows
    wall_top = max(t.crown.z_range[1] for t in orchard.trees)
    for trellis in orchard.trellis:
        trees = [t for t in orchard.trees if t.row == trellis.row]
        a_trees = _along(orchard, np.array([t.base for t in trees]))
        a_posts = _along(orchard, trellis.post_bases)
        assert a_posts[0] < a_trees.min() and a_posts[-1] > a_trees.max()  # end posts
        assert np.diff(a_posts).max() <= 1.5 * spec.trellis_post_spacing
        assert trellis.post_tops[:, 2].min() > wall_top  # taller than the wall
        across = trellis.post_bases[:, :2] @ orchard.right_direction
        assert across == pytest.approx(orchard.row_offsets[trellis.row], abs=1e-9)
        assert len(trellis.wires) == len(spec.trellis_wire_heights)
        ground = orchard.terrain.height(trellis.post_bases[:, 0], trellis.post_bases[:, 1])
        for wire, h in zip(trellis.wires, spec.trellis_wire_heights, strict=True):
            assert wire[:, 2] - ground == pytest.approx(h)
        assert trellis.drip_line[:, 2] - ground == pytest.approx(spec.drip_line_height)
    assert _wall(trellis_post_spacing=0.0).trellis == []


def test_the_lidar_hits_posts_and_wires_and_labels_them_no_tree() -> None:
    """Rays from the alley straight at a post, a wire and the drip line (where no crown
    hides them): what they hit is trellis, with the per-point label ``TRELLIS_ID``."""
    import open3d as o3d

    from canopy_kit.sim.scene import TRELLIS

    cfg = load_sim_config("fruiting-wall", {"seed": SEED, "orchard": {"rows": 1}})
    orchard, _, scene, _ = build_world(cfg)
    trellis = orchard.trellis[0]
    right = np.append(orchard.right_direction, 0.0)
    targets = [trellis.post_tops[0] - [0, 0, 0.1]]  # the post's top, above the wall
    targets += [trellis.post_bases[0] + [0, 0, 1.2]]  # the end post beside the last tree
    targets += [w[0] for w in trellis.wires] + [trellis.drip_line[0]]  # at the end post
    origins = np.array(targets) - 1.5 * right
    rays = np.hstack([origins, np.tile(right, (len(origins), 1))]).astype(np.float32)
    hit = scene.raycasting_scene().cast_rays(o3d.core.Tensor(rays))
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    assert np.isfinite(hit["t_hit"].numpy()).all()
    assert (scene.material[prim] == TRELLIS).all()
    assert (scene.tree_id[prim] == TRELLIS_ID).all()
    assert (scene.tree_id[scene.material == TRELLIS] == TRELLIS_ID).all()


@pytest.mark.parametrize(
    ("overrides", "parameter"),
    [
        ({"trellis_post_spacing": -1.0}, "orchard.trellis_post_spacing"),
        ({"trellis_wire_heights": [1.0, 4.5]}, "orchard.trellis_wire_heights"),
        ({"young_probability": 1.0}, "orchard.young_probability"),
        ({"drip_line_radius": 0.0}, "orchard.drip_line_height/drip_line_radius"),
    ],
)
def test_impossible_trellis_parameters_name_the_parameter(overrides, parameter) -> None:
    with pytest.raises(ConfigError, match=parameter.replace(".", r"\.")):
        load_sim_config("fruiting-wall", {"orchard": overrides})
