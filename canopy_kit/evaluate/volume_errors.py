"""Volume accuracy on simulated sessions: per-tree clouds, complete and one-sided, and
each method's error against the simulator's exact crown volume.

A tree's points are those the simulator's ``tree_id`` field gives it in the reference map
built with the true poses (so segmentation and odometry errors are left out). Its
one-sided scans are its points in the map of only the sweeps driven in the alley on one side
of its row line (:func:`canopy_kit.evaluate.truth_map.alley_maps`): what a drive along that alley
alone would have mapped.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.volume.base import VolumeResult

ProgressCallback = Callable[[str, float, float], None]


@dataclass
class SimulatedTree:
    """One simulated tree: truth and its points, complete and per side of its row."""

    tree_id: int
    label: str
    true_volume_m3: float
    trunk_xy: np.ndarray
    across_row: np.ndarray  # horizontal unit vector from the row line towards the "left" side
    complete: np.ndarray
    sides: dict[str, np.ndarray] = field(default_factory=dict)


def row_directions(trees: Any) -> dict[int, np.ndarray]:
    """Unit along-row direction per row, fitted through the row's trunk positions."""
    from canopy_kit.evaluate.truth_map import row_lines

    return {row: along for row, (_, along) in row_lines(trees).items()}


def simulated_trees(
    sim_dir: str | Path,
    voxel_size: float = 0.1,
    map_voxel_size: float = 0.05,
    reference_map: Any = None,
    progress: ProgressCallback | None = None,
) -> list[SimulatedTree]:
    """Per-tree clouds of a simulated session, voxel-thinned to ``voxel_size`` (paper: 0.1 m):
    complete (from ``reference_map``) and one-sided (``left``/``right`` of the row line, from
    the alley maps, :func:`canopy_kit.evaluate.truth_map.alley_maps`, on the same ``map_voxel_size``).

    ``reference_map`` (a PointCloud with a ``tree_id`` field) is built from the session with
    the true poses when not given.
    """
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.core.voxel import voxel_downsample
    from canopy_kit.evaluate.truth import load_truth
    from canopy_kit.evaluate.truth_map import alley_maps, truth_map

    truth = load_truth(sim_dir)
    cloud = (
        reference_map
        if reference_map is not None
        else truth_map(sim_dir, voxel_size=map_voxel_size, progress=progress)
    )
    directions = row_directions(truth.trees)
    tree_ids = np.asarray(cloud.fields["tree_id"])
    alleys = {
        key: (alley.xyz, np.asarray(alley.fields["tree_id"]))
        for key, alley in alley_maps(sim_dir, voxel_size=map_voxel_size).items()
    }
    empty = (np.empty((0, 3)), np.empty(0, dtype=tree_ids.dtype))

    def seen_from(row: int, side: int, tree_id: int) -> np.ndarray:
        xyz, ids = alleys.get((row, side), empty)
        return xyz[ids == tree_id]

    def thin(xyz: np.ndarray) -> np.ndarray:
        return voxel_downsample(PointCloud(xyz), voxel_size).xyz if voxel_size else xyz

    out = []
    for _, tree in truth.trees.iterrows():
        mask = tree_ids == tree.tree_id
        xyz = cloud.xyz[mask]
        along = directions[int(tree.row)]
        across = np.array([-along[1], along[0]])
        trunk = np.array([tree.x, tree.y])
        row = int(tree.row)
        out.append(
            SimulatedTree(
                int(tree.tree_id),
                str(tree.label),
                float(tree.crown_volume_m3),
                trunk,
                across,
                thin(xyz),
                {
                    "left": thin(seen_from(row, 1, int(tree.tree_id))),
                    "right": thin(seen_from(row, -1, int(tree.tree_id))),
                },
            )
        )
    return out


@dataclass(frozen=True)
class MethodSpec:
    """A volume method to evaluate: plugin name, parameters, and whether the mirror plane
    is given from the tree's trunk and row (as the pipeline knows them)."""

    label: str
    method: str
    params: dict[str, Any] = field(default_factory=dict)
    trunk_plane: bool = False

    def run(self, tree: SimulatedTree, xyz: np.ndarray) -> VolumeResult:
        """The method's result on one scan of one tree."""
        from canopy_kit.volume import estimate_volume

        params = dict(self.params)
        if self.trunk_plane:
            params.update(plane_point=tuple(tree.trunk_xy), plane_normal=tuple(tree.across_row))
        return estimate_volume(xyz, self.method, **params)


def volume_errors(
    trees: list[SimulatedTree], specs: list[MethodSpec], progress: ProgressCallback | None = None
) -> Any:
    """One row per tree, scan (complete, left, right) and method: volume, truth, error."""
    import pandas as pd

    rows = []
    total = len(trees)
    for i, tree in enumerate(trees):
        scans = {"complete": tree.complete, **tree.sides}
        for scan, xyz in scans.items():
            for spec in specs:
                result = spec.run(tree, xyz)
                rows.append(
                    {
                        "tree": tree.label,
                        "scan": scan,
                        "method": spec.label,
                        "n_points": len(xyz),
                        "volume_m3": result.volume_m3,
                        "true_volume_m3": tree.true_volume_m3,
                        "valid": result.valid,
                        "error": result.volume_m3 / tree.true_volume_m3 - 1,
                    }
                )
        if progress:
            progress("volumes", i + 1, total)
    return pd.DataFrame(rows)


def error_table(errors: Any) -> Any:
    """MAPE and bias (mean signed error) per scan kind (complete / one-sided) and method."""
    df = errors.assign(
        scan=np.where(errors["scan"] == "complete", "complete", "one-sided"),
        abs_error=errors["error"].abs(),
    )
    grouped = df.groupby(["scan", "method"], sort=False)
    return grouped.agg(
        n=("error", "size"),
        mape=("abs_error", "mean"),
        bias=("error", "mean"),
        invalid=("valid", lambda v: int((~v).sum())),
    ).reset_index()
