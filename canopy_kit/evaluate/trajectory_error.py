"""Mapping accuracy: trajectory error against a reference and map error against true surfaces.

- ATE: RMSE of positions after an SE(3) (Umeyama, no scale) alignment, through evo;
- drift: relative translation error over path segments of fixed length, in % of the
  segment length (KITTI-style, segments of 25/50/100/200 m that fit the drive);
- end drift: final position error after aligning the first seconds, in % of the path;
- map accuracy: distance of map points to the true scene surfaces (simulated sessions).

The reference is the bag's ground-truth odometry; the mapping itself never reads it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation, Slerp

from canopy_kit.core.cloud import PointCloud
from canopy_kit.core.extras import needs_extra
from canopy_kit.errors import InputError

SEGMENT_LENGTHS = (25.0, 50.0, 100.0, 200.0)


def _poses(table: pd.DataFrame) -> np.ndarray:
    out = np.tile(np.eye(4), (len(table), 1, 1))
    out[:, :3, :3] = Rotation.from_quat(table[["qx", "qy", "qz", "qw"]].to_numpy()).as_matrix()
    out[:, :3, 3] = table[["x", "y", "z"]].to_numpy()
    return out


def interpolate_reference(
    reference: pd.DataFrame, times: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Reference poses (N, 4, 4) at ``times`` (inside its span) and the mask of those times."""
    t = reference["time"].to_numpy()
    inside = (times >= t[0]) & (times <= t[-1])
    tt = times[inside]
    pos = np.column_stack([np.interp(tt, t, reference[c].to_numpy()) for c in ("x", "y", "z")])
    rot = Slerp(t, Rotation.from_quat(reference[["qx", "qy", "qz", "qw"]].to_numpy()))(tt)
    out = np.tile(np.eye(4), (len(tt), 1, 1))
    out[:, :3, :3] = rot.as_matrix()
    out[:, :3, 3] = pos
    return out, inside


def se3_alignment(estimated: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The rigid transform (4x4) that best maps estimated positions onto the reference (evo)."""
    with needs_extra("mapping"):
        from evo.core.trajectory import PoseTrajectory3D

    stamps = np.arange(len(estimated), dtype=float)
    est = PoseTrajectory3D(poses_se3=list(estimated), timestamps=stamps)
    ref = PoseTrajectory3D(poses_se3=list(reference), timestamps=stamps)
    r, t, _ = est.align(ref, correct_scale=False)
    a = np.eye(4)
    a[:3, :3] = r
    a[:3, 3] = t
    return a


def segment_drift(
    estimated: np.ndarray,
    reference: np.ndarray,
    lengths: tuple[float, ...] = SEGMENT_LENGTHS,
    step: float = 1.0,
) -> dict[str, float]:
    """Mean relative translation error (% of length) over segments of each length."""
    dist = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(reference[:, :3, 3], axis=0), axis=1))]
    out: dict[str, float] = {}
    starts = np.searchsorted(dist, np.arange(0.0, dist[-1], step))
    for length in lengths:
        if length > 0.75 * dist[-1]:
            continue
        ends = np.searchsorted(dist, dist[starts] + length)
        ok = ends < len(dist)
        if not ok.any():
            continue
        i, j = starts[ok], ends[ok]
        d_est = np.linalg.inv(estimated[i]) @ estimated[j]
        d_ref = np.linalg.inv(reference[i]) @ reference[j]
        err = np.linalg.norm((np.linalg.inv(d_ref) @ d_est)[:, :3, 3], axis=1)
        out[f"{int(length)}m"] = float(100.0 * np.mean(err / (dist[j] - dist[i])))
    return out


def trajectory_errors(
    trajectory: pd.DataFrame, reference: pd.DataFrame, start_window: float = 2.0
) -> dict[str, Any]:
    """ATE (SE(3)-aligned), per-axis ATE, segment drift and end drift against ``reference``."""
    times = trajectory["time"].to_numpy()
    ref, inside = interpolate_reference(reference, times)
    if inside.sum() < 10:
        raise InputError("trajectory and reference overlap in fewer than 10 poses; cannot evaluate")
    est = _poses(trajectory)[inside]
    align = se3_alignment(est, ref)
    aligned = align @ est
    err = aligned[:, :3, 3] - ref[:, :3, 3]
    rot_err = Rotation.from_matrix(np.einsum("nji,njk->nik", ref[:, :3, :3], aligned[:, :3, :3]))
    path = float(np.sum(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1)))
    # End drift: align on the first seconds only, as an odometry would start.
    t_in = times[inside]
    first = t_in <= t_in[0] + start_window
    a0 = ref[np.flatnonzero(first)[-1]] @ np.linalg.inv(est[np.flatnonzero(first)[-1]])
    end_err = float(np.linalg.norm((a0 @ est[-1])[:3, 3] - ref[-1, :3, 3]))
    drift = segment_drift(est, ref)
    return {
        "poses": int(inside.sum()),
        "path_length_m": path,
        "ate_rmse_m": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        "ate_rmse_xyz_m": np.sqrt(np.mean(err**2, axis=0)).tolist(),
        "ate_max_m": float(np.linalg.norm(err, axis=1).max()),
        "rotation_rmse_deg": float(np.degrees(np.sqrt(np.mean(rot_err.magnitude() ** 2)))),
        "drift_percent": float(np.mean(list(drift.values()))) if drift else float("nan"),
        "drift_percent_by_length": drift,
        "end_drift_percent": 100.0 * end_err / path if path > 0 else float("nan"),
        "alignment": align.tolist(),
    }


def absolute_errors(
    trajectory: pd.DataFrame, reference: pd.DataFrame, offset: np.ndarray
) -> dict[str, float]:
    """Position error with no alignment (georeferencing), after adding ``offset`` to the estimate."""
    times = trajectory["time"].to_numpy()
    ref, inside = interpolate_reference(reference, times)
    est = trajectory[["x", "y", "z"]].to_numpy()[inside] + offset
    err = est - ref[:, :3, 3]
    return {
        "rmse_m": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        "horizontal_rmse_m": float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1)))),
        "vertical_rmse_m": float(np.sqrt(np.mean(err[:, 2] ** 2))),
    }


def surface_distances(points: np.ndarray, raycasting_scene: Any) -> np.ndarray:
    """Unsigned distance (m) from each point to the nearest triangle of an Open3D scene."""
    with needs_extra("open3d"):
        import open3d as o3d

    query = o3d.core.Tensor(np.asarray(points, np.float32))
    return raycasting_scene.compute_distance(query).numpy().astype(np.float64)


def distance_summary(d: np.ndarray) -> dict[str, float]:
    """Mean, median, 90th percentile, RMS and the shares within 5 and 10 cm."""
    return {
        "mean_m": float(d.mean()),
        "median_m": float(np.median(d)),
        "p90_m": float(np.percentile(d, 90)),
        "rms_m": float(np.sqrt(np.mean(d**2))),
        "within_5cm": float(np.mean(d <= 0.05)),
        "within_10cm": float(np.mean(d <= 0.10)),
    }


def map_accuracy(
    cloud: PointCloud,
    raycasting_scene: Any,
    to_scene: np.ndarray | None = None,
    sample: int = 200_000,
    seed: int = 0,
) -> dict[str, float]:
    """Distances from (a seeded sample of) map points to the scene; ``to_scene`` maps local xyz."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(cloud), size=min(sample, len(cloud)), replace=False)
    xyz = cloud.xyz[idx]
    if to_scene is not None:
        xyz = xyz @ to_scene[:3, :3].T + to_scene[:3, 3]
    return distance_summary(surface_distances(xyz, raycasting_scene))


def estimate_in_frame(result: Any, frame: str | None) -> pd.DataFrame:
    """A mapping result's poses of ``frame``: its trajectory frame's or the LiDAR's.

    ``None`` or an unknown frame gives the trajectory as reported (the caller's reference
    says nothing about its frame)."""
    rig = getattr(result, "rig", None)
    if frame and rig is not None and frame != rig.base_name and frame == rig.lidar_frame:
        return result.sensor_trajectory
    return result.trajectory


def evaluate_against_simulation(
    result: Any,
    sim_dir: str | Path,
    reference: pd.DataFrame | None = None,
    truth_map_sample: bool = True,
) -> dict[str, Any]:
    """Trajectory and map errors of a :class:`MappingResult` on a simulated session."""
    from canopy_kit.evaluate.truth import load_truth

    truth = load_truth(sim_dir)
    if reference is None:
        reference = truth.trajectory_of(getattr(result, "trajectory_frame", ""))
        if reference is None:  # a base frame the simulator does not know: compare the LiDAR's poses
            reference = truth.trajectory
            reference.attrs["frame"] = truth.info.get("sensor_frame", "")
    estimate = estimate_in_frame(result, reference.attrs.get("frame"))
    report = trajectory_errors(estimate, reference)
    report["trajectory_frame"] = getattr(result, "trajectory_frame", "")
    # The map is in the frame of the poses, whichever frame they describe.
    align = np.array(report["alignment"])
    rc = truth.world().scene().raycasting_scene()
    report["map_aligned"] = map_accuracy(result.map, rc, align)
    if result.frame is not None:
        offset = result.frame.origin - truth.frame.origin
        report["georeferenced"] = absolute_errors(estimate, reference, offset)
        shift = np.eye(4)
        shift[:3, 3] = offset
        report["map_georeferenced"] = map_accuracy(result.map, rc, shift)
    return report


def reference_from_bag(bag_path: str | Path, topic: str | None = None) -> pd.DataFrame:
    """The bag's ground-truth odometry as a pose table (evaluation only)."""
    from canopy_kit.io.bag import open_bag

    with open_bag(bag_path) as bag:
        odo = bag.odometry(topic)
    if odo is None or len(odo.t) < 2:
        raise InputError(
            f"{bag_path}: no ground-truth odometry topic (nav_msgs/msg/Odometry) to "
            "evaluate against"
        )
    order = np.argsort(odo.t)
    table = pd.DataFrame(
        {
            "time": odo.t[order],
            "x": odo.position[order, 0],
            "y": odo.position[order, 1],
            "z": odo.position[order, 2],
            "qx": odo.orientation[order, 0],
            "qy": odo.orientation[order, 1],
            "qz": odo.orientation[order, 2],
            "qw": odo.orientation[order, 3],
        }
    )
    table.attrs["frame"] = odo.child_frame_id  # the frame whose poses these are
    return table


NO_TRAJECTORY = "not judged: no trajectory"
POSE_COLUMNS = ("time", "x", "y", "z", "qx", "qy", "qz", "qw")  # a trajectory with poses


def finished_map_errors(mapping: Any, sim_dir: Path) -> dict[str, Any]:
    """What a truth session can say of a map made elsewhere: its trajectory's ATE when it has
    times and orientations; else why the mapping is not judged."""
    if not mapping.has_trajectory:
        return {"not_judged": NO_TRAJECTORY}
    if not set(POSE_COLUMNS) <= set(mapping.trajectory.columns):
        return {"not_judged": "not judged: the trajectory has no times and orientations"}
    from canopy_kit.evaluate.truth import load_truth

    reference = load_truth(sim_dir).trajectory
    t = reference["time"].to_numpy()
    inside = mapping.trajectory["time"].between(t[0], t[-1])
    if inside.sum() < 10:  # trajectory_errors' own minimum
        return {"not_judged": "not judged: the trajectory's times are outside the truth's"}
    return trajectory_errors(mapping.trajectory[inside].reset_index(drop=True), reference)
