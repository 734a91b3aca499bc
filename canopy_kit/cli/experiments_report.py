"""The printout of ``canopy-kit paper experiments``: what was run, segmentation success and
volume errors per orchard, method and mapping beside the paper's figures, failed runs.

Printed on ``common.console``, looked up at each call (tests swap it for a narrow terminal).
"""

from __future__ import annotations

import math
from typing import Any

from canopy_kit.cli import common
from canopy_kit.cli.tables import Grid, print_grid


def pct(value: Any, digits: int = 1) -> str:
    """A percentage to ``digits`` decimals; ``-`` for a missing (None or NaN) one."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def print_experiments(results: Any) -> None:
    """Print experiment ``results`` (:class:`canopy_kit.paper.experiments` results)."""
    print_experiments_header(results)
    print_grid(segmentation_grid(results.comparison))
    print_grid(volume_grid(results.comparison))
    print_aerial_and_failures(results)
    p = results.paper
    common.console.print(
        f"Paper: segmentation as printed (§II.C, §III); volume figures recomputed from "
        f"Table I corrected ({p['n_trees']} pistachio trees, DBSCAN). "
        f"Bias vs crown: mean signed error."
    )


def print_experiments_header(results: Any) -> None:
    """The orchards' size, the seeds, the mappings and the time taken."""
    cfg = results.config
    seeds = ", ".join(map(str, cfg.seeds))
    runs_min = float(results.runs["seconds"].sum()) / 60 if "seconds" in results.runs else math.nan
    common.console.print(
        f"[bold]Abedi et al. 2025 re-run on simulated orchards[/]: "
        f"{cfg.rows} rows x {cfg.trees_per_row} trees, seeds {seeds}, "
        f"mapping: {', '.join(cfg.mappings)} (this command {results.seconds / 60:.1f} "
        f"min; the runs, mapping included and simulation not, {runs_min:.0f} min "
        f"in all, checkpointed ones included)"
    )


def segmentation_grid(c: Any) -> Grid:
    """Segmentation success per orchard, method and mapping (``c``: the comparison table),
    the paper's beside ours, and how the other trees failed."""
    seg = Grid(
        [
            "orchard",
            "method",
            "mapping",
            "paper",
            "ours",
            "seed range",
            "correct / trees",
            "merged",
            "split",
            "missed",
            "other",
            "map pts/tree",
        ],
        title="Segmentation success (%): one-to-one point IoU >= 0.5 with a true tree",
        keys=3,
        right=set(range(3, 12)),
    )
    for r in c.to_dict("records"):
        seg.add_row(
            r["orchard"],
            r["method"],
            r["mapping"],
            pct(r["paper_success_pct"], 0),
            pct(r["success_pct"]),
            f"{pct(r['success_min_pct'], 0)}-{pct(r['success_max_pct'], 0)}",
            f"{r['n_correct']}/{r['n_truth']}",
            str(r["n_merged"]),
            str(r["n_split"]),
            str(r["n_missed"]),
            str(r["n_other"]),
            pct(r["map_points_per_tree_median"], 0),
        )
    return seg


def volume_grid(c: Any) -> Grid:
    """Volume errors per orchard, method and mapping (``c``: the comparison table) against
    the aerial sphere (the paper's beside ours) and against the true crown."""
    vol = Grid(
        [
            "orchard",
            "method",
            "mapping",
            "trees",
            "hull vs sphere paper",
            "hull vs sphere ours",
            "alpha vs sphere paper",
            "alpha vs sphere ours",
            "max alpha err paper",
            "max alpha err ours",
            "alpha better paper",
            "alpha better ours",
            "hull vs crown",
            "alpha vs crown",
            "hull bias crown",
            "alpha bias crown",
        ],
        title="Volume error (%) on correctly segmented trees: MAPE vs the aerial sphere "
        "π d³/6 (the paper's ground truth) and vs the true crown volume",
        keys=3,
        right=set(range(3, 16)),
    )
    for r in c.to_dict("records"):
        n = r.get("n_trees_vs_sphere")
        better = (
            f"{int(r['alpha_better_vs_sphere'])}/{int(n)}"
            if n is not None and not math.isnan(n)
            else "-"
        )
        vol.add_row(
            r["orchard"],
            r["method"],
            r["mapping"],
            pct(n, 0),
            pct(r["paper_convex_hull_mape_vs_sphere_pct"]),
            pct(r.get("convex_hull_mape_vs_sphere_pct")),
            pct(r["paper_alpha_shape_mape_vs_sphere_pct"]),
            pct(r.get("alpha_shape_mape_vs_sphere_pct")),
            pct(r["paper_alpha_shape_max_error_vs_sphere_pct"]),
            pct(r.get("alpha_shape_max_error_vs_sphere_pct")),
            r["paper_alpha_better"] or "-",
            better,
            pct(r.get("convex_hull_mape_vs_crown_pct")),
            pct(r.get("alpha_shape_mape_vs_crown_pct")),
            pct(r.get("convex_hull_bias_vs_crown_pct")),
            pct(r.get("alpha_shape_bias_vs_crown_pct")),
        )
    return vol


def print_aerial_and_failures(results: Any) -> None:
    """Errors against the drone's sphere volumes (when a drone flew), then each failed run."""
    c = results.comparison
    if "aerial" in "".join(c.columns):
        common.console.print(
            "vs the drone photogrammetry sphere volumes: "
            + "; ".join(
                f"{r['orchard']}/{r['method']}/{r['mapping']} hull "
                f"{pct(r.get('convex_hull_mape_vs_aerial_pct'))}, alpha "
                f"{pct(r.get('alpha_shape_mape_vs_aerial_pct'))}"
                for r in c.to_dict("records")
            )
        )
    failed = (
        results.runs[results.runs.get("error", "").astype(str) != ""]
        if "error" in results.runs
        else results.runs.iloc[:0]
    )
    for r in failed.to_dict("records"):
        common.console.print(
            f"[red]failed[/]: {r['session']} {r['mapping']} {r['method']}: {r['error']}"
        )
