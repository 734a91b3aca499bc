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
