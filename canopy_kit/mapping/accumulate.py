"""Incremental voxel-thinned map: one point per voxel, every per-point attribute kept as is.

The grid is fixed to the map's local frame (not to the data's extent), so adding sweeps
in any grouping gives the same map. The first point to reach a voxel keeps it: a point's
coordinates and attributes are never averaged. Occupied voxels live in a vectorised
open-addressing hash set, so a sweep costs O(points) whatever the map size.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from canopy_kit.cloud import PointCloud
from canopy_kit.errors import InputError

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def voxel_hash(xyz: np.ndarray, size: float) -> np.ndarray:
    """One int64 per point naming its voxel of edge ``size`` (±52 km at 5 cm voxels)."""
    keys = np.floor(xyz / size).astype(np.int64) + _OFFSET
    if len(keys) and (keys.min() < 0 or keys.max() > _MASK):
        raise InputError(f"map extends beyond the voxel grid range for voxel size {size} m "
                         f"(±{_OFFSET * size / 1000:.0f} km from the origin)")
    return (keys[:, 0] << (2 * _BITS)) | (keys[:, 1] << _BITS) | keys[:, 2]


_EMPTY = np.int64(-1)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


class VoxelKeySet:
    """A set of non-negative int64 keys with vectorised insert (linear probing, load <= 1/2)."""

    def __init__(self, capacity_bits: int = 16) -> None:
        self._bits = capacity_bits
        self._table = np.full(1 << capacity_bits, _EMPTY, np.int64)
        self.size = 0

    def _slots(self, keys: np.ndarray) -> np.ndarray:
        return ((keys.astype(np.uint64) * _GOLDEN) >> np.uint64(64 - self._bits)).astype(np.int64)

    def insert(self, keys: np.ndarray) -> np.ndarray:
        """Insert unique ``keys``; returns a mask of those that were not in the set before."""
        if 2 * (self.size + len(keys)) > len(self._table):
            self._grow(self.size + len(keys))
        table = self._table
        mask = len(table) - 1
        new = np.zeros(len(keys), bool)
        todo = np.arange(len(keys))
        slot = self._slots(keys)
        while len(todo):
            s = slot[todo]
            k = keys[todo]
            current = table[s]
            found = current == k
            empty = current == _EMPTY
            # Claim empty slots; when two keys race for one slot, one wins and the other probes on.
            table[s[empty]] = k[empty]
            won = empty.copy()
            won[empty] = table[s[empty]] == k[empty]
            new[todo[won]] = True
            done = found | won
            slot[todo[~done]] = (s[~done] + 1) & mask
            todo = todo[~done]
        self.size += int(new.sum())
        return new

    def _grow(self, need: int) -> None:
        old = self._table[self._table != _EMPTY]
        while (1 << self._bits) < 2 * need:
            self._bits += 1
        self._table = np.full(1 << self._bits, _EMPTY, np.int64)
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
        keys = voxel_hash(xyz, self.voxel_size)
        first = np.flatnonzero(~pd.Series(keys).duplicated(keep="first").to_numpy())  # hashed: 2x np.unique
        take = first[self._keys.insert(keys[first])]
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
        layouts = {tuple((k, np.asarray(v).dtype.str) for k, v in fields.items()) for _, fields in parts}
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
        fields = {k: (np.concatenate(v) if v else np.zeros(0, self._dtypes[k]))
                  for k, v in self._fields.items()}
        return PointCloud(xyz, fields, crs=crs, origin=np.zeros(3) if origin is None else origin)
