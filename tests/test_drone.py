"""Simulated drone flight: plan, photos, EXIF and true cameras (a tiny orchard, small photos)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from canopy_kit.errors import ConfigError
from canopy_kit.sim import load_sim_config
from canopy_kit.sim.drone import ground_footprint, plan_flight, simulate_drone_session
from canopy_kit.sim.orchard import generate_orchard
from ground_truth.camera import camera_from_pose
from ground_truth.crowns import excess_green
from ground_truth.exif import read_flight

SMALL = {
    "orchard": {"rows": 1, "trees_per_row": 2},
    "drone": {"enabled": True, "image_width": 400, "image_height": 300, "altitude": 30.0},
}


@pytest.fixture(scope="module")
def small_flight(tmp_path_factory):
    cfg = load_sim_config("pistachio", {"seed": 3, **SMALL})
    root = tmp_path_factory.mktemp("drone")
    flight = simulate_drone_session(root, cfg)
    return cfg, root, flight


def _cameras(root):
    rows = pd.read_csv(root / "truth" / "drone_cameras.csv")
    return rows, [
        camera_from_pose(
            r.image,
            "SIMPLE_PINHOLE",
            (r.focal_px, r.cx, r.cy),
            r.width,
            r.height,
            np.array([r.x, r.y, r.z]),
            Rotation.from_quat([r.qx, r.qy, r.qz, r.qw]).as_matrix(),
        )
        for r in rows.itertuples()
    ]


def test_plan_meets_the_overlaps():
    cfg = load_sim_config(
        "pistachio",
        {"orchard": {"rows": 3, "trees_per_row": 6}, "drone": {"position_jitter_horizontal": 0.0}},
    )
    orchard = generate_orchard(cfg.orchard, np.random.default_rng(0))
    shots = plan_flight(orchard, cfg.drone, np.random.default_rng(0))
    across, along = ground_footprint(cfg.drone)
    lines = sorted({s.line for s in shots})
    assert len(lines) >= 2
    first = [s.view.position[:2] for s in shots if s.line == 0]
    steps = np.linalg.norm(np.diff(first, axis=0), axis=1)
    assert steps == pytest.approx(along * (1 - cfg.drone.forward_overlap), rel=1e-6)
    centre = [
        np.mean([s.view.position[:2] for s in shots if s.line == k], axis=0) for k in lines[:2]
    ]
    assert np.linalg.norm(centre[1] - centre[0]) == pytest.approx(
        across * (1 - cfg.drone.side_overlap), rel=1e-6
    )
    # Every crown is in many photos (forward x side overlap).
    for tree in orchard.trees:
        c = np.asarray(tree.crown.center[:2])
        seen = sum(
            abs(s.view.position[0] - c[0]) < across / 2 - 3
            and abs(s.view.position[1] - c[1]) < along / 2 - 3
            for s in shots
        )
        assert seen >= 4
    # Nadir within the attitude noise.
    tilt = [np.degrees(np.arccos(-s.view.rotation[2, 2])) for s in shots]
    assert max(tilt) < 5 * cfg.drone.attitude_sigma_deg


def test_exif_matches_the_true_gps(small_flight):
    cfg, root, flight = small_flight
    photos = read_flight(root / "drone")
    table = pd.read_csv(root / "truth" / "drone_cameras.csv").set_index("image")
    assert photos.names == list(table.index)
    for im in photos.images:
        row = table.loc[im.name]
        assert im.lat == pytest.approx(row.lat, abs=1e-8) and im.lon == pytest.approx(
            row.lon, abs=1e-8
        )
        assert im.altitude == pytest.approx(row.altitude, abs=1e-3)
        assert im.focal_px == pytest.approx(row.focal_px, rel=1e-5)
        assert (im.width, im.height) == (400, 300)
    # GPS noise as specified (RTK-like by default): a few centimetres off the true centre.
    noise = table[["gps_x", "gps_y"]].to_numpy() - table[["x", "y"]].to_numpy()
    assert 0 < np.abs(noise).max() < 6 * cfg.drone.gps_sigma_horizontal


def test_same_seed_same_bytes(tmp_path):
    cfg = load_sim_config(
        "pistachio",
        {
            "seed": 5,
            "orchard": {"rows": 1, "trees_per_row": 1},
            "drone": {"enabled": True, "image_width": 160, "image_height": 120},
        },
    )
    first = simulate_drone_session(tmp_path / "a", cfg)
    simulate_drone_session(tmp_path / "b", cfg)
    for name in first.cameras["image"]:
        assert (tmp_path / "a" / "drone" / name).read_bytes() == (
            tmp_path / "b" / "drone" / name
        ).read_bytes()
    for name in ("drone_cameras.csv", "trees.csv", "drone_flight.json"):
        assert (tmp_path / "a" / "truth" / name).read_bytes() == (
            tmp_path / "b" / "truth" / name
        ).read_bytes()


def _colour_at(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    u, v = int(uv[0]), int(uv[1])
    return image[v - 1 : v + 2, u - 1 : u + 2].reshape(-1, 3).mean(axis=0)


def test_textures_agree_between_photos_and_crowns_are_green(small_flight):
    cfg, root, _ = small_flight
    rows, cams = _cameras(root)
    images = [np.asarray(Image.open(root / "drone" / c.name)).astype(float) for c in cams]
    orchard = generate_orchard(
        cfg.orchard, np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(7)[0])
    )
    trees = pd.read_csv(root / "truth" / "trees.csv")
    # A bare ground point between the crowns and the headland, seen by several photos.
    rng = np.random.default_rng(0)
    same, other = [], []
    for _ in range(40):
        p = np.array([*rng.uniform(-8, 8, 2) + trees[["x", "y"]].mean().to_numpy() + [0, 12], 0.0])
        p[2] = orchard.terrain.height(p[0], p[1])
        seen = []
        for cam, img in zip(cams, images):
            uv, depth = cam.project(p[None, :])
            if 10 < uv[0, 0] < cam.width - 10 and 10 < uv[0, 1] < cam.height - 10:
                seen.append(_colour_at(img, uv[0]))
        if len(seen) >= 2:
            same.append(np.abs(seen[0] - seen[1]).mean())
            other.append(np.abs(seen[0] - _colour_at(images[0], rng.uniform(20, 280, 2))).mean())
    assert len(same) >= 10
    assert np.median(same) < 0.5 * np.median(other)
    # Crown tops look green, the soil does not.
    greens = []
    for t in trees.itertuples():
        top = np.array([[t.crown_x, t.crown_y, t.z_ground + t.tree_height_m - 0.3]])
        for cam, img in zip(cams, images):
            uv, _ = cam.project(top)
            if 20 < uv[0, 0] < cam.width - 20 and 20 < uv[0, 1] < cam.height - 20:
                u, v = uv[0].astype(int)
                greens.append(excess_green(img[v - 4 : v + 5, u - 4 : u + 5]).mean())
    assert len(greens) >= 4 and np.median(greens) > 0.1
    assert excess_green(images[0]).mean() < np.median(greens)


def test_drone_parameters_are_checked():
    with pytest.raises(ConfigError, match="drone.image_width/image_height"):
        load_sim_config("pistachio", {"drone": {"image_width": 10}})
    with pytest.raises(ConfigError, match="drone.altitude"):
        load_sim_config("pistachio", {"drone": {"altitude": -5.0}})
    with pytest.raises(ConfigError, match=r"drone.forward_overlap: must be in \(0, 1\), got 1.2"):
        load_sim_config("pistachio", {"drone": {"forward_overlap": 1.2}})
