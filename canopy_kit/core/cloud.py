"""The in-memory point cloud every stage passes around."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from canopy_kit.errors import InputError


def column_min(a: np.ndarray) -> np.ndarray:
    """Per-column minimum of an (N, k) array, as ``a.min(axis=0)``: numpy reduces a row-major
    array across its rows about 10x slower than each column on its own (0.19 against 0.014 s
    for 7 M points)."""
    a = np.asarray(a)
    return np.array([a[:, j].min() for j in range(a.shape[1])], dtype=a.dtype)


def column_max(a: np.ndarray) -> np.ndarray:
    """Per-column maximum of an (N, k) array, as ``a.max(axis=0)`` (see :func:`column_min`)."""
    a = np.asarray(a)
    return np.array([a[:, j].max() for j in range(a.shape[1])], dtype=a.dtype)


@dataclass
class PointCloud:
    """Points in float64 with per-point attributes that survive every stage.

    ``xyz`` is in a local metric frame; absolute coordinates are ``xyz + origin`` in ``crs``
    (an ``EPSG:`` code or WKT, ``None`` when unknown).
    """

    xyz: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    crs: str | None = None
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise InputError(f"point coordinates must have shape (N, 3), got {self.xyz.shape}")
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        for name, values in self.fields.items():
            if len(values) != len(self.xyz):
                raise InputError(
                    f"point attribute {name!r} has {len(values)} values for {len(self.xyz)} points"
                )

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def absolute_xyz(self) -> np.ndarray:
        """Coordinates in the CRS (local coordinates plus the origin)."""
        return self.xyz + self.origin

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Minimum and maximum corner of the local coordinates."""
        if len(self) == 0:
            raise InputError("an empty point cloud has no bounds")
        return column_min(self.xyz), column_max(self.xyz)

    def select(self, index: np.ndarray) -> PointCloud:
        """Subset by boolean mask or integer index, attributes included."""
        return PointCloud(
            self.xyz[index],
            {k: v[index] for k, v in self.fields.items()},
            crs=self.crs,
            origin=self.origin.copy(),
        )

    def with_field(self, name: str, values: np.ndarray) -> PointCloud:
        """A copy with one attribute added or replaced."""
        fields = dict(self.fields)
        fields[name] = np.asarray(values)
        return PointCloud(self.xyz, fields, crs=self.crs, origin=self.origin.copy())

    @staticmethod
    def concatenate(clouds: list[PointCloud]) -> PointCloud:
        """Join clouds that share origin and CRS; keeps attributes present in all of them."""
        if not clouds:
            return PointCloud(np.zeros((0, 3)))
        common = set(clouds[0].fields)
        for c in clouds[1:]:
            common &= set(c.fields)
        return PointCloud(
            np.concatenate([c.xyz for c in clouds]),
            {k: np.concatenate([c.fields[k] for c in clouds]) for k in sorted(common)},
            crs=clouds[0].crs,
            origin=clouds[0].origin.copy(),
        )
