"""The report's mapping section for a map made elsewhere (``canopy_kit.mapping.map_source``): which
file the map came from, its trajectory and georeference, instead of odometry figures."""

from __future__ import annotations

from typing import Any

import pandas as pd

from canopy_kit.report.html import ReportSection
from canopy_kit.results.checks import format_value


def finished_map_section(mapping: Any, evaluation: dict[str, Any] | None = None) -> ReportSection:
    """Text and a small table: the map file, its points and CRS, the trajectory file and, when
    a truth session judged it, the trajectory's ATE (or why it was not judged)."""
    d = mapping.diagnostics
    trajectory = d.get("trajectory_file") or "none given"
    rows = [
        ("map file", d.get("map_file", mapping.source)),
        ("points", f"{int(d.get('map_points', len(mapping.map))):,}"),
        ("CRS", d.get("crs") or "none: not georeferenced, local x/y"),
        ("trajectory file", trajectory),
        ("drive", format_value(d.get("path_length_m"), " m", 0)),
    ]
    evaluation = evaluation or {}
    if "ate_rmse_m" in evaluation:
        rows.append(("trajectory ATE vs truth", format_value(evaluation["ate_rmse_m"], " m", 3)))
    elif "not_judged" in evaluation:
        rows.append(("trajectory vs truth", evaluation["not_judged"]))
    text = (
        f"The map was made elsewhere and read from {d.get('map_file', mapping.source)}: "
        "canopy-kit did no odometry or mapping, so there are no mapping figures and the "
        "registration and GNSS checks are not judged. "
        + (
            "The trajectory file gives the drive (labels follow its first pass)."
            if d.get("trajectory_file")
            else "No trajectory was given: rows are labelled from the map alone."
        )
    )
    table = pd.DataFrame(rows, columns=["", "value"])
    return ReportSection("Mapping (map made elsewhere)", [], table, text)
