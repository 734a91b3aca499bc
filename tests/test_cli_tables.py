"""CLI tables on an 80-column terminal and through a pipe: no line wider than the terminal,
every value still there (whole), tab-separated text when piped."""

from __future__ import annotations

import pandas as pd
import pytest
from typer.testing import CliRunner

from canopy_kit.cli import app, common
from canopy_kit.cli.tables import Grid, frame_grid, plan_parts, print_grid, to_tsv, widen
from canopy_kit.paper import experiments as ex

WIDTH = 80


@pytest.fixture()
def terminal(monkeypatch):
    """The CLI's console as on an 80-column terminal (no colours, to read the text)."""
    con = common.make_console(force_terminal=True, width=WIDTH, color_system=None)
    monkeypatch.setattr(common, "console", con)
    return con


def invoke(*args: str) -> str:
    result = CliRunner().invoke(app, list(args))
    assert result.exit_code == 0, result.output
    return result.stdout


def assert_fits(text: str, width: int = WIDTH) -> None:
    wide = [line for line in text.splitlines() if len(line) > width]
    assert not wide, f"{len(wide)} lines wider than {width}: {wide[:2]}"


def test_parts_repeat_the_keys_and_fit():
    needs = [9, 15, 8] + [6] * 13
    parts = plan_parts(needs, keys=3, width=WIDTH)
    assert parts is not None and len(parts) > 1
    assert all(p[:3] == [0, 1, 2] for p in parts)
    assert sorted(i for p in parts for i in p[3:]) == list(range(3, 16))  # each once
    assert all(1 + sum(needs[i] + 3 for i in p) <= WIDTH for p in parts)
    assert plan_parts([40, 40, 5], keys=2, width=WIDTH) is None  # keys alone too wide
    assert plan_parts([5, 5], keys=1, width=WIDTH) == [[0, 1]]
    # value columns get their natural width first, prose columns share what is left
    assert widen([4, 4, 4], [10, 50, 50], 60, [False, True, True]) == [10, 20, 20]  # 60 - 1 - 3 x 3


def test_experiments_at_80_columns_and_piped(terminal):
    saved = ex.load_results()
    text = invoke("paper", "experiments", "--show-saved")
    assert_fits(text)
    assert "(1/" in text  # the wide tables came in parts
    for r in saved.comparison.to_dict("records"):
        assert f"{r['success_pct']:.1f}" in text and f"{r['n_correct']}/{r['n_truth']}" in text
        assert f"{r['alpha_shape_mape_vs_crown_pct']:.1f}" in text
    assert text.count("dbscan_spectral") >= 2 * len(saved.comparison) / 3
    # Piped (CliRunner's stdout is no terminal): a header line and one line per row.
    common.console = common.make_console()
    piped = invoke("paper", "experiments", "--show-saved")
    lines = piped.splitlines()
    head = (
        lines.index("# Segmentation success (%): one-to-one point IoU >= 0.5 with a true tree") + 1
    )
    columns = lines[head].split("\t")
    assert columns[:4] == ["orchard", "method", "mapping", "paper"] and len(columns) == 12
    rows = [line.split("\t") for line in lines[head + 1 : head + 1 + len(saved.comparison)]]
    assert all(len(r) == 12 for r in rows)
    assert [r[1] for r in rows] == list(saved.comparison["method"])
    assert [r[4] for r in rows] == [f"{v:.1f}" for v in saved.comparison["success_pct"]]
    assert "┃" not in piped and "│" not in piped


def test_table1_at_80_columns(terminal):
    text = invoke("paper", "table1")
    assert_fits(text)
    for value in (
        "28.06",
        "33.26",
        "18.55",
        "Bland-Altman 95% limits (m³)",
        "reordered",
        "-2.406 .. +6.492",
        "3.7700 .. 3.7704",
    ):
        assert value in text


def test_a_grid_too_wide_for_parts_becomes_records():
    from rich.console import Console

    grid = Grid(["very long key column name", "another long key"] + ["x"] * 3, keys=2, title="wide")
    grid.add_row("k" * 40, "j" * 35, "1", "2", "3")
    con = Console(force_terminal=True, width=WIDTH, color_system=None, record=True)
    print_grid(grid, con)
    text = con.export_text()
    assert_fits(text)
    assert "k" * 40 in text and "j" * 35 in text and "another long key" in text


def test_key_value_prose_wraps_within_the_width():
    from rich.console import Console

    grid = Grid(["fact", "value"], header=False, wrap={1})
    grid.add_row("topics", ", ".join(f"/sensor/topic_{i}" for i in range(20)))
    con = Console(force_terminal=True, width=WIDTH, color_system=None, record=True)
    print_grid(grid, con)
    text = con.export_text()
    assert_fits(text)
    assert "/sensor/topic_19" in text and "/sensor/topic_0," in text
    assert to_tsv(grid).count("\t") == 1


def test_store_growth_at_80_columns_and_piped(terminal, tmp_path):
    import datetime as dt

    import numpy as np

    from canopy_kit.core.geo import LocalFrame
    from canopy_kit.store import OrchardStore, SessionRecord

    frame = LocalFrame.at(37.281, -120.42)
    xy = np.array([[r * 6.0, i * 5.0, 0.0] for r in range(2) for i in range(3)])
    lat, lon, _ = frame.to_wgs84(xy)
    with OrchardStore(tmp_path / "orchard.duckdb") as db:
        for month, factor in ((4, 1.0), (6, 1.25)):
            table = pd.DataFrame(
                {
                    "segment": range(6),
                    "label": [f"L{i}" for i in range(6)],
                    "row": [0, 0, 0, 1, 1, 1],
                    "lat": lat,
                    "lon": lon,
                    "n_points": 1000,
                    "height_m": 3.0,
                    "crown_diameter_m": 3.5,
                    "volume_convex_hull_m3": 31.5 * factor,
                    "volume_alpha_m3": 30.0 * factor,
                    "volume_flags": "",
                }
            )
            db.ingest(SessionRecord(f"block-a-{month}", "block-a", dt.date(2025, month, 1)), table)
    store = str(tmp_path / "orchard.duckdb")
    for args in (("sessions",), ("growth",), ("growth", "--rows")):
        text = invoke("store", *args, store)
        assert_fits(text)
        assert "block-a" in text
    assert "37.500" in invoke("store", "growth", store)  # 30 m³ x 1.25, whole
    common.console = common.make_console()
    piped = invoke("store", "growth", store).splitlines()
    assert piped[0].split("\t")[:3] == ["orchard", "tree_id", "tree_label"]
    assert len(piped) == 1 + 12 and all(len(p.split("\t")) == 9 for p in piped)


def test_frame_grid_formats_and_escapes():
    grid = frame_grid(pd.DataFrame({"name": ["[red]x", None], "v": [1.23456, float("nan")]}))
    assert grid.rows[0][1] == "1.235" and grid.rows[1][1] == "-"
    assert to_tsv(grid).splitlines()[1] == "[red]x\t1.235"  # markup kept as text
    assert grid.right == {1}
