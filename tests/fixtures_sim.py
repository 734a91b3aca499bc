"""Helpers for the segmentation tests: synthetic orchards (fast, exact) and maps of small
simulated sessions built with the true poses (cached once per test run)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.core.cloud import PointCloud


@dataclass
class SyntheticOrchard:
    """A point cloud with known trees: ``tree_id`` per point (-1 ground, grass, trunks)."""

    cloud: PointCloud
    centres: np.ndarray  # (n, 2) crown centres
    rows: np.ndarray
    index_in_row: np.ndarray
    ground: callable


def synthetic_orchard(
    rows: int = 2,
    trees_per_row: int = 4,
    spacing: float = 5.0,
    row_spacing: float = 6.0,
    crown_radius: float = 1.8,
    bearing_deg: float = 0.0,
    slope_deg: float = 0.0,
    bow: float = 0.0,
    trunks: bool = True,
    density: float = 400.0,
    seed: int = 0,
    ground_extent: float = 6.0,
    crown_aspect: float = 0.8,
    crown_base: float = 1.0,
) -> SyntheticOrchard:
    """Rows of hollow ellipsoid crowns on trunks over a sloped, slightly bumpy ground.

    Rows run along the bearing ``bearing_deg`` (clockwise from +y), numbered left to right
    as seen along it; ``bow`` bends every row (metres at mid-row). ``density`` is points
    per square metre of crown shell; crowns are ``crown_aspect`` times as tall (half-height
    over radius) as wide and start ``crown_base`` m above the ground.
    """
    rng = np.random.default_rng(seed)
    b = np.radians(bearing_deg)
    d = np.array([np.sin(b), np.cos(b)])
    right = np.array([d[1], -d[0]])
    slope = np.tan(np.radians(slope_deg))

    def ground(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        along = x * d[0] + y * d[1]
        return slope * along + 0.05 * np.sin(x / 3.0) * np.cos(y / 4.0)

    pts, ids, centres, row_of, idx_of = [], [], [], [], []
    length = (trees_per_row - 1) * spacing
    for r in range(rows):
        for i in range(trees_per_row):
            a = i * spacing
            c = r * row_spacing + bow * (1 - (2 * a / max(length, 1e-9) - 1) ** 2)
            xy = a * d + c * right
            g = ground(xy[:1], xy[1:])[0]
            k = len(centres)
            n = int(density * 4 * np.pi * crown_radius**2 * max(1.0, crown_aspect))
            u = rng.normal(size=(n, 3))
            u /= np.linalg.norm(u, axis=1, keepdims=True)
            depth = rng.uniform(0.8, 1.0, n)
            semi = np.array([crown_radius, crown_radius, crown_aspect * crown_radius])
            shell = u * depth[:, None] * semi
            centre3 = np.array([xy[0], xy[1], g + crown_base + crown_aspect * crown_radius])
            pts.append(shell + centre3)
            ids.append(np.full(n, k))
            if trunks:
                h = rng.uniform(0.0, crown_base + 0.2, 250)
                ang = rng.uniform(0, 2 * np.pi, 250)
                pts.append(
                    np.column_stack([xy[0] + 0.1 * np.cos(ang), xy[1] + 0.1 * np.sin(ang), g + h])
                )
                ids.append(np.full(250, -1))
            centres.append(xy)
            row_of.append(r)
            idx_of.append(i)
    centres_a = np.array(centres).reshape(-1, 2)
    lo = centres_a.min(axis=0) - ground_extent if len(centres_a) else np.array([-5.0, -5.0])
    hi = centres_a.max(axis=0) + ground_extent if len(centres_a) else np.array([5.0, 5.0])
    n_ground = int(np.prod(hi - lo) * 20)
    gxy = rng.uniform(lo, hi, (n_ground, 2))
    gz = ground(gxy[:, 0], gxy[:, 1]) + rng.normal(0, 0.01, n_ground)
    grass = rng.random(n_ground) < 0.2
    gz[grass] += rng.uniform(0, 0.25, grass.sum())
    pts.append(np.column_stack([gxy, gz]))
    ids.append(np.full(n_ground, -1))
    xyz = np.concatenate(pts)
    cloud = PointCloud(
        xyz,
        {"tree_id": np.concatenate(ids).astype(np.int32)},
        crs="EPSG:32610",
        origin=np.array([700000.0, 4100000.0, 50.0]),
    )
    return SyntheticOrchard(cloud, centres_a, np.array(row_of), np.array(idx_of), ground)


def truth_map_of(session, voxel_size: float = 0.05) -> PointCloud:
    """The map of a simulated session built with its true poses."""
    from canopy_kit.evaluate.truth_map import truth_map

    return truth_map(session.root, voxel_size=voxel_size)


# -- row metrics against the simulator's exact crowns (issue 52) -----------------------------
def truth_onto_map(ctx, session_root) -> np.ndarray:
    """The rigid transform (4x4) taking the truth's local frame onto a run's map: the inverse
    of the SE(3) alignment of the estimated trajectory onto the true one (a georeferencing
    offset of a few decimetres is the mapping's error, not the row metrics')."""
    from canopy_kit.evaluate.trajectory_error import trajectory_errors
    from canopy_kit.evaluate.truth import load_truth

    truth = load_truth(session_root)
    reference = truth.trajectory_of(getattr(ctx.mapping, "trajectory_frame", ""))
    align = np.asarray(trajectory_errors(ctx.mapping.trajectory, reference)["alignment"])
    return np.linalg.inv(align)


def true_crown_interiors(
    orchard, onto_map: np.ndarray, step: float = 0.05, surface: bool = False
) -> np.ndarray:
    """Points on a ``step`` grid inside every exact crown envelope, as (x, y) in the map's
    frame and height above the true ground: the true canopy (posts and wires are no crown).
    ``surface``: with points on the envelope too (200,000 directions, about 1 cm apart), so
    that extents are the envelope's: the grid's lie half a step inside on average, 5 cm
    of width, 6 % of a fruiting wall's."""
    inside = []
    for tree in orchard.trees:
        lo, hi = tree.crown.bounds
        axes = [np.arange(lo[k], hi[k] + step, step) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        grid = grid[tree.crown.contains(grid)]
        if surface:
            grid = np.vstack([grid, tree.crown.surface_points(200_000)])
        h = grid[:, 2] - orchard.terrain.height(grid[:, 0], grid[:, 1])
        xy = grid[:, :2] @ onto_map[:2, :2].T + onto_map[:2, 3]
        inside.append(np.column_stack([xy, h]))
    return np.vstack(inside)


def true_row_sections(
    profiles, ctx, session_root, min_height: float, step: float = 0.05, surface: bool = False
):
    """Per measured section, the true canopy's top above the true ground and its reach left
    and right of the same fitted line: the interiors of the true crowns (a ``step`` grid inside
    the exact envelopes, with their surfaces when ``surface``) cut into the same 1 m sections."""
    import pandas as pd

    from canopy_kit.sim.session import regenerate_orchard

    orchard = regenerate_orchard(session_root)
    true_pts = true_crown_interiors(orchard, truth_onto_map(ctx, session_root), step, surface)
    true_pts = true_pts[true_pts[:, 2] >= min_height]
    half = 0.5 * profiles.row_spacing_m
    out = []
    for line in ctx.segmentation.rows.lines:
        offset = line.offset(true_pts[:, :2])
        along = true_pts[:, :2] @ line.direction
        near = np.abs(offset) <= half
        sections = profiles.sections[profiles.sections["row"] == line.row]
        mid = sections[["x", "y"]].to_numpy() @ line.direction
        for (_, sec), m in zip(sections.iterrows(), mid, strict=True):
            s = near & (along >= m - 0.5) & (along < m + 0.5)
            top = true_pts[s, 2].max() if s.any() else 0.0
            left = -offset[s].min() if s.any() else 0.0
            right = offset[s].max() if s.any() else 0.0
            out.append(
                {
                    "row": line.row,
                    "section": sec["section"],
                    "height_m": sec["height_m"],
                    "width_m": sec["width_m"],
                    "width_left_m": sec["width_left_m"],
                    "width_right_m": sec["width_right_m"],
                    "n_points": sec["n_points"],
                    "true_height_m": top,
                    "true_width_left_m": left,
                    "true_width_right_m": right,
                    "true_width_m": left + right,
                }
            )
    return pd.DataFrame(out)
