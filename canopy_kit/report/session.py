"""The report of one pipeline run: summary, checks, figures, per-tree table and config."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.report.figures import figure_to_data_uri
from canopy_kit.report.html import Check, ReportSection, render_report

TABLE_COLUMNS = ["tree_id", "row", "label", "x", "y", "lat", "lon", "n_points", "height_m",
                 "crown_diameter_m", "volume_convex_hull_m3", "volume_alpha_m3",
                 "aerial_diameter_m", "aerial_sphere_volume_m3", "error_alpha_vs_aerial_pct",
                 "aerial_flag",
                 "true_crown_volume_m3", "error_alpha_shape_vs_true_pct", "volume_flags",
                 "segment_flags"]


def _fmt(value: float | None, unit: str = "", digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}{unit}"


def build_checks(metrics: dict[str, Any], trees: pd.DataFrame) -> list[Check]:
    """Validation checks with targets; ``passed`` None for information only."""
    checks = [Check("trees segmented", len(trees) > 0, str(len(trees)), "≥ 1")]
    share = metrics.get("flagged_volumes", 0) / max(len(trees), 1)
    checks.append(Check("volumes flagged as unreliable", share <= 0.10,
                        f"{metrics.get('flagged_volumes', 0)} ({100 * share:.0f} %)", "≤ 10 % of trees"))
    if "flagged_segments" in metrics:
        from canopy_kit.pipeline import flagged

        odd = trees.loc[flagged(trees, "segment_flags"), "tree_id"].astype(str).tolist()
        share = metrics["flagged_segments"] / max(len(trees), 1)
        checks.append(Check("crowns unlike the others (below 0.5x or above 1.6x the median "
                            "diameter: fragments or merged trees?)", share <= 0.10,
                            f"{metrics['flagged_segments']} ({100 * share:.0f} %)", "≤ 10 % of trees",
                            ", ".join(odd[:12]) + (" ..." if len(odd) > 12 else "")))
    from canopy_kit.report.rig import rig_check

    imu_check = rig_check(metrics.get("mapping", {}))
    if imu_check is not None:
        checks.append(imu_check)
    mapping = metrics.get("evaluation", {}).get("mapping", {})
    if "ate_rmse_m" in mapping:
        checks.append(Check("trajectory ATE RMSE (vs true odometry)", mapping["ate_rmse_m"] <= 0.20,
                            _fmt(mapping["ate_rmse_m"], " m", 3), "≤ 0.20 m"))
    if "drift_percent" in mapping:
        checks.append(Check("drift (% of path length)", mapping["drift_percent"] <= 0.5,
                            _fmt(mapping["drift_percent"], " %", 3), "≤ 0.5 %"))
    if "map_aligned" in mapping:
        d = mapping["map_aligned"]
        checks.append(Check("map points to true surfaces, after alignment (median)",
                            d["median_m"] <= 0.05, _fmt(d["median_m"], " m", 3), "≤ 0.05 m",
                            f"90 % within {_fmt(d['p90_m'], ' m', 3)}"))
    if "georeferenced" in mapping:
        g = mapping["georeferenced"]
        checks.append(Check("absolute position error of the trajectory (GNSS-limited)", None,
                            _fmt(g["horizontal_rmse_m"], " m", 2), "information",
                            f"vertical {_fmt(g['vertical_rmse_m'], ' m', 2)}"))
    seg = metrics.get("evaluation", {}).get("segmentation")
    if seg:
        checks.append(Check("trees segmented one-to-one (IoU ≥ 0.5)", seg["success_rate"] >= 0.95,
                            f"{seg['n_correct']}/{seg['n_truth']} ({100 * seg['success_rate']:.0f} %)",
                            "≥ 95 %", f"merged {seg['n_merged']}, split {seg['n_split']}, "
                            f"missed {seg['n_missed']}"))
        checks.append(Check("row and label correct", seg["label_accuracy"] >= 0.95,
                            f"{100 * seg['label_accuracy']:.0f} %", "≥ 95 % of matched trees"))
    vols = metrics.get("evaluation", {}).get("volumes", {})
    for method, target in (("alpha_shape", None), ("convex_hull", None)):
        if method in vols:
            checks.append(Check(f"{method} volume vs true crown volume (MAPE)", target,
                                _fmt(vols[method]["mape_pct"], " %", 1), "information",
                                f"bias {_fmt(vols[method]['bias_pct'], ' %', 1)}"))
    aerial = metrics.get("aerial")
    if aerial:
        matched = aerial.get("matched_trees", 0)
        checks.append(Check("LiDAR trees matched to an aerial crown", matched >= 0.9 * len(trees),
                            f"{matched}/{len(trees)}", "≥ 90 %"))
        compared = aerial.get("compared_trees", matched)
        checks.append(Check("matched aerial crowns of plausible size", compared >= 0.9 * matched,
                            f"{compared}/{matched}", "≥ 90 %",
                            "others are fragments or merged neighbours: flagged in the table, "
                            "left out of the comparison" if compared < matched else ""))
        for col, name in (("volume_alpha_m3", "alpha shape"), ("volume_convex_hull_m3", "convex hull")):
            if col in aerial:
                checks.append(Check(f"{name} vs aerial sphere volume (MAPE)", None,
                                    _fmt(aerial[col]["mape_pct"], " %", 1), "paper: 0-23 % per tree",
                                    f"R² {_fmt(aerial[col]['r_squared'])}"))
    for w in metrics.get("warnings", []):
        checks.append(Check("warning", None, "", "", str(w)))
    return checks


def session_report_page(ctx: Any, trees: pd.DataFrame, metrics: dict[str, Any]) -> str:
    """The report of a run as one self-contained HTML page."""
    from canopy_kit.config import config_toml
    from canopy_kit.pipeline import comparable_aerial_sphere, config_used
    from canopy_kit.report import plots

    cloud, seg = ctx.mapping.map, ctx.segmentation
    traj = ctx.mapping.trajectory
    sections = []
    from canopy_kit.segment.plots import plot_failure_gallery, plot_top_view

    map_fig = plot_top_view(cloud, seg)
    map_fig.axes[0].plot(traj["x"], traj["y"], "-", color="0.4", lw=0.7)
    figs = [("Map from above, each segmented tree in its own colour, labelled row:label; "
             "dashed: fitted rows; grey: the estimated drive.", figure_to_data_uri(map_fig))]
    volume_columns = {"convex hull": "volume_convex_hull_m3", "alpha shape": "volume_alpha_m3"}
    if "aerial_sphere_volume_m3" in trees:
        volume_columns["aerial sphere"] = "aerial_sphere_volume_m3"
    if "true_crown_volume_m3" in trees:
        volume_columns["true crown (simulator)"] = "true_crown_volume_m3"
    shown = trees
    if "aerial_sphere_volume_m3" in trees:  # a merged crown's sphere would dwarf every other bar
        shown = trees.assign(aerial_sphere_volume_m3=comparable_aerial_sphere(trees))
    figs.append(("Canopy volume per tree by method (aerial spheres of flagged crowns left out).",
                 figure_to_data_uri(plots.plot_volumes(shown, volume_columns))))
    sections.append(ReportSection("Map and trees", figs))
    mapping_eval = metrics.get("evaluation", {}).get("mapping")
    if mapping_eval and ctx.truth_dir is not None:
        from canopy_kit.mapping.plots import mapping_figures
        from canopy_kit.sim.truth import load_truth

        truth = load_truth(ctx.truth_dir)
        reference = truth.trajectory_of(getattr(ctx.mapping, "trajectory_frame", ""))
        mfigs = mapping_figures(ctx.mapping, truth.trajectory if reference is None else reference, mapping_eval)
        sections.append(ReportSection("Mapping", [
            ("Estimated trajectory (SE(3)-aligned) against the true one, and the position error "
             "over time.", figure_to_data_uri(mfigs["trajectory"])),
            ("The map from above: highest point per cell, coloured by height.",
             figure_to_data_uri(mfigs["map"]))]))
    from canopy_kit.report.rig import rig_section

    rig = rig_section(metrics.get("mapping", {}))
    if rig is not None:
        sections.append(rig)
    if ctx.aerial is not None and "aerial_sphere_volume_m3" in trees:
        ok = comparable_aerial_sphere(trees).notna() & trees["volume_alpha_m3"].notna()
        figs = []
        if ok.sum() >= 2:
            sub = trees[ok]
            figs.append(("Alpha-shape volume against the aerial sphere volume (paper §III.A); "
                         "trees with a flagged aerial crown left out.",
                         figure_to_data_uri(plots.plot_agreement(
                             sub["volume_alpha_m3"].to_numpy(), sub["aerial_sphere_volume_m3"].to_numpy(),
                             ("LiDAR alpha shape", "aerial sphere"), list(sub["label"])))))
        from ground_truth.plots import plot_crowns

        ax = plot_crowns(ctx.aerial.ortho, ctx.aerial.segmentation, ctx.aerial.crowns)
        figs.append(("Orthomosaic from the drone photos with the delineated crowns (red) and "
                     "their numbers.", figure_to_data_uri(ax.figure)))
        sections.append(ReportSection("LiDAR against drone photogrammetry", figs))
    if "true_crown_volume_m3" in trees:
        ok = trees["true_crown_volume_m3"].notna() & trees["volume_alpha_m3"].notna()
        if ok.sum() >= 2:
            sub = trees[ok]
            sections.append(ReportSection("Against the simulator's truth", [
                ("Alpha-shape volume against the exact crown volume.",
                 figure_to_data_uri(plots.plot_agreement(
                     sub["volume_alpha_m3"].to_numpy(), sub["true_crown_volume_m3"].to_numpy(),
                     ("LiDAR alpha shape", "true crown"), list(sub["label"]))))]))
    if ctx.truth_matches is not None and "tree_id" in cloud.fields:
        from canopy_kit.evaluate import score_point_labels

        score = score_point_labels(seg.labels, np.asarray(cloud.fields["tree_id"]))
        gallery = plot_failure_gallery(cloud, seg, score, np.asarray(cloud.fields["tree_id"]))
        if gallery is not None:
            sections.append(ReportSection("Segmentation failures", [
                ("Side views around each true tree that was not segmented one-to-one: truth "
                 "(left) and segmentation (right).", figure_to_data_uri(gallery))]))
    seg_m = metrics.get("segmentation", {})
    summary = {
        "trees": len(trees),
        "rows": seg_m.get("n_rows", "n/a"),
        "segmenter": metrics.get("segmenter", ""),
        "map points": f"{len(cloud):,}",
        "drive": _fmt(metrics.get("mapping", {}).get("path_length_m"), " m", 0),
        "median alpha volume": _fmt(float(trees["volume_alpha_m3"].median()) if len(trees) and "volume_alpha_m3" in trees else None, " m³", 1),
        "CRS": cloud.crs or "none",
    }
    table = trees[[c for c in TABLE_COLUMNS if c in trees]]
    return render_report(f"canopy-kit report: {ctx.config.name}", summary, table, sections,
                         build_checks(metrics, trees), config_toml(config_used(ctx)),
                         subtitle="Per-tree canopy volumes from a mobile LiDAR drive")
