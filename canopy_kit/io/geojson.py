"""RFC 7946 GeoJSON: WGS84 longitude/latitude FeatureCollections, full precision.

No ``crs`` member (RFC 7946 §4: WGS84 only); positions are ``[lon, lat]`` or
``[lon, lat, height]``; polygon rings are closed and their exterior counter-clockwise
(§3.1.6); the run's provenance is the collection's foreign member ``provenance`` (§6.1).
Floats are written as Python's shortest round-trip repr, so no digit is lost.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from canopy_kit.core.atomic import json_default


def _finite(value: Any) -> Any:
    """JSON has no NaN: a missing number is null."""
    if isinstance(value, float | np.floating) and not math.isfinite(value):
        return None
    return value


def feature(geometry: dict[str, Any], properties: dict[str, Any]) -> dict[str, Any]:
    """One Feature; NaN properties become null."""
    return {
        "type": "Feature",
        "geometry": geometry,
        "properties": {k: _finite(v) for k, v in properties.items()},
    }


def point(lon: float, lat: float, height: float | None = None) -> dict[str, Any]:
    """A Point geometry at ``lon``, ``lat`` (and ``height`` above the ellipsoid)."""
    coords = [float(lon), float(lat)] + ([] if height is None else [float(height)])
    return {"type": "Point", "coordinates": coords}


def polygon(lon: np.ndarray, lat: np.ndarray) -> dict[str, Any]:
    """A Polygon from one ring of vertices (open or closed): closed, counter-clockwise."""
    ring = np.column_stack([lon, lat]).astype(float)
    if len(ring) and np.array_equal(ring[0], ring[-1]):
        ring = ring[:-1]
    x, y = ring[:, 0], ring[:, 1]
    if np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) < 0:  # shoelace: clockwise
        ring = ring[::-1]
    ring = np.vstack([ring, ring[:1]])
    return {"type": "Polygon", "coordinates": [ring.tolist()]}


def line_string(lon: np.ndarray, lat: np.ndarray) -> dict[str, Any]:
    """A LineString through ``lon``, ``lat`` in order."""
    return {"type": "LineString", "coordinates": np.column_stack([lon, lat]).astype(float).tolist()}


def feature_collection(
    features: list[dict[str, Any]], provenance: dict[str, Any] | None = None
) -> str:
    """The FeatureCollection as text, with ``provenance`` as a foreign member."""
    data: dict[str, Any] = {"type": "FeatureCollection", "features": features}
    if provenance:
        data["provenance"] = dict(provenance)
    return json.dumps(data, indent=1, default=json_default, allow_nan=False) + "\n"
