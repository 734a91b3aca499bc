"""Row metrics growers spray by: canopy height, width and cross-section per metre of row.

Every fitted row line of a segmentation (``segment.rows.RowLine``) is cut into sections of
``section_m`` (1 m) along the driving direction. The canopy points of a row are the map's
points at canopy height (at least the segmentation's ``min_canopy_height`` above the ground
model, at most its canopy ceiling) within half the row spacing of the row's line. Per
section, from those points:

* ``height_m``: the top of the canopy above the ground model;
* ``width_left_m`` / ``width_right_m``: how far the canopy reaches to the left and right of
  the fitted line (signed across-row offsets are positive to the right of the driving
  direction; a width is negative when the canopy does not reach the line on that side);
  ``width_m`` is their sum, the canopy's across-row extent;
* ``cross_section_m2``: the canopy's area in the section's across-row vertical plane: the
  points projected onto a grid of ``cell_m`` (0.1 m) cells across the row and in height, the
  occupied cells with gaps of one cell closed and enclosed holes filled (a LiDAR sees a
  crown's outer layers, not its inside), times the cell area;
* the spray-application metrics of that section, per hectare of orchard with the row
  spacing ``S``: Tree-Row Volume ``TRV = height x width x 10,000 / S`` (m³/ha; Byers et al.
  1971, Sutton & Unrath 1984) and Leaf Wall Area ``LWA = 2 x height x 10,000 / S`` (m²/ha;
  Koch 2007, Walklate et al. 2011).

Extents are robust to stray returns (a bird, dust, a mixed pixel): they are taken over the
points whose ``cell_m`` cell of the section's across-row x height grid holds at least
``MIN_CELL_POINTS`` (3) points, so an isolated return sets no extent. (Percentiles of the
points, the 98th of height and the 2nd/98th of offset, trim a dense section's true edge:
on the simulated pistachio rows they read 0.2 m low in height and 0.34 m narrow, TRV 17 %
low, against 0.02 m, 0.05 m and 3 % with the cell rule; tests/test_row_profile.py.)

A section with fewer than ``min_points`` canopy points is a gap: no canopy there, height,
widths, area, TRV and LWA 0. Sections run from the row's first to its last section holding
canopy; a row without any has no sections and its summary says so. The per-row summary
averages the sections, gaps included (what a sprayer driving the row meets): mean height,
mean width, TRV and LWA (the means of the sections'), and the row's length.

The row spacing comes from the layout (``segment.layout``) or the fitted lines; with a
single row it is unknown: the band is ``fallback_half_band_m`` either side of the line and
TRV and LWA are NaN.

References: Byers R.E., Hickey K.D., Hill C.H. (1971) Base gallonage per acre. Virginia
Fruit 60:19-23. Sutton T.B., Unrath C.R. (1984) Evaluation of the tree-row-volume concept
with density adjustments in relation to spray deposits in apple orchards. Plant Disease
68:480-484. Koch H. (2007) How to achieve conformity with the dose expression and sprayer
function in high crops. Pflanzenschutz-Nachrichten Bayer 60:71-84. Walklate P.J., Cross
J.V., Pergher G. (2011) Support system for efficient dosage of orchard and vineyard
spraying products. Computers and Electronics in Agriculture 75:355-362.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy import ndimage

from canopy_kit.errors import InputError
from canopy_kit.segment.rows import RowAssignment, RowLine

SECTION_M = 1.0  # section length along the row
CELL_M = 0.1  # cross-section grid cell (across the row and in height)
MIN_CELL_POINTS = 3  # points a grid cell needs to count (an isolated return does not)
MIN_POINTS = 10  # canopy points a section needs to hold canopy
FALLBACK_HALF_BAND_M = 3.0  # band either side of a row's line when the spacing is unknown
M2_PER_HA = 10_000.0

SECTION_COLUMNS = [
    "row",
    "section",
    "start_m",
    "end_m",
    "x",
    "y",
    "lat",
    "lon",
    "height_m",
    "width_left_m",
    "width_right_m",
    "width_m",
    "cross_section_m2",
    "trv_m3_per_ha",
    "lwa_m2_per_ha",
    "n_points",
]
SUMMARY_COLUMNS = [
    "row",
    "length_m",
    "n_sections",
    "canopy_sections",
    "mean_height_m",
    "mean_width_m",
    "mean_cross_section_m2",
    "trv_m3_per_ha",
    "lwa_m2_per_ha",
    "row_spacing_m",
    "n_points",
]
FILES = {
    "sections": "rows.csv",
    "summary": "rows_summary.csv",
    "geojson": "rows_sections.geojson",
}


@dataclass
class RowProfiles:
    """Per row and section metrics (``sections``), per row summary (``summary``)."""

    sections: pd.DataFrame  # SECTION_COLUMNS
    summary: pd.DataFrame  # SUMMARY_COLUMNS
    row_spacing_m: float
    section_m: float = SECTION_M
    warnings: list[str] = field(default_factory=list)
    geometry: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)  # section line xy


def tree_row_volume(height_m: Any, width_m: Any, row_spacing_m: float) -> Any:
    """Tree-Row Volume (m³/ha): ``height x width x 10,000 / row spacing`` (Byers et al. 1971,
    Sutton & Unrath 1984); NaN when the row spacing is unknown."""
    if not (np.isfinite(row_spacing_m) and row_spacing_m > 0):
        return np.asarray(height_m, float) * np.nan
    return np.asarray(height_m, float) * np.asarray(width_m, float) * M2_PER_HA / row_spacing_m


def leaf_wall_area(height_m: Any, row_spacing_m: float) -> Any:
    """Leaf Wall Area (m²/ha): ``2 x height x 10,000 / row spacing`` (Koch 2007, Walklate et
    al. 2011), both sides of the row's canopy wall; NaN when the row spacing is unknown."""
    if not (np.isfinite(row_spacing_m) and row_spacing_m > 0):
        return np.asarray(height_m, float) * np.nan
    return 2.0 * np.asarray(height_m, float) * M2_PER_HA / row_spacing_m


def cross_section_area(offset: np.ndarray, height: np.ndarray, cell_m: float = CELL_M) -> float:
    """Area (m²) the points (across-row ``offset``, ``height``) cover in the vertical plane:
    occupied ``cell_m`` cells, one-cell gaps closed, enclosed holes filled."""
    if len(offset) == 0:
        return 0.0
    i = np.floor((offset - offset.min()) / cell_m).astype(np.int64) + 1
    j = np.floor((height - height.min()) / cell_m).astype(np.int64) + 1
    grid = np.zeros((i.max() + 2, j.max() + 2), dtype=bool)  # a free border for the closing
    grid[i, j] = True
    grid = ndimage.binary_closing(grid, structure=np.ones((3, 3), bool))
    grid = ndimage.binary_fill_holes(grid)
    return float(grid.sum()) * cell_m**2


def _clustered(
    offset: np.ndarray, height: np.ndarray, cell_m: float, min_points: int
) -> tuple[np.ndarray, np.ndarray]:
    """The points whose ``cell_m`` cell of the across-row x height grid holds ``min_points``."""
    i = np.floor(offset / cell_m).astype(np.int64)
    j = np.floor(height / cell_m).astype(np.int64)
    _, inverse, counts = np.unique(
        np.column_stack([i, j]), axis=0, return_inverse=True, return_counts=True
    )
    keep = counts[inverse.ravel()] >= min_points
    return offset[keep], height[keep]


def section_metrics(
    along: np.ndarray,
    offset: np.ndarray,
    height: np.ndarray,
    start: float,
    n_sections: int,
    section_m: float = SECTION_M,
    cell_m: float = CELL_M,
    min_points: int = MIN_POINTS,
    min_cell_points: int = MIN_CELL_POINTS,
) -> pd.DataFrame:
    """Height, left/right width, cross-section and point count of ``n_sections`` sections
    of ``section_m`` from ``start``, from canopy points in a row's frame (``along`` the
    row, signed ``offset`` to the right of its line, ``height`` above the ground)."""
    along, offset, height = (np.asarray(a, float).ravel() for a in (along, offset, height))
    if not (len(along) == len(offset) == len(height)):
        raise InputError("row profile: along, offset and height must have one value per point")
    if not (section_m > 0 and cell_m > 0):
        raise InputError(f"row profile: section ({section_m}) and cell ({cell_m}) must be > 0")
    k = np.floor((along - start) / section_m).astype(np.int64)
    keep = (k >= 0) & (k < n_sections)
    k, offset, height = k[keep], offset[keep], height[keep]
    order = np.argsort(k, kind="stable")
    k, offset, height = k[order], offset[order], height[order]
    bounds = np.searchsorted(k, np.arange(n_sections + 1))
    out = {
        name: np.zeros(n_sections)
        for name in ("height_m", "width_left_m", "width_right_m", "width_m", "cross_section_m2")
    }
    counts = np.diff(bounds)
    for s in np.flatnonzero(counts >= min_points):
        o, h = offset[bounds[s] : bounds[s + 1]], height[bounds[s] : bounds[s + 1]]
        o, h = _clustered(o, h, cell_m, min_cell_points)
        if len(o) < min_points:
            continue
        out["height_m"][s] = h.max()
        out["width_left_m"][s] = -o.min()
        out["width_right_m"][s] = o.max()
        out["width_m"][s] = o.max() - o.min()
        out["cross_section_m2"][s] = cross_section_area(o, h, cell_m)
    table = pd.DataFrame(out)
    table.insert(0, "section", np.arange(n_sections))
    table.insert(1, "start_m", np.arange(n_sections) * section_m)
    table.insert(2, "end_m", (np.arange(n_sections) + 1) * section_m)
    table["n_points"] = counts.astype(np.int64)
    return table


def _line_xy(line: RowLine, along: np.ndarray) -> np.ndarray:
    c0, c1, c2 = line.coef
    across = c0 + c1 * along + c2 * along**2
    return along[:, None] * line.direction + across[:, None] * line.right


def row_profiles(
    xyz: np.ndarray,
    height: np.ndarray,
    rows: RowAssignment,
    row_spacing_m: float | None = None,
    canopy_band_m: tuple[float, float] = (0.8, math.inf),
    section_m: float = SECTION_M,
    cell_m: float = CELL_M,
    min_points: int = MIN_POINTS,
    fallback_half_band_m: float = FALLBACK_HALF_BAND_M,
) -> RowProfiles:
    """Sections and summary of every fitted row of ``rows`` (module docstring), from map
    points ``xyz`` (N, 3+, local frame) and their ``height`` above the ground model.

    ``row_spacing_m`` None: measured on the fitted lines (``segment.layout.row_spacing``).
    """
    from canopy_kit.segment.layout import row_spacing

    xyz = np.asarray(xyz, float)
    height = np.asarray(height, float).ravel()
    if xyz.ndim != 2 or xyz.shape[1] < 2 or len(xyz) != len(height):
        raise InputError(
            f"row profile: points must be (N, 3) with one height each, got {xyz.shape} "
            f"points and {len(height)} heights"
        )
    spacing = row_spacing(rows) if row_spacing_m is None else float(row_spacing_m)
    if row_spacing_m is not None and not (np.isfinite(spacing) and spacing > 0):
        raise InputError(f"row profile: row spacing must be a positive number, got {spacing}")
    warnings: list[str] = []
    if np.isfinite(spacing) and spacing > 0:
        half = 0.5 * spacing
    else:
        spacing, half = float("nan"), float(fallback_half_band_m)
        if rows.lines:
            warnings.append(
                f"row spacing unknown ({len(rows.lines)} fitted row): canopy taken within "
                f"{half:g} m of the row line, TRV and LWA not computed"
            )
    lo, hi = canopy_band_m
    hi = hi if np.isfinite(hi) else np.inf
    canopy = np.flatnonzero((height >= lo) & (height <= hi))
    pts, hts = xyz[canopy, :2], height[canopy]
    sections, summaries, geometry = [], [], {}
    for line in rows.lines:
        table = _row_sections(line, pts, hts, half, section_m, cell_m, min_points, geometry)
        if len(table) == 0:
            warnings.append(
                f"row {line.row}: no section holds {min_points} canopy points, no row metrics"
            )
            table = pd.DataFrame({c: pd.Series(dtype=float) for c in SECTION_COLUMNS if c != "row"})
        table["trv_m3_per_ha"] = tree_row_volume(table["height_m"], table["width_m"], spacing)
        table["lwa_m2_per_ha"] = leaf_wall_area(table["height_m"], spacing)
        table.insert(0, "row", line.row)
        sections.append(table)
        summaries.append(_summary(line.row, table, section_m, spacing))
    summary = pd.DataFrame(summaries, columns=SUMMARY_COLUMNS)
    return RowProfiles(_all_sections(sections), summary, spacing, section_m, warnings, geometry)


def _row_sections(
    line: RowLine,
    pts: np.ndarray,
    hts: np.ndarray,
    half: float,
    section_m: float,
    cell_m: float,
    min_points: int,
    geometry: dict[tuple[int, int], np.ndarray],
) -> pd.DataFrame:
    """One row's sections from the first to the last holding ``min_points`` canopy points
    (empty when none does), numbered from 0 with their centres; each section's line piece is
    added to ``geometry``. Canopy points count within ``half`` across the line and, along
    it, no further than ``half`` past the trees (not the headland's other rows or a U-turn's
    hedge)."""
    offset = line.offset(pts) if len(pts) else np.zeros(0)
    along = pts @ line.direction if len(pts) else np.zeros(0)
    a0, a1 = line.along_range
    near = (np.abs(offset) <= half) & (along >= a0 - half) & (along <= a1 + half)
    along, offset, h = along[near], offset[near], hts[near]
    if not len(along):
        return pd.DataFrame()
    first = math.floor(along.min() / section_m) * section_m
    n = int(math.floor((along.max() - first) / section_m)) + 1
    table = section_metrics(along, offset, h, first, n, section_m, cell_m, min_points)
    filled = np.flatnonzero(table["n_points"].to_numpy() >= min_points)
    if not len(filled):
        return pd.DataFrame()
    table = table.iloc[filled[0] : filled[-1] + 1].reset_index(drop=True)
    start = first + filled[0] * section_m
    table["section"] = np.arange(len(table))
    table["start_m"] = table["section"] * section_m
    table["end_m"] = table["start_m"] + section_m
    mid = start + (table["section"].to_numpy() + 0.5) * section_m
    centre = _line_xy(line, mid)
    table["x"], table["y"] = centre[:, 0], centre[:, 1]
    for s in range(len(table)):
        ends = start + s * section_m + np.linspace(0.0, section_m, 3)
        geometry[(line.row, s)] = _line_xy(line, ends)
    return table


def _all_sections(sections: list[pd.DataFrame]) -> pd.DataFrame:
    """Every row's sections in one table of ``SECTION_COLUMNS`` (lat/lon empty until the
    writer fills them; counts as integers)."""
    if sections:
        all_sections = pd.concat(sections, ignore_index=True)
    else:
        all_sections = pd.DataFrame({c: pd.Series(dtype=float) for c in SECTION_COLUMNS})
    for column in ("lat", "lon"):
        all_sections[column] = np.nan
    for column in ("row", "section", "n_points"):
        all_sections[column] = all_sections[column].astype(np.int64)
    return all_sections[SECTION_COLUMNS]


def _summary(row: int, table: pd.DataFrame, section_m: float, spacing: float) -> dict[str, Any]:
    n = len(table)
    empty = n == 0

    def mean(column: str) -> float:
        return float("nan") if empty else float(table[column].mean())

    return {
        "row": row,
        "length_m": n * section_m,
        "n_sections": n,
        "canopy_sections": int((table["height_m"] > 0).sum()) if n else 0,
        "mean_height_m": mean("height_m"),
        "mean_width_m": mean("width_m"),
        "mean_cross_section_m2": mean("cross_section_m2"),
        "trv_m3_per_ha": mean("trv_m3_per_ha"),
        "lwa_m2_per_ha": mean("lwa_m2_per_ha"),
        "row_spacing_m": spacing,
        "n_points": int(table["n_points"].sum()) if n else 0,
    }


def segmentation_row_profiles(
    seg: Any, xyz: np.ndarray, layout: Any = None, section_m: float = SECTION_M
) -> RowProfiles:
    """:func:`row_profiles` of a segmentation (its rows, heights and canopy band) on its map
    points ``xyz``; the row spacing from ``layout`` (``segment.layout.Layout``) when given,
    with lat/lon of the section centres when the map has a CRS."""
    spacing = getattr(layout, "row_spacing_m", None)
    spacing = float(spacing) if spacing is not None and np.isfinite(spacing) else None
    lo, hi = seg.canopy_band_m
    band = (float(lo) if np.isfinite(lo) else 0.8, float(hi) if np.isfinite(hi) else math.inf)
    profiles = row_profiles(xyz, seg.height, seg.rows, spacing, band, section_m)
    if seg.crs and len(profiles.sections):
        from canopy_kit.core.geo import lonlat_of

        table = profiles.sections
        lon, lat = lonlat_of(table[["x", "y"]].to_numpy(), seg.crs, seg.origin)
        table["lat"], table["lon"] = lat, lon
    return profiles


def sections_geojson(
    profiles: RowProfiles,
    crs: str | None,
    origin: np.ndarray,
    provenance: dict[str, Any] | None = None,
) -> str | None:
    """Every section as an RFC 7946 LineString along its row line (WGS84), its metrics as
    properties: a variable-rate sprayer's map. None when the map has no CRS."""
    from canopy_kit.core.geo import lonlat_of
    from canopy_kit.io import geojson

    if not crs:
        return None
    features = []
    for rec in profiles.sections.to_dict(orient="records"):
        xy = profiles.geometry.get((int(rec["row"]), int(rec["section"])))
        if xy is None:
            continue
        lon, lat = lonlat_of(xy, crs, origin)
        props = {k: v for k, v in rec.items() if k not in ("x", "y", "lat", "lon")}
        features.append(geojson.feature(geojson.line_string(lon, lat), props))
    return geojson.feature_collection(features, provenance)


def write_row_profiles(
    out_dir: str | Path,
    profiles: RowProfiles,
    crs: str | None,
    origin: np.ndarray,
    provenance: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """rows.csv (sections), rows_summary.csv (per row), each with its CSVW sidecar, and
    rows_sections.geojson (removed, not written, when the map has no CRS); paths by name."""
    from canopy_kit.io.csv_table import write_csv_table
    from canopy_kit.segment.export import write_geojson

    out = Path(out_dir)
    files = write_csv_table(
        profiles.sections, out / FILES["sections"], provenance, "canopy-kit row sections"
    )
    files |= write_csv_table(
        profiles.summary, out / FILES["summary"], provenance, "canopy-kit row summary"
    )
    text = sections_geojson(profiles, crs, origin, provenance)
    written = write_geojson(out, {FILES["geojson"]: text})
    files |= {p.name: p for p in written.values()}
    return files
