"""How much of each tree's crown touches another tree's: where crowns interweave, where the
segmentation draws the border between them is a guess, and so is each one's volume.

A tree's **contact** is the share of its canopy (thinned to one point per ``CELL_M`` voxel)
that lies within ``REACH_M`` of a point of another tree. Free-standing crowns have none; a
crown cut from an interwoven almond row, a tenth or more. Measured on simulated almond runs
(2 × 6 trees, `benchmarks/bench_interval_runs.py`, docs/VOLUMES.md "Touching crowns"):
trees with contact up to 0.03 held their volume interval 33 of 33 times, between 0.03 and
0.08 41 of 46, at or above ``TOUCHING_CONTACT`` (0.08, chosen on seeds 8101-8106) 26 of 50
(14 of 29 on the held-out seeds 8107-8112): the segmentation's border, not the drive, sets
their error; their interval is widened for it (``volume.interwoven``).
"""

from __future__ import annotations

import numpy as np

from canopy_kit.core.voxel import linear_keys, voxel_keys

CELL_M = 0.15  # canopy thinned to one point per voxel of this size (a map's density apart)
REACH_M = 0.3  # a point this close to another tree's touches it (two cells)
TOUCHING_CONTACT = 0.08  # at or above: the tree's border with its neighbours is uncertain


def crown_contact(xyz: np.ndarray, labels: np.ndarray) -> dict[int, float]:
    """Per tree label (``labels`` >= 0, one per point of ``xyz``): the share of its voxel-thinned
    points within ``REACH_M`` of another label's points (0 for a tree alone)."""
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, dtype=np.float64)
    labels = np.asarray(labels)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(labels) != len(xyz):
        raise ValueError(
            f"crown_contact: xyz must be (N, 3) with one label per point, got {xyz.shape} "
            f"and {labels.shape}"
        )
    trees = np.flatnonzero(labels >= 0)
    if len(trees) == 0:
        return {}
    cells = voxel_keys(xyz[trees], CELL_M, origin=np.zeros(3))  # a grid fixed to the frame
    _, first = np.unique(linear_keys(cells - cells.min(axis=0)), return_index=True)
    points, owner = xyz[trees[first]], labels[trees[first]]
    pairs = cKDTree(points).query_pairs(REACH_M, output_type="ndarray")
    across = pairs[owner[pairs[:, 0]] != owner[pairs[:, 1]]]
    touching = np.zeros(len(points), bool)
    touching[across.ravel()] = True
    ids, inverse = np.unique(owner, return_inverse=True)
    share = np.bincount(inverse, weights=touching) / np.bincount(inverse)
    return {int(i): float(s) for i, s in zip(ids, share, strict=True)}
