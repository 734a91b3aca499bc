"""The checks of finished runs as the table of docs/VALIDATION.md.

    .venv/bin/python benchmarks/bench_checks.py LABEL=RUN_DIR [LABEL=RUN_DIR ...]

Each RUN_DIR is a ``canopy-kit run`` output folder (metrics.json, trees.csv, config.toml);
its checks are computed again with this code (``checks.run_checks`` on the finished run),
one row per run: trees found, the spacing and trunk checks, the aerial MAPEs and the count
by status.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

COLUMNS = [
    "widest crown over the tree spacing along the row",
    "widest crown over the row spacing",
    "most trunks under one segmented tree",
    "alpha shape vs aerial height-aware ellipsoid volume (MAPE)",
    "alpha shape vs aerial paper's sphere volume (MAPE)",
]
HEADER = [
    "run",
    "trees",
    "crown / tree spacing",
    "crown / row spacing",
    "trunks under one tree",
    "MAPE vs ellipsoid",
    "MAPE vs sphere",
    "pass / warn / fail / info",
]


def row(label: str, run: Path) -> list[str]:
    """One table row for the run folder ``run``."""
    import pandas as pd

    from canopy_kit.config import load_preset
    from canopy_kit.results.checks import run_checks, summary

    metrics = json.loads((run / "metrics.json").read_text())
    trees = pd.read_csv(run / "trees.csv")
    found = run_checks(metrics, trees, load_preset(run / "config.toml").checks)
    checks = {c.name: c.as_dict() for c in found}
    cells = [label, str(metrics["n_trees"])]
    for name in COLUMNS:
        c = checks.get(name)
        cells.append(f"{c['value']} ({c['status']})" if c else "")
    s = summary(found)
    cells.append(f"{s['pass']} / {s['warn']} / {s['fail']} / {s['info']}")
    return cells


def main(argv: list[str]) -> None:
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for arg in argv:
        label, _, path = arg.partition("=")
        print("| " + " | ".join(row(label, Path(path))) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
