"""The compass heading and the oblique threshold of canopy_kit.core.gimbal, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.core.gimbal import camera_rotation, compass_heading_deg, gimbal_angles


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
