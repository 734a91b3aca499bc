"""End to end: simulate → run → evaluate, with outputs, caching and determinism."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from canopy_kit.config import load_preset
from canopy_kit.pipeline import run


@pytest.fixture(scope="module")
def pistachio_run(tiny_pistachio_run):
    return tiny_pistachio_run


@pytest.mark.slow
def test_end_to_end_against_truth(pistachio_run, tiny_pistachio):
    r = pistachio_run
    truth = pd.read_csv(tiny_pistachio.truth_dir / "trees.csv")
    ev = r.metrics["evaluation"]
    assert ev["segmentation"]["n_truth"] == len(truth)
    assert ev["segmentation"]["success_rate"] == 1.0
    assert ev["segmentation"]["label_accuracy"] == 1.0
    assert ev["mapping"]["ate_rmse_m"] < 0.20
    assert ev["mapping"]["drift_percent"] < 0.5
    # Volumes against the exact crown envelopes (both sides of each tree are scanned).
    assert ev["volumes"]["convex_hull"]["mape_pct"] < 10.0
    assert ev["volumes"]["alpha_shape"]["mape_pct"] < 10.0
    trees = r.trees
    assert list(trees.columns[:12]) == [
        "tree_id",
        "label",
        "row",
        "x",
        "y",
        "lat",
        "lon",
        "n_points",
        "height_m",
        "crown_diameter_m",
        "volume_convex_hull_m3",
        "volume_alpha_m3",
    ]
    # Positions in WGS84 agree with the truth's (same tree matched by segmentation).
    m = trees.dropna(subset=["truth_tree_id"]).merge(
        truth, left_on="truth_tree_id", right_on="tree_id", suffixes=("", "_true")
    )
    assert np.allclose(m["lat"], m["lat_true"], atol=2e-5)  # ~2 m: GNSS-level
    assert (m["label"] == m["label_true"]).all()
    # Every tree segmented one-to-one: no crown is flagged as a merge or a fragment.
    assert (trees["segment_flags"] == "").all() and r.metrics["flagged_segments"] == 0


@pytest.mark.slow
def test_a_run_folder_can_be_scored_by_evaluate(pistachio_run, tiny_pistachio):
    """`canopy-kit evaluate RUN --truth SIM` (the README's usage) on a `run` folder gives the
    scores the run itself recorded; by crown footprints too."""
    from canopy_kit.evaluate.segmentation_score import evaluate_run

    recorded = pistachio_run.metrics["evaluation"]["segmentation"]
    points = evaluate_run(pistachio_run.out_dir, tiny_pistachio.root).to_dict()
    for key in ("n_truth", "n_predicted", "n_correct", "n_label_correct", "mode"):
        assert points[key] == recorded[key], key
    footprints = evaluate_run(
        pistachio_run.out_dir, tiny_pistachio.root, mode="footprints"
    ).to_dict()
    assert footprints["n_truth"] == recorded["n_truth"]
    assert footprints["n_correct"] == recorded["n_truth"]  # every pistachio crown stands apart


@pytest.mark.slow
def test_outputs_are_complete_and_readable(pistachio_run):
    from canopy_kit.io.las import read_las

    out = pistachio_run.out_dir
    for name in (
        "trees.csv",
        "trees.parquet",
        "trees.geojson",
        "map.laz",
        "trajectory.csv",
        "config.toml",
        "metrics.json",
        "report.html",
    ):
        assert (out / name).stat().st_size > 0, name
    assert not list(out.glob(".*.tmp*"))  # no temporary files left behind
    csv = pd.read_csv(out / "trees.csv")
    parquet = pd.read_parquet(out / "trees.parquet")
    assert len(csv) == len(parquet) == len(pistachio_run.trees)
    geo = json.loads((out / "trees.geojson").read_text())
    assert len(geo["features"]) == len(csv)
    cloud = read_las(out / "map.laz")
    assert "segment_id" in cloud.fields and cloud.crs.startswith("EPSG:")
    assert set(np.unique(cloud.fields["segment_id"])) - {-1} == set(csv["segment"])
    assert load_preset(out / "config.toml").segment.method == "adaptive"


@pytest.mark.slow
def test_rerun_reuses_unchanged_stages_and_is_deterministic(
    pistachio_run, tiny_pistachio, tmp_path
):
    import shutil

    # A copy: the shared run's folder (its cache, its outputs) is read by other files' tests.
    out = shutil.copytree(pistachio_run.out_dir, tmp_path / "run")
    cfg = load_preset("adaptive", {"volume": {"params": {"alpha_shape": {"alpha": 1.5}}}})
    again = run(cfg, tiny_pistachio.bag, out, truth=tiny_pistachio.root)
    assert set(again.cache_hits) == {"map", "segment"}
    assert not np.allclose(again.trees["volume_alpha_m3"], pistachio_run.trees["volume_alpha_m3"])
    same = run(
        load_preset("adaptive"), tiny_pistachio.bag, out, truth=tiny_pistachio.root, use_cache=False
    )
    pd.testing.assert_frame_equal(same.trees, pistachio_run.trees)


@pytest.mark.slow
@pytest.mark.browser
def test_report_shows_the_run_offline(pistachio_run):
    from conftest import REPO

    from canopy_kit.report.browser import render_page

    page = render_page(
        pistachio_run.files["report.html"],
        screenshot=REPO / "test-artifacts" / "pipeline_report.png",
    )
    assert page.tree_rows == len(pistachio_run.trees)
    assert page.images_loaded >= 3 and page.images_broken == 0
    assert page.check_rows >= 6
    assert page.blocked_requests == [] and page.console_errors == []


def test_a_failing_map_writer_leaves_no_report_and_names_the_error(
    tiny_pistachio, tiny_pistachio_run, tmp_path, monkeypatch
) -> None:
    """map.laz is written on a thread beside the report: when it fails the run raises that
    error, and neither metrics.json nor report.html (written last) claims a finished run."""
    import shutil

    import canopy_kit.io.las as las
    from canopy_kit.errors import InputError

    out = tmp_path / "run"
    shutil.copytree(
        tiny_pistachio_run.out_dir / ".cache", out / ".cache"
    )  # straight to the outputs

    def broken(path, cloud):
        raise InputError(f"{path}: disk full (simulated)")

    monkeypatch.setattr(las, "write_las", broken)
    with pytest.raises(InputError, match=r"map\.laz: disk full \(simulated\)"):
        run(load_preset("adaptive"), tiny_pistachio.bag, out, truth=tiny_pistachio.root)
    written = {p.name for p in out.iterdir() if not p.name.startswith(".")}
    assert "trees.csv" in written and "map.laz" not in written
    assert not {"metrics.json", "report.html"} & written
