"""The report's statement of the volume estimator: what it measures, and how far the drive's
estimate was measured to be from that measurand on tree families it was not tuned on."""

from __future__ import annotations

import pandas as pd

from canopy_kit.report.html import ReportSection
from canopy_kit.volume.accuracy import family_accuracy_table

PAPER_METHODS = ("alpha_shape", "convex_hull")
SIDES = {"both": "both sides", "one": "one side only"}
FAMILY_NAMES = {
    "envelope": "the simulator's envelope crowns",
    "lobe_union": "unions of lobes on scaffold tips",
    "grown": "trees grown by space colonisation (vase, central leader, hedgerow)",
    "real": "real terrestrial scans of trees, re-scanned",
}


def measures(method: str) -> str:
    """What ``method`` measures (its plugin's ``measures``), or '' when it does not say."""
    from canopy_kit import plugins

    try:
        return str(getattr(plugins.load("volumes", method), "measures", "") or "")
    except Exception:  # an unknown or broken plugin says nothing here; the run reports it
        return ""


def pooled(rows: pd.DataFrame) -> pd.Series:
    """Bias, MAPE and interval coverage over ``rows`` (families pooled, weighted by trees)."""
    n = rows["n"].to_numpy(float)
    out = {"n": n.sum()}
    for col in ("bias", "mape", "interval_covers"):
        ok = rows[col].notna().to_numpy()
        out[col] = (
            float((rows[col].to_numpy()[ok] * n[ok]).sum() / n[ok].sum()) if ok.any() else None
        )
    return pd.Series(out)


def _side_phrase(r: pd.Series, name: str) -> str:
    covers = (
        f", its interval held that value for {r['interval_covers']:.0%} of them"
        if r["interval_covers"] is not None and pd.notna(r["interval_covers"])
        else ""
    )
    return (
        f"from {name}, mean signed error {r['bias']:+.1%} and mean absolute error "
        f"{r['mape']:.1%} over {int(r['n'])} crown scans{covers}"
    )


def estimator_text(recommended: str, params: dict, table: pd.DataFrame | None = None) -> str:
    """One paragraph: the recommended estimator, what it measures, and its measured errors on
    the tree families (``table``: :func:`family_accuracy_table`, read when not given)."""
    table = family_accuracy_table() if table is None else table
    mine = table[table["method"] == recommended]
    shown = (
        f"{recommended} ({', '.join(f'{k} = {v}' for k, v in params.items())})"
        if params
        else recommended
    )
    what = measures(recommended)
    text = (
        f"Volumes: the recommended estimator of this preset is {shown}"
        + (f"; it measures {what}." if what else ".")
        + " The per-tree table says which volume each tree's is (what the recommended volume "
        "measures) and bounds it by an interval (volume low / high)."
    )
    old = mine[mine["age"] == "old"]
    if old.empty:
        return text + " Its accuracy was not measured on the tree families (docs/VOLUMES.md)."
    families = [FAMILY_NAMES.get(f, f) for f in dict.fromkeys(old["family"])]
    parts = [
        _side_phrase(pooled(old[old["side"] == side]), name)
        for side, name in SIDES.items()
        if (old["side"] == side).any()
    ]
    first = old.iloc[0]
    text += (
        f" Measured on tree families built {len(families)} ways ({'; '.join(families)}), "
        f"sensors {first['sensors']}, held-out seeds, against the same measurand on each tree's "
        "complete foliage (every leaf and branch, seen or not; the interval calibrated without "
        "the family it was checked on): " + "; ".join(parts) + "."
    )
    worst = old.loc[old["mape"].idxmax()]
    text += (
        f" The largest error was on {FAMILY_NAMES.get(worst['family'], worst['family'])} "
        f"seen from {SIDES[worst['side']]}: {worst['bias']:+.1%} (mean absolute "
        f"{worst['mape']:.1%})."
    )
    young = mine[(mine["age"] == "young") & (mine["side"] == "both")]
    if not young.empty:
        r = pooled(young)
        text += (
            f" On young trees, {r['bias']:+.1%} (mean absolute {r['mape']:.1%}); those whose few "
            "leaves do not close a crown are measured as the enclosing ellipsoid of their "
            "foliage, as young trees are in the field, and the table says so."
        )
    return text + (
        " These are the errors of the drive; a crown the segmentation cuts wrongly (touching "
        "crowns) errs beyond them, which a run checked against a simulated session counts"
        + touching_text(recommended)
        + " A crown volume also depends on its definition: "
        "an envelope drawn round the leaves' tips, or the convex hull, is larger (the table "
        "gives the paper's estimators on the same trees)."
    )


def touching_text(recommended: str) -> str:
    """The end of a sentence: how the interval fared on interwoven crowns, and that it is
    widened for them (``volume.interwoven``), where that was measured for ``recommended``."""
    from canopy_kit.segment.contact import TOUCHING_CONTACT
    from canopy_kit.volume.interwoven import (
        FREE_HELD,
        HELD_OUT_RUNS,
        INTERWOVEN_RATIOS,
        UNWIDENED_HELD,
        WIDENED_HELD,
    )

    ratios = INTERWOVEN_RATIOS.get(recommended)
    if ratios is None:
        return "."
    return (
        f": on simulated almond runs the interval held {FREE_HELD} trees whose crown touches "
        f"little of a neighbour's (crown_contact below {TOUCHING_CONTACT:g}); an interwoven "
        "one's volume follows the border the segmentation drew, so its interval is widened for "
        f"it ({ratios[0]:g}-{ratios[1]:g} × the estimate, measured there), which then held "
        f"{WIDENED_HELD} interwoven trees of {HELD_OUT_RUNS} ({UNWIDENED_HELD} before; the "
        "checks name them)."
    )


#: The ``wall`` preset on the fruiting-wall simulator's held-out seeds 7, 11, 13 (2 x 10,
#: run once after the preset was chosen on seeds 0-2; docs/SEGMENTATION.md "Fruiting walls"):
#: trees one-to-one, the recommended volume's median error per session, its MAPE per session,
#: and the cut volumes its interval held.
WALL_HELD_OUT = {
    "trees": "57 of 57",
    "median": "-1.6 to -4.5 %",
    "mape": "4.4-5.0 %",
    "interval": "54 of 57",
}


def wall_text(recommended: str) -> str:
    """One paragraph: what a wall tree's volume is and the recommended estimator's measured
    accuracy on held-out simulated walls, before the family table (made for free crowns)."""
    from canopy_kit.volume.uncertainty import CALIBRATIONS

    ratios = CALIBRATIONS[recommended].kinds.get("wall") if recommended in CALIBRATIONS else None
    held = WALL_HELD_OUT
    return (
        "Trees of a fruiting wall: each tree is the wall between the midpoints to its "
        "neighbours' trunks (volume.interval_kind = wall), a slab of the wall, not a crown of "
        f"its own. On held-out simulated walls {held['trees']} trees were found one to one and "
        f"{recommended} read their cuts {held['median']} (median per session, mean absolute "
        f"{held['mape']}); its interval"
        + (
            f" ({ratios[0]:.3f}-{ratios[1]:.3f} × the estimate, measured on wall cuts)"
            if ratios
            else ""
        )
        + f' held {held["interval"]} (docs/SEGMENTATION.md, "Fruiting walls"). One scene '
        "generator made those walls; real trellised trunks are untested. The tree families "
        "below are free crowns, for comparison. "
    )


def accuracy_section(recommended: str, params: dict, interval_kind: str = "") -> ReportSection:
    """A report section: the statement and, per tree family and side, the measured errors of
    the recommended estimator beside the paper's alpha shape and convex hull (young trees:
    the recommended one alone); on a wall (``interval_kind`` "wall") what its trees are and
    the measured accuracy on walls first."""
    table = family_accuracy_table()
    methods = list(dict.fromkeys([recommended, *PAPER_METHODS]))
    # old trees: the recommended estimator beside the paper's two; young: the recommended
    old = (table["age"] == "old") & table["method"].isin(methods)
    rows = table[old | ((table["age"] == "young") & (table["method"] == recommended))].copy()
    rows["order"] = rows["method"].map({m: i for i, m in enumerate(methods)})
    rows = rows.sort_values(["family", "age", "side", "order"], kind="stable")
    shown = pd.DataFrame(
        {
            "estimator": [
                m + (" (recommended)" if m == recommended else "") for m in rows["method"]
            ],
            "tree family": rows["family"].map(lambda f: FAMILY_NAMES.get(f, f)).to_numpy(),
            "trees": rows["age"].to_numpy(),
            "scan": rows["side"].map(SIDES).to_numpy(),
            "crown scans": rows["n"].astype(int).to_numpy(),
            "mean signed error": [f"{v:+.1%}" for v in rows["bias"]],
            "mean |error|": [f"{v:.1%}" for v in rows["mape"]],
            "90th percentile |error|": [f"{v:.1%}" for v in rows["p90"]],
            "interval held the value": [
                "" if pd.isna(v) else f"{v:.0%}" for v in rows["interval_covers"]
            ],
        }
    )
    return ReportSection(
        "Volume estimator, what it measures and its measured accuracy",
        text=(wall_text(recommended) if interval_kind == "wall" else "")
        + estimator_text(recommended, params, table),
        table=shown if len(shown) else None,
    )
