"""Touching almond crowns from the photos alone, end to end through the CLI, against the
simulator's truth: a 2 × 5 almond flight (crowns 5-7 m wide on 3.5-6 m spacing, so
neighbours overlap), processed by ``canopy-kit ground-truth`` without ``--seeds``."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from fixtures_aerial import processed_simulated_flight

from canopy_kit.sim.truth import crown_row_extents
from ground_truth.flight_accuracy import crown_agreement

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def hedgerow_flight(tmp_path_factory):
    """(simulated session, output folder, CLI stdout) of a 2 × 5 almond flight, seed 61."""
    return processed_simulated_flight(
        tmp_path_factory.mktemp("hedgerow_flight"),
        "almond",
        {"seed": 61, "orchard": {"rows": 2, "trees_per_row": 5}},
        seeded=False,
    )


def test_touching_crowns_found_from_the_photos_alone(hedgerow_flight):
    sim, out, stdout = hedgerow_flight
    report = json.loads((out / "report.json").read_text())
    assert report["crown_seeding"] == "rows"
    assert report["crown_rows"]["rows"] == 2 and "seeded along 2 rows" in stdout
    truth = pd.read_csv(sim / "truth" / "trees.csv").merge(crown_row_extents(sim), on="tree_id")
    crowns = pd.read_csv(out / "crowns.csv")
    assert (crowns["seed_id"] == -1).all()  # nothing but the photos placed them
    table, m = crown_agreement(crowns, truth)
    # measured 9 of 10 trees and one extra crown (CHM maxima: 4 of 10, 3 extra)
    assert m["matched"] >= 0.9 * m["trees"] and m["unmatched_crowns"] <= 1, table
    # The across-row extent is not hidden by the neighbours: within a few decimetres.
    assert m["across_row_mae_m"] <= 0.45, table  # measured 0.36 m (bias +0.32 m)


def test_rows_beat_chm_maxima_on_the_same_rasters(hedgerow_flight):
    """The imagery-only mode before the rows (one crown per CHM maximum), on the same
    orthomosaic and CHM: fewer trees get a crown of their own."""
    from ground_truth.crowns import CrownOptions, delineate_crowns, measure_crowns
    from ground_truth.pipeline import load_result
    from ground_truth.raster import sample_bilinear

    sim, out, _ = hedgerow_flight
    result = load_result(out)
    ox, oy = result.ortho.grid.centers()
    chm = sample_bilinear(result.surface.grid, result.surface.chm, ox, oy)
    truth = pd.read_csv(sim / "truth" / "trees.csv")
    found = {}
    for mode in ("rows", "chm_maxima"):
        seg = delineate_crowns(
            result.ortho.rgb,
            result.ortho.valid,
            chm,
            result.ortho.grid,
            options=CrownOptions(unseeded=mode),
        )
        found[mode] = crown_agreement(measure_crowns(seg, chm), truth)[1]["matched"]
    assert found["rows"] > found["chm_maxima"], found


def test_no_correctly_delineated_crown_is_flagged(hedgerow_flight):
    """``crown_flag`` (from the imagery alone) leaves every crown that holds exactly one true
    crown centre and is one-to-one with that tree unflagged, and the CLI and report count it."""
    from ground_truth.crown_flags import FLAG_COLUMN
    from ground_truth.flight_accuracy import trees_per_crown
    from ground_truth.pipeline import load_result

    sim, out, stdout = hedgerow_flight
    result = load_result(out)
    report = result.report
    crowns = result.crowns
    flags = crowns[FLAG_COLUMN].fillna("").astype(str)
    counts = report["crown_flags"]
    assert counts["merged"] == int((flags == "merged").sum())
    assert counts["fragment"] == int((flags == "fragment").sum())
    assert counts["tree_spacing_source"].startswith("crown_rows")
    assert ("crowns flagged" in stdout) == bool(counts["merged"] + counts["fragment"])
    truth = pd.read_csv(sim / "truth" / "trees.csv")
    inside = trees_per_crown(result.segmentation.labels, result.segmentation.grid, crowns, truth)
    table, _ = crown_agreement(crowns, truth)
    one_to_one = crowns["crown_id"].isin(table["crown_id"]).to_numpy()
    correct = (inside == 1) & one_to_one & ~crowns["touches_border"].to_numpy(bool)
    assert correct.sum() >= 8, (inside, table)
    assert (flags[correct] == "").all(), crowns.loc[correct, ["crown_id", "area_m2", FLAG_COLUMN]]
