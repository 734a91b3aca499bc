"""A continuous wall's per-tree truth in a run's evaluation (issue 52): the trunk-midpoint cut.

In a fruiting wall the crowns overlap and a tree is only defined by the trunks: trees.csv then
says ``volume_truth == "trunk-midpoint cut"`` and gives each tree its slab
[``cut_start_m``, ``cut_end_m``) along the row direction (local frame) and the wall's volume
inside it (``cut_volume_m3``; ``canopy_kit.sim.wall_truth``). A map point hit on a crown
belongs to the tree of that crown's row whose slab holds the point, not to the crown it hit.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

WALL_TRUTH = "trunk-midpoint cut"  # trees.csv ``volume_truth`` (canopy_kit.sim.wall_truth)


def is_wall_truth(trees: pd.DataFrame) -> bool:
    """Whether trees.csv gives the trunk-midpoint cut as every tree's truth."""
    return "volume_truth" in trees and bool(
        len(trees) and (trees["volume_truth"].astype(str) == WALL_TRUTH).all()
    )


def cut_direction(trees: pd.DataFrame) -> np.ndarray:
    """The unit row direction the cuts were measured along, recovered from the table alone:
    every inner slab edge is the midpoint of two neighbouring trunks projected on it, so
    ``midpoint . d = edge`` holds exactly (least squares over the edges)."""
    mids, edges = [], []
    for _, group in trees.groupby("row"):
        g = group[np.isfinite(group["cut_end_m"].to_numpy(float))].sort_values("cut_end_m")
        following = group.set_index("cut_start_m")
        for _, tree in g.iterrows():
            if tree["cut_end_m"] not in following.index:
                continue
            nxt = following.loc[[tree["cut_end_m"]]].iloc[0]
            mids.append(0.5 * (tree[["x", "y"]].to_numpy(float) + nxt[["x", "y"]].to_numpy(float)))
            edges.append(float(tree["cut_end_m"]))
    if len(mids) >= 2:
        d, *_ = np.linalg.lstsq(np.array(mids), np.array(edges), rcond=None)
        if np.linalg.norm(d) > 0:
            return d / np.linalg.norm(d)
    return np.array([1.0, 0.0])


def cut_labels(xy: np.ndarray, hit: np.ndarray, trees: pd.DataFrame) -> np.ndarray:
    """Per map point (``xy`` in the truth's local frame): the tree whose cut holds it, among
    the trees of the row of the crown it hit (``hit``: per-point true tree id, below 0 for no
    tree, kept as it is)."""
    hit = np.asarray(hit).astype(np.int64)
    out = hit.copy()
    along = np.asarray(xy, float)[:, :2] @ cut_direction(trees)
    row_of = trees.set_index("tree_id")["row"]
    on_tree = hit >= 0
    rows = np.full(len(hit), -1, np.int64)
    known = on_tree & np.isin(hit, row_of.index.to_numpy())
    rows[known] = row_of.reindex(hit[known]).to_numpy(np.int64)
    for row, group in trees.groupby("row"):
        group = group.sort_values("cut_start_m")
        mine = np.flatnonzero(rows == row)
        k = np.searchsorted(group["cut_start_m"].to_numpy(float), along[mine], side="right") - 1
        out[mine] = group["tree_id"].to_numpy(np.int64)[np.clip(k, 0, len(group) - 1)]
    return out
