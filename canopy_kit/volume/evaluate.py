"""Volume accuracy on simulated sessions: per-tree clouds, complete and one-sided, and
each method's error against the simulator's exact crown volume.

A tree's points are those the simulator's ``tree_id`` field gives it in the reference map
built with the true poses (so segmentation and odometry errors are left out). Its
one-sided scans keep the points observed while the sensor was on one side of the tree's
row line (the line fitted through the trunks of that row).
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


def _row_directions(trees: Any) -> dict[int, np.ndarray]:
    """Unit along-row direction per row, fitted through the row's trunk positions."""
    out = {}
    for row, group in trees.groupby("row"):
        xy = group[["x", "y"]].to_numpy()
        if len(xy) < 2:
            out[int(row)] = np.array([1.0, 0.0])
            continue
        centred = xy - xy.mean(axis=0)
        direction = np.linalg.svd(centred, full_matrices=False)[2][0]
        if direction @ (xy[-1] - xy[0]) < 0:
            direction = -direction
        out[int(row)] = direction
    return out


def simulated_trees(sim_dir: str | Path, voxel_size: float = 0.1, map_voxel_size: float = 0.05,
                    reference_map: Any = None,
                    progress: ProgressCallback | None = None) -> list[SimulatedTree]:
    """Per-tree clouds of a simulated session, voxel-thinned to ``voxel_size`` (paper: 0.1 m).

    ``reference_map`` (a PointCloud with ``tree_id`` and ``time`` fields) is built from the
    session with the true poses when not given.
    """
    from canopy_kit.cloud import PointCloud
    from canopy_kit.truth import load_truth, true_pose_interpolator
    from canopy_kit.truth_map import truth_map
    from canopy_kit.voxel import voxel_downsample

    truth = load_truth(sim_dir)
    cloud = reference_map if reference_map is not None else truth_map(
        sim_dir, voxel_size=map_voxel_size, progress=progress)
    pose_at = true_pose_interpolator(sim_dir)
    directions = _row_directions(truth.trees)
    tree_ids = np.asarray(cloud.fields["tree_id"])
    times = np.asarray(cloud.fields["time"])

    def thin(xyz: np.ndarray) -> np.ndarray:
        return voxel_downsample(PointCloud(xyz), voxel_size).xyz if voxel_size else xyz

    out = []
    for _, tree in truth.trees.iterrows():
        mask = tree_ids == tree.tree_id
        xyz = cloud.xyz[mask]
        along = directions[int(tree.row)]
        across = np.array([-along[1], along[0]])
        trunk = np.array([tree.x, tree.y])
        sensor_xy = pose_at(times[mask])[0][:, :2]
        side = (sensor_xy - trunk) @ across
        out.append(SimulatedTree(int(tree.tree_id), str(tree.label), float(tree.crown_volume_m3),
                                 trunk, across, thin(xyz),
                                 {"left": thin(xyz[side > 0]), "right": thin(xyz[side < 0])}))
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


def volume_errors(trees: list[SimulatedTree], specs: list[MethodSpec],
                  progress: ProgressCallback | None = None) -> Any:
    """One row per tree, scan (complete, left, right) and method: volume, truth, error."""
    import pandas as pd

    rows = []
    total = len(trees)
    for i, tree in enumerate(trees):
        scans = {"complete": tree.complete, **tree.sides}
        for scan, xyz in scans.items():
            for spec in specs:
                result = spec.run(tree, xyz)
                rows.append({"tree": tree.label, "scan": scan, "method": spec.label,
                             "n_points": len(xyz), "volume_m3": result.volume_m3,
                             "true_volume_m3": tree.true_volume_m3, "valid": result.valid,
                             "error": result.volume_m3 / tree.true_volume_m3 - 1})
        if progress:
            progress("volumes", i + 1, total)
    return pd.DataFrame(rows)


def error_table(errors: Any) -> Any:
    """MAPE and bias (mean signed error) per scan kind (complete / one-sided) and method."""
    df = errors.assign(scan=np.where(errors["scan"] == "complete", "complete", "one-sided"),
                       abs_error=errors["error"].abs())
    grouped = df.groupby(["scan", "method"], sort=False)
    return grouped.agg(n=("error", "size"), mape=("abs_error", "mean"), bias=("error", "mean"),
                       invalid=("valid", lambda v: int((~v).sum()))).reset_index()


def alley_sides(sim_dir: str | Path, cloud: Any, trees: Any) -> np.ndarray:
    """Per map point: +1 / -1 for the side of its tree's row the sensor was on when the point
    was measured (true poses, row line fitted through the trunks), 0 for points of no tree."""
    from canopy_kit.truth import true_pose_interpolator

    pose_at = true_pose_interpolator(sim_dir)
    tree_id = np.asarray(cloud.fields["tree_id"])
    side = np.zeros(len(cloud), dtype=np.int8)
    directions = _row_directions(trees)
    for row, group in trees.groupby("row"):
        along = directions[int(row)]
        across = np.array([-along[1], along[0]])
        on_row = np.isin(tree_id, group["tree_id"].to_numpy())
        sensor_xy = pose_at(np.asarray(cloud.fields["time"])[on_row])[0][:, :2]
        centre = group[["x", "y"]].to_numpy().mean(axis=0)
        side[on_row] = np.sign((sensor_xy - centre) @ across).astype(np.int8)
    return side


def segmented_volume_errors(sim_dir: str | Path, config: Any, methods: list[str],
                            reference_map: Any = None) -> tuple[Any, Any]:
    """Volume errors on the trees the pipeline segments, as trees.csv measures them.

    The map (true poses unless ``reference_map`` is given) is segmented with ``config``'s
    segmenter; each segment matched one-to-one to a simulated tree (IoU ≥ 0.5) is measured
    by the volume stage with ``config.volume`` whole (scan ``both``) and keeping only the
    points seen from each alley (``left``, ``right``). Returns one row per tree, scan and
    method (``interval`` rows say whether the recommended estimator's interval held the
    truth) and the segmentation score.
    """
    import pandas as pd

    from canopy_kit.evaluate import score_point_labels
    from canopy_kit.io.las_write import on_las_grid
    from canopy_kit.segment.verb import make_segmenter, segment
    from canopy_kit.trees import measure_trees, volume_column
    from canopy_kit.truth import load_truth
    from canopy_kit.truth_map import truth_map

    truth = load_truth(sim_dir)
    cloud = on_las_grid(reference_map if reference_map is not None
                        else truth_map(sim_dir, voxel_size=0.05))
    seg = segment(cloud, make_segmenter(config.segment.method, config.segment.params),
                  config.preprocess, config.rows, seed=config.seed)
    score = score_point_labels(seg.labels, np.asarray(cloud.fields["tree_id"]))
    correct = score.trees[score.trees["status"] == "correct"]
    true_id_of = dict(zip(correct["segment_id"], correct["truth_id"], strict=True))
    true_volume = truth.trees.set_index("tree_id")["crown_volume_m3"]
    side = alley_sides(sim_dir, cloud, truth.trees)
    rows = []
    for scan, keep in [("both", None), ("left", side > 0), ("right", side < 0)]:
        labels = seg.labels if keep is None else np.where(keep, seg.labels, -1)
        table = measure_trees(cloud, labels, config.volume, ground_height=seg.ground.height)
        for tree in table.itertuples(index=False):
            true_id = true_id_of.get(int(tree.segment))
            if true_id is None:
                continue
            truth_v = float(true_volume[true_id])
            base = {"scan": scan, "tree": int(true_id), "true_volume_m3": truth_v}
            for method in methods:
                v = float(getattr(tree, volume_column(method)))
                rows.append({**base, "method": method, "volume_m3": v, "error": v / truth_v - 1})
            rows.append({**base, "method": "interval", "volume_m3": np.nan, "error": np.nan,
                         "covered": bool(tree.volume_low_m3 <= truth_v <= tree.volume_high_m3),
                         "coverage": float(tree.scan_coverage),
                         "flags": str(tree.volume_interval_flags)})
    return pd.DataFrame(rows), score
