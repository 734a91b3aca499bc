"""Local metric frames: UTM coordinates relative to a stored origin, and WGS84 conversions."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from canopy_kit.errors import InputError


def utm_epsg(lat: float, lon: float) -> int:
    """EPSG code of the WGS84 UTM zone containing (lat, lon)."""
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise InputError(f"latitude/longitude out of range: ({lat}, {lon})")
    zone = int((lon + 180) // 6) % 60 + 1
    return (32600 if lat >= 0 else 32700) + zone


@dataclass(frozen=True)
class LocalFrame:
    """A local frame: x east, y north, z up in metres, as UTM minus ``origin``."""

    epsg: int
    origin_easting: float
    origin_northing: float
    origin_height: float = 0.0

    @classmethod
    def at(cls, lat: float, lon: float, height: float = 0.0) -> LocalFrame:
        """The UTM-based frame whose origin is at (lat, lon, height)."""
        epsg = utm_epsg(lat, lon)
        e, n = _transformer(epsg, inverse=False).transform(lon, lat)
        return cls(epsg, float(e), float(n), float(height))

    @property
    def crs(self) -> str:
        return f"EPSG:{self.epsg}"

    @property
    def origin(self) -> np.ndarray:
        return np.array([self.origin_easting, self.origin_northing, self.origin_height])

    @cached_property
    def _forward(self):
        return _transformer(self.epsg, inverse=False)

    @cached_property
    def _inverse(self):
        return _transformer(self.epsg, inverse=True)

    def to_local(
        self, lat: np.ndarray, lon: np.ndarray, height: np.ndarray | float = 0.0
    ) -> np.ndarray:
        """WGS84 latitude, longitude (degrees) and height to local (N, 3) coordinates."""
        e, n = self._forward.transform(np.asarray(lon, float), np.asarray(lat, float))
        h = np.broadcast_to(np.asarray(height, float), np.shape(e))
        return np.column_stack(
            [
                np.ravel(e) - self.origin_easting,
                np.ravel(n) - self.origin_northing,
                np.ravel(h) - self.origin_height,
            ]
        )

    def to_wgs84(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local (N, 3) or (N, 2) coordinates to latitude, longitude and height."""
        xyz = np.atleast_2d(np.asarray(xyz, float))
        lon, lat = self._inverse.transform(
            xyz[:, 0] + self.origin_easting, xyz[:, 1] + self.origin_northing
        )
        h = (
            xyz[:, 2] + self.origin_height
            if xyz.shape[1] > 2
            else np.full(len(xyz), self.origin_height)
        )
        return np.asarray(lat), np.asarray(lon), h

    def to_dict(self) -> dict[str, float | int | str]:
        return {
            "crs": self.crs,
            "epsg": self.epsg,
            "origin_easting": self.origin_easting,
            "origin_northing": self.origin_northing,
            "origin_height": self.origin_height,
        }

    @classmethod
    def from_dict(cls, data: dict) -> LocalFrame:
        try:
            return cls(
                int(data["epsg"]),
                float(data["origin_easting"]),
                float(data["origin_northing"]),
                float(data.get("origin_height", 0.0)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"local frame description is incomplete or malformed: {exc}") from None


def _transformer(epsg: int, inverse: bool):
    from pyproj import Transformer

    if inverse:
        return Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)
    return Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)


def lonlat_of(xy: np.ndarray, crs: str, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Longitude and latitude (WGS84 degrees) of local map points ``xy`` (N, 2+): the map's
    projected ``crs`` coordinates are ``xy + origin``."""
    xy = np.atleast_2d(np.asarray(xy, float))
    lon, lat = _crs_transformer(crs, inverse=True).transform(
        xy[:, 0] + origin[0], xy[:, 1] + origin[1]
    )
    return np.asarray(lon, float), np.asarray(lat, float)


def local_of(lon: np.ndarray, lat: np.ndarray, crs: str, origin: np.ndarray) -> np.ndarray:
    """Local map (N, 2) coordinates of WGS84 ``lon``, ``lat``: the inverse of :func:`lonlat_of`."""
    e, n = _crs_transformer(crs, inverse=False).transform(
        np.asarray(lon, float), np.asarray(lat, float)
    )
    return np.column_stack([np.ravel(e) - origin[0], np.ravel(n) - origin[1]])


@lru_cache(maxsize=16)
def _crs_transformer(crs: str, inverse: bool):
    from pyproj import CRS, Transformer
    from pyproj.exceptions import CRSError

    try:
        projected = CRS.from_user_input(crs)
    except CRSError as exc:
        raise InputError(f"CRS {crs[:60]!r} is not understood by pyproj: {exc}") from None
    if inverse:
        return Transformer.from_crs(projected, "EPSG:4326", always_xy=True)
    return Transformer.from_crs("EPSG:4326", projected, always_xy=True)
