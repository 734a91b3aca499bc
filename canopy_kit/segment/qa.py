"""Segments whose crown is unlike the others: possible merges or fragments, without truth.

Trees of one row are planted together and grow alike, so a segment whose crown is far
wider than the row's typical crown most likely holds two or more trees, and one far
smaller is most likely a piece of a tree. Measured on simulated pistachio and almond
drives: correctly segmented crowns lie within 0.75-1.25 times the median crown diameter
of their row; two merged pistachio trees measure 2.2-2.4 times it. A short row's median
is itself spoilt by one merge (two of four segments were merged pairs on one drive), so
rows of fewer than ``ROW_TREES`` trees, and trees in no row, are compared with all trees.

A small crown standing over a trunk of its own (``n_trunks`` = 1, when the table has the
trunks found in the stem band) is a small tree, not a fragment: young trees replanted in an
old row are 0.4-0.5 times its crowns, and a fragment cut from a crown leaves the trunk to
the rest of the tree. On a simulated mixed orchard (seed 463, sparse young crowns among
full-size ones, all 18 trees segmented one-to-one) the three young trees were flagged as
fragments, and failed the run's check, before this rule.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

WIDE = 1.6  # times the median crown diameter: more than one tree?
SMALL = 0.5  # times the median crown diameter: a fragment?
MIN_TREES = 4  # fewer trees give no typical crown to compare with
ROW_TREES = 6  # a row of at least this many trees is its own reference


def crown_outliers(
    trees: pd.DataFrame, wide: float = WIDE, small: float = SMALL, min_trees: int = MIN_TREES
) -> pd.Series:
    """A note per tree ("" when none) for crowns ``wide`` or ``small`` times the median crown
    diameter (column ``crown_diameter_m``) of its row, or of all trees; a small crown over one
    trunk of its own (column ``n_trunks``, if there) is not a fragment (module docstring)."""
    notes = pd.Series([""] * len(trees), index=trees.index, dtype=object)
    if "crown_diameter_m" not in trees or len(trees) < min_trees:
        return notes
    diameter = trees["crown_diameter_m"].to_numpy(float)
    typical = np.full(len(trees), np.nanmedian(diameter) if np.isfinite(diameter).any() else np.nan)
    where = np.full(len(trees), "all trees", dtype=object)
    if "row" in trees:
        row = trees["row"].to_numpy()
        for r in pd.unique(row[pd.notna(row)]):
            members = (row == r) & np.isfinite(diameter)
            if r >= 0 and members.sum() >= ROW_TREES:
                typical[row == r] = np.median(diameter[members])
                where[row == r] = "its row"
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = diameter / typical
    for i in np.flatnonzero(ratio > wide):
        notes.iloc[i] = (
            f"crown {diameter[i]:.1f} m wide, {ratio[i]:.1f}x the median crown of "
            f"{where[i]} ({typical[i]:.1f} m): two or more trees in one segment?"
        )
    own_trunk = (
        trees["n_trunks"].to_numpy() == 1 if "n_trunks" in trees else np.zeros(len(trees), bool)
    )
    for i in np.flatnonzero((ratio < small) & ~own_trunk):
        notes.iloc[i] = (
            f"crown {diameter[i]:.1f} m wide, {ratio[i]:.1f}x the median crown of "
            f"{where[i]} ({typical[i]:.1f} m): a fragment of a tree?"
        )
    return notes
