"""A reference map of a session built with its true poses (no odometry error).

Used to study segmentation and volumes separately from mapping error, and as the yardstick
the mapping stage is compared with. It reads the session's bag and truth trajectory
(:mod:`canopy_kit.evaluate.truth`), nothing of the simulator, so evaluation can build it (moved
from ``canopy_kit.sim.truth_map``).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.core.cloud import PointCloud
from canopy_kit.core.geo import LocalFrame
from canopy_kit.core.voxel import voxel_downsample
from canopy_kit.evaluate.truth import load_truth, true_pose_interpolator
from canopy_kit.io.bag import LIDAR_TYPES, open_bag
from canopy_kit.io.session_layout import find_bag


def truth_map(
    sim_dir: str | Path,
    voxel_size: float = 0.05,
    every: int = 1,
    max_range: float = 30.0,
    progress: Callable[[str, float, float], None] | None = None,
) -> PointCloud:
    """Deskew every ``every``-th scan with the true poses and accumulate a voxel-thinned map.

    Per-point attributes (intensity, ring, tree_id...) are kept; ``time`` holds absolute
    per-point times. Coordinates are in the session's local frame (CRS and origin set).
    """
    return truth_maps(sim_dir, None, voxel_size, every, max_range, progress)[None]


def truth_maps(
    sim_dir: str | Path,
    groups: Callable[[np.ndarray], Iterable[Hashable]] | None,
    voxel_size: float = 0.05,
    every: int = 1,
    max_range: float = 30.0,
    progress: Callable[[str, float, float], None] | None = None,
) -> dict[Hashable, PointCloud]:
    """Like :func:`truth_map`, one map per group of sweeps, in one pass over the bag:
    ``groups(sensor_xy)`` names the groups a sweep belongs to from where the sensor was at its
    stamp (None: one map of every sweep, key None). A group no sweep joined is absent."""
    truth = load_truth(sim_dir)
    pose_at = true_pose_interpolator(sim_dir)
    chunks: dict[Hashable, list[PointCloud]] = {}
    pending: dict[Hashable, int] = {}
    with open_bag(find_bag(sim_dir)) as bag:
        lidar = bag.find_topic(LIDAR_TYPES)  # a PointCloud2, Velodyne or Livox topic
        total = next(t.count for t in bag.topics() if t.name == lidar)
        for scan in bag.scans(lidar):
            if scan.index % every:
                continue
            keys = (
                [None]
                if groups is None
                else list(groups(pose_at(np.array([scan.stamp]))[0][0, :2]))
            )
            if not keys:
                continue
            times = scan.times if scan.times is not None else np.full(len(scan), scan.stamp)
            keep = np.linalg.norm(scan.xyz, axis=1) <= max_range
            # Points of one firing share a time: interpolate once per distinct time.
            uniq, inv = np.unique(times[keep], return_inverse=True)
            p, r = pose_at(uniq)
            mats = r.as_matrix()[inv.ravel()]
            world = np.einsum("nij,nj->ni", mats, scan.xyz[keep]) + p[inv.ravel()]
            fields = {
                k: v[keep] for k, v in scan.fields.items() if k not in ("t", "time", "timestamp")
            }
            fields["time"] = times[keep]
            for key in keys:
                chunks.setdefault(key, []).append(PointCloud(world, fields))
                pending[key] = pending.get(key, 0) + len(world)
                if pending[key] > 4_000_000:
                    chunks[key] = [
                        voxel_downsample(PointCloud.concatenate(chunks[key]), voxel_size)
                    ]
                    pending[key] = len(chunks[key][0])
            if progress:
                progress("truth map", scan.index + 1, total)
    maps = {}
    for key, parts in chunks.items():
        cloud = voxel_downsample(PointCloud.concatenate(parts), voxel_size)
        cloud.crs = truth.frame.crs
        cloud.origin = truth.frame.origin
        maps[key] = cloud
    return maps


def row_lines(trees: pd.DataFrame) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per row: a point on its line (the trunks' mean x, y) and the unit along-row direction
    fitted through its trunks (pointing from its first tree to its last; x for a lone tree)."""
    out = {}
    for row, group in trees.groupby("row"):
        xy = group[["x", "y"]].to_numpy(dtype=float)
        direction = np.array([1.0, 0.0])
        if len(xy) >= 2:
            direction = np.linalg.svd(xy - xy.mean(axis=0), full_matrices=False)[2][0]
            if direction @ (xy[-1] - xy[0]) < 0:
                direction = -direction
        out[int(row)] = (xy.mean(axis=0), direction)
    return out


def alley_maps(
    sim_dir: str | Path, voxel_size: float = 0.05, max_range: float = 30.0
) -> dict[tuple[int, int], PointCloud]:
    """Per row and side (+1: left of the row line, as ``(-along_y, along_x)`` points; -1:
    right), the map of only the sweeps driven in the alley on that side: the sensor on that
    side of the line and nearer to it than the row spacing (20 m for a lone row). What a drive
    along that alley alone would have mapped, unlike a split of the whole map, where the alley
    driven first keeps every voxel both alleys saw."""
    lines = row_lines(load_truth(sim_dir).trees)
    across = {r: np.array([-d[1], d[0]]) for r, (_, d) in lines.items()}
    centres = np.array([c for c, _ in lines.values()])
    gaps = [abs((centres[i + 1] - centres[i]) @ across[r]) for i, r in enumerate(list(lines)[:-1])]
    reach = float(np.median(gaps)) if gaps else 20.0

    def sides(xy: np.ndarray) -> list[tuple[int, int]]:
        out = []
        for r, (centre, _) in lines.items():
            d = float((xy - centre) @ across[r])
            if 0 < abs(d) < reach:
                out.append((r, 1 if d > 0 else -1))
        return out

    return truth_maps(sim_dir, sides, voxel_size, max_range=max_range)


@dataclass
class TruthMapping:
    """A mapping result made from the true poses (same fields the mapping stage returns)."""

    map: PointCloud
    trajectory: pd.DataFrame
    frame: LocalFrame
    diagnostics: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def truth_mapping(
    sim_dir: str | Path,
    voxel_size: float = 0.05,
    progress: Callable[[str, float, float], None] | None = None,
    max_range: float = 30.0,
) -> TruthMapping:
    """Map and trajectory of a simulated session from its true poses (for controlled studies)."""
    truth = load_truth(sim_dir)
    cloud = truth_map(sim_dir, voxel_size, max_range=max_range, progress=progress)
    traj = truth.trajectory.copy()
    steps = np.linalg.norm(np.diff(traj[["x", "y", "z"]].to_numpy(), axis=0), axis=1)
    return TruthMapping(
        cloud, traj, truth.frame, {"source": "true poses", "path_length_m": float(steps.sum())}
    )
