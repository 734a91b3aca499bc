"""The true row metrics of a simulated session (issue 52): the exact crowns cut into a run's
1 m row sections, to score :mod:`canopy_kit.segment.row_profile` against.

The exact crown envelopes and terrain come from the session's world model
(:meth:`canopy_kit.evaluate.truth.SessionTruth.orchard`), so this module loads no simulator
itself. The truth is moved onto the run's map by the drive's trajectory alignment: a
georeferencing offset of a few decimetres is the mapping's error, not the row metrics'.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.evaluate.trajectory_error import trajectory_errors
from canopy_kit.evaluate.truth import load_truth

#: Directions sampled on each envelope when ``surface`` (about 1 cm apart on a crown).
SURFACE_POINTS = 200_000


def truth_onto_map(ctx: Any, session_root: str | Path) -> np.ndarray:
    """The rigid transform (4x4) taking the truth's local frame onto a run's map: the inverse
    of the SE(3) alignment of the run's estimated trajectory (``ctx.mapping``) onto the true
    one."""
    truth = load_truth(session_root)
    reference = truth.trajectory_of(getattr(ctx.mapping, "trajectory_frame", ""))
    align = np.asarray(trajectory_errors(ctx.mapping.trajectory, reference)["alignment"])
    return np.linalg.inv(align)


def true_crown_interiors(
    orchard: Any, onto_map: np.ndarray, step: float = 0.05, surface: bool = False
) -> np.ndarray:
    """Points on a ``step`` grid inside every exact crown envelope, as (x, y) in the map's
    frame and height above the true ground: the true canopy (posts and wires are no crown).
    ``surface``: with points on the envelope too, so that extents are the envelope's: the
    grid's lie half a step inside on average, 5 cm of width, 6 % of a fruiting wall's."""
    inside = []
    for tree in orchard.trees:
        lo, hi = tree.crown.bounds
        axes = [np.arange(lo[k], hi[k] + step, step) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        grid = grid[tree.crown.contains(grid)]
        if surface:
            grid = np.vstack([grid, tree.crown.surface_points(SURFACE_POINTS)])
        h = grid[:, 2] - orchard.terrain.height(grid[:, 0], grid[:, 1])
        xy = grid[:, :2] @ onto_map[:2, :2].T + onto_map[:2, 3]
        inside.append(np.column_stack([xy, h]))
    return np.vstack(inside)


def sections_of_points(
    points: np.ndarray, lines: list[Any], sections: pd.DataFrame, row_spacing_m: float
) -> pd.DataFrame:
    """Per section of ``sections`` (``row``, ``section``, centre ``x``, ``y``): the top of
    ``points`` ((x, y, height)) within half a row spacing of the row's line and 1 m along
    it around the centre, and their reach left and right of the line (0 where none)."""
    half = 0.5 * row_spacing_m
    out = []
    for line in lines:
        offset = line.offset(points[:, :2])
        along = points[:, :2] @ line.direction
        near = np.abs(offset) <= half
        mine = sections[sections["row"] == line.row]
        mid = mine[["x", "y"]].to_numpy() @ line.direction
        for section, m in zip(mine["section"], mid, strict=True):
            s = near & (along >= m - 0.5) & (along < m + 0.5)
            left = float(-offset[s].min()) if s.any() else 0.0
            right = float(offset[s].max()) if s.any() else 0.0
            out.append(
                {
                    "row": line.row,
                    "section": section,
                    "true_height_m": float(points[s, 2].max()) if s.any() else 0.0,
                    "true_width_left_m": left,
                    "true_width_right_m": right,
                    "true_width_m": left + right,
                }
            )
    return pd.DataFrame(
        out,
        columns=[
            "row",
            "section",
            "true_height_m",
            "true_width_left_m",
            "true_width_right_m",
            "true_width_m",
        ],
    )


MEASURED = ["height_m", "width_m", "width_left_m", "width_right_m", "n_points"]


def true_row_sections(
    profiles: Any,
    ctx: Any,
    session_root: str | Path,
    min_height: float,
    step: float = 0.05,
    surface: bool = False,
) -> pd.DataFrame:
    """Per measured section (``profiles.sections``), the measured metrics beside the true
    canopy's top above the true ground and its reach left and right of the same fitted line
    (``ctx.segmentation.rows.lines``): the exact crowns' interiors (a ``step`` grid, with
    their surfaces when ``surface``) above ``min_height``, cut into the same 1 m sections."""
    orchard = load_truth(session_root).orchard()
    points = true_crown_interiors(orchard, truth_onto_map(ctx, session_root), step, surface)
    points = points[points[:, 2] >= min_height]
    truth = sections_of_points(
        points, ctx.segmentation.rows.lines, profiles.sections, profiles.row_spacing_m
    )
    measured = profiles.sections[["row", "section", *MEASURED]]
    both = truth.merge(measured, on=["row", "section"], how="left", validate="one_to_one")
    return both[["row", "section", *MEASURED, *truth.columns[2:]]]
