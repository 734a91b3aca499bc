"""A reference map of a session built with its true poses (no odometry error).

Used to study segmentation and volumes separately from mapping error, and as the yardstick
the mapping stage is compared with. It reads the session's bag and truth trajectory
(:mod:`canopy_kit.truth`), nothing of the simulator, so evaluation can build it (moved
from ``canopy_kit.sim.truth_map``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.cloud import PointCloud
from canopy_kit.geo import LocalFrame
from canopy_kit.io.bag import open_bag
from canopy_kit.session_layout import find_bag
from canopy_kit.truth import load_truth, true_pose_interpolator
from canopy_kit.voxel import voxel_downsample


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
    truth = load_truth(sim_dir)
    pose_at = true_pose_interpolator(sim_dir)
    chunks: list[PointCloud] = []
    pending = 0
    with open_bag(find_bag(sim_dir)) as bag:
        total = next(t.count for t in bag.topics() if t.msgtype.endswith("PointCloud2"))
        for scan in bag.scans():
            if scan.index % every:
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
            chunks.append(PointCloud(world, fields))
            pending += len(world)
            if pending > 4_000_000:
                chunks = [voxel_downsample(PointCloud.concatenate(chunks), voxel_size)]
                pending = len(chunks[0])
            if progress:
                progress("truth map", scan.index + 1, total)
    cloud = voxel_downsample(PointCloud.concatenate(chunks), voxel_size)
    cloud.crs = truth.frame.crs
    cloud.origin = truth.frame.origin
    return cloud


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
