"""Per-photo crown silhouettes for the visual hull (``ground_truth.visual_hull``).

A photo's vegetation is excess green above one Otsu threshold over all the flight's photos
(``crowns.vegetation_images``, as the surface stage uses). Gaps between leaf clusters are not
the crown's outline, so each mask is closed with a disk ``close_m`` wide at the ground (its
radius in pixels from the camera's height above the ground and its focal length) and its
holes filled. The 0.45 m disk was chosen among three tried (0.3, 0.45, 0.6 m) on the
pistachio 4 x 10 nadir flight of seed 1 (docs/GROUND_TRUTH.md, "Oblique flights").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ground_truth.camera import PosedCamera

CLOSE_M = 0.45  # closing disk's width at the ground (m)


def closing_disk(camera: PosedCamera, ground_z: float, close_m: float = CLOSE_M) -> np.ndarray:
    """The closing footprint of ``camera``: a disk ``close_m`` wide at the ground's height
    ``ground_z`` (at least 3 px across)."""
    gsd = max(float(camera.center[2] - ground_z), 1e-6) / camera.focal
    r = max(int(round(close_m / gsd / 2)), 1)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return xx**2 + yy**2 <= r * r


def crown_silhouettes(
    rgbs: Sequence[np.ndarray],
    cameras: Sequence[PosedCamera],
    ground_z: float,
    close_m: float = CLOSE_M,
) -> list[np.ndarray]:
    """Per photo (RGB uint8, the size of its camera's image), a boolean mask of the crowns:
    vegetation closed by a disk ``close_m`` wide at the ground, holes filled."""
    from scipy.ndimage import binary_closing, binary_fill_holes

    from ground_truth.crowns import vegetation_images

    if len(rgbs) != len(cameras):
        raise ValueError(f"{len(rgbs)} photos for {len(cameras)} cameras")
    out = []
    for cam, green in zip(cameras, vegetation_images(list(rgbs)), strict=True):
        disk = closing_disk(cam, ground_z, close_m)
        # border_value=0 with a padded image: a crown cut by the frame is not closed onto it
        pad = disk.shape[0]
        padded = np.pad(green > 0.5, pad)
        closed = binary_closing(padded, disk)[pad:-pad, pad:-pad]
        out.append(binary_fill_holes(closed))
    return out
