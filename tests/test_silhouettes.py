"""Crown silhouettes for the visual hull (``ground_truth.silhouettes``) on a drawn photo whose
crowns are discs of known size: gaps between leaf clusters are closed, a gap between crowns
wider than the closing disk is kept, and a crown cut by the photo's edge keeps its pixels
there."""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.core.gimbal import camera_rotation
from ground_truth.camera import camera_from_pose
from ground_truth.silhouettes import closing_disk, crown_silhouettes

HEIGHT_M, FOCAL = 40.0, 400.0  # 0.1 m per pixel at the ground
GREEN, SOIL = (60, 150, 50), (150, 115, 85)


def _camera(width: int = 300, height: int = 200):
    return camera_from_pose(
        "p", "SIMPLE_PINHOLE", (FOCAL, width / 2, height / 2), width, height,
        np.array([0.0, 0.0, HEIGHT_M]), camera_rotation(0.0, -90.0),
    )  # fmt: skip


def _photo(discs: list[tuple[float, float, float]], gaps: bool = True) -> np.ndarray:
    """Soil with green discs (column, row, radius in px), speckled with 1-2 px gaps of soil."""
    v, u = np.mgrid[0:200, 0:300]
    rgb = np.empty((200, 300, 3), np.uint8)
    rgb[:] = SOIL
    for c, r, radius in discs:
        rgb[np.hypot(u - c, v - r) <= radius] = GREEN
    if gaps:  # holes through the foliage, 0.1-0.2 m: narrower than the 0.45 m closing
        rng = np.random.default_rng(0)
        for c, r in rng.integers(0, (300, 200), (600, 2)):
            rgb[r : r + 2, c : c + 2] = SOIL
    return rgb


def _disc(c: float, r: float, radius: float) -> np.ndarray:
    v, u = np.mgrid[0:200, 0:300]
    return np.hypot(u - c, v - r) <= radius


def test_the_closing_disk_is_045_m_at_the_ground() -> None:
    disk = closing_disk(_camera(), 0.0)
    assert disk.shape == (5, 5)  # 0.45 m / 0.1 m per px: radius 2 px
    assert closing_disk(_camera(), 20.0).shape == (9, 9)  # ground 20 m up: 0.05 m per px


def test_gaps_in_a_crown_close_and_crowns_stay_apart() -> None:
    # two crowns of 2.5 m radius, 1 m apart edge to edge (wider than the 0.45 m disk)
    discs = [(100.0, 100.0, 25.0), (160.0, 100.0, 25.0)]
    (mask,) = crown_silhouettes([_photo(discs)], [_camera()], ground_z=0.0)
    truth = _disc(*discs[0]) | _disc(*discs[1])
    assert mask.dtype == bool and mask.shape == truth.shape
    assert (mask & truth).sum() / truth.sum() > 0.995  # the leaf gaps are filled
    assert (mask & ~truth).sum() < 0.02 * truth.sum()  # soil stays soil
    from scipy.ndimage import label

    assert label(mask)[1] == 2
    assert not mask[100, 128:132].any()  # the gap between them


def test_a_crown_cut_by_the_photo_edge_keeps_its_pixels_there() -> None:
    discs = [(5.0, 100.0, 25.0)]  # centred 0.5 m inside the left edge
    (mask,) = crown_silhouettes([_photo(discs, gaps=False)], [_camera()], ground_z=0.0)
    truth = _disc(*discs[0])
    assert np.array_equal(mask[:, :3], truth[:, :3])
    assert mask.sum() == pytest.approx(truth.sum(), rel=0.01)


def test_photos_and_cameras_must_pair() -> None:
    with pytest.raises(ValueError, match="2 photos for 1 cameras"):
        crown_silhouettes([_photo([]), _photo([])], [_camera()], 0.0)
