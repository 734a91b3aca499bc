"""Crown forms of the simulator: exact volumes against Monte Carlo, the forms' geometry,
sessions per form, the default form unchanged, and config errors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from canopy_kit.errors import ConfigError
from canopy_kit.sim.config import load_sim_config
from canopy_kit.sim.crown import volume_by_quadrature
from canopy_kit.sim.orchard import generate_orchard

FORMS = ["ellipsoid", "lobed", "vase", "hedged", "sparse"]
# The default scenes of 1 x 3 trees, seed 7, as main 5eb15d7 made them before the forms
# existed: vertex count, vertices per tree (ground first) and the vertex sum to 1 mm.
SCENES_BEFORE_FORMS = {
    "pistachio": (24971, [10080, 6616, 4544, 6028], [-549.528, 123795.978, 35355.476]),
    "almond": (55779, [11032, 17308, 22388, 17076], [5922.313, 254240.716, 129363.135]),
}


def _orchard(form: str, seed: int, kind: str = "pistachio", **orchard):
    cfg = load_sim_config(
        kind, {"orchard": {"rows": 1, "trees_per_row": 3, "crown_form": form, **orchard}}
    )
    return generate_orchard(cfg.orchard, np.random.default_rng(seed))


@pytest.mark.parametrize("form", [*FORMS, "mix"])
def test_quadrature_volume_matches_monte_carlo(form):
    """400k uniform points in the bounding box; the quadrature within 3 sigma (+0.05 %)."""
    rng = np.random.default_rng(101)
    for kind, seed in (("pistachio", 11), ("pistachio", 12), ("almond", 13)):
        for tree in _orchard(form, seed, kind).trees:
            lo, hi = tree.crown.bounds
            n = 400_000
            f = tree.crown.contains(rng.uniform(lo, hi, (n, 3))).mean()
            box = float(np.prod(hi - lo))
            sigma = np.sqrt(f * (1 - f) / n) * box
            assert abs(f * box - tree.crown.volume) < 3 * sigma + 5e-4 * tree.crown.volume, (
                form,
                seed,
                tree.tree_id,
                f * box,
                tree.crown.volume,
            )


@pytest.mark.parametrize("form", ["lobed", "vase", "hedged"])
def test_quadrature_is_converged(form):
    """The form's node counts agree with a quadrature of 8x the nodes each way to 1e-4."""
    for tree in _orchard(form, 21).trees[:2]:
        fine = volume_by_quadrature(tree.crown, 768, 3072)
        assert tree.crown.volume == pytest.approx(fine, rel=1e-4)


def test_forms_are_what_they_say():
    for form in FORMS:
        for tree in _orchard(form, 5).trees:
            assert tree.crown_form == form
            assert tree.crown.form_name == ("ellipsoid" if form == "sparse" else form)
    mixed = {t.crown_form for s in (1, 2, 3) for t in _orchard("mix", s, trees_per_row=6).trees}
    assert len(mixed) >= 3 and mixed <= set(FORMS)
    # Mix is seeded: the same seed gives the same forms.
    assert [t.crown_form for t in _orchard("mix", 4).trees] == [
        t.crown_form for t in _orchard("mix", 4).trees
    ]


def test_vase_is_hollow_in_the_middle():
    for seed in (1, 2, 3):
        for tree in _orchard("vase", seed).trees:
            z_lo, z_hi = tree.crown.z_range
            cx, cy, cz = tree.crown.center
            assert cz < z_lo + 0.35 * (z_hi - z_lo)  # the centre is low: the trunk top
            mid = 0.5 * (z_lo + z_hi)
            axis = np.array([[cx, cy, z] for z in np.linspace(mid, z_hi, 20)])
            assert not tree.crown.contains(axis).any()
            # ... while the walls at mid height are inside, all round the axis.
            ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
            a, b = tree.crown.semi_axes[:2]
            ring = np.column_stack(
                [
                    cx + 0.6 * min(a, b) * np.cos(ang),
                    cy + 0.6 * min(a, b) * np.sin(ang),
                    np.full(12, mid),
                ]
            )
            assert tree.crown.contains(ring).all()


def test_hedged_crowns_have_flat_faces():
    for seed in (1, 2):
        orchard = _orchard("hedged", seed)
        right = np.append(orchard.right_direction, 0.0)
        for tree in orchard.trees:
            form = tree.crown.form
            s = tree.crown.surface_points(20000) - np.asarray(tree.crown.center)
            for n, off in zip(form.normals, form.offsets):
                along_n = s @ np.asarray(n)
                assert along_n.max() == pytest.approx(off, abs=1e-9)
                assert (np.abs(along_n - off) < 1e-9).mean() > 0.03  # a face, not a touch
            # The side planes are the row's: normals across the row, planes straddling the trunk.
            assert abs(np.asarray(form.normals[0]) @ right) == pytest.approx(1.0)
            base_across = np.dot(tree.base[:2], orchard.right_direction)
            c_across = np.dot(tree.crown.center[:2], orchard.right_direction)
            assert (c_across + form.offsets[0]) - base_across == pytest.approx(
                base_across - (c_across - form.offsets[1]), abs=1e-9
            )


def test_lobed_crowns_have_deep_hollows_between_lobes():
    for tree in [t for seed in (7, 8, 9) for t in _orchard("lobed", seed).trees]:
        form = tree.crown.form
        dirs = np.asarray(form.directions)
        at_lobes = tree.crown.radius(dirs)
        # Half-way (in azimuth) between neighbouring lobes, at the lobes' mean elevation.
        az = np.sort(np.arctan2(dirs[:, 1], dirs[:, 0]))
        mid = az + np.diff(np.append(az, az[0] + 2 * np.pi)) / 2
        el = np.arcsin(dirs[:, 2]).mean()
        between = np.column_stack(
            [np.cos(el) * np.cos(mid), np.cos(el) * np.sin(mid), np.full(len(mid), np.sin(el))]
        )
        assert (at_lobes.min() - tree.crown.radius(between)).max() > 0.3


def test_default_form_is_bit_identical():
    """Crowns and scene of the default form as before the forms existed (main 5eb15d7).
    Rounded, not hashed: a newer numpy may change the last bits of a sine."""
    from canopy_kit.sim.scene import build_scene

    expected = {
        "pistachio": [25.284232072, 16.842441365, 22.793960436],
        "almond": [71.380786427, 90.040413479, 69.958556124],
    }
    made = {}
    for kind, volumes in expected.items():
        cfg = load_sim_config(kind, {"orchard": {"rows": 1, "trees_per_row": 3}})
        assert cfg.orchard.crown_form == "ellipsoid"
        rng = np.random.default_rng(7)
        orchard = generate_orchard(cfg.orchard, rng)
        scene = build_scene(orchard, rng)
        assert [t.crown.volume for t in orchard.trees] == pytest.approx(volumes, rel=1e-9)
        made[kind] = (
            len(scene.vertices),
            np.bincount(scene.tree_id + 1).tolist(),
            np.round(scene.vertices.sum(axis=0), 3).tolist(),
        )
    assert made == SCENES_BEFORE_FORMS


def test_default_session_truth_is_unchanged(sim_factory):
    """A default MICRO session: the trees and the point count as main 5eb15d7 made them,
    before the crown forms."""
    import pandas as pd
    from conftest import MICRO

    session = sim_factory("pistachio", overrides=MICRO)
    trees = pd.read_csv(session.truth_dir / "trees.csv")
    assert [t.crown.volume for t in session.orchard.trees] == pytest.approx(
        trees["crown_volume_m3"].to_list(), rel=1e-6
    )  # the CSV keeps 6 decimals
    assert session.n_points == 731076


def test_leaf_penetration_limits_the_foliage_depth():
    from canopy_kit.sim.scene import FOLIAGE, build_scene, depth_below_envelope

    for pen in (0.3, 0.6):
        cfg = load_sim_config(
            "pistachio", {"orchard": {"rows": 1, "trees_per_row": 2, "leaf_penetration_m": pen}}
        )
        rng = np.random.default_rng(3)
        orchard = generate_orchard(cfg.orchard, rng)
        scene = build_scene(orchard, rng)
        for tree in orchard.trees:
            tri = (scene.material == FOLIAGE) & (scene.tree_id == tree.tree_id)
            centres = scene.vertices[scene.triangles[tri]].mean(axis=1)
            below = depth_below_envelope(tree.crown, centres)
            # A cluster's centre is its leaf position (up to its 0.22 m size).
            assert below.max() < pen + 0.25 and below.min() > -1e-9
            assert np.quantile(below, 0.9) > 0.5 * pen  # the shell is filled, not only its skin


@pytest.mark.parametrize("form", FORMS)
def test_leaf_clusters_fill_each_envelope_up_to_it(form):
    """Every leaf-cluster vertex lies inside its crown's envelope, and the clusters reach it."""
    from canopy_kit.sim.scene import leaf_cluster_vertices

    cfg = load_sim_config("pistachio", {"orchard": {"rows": 1, "trees_per_row": 2}})
    spec = replace(cfg.orchard, crown_form=form)
    rng = np.random.default_rng(8)
    for tree in generate_orchard(spec, rng).trees:
        density = tree.foliage_scale
        verts = leaf_cluster_vertices(
            tree,
            rng,
            spec.foliage_density_shell * density,
            spec.foliage_density_core * density,
            spec.leaf_cluster_size_range,
        )
        assert len(verts) >= 6 * 5 and len(verts) % 6 == 0
        depth = tree.crown.relative_depth(verts)
        assert depth.max() <= 1.0 + 1e-9
        assert (depth > 0.999).mean() > 0.05  # clipped onto the envelope where they stuck out


@pytest.mark.parametrize(
    "overrides, parameter",
    [
        ({"crown_form": "cone"}, "orchard.crown_form"),
        ({"leaf_penetration_m": 0.0}, "orchard.leaf_penetration_m"),
        ({"hedge_cut": 1.5}, "orchard.hedge_cut"),
        ({"lobe_hollow_range": [0.5, 1.2]}, "orchard.lobe_hollow_range"),
        ({"sparse_foliage_scale": 0.0}, "orchard.sparse_foliage_scale"),
    ],
)
def test_config_errors_name_the_key(overrides, parameter):
    with pytest.raises(ConfigError, match=parameter.replace(".", r"\.")):
        load_sim_config("pistachio", {"orchard": overrides})


SESSION = {"orchard": {"rows": 1, "trees_per_row": 3}, "lidar": {"columns": 256, "rings": 16}}


@pytest.mark.parametrize("form", FORMS)
def test_session_of_each_form_scans_its_envelopes(sim_factory, form):
    """A small session per form: labelled points on/inside their tree's envelope, leaves within
    ``leaf_penetration_m`` of it, and the truth table holding the forms' exact volumes."""
    from canopy_kit.config import merge
    from canopy_kit.evaluate.truth_map import truth_map
    from canopy_kit.sim import load_truth
    from canopy_kit.sim.scene import depth_below_envelope

    pen = 0.4
    session = sim_factory(
        "pistachio",
        seed=31,
        overrides=merge(SESSION, {"orchard": {"crown_form": form, "leaf_penetration_m": pen}}),
    )
    truth = load_truth(session.root)
    orchard = truth.orchard()
    assert [t.crown_form for t in orchard.trees] == [form] * 3
    assert np.allclose(
        truth.trees["crown_volume_m3"], [t.crown.volume for t in orchard.trees], atol=1e-6
    )
    if form == "sparse":
        assert (truth.trees["crown_diameter_m"] < 2.5).all()
    cloud = truth_map(session.root, voxel_size=0.03)
    tid = np.asarray(cloud.fields["tree_id"])
    for tree in orchard.trees:
        pts = cloud.xyz[tid == tree.tree_id]
        assert len(pts) > (30 if form == "sparse" else 300), (form, tree.tree_id, len(pts))
        c = np.asarray(tree.crown.center)
        assert tree.crown.contains(c + (pts - c) * 0.98).mean() > 0.98  # range noise allowed
        below = depth_below_envelope(tree.crown, pts)
        # Leaves within the penetration depth (plus a cluster's size); the wood may go deeper.
        assert (below <= pen + 0.25).mean() > 0.9, (form, np.quantile(below, [0.5, 0.9]))


@pytest.mark.parametrize("form", ["lobed", "vase", "hedged", "sparse"])
def test_drone_photos_show_every_form(tmp_path, form):
    """The drone ray-casts the same scene: each form's highest crown points photograph green."""
    import pandas as pd
    from PIL import Image
    from scipy.spatial.transform import Rotation

    from canopy_kit.sim.drone import simulate_drone_session
    from canopy_kit.sim.session import regenerate_orchard
    from ground_truth.camera import camera_from_pose
    from ground_truth.crowns import excess_green

    cfg = load_sim_config(
        "pistachio",
        {
            "seed": 3,
            "orchard": {"rows": 1, "trees_per_row": 2, "crown_form": form},
            "drone": {"enabled": True, "image_width": 240, "image_height": 180, "altitude": 30.0},
        },
    )
    simulate_drone_session(tmp_path, cfg)
    orchard = regenerate_orchard(tmp_path)
    assert {t.crown_form for t in orchard.trees} == {form}
    rows = pd.read_csv(tmp_path / "truth" / "drone_cameras.csv")
    greens, soil = [], []
    for r in rows.itertuples():
        cam = camera_from_pose(
            r.image,
            "SIMPLE_PINHOLE",
            (r.focal_px, r.cx, r.cy),
            r.width,
            r.height,
            np.array([r.x, r.y, r.z]),
            Rotation.from_quat([r.qx, r.qy, r.qz, r.qw]).as_matrix(),
        )
        img = np.asarray(Image.open(tmp_path / "drone" / cam.name)).astype(float)
        for tree in orchard.trees:
            s = tree.crown.surface_points(4000)
            tops = s[np.argsort(s[:, 2])[-40:]]  # on a lobe, the vase's rim, the hedge's top
            uv, _ = cam.project(tops)
            ok = (
                (uv[:, 0] > 3)
                & (uv[:, 0] < cam.width - 3)
                & (uv[:, 1] > 3)
                & (uv[:, 1] < cam.height - 3)
            )
            for u, v in uv[ok].astype(int):
                greens.append(excess_green(img[v - 1 : v + 2, u - 1 : u + 2]).mean())
        soil.append(excess_green(img[:10, :10]).mean())
    assert len(greens) >= 40
    green = np.mean(np.asarray(greens) > 0.15)
    assert np.mean(np.asarray(soil) > 0.15) < 0.1
    # Sparse young trees (0.3 x the leaves, ~0.2 m pixels here) mostly show the ground
    # through: measured 4 % green hits against 85-95 % for the other forms.
    assert green > (0.02 if form == "sparse" else 0.6), green


@pytest.mark.parametrize("form", ["lobed", "vase", "hedged"])
def test_scaled_moved_and_resized_crowns_keep_their_form(form):
    crown = _orchard(form, 6).trees[0].crown
    k = 0.8
    small = crown.scaled(k)
    assert small.form_name == form and small.volume == pytest.approx(k**3 * crown.volume, rel=1e-6)
    moved = crown.moved((10.0, -3.0, 2.0))
    assert moved.volume == pytest.approx(crown.volume, rel=1e-12)
    shifted = crown.surface_points(500) * 0.99 + 0.01 * np.asarray(crown.center)  # just inside
    assert moved.contains(shifted - np.asarray(crown.center) + np.array([10.0, -3.0, 2.0])).all()
    a, b, cu, cd = crown.semi_axes
    narrow = crown.with_semi_axes((a, 0.7 * b, cu, cd))
    assert narrow.form_name == form and narrow.volume < crown.volume
    if form == "hedged":  # the side planes follow the across semi-axis
        assert narrow.form.offsets[:2] == pytest.approx([0.7 * o for o in crown.form.offsets[:2]])
