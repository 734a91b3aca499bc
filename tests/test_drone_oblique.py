"""Oblique drone flights (issue 51): a double or single grid and orbits with a pitched
camera, photos carrying the gimbal attitude as DJI writes it, checked against the simulator's
true camera poses (truth/drone_cameras.csv) and hand-computed gimbal geometry."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from canopy_kit.core.gimbal import camera_rotation, gimbal_angles
from canopy_kit.errors import ConfigError, InputError
from canopy_kit.sim import load_sim_config
from canopy_kit.sim.drone import ground_footprint, simulate_drone_session
from canopy_kit.sim.session import build_world
from ground_truth.exif import read_flight
from ground_truth.xmp import read_drone_attitude

SMALL = {"orchard": {"rows": 2, "trees_per_row": 3}}
CAMERA = {"image_width": 240, "image_height": 180}  # the default lens: the same field of view


def _config(pattern: str, **drone):
    return load_sim_config(
        "pistachio", {**SMALL, "drone": {"enabled": True, "pattern": pattern, **CAMERA, **drone}}
    )


@pytest.fixture(scope="module", params=["double-grid", "single-grid", "orbit"])
def oblique(request, tmp_path_factory):
    folder = tmp_path_factory.mktemp(request.param)
    config = _config(request.param)
    flight = simulate_drone_session(folder, config)
    return request.param, config, flight, folder


def _true_rotations(cameras: pd.DataFrame) -> np.ndarray:
    return Rotation.from_quat(cameras[["qx", "qy", "qz", "qw"]].to_numpy()).as_matrix()


def test_gimbal_angles_by_hand() -> None:
    down_north = camera_rotation(0.0, -90.0)  # image top to the north, right to the east
    assert np.allclose(down_north[:, 0], [1, 0, 0]) and np.allclose(down_north[:, 1], [0, -1, 0])
    east_level = camera_rotation(90.0, 0.0)  # looking east at the horizon
    assert np.allclose(east_level[:, 2], [1, 0, 0]) and np.allclose(east_level[:, 1], [0, 0, -1])
    rolled = camera_rotation(90.0, 0.0, 10.0)  # right side down
    assert rolled[2, 0] == pytest.approx(-np.sin(np.radians(10.0)))
    rng = np.random.default_rng(3)
    for yaw, pitch, roll in zip(
        rng.uniform(-179, 179, 200), rng.uniform(-89, 0, 200), rng.uniform(-15, 15, 200)
    ):
        back = gimbal_angles(camera_rotation(yaw, pitch, roll))
        assert back == pytest.approx((yaw, pitch, roll), abs=1e-6)


def test_photos_carry_the_true_gimbal_attitude(oblique) -> None:
    pattern, config, flight, folder = oblique
    photos = read_flight(folder / "drone")
    cameras = flight.cameras.set_index("image")
    rotations = dict(zip(cameras.index, _true_rotations(cameras), strict=True))
    for image in photos.images:
        att = image.attitude
        assert att is not None and att.oblique, image.name
        prior = camera_rotation(att.gimbal_yaw_deg, att.gimbal_pitch_deg, att.gimbal_roll_deg)
        truth = rotations[image.name]
        angle = np.degrees(Rotation.from_matrix(prior.T @ truth).magnitude())
        assert angle < 0.05, f"{image.name}: XMP attitude {angle:.3f} deg from the true camera"
        # the plan's pitch, within the attitude noise of the flight (0.8 deg sigma)
        if pattern.endswith("grid"):
            assert att.gimbal_pitch_deg == pytest.approx(config.drone.gimbal_pitch_deg, abs=4.0)
        assert att.relative_altitude_m == pytest.approx(config.drone.altitude, abs=3.0)


def test_centre_rays_land_on_the_orchard(oblique) -> None:
    pattern, config, flight, folder = oblique
    orchard, *_ = build_world(config)
    cameras = flight.cameras
    centres = cameras[["x", "y", "z"]].to_numpy()
    forward = _true_rotations(cameras)[:, :, 2]
    assert (forward[:, 2] < -0.3).all()  # every photo looks down at the orchard
    ground = np.array([t.base[2] for t in orchard.trees]).mean()
    hit = centres + forward * ((ground - centres[:, 2]) / forward[:, 2])[:, None]
    ac = orchard.to_orchard(hit[:, :2])
    trees = orchard.to_orchard(np.array([t.base[:2] for t in orchard.trees]))
    if pattern == "orbit":  # aimed at its row's line, at mid-crown height: near it on the ground
        rows = np.array(sorted({t.row for t in orchard.trees}))
        across = np.array([np.median(trees[[t.row == r for t in orchard.trees], 1]) for r in rows])
        off = np.abs(ac[:, 1] - across[cameras["line"].to_numpy()])
        assert np.median(off) < 4.0
    # the planned area: the crowns plus area_margin, overshot by at most half a line or
    # station spacing (lines are centred on it), plus the flight's position noise
    spacing = max(ground_footprint(config.drone)) * (1 - min(config.drone.side_overlap, 0.75))
    margin = config.drone.area_margin + 2.0 + spacing / 2 + 1.0
    lo, hi = trees.min(axis=0) - margin, trees.max(axis=0) + margin
    assert ((ac >= lo) & (ac <= hi)).all(axis=1).mean() > 0.95


def test_every_planned_heading_is_flown(oblique) -> None:
    pattern, config, flight, _ = oblique
    yaws = np.array([gimbal_angles(r)[0] for r in _true_rotations(flight.cameras)])
    orchard, *_ = build_world(config)
    along = np.degrees(np.arctan2(*orchard.row_direction[:2]))
    relative = (yaws - along + 180.0) % 360.0 - 180.0
    quadrants = {int(((r + 45.0) % 360.0) // 90.0) for r in relative}
    flown = {0, 2} if pattern == "single-grid" else {0, 1, 2, 3}  # along the rows, both ways
    assert quadrants == flown, f"{pattern}: camera headings {sorted(quadrants)}"
    summary = flight.summary
    assert summary["pattern"] == pattern and summary["flight_time_s"] > 0
    speed = config.drone.flight_speed
    path = np.linalg.norm(np.diff(flight.cameras[["x", "y"]].to_numpy(), axis=0), axis=1).sum()
    assert summary["flight_time_s"] >= path / speed  # cruise at most at the set speed


def test_nadir_photos_say_they_look_down(tmp_path) -> None:
    flight = simulate_drone_session(tmp_path, _config("nadir"))
    for image in read_flight(tmp_path / "drone").images:
        assert image.attitude is not None and not image.attitude.oblique
        assert image.attitude.gimbal_pitch_deg == pytest.approx(-90.0, abs=4.0)
    assert flight.summary["gimbal_pitch_deg"] == -90.0


@pytest.mark.parametrize(
    ("setting", "named"),
    [({"pattern": "spiral"}, "drone.pattern"), ({"gimbal_pitch_deg": -10.0}, "gimbal_pitch_deg")],
)
def test_bad_flight_settings_are_named(setting, named) -> None:
    with pytest.raises(ConfigError, match=named):
        _config(**{"pattern": "double-grid", **setting})


@pytest.mark.parametrize(
    ("xmp", "named"),
    [
        (
            '<x drone-dji:GimbalPitchDegree="down" drone-dji:GimbalYawDegree="+0.00"/>',
            "not a number",
        ),
        ('<x drone-dji:GimbalPitchDegree="-500" drone-dji:GimbalYawDegree="+0.00"/>', "outside"),
    ],
)
def test_a_lying_xmp_tag_is_named_with_the_photo(xmp, named) -> None:
    with pytest.raises(InputError, match=f"IMG_1.jpg: XMP drone-dji:GimbalPitchDegree.*{named}"):
        read_drone_attitude(xmp.encode(), "IMG_1.jpg")


def test_xmp_as_elements_and_without_dji_tags() -> None:
    elements = (
        "<drone-dji:GimbalYawDegree>45.5</drone-dji:GimbalYawDegree>"
        "<drone-dji:GimbalPitchDegree> -60 </drone-dji:GimbalPitchDegree>"
    )
    att = read_drone_attitude(elements, "a.jpg")
    assert (att.gimbal_yaw_deg, att.gimbal_pitch_deg, att.flight_yaw_deg) == (45.5, -60.0, None)
    assert read_drone_attitude(b"<x:xmpmeta><xmp:Rating>0</xmp:Rating></x:xmpmeta>", "b") is None
    assert read_drone_attitude(None, "c.jpg") is None


@pytest.mark.slow
def test_an_oblique_double_grid_finds_every_crown_and_nothing_else(tmp_path) -> None:
    """Structure from motion with pitched photos, then the surface and crowns: every crown
    one-to-one with the simulator's trees, none from the far field the photos also see."""
    import json

    from scipy.spatial import cKDTree

    from canopy_kit.core.geo import LocalFrame
    from ground_truth.pipeline import process_flight

    config = _config("double-grid", image_width=600, image_height=450)
    session = tmp_path / "session"
    simulate_drone_session(session, config)
    trees = pd.read_csv(session / "truth" / "trees.csv")
    frame = LocalFrame.from_dict(
        json.loads((session / "truth" / "frame.json").read_text())["frame"]
    )
    result = process_flight(session / "drone", tmp_path / "out", frame, threads=1)
    report = result.report["sfm"]
    assert report["registered_images"] == report["total_images"]
    crowns = result.crowns
    centres = trees[["crown_x", "crown_y"]].to_numpy()
    distance, nearest = cKDTree(centres).query(crowns[["x", "y"]].to_numpy())
    assert len(crowns) == len(trees) and len(set(nearest)) == len(trees)
    assert distance.max() < 0.6
    true_diameter = trees["crown_diameter_m"].to_numpy()[nearest]
    diameter = crowns["diameter_max_m"].to_numpy() - true_diameter
    assert np.abs(diameter).mean() < 0.25
