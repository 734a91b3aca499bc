"""Writing and reading a segmentation run folder.

``segmented.laz`` (the map with ``segment_id``, LAS ``classification`` and
``height_above_ground`` per point, every input attribute kept, the simulator's truth id as
``truth_tree_id``: see ``segment.labelled``), ``trees.csv``, ``trees.geojson`` (tree
positions), ``crowns.geojson`` (crown footprints), ``rows.geojson`` (row lines),
``trees.gpkg`` (the same three as layers in the map's projected CRS) and
``segmentation.json`` (summary). GeoJSON is RFC 7946: WGS84 lon/lat, no ``crs`` member
(``canopy_kit.io.geojson``); a map without a CRS gets none, and segmentation.json says why
(``geojson``). Every file is written atomically.

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

from canopy_kit.core.atomic import atomic_write_text
from canopy_kit.core.cloud import PointCloud
from canopy_kit.core.geo import local_of, lonlat_of
from canopy_kit.errors import InputError
from canopy_kit.io import geojson
from canopy_kit.io.gpkg import read_gpkg_layer, write_gpkg
from canopy_kit.segment.result import Segmentation
from canopy_kit.volume.metrics import POSITION_AND_SIZE

FILES = {
    "cloud": "segmented.laz",
    "trees": "trees.csv",
    "positions": "trees.geojson",
    "crowns": "crowns.geojson",
    "rows": "rows.geojson",
    "gis": "trees.gpkg",
    "summary": "segmentation.json",
}
NO_CRS_NOTE = (
    "no GeoJSON written: the map has no CRS (no GNSS fix georeferenced it), and "
    "RFC 7946 GeoJSON is WGS84 only; trees.gpkg holds the layers in the local frame"
)
RUN_CLOUD = "map.laz"  # the cloud of a ``canopy-kit run`` folder
# trees.csv of ``segment``: the columns ``run`` writes for a tree before its volumes, in its
# order (``tree_table.FIRST_COLUMNS``), so one script reads both.
TREE_COLUMNS = [
    "tree_id",
    "label",
    "row",
    *POSITION_AND_SIZE,
    "segment",
    "crown_base_height_m",
    "crown_diameter_mean_m",
    "projected_area_m2",
    "sphere_volume_m3",
    "index_in_row",
]


def tree_rows(seg: Segmentation, cloud: PointCloud) -> pd.DataFrame:
    """The per-tree table ``segment`` writes: each tree's position and size measured as ``run``
    measures them (``volume.metrics.crown_columns`` on its points, heights above the
    segmentation's ground), lat/lon when the map has a CRS; no volumes."""
    from canopy_kit.volume.metrics import crown_columns
    from canopy_kit.volume.verb import grouped_by_label

    rows = []
    order, sorted_labels = grouped_by_label(seg.labels)  # as the run's volume stage groups
    for tree in seg.trees:
        lo, hi = np.searchsorted(sorted_labels, [tree.segment_id, tree.segment_id + 1])
        row = crown_columns(cloud.xyz[order[lo:hi]], seg.ground.height)
        row.update(
            tree_id=tree.tree_id,
            label=tree.label,
            row=tree.row,
            segment=tree.segment_id,
            index_in_row=tree.index_in_row,
        )
        rows.append(row)
    table = pd.DataFrame(rows, columns=[c for c in TREE_COLUMNS if c not in ("lat", "lon")])
    lat = lon = np.full(len(table), np.nan)
    if seg.crs and len(table):
        lon, lat = lonlat_of(table[["x", "y"]].to_numpy(), seg.crs, seg.origin)
    table.insert(TREE_COLUMNS.index("lat"), "lat", lat)
    table.insert(TREE_COLUMNS.index("lon"), "lon", lon)
    return table


@dataclass
class SegmentationRun:
    """What a run folder holds (the cloud only when asked for)."""

    root: Path
    trees: pd.DataFrame
    footprints: dict[int, np.ndarray]  # local frame
    summary: dict[str, Any]
    cloud: PointCloud | None = None


def positions_geojson(seg: Segmentation, provenance: dict[str, Any] | None = None) -> str | None:
    """Tree positions (crown centroids) as RFC 7946 points ``[lon, lat, height]``; None when
    the map has no CRS."""
    if not seg.crs:
        return None
    table = seg.table()
    lon, lat = lonlat_of(table[["x", "y"]].to_numpy(), seg.crs, seg.origin)
    feats = [
        geojson.feature(
            geojson.point(lo, la, rec["z"] + seg.origin[2]),
            {k: v for k, v in rec.items() if k not in ("x", "y", "z")},
        )
        for lo, la, rec in zip(lon, lat, table.to_dict(orient="records"))
    ]
    return geojson.feature_collection(feats, provenance)


def crowns_geojson(seg: Segmentation, provenance: dict[str, Any] | None = None) -> str | None:
    """Crown footprints (convex hulls) as RFC 7946 polygons; None when the map has no CRS."""
    if not seg.crs:
        return None
    feats = []
    for t, hull in _crowns(seg):
        lon, lat = lonlat_of(hull, seg.crs, seg.origin)
        feats.append(geojson.feature(geojson.polygon(lon, lat), _crown_properties(t)))
    return geojson.feature_collection(feats, provenance)


def rows_geojson(seg: Segmentation, provenance: dict[str, Any] | None = None) -> str | None:
    """Row lines as RFC 7946 line strings in the driving direction; None without a CRS."""
    if not seg.crs:
        return None
    feats = []
    for line in seg.rows.lines:
        lon, lat = lonlat_of(line.polyline(), seg.crs, seg.origin)
        feats.append(
            geojson.feature(
                geojson.line_string(lon, lat), {"row": line.row, "n_trees": line.n_trees}
            )
        )
    return geojson.feature_collection(feats, provenance)


def _crowns(seg: Segmentation) -> list[tuple[Any, np.ndarray]]:
    """(tree record, footprint) of every tree with a footprint polygon."""
    out = []
    for t in seg.trees:
        hull = seg.footprints.get(t.segment_id, np.zeros((0, 2)))
        if len(hull) >= 3:
            out.append((t, hull))
    return out


def _crown_properties(t: Any) -> dict[str, Any]:
    return {"segment_id": t.segment_id, "tree_id": t.tree_id, "row": t.row, "label": t.label}


def gis_layers(
    seg: Segmentation, trees: pd.DataFrame | None = None
) -> dict[str, tuple[pd.DataFrame, list[Any]]]:
    """The GeoPackage layers in the map's projected CRS (``local + origin``): ``trees``
    (points of ``trees``, default the segmentation's table), ``crowns``, ``rows``."""
    from shapely.geometry import LineString, Point, Polygon

    ox, oy = seg.origin[:2]
    table = seg.table() if trees is None else trees
    points = [Point(x + ox, y + oy) for x, y in table[["x", "y"]].to_numpy()]
    crowns = _crowns(seg)
    crown_rows = pd.DataFrame(
        [_crown_properties(t) for t, _ in crowns], columns=["segment_id", "tree_id", "row", "label"]
    )
    polygons = [Polygon(hull + seg.origin[:2]) for _, hull in crowns]
    lines = seg.rows.lines
    row_rows = pd.DataFrame(
        {"row": [ln.row for ln in lines], "n_trees": [ln.n_trees for ln in lines]}
    )
    strings = [LineString(ln.polyline() + seg.origin[:2]) for ln in lines]
    return {"trees": (table, points), "crowns": (crown_rows, polygons), "rows": (row_rows, strings)}


def write_segmentation(
    out_dir: str | Path,
    seg: Segmentation,
    cloud: PointCloud,
    with_cloud: bool = True,
    provenance: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """Write a run folder (see module docstring); returns the paths written."""
    from canopy_kit.io.clouds import write_cloud
    from canopy_kit.io.csv_table import write_csv_table
    from canopy_kit.segment.labelled import labelled_map
    from canopy_kit.segment.row_profile import segmentation_row_profiles, write_row_profiles

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    if with_cloud:
        labelled = labelled_map(_las_compatible(cloud), seg, with_height=True)
        paths["cloud"] = write_cloud(out / FILES["cloud"], labelled)
    written = write_csv_table(
        tree_rows(seg, cloud), out / FILES["trees"], provenance, "canopy-kit segments"
    )
    paths["trees"] = written[FILES["trees"]]
    paths |= write_geojson(out, {"positions": positions_geojson(seg, provenance)})
    # The row metrics a run writes (rows.csv, rows_summary.csv, rows_sections.geojson).
    profiles = segmentation_row_profiles(seg, cloud.xyz)
    paths |= write_row_profiles(out, profiles, seg.crs, seg.origin, provenance)
    return paths | write_segmentation_summary(out, seg, provenance=provenance)


def write_geojson(out_dir: Path, texts: dict[str, str | None]) -> dict[str, Path]:
    """Write each GeoJSON text under its ``FILES`` name; a None (no CRS) removes a stale file
    of an earlier run instead, so no folder holds GeoJSON of another map."""
    paths = {}
    for key, text in texts.items():
        path = Path(out_dir) / FILES.get(key, key)
        if text is not None:
            paths[key] = atomic_write_text(path, text)
        elif path.exists():
            path.unlink()
    return paths


def write_segmentation_summary(
    out_dir: str | Path,
    seg: Segmentation,
    trees: pd.DataFrame | None = None,
    provenance: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """``crowns.geojson``, ``rows.geojson``, ``trees.gpkg`` and ``segmentation.json``: what
    scoring a run needs besides its tree table and labelled cloud (``trees``: the table of
    the GeoPackage's trees layer, default the segmentation's)."""
    out = Path(out_dir)
    paths = write_geojson(
        out, {"crowns": crowns_geojson(seg, provenance), "rows": rows_geojson(seg, provenance)}
    )
    paths["gis"] = write_gpkg(out / FILES["gis"], gis_layers(seg, trees), seg.crs, provenance)
    summary = seg.summary() | ({} if seg.crs else {"geojson": NO_CRS_NOTE})
    paths["summary"] = atomic_write_text(
        out / FILES["summary"], json.dumps(summary, indent=2, default=_plain) + "\n"
    )
    return paths


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


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


def read_footprints(root: Path, summary: dict[str, Any]) -> dict[int, np.ndarray]:
    """Crown footprints in the run's local frame: from the GeoPackage's projected ``crowns``
    layer, else (folders written before it) from crowns.geojson, projected with a ``crs``
    member or WGS84 lon/lat."""
    origin = np.asarray(summary.get("origin", [0, 0, 0]), float)
    if (root / FILES["gis"]).exists():
        crowns = read_gpkg_layer(root / FILES["gis"], "crowns")
        return {
            int(sid): np.asarray(poly.exterior.coords, float)[:-1] - origin[:2]
            for sid, poly in zip(crowns["segment_id"], crowns.geometry)
        }
    path = root / FILES["crowns"]
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
        features = [
            (
                int(f["properties"]["segment_id"]),
                np.asarray(f["geometry"]["coordinates"][0], float)[:-1, :2],
            )
            for f in data["features"]
        ]
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise InputError(f"{path}: not a crowns GeoJSON ({type(exc).__name__}: {exc})") from None
    if "crs" in data:  # projected, the deprecated member of older runs
        return {sid: ring - origin[:2] for sid, ring in features}
    if not summary.get("crs"):
        raise InputError(
            f"{path}: WGS84 crowns but {FILES['summary']} names no CRS to project them"
        )
    return {sid: local_of(ring[:, 0], ring[:, 1], summary["crs"], origin) for sid, ring in features}


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
    trees = trees.rename(columns={"segment": "segment_id"})  # both tables name it `segment`
    run_folder = (root / "metrics.json").exists()  # `canopy-kit run` writes it, `segment` not
    origin = np.asarray(summary.get("origin", [0, 0, 0]), float)
    footprints = read_footprints(root, summary)
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
