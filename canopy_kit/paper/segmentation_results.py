"""The segmentation accuracy results: success per method and orchard over simulated seeds.

``benchmarks/bench_segment.py accuracy`` writes one line per (session, method) to
``canopy_kit/paper/data/segmentation_results.csv`` (package data, so an installed
canopy-kit reads it too); :func:`results_table` reads it back as the table in
docs/SEGMENTATION.md, for notebooks.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pandas as pd

from canopy_kit.errors import InputError

#: Where the saved results are, inside the package (``canopy_kit.paper`` data).
RESULTS_CSV = "data/segmentation_results.csv"
#: The file in a source checkout, for the benchmark that writes it.
RESULTS_CSV_SOURCE = "canopy_kit/paper/data/segmentation_results.csv"
#: ``dbscan_spectral_scaled``: the paper's almond method with the ``almond-scaled`` preset;
#: ``dbscan_spectral_cells``: only its graph on 0.3 m cells, the paper's threshold
METHOD_ORDER = [
    "dbscan",
    "dbscan_spectral",
    "dbscan_spectral_cells",
    "dbscan_spectral_scaled",
    "adaptive",
]


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
        m for m in table.index if m not in METHOD_ORDER
    ]
    return table.loc[order]


def load_results(path: str | Path | None = None) -> pd.DataFrame:
    """The per-session results (long form) written by the accuracy benchmark."""
    if path is None:
        packaged = resources.files("canopy_kit.paper").joinpath(RESULTS_CSV)
        if not packaged.is_file():
            raise InputError(
                f"{RESULTS_CSV_SOURCE}: no segmentation results (run benchmarks/"
                f"bench_segment.py accuracy --csv {RESULTS_CSV_SOURCE})"
            )
        with resources.as_file(packaged) as p:
            return pd.read_csv(p)
    p = Path(path)
    if not p.exists():
        raise InputError(
            f"{p}: no segmentation results (run benchmarks/bench_segment.py accuracy "
            f"--csv {RESULTS_CSV_SOURCE})"
        )
    return pd.read_csv(p)


def results_table(
    path: str | Path | None = None, variant: str = "default", metric: str = "success_points"
) -> pd.DataFrame:
    """Method x orchard -> success rate over seeds (mean, min, max, sessions) for notebooks."""
    runs = load_results(path)
    if "variant" in runs.columns:
        runs = runs[runs["variant"] == variant]
    return success_table(runs, metric)


#: Our targets (issue: adaptive >= 98 % pistachio and >= 95 % almond with the same settings;
#: dbscan_spectral at least the paper's 80 % on almond). The almond rows apply to every
#: almond-like orchard; on the default ``almond`` the ``almond-scaled`` preset's 30,000-point
#: threshold is below a typical tree's map points there, so it is not expected to meet it.
TARGETS = {
    ("pistachio", "adaptive"): 0.98,
    ("almond", "adaptive"): 0.95,
    ("almond", "dbscan_spectral"): 0.80,
    ("almond", "dbscan_spectral_scaled"): 0.80,
}


def reproduction_table(runs: pd.DataFrame, metric: str = "success_points") -> pd.DataFrame:
    """Method x orchard, flat: trees correct over all sessions (pooled), the per-session
    range, the paper's figure and our target beside; one row per method and orchard."""
    from canopy_kit.evaluate.truth import orchard_kind
    from canopy_kit.paper.comparison import PAPER_SEGMENTATION

    if runs.empty:
        return pd.DataFrame()
    for col in ("method", "orchard", "seed", "n_truth", metric):
        if col not in runs.columns:
            raise InputError(f"results: column {col!r} missing (have {', '.join(runs.columns)})")
    runs = runs.assign(_correct=(runs[metric] * runs["n_truth"]).round())
    rows = []
    methods = [m for m in METHOD_ORDER if m in set(runs["method"])] + sorted(
        set(runs["method"]) - set(METHOD_ORDER)
    )
    for orchard in sorted(set(runs["orchard"]), key=lambda o: (o != "pistachio", o)):
        for method in methods:
            r = runs[(runs["orchard"] == orchard) & (runs["method"] == method)]
            if r.empty:
                continue
            key = (orchard_kind(orchard), method)
            rows.append(
                {
                    "orchard": orchard,
                    "method": method,
                    "seeds": " ".join(str(s) for s in sorted(set(r["seed"]))),
                    "trees": int(r["n_truth"].sum()),
                    "correct": int(r["_correct"].sum()),
                    "success": r["_correct"].sum() / r["n_truth"].sum(),
                    "min": r[metric].min(),
                    "max": r[metric].max(),
                    "paper": PAPER_SEGMENTATION.get(key, float("nan")),
                    "target": TARGETS.get(key, float("nan")),
                }
            )
    return pd.DataFrame(rows)


def reproduction_results(
    path: str | Path | None = None,
    seeds: list[int] | None = None,
    variant: str = "default",
    metric: str = "success_points",
) -> pd.DataFrame:
    """The table of docs/SEGMENTATION.md from the saved results (``seeds``: only these)."""
    runs = load_results(path)
    if "variant" in runs.columns:
        runs = runs[runs["variant"] == variant]
    if seeds is not None:
        runs = runs[runs["seed"].isin(seeds)]
    return reproduction_table(runs, metric)
