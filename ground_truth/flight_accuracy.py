"""How good is the aerial ground truth? Crowns and cameras against a simulator's exact truth.

Used by the tests, the benchmark and docs/GROUND_TRUTH.md. The yardsticks are the
simulator's ``trees.csv`` (crown centre, widest extent, mean of perpendicular extents,
exact envelope volume) and ``drone_cameras.csv`` (true camera centres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.evaluate.stats import agreement
from ground_truth.camera import PosedCamera, camera_from_pose
from ground_truth.match import assign
from ground_truth.raster import Grid
from ground_truth.sfm import SparseModel


def true_cameras(cameras_csv: str | Path) -> list[PosedCamera]:
    """The simulator's camera poses and intrinsics (``truth/drone_cameras.csv``), in its
    order."""
    from scipy.spatial.transform import Rotation

    table = pd.read_csv(cameras_csv)
    rotations = Rotation.from_quat(table[["qx", "qy", "qz", "qw"]].to_numpy()).as_matrix()
    return [
        camera_from_pose(
            r.image, "SIMPLE_PINHOLE", (r.focal_px, r.cx, r.cy), r.width, r.height,
            np.array([r.x, r.y, r.z]), rotation,
        )
        for r, rotation in zip(table.itertuples(), rotations, strict=True)
    ]  # fmt: skip


def camera_errors(model: SparseModel, cameras_csv: str | Path) -> pd.DataFrame:
    """Distance of every registered camera centre from its true position (metres)."""
    truth = pd.read_csv(cameras_csv).set_index("image")
    rows = []
    for name, cam in sorted(model.cameras.items()):
        t = truth.loc[name, ["x", "y", "z"]].to_numpy(float)
        d = cam.center - t
        rows.append(
            {"image": name, "dx": d[0], "dy": d[1], "dz": d[2], "error_m": float(np.linalg.norm(d))}
        )
    return pd.DataFrame(rows)


def crown_agreement(
    crowns: pd.DataFrame,
    truth: pd.DataFrame,
    max_distance_m: float = 1.5,
    exclude_border: bool = True,
) -> tuple[pd.DataFrame, dict]:
    """Match crowns one-to-one to true trees (Hungarian, gated) and summarise the errors.

    Returns (per-tree table, metrics). Detection rate: trees with exactly one crown within
    the gate. Crowns cut by the mosaic border are left out when ``exclude_border``. With the
    columns of ``canopy_kit.sim.truth.crown_row_extents`` merged into ``truth``, the along-
    and across-row extents are scored too (MAE and bias; ``*_free_m``: crowns that touch no
    other crown).
    """
    c = (
        crowns[~crowns["touches_border"]]
        if exclude_border and "touches_border" in crowns
        else crowns
    )
    c = c.reset_index(drop=True)
    ia, ib, dist = assign(
        truth[["crown_x", "crown_y"]].to_numpy(), c[["x", "y"]].to_numpy(), max_distance_m
    )
    t = truth.iloc[ia].reset_index(drop=True)
    m = c.iloc[ib].reset_index(drop=True)
    table = pd.DataFrame(
        {
            "tree_id": t["tree_id"].to_numpy(),
            "label": t["label"],
            "row": t["row"],
            "distance_m": dist,
            "diameter_true_m": t["crown_diameter_m"],
            "diameter_m": m["diameter_max_m"],
            "diameter_mean_true_m": t["crown_diameter_mean_m"],
            "diameter_mean_m": m["diameter_mean_m"],
            "height_true_m": t["tree_height_m"],
            "height_m": m["height_m"],
            "volume_true_m3": t["crown_volume_m3"],
            "sphere_true_diameter_m3": t["sphere_volume_m3"],
            "sphere_volume_m3": m["sphere_volume_m3"],
            "sphere_volume_mean_m3": m["sphere_volume_mean_m3"],
            "ellipsoid_volume_m3": m["ellipsoid_volume_m3"],
            "chm_volume_m3": m["chm_volume_m3"],
            "envelope_volume_m3": m.get("envelope_volume_m3", pd.Series(np.nan, index=m.index)),
            "hull_volume_m3": m.get("hull_volume_m3", pd.Series(np.nan, index=m.index)),
        }
    )
    if "crown_id" in m:
        table["crown_id"] = m["crown_id"].to_numpy()
    if "extent_along_row_m" in t and "diameter_along_row_m" in m:
        table["along_row_true_m"] = t["extent_along_row_m"].to_numpy()
        table["along_row_m"] = m["diameter_along_row_m"].to_numpy()
        table["across_row_true_m"] = t["extent_across_row_m"].to_numpy()
        table["across_row_m"] = m["diameter_across_row_m"].to_numpy()
        table["shared_outline_fraction"] = m["shared_outline_fraction"].to_numpy()
    err = table["diameter_m"] - table["diameter_true_m"]
    err_mean = table["diameter_mean_m"] - table["diameter_mean_true_m"]
    metrics = {
        "trees": int(len(truth)),
        "crowns": int(len(c)),
        "matched": int(len(table)),
        "detection_rate": float(len(table) / max(len(truth), 1)),
        "unmatched_crowns": int(len(c) - len(table)),
        "centre_error_mean_m": float(dist.mean()) if len(dist) else np.nan,
        "diameter_mae_m": float(err.abs().mean()) if len(err) else np.nan,
        "diameter_bias_m": float(err.mean()) if len(err) else np.nan,
        "diameter_mean_mae_m": float(err_mean.abs().mean()) if len(err) else np.nan,
        "diameter_mean_bias_m": float(err_mean.mean()) if len(err) else np.nan,
        "height_mae_m": float((table["height_m"] - table["height_true_m"]).abs().mean())
        if len(err)
        else np.nan,
    }
    if "along_row_m" in table:  # NaN where no crown matched, so the keys are always there
        free = table["shared_outline_fraction"] == 0
        for side in ("along", "across"):
            e = table[f"{side}_row_m"] - table[f"{side}_row_true_m"]
            metrics[f"{side}_row_mae_m"] = float(e.abs().mean()) if len(e) else np.nan
            metrics[f"{side}_row_bias_m"] = float(e.mean()) if len(e) else np.nan
            metrics[f"{side}_row_mae_free_m"] = (
                float(e[free].abs().mean()) if free.any() else np.nan
            )
        metrics["free_standing"] = int(free.sum())
    if len(table) >= 2:
        for name, col in (
            ("sphere_from_true_diameter", "sphere_true_diameter_m3"),
            ("sphere_aerial", "sphere_volume_m3"),
            ("sphere_mean_aerial", "sphere_volume_mean_m3"),
            ("ellipsoid_aerial", "ellipsoid_volume_m3"),
            ("chm_aerial", "chm_volume_m3"),
            ("envelope_aerial", "envelope_volume_m3"),
            ("hull_aerial", "hull_volume_m3"),
        ):
            known = table[col].notna()  # NaN: a model not measured (or a hull with too few views)
            if known.sum() < 2:
                continue
            a = agreement(
                table.loc[known, col].to_numpy(float),
                table.loc[known, "volume_true_m3"].to_numpy(float),
            )
            metrics[f"volume_{name}_bias_pct"] = a.bias_pct
            metrics[f"volume_{name}_mape_pct"] = a.mape_pct
    return table, metrics


def trees_per_crown(
    labels: np.ndarray, grid: Grid, crowns: pd.DataFrame, truth: pd.DataFrame
) -> np.ndarray:
    """How many true crown centres (``crown_x``, ``crown_y`` of the simulator's trees) lie in
    each crown's label: 1 for a crown of one tree, 2 or more for trees merged into one
    label, 0 for a fragment (or a crown of no tree)."""
    r, c = grid.index(truth["crown_x"].to_numpy(float), truth["crown_y"].to_numpy(float))
    r, c = np.round(r).astype(int), np.round(c).astype(int)
    inside = (r >= 0) & (r < labels.shape[0]) & (c >= 0) & (c < labels.shape[1])
    hit = labels[r[inside], c[inside]]
    counts = pd.Series(hit[hit > 0]).value_counts()
    ids = crowns["crown_id"].astype(int)
    return ids.map(counts).fillna(0).astype(int).to_numpy()
