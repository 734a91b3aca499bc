"""The data behind the report's interactive map, table and per-tree drill-down, as plain JSON.

Every tree is named by the table's ``tree_id``. Coordinates are the map's local frame in
metres (x east, y north), as trees.csv's ``x, y``. Per tree the drill-down gets at most
``max_points`` of its map points and the surfaces its volumes were measured on, as
little-endian integer arrays in base64 (centimetres from the tree's centre), so a tree
costs tens of kilobytes rather than hundreds.
"""

from __future__ import annotations

import base64
import io
import json
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.report.columns import column_label
from canopy_kit.volume.surface import Surface
from canopy_kit.volume.verb import ALPHA_COLUMN

MAX_POINTS = 2000  # points per tree in the 3-D view
ORTHO_PIXELS = 240  # longest side of a tree's orthomosaic crop
ORTHO_QUALITY = 80  # its JPEG quality (a PNG costs about six times as much)
COLUMN_DIGITS = {"lat": 7, "lon": 7, "x": 2, "y": 2}


def _b64(values: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(values, dtype=dtype).tobytes()).decode()


def encode_xyz(xyz: np.ndarray, centre: np.ndarray) -> str:
    """(N, 3) metres as int16 centimetres from ``centre`` (±327 m), base64."""
    return _b64(np.round((xyz - centre) * 100.0), "<i2")


def encode_surface(surface: Surface, centre: np.ndarray) -> dict[str, Any]:
    """A surface as the drill-down reads it: vertices (int16 cm) and faces (uint16 indices,
    uint32 from 65536 vertices on, as ``index_bytes`` says)."""
    wide = len(surface.vertices) > np.iinfo(np.uint16).max
    return {
        "name": surface.name,
        "volume_m3": surface.volume_m3,
        "n_vertices": len(surface.vertices),
        "n_faces": len(surface.faces),
        "vertices": encode_xyz(surface.vertices, centre),
        "index_bytes": 4 if wide else 2,
        "faces": _b64(surface.faces, "<u4" if wide else "<u2"),
    }


def json_records(table: pd.DataFrame) -> list[dict[str, Any]]:
    """Rows as JSON-ready dicts (NaN as null, numpy scalars as Python ones)."""
    return json.loads(table.to_json(orient="records", double_precision=10))


def column_specs(table: pd.DataFrame) -> list[dict[str, Any]]:
    """Per column: key, human label with units, whether it is numeric and its decimals."""
    specs = []
    for col in table.columns:
        numeric = pd.api.types.is_numeric_dtype(table[col]) and not pd.api.types.is_bool_dtype(
            table[col]
        )
        integer = pd.api.types.is_integer_dtype(table[col])
        specs.append(
            {
                "key": col,
                "label": column_label(col),
                "numeric": bool(numeric),
                "digits": 0 if integer else COLUMN_DIGITS.get(col, 3),
            }
        )
    return specs


def downsample(n: int, limit: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``limit`` of ``n`` items (all of them when ``n <= limit``)."""
    if n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, limit, replace=False))


def ortho_crop(mosaic: Any, x: float, y: float, half: float) -> dict[str, Any] | None:
    """The orthomosaic around (x, y) in its own frame as a JPEG data URI with its extent
    (cells no photo saw are white)."""
    from PIL import Image

    r0, c0 = mosaic.grid.index(np.array([x - half]), np.array([y + half]))
    r1, c1 = mosaic.grid.index(np.array([x + half]), np.array([y - half]))
    rows, cols = mosaic.rgba.shape[:2]
    top, left = max(0, math.floor(r0[0])), max(0, math.floor(c0[0]))
    bottom, right = min(rows, math.ceil(r1[0]) + 1), min(cols, math.ceil(c1[0]) + 1)
    if bottom - top < 2 or right - left < 2:
        return None
    crop = mosaic.rgba[top:bottom, left:right]
    if not crop[..., 3].any():
        return None
    rgb = np.where(crop[..., 3:] > 0, crop[..., :3], 255).astype(np.uint8)
    image = Image.fromarray(rgb, "RGB")
    scale = ORTHO_PIXELS / max(image.size)
    if scale < 1:
        image = image.resize(
            (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
        )
    buf = io.BytesIO()
    image.save(buf, format="JPEG", quality=ORTHO_QUALITY, optimize=True)
    g = mosaic.grid
    return {
        "uri": "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode(),
        "x0": g.x0 + left * g.resolution,
        "x1": g.x0 + right * g.resolution,
        "y0": g.y0 - bottom * g.resolution,
        "y1": g.y0 - top * g.resolution,
    }


def _trees_points(ctx: Any, trees: pd.DataFrame) -> Iterator[tuple[Any, np.ndarray]]:
    """Each table row with its points as the volume stage measured them (on map.laz's
    coordinate grid); trees without points are left out."""
    from canopy_kit.io.las_write import on_las_grid

    cloud, labels = on_las_grid(ctx.mapping.map), np.asarray(ctx.segmentation.labels)
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    for rec in trees.itertuples(index=False):
        lo, hi = np.searchsorted(sorted_labels, [rec.segment, rec.segment + 1])
        if hi > lo:
            yield rec, cloud.xyz[order[lo:hi]]


def _centre(rec: Any, xyz: np.ndarray) -> np.ndarray:
    """The drill-down's origin for a tree: its table position at its lowest point."""
    return np.array([rec.x, rec.y, float(xyz[:, 2].min())])


def _encoded_surfaces(
    items: list[tuple[Any, np.ndarray]], volume: Any, known: dict[int, list[Surface]]
) -> list[list[dict[str, Any]]]:
    """Each tree's surfaces encoded for the drill-down: those the volume stage kept
    (``known``, per segment), the others drawn now (:func:`~canopy_kit.volume.verb.tree_surfaces`)
    in forked processes (``volume.workers``, as the volume stage): a tetrahedralisation
    per tree is the report's largest cost."""
    from canopy_kit.core.parallel import run_jobs, worker_count
    from canopy_kit.volume.verb import MIN_TREES_PER_WORKER, drawn_methods, tree_surfaces

    surfaces = [
        [encode_surface(s, _centre(rec, xyz)) for s in known.get(int(rec.segment), [])]
        for rec, xyz in items
    ]
    missing = [i for i, (rec, _) in enumerate(items) if int(rec.segment) not in known]
    if not drawn_methods(volume):  # nothing to draw: no tree is missing a surface
        missing = []

    def encode(part: list[int], tick: Callable[[], None]) -> list[list[dict[str, Any]]]:
        out = []
        for i in part:
            rec, xyz = items[i]
            out.append([encode_surface(s, _centre(rec, xyz)) for s in tree_surfaces(xyz, volume)])
            tick()
        return out

    n = worker_count(volume.workers, len(missing) // MIN_TREES_PER_WORKER)
    parts = [missing[k::n] for k in range(n)]
    done = run_jobs(encode, parts, "report", len(missing), first_in_parent=True)
    for part, encoded in zip(parts, done, strict=True):
        for i, tree in zip(part, encoded, strict=True):
            surfaces[i] = tree
    return surfaces


def tree_details(ctx: Any, trees: pd.DataFrame, max_points: int = MAX_POINTS) -> dict[str, Any]:
    """Per tree_id: its points (at most ``max_points``), surfaces and orthomosaic crop; the
    points as the volume stage measured them (on map.laz's coordinate grid). The surfaces
    are those the volume stage kept (``ctx.surfaces``); trees without them are drawn in
    forked processes: call it before starting any thread."""
    aerial = getattr(ctx, "aerial", None)
    shift = None
    if aerial is not None and getattr(aerial, "ortho", None) is not None:
        frame = getattr(ctx.mapping, "frame", None)
        origin = frame.origin[:2] if frame is not None else np.zeros(2)
        shift = ctx.mapping.map.origin[:2] - origin
    items = list(_trees_points(ctx, trees))
    known = getattr(ctx, "surfaces", None) or {}
    surfaces = _encoded_surfaces(items, ctx.config.volume, known)
    details: dict[str, Any] = {}
    for (rec, xyz), encoded in zip(items, surfaces, strict=True):
        centre = _centre(rec, xyz)
        shown = xyz[downsample(len(xyz), max_points, seed=int(rec.segment))]
        item: dict[str, Any] = {
            "centre": centre.tolist(),
            "n_points": len(xyz),
            "n_shown": len(shown),
            "points": encode_xyz(shown, centre),
            "surfaces": encoded,
        }
        if shift is not None:
            radius = max(float(getattr(rec, "crown_diameter_m", 0) or 0) / 2, 1.0) + 1.5
            crop = ortho_crop(aerial.ortho, rec.x + shift[0], rec.y + shift[1], radius)
            if crop is not None:  # back in the map's frame
                crop.update(
                    x0=crop["x0"] - shift[0],
                    x1=crop["x1"] - shift[0],
                    y0=crop["y0"] - shift[1],
                    y1=crop["y1"] - shift[1],
                )
                item["ortho"] = crop
        details[str(rec.tree_id)] = item
    return details


def map_layers(ctx: Any, trees: pd.DataFrame) -> dict[str, Any]:
    """Crown footprints per tree_id, row lines and the drive, in the map's frame."""
    seg = ctx.segmentation
    ids = dict(zip(trees["segment"].astype(int), trees["tree_id"].astype(str), strict=True))
    footprints = {
        ids[sid]: np.round(np.asarray(hull, float), 3).tolist()
        for sid, hull in seg.footprints.items()
        if sid in ids and len(hull) >= 3
    }
    rows = [
        {"row": int(line.row), "xy": np.round(line.polyline(), 3).tolist()}
        for line in seg.rows.lines
    ]
    traj = ctx.mapping.trajectory
    step = max(1, len(traj) // 1500)
    drive = np.round(np.column_stack([traj["x"], traj["y"]])[::step], 2).tolist()
    return {"footprints": footprints, "rows": rows, "drive": drive}


def row_summary(trees: pd.DataFrame, volume: str = ALPHA_COLUMN) -> pd.DataFrame:
    """Per row: trees, median and total of ``volume`` (m³; NaN for a row without one) and
    flagged trees. Empty without a row or ``volume`` column."""
    columns = ["row", "trees", "median_m3", "total_m3", "flagged"]
    if "row" not in trees or volume not in trees or not len(trees):
        return pd.DataFrame(columns=columns)
    grouped = trees.assign(_flag=_flagged(trees)).groupby("row", sort=True)
    out = pd.DataFrame(
        {
            "trees": grouped.size(),
            "median_m3": grouped[volume].median(),
            "total_m3": grouped[volume].sum(min_count=1),
            "flagged": grouped["_flag"].sum().astype(int),
        }
    )
    return out.reset_index()[columns]


def _flagged(trees: pd.DataFrame) -> pd.Series:
    """Trees with a volume, segment or drone-crown flag."""
    from canopy_kit.results.tree_table import flagged

    return (
        flagged(trees, "volume_flags")
        | flagged(trees, "segment_flags")
        | flagged(trees, "aerial_flag")
    )


def explorer_data(
    ctx: Any,
    trees: pd.DataFrame,
    downloads: list[dict[str, str]],
    max_points: int = MAX_POINTS,
    details: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Everything the page's script draws, as one JSON-ready dict (``details``: the
    :func:`tree_details` made already, else they are made now). ``recommended``: the volume
    the map is coloured by and every chart leads with."""
    from canopy_kit.volume.verb import volume_column

    name = ctx.config.volume.recommended
    return {
        "recommended": {"name": name, "column": volume_column(name)},
        "trees": json_records(trees),
        "columns": column_specs(trees),
        "flagged": [bool(f) for f in _flagged(trees)],
        "map": map_layers(ctx, trees),
        "details": details if details is not None else tree_details(ctx, trees, max_points),
        "downloads": downloads,
    }
