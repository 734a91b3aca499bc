"""The sliding window of the map: voxel-thinned points not yet turned into trees.

Points are thinned as in the batch map (one point per voxel, the first to arrive keeps
it). Finished parts of the orchard are *closed*: their points leave the window and later
points falling there are not kept, so the window holds only the unfinished rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.core.cloud import PointCloud


@dataclass(frozen=True)
class ClosedArea:
    """Points with ``lo < across <= hi`` and ``sigma * along < before`` are finished."""

    lo: float
    hi: float
    sigma: int = 1
    before: float = np.inf

    def contains(self, along: np.ndarray, across: np.ndarray) -> np.ndarray:
        return (across > self.lo) & (across <= self.hi) & (self.sigma * along < self.before)


class PointWindow:
    """Voxel-thinned points in the odometry frame, with every per-point field."""

    def __init__(self, voxel_size: float) -> None:
        from canopy_kit.mapping.accumulate import VoxelKeySet

        self.voxel_size = float(voxel_size)
        self._keys = VoxelKeySet()
        self._chunks: list[PointCloud] = []
        self._merged: PointCloud | None = None
        self.n_points = 0
        self.peak_points = 0
        self.n_offered = 0

    def add(self, points: PointCloud) -> int:
        """Keep the points that reach an empty voxel; returns how many were kept."""
        from canopy_kit.mapping.accumulate import voxel_hash

        self.n_offered += len(points)
        if len(points) == 0:
            return 0
        keys = voxel_hash(points.xyz, self.voxel_size)
        uniq, first = np.unique(keys, return_index=True)
        take = np.sort(first[self._keys.insert(uniq)])
        if len(take):
            self._chunks.append(points.select(take))
            self.n_points += len(take)
            self.peak_points = max(self.peak_points, self.n_points)
        return len(take)

    def cloud(self) -> PointCloud:
        """Every point in the window as one cloud (chunks merged once)."""
        if self._chunks:
            parts = ([self._merged] if self._merged is not None else []) + self._chunks
            self._merged = PointCloud.concatenate(parts) if len(parts) > 1 else parts[0]
            self._chunks = []
        if self._merged is None:
            return PointCloud(np.zeros((0, 3)))
        return self._merged

    def drop(self, mask: np.ndarray) -> None:
        """Remove the points ``mask`` selects (indices of :meth:`cloud`) and free their voxels."""
        from canopy_kit.mapping.accumulate import VoxelKeySet, voxel_hash

        cloud = self.cloud()
        if not np.any(mask):
            return
        self._merged = cloud.select(np.flatnonzero(~mask))
        self.n_points = len(self._merged)
        # A closed area's voxels must not be refilled by the window; they are rejected before
        # they get here, so the key set only needs the points that stay.
        self._keys = VoxelKeySet()
        if self.n_points:
            self._keys.insert(np.unique(voxel_hash(self._merged.xyz, self.voxel_size)))

    @property
    def nbytes(self) -> int:
        """Memory held by the points and their fields."""
        clouds = ([self._merged] if self._merged is not None else []) + self._chunks
        return int(
            sum(c.xyz.nbytes + sum(np.asarray(v).nbytes for v in c.fields.values()) for c in clouds)
        )
