"""GeoPackage output and input (geopandas + pyogrio): the run's layers in the projected CRS.

The GeoJSON files are WGS84 by RFC 7946; GIS work in metres wants the map's own projected
CRS (the UTM zone of the drive), which this file keeps: one layer per table (``trees``
points, ``crowns`` polygons, ``rows`` lines), coordinates ``local + origin`` in ``crs``
(no CRS when the map has none: then the local frame). Provenance goes in the dataset's
and every layer's metadata, one string item per key. The file is a GeoPackage 1.2 (GDAL
3.7+ would write 1.4, which GDAL 3.6 and other readers of 1.2/1.3 warn about; nothing here
needs more than 1.2).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import pandas as pd

from canopy_kit.core.atomic import atomic_path
from canopy_kit.errors import InputError

GPKG_VERSION = "1.2"  # the GeoPackage version written: the one every reader knows


def write_gpkg(
    path: str | Path,
    layers: dict[str, tuple[pd.DataFrame, list[Any]]],
    crs: str | None,
    metadata: dict[str, Any] | None = None,
) -> Path:
    """Write ``layers`` (name -> (attributes, shapely geometries)) as one GeoPackage, atomically."""
    import geopandas as gpd
    import pyogrio

    path = Path(path)
    meta = {str(k): str(v) for k, v in (metadata or {}).items()}
    with atomic_path(path) as tmp:
        tmp.unlink()  # GDAL creates the file; an empty one is not a GeoPackage
        for i, (name, (table, geometry)) in enumerate(layers.items()):
            frame = gpd.GeoDataFrame(
                table.reset_index(drop=True), geometry=gpd.GeoSeries(geometry), crs=crs
            )
            with warnings.catch_warnings():  # no CRS is what a map without GNSS has
                warnings.filterwarnings("ignore", "'crs' was not provided", UserWarning)
                pyogrio.write_dataframe(
                    frame,
                    tmp,
                    layer=name,
                    driver="GPKG",
                    dataset_metadata=meta if i == 0 and meta else None,
                    layer_metadata=meta or None,
                    dataset_options={"VERSION": GPKG_VERSION} if i == 0 else None,
                )
    return path


def read_gpkg_layer(path: str | Path, layer: str) -> Any:
    """One layer of a GeoPackage as a GeoDataFrame (InputError naming the file otherwise)."""
    import pyogrio
    from pyogrio.errors import DataLayerError, DataSourceError

    path = Path(path)
    try:
        return pyogrio.read_dataframe(path, layer=layer)
    except (DataSourceError, DataLayerError) as exc:
        raise InputError(
            f"{path}: cannot read layer {layer!r} ({type(exc).__name__}: {exc})"
        ) from None


def gpkg_metadata(path: str | Path) -> dict[str, str]:
    """The dataset metadata items of a GeoPackage."""
    import pyogrio

    return dict(pyogrio.read_info(path, layer=0).get("dataset_metadata") or {})
