"""The compass heading and the oblique threshold of canopy_kit.core.gimbal, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.core.gimbal import camera_rotation, compass_heading_deg, gimbal_angles, is_oblique
from ground_truth.camera import PosedCamera
from ground_truth.pipeline import looked_at_area
from ground_truth.xmp import read_drone_attitude


@pytest.mark.parametrize(
    ("east", "north", "heading"),
    [(0, 1, 0.0), (1, 0, 90.0), (0, -1, 180.0), (-1, 0, -90.0), (1, 1, 45.0), (-3, -3, -135.0)],
)
def test_compass_heading_by_hand(east: float, north: float, heading: float) -> None:
    assert compass_heading_deg(np.array([east, north])) == pytest.approx(heading)


def test_compass_heading_is_the_yaw_a_camera_looks_along() -> None:
    # a camera pitched down at 30 degrees looks along its yaw: its viewing direction's heading
    for yaw in (-170.0, -45.0, 0.0, 30.0, 120.0):
        forward = camera_rotation(yaw, -30.0)[:, 2]
        assert compass_heading_deg(forward[:2]) == pytest.approx(yaw)
        assert gimbal_angles(camera_rotation(yaw, -30.0))[0] == pytest.approx(yaw)


def _dji_xmp(pitch: float) -> str:
    return (
        f'<rdf:Description drone-dji:GimbalYawDegree="30" drone-dji:GimbalPitchDegree="{pitch}"/>'
    )


def _camera(yaw: float, pitch: float, centre: tuple[float, float, float]) -> PosedCamera:
    to_world = camera_rotation(yaw, pitch)
    return PosedCamera(
        "p.jpg", "PINHOLE", (500.0, 500.0, 320.0, 240.0), 640, 480,
        to_world.T, -to_world.T @ np.asarray(centre, float),
    )  # fmt: skip


@pytest.mark.parametrize(
    ("pitch", "oblique"),
    [(-90.0, False), (-80.0, False), (-75.5, False), (-74.5, True), (-60, True)],
)
def test_one_oblique_threshold_for_the_xmp_and_the_aimed_area(pitch: float, oblique: bool) -> None:
    """The photo's XMP attitude and the ground-truth pipeline's area cut agree on which
    photos are oblique: more than 15 degrees off straight down."""
    assert is_oblique(pitch) is oblique
    attitude = read_drone_attitude(_dji_xmp(pitch), "p.jpg")
    assert attitude is not None and attitude.oblique is oblique
    cameras = [_camera(30.0, pitch, (x, 0.0, 40.0)) for x in (0.0, 10.0, 20.0)]
    area = looked_at_area(cameras, ground_z=0.0)
    assert (area is not None) is oblique
    if oblique:  # the centre ray meets the ground 40 / tan(-pitch) ahead, along the yaw
        reach = 40.0 / np.tan(np.radians(-pitch))
        ahead = reach * np.array([np.sin(np.radians(30.0)), np.cos(np.radians(30.0))])
        assert area[0] == pytest.approx(np.array([0.0, 0.0]) + ahead - 2.0)
        assert area[1] == pytest.approx(np.array([20.0, 0.0]) + ahead + 2.0)
