"""A wall run says when its trunks were probably missed (issue 52): per row, the map points at
the stem band's foot against its canopy's, the gaps between the trunks found, the check and
the per-tree flag. Hand-made rows with counts known by construction (no simulation)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from canopy_kit.segment.rows import RowAssignment, RowLine
from canopy_kit.segment.trunk_feet import (
    CANOPY_BAND_M,
    FOOT_BAND_M,
    MIN_FOOT_SHARE,
    row_feet,
    trunk_feet,
)

ANGLE = np.pi / 6  # rows along a direction at 30 degrees: nothing hangs on the axes
D = np.array([np.cos(ANGLE), np.sin(ANGLE)])
RIGHT = np.array([D[1], -D[0]])
LENGTH = 10.0  # each row's trees span 0-10 m along it


def _rows(across: list[float]) -> RowAssignment:
    lines = [RowLine(k, D, (c, 0.0, 0.0), (0.0, LENGTH), 10) for k, c in enumerate(across)]
    return RowAssignment(np.zeros(0, int), np.zeros(0, int), [], lines, D, "test")


def _points(n: int, across: float, offset: float, band: tuple[float, float]) -> np.ndarray:
    """``n`` points evenly along 0-10 m of the row at ``across``, ``offset`` from its line,
    at heights inside ``band``; (xyz, height)."""
    along = (np.arange(n) + 0.5) * LENGTH / n
    xy = along[:, None] * D + (across + offset) * RIGHT
    h = np.full(n, 0.5 * (band[0] + band[1]))
    return np.column_stack([xy, h])


def _wall(foot: list[int], canopy: int = 20000) -> tuple[np.ndarray, RowAssignment]:
    """Two rows 3.2 m apart, ``canopy`` points in each one's canopy band (0.5 m off its line)
    and ``foot[k]`` at row k's foot (0.2 m off); at each row also points the rule must not
    count: grass in the alley at the foot's height (0.8 m off), the wall's top above the
    canopy band and foot points beyond the row's end."""
    rows = _rows([0.0, 3.2])
    parts = []
    for k, c in enumerate([0.0, 3.2]):
        parts += [
            _points(canopy, c, 0.5, CANOPY_BAND_M),
            _points(foot[k], c, -0.2, FOOT_BAND_M),
            _points(5000, c, 0.8, FOOT_BAND_M),  # grass in the alley: beyond the foot's reach
            _points(5000, c, 0.0, (2.5, 3.0)),  # the wall's top: above the canopy band
        ]
        beyond = _points(3000, c, 0.0, FOOT_BAND_M)
        beyond[:, :2] += 12.0 * D  # past the row's last tree
        parts.append(beyond)
    cloud = np.vstack(parts)
    return cloud, rows


def test_the_foot_and_canopy_are_counted_per_metre_of_the_row() -> None:
    """600 foot and 20000 canopy points over the 10 m of row 0 (3 % by construction), 200
    over row 1 (1 %); the alley's grass, the wall's top and points past the row's end are
    not counted."""
    cloud, rows = _wall([600, 200])
    feet = row_feet(cloud, cloud[:, 2], np.zeros((0, 2)), rows)
    assert [r.row for r in feet] == [0, 1]
    assert feet[0].length_m == pytest.approx(10.0)
    assert feet[0].foot_per_m == pytest.approx(60.0)
    assert feet[0].canopy_per_m == pytest.approx(2000.0)
    assert feet[0].foot_share == pytest.approx(0.03)
    assert feet[1].foot_share == pytest.approx(0.01)
    assert [r.trunks_missed for r in feet] == [False, True]


def test_only_the_thinly_sampled_row_warns_and_its_trees_are_flagged() -> None:
    """Row 1's foot at 1 % of its canopy (below the 1.8 % limit) warns, naming the row and
    its share; its trees, not row 0's, are flagged. Both rows above the limit: no warning."""
    cloud, rows = _wall([600, 200])
    ids = ["r0-L0", "r0-L1", "r1-R0", "r1-R1"]
    got = trunk_feet(cloud, cloud[:, 2], np.zeros((0, 2)), rows, ids, np.array([0, 0, 1, 1]))
    assert got.flagged_trees == ["r1-R0", "r1-R1"]
    assert "row r1:" in got.warning and "1.0 % of its canopy" in got.warning
    assert "row r0" not in got.warning
    d = got.as_dict()
    assert [r["trunks_missed"] for r in d["rows"]] == [False, True]
    # just above the limit on both rows: silent
    above = int(np.ceil(MIN_FOOT_SHARE * 20000)) + 1
    cloud, rows = _wall([above, above])
    quiet = trunk_feet(cloud, cloud[:, 2], np.zeros((0, 2)), rows, ids, np.array([0, 0, 1, 1]))
    assert quiet.warning == "" and quiet.flagged_trees == []


def test_a_removed_trunk_leaves_a_doubled_gap() -> None:
    """Trunks every 1 m along row 0 with the one at 3 m removed: gaps 1, 1, 1, 2, 1, 1 m,
    median 1 m, one gap at least 1.6x it; all ten trunks: none. Row 1's trunks (3.2 m
    across) are not row 0's."""
    cloud, rows = _wall([600, 600])
    along = np.array([0.0, 1.0, 2.0, 4.0, 5.0, 6.0, 7.0])
    row0 = along[:, None] * D + 0.05 * RIGHT
    row1 = np.arange(10.0)[:, None] * D + 3.2 * RIGHT
    feet = row_feet(cloud, cloud[:, 2], np.vstack([row0, row1]), rows)
    np.testing.assert_allclose(feet[0].gaps, [1, 1, 2, 1, 1, 1], atol=1e-9)
    assert feet[0].median_gap_m == pytest.approx(1.0)
    assert feet[0].doubled == 1
    assert len(feet[1].trunks_along) == 10 and feet[1].doubled == 0
    assert "1 of 6 gaps 1.6x the median 1.00 m" in feet[0].statement()


def _metrics(missed: bool) -> dict:
    cloud, rows = _wall([600, 200 if missed else 600])
    got = trunk_feet(cloud, cloud[:, 2], np.zeros((0, 2)), rows, ["a", "b"], np.array([0, 1]))
    warnings = [got.warning] if got.warning else []
    return {"segmentation": {"trunk_feet": got.as_dict()}, "warnings": warnings}


def test_the_check_warns_once_and_a_crown_run_has_none() -> None:
    """The run's check warns on the thin row (its warning is carried by the check, not
    repeated as a plain warning), passes when both rows are sampled, and is absent from a run
    that is not cut at the trunks' midpoints."""
    from canopy_kit.results.checks import run_checks

    trees = pd.DataFrame({"tree_id": ["a", "b"]})
    name = "rows whose trunks' feet are barely sampled (trunks missed, trees joined?)"
    warned = run_checks(_metrics(True), trees)
    mine = [c for c in warned if c.name == name]
    assert len(mine) == 1 and mine[0].status == "warn" and mine[0].value == "1 of 2"
    assert "r1 1.0 %" in mine[0].note and "trunk_flags: b" in mine[0].note
    assert not [c for c in warned if c.name == "warning"]
    passed = [c for c in run_checks(_metrics(False), trees) if c.name == name]
    assert len(passed) == 1 and passed[0].status == "pass"
    crowns = run_checks({"segmentation": {}, "warnings": []}, trees)
    assert not [c for c in crowns if c.name == name]


def test_trunk_flags_name_the_trees_of_the_thin_rows() -> None:
    from canopy_kit.results.tree_table import trunk_flags

    trees = pd.DataFrame({"tree_id": ["a", "b", "c"]})
    got = trunk_flags(trees, {"flagged_trees": ["b"]})
    assert (got != "").tolist() == [False, True, False]


def test_a_tree_of_a_row_whose_trunks_were_missed_claims_no_interval() -> None:
    """Its volume may hold a missed neighbour: the bounds become NaN with the reason after
    any earlier flag; the other trees keep theirs; a table without the columns is unchanged."""
    from canopy_kit.results.tree_table import (
        NO_INTERVAL_NOTE,
        no_interval_where_trunks_missed,
        trunk_flags,
    )

    trees = pd.DataFrame(
        {
            "tree_id": ["a", "b", "c"],
            "volume_low_m3": [1.0, 2.0, 3.0],
            "volume_high_m3": [1.2, 2.4, 3.6],
            "volume_interval_flags": ["", "one-sided scan", ""],
        }
    )
    trees["trunk_flags"] = trunk_flags(trees, {"flagged_trees": ["b", "c"]})
    out = no_interval_where_trunks_missed(trees)
    assert out["volume_low_m3"].tolist()[0] == 1.0 and out["volume_high_m3"].tolist()[0] == 1.2
    assert out[["volume_low_m3", "volume_high_m3"]].iloc[1:].isna().all().all()
    assert out["volume_interval_flags"].tolist() == [
        "",
        f"one-sided scan; {NO_INTERVAL_NOTE}",
        NO_INTERVAL_NOTE,
    ]
    assert no_interval_where_trunks_missed(trees.drop(columns="trunk_flags")).equals(
        trees.drop(columns="trunk_flags")
    )


def test_trunk_flags_follow_the_ids_of_the_segmentation_that_measured_the_feet() -> None:
    """A streamed stretch's table has segments, not the run's tree ids: the flags and the
    withdrawn interval follow the ids given for its rows."""
    from canopy_kit.results.tree_table import NO_INTERVAL_NOTE, with_trunk_flags

    table = pd.DataFrame(
        {
            "segment": [4, 7],
            "volume_low_m3": [1.0, 2.0],
            "volume_high_m3": [1.2, 2.4],
            "volume_interval_flags": ["", ""],
        }
    )
    ids = table["segment"].map({4: "r0-L0", 7: "r0-L1"})
    out = with_trunk_flags(table, {"flagged_trees": ["r0-L1"]}, ids)
    assert (out["trunk_flags"] != "").tolist() == [False, True]
    assert out["volume_low_m3"].tolist()[0] == 1.0 and np.isnan(out["volume_low_m3"][1])
    assert out["volume_interval_flags"].tolist() == ["", NO_INTERVAL_NOTE]
    assert "tree_id" not in out  # the run names its trees later
