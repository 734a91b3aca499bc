"""Match aerial crowns to LiDAR trees by position: one row per tree with both estimates.

Trees come from a CSV (e.g. the LiDAR stage's ``trees.csv``) with ``lat``/``lon``
columns (preferred: they survive a change of local frame) or ``x``/``y`` in the
processing frame. A crown seeded by a tree goes to that tree; the others are assigned
Hungarian (minimum total distance). Both are gated: a crown farther than ``max_distance_m``
(``[ground_truth] match_distance_m``) from a tree is never that tree's crown.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.core.geo import LocalFrame
from canopy_kit.errors import InputError

POSITION_COLUMNS = (("crown_x", "crown_y"), ("x", "y"))


def read_trees(path: str | Path, frame: LocalFrame | None) -> pd.DataFrame:
    """Tree positions from a CSV as columns ``tree_x``/``tree_y`` in ``frame`` (plus the rest)."""
    path = Path(path)
    try:
        trees = pd.read_csv(path)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a readable CSV of tree positions ({exc})") from None
    return tree_positions(trees, frame, str(path))


def tree_positions(
    trees: pd.DataFrame, frame: LocalFrame | None, where: str = "trees"
) -> pd.DataFrame:
    """Add ``tree_x``/``tree_y`` (local frame) from ``lat``/``lon`` or from crown/trunk x, y."""
    out = trees.copy()
    if {"lat", "lon"} <= set(out.columns) and frame is not None:
        xy = frame.to_local(out["lat"].to_numpy(float), out["lon"].to_numpy(float))
        out["tree_x"], out["tree_y"] = xy[:, 0], xy[:, 1]
        # A trunk lat/lon misses a leaning crown; shift by the crown offset when both are given.
        if {"crown_x", "crown_y", "x", "y"} <= set(out.columns):
            out["tree_x"] += out["crown_x"] - out["x"]
            out["tree_y"] += out["crown_y"] - out["y"]
        return out
    for cx, cy in POSITION_COLUMNS:
        if {cx, cy} <= set(out.columns):
            out["tree_x"], out["tree_y"] = out[cx].astype(float), out[cy].astype(float)
            return out
    raise InputError(
        f"{where}: needs lat/lon (with a frame) or x/y columns for tree positions; "
        f"found {', '.join(map(str, out.columns))}"
    )


def assign(
    a_xy: np.ndarray, b_xy: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hungarian assignment of points ``a`` to ``b`` within ``max_distance``: (ia, ib, distance)."""
    from scipy.optimize import linear_sum_assignment

    a_xy, b_xy = np.asarray(a_xy, float).reshape(-1, 2), np.asarray(b_xy, float).reshape(-1, 2)
    if len(a_xy) == 0 or len(b_xy) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    d = np.linalg.norm(a_xy[:, None, :] - b_xy[None, :, :], axis=2)
    cost = np.where(d <= max_distance, d, 1e6)
    ia, ib = linear_sum_assignment(cost)
    keep = d[ia, ib] <= max_distance
    return ia[keep], ib[keep], d[ia, ib][keep]


def match_crowns(trees: pd.DataFrame, crowns: pd.DataFrame, max_distance_m: float) -> pd.DataFrame:
    """One row per tree: the tree's columns plus its crown's columns prefixed ``aerial_``.

    Crowns seeded by a tree (``seed_id`` = the tree's row index) go to that tree when within
    ``max_distance_m`` of it; the others are assigned by position within the same distance.
    Trees without a crown get NaN aerial columns.
    """
    out = trees.reset_index(drop=True).copy()
    aerial = crowns.add_prefix("aerial_")
    crown_of_tree = np.full(len(out), -1)
    seeded = crowns["seed_id"].to_numpy() if "seed_id" in crowns else np.full(len(crowns), -1)
    tree_xy = out[["tree_x", "tree_y"]].to_numpy(float)
    crown_xy = crowns[["x", "y"]].to_numpy(float) if len(crowns) else np.zeros((0, 2))
    for ci, si in enumerate(seeded):
        if 0 <= si < len(out) and np.hypot(*(crown_xy[ci] - tree_xy[int(si)])) <= max_distance_m:
            crown_of_tree[int(si)] = ci
    free_trees = np.flatnonzero(crown_of_tree < 0)
    free_crowns = np.setdiff1d(np.arange(len(crowns)), crown_of_tree[crown_of_tree >= 0])
    ia, ib, _ = assign(
        out.loc[free_trees, ["tree_x", "tree_y"]].to_numpy(),
        crowns.iloc[free_crowns][["x", "y"]].to_numpy(),
        max_distance_m,
    )
    crown_of_tree[free_trees[ia]] = free_crowns[ib]
    rows = [
        aerial.iloc[c] if c >= 0 else pd.Series(index=aerial.columns, dtype=float)
        for c in crown_of_tree
    ]
    joined = pd.concat([out, pd.DataFrame(rows).reset_index(drop=True)], axis=1)
    joined["aerial_distance_m"] = np.hypot(
        joined["aerial_x"] - joined["tree_x"], joined["aerial_y"] - joined["tree_y"]
    )
    joined["matched"] = crown_of_tree >= 0
    return joined


def seed_offset(matched: pd.DataFrame, min_pairs: int = 3) -> dict:
    """How far the aerial crowns sit from their seed trees, east and north (median over the
    matched trees), with its standard error: the offset between the two georeferencings.

    A LiDAR map georeferenced by standalone GNSS carries the receiver's error averaged over
    the drive, one translation for the whole session (simulated sessions: 0.3-0.4 m RMS per
    axis over a 70-240 s drive, zero over many seeds), while an RTK drone is within
    centimetres; a one-sided or badly segmented tree shows as a single outlier instead. The
    median ignores such outliers; the standard error is 1.25 sd / sqrt(n) (median of a
    normal sample). ``significant``: the offset exceeds three standard errors and 5 cm.
    """
    ok = matched["matched"].to_numpy(bool) if "matched" in matched else np.ones(len(matched), bool)
    d = np.column_stack(
        [matched["aerial_x"] - matched["tree_x"], matched["aerial_y"] - matched["tree_y"]]
    )[ok]
    d = d[np.isfinite(d).all(axis=1)]
    n = len(d)
    if n < min_pairs:
        return {
            "pairs": n,
            "east_m": None,
            "north_m": None,
            "standard_error_m": None,
            "significant": False,
        }
    med = np.median(d, axis=0)
    se = float(1.2533 * np.sqrt(np.mean(np.var(d, axis=0, ddof=1))) / np.sqrt(n))
    size = float(np.hypot(*med))
    return {
        "pairs": n,
        "east_m": float(med[0]),
        "north_m": float(med[1]),
        "standard_error_m": se,
        "significant": bool(size > max(3 * se, 0.05)),
    }


def crown_tree_ids(crowns: pd.DataFrame, matched: pd.DataFrame) -> pd.Series:
    """Per crown, the ``tree_id`` of the tree it was matched to ("" for an unmatched crown)."""
    hit = matched[matched["matched"].to_numpy(bool)]
    by_crown = dict(zip(hit["aerial_crown_id"].astype(int), hit["tree_id"].astype(str)))
    return pd.Series(
        [by_crown.get(int(c), "") for c in crowns["crown_id"]], index=crowns.index, dtype=object
    )
