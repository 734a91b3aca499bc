"""A camera's attitude as a drone's gimbal reports it, and back (DJI's XMP convention).

DJI drones write the gimbal's attitude into each photo's XMP as ``GimbalYawDegree`` (the
heading the camera looks along, degrees clockwise from north), ``GimbalPitchDegree`` (-90:
straight down, 0: at the horizon) and ``GimbalRollDegree`` (positive: the image's right side
down). Camera rotations here follow COLMAP (x right, y down, z along the viewing direction;
the matrix maps camera to world, world x east, y north, z up). With yaw ψ, pitch θ and
roll 0 the viewing direction is ``(sin ψ cos θ, cos ψ cos θ, sin θ)`` and the image's right
``(cos ψ, -sin ψ, 0)``: looking straight down, the top of the image points along ψ.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# A photo pitched above this (degrees; -90 looks straight down) is oblique: it sees the
# crowns' sides and ground far ahead at grazing angles. 15 degrees off nadir: a nadir mapping
# flight's gimbal holds -90 within a few degrees, a planned oblique flight pitches to -45..-70.
OBLIQUE_PITCH_DEG = -75.0


def is_oblique(pitch_deg: float) -> bool:
    """Whether a camera pitched ``pitch_deg`` (-90: straight down) looks obliquely."""
    return pitch_deg > OBLIQUE_PITCH_DEG


def compass_heading_deg(direction_xy: np.ndarray) -> float:
    """Compass heading (degrees clockwise from north, in [-180, 180]) of a local
    (east, north) direction."""
    return float(np.degrees(np.arctan2(direction_xy[0], direction_xy[1])))


def camera_rotation(yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """The camera-to-world rotation (3x3) of gimbal angles (degrees)."""
    psi, theta = np.radians(yaw_deg), np.radians(pitch_deg)
    forward = np.array([np.sin(psi) * np.cos(theta), np.cos(psi) * np.cos(theta), np.sin(theta)])
    right = np.array([np.cos(psi), -np.sin(psi), 0.0])
    up = np.cross(right, forward)
    level = np.column_stack([right, -up, forward])
    # roll about the viewing direction: positive turns the image's right side down
    return level @ Rotation.from_rotvec([0.0, 0.0, np.radians(roll_deg)]).as_matrix()


def gimbal_angles(rotation: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in degrees of a camera-to-world rotation; yaw in (-180, 180]."""
    rotation = np.asarray(rotation, float)
    forward = rotation[:, 2]
    pitch = float(np.degrees(np.arcsin(np.clip(forward[2], -1.0, 1.0))))
    # the heading of the viewing direction; looking straight down, of the image's top (the
    # roll is then part of the yaw, and reported as 0)
    heading = forward if np.hypot(forward[0], forward[1]) > 1e-6 else -rotation[:, 1]
    yaw = compass_heading_deg(heading)
    level = camera_rotation(yaw, pitch, 0.0)
    # what is left is a turn about the viewing direction: the roll
    rest = level.T @ rotation
    roll = float(np.degrees(np.arctan2(rest[1, 0], rest[0, 0])))
    return yaw if yaw > -180.0 else 180.0, pitch, roll
