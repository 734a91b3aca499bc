"""What Table I implies but the paper does not state: agreement statistics, the
"alpha shape consistently outperformed convex hull" claim, and the crown diameters
behind the sphere ground truth.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.stats import binomtest

from canopy_kit.errors import InputError
from canopy_kit.evaluate.stats import Agreement, agreement
from canopy_kit.paper.consistency import METHODS, Table1Check, max_abs_residual
from canopy_kit.paper.table1 import VALUE_COLUMNS, printed_half_units


def method_agreement(table: pd.DataFrame) -> dict[str, Agreement]:
    """Agreement of each method's volume (``hull_m3``, ``alpha_m3``) with ``gt_m3``."""
    return {
        m: agreement(table[vol].to_numpy(), table["gt_m3"].to_numpy())
        for m, (vol, _) in METHODS.items()
    }


def printed_error_means(table: pd.DataFrame) -> dict[str, float]:
    """Mean of each printed error column (the MAPE the printed errors imply), in %."""
    return {m: float(table[err].mean()) for m, (_, err) in METHODS.items()}


@dataclass(frozen=True)
class ClaimCheck:
    """How often alpha shape beats convex hull, and whether that follows from hull overshoot."""

    n_trees: int
    alpha_better: list[int]  # trees where the alpha error is lower (recomputed errors)
    hull_better: list[int]
    ties: list[int]
    alpha_better_printed: list[int]  # the same judged on the printed error columns
    hull_over_gt: list[int]  # trees whose convex hull volume exceeds the ground truth
    alpha_better_when_hull_over: int
    alpha_better_when_hull_not_over: int
    sign_test_p: float  # two-sided binomial test of alpha_better vs hull_better (ties dropped)


def check_alpha_claim(table: pd.DataFrame) -> ClaimCheck:
    """Count trees where alpha shape has the lower error (the paper says it does "consistently")."""
    gt = table["gt_m3"]
    hull_err = (table["hull_m3"] - gt).abs() / gt
    alpha_err = (table["alpha_m3"] - gt).abs() / gt
    trees = table.index.to_numpy()
    alpha_better = [int(t) for t in trees[(alpha_err < hull_err).to_numpy()]]
    hull_better = [int(t) for t in trees[(hull_err < alpha_err).to_numpy()]]
    ties = [int(t) for t in trees[(hull_err == alpha_err).to_numpy()]]
    printed = table["alpha_err_pct"] < table["hull_err_pct"]
    over = table["hull_m3"] > gt
    n_decided = len(alpha_better) + len(hull_better)
    p = binomtest(len(alpha_better), n_decided, 0.5).pvalue if n_decided else float("nan")
    return ClaimCheck(
        n_trees=len(table),
        alpha_better=alpha_better,
        hull_better=hull_better,
        ties=ties,
        alpha_better_printed=[int(t) for t in trees[printed.to_numpy()]],
        hull_over_gt=[int(t) for t in trees[over.to_numpy()]],
        alpha_better_when_hull_over=int(sum(t in alpha_better for t in trees[over.to_numpy()])),
        alpha_better_when_hull_not_over=int(
            sum(t in alpha_better for t in trees[(~over).to_numpy()])
        ),
        sign_test_p=float(p),
    )


def sphere_diameter(volume_m3: ArrayLike) -> NDArray[np.float64]:
    """Diameter of the sphere with the given volume: ``d = (6 V / pi)^(1/3)``."""
    return np.cbrt(6.0 * np.asarray(volume_m3, dtype=np.float64) / np.pi)


def sphere_volume(diameter_m: ArrayLike) -> NDArray[np.float64]:
    """Volume of a sphere of the given diameter: ``pi d^3 / 6``."""
    return np.pi * np.asarray(diameter_m, dtype=np.float64) ** 3 / 6.0


def implied_diameters(gt_text: pd.Series, resolution_m: float = 0.01) -> pd.DataFrame:
    """Crown diameters implied by the printed sphere volumes (text, to know their rounding).

    Gives the diameter, its range given the volume's rounding, the nearest multiple of
    ``resolution_m`` and whether a sphere of that rounded diameter, rounded like the
    printed value, gives back the printed volume exactly.
    """
    gt = gt_text.astype(float)
    half = printed_half_units(gt_text.to_frame()).iloc[:, 0]
    decimals = gt_text.map(lambda s: len(s.split(".", 1)[1]) if "." in s else 0)
    rounded = np.round(sphere_diameter(gt) / resolution_m) * resolution_m
    back = [round(float(v), int(k)) for v, k in zip(sphere_volume(rounded), decimals)]
    return pd.DataFrame(
        {
            "gt_m3": gt,
            "diameter_m": sphere_diameter(gt),
            "diameter_min_m": sphere_diameter(gt - half),
            "diameter_max_m": sphere_diameter(gt + half),
            "diameter_rounded_m": rounded,
            "rounded_reproduces_gt": np.isclose(back, gt.to_numpy(), rtol=0, atol=1e-9),
        },
        index=gt_text.index,
    )


@dataclass(frozen=True)
class Table1Summary:
    """Everything ``canopy-kit paper table1`` reports about one reading of the table."""

    reading: str  # "corrected" or "as_printed"
    agreement: dict[str, Agreement]
    printed_error_means: dict[str, float]
    claim: ClaimCheck
    diameters: pd.DataFrame


def summarise_table1(
    check: Table1Check, reading: str = "corrected", resolution_m: float = 0.01
) -> Table1Summary:
    """Statistics, claim check and implied diameters for the corrected or as-printed table."""
    if reading not in ("corrected", "as_printed"):
        raise InputError(f"reading: expected 'corrected' or 'as_printed', got {reading!r}")
    table = check.corrected if reading == "corrected" else check.as_printed
    return Table1Summary(
        reading=reading,
        agreement=method_agreement(table),
        printed_error_means=printed_error_means(table),
        claim=check_alpha_claim(table),
        diameters=implied_diameters(check.corrected_text["gt_m3"], resolution_m),
    )


def _records(frame: pd.DataFrame) -> list[dict[str, Any]]:
    return [
        {
            "tree": int(tree),
            **{k: (v.item() if isinstance(v, np.generic) else v) for k, v in row.items()},
        }
        for tree, row in frame.iterrows()
    ]


def table1_result(check: Table1Check, summary: Table1Summary) -> dict[str, Any]:
    """Plain, JSON-ready form of a check and its summary (what ``--json`` prints)."""
    table = check.corrected if summary.reading == "corrected" else check.as_printed
    return {
        "source": str(check.source),
        "reading": summary.reading,
        "rounding_aware": check.rounding,
        "tolerance_pp": check.tolerance_pp,
        "table": _records(table),
        "findings": [
            {
                "tree": r.tree,
                "status": r.status,
                "printed_order": list(VALUE_COLUMNS),
                "order_from_numbers": list(r.chosen.order),
                "moved_columns": [
                    {"header_says": h, "numbers_say": a} for h, a in r.moved_columns()
                ],
                "residual_as_printed_pp": r.as_printed.residual,
                "residual_corrected_pp": r.chosen.residual,
                "n_consistent_orders": len(r.candidates),
            }
            for r in check.findings
        ],
        "max_abs_residual_pp": max_abs_residual(check),
        "agreement": {m: a.as_dict() for m, a in summary.agreement.items()},
        "printed_error_means_pct": summary.printed_error_means,
        "claim_alpha_better": asdict(summary.claim),
        "implied_diameters": _records(summary.diameters),
    }
