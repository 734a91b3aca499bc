"""The measured accuracy of each volume estimator, as the report quotes it.

``data/accuracy.csv`` is written by ``benchmarks/bench_volume_matrix.py --summary``: every
crown form the simulator makes, seen by four sensor models, on held-out seeds, trees
segmented by the pipeline, both sides and one side of the row. Signed bias, MAPE and p90 of
|error| against the exact crown volume, and how often the interval held the truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import pandas as pd

ACCURACY_FILE = "accuracy.csv"


@dataclass(frozen=True)
class MeasuredAccuracy:
    """One estimator's measured errors on one kind of scan (both sides or one-sided)."""

    method: str
    scan: str
    n: int
    bias: float
    mape: float
    p90: float
    interval_covers: float | None
    sensors: str
    seeds: str


def accuracy_table() -> pd.DataFrame:
    """The shipped accuracy table (scan, form, method, n, bias, mape, p90, interval_covers...)."""
    path = resources.files("canopy_kit.volume") / "data" / ACCURACY_FILE
    with resources.as_file(path) as file:
        return pd.read_csv(file)


def measured_accuracy(
    method: str, scan: str = "both", form: str = "all"
) -> MeasuredAccuracy | None:
    """The measured accuracy of ``method`` (``None`` when it was not in the matrix)."""
    table = accuracy_table()
    hit = table[(table["method"] == method) & (table["scan"] == scan) & (table["form"] == form)]
    if hit.empty:
        return None
    r = hit.iloc[0]
    covers = float(r["interval_covers"]) if pd.notna(r["interval_covers"]) else None
    return MeasuredAccuracy(
        method,
        scan,
        int(r["n"]),
        float(r["bias"]),
        float(r["mape"]),
        float(r["p90"]),
        covers,
        str(r["sensors"]),
        str(r["seeds"]),
    )
