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


def test_end_posts_lean_out_of_the_row_and_the_wires_meet_them() -> None:
    """``trellis_end_post_lean_deg``: each row's two end posts lean outward along the row, their
    tops ``height * tan(lean)`` beyond their feet; the middle posts stay upright, and every
    wire meets each post on its axis at its height."""
    lean = 20.0
    orchard = _wall(trellis_end_post_lean_deg=lean)
    spec = orchard.spec
    reach = spec.trellis_post_height * np.tan(np.radians(lean))
    for trellis in orchard.trellis:
        shift = _along(orchard, trellis.post_tops) - _along(orchard, trellis.post_bases)
        assert shift[0] == pytest.approx(-reach) and shift[-1] == pytest.approx(reach)
        assert np.abs(shift[1:-1]).max(initial=0.0) < 1e-9
        assert trellis.post_tops[:, 2] - trellis.post_bases[:, 2] == pytest.approx(
            spec.trellis_post_height
        )
        for wire, h in zip(trellis.wires, spec.trellis_wire_heights, strict=True):
            np.testing.assert_allclose(wire, trellis.post_at(h), atol=1e-12)
            assert _along(orchard, wire[-1]) - _along(orchard, trellis.post_bases[-1]) == (
                pytest.approx(h * np.tan(np.radians(lean)))
            )
    upright = _wall()
    for a, b in zip(upright.trellis, orchard.trellis, strict=True):
        np.testing.assert_allclose(a.post_bases, b.post_bases)  # the same feet


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
        ({"trellis_end_post_lean_deg": 70.0}, "orchard.trellis_end_post_lean_deg"),
        ({"trellis_end_post_lean_deg": -5.0}, "orchard.trellis_end_post_lean_deg"),
        ({"young_probability": 1.0}, "orchard.young_probability"),
        ({"drip_line_radius": 0.0}, "orchard.drip_line_height/drip_line_radius"),
    ],
)
def test_impossible_trellis_parameters_name_the_parameter(overrides, parameter) -> None:
    with pytest.raises(ConfigError, match=parameter.replace(".", r"\.")):
        load_sim_config("fruiting-wall", {"orchard": overrides})


# -- per-tree truth: the wall between trunk midpoints ----------------------------------------
def _sphere_wall(trunks_along: list[float], radius: float = 1.0, bearing_deg: float = 30.0):
    """A one-row orchard (rows at ``bearing_deg``) whose trees are spheres of ``radius``
    centred 2 m above their trunks at ``trunks_along`` along the row."""
    from dataclasses import replace

    from canopy_kit.sim.crown import CrownEnvelope

    orchard = _wall(rows=1, row_bearing_deg=bearing_deg)
    template = orchard.trees[0]
    trees = []
    for k, a in enumerate(trunks_along):
        xy = a * orchard.row_direction
        sphere = CrownEnvelope((xy[0], xy[1], 2.0), (radius,) * 4, 0.3, 2.0)
        trees.append(
            replace(template, tree_id=k, index_in_row=k, base=(xy[0], xy[1], 0.0), crown=sphere)
        )
    return replace(orchard, trees=trees)


def test_two_overlapping_spheres_split_their_union_at_the_trunk_midpoint() -> None:
    """Unit spheres 1 m apart: the union is two balls less the lens, 8π/3 - π(4 + 1)(2 - 1)²/12
    (closed form); by symmetry each tree owns half, cut at 0.5 m between the trunks."""
    from canopy_kit.sim.wall_truth import trunk_midpoint_cuts

    orchard = _sphere_wall([0.0, 1.0])
    union = 8 * np.pi / 3 - np.pi * 5 / 12
    cuts = trunk_midpoint_cuts(orchard)
    assert [c.tree_id for c in cuts] == [0, 1]
    assert cuts[0].start_m == -np.inf and cuts[1].end_m == np.inf
    assert cuts[0].end_m == pytest.approx(0.5) and cuts[1].start_m == pytest.approx(0.5)
    total = sum(c.volume_m3 for c in cuts)
    assert total == pytest.approx(union, rel=0.003)
    assert total < 2 * orchard.trees[0].crown.volume - 1.0  # the lens is counted once
    for c in cuts:
        assert c.volume_m3 == pytest.approx(union / 2, rel=0.005)


def test_a_cut_off_centre_gives_each_tree_its_side_of_the_wall() -> None:
    """Three unit spheres at 0, 1.2 and 2.0 m: the middle tree owns [0.6, 1.6), where its
    neighbours' spheres lie inside its own (their radius at each along position is smaller),
    so its cut is its sphere's slice, π ∫ (1 - x²) dx from -0.6 to 0.4 (by hand); all three
    cuts against a Monte-Carlo estimate independent of the grid."""
    from canopy_kit.sim.wall_truth import trunk_midpoint_cuts

    orchard = _sphere_wall([0.0, 1.2, 2.0], bearing_deg=0.0)
    cuts = trunk_midpoint_cuts(orchard)
    assert [round(c.end_m, 6) for c in cuts[:2]] == [0.6, 1.6]
    slice_12 = np.pi * ((0.4 - 0.4**3 / 3) - (-0.6 + 0.6**3 / 3))
    assert cuts[1].volume_m3 == pytest.approx(slice_12, rel=0.005)
    rng = np.random.default_rng(5)
    p = rng.uniform([-1.0, -1.0, 1.0], [1.0, 3.0, 3.0], (2_000_000, 3))
    inside = np.zeros(len(p), bool)
    for t in orchard.trees:
        inside |= t.crown.contains(p)
    box = 2.0 * 4.0 * 2.0
    along = p[:, 1]  # bearing 0: rows run along +y
    for c in cuts:
        s = inside & (along >= c.start_m) & (along < c.end_m)
        assert c.volume_m3 == pytest.approx(box * s.mean(), rel=0.01), c.tree_id


def test_preset_cuts_sum_to_the_union_and_match_single_crowns() -> None:
    from canopy_kit.sim.wall_truth import slab_volumes, trunk_midpoint_cuts

    orchard = _wall()
    cuts = trunk_midpoint_cuts(orchard)
    # each crown alone, sampled like the wall, against its exact quadrature volume
    for t in orchard.trees[:6]:
        alone = slab_volumes(orchard, [t], np.array([-np.inf, np.inf]))[0]
        assert alone == pytest.approx(t.crown.volume, rel=0.01), t.tree_id
    for row in range(orchard.spec.rows):
        trees = [t for t in orchard.trees if t.row == row]
        mine = [c for c in cuts if c.row == row]
        union = slab_volumes(orchard, trees, np.array([-np.inf, np.inf]), seed=3)[0]
        total = sum(c.volume_m3 for c in mine)
        assert total == pytest.approx(union, rel=0.003)
        assert total < sum(t.crown.volume for t in trees)  # the crowns overlap
        starts = sorted(c.start_m for c in mine)
        ends = sorted(c.end_m for c in mine)
        assert starts[0] == -np.inf and ends[-1] == np.inf and starts[1:] == ends[:-1]


def test_trees_csv_of_a_wall_says_its_volume_is_a_trunk_midpoint_cut() -> None:
    from canopy_kit.evaluate.truth import TREE_COLUMNS, WALL_COLUMNS
    from canopy_kit.sim.truth import tree_table

    table = tree_table(_wall(rows=1))
    assert list(table.columns) == [*TREE_COLUMNS, *WALL_COLUMNS]
    assert (table["volume_truth"] == "trunk-midpoint cut").all()
    assert (table["cut_volume_m3"] > 0).all()
    plain = tree_table(_wall(rows=1, tree_volume_truth="crown"))
    assert list(plain.columns) == TREE_COLUMNS
