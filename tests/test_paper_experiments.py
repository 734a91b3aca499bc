"""The paper's experiments on a tiny simulated configuration: structure, provenance of every
number (the runs, the truth folder, the paper), files, resume and the CLI."""

from __future__ import annotations

import inspect
import json
import math

import numpy as np
import pandas as pd
import pytest

from canopy_kit.cli import paper as paper_cli
from canopy_kit.config import load_preset
from canopy_kit.errors import InputError
from canopy_kit.paper import experiments as ex

# One seed, one row of three trees per orchard, a sparse 16 x 256 sensor; the map from the
# true poses keeps odometry out of the test's time (the pipeline mapping is tested below).
TINY = ex.ExperimentConfig(
    seeds=(1,),
    rows=1,
    trees_per_row=3,
    methods=("dbscan", "dbscan_spectral"),
    mappings=("true_poses",),
    sim_overrides={"lidar": {"columns": 256, "rings": 16}},
)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    work = tmp_path_factory.mktemp("experiments")
    calls: list[tuple[str, float, float]] = []
    results = ex.run_experiments(
        TINY, work, progress=lambda *a: calls.append(a), keep_sessions=True
    )
    return results, work, calls


def test_one_run_per_orchard_seed_mapping_method(tiny):
    results, _, calls = tiny
    runs, comp = results.runs, results.comparison
    assert len(runs) == TINY.n_runs() == 4
    assert set(zip(runs["orchard"], runs["method"])) == {
        (o, m) for o in ("pistachio", "almond") for m in ("dbscan", "dbscan_spectral")
    }
    assert (runs["error"] == "").all() and (runs["mapping"] == "true_poses").all()
    assert list(runs["preset"]) == [ex.METHOD_PRESETS[m] for m in runs["method"]]
    assert len(comp) == 4 and (comp["sessions"] == 1).all()
    assert ("experiment runs", 4, 4) in calls
    # Every segment of every run is in the tree table, tagged with its run.
    assert set(results.trees.groupby(["orchard", "method"]).size().index) == set(
        zip(runs["orchard"], runs["method"])
    )


def test_segmentation_numbers_are_those_of_the_runs(tiny):
    results, work, _ = tiny
    runs, comp, trees = results.runs, results.comparison, results.trees
    for r in runs.to_dict("records"):
        truth = pd.read_csv(work / r["session"] / "truth" / "trees.csv")
        assert r["n_truth"] == len(truth)
        matched = trees[
            (trees["orchard"] == r["orchard"])
            & (trees["method"] == r["method"])
            & trees["truth_tree_id"].notna()
        ]
        assert len(matched) == r["n_correct"]  # volumes are only scored on correct trees
        assert r["success_rate"] == pytest.approx(r["n_correct"] / r["n_truth"])
        c = comp[(comp["orchard"] == r["orchard"]) & (comp["method"] == r["method"])].iloc[0]
        assert c["success_pct"] == pytest.approx(100 * r["success_rate"])
        assert c["success_min_pct"] == c["success_max_pct"] == pytest.approx(c["success_pct"])


def test_segmentation_rescored_independently(tiny):
    """Segment the kept session again with the almond preset and score it by hand."""
    from canopy_kit.config import load_preset
    from canopy_kit.evaluate.segmentation_score import score_point_labels
    from canopy_kit.evaluate.truth_map import truth_mapping
    from canopy_kit.pipeline import driving_direction
    from canopy_kit.segment.verb import make_segmenter, segment

    results, work, _ = tiny
    run = results.runs.query("orchard == 'almond' and method == 'dbscan_spectral'").iloc[0]
    mapping = truth_mapping(work / run["session"])
    cfg = load_preset("almond")
    seg = segment(
        mapping.map,
        make_segmenter(cfg.segment.method, cfg.segment.params),
        cfg.preprocess,
        cfg.rows,
        driving_direction=driving_direction(mapping.trajectory),
        direction_source="trajectory",
        seed=cfg.seed,
    )
    score = score_point_labels(seg.labels, mapping.map.fields["tree_id"])
    assert (score.n_correct, score.n_truth) == (run["n_correct"], run["n_truth"])


def test_volume_errors_against_the_truth_folder(tiny):
    results, work, _ = tiny
    trees = results.trees.dropna(subset=["truth_tree_id"])
    assert len(trees) > 0
    for (orchard, method), group in trees.groupby(["orchard", "method"]):  # noqa: B007 (query)
        session = results.runs.query("orchard == @orchard and method == @method")["session"].iloc[0]
        truth = pd.read_csv(work / session / "truth" / "trees.csv").set_index("tree_id")
        t = truth.loc[group["truth_tree_id"].astype(int)]
        # The aerial sphere ground truth is pi d^3 / 6 of the widest true crown diameter.
        assert np.allclose(group["true_sphere_volume_m3"], np.pi * t["crown_diameter_m"] ** 3 / 6)
        assert np.allclose(group["true_crown_volume_m3"], t["crown_volume_m3"])
        c = results.comparison.query("orchard == @orchard and method == @method").iloc[0]
        for est, col in (
            ("convex_hull", "volume_convex_hull_m3"),
            ("alpha_shape", "volume_alpha_m3"),
        ):
            for ref, ref_col in (
                ("sphere", "true_sphere_volume_m3"),
                ("crown", "true_crown_volume_m3"),
            ):
                err = 100 * (group[col] - group[ref_col]) / group[ref_col]
                assert c[f"{est}_mape_vs_{ref}_pct"] == pytest.approx(err.abs().mean())
                assert c[f"{est}_bias_vs_{ref}_pct"] == pytest.approx(err.mean())
        assert c["n_trees_vs_sphere"] == len(group)


def test_paper_column_holds_the_printed_figures(tiny):
    from canopy_kit.paper import check_table1

    comp = tiny[0].comparison.set_index(["orchard", "method"])
    assert comp.loc[("pistachio", "dbscan"), "paper_success_pct"] == 93
    assert comp.loc[("almond", "dbscan"), "paper_success_pct"] == 46
    assert comp.loc[("almond", "dbscan_spectral"), "paper_success_pct"] == 80
    assert math.isnan(comp.loc[("pistachio", "dbscan_spectral"), "paper_success_pct"])
    # Volume figures exist only for the paper's pistachio DBSCAN run: Table I, corrected.
    table = check_table1().corrected
    row = comp.loc[("pistachio", "dbscan")]
    assert row["paper_alpha_shape_mape_vs_sphere_pct"] == pytest.approx(
        table["alpha_err_pct"].mean(), abs=0.01
    )  # 8.54
    assert row["paper_convex_hull_mape_vs_sphere_pct"] == pytest.approx(
        table["hull_err_pct"].mean(), abs=0.01
    )  # 10.68
    assert row["paper_alpha_shape_max_error_vs_sphere_pct"] == 22.91
    assert row["paper_alpha_better"] == "12/17"
    assert comp.drop(("pistachio", "dbscan"))["paper_alpha_shape_mape_vs_sphere_pct"].isna().all()


def test_results_files_round_trip_and_cli_shows_them(tiny, tmp_path):
    from typer.testing import CliRunner

    from canopy_kit.cli import app

    results = tiny[0]
    files = ex.write_results(results, tmp_path)
    assert set(files) == {"runs", "trees", "comparison", "summary"}
    back = ex.load_results(tmp_path)
    assert back.config == results.config
    pd.testing.assert_frame_equal(back.comparison, results.comparison, check_dtype=False)
    out = CliRunner().invoke(
        app, ["paper", "experiments", "--show-saved", "--out", str(tmp_path), "--json"]
    )
    assert out.exit_code == 0, out.output
    data = json.loads(out.output)
    assert len(data["comparison"]) == 4 and data["paper"]["n_trees"] == 17
    text = CliRunner().invoke(
        app,
        ["paper", "experiments", "--show-saved", "--out", str(tmp_path)],
        env={"COLUMNS": "250"},
    )
    assert text.exit_code == 0 and "Segmentation success" in text.output


def test_rerun_in_the_same_work_folder_resumes(tiny, monkeypatch):
    results, work, _ = tiny

    def no_simulation(*_a, **_k):
        raise AssertionError("a finished session was simulated again")

    monkeypatch.setattr(ex, "simulate", no_simulation)
    again = ex.run_experiments(TINY, work, keep_sessions=True)
    pd.testing.assert_frame_equal(again.comparison, results.comparison, check_dtype=False)


def test_settings_are_checked():
    with pytest.raises(InputError, match="unknown method 'kmeans'"):
        ex.ExperimentConfig(methods=("kmeans",)).validate()
    with pytest.raises(InputError, match="seeds repeat"):
        ex.ExperimentConfig(seeds=(1, 1)).validate()
    ex.ExperimentConfig(orchards=("almond-paper",)).validate()
    # the scaled almond method on request, through a preset that sets it up
    ex.ExperimentConfig(methods=("dbscan_spectral_scaled",)).validate()
    assert load_preset(ex.METHOD_PRESETS["dbscan_spectral_scaled"]).segment.params["graph_cell"] > 0
    assert "dbscan_spectral_scaled" not in ex.ExperimentConfig().methods
    # the CLI (which keeps pandas out of its start-up) offers the same default methods
    cli_default = inspect.signature(paper_cli.experiments).parameters["method"].default
    assert tuple(cli_default.default) == ex.DEFAULT_METHODS
    with pytest.raises(InputError, match="unknown orchard 'walnut'"):
        ex.ExperimentConfig(orchards=("walnut",)).validate()
    with pytest.raises(InputError, match="no experiment results"):
        ex.load_results("/nonexistent/folder")


@pytest.mark.slow
def test_pipeline_mapping_run(tmp_path):
    """The main table's path: the pipeline's own mapping (compute), scored with its ATE."""
    config = ex.ExperimentConfig(
        seeds=(2,),
        rows=1,
        trees_per_row=3,
        orchards=("pistachio",),
        methods=("dbscan",),
        sim_overrides=TINY.sim_overrides,
    )
    results = ex.run_experiments(config, tmp_path)
    run = results.runs.iloc[0]
    assert run["error"] == "" and run["mapping"] == "pipeline"
    assert np.isfinite(run["ate_rmse_m"]) and run["map_points_per_tree_median"] > 0
    matched = results.trees.dropna(subset=["truth_tree_id"])
    assert len(matched) == run["n_correct"]
    assert results.comparison.iloc[0]["success_pct"] == pytest.approx(100 * run["success_rate"])
    assert not (tmp_path / run["session"]).exists()  # simulated session deleted after use


def test_a_complete_session_is_reused(tiny, monkeypatch):
    import canopy_kit.sim

    results, work, _ = tiny
    run = results.runs.iloc[0]

    def no_simulation(*_a, **_k):
        raise AssertionError("a complete session with the same config was simulated again")

    monkeypatch.setattr(canopy_kit.sim, "simulate_session", no_simulation)
    bag = ex.simulate(run["orchard"], int(run["seed"]), TINY, work / run["session"])
    assert bag.exists() and bag.parent == work / run["session"]


def test_saved_only_collects_finished_sessions_and_runs_nothing(tiny, monkeypatch, tmp_path):
    """Several processes can share a work folder; --saved-only gathers what they finished."""
    from dataclasses import replace

    from typer.testing import CliRunner

    from canopy_kit.cli import app

    results, work, _ = tiny

    def no_simulation(*_a, **_k):
        raise AssertionError("--saved-only simulated a session")

    monkeypatch.setattr(ex, "simulate", no_simulation)
    # Seed 2 never ran in this folder: left out, not simulated.
    wider = replace(TINY, seeds=(1, 2))
    got = ex.run_experiments(wider, work, keep_sessions=True, saved_only=True)
    assert set(got.runs["seed"]) == {1} and len(got.runs) == len(results.runs)
    pd.testing.assert_frame_equal(got.comparison, results.comparison, check_dtype=False)
    with pytest.raises(InputError, match="no finished sessions"):
        ex.run_experiments(replace(TINY, seeds=(2,)), work, saved_only=True)
    no_work = CliRunner().invoke(app, ["paper", "experiments", "--saved-only"])
    assert isinstance(no_work.exception, InputError)  # main() turns it into exit code 2
    assert "--saved-only needs --work" in str(no_work.exception)


def test_defaults_are_the_settings_of_the_committed_results():
    """`canopy-kit paper experiments` with no option redoes what data/paper holds."""
    committed = json.loads((ex.default_results_dir() / "experiments.json").read_text())
    cfg = {k: tuple(v) if isinstance(v, list) else v for k, v in committed["config"].items()}
    assert ex.ExperimentConfig(**cfg) == ex.ExperimentConfig()
    params = inspect.signature(paper_cli.experiments).parameters
    first, n = params["first_seed"].default.default, params["seeds"].default.default
    assert tuple(range(first, first + n)) == ex.ExperimentConfig().seeds
    assert params["rows"].default.default == ex.ExperimentConfig().rows
    assert params["trees_per_row"].default.default == ex.ExperimentConfig().trees_per_row
    assert tuple(params["orchard"].default.default) == ex.ExperimentConfig().orchards


def test_committed_results_are_never_overwritten_by_default(tiny, tmp_path):
    from datetime import UTC, datetime

    results = tiny[0]
    committed = ex.default_results_dir() / "experiments.json"
    before = committed.read_bytes()
    with pytest.raises(InputError, match="refusing to write into the committed data folder"):
        ex.write_results(results, ex.default_results_dir())
    with pytest.raises(InputError, match=str(ex.default_results_dir())):
        ex.check_results_dir(ex.default_results_dir() / "sub")
    assert committed.read_bytes() == before
    assert (
        ex.check_results_dir(ex.default_results_dir(), overwrite=True) == ex.default_results_dir()
    )
    # A folder holding results is refused too, unless asked.
    ex.write_results(results, tmp_path)
    with pytest.raises(InputError, match="already holds experiment results"):
        ex.write_results(results, tmp_path)
    assert set(ex.write_results(results, tmp_path, overwrite=True)) == set(ex.RESULT_FILES)
    when = datetime(2026, 12, 2, 7, 5, 9, tzinfo=UTC)
    assert ex.new_results_dir("out", when) == ex.Path("out/paper-20261202-070509")


def test_cli_refuses_committed_data_before_running(monkeypatch):
    from typer.testing import CliRunner

    from canopy_kit.cli import app

    def no_run(*_a, **_k):
        raise AssertionError("ran experiments before checking --out")

    monkeypatch.setattr(ex, "run_experiments", no_run)
    got = CliRunner().invoke(app, ["paper", "experiments", "--out", str(ex.default_results_dir())])
    assert isinstance(got.exception, InputError)
    assert str(ex.default_results_dir()) in str(got.exception)


def test_committed_results_are_complete_and_their_tables_recompute():
    """data/paper/experiments*: every run of the recorded settings, none failed, the same true
    trees for every method of a session, and the comparison table recomputed by hand from the
    runs and the per-segment volumes (the CSVs agree with experiments.json)."""
    saved = ex.load_results()
    runs, trees, comp = saved.runs, saved.trees, saved.comparison
    out = ex.default_results_dir()
    assert len(runs) == saved.config.n_runs() and (runs["error"].fillna("") == "").all()
    assert set(zip(runs["orchard"], runs["seed"], runs["method"])) == {
        (o, s, m)
        for o in saved.config.orchards
        for s in saved.config.seeds
        for m in saved.config.methods
    }
    assert (runs.groupby(["orchard", "seed"])["n_truth"].nunique() == 1).all()
    comp_csv = pd.read_csv(out / ex.RESULT_FILES["comparison"])
    for col in [c for c in comp if comp[c].map(lambda v: isinstance(v, str)).any()]:
        # an empty text cell reads back as NaN
        comp_csv[col] = comp_csv[col].fillna("")
    pd.testing.assert_frame_equal(comp_csv, comp, check_dtype=False, atol=1e-4)
    runs_csv = pd.read_csv(out / ex.RESULT_FILES["runs"], keep_default_na=False)
    numeric = runs.select_dtypes("number").columns
    pd.testing.assert_frame_equal(
        runs_csv[numeric].astype(float), runs[numeric].astype(float), atol=1e-4
    )
    matched = trees.dropna(subset=["truth_tree_id"])
    # A true tree's crown and sphere are the same in every run of its session.
    per_tree = matched.groupby(["orchard", "seed", "truth_tree_id"])
    assert (per_tree[["true_crown_volume_m3", "true_sphere_volume_m3"]].nunique() == 1).all().all()
    for r in runs.to_dict("records"):
        got = matched[
            (matched["orchard"] == r["orchard"])
            & (matched["seed"] == r["seed"])
            & (matched["method"] == r["method"])
        ]
        assert len(got) == r["n_correct"] and got["truth_tree_id"].is_unique
    for c in comp.to_dict("records"):
        r = runs[(runs["orchard"] == c["orchard"]) & (runs["method"] == c["method"])]
        assert (c["n_truth"], c["n_correct"]) == (r["n_truth"].sum(), r["n_correct"].sum())
        assert c["success_pct"] == pytest.approx(100 * c["n_correct"] / c["n_truth"])
        assert c["success_min_pct"] == pytest.approx(100 * r["success_rate"].min(), abs=1e-3)
        assert c["success_max_pct"] == pytest.approx(100 * r["success_rate"].max(), abs=1e-3)
        for k in ("n_merged", "n_split", "n_missed", "n_other"):
            assert c[k] == r[k].sum()
        assert c["map_points_per_tree_median"] == r["map_points_per_tree_median"].median()
        t = matched[(matched["orchard"] == c["orchard"]) & (matched["method"] == c["method"])]
        errs = {}
        for ref, ref_col in (
            ("sphere", "true_sphere_volume_m3"),
            ("crown", "true_crown_volume_m3"),
        ):
            for est, col in (
                ("convex_hull", "volume_convex_hull_m3"),
                ("alpha_shape", "volume_alpha_m3"),
            ):
                errs[est] = err = 100 * (t[col] - t[ref_col]) / t[ref_col]
                assert c[f"{est}_mape_vs_{ref}_pct"] == pytest.approx(err.abs().mean(), abs=1e-3)
                assert c[f"{est}_bias_vs_{ref}_pct"] == pytest.approx(err.mean(), abs=1e-3)
                assert c[f"{est}_max_error_vs_{ref}_pct"] == pytest.approx(
                    err.abs().max(), abs=1e-3
                )
            assert (
                c[f"alpha_better_vs_{ref}"]
                == (errs["alpha_shape"].abs() < errs["convex_hull"].abs()).sum()
            )
            assert c[f"n_trees_vs_{ref}"] == len(t)


def test_reproduction_doc_quotes_the_committed_tables():
    """docs/REPRODUCTION.md's result tables are those of data/paper/experiments_comparison.csv."""
    doc = (ex.default_results_dir().parents[1] / "docs" / "REPRODUCTION.md").read_text()
    results = doc[doc.index("### Results") : doc.index("**On an almond orchard like the paper's**")]
    rows = {}
    for line in results.splitlines():
        cells = [x.strip() for x in line.strip().strip("|").split("|")]
        if len(cells) > 2 and cells[0] in ex.ORCHARDS and not cells[1].startswith("**"):
            rows.setdefault((cells[0], cells[1].split(" (")[0]), []).append(cells)
    comp = pd.read_csv(ex.default_results_dir() / ex.RESULT_FILES["comparison"])
    assert len(rows) == len(comp)
    for c in comp.to_dict("records"):
        seg, vol = rows[(c["orchard"], c["method"])]
        paper = c["paper_success_pct"]
        assert seg[2] == ("-" if math.isnan(paper) else f"{paper:.0f}")
        assert seg[3] == f"{c['success_pct']:.1f}"
        assert seg[4] == f"{c['success_min_pct']:.0f}-{c['success_max_pct']:.0f}"
        assert seg[5:11] == [
            f"{c['n_correct']}/{c['n_truth']}",
            str(c["n_merged"]),
            str(c["n_split"]),
            str(c["n_missed"]),
            str(c["n_other"]),
            f"{c['map_points_per_tree_median']:.0f}",
        ]

        def mape_bias(est, ref, c=c):
            return f"{c[f'{est}_mape_vs_{ref}_pct']:.1f} ({c[f'{est}_bias_vs_{ref}_pct']:+.1f})"

        assert vol[2:] == [
            str(c["n_trees_vs_sphere"]),
            mape_bias("convex_hull", "sphere"),
            mape_bias("alpha_shape", "sphere"),
            f"{c['alpha_shape_max_error_vs_sphere_pct']:.1f}",
            f"{c['alpha_better_vs_sphere']}/{c['n_trees_vs_sphere']}",
            mape_bias("convex_hull", "crown"),
            mape_bias("alpha_shape", "crown"),
            f"{c['alpha_better_vs_crown']}/{c['n_trees_vs_crown']}",
        ]
