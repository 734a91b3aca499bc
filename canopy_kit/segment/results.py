"""The results table: segmentation success per method and orchard over simulated seeds.

``benchmarks/bench_segment.py accuracy`` writes one line per (session, method) to
``docs/segmentation_results.csv``; :func:`results_table` reads it back as the table in
docs/SEGMENTATION.md, for notebooks.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from canopy_kit.errors import InputError

RESULTS_CSV = Path(__file__).resolve().parents[2] / "docs" / "segmentation_results.csv"
METHOD_ORDER = ["dbscan", "dbscan_spectral", "adaptive"]


def success_table(runs: pd.DataFrame, metric: str = "success_points") -> pd.DataFrame:
    """Method x orchard: mean success over sessions, with min, max and session count."""
    if runs.empty:
        return pd.DataFrame()
    for col in ("method", "orchard", metric):
        if col not in runs.columns:
            raise InputError(f"results: column {col!r} missing (have {', '.join(runs.columns)})")
    g = runs.groupby(["method", "orchard"])[metric]
    table = pd.DataFrame({"mean": g.mean(), "min": g.min(), "max": g.max(), "sessions": g.size()})
    table = table.unstack("orchard")
    order = [m for m in METHOD_ORDER if m in table.index] + [
        m for m in table.index if m not in METHOD_ORDER]
    return table.loc[order]


def load_results(path: str | Path | None = None) -> pd.DataFrame:
    """The per-session results (long form) written by the accuracy benchmark."""
    p = Path(path) if path is not None else RESULTS_CSV
    if not p.exists():
        raise InputError(f"{p}: no segmentation results (run benchmarks/bench_segment.py accuracy "
                         "--csv docs/segmentation_results.csv)")
    return pd.read_csv(p)


def results_table(path: str | Path | None = None, variant: str = "default",
                  metric: str = "success_points") -> pd.DataFrame:
    """Method x orchard -> success rate over seeds (mean, min, max, sessions) for notebooks."""
    runs = load_results(path)
    if "variant" in runs.columns:
        runs = runs[runs["variant"] == variant]
    return success_table(runs, metric)
