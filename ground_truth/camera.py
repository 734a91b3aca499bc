"""Posed cameras as plain arrays: projection of world points into images (no pycolmap needed).

Conventions follow COLMAP: camera x right, y down, z forward; pixel centres at
``i + 0.5``; ``rotation``/``translation`` map world to camera (``x_cam = R X + t``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.errors import InputError

# Parameter layouts of the camera models supported here (COLMAP names).
MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
}


@dataclass(frozen=True)
class PosedCamera:
    """One registered image: intrinsics (COLMAP model and parameters) and world-to-camera pose."""

    name: str
    model: str
    params: tuple[float, ...]
    width: int
    height: int
    rotation: np.ndarray  # (3, 3) world to camera
    translation: np.ndarray  # (3,)

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise InputError(
                f"camera {self.name}: model {self.model} is not one of {', '.join(MODELS)}"
            )

    @property
    def center(self) -> np.ndarray:
        """Projection centre in world coordinates."""
        return -self.rotation.T @ self.translation

    @property
    def focal(self) -> float:
        """Mean focal length in pixels."""
        p = self.params
        return float((p[0] + p[1]) / 2 if self.model == "PINHOLE" else p[0])

    def intrinsics(self) -> tuple[float, float, float, float, float, float]:
        """(fx, fy, cx, cy, k1, k2) of the model (zeros for absent distortion terms)."""
        p = self.params
        if self.model == "SIMPLE_PINHOLE":
            return p[0], p[0], p[1], p[2], 0.0, 0.0
        if self.model == "PINHOLE":
            return p[0], p[1], p[2], p[3], 0.0, 0.0
        if self.model == "SIMPLE_RADIAL":
            return p[0], p[0], p[1], p[2], p[3], 0.0
        return p[0], p[0], p[1], p[2], p[3], p[4]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) of world points (N, 3) and their depth along the view axis."""
        pts = np.asarray(points, dtype=np.float64)
        cam = pts @ self.rotation.T + self.translation
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = cam[:, 0] / depth, cam[:, 1] / depth
        fx, fy, cx, cy, k1, k2 = self.intrinsics()
        if k1 or k2:
            r2 = x * x + y * y
            d = 1.0 + k1 * r2 + k2 * r2 * r2
            x, y = x * d, y * d
        return np.column_stack([fx * x + cx, fy * y + cy]), depth

    def scaled(self, factor: float) -> PosedCamera:
        """The same camera for the image resized by ``factor`` (e.g. 0.5 for half size)."""
        p = list(self.params)
        n_lin = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 3, "RADIAL": 3}[self.model]
        p[:n_lin] = [v * factor for v in p[:n_lin]]
        return PosedCamera(
            self.name,
            self.model,
            tuple(p),
            round(self.width * factor),
            round(self.height * factor),
            self.rotation,
            self.translation,
        )


def camera_from_pose(
    name: str,
    model: str,
    params: tuple[float, ...],
    width: int,
    height: int,
    center: np.ndarray,
    cam_to_world: np.ndarray,
) -> PosedCamera:
    """A camera from its centre and camera-to-world rotation (as the simulator stores them)."""
    r = np.asarray(cam_to_world, float).T
    return PosedCamera(
        name,
        model,
        tuple(float(v) for v in params),
        int(width),
        int(height),
        r,
        -r @ np.asarray(center, float),
    )
