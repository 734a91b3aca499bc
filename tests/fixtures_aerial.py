"""Helpers for the drone ground-truth tests: synthetic photos and aerial results."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd

NADIR = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # camera x east, y south, z down


def two_photos_of_a_block(height: float) -> tuple[list, list[np.ndarray]]:
    """Two nadir photos (30 m up, 8 m apart) of textured flat ground with a 6 × 6 m block
    ``height`` metres tall at the origin: their cameras and grey images."""
    from canopy_kit.sim.drone_render import PinholeView, fbm2
    from ground_truth.camera import camera_from_pose

    cams, images = [], []
    for k, cx in enumerate((-4.0, 4.0)):
        view = PinholeView(np.array([cx, 0.0, 30.0]), NADIR, 400.0, 300, 300)
        d = view.ray_directions().reshape(-1, 3)
        t_top = (height - 30.0) / d[:, 2]
        p = view.position + d * t_top[:, None]
        on_block = (np.abs(p[:, 0]) < 3) & (np.abs(p[:, 1]) < 3)
        t = np.where(on_block, t_top, (0.0 - 30.0) / d[:, 2])
        p = view.position + d * t[:, None]
        images.append(fbm2(p[:, 0], p[:, 1], 0.6, 3, 5).reshape(300, 300).astype(np.float32))
        cams.append(
            camera_from_pose(
                f"c{k}", "SIMPLE_PINHOLE", (400.0, 150.0, 150.0), 300, 300, view.position, NADIR
            )
        )
    return cams, images


def aerial_result(diameters: list[float] | np.ndarray) -> SimpleNamespace:
    """An aerial result whose crowns, one per segment 0.., all matched, have these diameters
    (sphere volumes from them, no ellipsoid or CHM volume)."""
    d = np.asarray(diameters, float)
    trees = pd.DataFrame(
        {
            "segment": np.arange(len(d)),
            "matched": True,
            "aerial_diameter_max_m": d,
            "aerial_diameter_mean_m": d,
            "aerial_sphere_volume_m3": np.pi * d**3 / 6,
            "aerial_ellipsoid_volume_m3": np.nan,
            "aerial_chm_volume_m3": np.nan,
            "aerial_height_m": 4.0,
            "aerial_distance_m": 0.2,
        }
    )
    return SimpleNamespace(trees=trees)
