"""Writing and reading a segmentation run folder.

``segmented.laz`` (the map with ``segment_id`` and ``height_above_ground`` per point, every
input attribute kept), ``trees.csv``, ``trees.geojson`` (tree positions), ``crowns.geojson``
(crown footprints), ``rows.geojson`` (row lines), ``segmentation.json`` (summary). GeoJSON
coordinates are in the map's CRS (local coordinates plus the map origin) and name the CRS
in a ``crs`` member, as GDAL and QGIS read it. Every file is written atomically.

A ``canopy-kit run`` folder is a segmentation folder too: it holds the summary, crowns and
rows beside its own ``trees.csv`` (segment ids in ``segment``) and ``map.laz`` (the map
with ``segment_id``), so ``canopy-kit evaluate`` takes either.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.io.atomic import atomic_write_text
from canopy_kit.segment.result import Segmentation

FILES = {"cloud": "segmented.laz", "trees": "trees.csv", "positions": "trees.geojson",
         "crowns": "crowns.geojson", "rows": "rows.geojson", "summary": "segmentation.json"}
RUN_CLOUD = "map.laz"  # the cloud of a ``canopy-kit run`` folder


@dataclass
class SegmentationRun:
    """What a run folder holds (the cloud only when asked for)."""

    root: Path
    trees: pd.DataFrame
    footprints: dict[int, np.ndarray]  # local frame
    summary: dict[str, Any]
    cloud: PointCloud | None = None


def _crs_member(crs: str | None) -> dict[str, Any] | None:
    if not crs:
        return None
    name = f"urn:ogc:def:crs:EPSG::{crs.split(':', 1)[1]}" if crs.upper().startswith("EPSG:") else crs
    return {"type": "name", "properties": {"name": name}}


def _collection(features: list[dict[str, Any]], crs: str | None) -> str:
    data: dict[str, Any] = {"type": "FeatureCollection", "features": features}
    member = _crs_member(crs)
    if member:
        data["crs"] = member
    return json.dumps(data, indent=1, default=_plain) + "\n"


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def positions_geojson(seg: Segmentation) -> str:
    """Tree positions (crown centroids) as GeoJSON points in the map's CRS."""
    feats = []
    for rec in seg.table().to_dict(orient="records"):
        x, y, z = np.array([rec["x"], rec["y"], rec["z"]]) + seg.origin
        props = {k: v for k, v in rec.items() if k not in ("x", "y", "z")}
        feats.append({"type": "Feature", "geometry": {"type": "Point",
                                                      "coordinates": [float(x), float(y), float(z)]},
                      "properties": props})
    return _collection(feats, seg.crs)


def crowns_geojson(seg: Segmentation) -> str:
    """Crown footprints (convex hulls) as GeoJSON polygons in the map's CRS."""
    feats = []
    for t in seg.trees:
        hull = seg.footprints.get(t.segment_id, np.zeros((0, 2)))
        if len(hull) < 3:
            continue
        ring = hull + seg.origin[:2]
        ring = np.vstack([ring, ring[:1]])
        feats.append({"type": "Feature",
                      "geometry": {"type": "Polygon", "coordinates": [ring.tolist()]},
                      "properties": {"segment_id": t.segment_id, "tree_id": t.tree_id,
                                     "row": t.row, "label": t.label}})
    return _collection(feats, seg.crs)


def rows_geojson(seg: Segmentation) -> str:
    """Row lines as GeoJSON line strings in the map's CRS, in the driving direction."""
    feats = []
    for line in seg.rows.lines:
        pts = line.polyline() + seg.origin[:2]
        feats.append({"type": "Feature",
                      "geometry": {"type": "LineString", "coordinates": pts.tolist()},
                      "properties": {"row": line.row, "n_trees": line.n_trees}})
    return _collection(feats, seg.crs)


def write_segmentation(out_dir: str | Path, seg: Segmentation, cloud: PointCloud,
                       with_cloud: bool = True) -> dict[str, Path]:
    """Write a run folder (see module docstring); returns the paths written."""
    from canopy_kit.io.clouds import write_cloud
    from canopy_kit.sim.truth import write_csv

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    if with_cloud:
        labelled = _las_compatible(cloud).with_field("segment_id", seg.labels.astype(np.int32))
        labelled = labelled.with_field("height_above_ground", seg.height.astype(np.float32))
        paths["cloud"] = write_cloud(out / FILES["cloud"], labelled)
    paths["trees"] = write_csv(seg.table(), out / FILES["trees"])
    paths["positions"] = atomic_write_text(out / FILES["positions"], positions_geojson(seg))
    return paths | write_segmentation_summary(out, seg)


def write_segmentation_summary(out_dir: str | Path, seg: Segmentation) -> dict[str, Path]:
    """``crowns.geojson``, ``rows.geojson`` and ``segmentation.json``: what scoring a run needs
    besides its tree table and labelled cloud."""
    out = Path(out_dir)
    return {"crowns": atomic_write_text(out / FILES["crowns"], crowns_geojson(seg)),
            "rows": atomic_write_text(out / FILES["rows"], rows_geojson(seg)),
            "summary": atomic_write_text(out / FILES["summary"],
                                         json.dumps(seg.summary(), indent=2, default=_plain) + "\n")}


def _las_compatible(cloud: PointCloud) -> PointCloud:
    """LAS keeps intensity as 0..65535 integers; a float intensity (simulated scans) is
    rounded when it fits, else kept under another name as an extra dimension."""
    value = cloud.fields.get("intensity")
    if value is None or np.issubdtype(np.asarray(value).dtype, np.integer):
        return cloud
    fields = dict(cloud.fields)
    v = np.asarray(fields.pop("intensity"), dtype=np.float64)
    if len(v) == 0 or (np.nanmin(v) >= 0 and np.nanmax(v) <= 65535):
        fields["intensity"] = np.round(np.nan_to_num(v)).astype(np.uint16)
    else:
        fields["intensity_value"] = v.astype(np.float32)
    return PointCloud(cloud.xyz, fields, cloud.crs, cloud.origin.copy())


def read_segmentation(run_dir: str | Path, with_cloud: bool = True) -> SegmentationRun:
    """Read a folder written by :func:`write_segmentation` (``canopy-kit segment``) or by
    ``canopy-kit run``."""
    from canopy_kit.io.clouds import read_cloud

    root = Path(run_dir)
    if not root.is_dir():
        raise InputError(f"{root}: segmentation folder does not exist")
    for key in ("trees", "summary"):
        if not (root / FILES[key]).exists():
            raise InputError(f"{root}: not a segmentation folder (no {FILES[key]})")
    summary = json.loads((root / FILES["summary"]).read_text())
    trees = pd.read_csv(root / FILES["trees"], dtype={"tree_id": str, "label": str})
    run_folder = "segment_id" not in trees and "segment" in trees  # `canopy-kit run`'s table
    if run_folder:
        trees = trees.rename(columns={"segment": "segment_id"})
    origin = np.asarray(summary.get("origin", [0, 0, 0]), float)
    footprints: dict[int, np.ndarray] = {}
    if (root / FILES["crowns"]).exists():
        for f in json.loads((root / FILES["crowns"]).read_text())["features"]:
            ring = np.asarray(f["geometry"]["coordinates"][0], float)[:-1] - origin[:2]
            footprints[int(f["properties"]["segment_id"])] = ring
    cloud = None
    # A run's map.laz holds its segment ids; beside a `segment --no-cloud` table it is not ours.
    path = root / (RUN_CLOUD if run_folder else FILES["cloud"])
    path = path if path.exists() else None
    if with_cloud and path is not None:
        cloud = read_cloud(path)
        if "segment_id" not in cloud.fields:
            raise InputError(f"{path}: no segment_id field; is this a segmentation or run folder?")
        # LAS stores its own origin; bring the points into the run's local frame.
        cloud = PointCloud(cloud.absolute_xyz - origin, cloud.fields, cloud.crs, origin)
    return SegmentationRun(root, trees, footprints, summary, cloud)
