"""Crowns flagged from the imagery alone (``ground_truth.crown_flags``) on hand-made canopy
height models whose labels are known: two trees in one label, a fragment, single crowns."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from canopy_kit.errors import ConfigError, InputError
from ground_truth.crown_flags import (
    FLAG_COLUMN,
    FlagOptions,
    crown_rows,
    flag_crowns,
    flag_spacing,
    flag_summary,
    nearest_neighbour_spacing,
)
from ground_truth.crowns import CrownSegmentation, measure_crowns
from ground_truth.raster import Grid
from ground_truth.rows import RowDirection

SPACING = 5.0  # trees along each row (east), metres
RADIUS = 2.7  # cone crowns, touching their neighbours
ROWS_Y = (0.0, 8.0)


def cone_rows(trees: int = 6) -> tuple[Grid, np.ndarray, np.ndarray, np.ndarray]:
    """Two rows of cone crowns (4 m tall) along x: grid, CHM, tree centres (N, 2), and one label
    per tree (each cell to its nearest tree, canopy where the CHM is above 0.5 m)."""
    res = 0.1
    grid = Grid(-5.0, 13.0, res, int(26 / res), int((trees * SPACING + 5) / res))
    x, y = grid.centers()
    centres = np.array([(i * SPACING, ry) for ry in ROWS_Y for i in range(trees)])
    d = np.hypot(x[..., None] - centres[:, 0], y[..., None] - centres[:, 1])
    chm = np.clip(4.0 * (1.0 - d / RADIUS), 0.0, None).max(axis=-1)
    labels = np.where(chm > 0.5, d.argmin(axis=-1) + 1, 0).astype(np.int32)
    return grid, chm, centres, labels


def crowns_of(grid: Grid, chm: np.ndarray, labels: np.ndarray) -> pd.DataFrame:
    """The crowns table of these labels, extents along the rows (bearing 90°, east)."""
    from skimage.segmentation import relabel_sequential

    labels = relabel_sequential(labels)[0].astype(np.int32)
    n = int(labels.max())
    seg = CrownSegmentation(
        grid, labels, labels > 0, labels > 0, 0.0, np.zeros((n, 2)), np.full(n, -1), "rows"
    )
    return measure_crowns(seg, chm, RowDirection.from_bearing(90.0))


def row_of(crowns: pd.DataFrame) -> np.ndarray:
    return (crowns["y"].to_numpy() > 4.0).astype(int)


def crown_at(crowns: pd.DataFrame, x: float, y: float) -> int:
    return int(np.argmin(np.hypot(crowns["x"] - x, crowns["y"] - y)))


def test_single_cone_crowns_are_not_flagged():
    grid, chm, _, labels = cone_rows()
    crowns = crowns_of(grid, chm, labels)
    flags = flag_crowns(crowns, SPACING, row_of(crowns))
    assert len(crowns) == 12 and (flags == "").all(), crowns[["x", "diameter_along_row_m"]]


def test_two_cones_in_one_label_are_flagged_merged():
    grid, chm, _, labels = cone_rows()
    labels[labels == 4] = 3  # trees 3 and 4 of the first row (x = 10, 15 m) in one label
    crowns = crowns_of(grid, chm, labels)
    flags = flag_crowns(crowns, SPACING, row_of(crowns))
    merged = crown_at(crowns, 12.5, 0.0)
    # the label reaches from one crown's edge to the other's: about two spacings along the row
    assert crowns["diameter_along_row_m"].iloc[merged] == pytest.approx(SPACING + 2 * 2.5, abs=0.6)
    assert flags.iloc[merged] == "merged"
    assert (flags.drop(flags.index[merged]) == "").all(), flags.tolist()


def test_merged_found_by_area_when_the_spacing_is_unknown():
    """Without a spacing (NaN) the along-row test is off; twice the row's median area is not."""
    grid, chm, _, labels = cone_rows()
    labels[labels == 4] = 3
    crowns = crowns_of(grid, chm, labels)
    flags = flag_crowns(crowns, float("nan"), row_of(crowns))
    assert flags.iloc[crown_at(crowns, 12.5, 0.0)] == "merged"
    assert (flags == "merged").sum() == 1


def test_a_piece_of_a_crown_is_flagged_fragment():
    grid, chm, centres, labels = cone_rows()
    x, _ = grid.centers()
    # the outer 0.9 m of the second row's third tree (x = 10 m) becomes a label of its own
    piece = (labels == 9) & (x > 10.0 + RADIUS - 0.9)
    labels[piece] = labels.max() + 1
    crowns = crowns_of(grid, chm, labels)
    flags = flag_crowns(crowns, SPACING, row_of(crowns))
    fragment = crown_at(crowns, 12.3, 8.0)
    assert crowns["area_m2"].iloc[fragment] < 1.5
    assert flags.iloc[fragment] == "fragment"
    assert (flags == "fragment").sum() == 1 and (flags == "merged").sum() == 0, flags.tolist()


def test_a_crown_cut_by_the_border_is_no_fragment():
    grid, chm, _, labels = cone_rows()
    x, _ = grid.centers()
    labels[(labels == 9) & (x > 10.0 + RADIUS - 0.9)] = labels.max() + 1
    crowns = crowns_of(grid, chm, labels)
    crowns["touches_border"] = False
    crowns.loc[crowns.index[crown_at(crowns, 12.3, 8.0)], "touches_border"] = True
    assert (flag_crowns(crowns, SPACING, row_of(crowns)) == "").all()


def test_spacing_from_the_nearest_crowns_and_the_row_bands():
    _, _, centres, _ = cone_rows()
    assert nearest_neighbour_spacing(centres) == pytest.approx(SPACING)
    crowns = pd.DataFrame({"x": centres[:, 0], "y": centres[:, 1]})
    assert flag_spacing(crowns, None) == (pytest.approx(SPACING), "nearest_crowns")
    assert flag_spacing(crowns, None, 4.5) == (4.5, "given")
    assert (crown_rows(centres, None) == 0).all()


def test_summary_counts_each_kind():
    flags = pd.Series(["", "merged", "fragment", "merged", np.nan], name=FLAG_COLUMN)
    summary = flag_summary(flags, 4.8, "given")
    assert summary == {
        "merged": 2,
        "fragment": 1,
        "tree_spacing_m": 4.8,
        "tree_spacing_source": "given",
    }


def test_bad_input_names_the_parameter():
    crowns = pd.DataFrame({"area_m2": [10.0, 11.0], "diameter_along_row_m": [3.0, 3.1]})
    with pytest.raises(InputError, match="spacing_m"):
        flag_crowns(crowns, -1.0)
    with pytest.raises(InputError, match="rows"):
        flag_crowns(crowns, 4.0, np.zeros(3, int))
    with pytest.raises(InputError, match="diameter_along_row_m"):
        flag_crowns(crowns.drop(columns="diameter_along_row_m"), 4.0)
    with pytest.raises(ConfigError, match="merged_spacings"):
        FlagOptions(merged_spacings=0.0)
    with pytest.raises(ConfigError, match="fragment_area"):
        FlagOptions(fragment_area=3.0)
    assert flag_crowns(crowns.iloc[:0], 4.0).empty


def test_the_cli_says_how_many_crowns_are_flagged(tmp_path, monkeypatch, capsys):
    """``canopy-kit ground-truth`` prints the report's ``crown_flags`` (the flight's processing
    replaced by a made-up result)."""
    import sys
    from types import SimpleNamespace

    import ground_truth.pipeline as gp
    from canopy_kit.cli import main

    sfm = {
        "registered_images": 5,
        "total_images": 5,
        "mean_reprojection_error_px": 0.5,
        "gps_residual_rms_horizontal_m": 0.1,
        "gps_residual_rms_vertical_m": 0.1,
    }
    flags = {"merged": 2, "fragment": 1, "tree_spacing_m": 4.72, "tree_spacing_source": "given"}
    result = SimpleNamespace(
        report={"sfm": sfm, "crown_flags": flags},
        crowns=pd.DataFrame({"crown_id": [1, 2, 3]}),
        trees=None,
        paths={},
    )
    monkeypatch.setattr(gp, "process_flight", lambda *a, **k: result)
    photos = tmp_path / "photos"
    photos.mkdir()
    argv = ["canopy-kit", "ground-truth", str(photos), "--out", str(tmp_path / "out")]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as exit_info:
        main()
    out = " ".join(capsys.readouterr().out.split())
    assert exit_info.value.code in (0, None), out
    assert "crowns flagged from the imagery (crown_flag): 2 probably two trees, 1 fragments" in out
    assert "4.72 m (given)" in out
