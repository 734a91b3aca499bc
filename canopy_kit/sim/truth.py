"""The simulator's side of the truth tables: the per-tree table of a generated orchard.

The format (columns, CSV writer, reader) lives in :mod:`canopy_kit.evaluate.truth`; the simulator
writes through it. ``write_csv``, ``load_truth``, ``SessionTruth`` and ``TREE_COLUMNS`` are
re-exported here for code that imported them from the simulator.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.evaluate.truth import (
    TREE_COLUMNS,
    WALL_COLUMNS,
    SessionTruth,
    load_truth,
    write_csv,
)
from canopy_kit.sim.orchard import Orchard

__all__ = [
    "TREE_COLUMNS",
    "WALL_COLUMNS",
    "SessionTruth",
    "crown_row_extents",
    "load_truth",
    "tree_table",
    "write_csv",
]


def tree_table(orchard: Orchard) -> pd.DataFrame:
    """One row per tree with position, sizes, exact crown volume and the sphere-model volume;
    on a continuous wall (``tree_volume_truth = "trunk-midpoint"``) also each tree's cut of the
    wall (:data:`WALL_COLUMNS`, :mod:`canopy_kit.sim.wall_truth`)."""
    rows = []
    for t in orchard.trees:
        lat, lon, _ = orchard.frame.to_wgs84(np.array([t.base]))
        z_lo, z_hi = t.crown.z_range
        widest, perpendicular = t.crown.horizontal_extents
        rows.append(
            {
                "tree_id": t.tree_id,
                "row": t.row,
                "index_in_row": t.index_in_row,
                "label": t.label,
                "x": t.base[0],
                "y": t.base[1],
                "z_ground": t.base[2],
                "lat": lat[0],
                "lon": lon[0],
                "crown_x": t.crown.center[0],
                "crown_y": t.crown.center[1],
                "crown_z": t.crown.center[2],
                "trunk_height_m": t.crown_base_height,
                "crown_base_height_m": t.crown_base_height,
                "crown_height_m": z_hi - z_lo,
                "tree_height_m": t.height,
                "crown_diameter_m": widest,
                "crown_diameter_mean_m": 0.5 * (widest + perpendicular),
                "crown_volume_m3": t.crown.volume,
                "sphere_volume_m3": np.pi * widest**3 / 6.0,
                "doubled": bool(t.doubled),
            }
        )
    table = pd.DataFrame(rows, columns=TREE_COLUMNS)
    if orchard.spec.tree_volume_truth == "trunk-midpoint":
        from canopy_kit.sim.wall_truth import DEFINITION, trunk_midpoint_cuts

        cuts = trunk_midpoint_cuts(orchard)
        table["cut_volume_m3"] = [c.volume_m3 for c in cuts]
        table["cut_start_m"] = [c.start_m for c in cuts]
        table["cut_end_m"] = [c.end_m for c in cuts]
        table["volume_truth"] = DEFINITION
        table["young"] = [bool(t.young) for t in orchard.trees]
        table = table[[*TREE_COLUMNS, *WALL_COLUMNS]]
    return table


def crown_row_extents(sim_dir: str | Path, samples: int = 4000) -> pd.DataFrame:
    """Every simulated tree's crown extent along and across its rows (``tree_id``,
    ``extent_along_row_m``, ``extent_across_row_m``): the crown envelope of the session's
    orchard (rebuilt from its config and seed) projected on the orchard's row direction."""
    from canopy_kit.sim.session import regenerate_orchard

    orchard = regenerate_orchard(sim_dir)
    u = np.asarray(orchard.row_direction, float)[:2]
    v = np.asarray(orchard.right_direction, float)[:2]
    rows = []
    for tree in orchard.trees:
        xy = tree.crown.surface_points(samples)[:, :2]
        rows.append(
            {
                "tree_id": tree.tree_id,
                "extent_along_row_m": float(np.ptp(xy @ u)),
                "extent_across_row_m": float(np.ptp(xy @ v)),
            }
        )
    return pd.DataFrame(rows)
