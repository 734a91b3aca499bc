"""The printout of ``canopy-kit paper table1``: Table I as read, its column orders and
inconsistencies, the agreement statistics, the paper's claim and the implied diameters.

Printed on ``common.console``, looked up at each call (tests swap it for a narrow terminal).
"""

from __future__ import annotations

from typing import Any

from canopy_kit.cli import common
from canopy_kit.cli.tables import Grid, print_grid
from canopy_kit.paper.consistency import order_groups
from canopy_kit.paper.table1 import HEADER_OF, VALUE_COLUMNS

SHORT = {
    "hull_m3": "hull m³",
    "hull_err_pct": "hull err %",
    "alpha_m3": "alpha m³",
    "alpha_err_pct": "alpha err %",
}


def tree_ranges(trees: list[int]) -> str:
    """``[1, 2, 3, 6, 8, 9]`` -> ``"1-3, 6, 8-9"``."""
    parts: list[str] = []
    for t in sorted(trees):
        if parts and parts[-1][1] == t - 1:
            parts[-1][1] = t
        else:
            parts.append([t, t])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in parts) or "none"


def print_table1_report(check: Any, summary: Any, result: dict[str, Any]) -> None:
    """Print the check of Table I (``check``), its statistics (``summary``) and the largest
    residual left (``result``, :func:`canopy_kit.paper.summary.table1_result`)."""
    print_consistency_test(check)
    print_table_as_read(check, corrected=summary.reading == "corrected")
    print_column_orders(check, result)
    print_agreement(summary)
    print_claim(summary.claim)
    print_implied_diameters(summary.diameters)


def print_consistency_test(check: Any) -> None:
    """Where the table comes from and the tolerance its errors are recomputed to."""
    if not check.rounding:
        tolerance = f"a flat tolerance of {check.tolerance_pp:g} pp (rounding ignored)"
    else:
        tolerance = "rounding of the printed values"
        tolerance += f" + {check.tolerance_pp:g} pp" if check.tolerance_pp else ""
    common.console.print(f"[bold]Table I[/] of Abedi et al. 2025 from {check.source}")
    common.console.print(
        f"Consistency test: recomputed |V - GT| / GT * 100 vs printed error, "
        f"allowing for {tolerance}.\n"
    )


def print_table_as_read(check: Any, corrected: bool) -> None:
    """The table row by row (corrected or as printed), recomputed errors beside the printed
    ones; moved rows in yellow, rows no order explains in red."""
    title = "corrected (columns where the numbers put them)" if corrected else "as printed"
    table = Grid(
        [
            "tree",
            "GT m³",
            "hull m³",
            "hull err %",
            "recomp",
            "alpha m³",
            "alpha err %",
            "recomp",
            "status",
        ],
        title=f"Table I, {title}",
        right=set(range(8)),
    )
    frame = check.corrected if corrected else check.as_printed
    text = check.corrected_text if corrected else None
    for tree, row in frame.iterrows():

        def cell(c: str, tree=tree, row=row) -> str:
            return str(text.loc[tree, c]) if text is not None else f"{row[c]:.2f}"

        style = "" if row["status"] == "as_printed" else "yellow"
        if row["status"] in ("unresolved", "ambiguous"):
            style = "red"
        table.add_row(
            str(tree),
            cell("gt_m3"),
            cell("hull_m3"),
            cell("hull_err_pct"),
            f"{row['hull_err_recomputed']:.2f}",
            cell("alpha_m3"),
            cell("alpha_err_pct"),
            f"{row['alpha_err_recomputed']:.2f}",
            row["status"],
            style=style,
        )
    print_grid(table)


def print_column_orders(check: Any, result: dict[str, Any]) -> None:
    """What the numbers say about the order of the value columns, row by row, and the rows
    that disagree with the header."""
    common.console.print("[bold]Column order found from the numbers[/]")
    for order, trees in order_groups(check).items():
        same = order == VALUE_COLUMNS
        desc = "as the header says" if same else ", ".join(HEADER_OF[q] for q in order)
        common.console.print(f"  trees {tree_ranges(trees)}: {desc}")
    n_fits = sorted({len(r.candidates) for r in check.rows})
    by_geometry = [
        r.tree for r in check.rows if len({a.hull_not_below_alpha for a in r.candidates}) > 1
    ]
    common.console.print(
        f"  orders of the four value columns that fit a row: "
        f"{', '.join(map(str, n_fits))}; convex hull >= alpha shape (an alpha shape "
        f"lies inside its hull) decided between them in trees {tree_ranges(by_geometry)}"
    )
    if check.findings:
        print_grid(inconsistency_grid(check))
    else:
        common.console.print("  no inconsistencies")
    unresolved = [r.tree for r in check.rows if r.status in ("unresolved", "ambiguous")]
    if unresolved:
        common.console.print(
            f"  [red]trees {tree_ranges(unresolved)} could not be resolved and are kept "
            f"as printed in the statistics below[/]"
        )
    common.console.print(
        f"  largest |recomputed - printed| error after correction: "
        f"{result['max_abs_residual_pp']:.3f} pp\n"
    )


def inconsistency_grid(check: Any) -> Grid:
    """One line per inconsistent row: which value sits under which header, and the residuals
    of the errors as printed and as corrected."""
    inc = Grid(
        [
            "tree",
            "status",
            "header says: numbers say (value)",
            "residual as printed (pp)",
            "residual corrected (pp)",
        ],
        title=f"Inconsistencies ({len(check.findings)} rows)",
        wrap={2, 3, 4},
    )
    for r in check.findings:
        moved = (
            "; ".join(
                f"{SHORT[h]}: {SHORT[a]} ({check.as_printed.loc[r.tree, h]:.2f})"
                for h, a in zip(VALUE_COLUMNS, r.chosen.order)
                if h != a
            )
            or "no order of the columns fits"
        )
        res_p = ", ".join(f"{m} {v:+.2f}" for m, v in r.as_printed.residual.items())
        res_c = ", ".join(f"{m} {v:+.3f}" for m, v in r.chosen.residual.items())
        inc.add_row(str(r.tree), r.status, moved, res_p, res_c if r.status != "unresolved" else "-")
    return inc


def print_agreement(summary: Any) -> None:
    """Agreement of each method's volumes with the sphere ground truth (MAPE, bias, RMSE,
    R², Bland-Altman)."""
    stats = Grid(
        ["statistic", "convex hull", "alpha shape"],
        right={1, 2},
        wrap={0},
        title=f"Agreement with the sphere ground truth ({summary.reading} table)",
    )
    a, means = summary.agreement, summary.printed_error_means
    ba = {m: x.bland_altman for m, x in a.items()}
    lines = [
        ("n trees", lambda m: f"{a[m].n}"),
        ("MAPE (%) from volumes", lambda m: f"{a[m].mape_pct:.3f}"),
        ("mean of printed error column (%)", lambda m: f"{means[m]:.3f}"),
        ("bias, mean(V - GT) (m³)", lambda m: f"{a[m].bias:+.3f}"),
        ("bias, mean signed error (%)", lambda m: f"{a[m].bias_pct:+.3f}"),
        ("RMSE (m³)", lambda m: f"{a[m].rmse:.3f}"),
        ("R² (1 - SSres/SStot, V vs GT)", lambda m: f"{a[m].r_squared:.3f}"),
        ("Pearson r²", lambda m: f"{a[m].pearson_r2:.3f}"),
        ("Bland-Altman mean difference (m³)", lambda m: f"{ba[m].mean_difference:+.3f}"),
        ("Bland-Altman SD of differences (m³)", lambda m: f"{ba[m].sd_difference:.3f}"),
        (
            "Bland-Altman 95% limits (m³)",
            lambda m: f"{ba[m].lower_limit:+.3f} .. {ba[m].upper_limit:+.3f}",
        ),
    ]
    for label, fmt in lines:
        stats.add_row(label, fmt("hull"), fmt("alpha"))
    print_grid(stats)


def print_claim(c: Any) -> None:
    """The paper's claim that the alpha shape beat the convex hull, counted tree by tree."""
    common.console.print(
        '[bold]Claim: "The Alpha Shape method consistently outperformed Convex Hull"[/]'
    )
    common.console.print(
        f"  alpha error lower in {len(c.alpha_better)} of {c.n_trees} trees "
        f"({tree_ranges(c.alpha_better)}); convex hull lower in {len(c.hull_better)} "
        f"({tree_ranges(c.hull_better)}); ties {len(c.ties)}"
    )
    common.console.print(
        f"  judged on the printed error columns: alpha lower in "
        f"{len(c.alpha_better_printed)} of {c.n_trees}"
    )
    n_over = len(c.hull_over_gt)
    common.console.print(
        f"  convex hull above ground truth in {n_over} trees: alpha better in "
        f"{c.alpha_better_when_hull_over} of them, and in "
        f"{c.alpha_better_when_hull_not_over} of the {c.n_trees - n_over} others"
    )
    common.console.print(f"  two-sided sign test, alpha vs hull better: p = {c.sign_test_p:.3f}\n")


def print_implied_diameters(diameters: Any) -> None:
    """The crown diameters the sphere volumes imply, and whether a diameter to the centimetre
    gives each printed volume back."""
    diam = Grid(
        ["tree", "GT m³", "d (m)", "d range from rounding (m)", "d to 0.01 m", "gives GT back"],
        right=set(range(6)),
        title="Crown diameters implied by the sphere volumes, d = (6V/π)^(1/3)",
    )
    for tree, row in diameters.iterrows():
        diam.add_row(
            str(tree),
            f"{row['gt_m3']:.2f}",
            f"{row['diameter_m']:.4f}",
            f"{row['diameter_min_m']:.4f} .. {row['diameter_max_m']:.4f}",
            f"{row['diameter_rounded_m']:.2f}",
            "yes" if row["rounded_reproduces_gt"] else "no",
        )
    print_grid(diam)
    n_back = int(diameters["rounded_reproduces_gt"].sum())
    common.console.print(
        f"  {n_back} of {len(diameters)} printed volumes are spheres of a "
        f"diameter given to the centimetre"
    )
