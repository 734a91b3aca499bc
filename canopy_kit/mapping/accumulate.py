"""Incremental voxel-thinned map: one point per voxel, every per-point attribute kept as is.

The grid is fixed to the map's local frame (not to the data's extent), so adding sweeps
in any grouping gives the same map. The first point to reach a voxel keeps it: a point's
coordinates and attributes are never averaged. Occupied voxels live in an open-addressing
hash set with a compiled insert (:mod:`.kernels`), so a sweep costs O(points) whatever the
map size.
"""

from __future__ import annotations

import numpy as np

from canopy_kit.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.mapping.kernels import EMPTY, insert_keys, voxel_keys

_BITS = 21
_OFFSET = 1 << (_BITS - 1)


def voxel_hash(xyz: np.ndarray, size: float) -> np.ndarray:
    """One int64 per point naming its voxel of edge ``size`` (±52 km at 5 cm voxels)."""
    keys, fits = voxel_keys(
        np.ascontiguousarray(xyz, np.float64).reshape(-1, 3), float(size), _BITS
    )
    if not fits:
        raise InputError(
            f"map extends beyond the voxel grid range for voxel size {size} m "
            f"(±{_OFFSET * size / 1000:.0f} km from the origin)"
        )
    return keys


class VoxelKeySet:
    """A set of non-negative int64 keys with compiled in-order insert (linear probing, load <= 1/2)."""

    def __init__(self, capacity_bits: int = 16) -> None:
        self._bits = capacity_bits
        self._table = np.full(1 << capacity_bits, EMPTY, np.int64)
        self.size = 0

    def insert(self, keys: np.ndarray) -> np.ndarray:
        """Insert ``keys``; True where a key was not in the set before (a key repeated
        within ``keys`` counts at its first occurrence only)."""
        keys = np.ascontiguousarray(keys, np.int64)
        if 2 * (self.size + len(keys)) > len(self._table):
            self._grow(self.size + len(keys))
        new = insert_keys(keys, self._table, self._bits)
        self.size += int(np.count_nonzero(new))
        return new

    def _grow(self, need: int) -> None:
        old = self._table[self._table != EMPTY]
        while (1 << self._bits) < 2 * need:
            self._bits += 1
        self._table = np.full(1 << self._bits, EMPTY, np.int64)
        self.size = 0
        self.insert(old)


class MapAccumulator:
    """Accumulates registered points into a voxel-thinned :class:`PointCloud`."""

    def __init__(self, voxel_size: float) -> None:
        if not voxel_size > 0:
            raise InputError(f"mapping.map_voxel_size must be positive, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self._keys = VoxelKeySet()
        self._xyz: list[np.ndarray] = []
        self._fields: dict[str, list[np.ndarray]] = {}
        self._dtypes: dict[str, np.dtype] = {}
        self.n_points = 0
        self.n_offered = 0

    def add(self, xyz: np.ndarray, fields: dict[str, np.ndarray]) -> np.ndarray:
        """Add points (local frame); returns the indices of those that took a new voxel."""
        self.n_offered += len(xyz)
        if len(xyz) == 0:
            return np.zeros(0, np.int64)
        take = np.flatnonzero(self._keys.insert(voxel_hash(xyz, self.voxel_size)))
        if len(take) == 0:
            return take
        if not self._dtypes:
            self._dtypes = {k: np.asarray(v).dtype for k, v in fields.items()}
            self._fields = {k: [] for k in fields}
        for name, dtype in self._dtypes.items():
            values = fields.get(name)
            if values is None:  # a field missing in this sweep: zeros keep the columns aligned
                self._fields[name].append(np.zeros(len(take), dtype))
            else:
                self._fields[name].append(np.asarray(values)[take].astype(dtype, copy=False))
        self._xyz.append(np.asarray(xyz, np.float64)[take])
        self.n_points += len(take)
        return take

    def add_many(self, parts: list[tuple[np.ndarray, dict[str, np.ndarray]]]) -> None:
        """Add several sweeps in order, as one :meth:`add` when their fields agree (cheaper)."""
        layouts = {
            tuple((k, np.asarray(v).dtype.str) for k, v in fields.items()) for _, fields in parts
        }
        if len(parts) > 1 and len(layouts) == 1:
            xyz = np.concatenate([p[0] for p in parts])
            names = list(parts[0][1])
            self.add(xyz, {k: np.concatenate([p[1][k] for p in parts]) for k in names})
        else:
            for xyz, fields in parts:
                self.add(xyz, fields)

    def cloud(self, crs: str | None = None, origin: np.ndarray | None = None) -> PointCloud:
        """The map so far as a PointCloud (local coordinates, ``origin`` and ``crs`` attached)."""
        xyz = np.concatenate(self._xyz) if self._xyz else np.zeros((0, 3))
        fields = {
            k: (np.concatenate(v) if v else np.zeros(0, self._dtypes[k]))
            for k, v in self._fields.items()
        }
        return PointCloud(xyz, fields, crs=crs, origin=np.zeros(3) if origin is None else origin)
