"""The volume accuracy matrix: the shipped table the report quotes, the report's statement,
and the recommended estimator on trees the pipeline segments, per crown form (issue 25)."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

from canopy_kit.volume.accuracy import accuracy_table

MATRIX_METHODS = ["convex_hull", "alpha_shape", "adaptive_alpha"]  # the matrix of accuracy.csv


def test_the_shipped_table_covers_every_form_scan_and_estimator() -> None:
    from canopy_kit.sim.crown_forms import FORM_NAMES

    table = accuracy_table()
    for form in ("all", "dense", *FORM_NAMES):
        for scan in ("both", "one-sided"):
            for method in MATRIX_METHODS:
                hit = table[(table.form == form) & (table.scan == scan) & (table.method == method)]
                assert len(hit) == 1, (form, scan, method)
                r = hit.iloc[0]
                assert r.n > 0 and 0 <= r.mape <= r.p90 + 1e-9 and abs(r.bias) <= r.mape + 1e-9
    # per form rows add up to the overall row: the same trees, split by form
    both = table[(table.scan == "both") & (table.method == "adaptive_alpha")].set_index("form")
    assert both.loc[list(FORM_NAMES), "n"].sum() == both.loc["all", "n"]
    weighted = (both.loc[list(FORM_NAMES), "bias"] * both.loc[list(FORM_NAMES), "n"]).sum()
    assert weighted / both.loc["all", "n"] == pytest.approx(both.loc["all", "bias"], abs=1e-3)


def test_the_accuracy_figure_draws_the_table() -> None:
    """Every bar of the notebook's figure is a form's signed bias from the shipped table."""
    import matplotlib

    matplotlib.use("Agg")
    from canopy_kit.report.plots import plot_accuracy_matrix
    from canopy_kit.sim.crown_forms import FORM_NAMES

    table = accuracy_table()
    fig = plot_accuracy_matrix(table)
    panels = fig.axes
    assert [ax.get_title() for ax in panels] == ["scan: both", "scan: one-sided"]
    for ax, scan in zip(panels, ("both", "one-sided"), strict=True):
        assert [t.get_text() for t in ax.get_xticklabels()] == list(FORM_NAMES)
        rows = table[table.scan == scan].set_index(["form", "method"])
        for container, method in zip(ax.containers, MATRIX_METHODS, strict=True):
            heights = [bar.get_height() for bar in container.patches]
            expected = [100 * rows.loc[(form, method), "bias"] for form in FORM_NAMES]
            assert heights == pytest.approx(expected)


def test_the_statement_quotes_the_family_table() -> None:
    from canopy_kit.report.volumes import accuracy_section, estimator_text, pooled
    from canopy_kit.volume.accuracy import family_accuracy_table

    table = family_accuracy_table()
    text = estimator_text("foliage_envelope", {})
    assert "it measures the foliage envelope" in text  # the measurand, stated
    mine = table[(table["method"] == "foliage_envelope") & (table["age"] == "old")]
    for side in ("both", "one"):
        r = pooled(mine[mine["side"] == side])
        assert f"{r['bias']:+.1%}" in text and f"{r['mape']:.1%}" in text
        assert f"{r['interval_covers']:.0%}" in text
    assert "held-out seeds" in text and "real terrestrial scans" in text
    assert "not measured" in estimator_text("no_such_estimator", {})  # never claims a figure
    section = accuracy_section("alpha_shape", {"alpha": 0.9})
    assert "alpha_shape (alpha = 0.9)" in section.text
    assert list(section.table["estimator"]).count("alpha_shape (recommended)") > 0
    assert set(section.table["tree family"]) >= {"unions of lobes on scaffold tips"}


def test_the_family_table_is_consistent() -> None:
    """Every family, age and side holds every method once; MAPE bounds |bias| and p90 bounds
    MAPE; the recommended estimator's interval coverage is a share."""
    from canopy_kit.volume.accuracy import family_accuracy_table

    table = family_accuracy_table()
    assert set(table["family"]) == {"envelope", "lobe_union", "grown", "real"}
    counts = table.groupby(["family", "age", "side", "method"]).size()
    assert (counts == 1).all()
    assert (table["mape"] + 1e-9 >= table["bias"].abs()).all()
    assert (table["p90"] + 1e-9 >= 0).all() and (table["n"] > 0).all()
    covers = table.loc[table["method"] == "foliage_envelope", "interval_covers"]
    assert covers.between(0, 1).all()
    assert table.loc[table["method"] != "foliage_envelope", "interval_covers"].isna().all()


@pytest.mark.parametrize("recommended", ["alpha_shape", "convex_hull", "foliage_envelope"])
def test_the_per_tree_table_shows_the_recommended_volume_and_its_interval(recommended) -> None:
    from canopy_kit.report.session import TABLE_COLUMNS, table_columns
    from canopy_kit.volume.verb import volume_column

    cols = table_columns(recommended)
    rec = volume_column(recommended)
    assert len(cols) == len(set(cols)) and set(TABLE_COLUMNS) <= set(cols)
    assert cols[cols.index(rec) + 1 : cols.index(rec) + 3] == ["volume_low_m3", "volume_high_m3"]
    assert cols.index("volume_convex_hull_m3") < cols.index("volume_alpha_m3")  # paper's order


def test_the_report_names_the_estimator_its_measurand_and_its_interval(tiny_pistachio_run) -> None:
    import html

    from canopy_kit.report.volumes import pooled
    from canopy_kit.volume.accuracy import family_accuracy_table

    page = (tiny_pistachio_run.out_dir / "report.html").read_text()
    plain = html.unescape(re.sub(r"<[^>]+>", " ", page))
    assert "the recommended estimator of this preset is foliage_envelope" in plain
    table = family_accuracy_table()
    mine = table[(table["method"] == "foliage_envelope") & (table["age"] == "old")]
    acc = pooled(mine[mine["side"] == "both"])
    assert f"mean signed error {acc['bias']:+.1%}" in plain
    for column in ("volume_foliage_envelope_m3", "volume_low_m3", "volume_high_m3"):
        assert f'data-key="{column}"' in page
    # the checks hold the recommended estimator against its own measurand, and every
    # estimator against the simulator's drawn envelope, which they name
    assert "foliage_envelope (recommended) volume vs its measurand on the complete foliage" in plain
    assert "alpha_shape volume vs true crown volume, the simulator's drawn envelope" in plain
    trees = pd.read_csv(tiny_pistachio_run.out_dir / "trees.csv")
    assert (trees["volume_method"] == "foliage_envelope").all()
    assert trees["volume_measurand"].str.contains("foliage envelope|ellipsoid").all()
    assert np.all(trees["volume_low_m3"] <= trees["volume_foliage_envelope_m3"])


def test_the_measurand_truth_is_the_estimator_on_the_complete_foliage(
    tiny_pistachio, tiny_pistachio_run
) -> None:
    """The run's ``true_measurand_m3`` (computed for the kind's measurand only) equals the
    recommended estimator on the matched tree's complete foliage computed from scratch."""
    from canopy_kit.config import load_preset
    from canopy_kit.evaluate.truth import load_truth
    from canopy_kit.evaluate.validation import MEASURAND_DENSITY
    from canopy_kit.evaluate.volume_accuracy import foliage_references, reference_volume

    table = tiny_pistachio_run.trees
    matched = table[table["truth_tree_id"].notna()]
    assert len(matched) >= 2 and matched["true_measurand_m3"].notna().all()
    volume = load_preset("adaptive").volume
    first = matched.iloc[0]
    truth = load_truth(tiny_pistachio.root)
    tree, kind = int(first["truth_tree_id"]), str(first["crown_kind"])
    for density, rel in ((MEASURAND_DENSITY, 1e-9), (None, 0.01)):  # None: the benchmarks' 4000
        refs = foliage_references(truth, [tree], volume, [volume.recommended], density=density)
        expected = reference_volume(refs[tree], volume.recommended, kind)
        assert first["true_measurand_m3"] == pytest.approx(expected, rel=rel)


MATRIX_SESSION = {
    "orchard": {"rows": 2, "trees_per_row": 2},
    "lidar": {"columns": 512, "rings": 16},
    "imu": {"enabled": False},
    "gnss": {"enabled": False},
}


@pytest.mark.slow
def test_recommended_estimator_on_trees_the_pipeline_segments(sim_factory) -> None:
    """A 2 × 2 session per crown form on seed 451 (used by no benchmark or tuning), segmented
    by the adaptive preset and measured by the volume stage, against the recommended
    estimator's own measurand on each tree's complete foliage (every leaf and branch the
    simulator meshed, seen or not): on every dense form from both sides within |bias| ≤ 5 %
    and MAPE ≤ 8 %, and its interval holds the measurand for ≥ 90 % of the dense-crown scans
    (both and one-sided). Sparse young trees, seen by this thin 16-ring sensor of 512
    columns and cut by the segmentation (one of them to IoU 0.69), are measured as their
    enclosing ellipsoid, flagged sparse, and closer to their measurand than the hull is to
    its own (measured: the ellipsoid −8.8 % bias, MAPE 12.6 %; the hull −21.5 %)."""
    from canopy_kit.config import load_preset, merge
    from canopy_kit.evaluate.volume_accuracy import segmented_volume_errors
    from canopy_kit.sim.crown_forms import FORM_NAMES

    config = load_preset("adaptive")
    recommended = config.volume.recommended
    covered = []
    for form in FORM_NAMES:
        session = sim_factory(
            "pistachio",
            fmt="ros1",
            seed=451,
            overrides=merge(MATRIX_SESSION, {"orchard": {"crown_form": form}}),
        )
        errors, score = segmented_volume_errors(
            session.root, config, [recommended, "convex_hull"], reference="foliage"
        )
        # sparse young trees are the hard case for segmentation too (measured 3 of 4)
        assert score.n_truth == 4 and score.n_correct >= (3 if form == "sparse" else 4), form
        mine = errors[errors["method"] == recommended]
        both = mine[mine["scan"] == "both"]["error"]
        print(f"{form}: bias {both.mean():+.3f}, MAPE {both.abs().mean():.3f}")
        intervals = errors[errors["method"] == "interval"]
        if form == "sparse":
            hull = errors[(errors["method"] == "convex_hull") & (errors["scan"] == "both")]
            print(f"sparse: convex hull bias {hull['error'].mean():+.3f}")
            assert (intervals["kind"] == "sparse").all()
            assert intervals["flags"].str.contains("sparse crown").all()
            assert both.abs().mean() < hull["error"].abs().mean()
            continue
        assert abs(both.mean()) <= 0.05 and both.abs().mean() <= 0.08, form
        covered.extend(intervals["covered"])
    assert len(covered) == 4 * 4 * 3 and np.mean(covered) >= 0.9


@pytest.mark.slow
def test_the_interval_holds_deeply_lobed_crowns(sim_factory) -> None:
    """Crowns cut deep between their lobes, leaves only in a 0.3 m shell (harsher than any
    default form; seed 451, never tuned on): the recommended estimate is close to its
    measurand on the complete foliage and the interval holds it for ≥ 90 % of the scans;
    the leafless inside the shell is reported, not hidden."""
    from canopy_kit.config import load_preset, merge
    from canopy_kit.evaluate.volume_accuracy import segmented_volume_errors

    config = load_preset("adaptive")
    harsh = {"crown_form": "lobed", "lobe_hollow_range": [0.25, 0.35], "leaf_penetration_m": 0.3}
    session = sim_factory(
        "pistachio", fmt="ros1", seed=451, overrides=merge(MATRIX_SESSION, {"orchard": harsh})
    )
    errors, score = segmented_volume_errors(
        session.root, config, [config.volume.recommended], reference="foliage"
    )
    assert score.n_truth == 4 and score.n_correct == 4
    mine = errors[errors["method"] == config.volume.recommended]
    print(f"deep lobes: bias {mine['error'].mean():+.3f}, MAPE {mine['error'].abs().mean():.3f}")
    assert mine["error"].abs().mean() <= 0.08
    intervals = errors[errors["method"] == "interval"]
    assert len(intervals) == 12 and intervals["covered"].mean() >= 0.9


def test_the_family_figure_draws_the_shipped_table() -> None:
    """The report's family figure: one panel per side, each bar the table's bias (%) for its
    family and estimator, and under the recommended estimator's bars its interval coverage."""
    import matplotlib

    matplotlib.use("Agg")
    from canopy_kit.report.plots import plot_family_accuracy
    from canopy_kit.volume.accuracy import family_accuracy_table

    table = family_accuracy_table()
    fig = plot_family_accuracy(table)
    old = table[table["age"] == "old"]
    both = old[(old["side"] == "both") & (old["method"] == "foliage_envelope")]
    panel = fig.axes[0]
    heights = [p.get_height() for p in panel.patches[: len(both)]]
    assert heights == pytest.approx(list(100 * both["bias"]), abs=1e-9)
    notes = [t.get_text() for t in panel.texts]
    assert notes == [f"{v:.0%}" for v in both["interval_covers"]]
    assert len(fig.axes) == 2 and "one side" in fig.axes[1].get_title()
