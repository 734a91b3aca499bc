"""Occupied-voxel volume, optionally with the holes of each horizontal slice filled.

Counting occupied voxels measures where points are, so a LiDAR crown seen only on its
shell gives a shell; filling the enclosed holes of every horizontal layer
(``scipy.ndimage.binary_fill_holes``) turns closed rings into discs. Rings with gaps (the
unseen side of a one-sided scan) stay open: this estimator is a lower bound there.
"""

from __future__ import annotations

import numpy as np

from canopy_kit.plugins.params import Positive
from canopy_kit.volume.base import VolumeEstimator

MAX_VOXELS = 50_000_000


def occupancy_grid(xyz: np.ndarray, voxel_size: float) -> np.ndarray:
    """Boolean (nx, ny, nz) grid of the voxels of edge ``voxel_size`` that hold a point."""
    ijk = np.floor((xyz - xyz.min(axis=0)) / voxel_size).astype(np.intp)
    grid = np.zeros(tuple(ijk.max(axis=0) + 1), bool)
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return grid


def fill_slice_holes(grid: np.ndarray) -> np.ndarray:
    """Each horizontal layer (last axis) with its enclosed holes filled."""
    from scipy import ndimage

    filled = np.empty_like(grid)
    for k in range(grid.shape[2]):
        filled[:, :, k] = ndimage.binary_fill_holes(grid[:, :, k])
    return filled


class VoxelVolume(VolumeEstimator):
    """Number of occupied voxels × voxel volume; ``fill_holes`` fills each horizontal layer.

    Parameters
    ----------
    voxel_size : float, default 0.1
        Voxel edge in metres.
    fill_holes : bool, default True
        Fill the enclosed holes of every horizontal layer of voxels (closed rings become
        discs).
    """

    name = "voxel"
    measures = (
        "occupied voxels of the given size, enclosed holes of each layer filled: where "
        "returns are, a lower bound of the crown"
    )

    def __init__(self, voxel_size: Positive = 0.1, fill_holes: bool = True) -> None:
        self.voxel_size = voxel_size
        self.fill_holes = fill_holes

    def _volume(self, xyz: np.ndarray) -> float | tuple[float, dict]:
        size = float(self.voxel_size)
        cells = np.prod(np.floor(np.ptp(xyz, axis=0) / size) + 1)
        if cells > MAX_VOXELS:
            return 0.0, {
                "reason": f"voxel_size = {size} m makes {cells:.3g} voxels for this "
                f"extent (limit {MAX_VOXELS:.0e}); use a larger voxel_size"
            }
        grid = occupancy_grid(xyz, size)
        occupied = int(grid.sum())
        if self.fill_holes:
            grid = fill_slice_holes(grid)
        n = int(grid.sum())
        return n * size**3, {"occupied_voxels": occupied, "filled_voxels": n - occupied}
