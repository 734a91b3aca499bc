"""The report's statement of the volume estimator: which one, and how biased it was measured."""

from __future__ import annotations

import pandas as pd

from canopy_kit.report.html import ReportSection
from canopy_kit.volume.accuracy import accuracy_table

PAPER_METHODS = ("alpha_shape", "convex_hull")
SCANS = {"both": "both sides", "one-sided": "one side only"}
DENSE_FORMS = ("ellipsoid", "lobed", "vase", "hedged")


def _scan_phrase(r: pd.Series, name: str) -> str:
    covers = (
        f", its interval held the true volume for {r['interval_covers']:.0%} of them"
        if pd.notna(r["interval_covers"])
        else ""
    )
    return (
        f"seen from {name}, mean signed error {r['bias']:+.1%} and mean absolute error "
        f"{r['mape']:.1%} over {int(r['n'])} crown scans{covers}"
    )


def estimator_text(recommended: str, params: dict, table: pd.DataFrame | None = None) -> str:
    """One paragraph: the recommended estimator, its measured bias and where it comes from
    (``table``: :func:`accuracy_table`, read when not given)."""
    table = accuracy_table() if table is None else table
    mine = table[table["method"] == recommended]
    shown = (
        f"{recommended} ({', '.join(f'{k} = {v}' for k, v in params.items())})"
        if params
        else recommended
    )
    text = (
        f"Volumes: the recommended estimator of this preset is {shown}; the per-tree "
        "table's interval (volume low / high) bounds its volume."
    )
    dense = mine[mine["form"] == "dense"].set_index("scan")
    if dense.empty:
        return text + " Its accuracy was not measured in the accuracy matrix (docs/VOLUMES.md)."
    first = dense.iloc[0]
    parts = [
        _scan_phrase(dense.loc[scan], name) for scan, name in SCANS.items() if scan in dense.index
    ]
    text += (
        f" Measured on simulated crowns (sensors {first['sensors']}, held-out seeds "
        f"{first['seeds']}, trees segmented by the pipeline, "
        "benchmarks/bench_volume_matrix.py), on crowns whose foliage outlines the envelope "
        f"({', '.join(DENSE_FORMS)}): " + "; ".join(parts) + "."
    )
    sparse = mine[(mine["form"] == "sparse") & (mine["scan"] == "both")]
    if not sparse.empty:
        text += (
            f" On sparse young trees it is {sparse.iloc[0]['bias']:+.0%} (a few leaves do "
            "not outline the envelope, and every estimator is low there); such trees are "
            "flagged 'sparse crown' and get a wider interval."
        )
    return text + (
        " Real crowns unlike these can be further off; the table gives the paper's "
        "estimators on the same trees."
    )


def accuracy_section(recommended: str, params: dict) -> ReportSection:
    """A report section: the statement and the measured errors of the recommended estimator
    beside the paper's alpha shape and convex hull, per scan, on dense and on sparse crowns."""
    table = accuracy_table()
    methods = list(dict.fromkeys([recommended, *PAPER_METHODS]))
    rows = table[table["form"].isin(["dense", "sparse"]) & table["method"].isin(methods)].copy()
    rows["order"] = rows["method"].map({m: i for i, m in enumerate(methods)})
    rows = rows.sort_values(["form", "scan", "order"])
    shown = pd.DataFrame(
        {
            "estimator": [
                m + (" (recommended)" if m == recommended else "") for m in rows["method"]
            ],
            "crowns": rows["form"].map({"dense": "dense (4 forms)", "sparse": "sparse"}).to_numpy(),
            "scan": rows["scan"].map(SCANS).to_numpy(),
            "crown scans": rows["n"].astype(int).to_numpy(),
            "mean signed error": [f"{v:+.1%}" for v in rows["bias"]],
            "mean |error|": [f"{v:.1%}" for v in rows["mape"]],
            "90th percentile |error|": [f"{v:.1%}" for v in rows["p90"]],
        }
    )
    return ReportSection(
        "Volume estimator and its measured accuracy",
        text=estimator_text(recommended, params, table),
        table=shown if len(shown) else None,
    )
