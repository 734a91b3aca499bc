"""Checks that need no truth, on hand-built tables whose answer is known by construction."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from canopy_kit.config import ChecksConfig, load_preset
from canopy_kit.errors import ConfigError
from canopy_kit.results.checks import (
    Check,
    aerial_checks,
    ceiling_check,
    crown_spacing_checks,
    grade,
    map_checks,
    map_edge_check,
    run_checks,
    split_crown_check,
    summary,
    trunk_checks,
)

ST = ChecksConfig()


def _row(diameters: list[float], spacing: float = 5.0) -> pd.DataFrame:
    n = len(diameters)
    return pd.DataFrame(
        {
            "tree_id": [f"r0-L{i}" for i in range(n)],
            "row": 0,
            "x": np.zeros(n),
            "y": spacing * np.arange(n),
            "crown_diameter_m": diameters,
            "segment_flags": "",
            "volume_flags": "",
        }
    )


def _by_name(checks: list[Check], start: str) -> Check:
    (c,) = [c for c in checks if c.name.startswith(start)]
    return c


def test_regular_trees_pass_the_spacing_checks() -> None:
    trees = _row([4.0, 4.2, 3.9, 4.1, 4.0, 4.3])
    checks = crown_spacing_checks(
        trees, {"tree_spacing_m": 5.0, "row_spacing_m": 6.0, "tree_spacing_source": "trunks"}, ST
    )
    assert [c.status for c in checks] == ["pass", "pass"]
    assert _by_name(checks, "widest crown over the tree").value == "0.86x"  # 4.3 / 5.0


def test_a_crown_three_spacings_wide_fails() -> None:
    trees = _row([4.0, 4.2, 15.0, 4.1, 4.0, 4.3])  # 15 m = 3x the 5 m spacing, 2.5x the rows'
    checks = crown_spacing_checks(
        trees, {"tree_spacing_m": 5.0, "row_spacing_m": 6.0, "tree_spacing_source": "trunks"}, ST
    )
    tree, row = (
        _by_name(checks, "widest crown over the tree"),
        _by_name(checks, "widest crown over the row"),
    )
    assert tree.value == "3.00x" and tree.status == "warn"  # fail beyond 3.0x, not at it
    assert row.value == "2.50x" and row.status == "fail" and "r0-L2" in row.note
    assert row.threshold == "warn > 1.00x, fail > 1.75x"


def test_unknown_spacings_give_no_spacing_check() -> None:
    assert (
        crown_spacing_checks(_row([4.0, 4.0]), {"tree_spacing_m": None, "row_spacing_m": None}, ST)
        == []
    )


def test_trunks_per_segment() -> None:
    trees = _row([4.0] * 4).assign(n_trunks=[1, 1, 0, 1])
    (one,) = trunk_checks(trees, {"trunks": 3}, ST)
    assert one.status == "pass" and one.value == "1"
    (two,) = trunk_checks(trees.assign(n_trunks=[1, 2, 1, 1]), {"trunks": 5}, ST)
    assert two.status == "warn" and "r0-L1" in two.note
    (five,) = trunk_checks(trees.assign(n_trunks=[5, 1, 1, 1]), {"trunks": 8}, ST)
    assert five.status == "fail"
    assert trunk_checks(trees, {"trunks": 0}, ST) == []  # no trunks seen: nothing to say


def test_a_trunkless_piece_beside_its_tree_is_a_split_crown() -> None:
    """Four trees 5 m apart on their trunks pass; a fifth segment on no trunk 2 m from a
    tree (the other half of its crown) fails and is named; a trunkless tree a full spacing
    from its neighbours (its trunk hidden) is not counted; with trunks under too few trees
    (an airborne scan) the check only informs."""
    layout = {"trunks": 4, "tree_spacing_m": 5.0, "tree_spacing_source": "trunks"}
    trees = _row([4.0] * 4).assign(n_trunks=1)
    (whole,) = split_crown_check(trees, layout, ST)
    assert whole.status == "pass" and whole.value == "0"
    piece = pd.DataFrame({"tree_id": ["r0-L4"], "row": 0, "x": [0.0], "y": [7.0], "n_trunks": [0]})
    split = pd.concat([trees, piece], ignore_index=True)
    (cut,) = split_crown_check(split, layout, ST)
    assert cut.status == "fail" and cut.value == "1" and "r0-L4" in cut.note
    assert cut.threshold == "fail > 0"  # any piece fails: no warning band between
    assert "4 trunks found in the stem band under 5 trees" in cut.note
    hidden = trees.assign(n_trunks=[1, 1, 0, 1])  # 5 m from both neighbours
    assert split_crown_check(hidden, {**layout, "trunks": 3}, ST)[0].status == "pass"
    loose = ChecksConfig(split_crowns_warn=0, split_crowns_fail=2)
    assert split_crown_check(split, layout, loose)[0].status == "warn"
    airborne = split.assign(n_trunks=[1, 0, 0, 0, 0])
    (info,) = split_crown_check(airborne, layout, ST)
    assert info.status == "info" and "not judged" in info.note
    assert split_crown_check(split, {**layout, "tree_spacing_source": "segments"}, ST) == []
    assert _by_name(run_checks({"layout": layout}, split), "segments on no trunk").status == "fail"
    # in a row whose trunks' feet the sensor barely saw (segment.trunk_feet), the note says
    # that missed trunks are the likelier cause; the grade stays
    feet = split.assign(trunk_flags="its row's trunk feet barely sampled")  # every tree's row
    (missed,) = split_crown_check(feet, layout, ST)
    assert (
        missed.status == "fail" and "1 of them in rows whose trunks' feet are barely" in missed.note
    )
    assert "barely sampled" not in cut.note


def test_crowns_cut_at_a_set_canopy_top_fail_and_a_band_from_the_data_passes() -> None:
    cut = {
        "canopy_band_m": [0.8, 12.0],
        "canopy_ceiling_source": "preprocess.max_canopy_height",
        "cut_at_ceiling": ["r0-L0", "r0-L2"],
    }
    (check,) = ceiling_check(cut, ST)
    assert check.status == "fail" and check.value == "2" and "r0-L0, r0-L2" in check.note
    whole = {**cut, "canopy_band_m": [0.8, 17.43], "canopy_ceiling_source": "data"}
    (ok,) = ceiling_check({**whole, "cut_at_ceiling": []}, ST)
    assert ok.status == "pass" and "0.8-17.4 m above ground (from the data)" in ok.note
    assert ceiling_check({}, ST) == []  # a run from before the band was recorded


def test_crown_outliers_share() -> None:
    trees = _row([4.0] * 10)
    assert _by_name(run_checks({}, trees), "crowns unlike").status == "pass"
    one = trees.assign(segment_flags=[""] * 9 + ["crown 9 m wide"])
    assert _by_name(run_checks({}, one), "crowns unlike").status == "warn"  # 10 %: not beyond
    two = trees.assign(segment_flags=[""] * 8 + ["wide"] * 2)
    assert _by_name(run_checks({}, two), "crowns unlike").status == "fail"


def test_trees_with_a_wide_volume_interval_are_named_for_information() -> None:
    trees = _row([4.0] * 10)
    assert not [c for c in run_checks({}, trees) if "wide interval" in c.name]  # no column
    flags = [""] * 10
    flags[2] = flags[7] = "sparse crown (surface fill 1.05 < 1.2): wide interval"
    check = _by_name(
        run_checks({}, trees.assign(volume_interval_flags=flags)), "volumes with a wide"
    )
    assert check.status == "info" and check.value == "2 (20 %)"
    names = list(trees["tree_id"].iloc[[2, 7]])
    assert check.note.startswith(", ".join(names))
    none = _by_name(run_checks({}, trees.assign(volume_interval_flags="")), "volumes with a wide")
    assert none.value == "0 (0 %)" and none.note == ""
    # a tree with no interval at all (NaN bounds) is named apart from the wide ones
    bounds = np.where(np.arange(10) == 7, np.nan, 1.0)
    apart = _by_name(
        run_checks({}, trees.assign(volume_interval_flags=flags, volume_low_m3=bounds)),
        "volumes with a wide",
    )
    assert apart.value == "2 (20 %)"
    assert (
        apart.note
        == f"{names[0]}: see volume_low_m3 / volume_high_m3; no interval: {names[1]} (volume_interval_flags says why)"
    )


def test_map_quality_from_the_mapping_diagnostics() -> None:
    clean = {
        "sweeps_registered": 200,
        "registrations_rejected": 1,
        "gnss": {"rejected_share": 0.01, "bias_rms_m": 0.8, "mode_changes": 0},
    }
    assert [c.status for c in map_checks(clean, ST)] == ["pass", "pass", "pass"]
    bad = {
        "sweeps_registered": 150,
        "registrations_rejected": 50,  # 25 % rejected
        "gnss": {"rejected_share": 0.6, "bias_rms_m": 4.0},
        "quality_flags": ["scan_gaps"],
    }
    checks = map_checks(bad, ST)
    assert [c.status for c in checks] == ["fail", "fail", "warn", "warn"]
    assert checks[0].value == "50 of 200 (25.0 %)"


def _aerial_table(alpha: list[float], ellipsoid: list[float]) -> tuple[dict, pd.DataFrame]:
    n = len(alpha)
    trees = _row([4.0] * n).assign(
        volume_alpha_m3=alpha,
        aerial_ellipsoid_volume_m3=ellipsoid,
        aerial_sphere_volume_m3=np.asarray(ellipsoid) * 1.5,
        aerial_flag="",
    )
    return {"aerial": {"matched_trees": n, "compared_trees": n}}, trees


def test_aerial_disagreement_against_the_ellipsoid() -> None:
    metrics, trees = _aerial_table([10.0, 20.0, 30.0], [11.0, 19.0, 33.0])
    ell = _by_name(aerial_checks(metrics, trees, ST), "alpha shape vs aerial height-aware")
    assert ell.status == "pass"
    metrics, trees = _aerial_table([10.0, 20.0, 30.0], [40.0, 80.0, 120.0])  # 75 % below
    checks = aerial_checks(metrics, trees, ST)
    assert _by_name(checks, "alpha shape vs aerial height-aware").value == "75.0 %"
    assert _by_name(checks, "alpha shape vs aerial height-aware").status == "fail"
    # The paper's sphere is biased +28..+85 % itself: information beside the ellipsoid,
    # a warning at most without it; it never fails the run.
    assert _by_name(checks, "alpha shape vs aerial paper's sphere").status == "info"
    alone = aerial_checks(metrics, trees.drop(columns="aerial_ellipsoid_volume_m3"), ST)
    assert [c.status for c in alone][-1] == "warn"


def test_an_oblique_flight_holds_the_lidar_to_its_visual_hull() -> None:
    """The flight recommends its visual hull (metrics' reference column): the hull's row can
    fail the run, the ellipsoid beside it is information, whatever its MAPE; a run whose
    reference column is missing falls back on the ellipsoid."""
    metrics, trees = _aerial_table([10.0, 20.0, 30.0], [40.0, 80.0, 120.0])  # ellipsoid 75 % off
    trees["aerial_hull_volume_m3"] = [10.5, 19.0, 31.0]  # hull within 5 %
    metrics["aerial"]["reference_column"] = "aerial_hull_volume_m3"
    checks = aerial_checks(metrics, trees, ST)
    hull = _by_name(checks, "alpha shape vs aerial visual hull")
    assert hull.status == "pass" and "recommended" in hull.note
    ell = _by_name(checks, "alpha shape vs aerial height-aware")
    assert ell.value == "75.0 %" and ell.status == "info"
    trees["aerial_hull_volume_m3"] = [40.0, 80.0, 120.0]
    assert _by_name(aerial_checks(metrics, trees, ST), "alpha shape vs aerial visual").status == (
        "fail"
    )
    fallback = aerial_checks(metrics, trees.drop(columns="aerial_hull_volume_m3"), ST)
    assert _by_name(fallback, "alpha shape vs aerial height-aware").status == "fail"


def test_few_trees_matched_to_the_drone_fails() -> None:
    metrics, trees = _aerial_table([10.0] * 10, [10.0] * 10)
    metrics["aerial"]["matched_trees"] = 8
    assert _by_name(aerial_checks(metrics, trees, ST), "LiDAR trees matched").status == "fail"


def test_checks_status_and_summary() -> None:
    checks = [
        Check("a", True, "1"),
        Check("b", False, "2"),
        Check("c", None, "3"),
        Check("d", "warn", "4"),
    ]
    assert [c.status for c in checks] == ["pass", "fail", "info", "warn"]
    assert summary(checks) == {"pass": 1, "warn": 1, "fail": 1, "info": 1}
    with pytest.raises(ValueError, match="status 'bad'"):
        Check("e", "bad", "")
    assert grade(float("nan"), 1, 2) == "info"
    assert grade(0.5, 0.95, 0.9, lower_is_worse=True) == "fail"


def test_thresholds_are_settings_and_checked() -> None:
    cfg = load_preset("pistachio", {"checks": {"aerial_mape_warn_pct": 20.0}})
    assert cfg.checks.aerial_mape_warn_pct == 20.0
    with pytest.raises(ConfigError, match=r"checks\.aerial_mape_warn_pct/aerial_mape_fail_pct"):
        load_preset("pistachio", {"checks": {"aerial_mape_warn_pct": 70.0}})
    with pytest.raises(
        ConfigError, match=r"checks\.aerial_matched_share_warn/aerial_matched_share_fail"
    ):
        ChecksConfig(aerial_matched_share_warn=0.5)


def test_the_report_headline_says_when_not_to_trust_a_run() -> None:
    from canopy_kit.report.html import render_report

    checks = [
        Check("trees segmented", True, "4", "fail < 1"),
        Check("widest crown over the row spacing", "fail", "2.50x", "warn > 1.00x, fail > 1.50x"),
        Check("GNSS bias", "warn", "4.00 m", "warn > 3.0 m, fail > 10.0 m"),
        Check("absolute position error", None, "1.2 m"),
    ]
    page = render_report("r", {}, _row([4.0]), [], checks, "")
    assert "Do not trust this run: 1 check failed" in page
    assert "widest crown over the row spacing: 2.50x (warn &gt; 1.00x, fail &gt; 1.50x)" in page
    assert "Validation checks (1 of 3 passed, 1 warned, 1 for information)" in page
    assert 'class="verdict verdict-fail"' in page
    calm = render_report("r", {}, _row([4.0]), [], checks[:1], "")
    assert "Every check passed" in calm and "verdict-pass" in calm
    amber = render_report("r", {}, _row([4.0]), [], [checks[0], checks[2]], "")
    assert "Use with care: 1 check warned, none failed" in amber


def test_layout_spacings_on_a_synthetic_orchard() -> None:
    """Rows 6 m apart with trees every 5 m: the layout measures both from the map."""
    from fixtures_sim import synthetic_orchard

    from canopy_kit.segment.layout import measure_layout
    from canopy_kit.segment.verb import segment

    orchard = synthetic_orchard(
        rows=2, trees_per_row=5, spacing=5.0, row_spacing=6.0, crown_radius=1.6
    )
    seg = segment(orchard.cloud, "adaptive")
    layout = measure_layout(orchard.cloud.xyz, seg.height, seg)
    assert layout.row_spacing_m == pytest.approx(6.0, abs=0.2)
    assert layout.tree_spacing_m == pytest.approx(5.0, abs=0.2)
    ids = np.array([t.segment_id for t in seg.trees])
    if layout.tree_spacing_source == "trunks":
        assert (layout.trunks_per_segment(ids) <= 1).all()


def test_strict_refuses_a_streamed_run_it_could_not_check(tmp_path) -> None:
    from test_cli_foundation import run_cli

    result = run_cli(
        "run", str(tmp_path / "none.bag"), "--out", str(tmp_path / "o"), "--stream", "--strict"
    )
    assert result.returncode == 2
    assert "--strict: a --stream run has no checks" in result.stderr + result.stdout
    assert "Traceback" not in result.stderr


def test_run_help_documents_the_strict_exit_code() -> None:
    from test_cli_foundation import run_cli

    result = run_cli("run", "--help")
    assert "--strict" in result.stdout and "4 with --strict" in " ".join(result.stdout.split())


def test_interval_check_counts_the_trees_whose_interval_holds_their_measurand() -> None:
    """Four matched trees, one outside its interval (cut at IoU 0.7), one unmatched: 3/4 held,
    a warning (the families hold ≥ 90 %) naming the miss's IoU; all held: a pass."""
    from canopy_kit.evaluate.validation import interval_holds
    from canopy_kit.results.checks import interval_check

    trees = pd.DataFrame(
        {
            "volume_low_m3": [9.0, 18.0, 27.0, 36.0, 5.0],
            "volume_high_m3": [11.0, 22.0, 33.0, 44.0, 6.0],
            "truth_iou": [0.95, 0.97, 0.70, 0.96, np.nan],
        }
    )
    measurand = pd.Series([10.0, 21.9, 40.0, 36.0, np.nan])
    held = interval_holds(trees, measurand)
    assert held == {"held": 3, "n": 4, "missed_iou": [0.7], "no_interval": 0}
    check = interval_check("foliage_envelope", held)
    assert check.status == "warn" and check.value == "3/4 (75 %)"
    assert "1 missed, its IoU with the true tree 0.70 " in check.note
    two = interval_check("foliage_envelope", {"held": 2, "n": 4, "missed_iou": [0.7, 0.55]})
    assert "2 missed, their IoU with the true tree 0.55-0.70" in two.note
    measurand[2] = 30.0
    assert interval_check("foliage_envelope", interval_holds(trees, measurand)).status == "pass"
    assert interval_holds(trees.drop(columns="volume_low_m3"), measurand) is None
    # trees that claim no interval (a wall row whose trunks were missed) are not counted, and
    # said; with none left the check only informs
    withdrawn = trees.assign(volume_low_m3=[9.0, np.nan, 27.0, 36.0, 5.0])
    part = interval_holds(withdrawn, measurand)
    assert part["n"] == 3 and part["no_interval"] == 1
    assert "1 tree claims no interval, not counted" in interval_check("x", part).note
    empty = interval_holds(trees.assign(volume_low_m3=np.nan), measurand)
    assert empty["n"] == 0 and empty["no_interval"] == 4
    info = interval_check("x", empty)
    assert info.status == "info" and info.value == "0/0"


def test_crowns_at_the_maps_edge_warn_and_many_fail() -> None:
    trees = _row([4.0] * 8)
    (none,) = map_edge_check(trees, {"trees_at_map_edge": []}, ST)
    assert none.status == "pass" and none.value == "0 (0 %)"
    (one,) = map_edge_check(trees, {"trees_at_map_edge": ["r0-L7"]}, ST)
    assert one.status == "warn" and "r0-L7" in one.note
    edge = [f"r0-L{i}" for i in (0, 1, 6, 7)]
    assert map_edge_check(trees, {"trees_at_map_edge": edge}, ST)[0].status == "fail"
    assert map_edge_check(trees, {}, ST) == []  # a run from before the outline was measured


def test_a_warning_a_check_carries_is_listed_once_and_not_repeated_as_a_check() -> None:
    """The run keeps every warning in metrics["warnings"] (the CLI prints them); the ones a
    check of their own carries (the canopy ceiling's, the trunk feet's: the segmentation
    names them) get no second "warning" check, any other warning does."""
    from canopy_kit.segment.result import Segmentation

    ceiling = "2 tree(s) reach preprocess.max_canopy_height (3.5 m): r0-L0, r0-L1"
    feet = "row r0: 13 points per metre at the stem band's foot"
    seg = Segmentation.__new__(Segmentation)
    seg.ceiling_warning, seg.trunk_feet = ceiling, {"warning": feet}
    assert seg.carried_warnings() == [ceiling, feet]
    seg.ceiling_warning, seg.trunk_feet = "", {}
    assert seg.carried_warnings() == []
    other = "odometry: 3 sweeps skipped"
    metrics = {
        "segmentation": {"carried_warnings": [ceiling, feet]},
        "warnings": [other, ceiling, feet],
    }
    warned = [c.note for c in run_checks(metrics, _row([4.0] * 4)) if c.name == "warning"]
    assert warned == [other]
    # metrics.json of a run from before the list: the trunk feet's warning still carried
    old = {"segmentation": {"trunk_feet": {"warning": feet}}, "warnings": [feet, other]}
    assert [c.note for c in run_checks(old, _row([4.0] * 4)) if c.name == "warning"] == [other]
