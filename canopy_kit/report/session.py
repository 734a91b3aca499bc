"""The report of one pipeline run: summary, checks, figures, per-tree table and config."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.config import config_toml
from canopy_kit.evaluate.segmentation_score import score_point_labels
from canopy_kit.evaluate.truth import load_truth
from canopy_kit.io.csv_table import csv_text
from canopy_kit.report import plots
from canopy_kit.report.aerial import aerial_reference_text
from canopy_kit.report.columns import column_label
from canopy_kit.report.explorer import explorer_data, row_summary
from canopy_kit.report.figures import figure_to_data_uri
from canopy_kit.report.finished_map import finished_map_section
from canopy_kit.report.html import ReportSection, render_report
from canopy_kit.report.mapdecor import add_north_arrow_and_scale
from canopy_kit.report.rig import rig_section
from canopy_kit.report.volumes import accuracy_section
from canopy_kit.results.aerial_reference import recommended_aerial_column
from canopy_kit.results.checks import Check, format_value, run_checks
from canopy_kit.results.outputs import config_used, trees_geojson
from canopy_kit.results.tree_table import comparable_aerial_sphere
from canopy_kit.segment.export import crowns_geojson, rows_geojson
from canopy_kit.segment.plots import plot_failure_gallery, plot_top_view
from canopy_kit.volume.metrics import POSITION_AND_SIZE
from canopy_kit.volume.verb import ALPHA_COLUMN, CONVEX_HULL_COLUMN, volume_column
from ground_truth.crowns import describe_seeding
from ground_truth.plots import plot_crowns

TABLE_COLUMNS = [
    "tree_id",
    "row",
    "label",
    *POSITION_AND_SIZE,
    CONVEX_HULL_COLUMN,
    ALPHA_COLUMN,
    "aerial_diameter_m",
    "aerial_sphere_volume_m3",
    "error_alpha_vs_aerial_pct",
    "aerial_flag",
    "n_trunks",
    "true_crown_volume_m3",
    "error_alpha_shape_vs_true_pct",
    "volume_flags",
    "segment_flags",
]


def report_checks(metrics: dict[str, Any], trees: pd.DataFrame, config: Any) -> list[Check]:
    """The run's checks: those in ``metrics`` (metrics.json), else computed now."""
    if "checks" in metrics:
        return [Check(**c) for c in metrics["checks"]]
    return run_checks(metrics, trees, config.checks)


def session_report_page(
    ctx: Any,
    trees: pd.DataFrame,
    metrics: dict[str, Any],
    details: dict[str, Any] | None = None,
) -> str:
    """The report of a run as one self-contained HTML page (``details``: the drill-down's
    :func:`~canopy_kit.report.explorer.tree_details`, when made already)."""
    volume_cfg = ctx.config.volume
    sections = [map_and_trees_section(ctx, trees)]
    profiles = getattr(ctx, "row_profiles", None)
    if profiles is not None and len(profiles.summary):
        sections.append(row_metrics_section(profiles))
    sections.append(
        accuracy_section(
            volume_cfg.recommended,
            volume_cfg.params.get(volume_cfg.recommended, {}),
            volume_cfg.interval_kind,
        )
    )
    optional = (
        mapping_section(ctx, metrics.get("evaluation", {}).get("mapping")),
        rig_section(metrics.get("mapping", {})),
        aerial_section(ctx, trees),
        truth_volume_section(trees),
        segmentation_failures_section(ctx),
    )
    sections += [s for s in optional if s is not None]
    rec_column = volume_column(volume_cfg.recommended)
    table = trees[[c for c in table_columns(volume_cfg.recommended) if c in trees]]
    provenance = dict(metrics.get("provenance") or {})
    title, subtitle = report_title(provenance, ctx.config.name)
    downloads = report_downloads(ctx, trees, metrics.get("provenance"))
    return render_report(
        title,
        summary_items(ctx, trees, metrics),
        table,
        sections,
        report_checks(metrics, trees, ctx.config),
        config_toml(config_used(ctx)),
        subtitle=subtitle,
        provenance=provenance,
        explorer=explorer_data(ctx, trees, downloads, details=details),
        row_table=row_table(row_summary(trees, rec_column), rec_column),
    )


def summary_items(ctx: Any, trees: pd.DataFrame, metrics: dict[str, Any]) -> dict[str, Any]:
    """The figures at the head of the page: trees, rows, segmenter, map size, drive, volume."""
    recommended = ctx.config.volume.recommended
    rec_column = volume_column(recommended)
    return {
        "trees": len(trees),
        "rows": metrics.get("segmentation", {}).get("n_rows", "n/a"),
        "segmenter": metrics.get("segmenter", ""),
        "map points": f"{len(ctx.mapping.map):,}",
        "drive": format_value(metrics.get("mapping", {}).get("path_length_m"), " m", 0),
        f"median volume ({recommended.replace('_', ' ')})": format_value(
            float(trees[rec_column].median()) if len(trees) and rec_column in trees else None,
            " m³",
            1,
        ),
        "CRS": ctx.mapping.map.crs or "none",
    }


def map_and_trees_section(ctx: Any, trees: pd.DataFrame) -> ReportSection:
    """The map from above with the drive, and each tree's volume by every method."""
    traj = ctx.mapping.trajectory
    map_fig = plot_top_view(ctx.mapping.map, ctx.segmentation)
    map_fig.axes[0].plot(traj["x"], traj["y"], "-", color="0.4", lw=0.7)
    add_north_arrow_and_scale(map_fig.axes[0])
    drive = "grey: the estimated drive." if len(traj) else "no drive known (map made elsewhere)."
    recommended = ctx.config.volume.recommended
    volume_columns = {f"{recommended} (recommended)": volume_column(recommended)}
    for name, column in (("convex hull", CONVEX_HULL_COLUMN), ("alpha shape", ALPHA_COLUMN)):
        if column not in volume_columns.values():
            volume_columns[name] = column
    if "aerial_sphere_volume_m3" in trees:
        volume_columns["aerial sphere"] = "aerial_sphere_volume_m3"
    if "true_crown_volume_m3" in trees:
        volume_columns["true crown (simulator)"] = "true_crown_volume_m3"
    shown = trees
    if "aerial_sphere_volume_m3" in trees:  # a merged crown's sphere would dwarf every other bar
        shown = trees.assign(aerial_sphere_volume_m3=comparable_aerial_sphere(trees))
    figs = [
        (
            "Map from above, each segmented tree in its own colour, labelled with its tree ID; "
            f"dashed: fitted rows; {drive}",
            figure_to_data_uri(map_fig),
        ),
        (
            "Canopy volume per tree by method (aerial spheres of flagged crowns left out).",
            figure_to_data_uri(plots.plot_volumes(shown, volume_columns)),
        ),
    ]
    return ReportSection("Map and trees", figs)


def mapping_section(ctx: Any, mapping_eval: dict[str, Any] | None) -> ReportSection | None:
    """How good the map is: the finished map's checks when it was made elsewhere, else the
    trajectory against the simulator's truth (None without a truth to check against)."""
    if getattr(ctx.mapping, "made_elsewhere", False):
        return finished_map_section(ctx.mapping, mapping_eval)
    if not mapping_eval or ctx.truth_dir is None:
        return None
    # Imported here: canopy_kit.mapping loads numba (about 1 s), needed only with a truth.
    from canopy_kit.mapping.plots import mapping_figures

    truth = load_truth(ctx.truth_dir)
    reference = truth.trajectory_of(getattr(ctx.mapping, "trajectory_frame", ""))
    mfigs = mapping_figures(
        ctx.mapping,
        truth.trajectory if reference is None else reference,
        mapping_eval,
        ground_height=ctx.segmentation.ground.height,
    )
    add_north_arrow_and_scale(mfigs["map"].axes[0])
    return ReportSection(
        "Mapping",
        [
            (
                "Estimated trajectory against the true one (SE(3)-aligned onto the map's "
                "frame, the frame of the maps above), and the position error over time.",
                figure_to_data_uri(mfigs["trajectory"]),
            ),
            (
                "The map from above: highest point per cell, coloured by its height above the "
                "segmentation's ground surface.",
                figure_to_data_uri(mfigs["map"]),
            ),
        ],
    )


#: Aerial references the alpha-shape volume is plotted against: column, name, caption.
AERIAL_REFERENCES = [
    (
        "aerial_sphere_volume_m3",
        "aerial sphere",
        "Alpha-shape volume against the aerial sphere volume (paper §III.A); "
        "trees with a flagged aerial crown left out.",
    ),
    (
        "aerial_ellipsoid_volume_m3",
        "aerial ellipsoid",
        "Alpha-shape volume against the aerial height-aware ellipsoid (both crown "
        "extents and the CHM crown depth), the aerial reference of a nadir flight: the "
        "paper's sphere of the widest extent overstates crowns that are flatter or "
        "longer than wide (docs/GROUND_TRUTH.md gives both models' measured bias "
        "per crown form).",
    ),
    (
        "aerial_hull_volume_m3",
        "aerial visual hull",
        "Alpha-shape volume against the aerial visual hull (each crown carved from its "
        "silhouettes in every photo), the aerial reference of an oblique flight: oblique photos "
        "see below the crowns' widest level, which no nadir model can.",
    ),
]


def aerial_section(ctx: Any, trees: pd.DataFrame) -> ReportSection | None:
    """LiDAR volumes against the drone's crowns, and the orthomosaic with the crowns drawn
    (None without a drone flight)."""
    if ctx.aerial is None or "aerial_sphere_volume_m3" not in trees:
        return None
    ok = comparable_aerial_sphere(trees).notna() & trees[ALPHA_COLUMN].notna()
    figs = []
    if ok.sum() >= 2:
        sub = trees[ok]
        recommended = recommended_aerial_column(ctx.aerial.report)
        for column, name, caption in AERIAL_REFERENCES:
            if column not in sub or sub[column].notna().sum() < 2:
                continue
            if column == recommended:
                caption += " Recommended aerial reference for this flight."
            figure = plots.plot_agreement(
                sub[ALPHA_COLUMN].to_numpy(),
                sub[column].to_numpy(),
                ("LiDAR alpha shape", name),
                list(sub["tree_id"]),
            )
            figs.append((caption, figure_to_data_uri(figure)))
    ax = plot_crowns(ctx.aerial.ortho, ctx.aerial.segmentation, ctx.aerial.crowns)
    add_north_arrow_and_scale(ax)
    figs.append(
        (
            "Orthomosaic from the drone photos with the delineated crowns (red), each "
            "labelled with the ID of the LiDAR tree it was matched to ('aerial n': "
            "crown n, matched to none). " + describe_seeding(ctx.aerial.segmentation),
            figure_to_data_uri(ax.figure),
        )
    )
    return ReportSection(
        "LiDAR against drone photogrammetry",
        figs,
        text=aerial_reference_text(ctx.aerial.report),
    )


def truth_volume_section(trees: pd.DataFrame) -> ReportSection | None:
    """Alpha-shape volumes against the simulator's exact crown volumes (None with fewer than
    two trees to compare)."""
    if "true_crown_volume_m3" not in trees:
        return None
    ok = trees["true_crown_volume_m3"].notna() & trees[ALPHA_COLUMN].notna()
    if ok.sum() < 2:
        return None
    sub = trees[ok]
    figure = plots.plot_agreement(
        sub[ALPHA_COLUMN].to_numpy(),
        sub["true_crown_volume_m3"].to_numpy(),
        ("LiDAR alpha shape", "true crown"),
        list(sub["tree_id"]),
    )
    return ReportSection(
        "Against the simulator's truth",
        [("Alpha-shape volume against the exact crown volume.", figure_to_data_uri(figure))],
    )


def segmentation_failures_section(ctx: Any) -> ReportSection | None:
    """Side views of each true tree not segmented one-to-one (None without a truth field in
    the map, or without failures)."""
    cloud, seg = ctx.mapping.map, ctx.segmentation
    if ctx.truth_matches is None or "tree_id" not in cloud.fields:
        return None
    truth_ids = np.asarray(cloud.fields["tree_id"])
    score = score_point_labels(seg.labels, truth_ids)
    gallery = plot_failure_gallery(cloud, seg, score, truth_ids)
    if gallery is None:
        return None
    return ReportSection(
        "Segmentation failures",
        [
            (
                "Side views around each true tree that was not segmented one-to-one: truth "
                "(left) and segmentation (right).",
                figure_to_data_uri(gallery),
            )
        ],
    )


def row_metrics_section(profiles: Any) -> ReportSection:
    """The row metrics (``canopy_kit.segment.row_profile``): profiles figure, per-row table."""
    caption = (
        "Per row, per 1 m section along it: the canopy's top above the ground (left) and how far "
        "it reaches left and right of the fitted row line (right), as written to rows.csv. "
        "Tree-Row Volume TRV = height x width x 10,000 / row spacing, Leaf Wall Area "
        "LWA = 2 x height x 10,000 / row spacing (docs/OUTPUTS.md, Row metrics)."
    )
    figure = plots.plot_row_profiles(profiles.sections, profiles.summary)
    table = profiles.summary.rename(
        columns={
            "row": "Row",
            "length_m": "Length (m)",
            "mean_height_m": "Mean height (m)",
            "mean_width_m": "Mean width (m)",
            "trv_m3_per_ha": "TRV (m³/ha)",
            "lwa_m2_per_ha": "LWA (m²/ha)",
        }
    )[["Row", "Length (m)", "Mean height (m)", "Mean width (m)", "TRV (m³/ha)", "LWA (m²/ha)"]]
    # TRV and LWA per hectare shown whole (the table shows other numbers to the mm).
    for column in ("TRV (m³/ha)", "LWA (m²/ha)"):
        table[column] = pd.Series(
            [int(round(v)) if np.isfinite(v) else float("nan") for v in table[column]],
            index=table.index,
            dtype=object,
        )
    text = " ".join(profiles.warnings)
    return ReportSection("Row metrics", [(caption, figure_to_data_uri(figure))], table, text)


def table_columns(recommended: str) -> list[str]:
    """The per-tree table's columns: ``TABLE_COLUMNS`` with the recommended estimator's volume
    and interval after the paper's alpha-shape volume."""

    cols = list(TABLE_COLUMNS)
    rec = volume_column(recommended)
    if rec not in cols:
        cols.insert(cols.index(ALPHA_COLUMN) + 1, rec)
    at = cols.index(rec) + 1
    return [*cols[:at], "volume_low_m3", "volume_high_m3", *cols[at:]]


def report_title(provenance: dict[str, Any], preset: str) -> tuple[str, str]:
    """The page's title and subtitle: named after the orchard when the provenance names one,
    else after the preset."""
    orchard = str(provenance.get("orchard") or "").strip()
    subtitle = "Per-tree canopy volumes from a mobile LiDAR drive"
    if orchard:
        return f"canopy-kit report: {orchard}", f"{subtitle} (preset {preset})"
    return f"canopy-kit report: {preset}", subtitle


def report_downloads(
    ctx: Any, trees: pd.DataFrame, provenance: dict[str, Any] | None = None
) -> list[dict[str, str]]:
    """The files the page offers for download, made by the functions that write them beside
    it (with the run's ``provenance``); a GeoJSON the run does not write (no CRS) is left out."""
    geo = "application/geo+json"
    files = [
        ("trees.csv", "text/csv", csv_text(trees)),
        ("trees.geojson", geo, trees_geojson(trees, provenance)),
        ("crowns.geojson", geo, crowns_geojson(ctx.segmentation, provenance)),
        ("rows.geojson", geo, rows_geojson(ctx.segmentation, provenance)),
    ]
    return [
        {"name": name, "mime": mime, "text": text} for name, mime, text in files if text is not None
    ]


def row_table(rows: pd.DataFrame, volume: str = ALPHA_COLUMN) -> pd.DataFrame | None:
    """The per-row summary (:func:`~canopy_kit.report.explorer.row_summary` of the column
    ``volume``) with human headers; None without rows."""
    if not len(rows):
        return None
    label = column_label(volume)
    label = label[0].lower() + label[1:]
    return rows.rename(
        columns={
            "row": "Row",
            "trees": "Trees",
            "median_m3": f"Median {label}",
            "total_m3": f"Total {label}",
            "flagged": "Flagged trees",
        }
    )
