"""Check a run against a simulated session's truth: segmentation, labels, volumes, mapping."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.errors import InputError
from canopy_kit.evaluate import stats

# Points per m² of leaf surface in the complete foliage a run's measurand truth is measured
# on: a quarter of the benchmarks' 4000, which fills the same 0.1 m voxels (on a 3 x 6 almond
# session the recommended volumes differ by 0.01-0.16 %) in a third of the time.
MEASURAND_DENSITY = 1000.0


def truth_offset(
    run_origin: np.ndarray, run_crs: str | None, truth_origin: np.ndarray, truth_crs: str
) -> np.ndarray:
    """Vector to add to run-local coordinates to get truth-local ones (same CRS required)."""
    if run_crs is None:
        raise InputError(
            "the map has no CRS (no GNSS?): footprints cannot be compared with the "
            "truth; keep the per-point truth field for evaluation"
        )
    if run_crs != truth_crs:
        raise InputError(f"map CRS {run_crs} differs from the truth's {truth_crs}")
    return np.asarray(run_origin, float) - np.asarray(truth_origin, float)


def score_segmentation(ctx: Any, sim_dir: Path, alignment: Any = None) -> Any:
    """Segmentation score: per-point truth labels when the map carries them, else footprints.

    Footprints are placed in the truth's frame by ``alignment`` (4 x 4: the drive's best fit
    to the true poses, the one ATE is measured after) when given, else by the map's
    georeference: a metre-level receiver's offset would otherwise be scored as a
    segmentation error (the georeference is judged on its own, mapping "georeferenced").
    On a wall (trees.csv ``volume_truth`` "trunk-midpoint cut") a point hit on a crown is the
    tree whose cut holds it (``evaluate.wall_cuts``)."""
    from canopy_kit.evaluate.segmentation_score import (
        score_footprints,
        score_point_labels,
        truth_footprints,
    )
    from canopy_kit.evaluate.truth import load_truth
    from canopy_kit.evaluate.wall_cuts import cut_labels, is_wall_truth

    truth = load_truth(sim_dir)
    seg, cloud = ctx.segmentation, ctx.mapping.map
    truth_labels = truth.trees.set_index("tree_id")[["row", "label"]]
    pred_labels = seg.table().set_index("segment_id")[["row", "label"]]
    if "tree_id" in cloud.fields:
        field = np.asarray(cloud.fields["tree_id"]).astype(np.int64)
        if is_wall_truth(truth.trees):  # a wall's tree is its trunk-midpoint cut (issue 52)
            field = cut_labels(_in_truth_frame(cloud, truth, alignment), field, truth.trees)
        observed = sorted(set(np.unique(field[field >= 0]).tolist()) & set(truth_labels.index))
        return score_point_labels(
            seg.labels, field, truth_labels=truth_labels.loc[observed], pred_labels=pred_labels
        )
    if alignment is not None:
        a = np.asarray(alignment, dtype=float)
        pred = {k: np.asarray(v) @ a[:2, :2].T + a[:2, 3] for k, v in seg.footprints.items()}
    else:
        shift = truth_offset(cloud.origin, cloud.crs, truth.frame.origin, truth.frame.crs)[:2]
        pred = {k: v + shift for k, v in seg.footprints.items()}
    return score_footprints(
        pred, truth_footprints(sim_dir), truth_labels=truth_labels, pred_labels=pred_labels
    )


def _in_truth_frame(cloud: Any, truth: Any, alignment: Any) -> np.ndarray:
    """The map's points x, y in the truth's local frame: by ``alignment`` (4 x 4, the drive's
    best fit to the true poses) when given, else by the georeference (none: the same frame)."""
    xyz = np.asarray(cloud.xyz, float)
    if alignment is not None:
        a = np.asarray(alignment, dtype=float)
        return xyz[:, :2] @ a[:2, :2].T + xyz[:, 2:3] * a[:2, 2] + a[:2, 3]
    if cloud.crs is None:
        return xyz[:, :2]
    return (
        xyz[:, :2] + truth_offset(cloud.origin, cloud.crs, truth.frame.origin, truth.frame.crs)[:2]
    )


def evaluate_against_truth(ctx: Any, trees: pd.DataFrame, sim_dir: Path) -> dict[str, Any]:
    """Scores of a run against simulator truth, and the tree table with truth columns added.

    On a wall (trees.csv ``volume_truth`` "trunk-midpoint cut", issue 52) segments are matched
    to the trees' cuts and volumes compared with ``cut_volume_m3`` (``true_crown_volume_m3``
    then holds it); the measurand (one crown's complete foliage) is not a wall tree's."""
    from canopy_kit.evaluate.truth import load_truth
    from canopy_kit.evaluate.wall_cuts import WALL_TRUTH, is_wall_truth
    from canopy_kit.volume.verb import volume_column, volume_methods

    truth = load_truth(sim_dir)
    wall = is_wall_truth(truth.trees)
    mapping_eval = _mapping_evaluation(ctx, sim_dir)
    score = score_segmentation(ctx, sim_dir, mapping_eval.get("alignment"))
    pairs = score.trees[score.trees["segment_id"] >= 0][["truth_id", "segment_id", "iou"]]
    t = truth.trees.set_index("tree_id")
    if wall:
        t["crown_volume_m3"] = t["cut_volume_m3"]
    matched = pairs.join(
        t[
            [
                "label",
                "row",
                "crown_volume_m3",
                "sphere_volume_m3",
                "crown_diameter_m",
                "tree_height_m",
            ]
        ],
        on="truth_id",
    )
    matched = matched.rename(
        columns={
            "truth_id": "truth_tree_id",
            "segment_id": "segment",
            "label": "truth_label",
            "row": "truth_row",
            "crown_volume_m3": "true_crown_volume_m3",
            "sphere_volume_m3": "true_sphere_volume_m3",
            "crown_diameter_m": "true_crown_diameter_m",
            "tree_height_m": "true_height_m",
            "iou": "truth_iou",
        }
    )
    out = trees.merge(matched, on="segment", how="left")
    volumes: dict[str, Any] = {}
    ok = out["true_crown_volume_m3"].notna()
    for method in volume_methods(ctx.config.volume):
        col = volume_column(method)
        if col not in out:
            continue
        out[f"error_{method}_vs_true_pct"] = (
            100 * (out[col] - out["true_crown_volume_m3"]) / out["true_crown_volume_m3"]
        )
        good = ok & out[col].notna()
        if good.sum() >= 2:
            volumes[method] = stats.agreement(
                out.loc[good, col].to_numpy(), out.loc[good, "true_crown_volume_m3"].to_numpy()
            ).as_dict()
    if ok.sum() >= 2:
        volumes["sphere_from_lidar_diameter"] = stats.agreement(
            out.loc[ok, "sphere_volume_m3"].to_numpy(),
            out.loc[ok, "true_crown_volume_m3"].to_numpy(),
        ).as_dict()
        volumes["diameter_mae_m"] = float(
            np.mean(np.abs(out.loc[ok, "crown_diameter_m"] - out.loc[ok, "true_crown_diameter_m"]))
        )
    measurand = None if wall else _measurand_truth(truth, out, ctx.config.volume)
    rec = ctx.config.volume.recommended
    if measurand is not None:
        out["true_measurand_m3"] = measurand
        col = volume_column(rec)
        out[f"error_{rec}_vs_measurand_pct"] = 100 * (out[col] - measurand) / measurand
        good = measurand.notna() & out[col].notna() & (measurand > 0)
        if good.sum() >= 2:
            volumes["recommended_vs_measurand"] = stats.agreement(
                out.loc[good, col].to_numpy(), measurand[good].to_numpy()
            ).as_dict()
        held = interval_holds(out, measurand)
        if held is not None:
            volumes["recommended_interval"] = held
    result: dict[str, Any] = {
        "segmentation": score.to_dict(),
        "volumes": volumes,
        "recommended_volume": ctx.config.volume.recommended,
        "volume_truth": WALL_TRUTH if wall else "crown",
        "segmentation_trees": score.trees,
        "trees": out,
    }
    if mapping_eval:
        result["mapping"] = mapping_eval
    return result


def interval_holds(trees: pd.DataFrame, measurand: pd.Series) -> dict[str, Any] | None:
    """How many trees' interval (``volume_low_m3`` … ``volume_high_m3``) holds their
    measurand, and the IoU with their true tree of those it misses (a crown the segmentation
    cut wrongly is outside what the interval covers), and how many trees with a measurand
    claim no interval (``no_interval``: not counted); None without bounds or measurands."""
    if "volume_low_m3" not in trees or "volume_high_m3" not in trees:
        return None
    low, high = trees["volume_low_m3"], trees["volume_high_m3"]
    bounded = low.notna() & high.notna()
    known = measurand.notna() & bounded
    if not measurand.notna().any():
        return None
    inside = (low <= measurand) & (measurand <= high)
    missed = known & ~inside
    iou = trees["truth_iou"] if "truth_iou" in trees else pd.Series(np.nan, index=trees.index)
    return {
        "held": int((known & inside).sum()),
        "n": int(known.sum()),
        "missed_iou": [round(float(v), 3) for v in iou[missed]],
        "no_interval": int((measurand.notna() & ~bounded).sum()),
    }


def _measurand_truth(truth: Any, trees: pd.DataFrame, volume: Any) -> pd.Series | None:
    """Per row of ``trees``: the recommended estimator on the matched tree's complete foliage
    (as the measurand its estimate took: a sparse crown's ellipsoid), NaN where unmatched;
    None when the world model knows no complete foliage."""
    from canopy_kit.evaluate.volume_accuracy import foliage_references, reference_volume
    from canopy_kit.volume.uncertainty import measurand_of_kind

    rec = volume.recommended
    kinds = trees["crown_kind"] if "crown_kind" in trees else pd.Series("", index=trees.index)
    wanted: dict[int, set[str]] = {}
    for tree_id, kind in zip(trees["truth_tree_id"], kinds, strict=True):
        if pd.notna(tree_id):
            wanted.setdefault(int(tree_id), set()).add(measurand_of_kind(str(kind)))
    if not wanted or not hasattr(truth.world(), "complete_foliage"):
        return None
    refs = foliage_references(
        truth, list(wanted), volume, [rec], measurands=wanted, density=MEASURAND_DENSITY
    )
    values = [
        reference_volume(refs[int(t)], rec, str(k)) if pd.notna(t) else np.nan
        for t, k in zip(trees["truth_tree_id"], kinds, strict=True)
    ]
    return pd.Series(values, index=trees.index, dtype=float)


def _mapping_evaluation(ctx: Any, sim_dir: Path) -> dict[str, Any]:
    """ATE, drift and map-to-surface distances of the mapping result against the truth."""
    from canopy_kit.evaluate.trajectory_error import evaluate_against_simulation

    if getattr(ctx.mapping, "made_elsewhere", False):  # a finished map: its trajectory, if any
        from canopy_kit.evaluate.trajectory_error import finished_map_errors

        return finished_map_errors(ctx.mapping, sim_dir)
    if not hasattr(ctx.mapping, "config"):  # a map made from the true poses: nothing to score
        return {}
    return evaluate_against_simulation(ctx.mapping, sim_dir)
