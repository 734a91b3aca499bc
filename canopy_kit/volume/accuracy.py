"""The measured accuracy of each volume estimator, as the report quotes it.

``data/family_accuracy.csv`` is written by ``benchmarks/bench_volume_families.py report
--summary``: tree families built different ways (the simulator's envelope crowns, lobe
unions, space-colonisation trees, real terrestrial scans re-scanned), four sensor models,
held-out seeds, both sides and one side of the row. Signed bias, MAPE and p90 of |error| of
the drive's estimate against the same estimator on the tree's complete foliage (what the
drive lost), and how often the recommended estimator's interval, calibrated without that
family, held that value.

``data/accuracy.csv`` is written by ``benchmarks/bench_volume_matrix.py --summary``: the
simulator's crown forms, trees segmented by the pipeline, against the simulator's envelope.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import pandas as pd

ACCURACY_FILE = "accuracy.csv"
FAMILY_ACCURACY_FILE = "family_accuracy.csv"


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
    return _shipped(ACCURACY_FILE)


def family_accuracy_table() -> pd.DataFrame:
    """The shipped accuracy on tree families (family, age, side, method, n, bias, mape, p90,
    interval_covers, seeds, sensors): errors against the same estimator on complete foliage."""
    return _shipped(FAMILY_ACCURACY_FILE)


def _shipped(name: str) -> pd.DataFrame:
    path = resources.files("canopy_kit.volume") / "data" / name
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
