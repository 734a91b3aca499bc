"""Crowns that probably are not one tree, from the imagery alone (``crown_flag``).

A crown label bounds every per-crown volume, the visual hull included: a label that holds
two trees gives one volume of both, a label that holds a piece of a tree gives a piece.
Nothing here uses tree positions or LiDAR; the evidence is the crowns' own layout:

* **merged**: the crown reaches further along its row than ``merged_spacings`` tree
  spacings. The spacing is the one the crown seeding found in the photos (the row layout's:
  the planting distance when given, else the hedge's crown width across the row), or the
  given ``tree_spacing_m``, or the median distance from each crown to its nearest
  neighbour. One tree of a row spans about one spacing along it where crowns touch (less
  where they stand free), two merged trees about two.
* **merged** too: its area is above ``merged_area`` times the median area of its row's
  crowns (two equal crowns in one label: about twice; 1.75 leaves room for a smaller
  second tree, and is 1.3 times the median crown's diameter).
* **fragment**: its area is below ``fragment_area`` times its row's median (half the
  diameter of a typical crown: a quarter of its area), unless the crown is cut by the
  mosaic border (``touches_border``: already marked, and small for that reason).

A row's median needs ``min_row_crowns`` crowns; a row with fewer uses the flight's median.

Not caught (measured, docs/GROUND_TRUTH.md): trees planted closer than about half a crown
width. Their label is no longer or larger than one tree's, and the porous hedge's CHM has
no second maximum in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from canopy_kit.errors import ConfigError, InputError
from ground_truth.row_seeds import RowLayout

FLAG_COLUMN = "crown_flag"
MERGED = "merged"
FRAGMENT = "fragment"


@dataclass(frozen=True)
class FlagOptions:
    """Thresholds of :func:`flag_crowns` (multiples of the spacing or the row's median area)."""

    merged_spacings: float = 1.5
    merged_area: float = 1.75
    fragment_area: float = 0.25
    min_row_crowns: int = 3

    def __post_init__(self) -> None:
        for name in ("merged_spacings", "merged_area", "fragment_area"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ConfigError(f"{name}: expected a positive number, got {value!r}")
        if self.fragment_area >= self.merged_area:
            raise ConfigError(
                f"fragment_area: expected below merged_area ({self.merged_area}), "
                f"got {self.fragment_area}"
            )
        if self.min_row_crowns < 1:
            raise ConfigError(f"min_row_crowns: expected at least 1, got {self.min_row_crowns}")


def nearest_neighbour_spacing(xy: np.ndarray) -> float:
    """Median distance from each point to its nearest other point (NaN with fewer than two)."""
    from scipy.spatial import cKDTree

    xy = np.asarray(xy, float).reshape(-1, 2)
    if len(xy) < 2:
        return float("nan")
    dist, _ = cKDTree(xy).query(xy, k=2)
    return float(np.median(dist[:, 1]))


def crown_rows(xy: np.ndarray, layout: RowLayout | None) -> np.ndarray:
    """Index of the row whose band holds each crown centre (0 for all without a layout)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    if layout is None or not layout.rows:
        return np.zeros(len(xy), int)
    u = np.asarray(layout.direction)
    across = (xy - np.asarray(layout.origin)) @ np.array([-u[1], u[0]])
    lower = np.array([row.band_m[0] for row in layout.rows])
    return np.clip(np.searchsorted(lower, across, side="right") - 1, 0, len(lower) - 1)


def flag_spacing(
    crowns: pd.DataFrame, layout: RowLayout | None, tree_spacing_m: float | None = None
) -> tuple[float, str]:
    """The tree spacing the flags measure against and where it comes from: the row layout's,
    the given ``tree_spacing_m``, else the crowns' nearest-neighbour spacing."""
    if layout is not None:
        return float(layout.spacing_m), f"crown_rows ({layout.spacing_source})"
    if tree_spacing_m is not None:
        return float(tree_spacing_m), "given"
    return nearest_neighbour_spacing(crowns[["x", "y"]].to_numpy()), "nearest_crowns"


def flag_crowns(
    crowns: pd.DataFrame,
    spacing_m: float,
    rows: np.ndarray | None = None,
    options: FlagOptions | None = None,
) -> pd.Series:
    """Per crown: ``"merged"``, ``"fragment"`` or ``""`` (module docstring).

    ``crowns`` needs ``area_m2`` and ``diameter_along_row_m`` (``touches_border`` optional);
    ``spacing_m`` is the tree spacing along the rows (NaN: the along-row test is skipped);
    ``rows`` the row index of each crown (default: one row).
    """
    opts = options or FlagOptions()
    for column in ("area_m2", "diameter_along_row_m"):
        if column not in crowns:
            raise InputError(f"crowns: no column {column!r}")
    if not (np.isnan(spacing_m) or spacing_m > 0):
        raise InputError(f"spacing_m: expected a positive distance or NaN, got {spacing_m!r}")
    n = len(crowns)
    rows = np.zeros(n, int) if rows is None else np.asarray(rows, int)
    if rows.shape != (n,):
        raise InputError(f"rows: expected one row index per crown ({n}), got shape {rows.shape}")
    if n == 0:
        return pd.Series([], index=crowns.index, name=FLAG_COLUMN, dtype=object)
    area = crowns["area_m2"].to_numpy(float)
    along = crowns["diameter_along_row_m"].to_numpy(float)
    border = (
        crowns["touches_border"].to_numpy(bool) if "touches_border" in crowns else np.zeros(n, bool)
    )
    inner = ~border  # crowns cut by the border do not set the typical size
    flight_median = float(np.median(area[inner])) if inner.any() else np.nan
    median = np.full(n, flight_median)
    for r in np.unique(rows):
        mine = (rows == r) & inner
        if mine.sum() >= opts.min_row_crowns:
            median[rows == r] = float(np.median(area[mine]))
    merged = area > opts.merged_area * median
    if np.isfinite(spacing_m):
        merged |= along > opts.merged_spacings * spacing_m
    fragment = ~merged & ~border & (area < opts.fragment_area * median)
    flags = np.where(merged, MERGED, np.where(fragment, FRAGMENT, ""))
    return pd.Series(flags, index=crowns.index, name=FLAG_COLUMN, dtype=object)


def flag_summary(flags: pd.Series, spacing_m: float, source: str) -> dict:
    """For ``report.json``: how many crowns are flagged, of each kind, and the spacing used."""
    values = flags.fillna("").astype(str)
    return {
        "merged": int((values == MERGED).sum()),
        "fragment": int((values == FRAGMENT).sum()),
        "tree_spacing_m": round(float(spacing_m), 3) if np.isfinite(spacing_m) else None,
        "tree_spacing_source": source,
    }
