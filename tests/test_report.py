"""The HTML report opens offline in a real browser with its table, figures and checks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from canopy_kit.report import Check, ReportSection, render_report, write_report
from canopy_kit.report.figures import figure_to_data_uri

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts"


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1, 2], [2, 0, 1])
    return figure_to_data_uri(fig)


@pytest.mark.browser
def test_report_renders_offline_in_chromium(tmp_path):
    trees = pd.DataFrame(
        {
            "tree_id": np.arange(12),
            "label": [f"L{i}" for i in range(12)],
            "volume_alpha_m3": np.linspace(30.0, 8.0, 12),
        }
    )
    page = render_report(
        "Test session",
        {"trees": 12, "ATE (m)": "0.05"},
        trees,
        [ReportSection("Map", figures=[("a figure", _figure()), ("another", _figure())])],
        [
            Check("trees matched", True, "12/12", "≥ 95 %"),
            Check("flagged volumes", False, "3", "0"),
        ],
        "[segment]\nmethod = 'adaptive'\n",
    )
    path = write_report(tmp_path / "report.html", page)
    assert "http://" not in page and "https://" not in page  # nothing to fetch
    from canopy_kit.report.browser import render_page

    shown = render_page(path, screenshot=ARTIFACTS / "test_report.png", sort_column=2)
    assert shown.title == "Test session"
    assert shown.tree_rows == 12
    assert shown.check_rows == 2
    assert shown.headline == "Do not trust this run: 1 check failed"
    assert shown.images_loaded == 2 and shown.images_broken == 0
    assert shown.blocked_requests == []
    assert shown.console_errors == []
    # Clicking the volume header sorts ascending numerically.
    values = [float(v) for v in shown.sorted_first_cells]
    assert values == sorted(values) and values[0] == pytest.approx(8.0)


def test_table_keeps_enough_decimals_for_geographic_coordinates() -> None:
    """Two trees 5 m apart differ in the 5th decimal of latitude: 3 decimals would show
    every tree at the same place."""
    from canopy_kit.report.html import table_html

    lat0 = 37.281002
    df = pd.DataFrame(
        {
            "tree_id": ["r0-L0", "r0-L1"],
            "lat": [lat0, lat0 + 5 / 111_320],
            "lon": [-120.419997, -120.419997],
            "height_m": [4.12345, 3.5],
        }
    )
    page = table_html(df, "trees")
    assert ">37.281002<" in page and ">37.281047<" in page and ">-120.419997<" in page
    assert ">4.123<" in page  # metres keep 3 decimals
