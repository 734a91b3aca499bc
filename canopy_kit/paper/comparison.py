"""The experiments table: per orchard, segmenter and mapping, our figures beside the paper's.

Segmentation success is pooled over seeds (trees correct / true trees) with the range of
the per-seed rates (:func:`canopy_kit.paper.segmentation_results.success_table`); volume
statistics pool the correctly segmented trees of all seeds. The paper has volume figures only for its
pistachio DBSCAN run (Table I).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    from canopy_kit.paper.experiments import ExperimentConfig

#: Volume reference -> per-tree table column (``aerial`` only with a simulated drone flight).
REFERENCES = {
    "sphere": "true_sphere_volume_m3",
    "crown": "true_crown_volume_m3",
    "aerial": "aerial_sphere_volume_m3",
}
#: The paper's two estimators, first in every table.
ESTIMATORS = ("convex_hull", "alpha_shape")
#: Segmentation success printed in the paper's text (§II.C.1, §III.A, §III.B).
PAPER_SEGMENTATION = {
    ("pistachio", "dbscan"): 0.93,
    ("almond", "dbscan"): 0.46,
    ("almond", "dbscan_spectral"): 0.80,
}


def volume_errors(trees: pd.DataFrame, estimator: str, reference: str) -> pd.Series:
    """Signed % error of ``estimator`` against ``reference`` on the correctly segmented trees."""
    from canopy_kit.volume.verb import volume_column

    col, ref = volume_column(estimator), REFERENCES[reference]
    if col not in trees or ref not in trees:
        return pd.Series(dtype=float)
    ok = trees["truth_tree_id"].notna() & trees[col].notna() & trees[ref].notna()
    return 100.0 * (trees.loc[ok, col] - trees.loc[ok, ref]) / trees.loc[ok, ref]


def estimators_in(trees: pd.DataFrame) -> list[str]:
    """Volume estimators with a column in a per-tree table: the paper's two first."""
    from canopy_kit.volume.verb import VOLUME_COLUMN

    named = {v: k for k, v in VOLUME_COLUMN.items()}
    found = [
        named.get(c, c[len("volume_") : -len("_m3")])
        for c in trees.columns
        if c.startswith("volume_") and c.endswith("_m3") and trees[c].notna().any()
    ]
    return [e for e in ESTIMATORS if e in found] + [e for e in found if e not in ESTIMATORS]


def volume_summary(trees: pd.DataFrame) -> dict[str, float]:
    """MAPE, bias, largest error per estimator x reference, and alpha-better counts."""
    out: dict[str, float] = {}
    for reference in REFERENCES:
        errs = {e: volume_errors(trees, e, reference) for e in estimators_in(trees)}
        for est, err in errs.items():
            if len(err) == 0:
                continue
            out[f"{est}_mape_vs_{reference}_pct"] = float(err.abs().mean())
            out[f"{est}_bias_vs_{reference}_pct"] = float(err.mean())
            out[f"{est}_max_error_vs_{reference}_pct"] = float(err.abs().max())
        if "convex_hull" not in errs or "alpha_shape" not in errs:
            continue
        hull, alpha = errs["convex_hull"], errs["alpha_shape"]
        both = hull.index.intersection(alpha.index)
        if len(both):
            out[f"alpha_better_vs_{reference}"] = int((alpha[both].abs() < hull[both].abs()).sum())
            out[f"n_trees_vs_{reference}"] = len(both)
    return out


def compare(
    runs: pd.DataFrame, trees: pd.DataFrame, paper: dict[str, Any], config: ExperimentConfig
) -> pd.DataFrame:
    """One row per orchard x method x mapping of ``config``: the paper's figure beside ours
    for segmentation success and volume errors."""
    from canopy_kit.evaluate.truth import orchard_kind
    from canopy_kit.paper.segmentation_results import success_table

    rows = []
    ok_runs = runs[runs["error"] == ""] if "error" in runs else runs
    for mapping in config.mappings:
        sub = ok_runs[ok_runs["mapping"] == mapping]
        seeds = success_table(sub, "success_rate") if len(sub) else pd.DataFrame()
        for orchard in config.orchards:
            for method in config.methods:
                key = (orchard_kind(orchard), method)
                r = sub[(sub["orchard"] == orchard) & (sub["method"] == method)]
                row: dict[str, Any] = {
                    "orchard": orchard,
                    "method": method,
                    "mapping": mapping,
                    "sessions": len(r),
                    "failed_runs": int(
                        (
                            (runs["mapping"] == mapping)
                            & (runs["orchard"] == orchard)
                            & (runs["method"] == method)
                        ).sum()
                        - len(r)
                    ),
                    "paper_success_pct": 100 * PAPER_SEGMENTATION[key]
                    if key in PAPER_SEGMENTATION
                    else np.nan,
                    "n_truth": int(r["n_truth"].sum()),
                    "n_correct": int(r["n_correct"].sum()),
                }
                row["success_pct"] = (
                    100 * row["n_correct"] / row["n_truth"] if row["n_truth"] else np.nan
                )
                has = len(seeds) and method in seeds.index and ("min", orchard) in seeds.columns
                row["success_min_pct"] = (
                    100 * seeds.loc[method, ("min", orchard)] if has else np.nan
                )
                row["success_max_pct"] = (
                    100 * seeds.loc[method, ("max", orchard)] if has else np.nan
                )
                for k in ("n_merged", "n_split", "n_missed", "n_other"):
                    row[k] = int(r[k].sum())
                row["map_points_per_tree_median"] = (
                    float(r["map_points_per_tree_median"].median())
                    if "map_points_per_tree_median" in r
                    else np.nan
                )
                row["ate_rmse_m"] = float(r["ate_rmse_m"].mean()) if len(r) else np.nan
                paper_volumes = key == ("pistachio", "dbscan")
                for est in ESTIMATORS:
                    row[f"paper_{est}_mape_vs_sphere_pct"] = (
                        paper["mape_vs_sphere_pct"][est] if paper_volumes else np.nan
                    )
                    row[f"paper_{est}_max_error_vs_sphere_pct"] = (
                        paper["max_error_vs_sphere_pct"][est] if paper_volumes else np.nan
                    )
                row["paper_alpha_better"] = (
                    f"{paper['alpha_better_trees']}/{paper['n_trees']}" if paper_volumes else ""
                )
                t = (
                    trees[
                        (trees["orchard"] == orchard)
                        & (trees["method"] == method)
                        & (trees["mapping"] == mapping)
                    ]
                    if len(trees)
                    else trees
                )
                row.update(volume_summary(t) if len(t) else {})
                rows.append(row)
    return pd.DataFrame(rows)
