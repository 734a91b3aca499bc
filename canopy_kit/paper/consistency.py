"""Find, from the numbers alone, which column of Table I holds what in each row.

Each printed error should equal ``|V - GT| / GT * 100`` of its own volume. For every row
all 24 orders of the four value columns are tried; an order is *consistent* when both
recomputed errors agree with the printed ones up to the rounding of the printed values
(every cell is only known to within half its last digit, so the recomputed error is an
interval, and so is the printed one). Among consistent orders the one with convex hull
volume >= alpha-shape volume is kept (an alpha shape of a point set lies inside its
convex hull), then the one moving the fewest columns. A row that no order explains is
reported as ``unresolved`` and kept as printed, never forced.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from canopy_kit.paper.table1 import (
    HEADER_OF,
    VALUE_COLUMNS,
    default_table1_path,
    printed_half_units,
    read_table1_text,
)

#: Per method: (volume column, error column).
METHODS: dict[str, tuple[str, str]] = {
    "hull": ("hull_m3", "hull_err_pct"),
    "alpha": ("alpha_m3", "alpha_err_pct"),
}
Status = Literal["as_printed", "reordered", "ambiguous", "unresolved"]


@dataclass(frozen=True)
class Assignment:
    """One reading of a row: ``order[j]`` is the quantity held by printed value column j."""

    order: tuple[str, ...]
    recomputed: dict[str, float]  # method -> |V - GT| / GT * 100 from the printed values
    residual: dict[str, float]  # method -> recomputed - printed error (percentage points)
    slack: dict[str, float]  # method -> gap between the rounding intervals (0: they overlap)
    consistent: bool
    hull_not_below_alpha: bool
    moved: int  # value columns whose quantity differs from the header

    @property
    def max_abs_residual(self) -> float:
        """Largest |recomputed - printed| of the two errors (percentage points)."""
        return max(abs(r) for r in self.residual.values())


@dataclass(frozen=True)
class RowCheck:
    """The verdict for one tree: the chosen reading, the header's reading, the alternatives."""

    tree: int
    status: Status
    chosen: Assignment
    as_printed: Assignment
    candidates: tuple[Assignment, ...]  # every consistent reading

    def moved_columns(self) -> list[tuple[str, str]]:
        """(header of the printed column, header of what it actually holds) for moved columns."""
        return [
            (HEADER_OF[printed], HEADER_OF[actual])
            for printed, actual in zip(VALUE_COLUMNS, self.chosen.order)
            if printed != actual
        ]


@dataclass(frozen=True)
class Table1Check:
    """Outcome of :func:`check_table1`: per-row verdicts and the two readings of the table."""

    source: Path
    rows: tuple[RowCheck, ...]
    corrected: pd.DataFrame  # values moved to the columns the numbers say they belong to
    as_printed: pd.DataFrame  # values under the printed header
    corrected_text: pd.DataFrame  # the same as ``corrected``, cells as printed text
    rounding: bool
    tolerance_pp: float

    @property
    def findings(self) -> list[RowCheck]:
        """Rows that are not consistent as printed (reordered, ambiguous or unresolved)."""
        return [r for r in self.rows if r.status != "as_printed"]


def _error_interval(volume: float, hv: float, gt: float, hg: float) -> tuple[float, float]:
    """Range of ``|V/G - 1| * 100`` over V in [volume ± hv], G in [gt ± hg] (all positive)."""
    lo_ratio, hi_ratio = (volume - hv) / (gt + hg), (volume + hv) / (gt - hg)
    ends = (abs(lo_ratio - 1.0), abs(hi_ratio - 1.0))
    low = 0.0 if lo_ratio <= 1.0 <= hi_ratio else min(ends)
    return 100.0 * low, 100.0 * max(ends)


def assess_order(
    values: dict[str, float],
    half: dict[str, float],
    order: tuple[str, ...],
    *,
    tolerance_pp: float = 0.0,
) -> Assignment:
    """Judge one reading of a row (``values``/``half`` keyed by column name, incl. ``gt_m3``)."""
    role = {quantity: column for column, quantity in zip(VALUE_COLUMNS, order)}
    gt, hg = values["gt_m3"], half["gt_m3"]
    recomputed, residual, slack = {}, {}, {}
    for method, (vol_q, err_q) in METHODS.items():
        v, hv = values[role[vol_q]], half[role[vol_q]]
        e, he = values[role[err_q]], half[role[err_q]]
        recomputed[method] = abs(v - gt) / gt * 100.0
        residual[method] = recomputed[method] - e
        lo, hi = _error_interval(v, hv, gt, hg)
        slack[method] = max(0.0, (e - he) - hi, lo - (e + he))
    hull = values[role["hull_m3"]] + half[role["hull_m3"]]
    alpha = values[role["alpha_m3"]] - half[role["alpha_m3"]]
    return Assignment(
        order=order,
        recomputed=recomputed,
        residual=residual,
        slack=slack,
        consistent=all(s <= tolerance_pp + 1e-12 for s in slack.values()),
        hull_not_below_alpha=bool(hull >= alpha),
        moved=sum(a != b for a, b in zip(order, VALUE_COLUMNS)),
    )


def check_row(
    tree: int, values: dict[str, float], half: dict[str, float], *, tolerance_pp: float = 0.0
) -> RowCheck:
    """Try every order of the four value columns of one row and pick the one the numbers support."""
    readings = [
        assess_order(values, half, order, tolerance_pp=tolerance_pp)
        for order in itertools.permutations(VALUE_COLUMNS)
    ]
    as_printed = readings[0]  # permutations() yields the identity first
    candidates = [a for a in readings if a.consistent]
    if not candidates:
        return RowCheck(tree, "unresolved", as_printed, as_printed, ())
    plausible = [a for a in candidates if a.hull_not_below_alpha] or candidates
    fewest = min(a.moved for a in plausible)
    best = sorted((a for a in plausible if a.moved == fewest), key=lambda a: sum(a.slack.values()))
    chosen = best[0]
    if len(best) > 1:
        status: Status = "ambiguous"
    elif chosen.moved == 0:
        status = "as_printed"
    else:
        status = "reordered"
    return RowCheck(tree, status, chosen, as_printed, tuple(candidates))


def _reading(frame: pd.DataFrame, orders: dict[int, tuple[str, ...]]) -> pd.DataFrame:
    """Move each row's value cells to the columns its order names."""
    out = frame.copy()
    for tree, order in orders.items():
        cells = frame.loc[tree, list(VALUE_COLUMNS)].tolist()
        for quantity, cell in zip(order, cells):
            out.loc[tree, quantity] = cell
    return out


def _with_diagnostics(table: pd.DataFrame, rows: list[RowCheck], pick: str) -> pd.DataFrame:
    out = table.copy()
    for method in METHODS:
        out[f"{method}_err_recomputed"] = [getattr(r, pick).recomputed[method] for r in rows]
        out[f"{method}_residual_pp"] = [getattr(r, pick).residual[method] for r in rows]
    out["consistent"] = [getattr(r, pick).consistent for r in rows]
    out["status"] = [r.status for r in rows]
    return out


def check_table1(
    path: str | Path | None = None, *, rounding: bool = True, tolerance_pp: float = 0.0
) -> Table1Check:
    """Check every row of Table I and build the corrected table.

    ``rounding`` accounts for each printed value being rounded to its last digit;
    ``tolerance_pp`` widens the test by that many percentage points. With
    ``rounding=False`` the check is a flat ``|recomputed - printed| <= tolerance_pp``.
    """
    source = Path(path) if path is not None else default_table1_path()
    text = read_table1_text(source)
    values = text.astype(float)
    half = printed_half_units(text) if rounding else text.map(lambda _: 0.0)
    rows = [
        check_row(
            int(tree),
            values.loc[tree].to_dict(),
            half.loc[tree].to_dict(),
            tolerance_pp=tolerance_pp,
        )
        for tree in values.index
    ]
    orders = {r.tree: r.chosen.order for r in rows}
    return Table1Check(
        source=source,
        rows=tuple(rows),
        corrected=_with_diagnostics(_reading(values, orders), rows, "chosen"),
        as_printed=_with_diagnostics(values, rows, "as_printed"),
        corrected_text=_reading(text, orders),
        rounding=rounding,
        tolerance_pp=float(tolerance_pp),
    )


def order_groups(check: Table1Check) -> dict[tuple[str, ...], list[int]]:
    """Trees grouped by the column order the numbers chose (printed order first if present)."""
    groups: dict[tuple[str, ...], list[int]] = {}
    for row in sorted(check.rows, key=lambda r: (r.chosen.order != VALUE_COLUMNS, r.tree)):
        groups.setdefault(row.chosen.order, []).append(row.tree)
    return groups


def max_abs_residual(check: Table1Check) -> float:
    """Largest |recomputed - printed| error over the consistent rows of the corrected table."""
    res = [r.chosen.max_abs_residual for r in check.rows if r.status != "unresolved"]
    return float(np.max(res)) if res else float("nan")
