"""benchmarks/bench_interval_runs.py scores a run's intervals per contact class, widened and
unwidened, against hand-computed counts and ratios."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_interval_runs.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_interval_runs", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_score_trees_counts_widened_and_unwidened_per_contact_class(bench) -> None:
    # segment, contact, estimate, truth, widened [low, high], unwidened [low, high]
    rows = [
        (0, 0.00, 50.0, 52.0, (48.0, 55.0), (48.0, 55.0)),  # free, held
        (1, 0.05, 40.0, 50.0, (38.0, 44.0), (38.0, 44.0)),  # touching a little, missed
        (2, 0.20, 30.0, 45.0, (28.9, 58.3), (29.0, 33.0)),  # interwoven: held only widened
        (3, 0.10, 60.0, 50.0, (57.8, 116.5), (58.0, 66.0)),  # interwoven: missed both
        (4, 0.30, 20.0, np.nan, (19.3, 38.8), (19.5, 22.0)),  # no measurand: not scored
    ]
    trees = pd.DataFrame(
        {
            "segment": [r[0] for r in rows],
            "crown_contact": [r[1] for r in rows],
            "volume_foliage_envelope_m3": [r[2] for r in rows],
            "true_measurand_m3": [r[3] for r in rows],
            "volume_low_m3": [r[4][0] for r in rows],
            "volume_high_m3": [r[4][1] for r in rows],
            "truth_iou": [0.95, 0.95, 0.7, 0.95, 0.95],
        }
    )
    # the cache's table is keyed by segment, in another order than the tree table
    raw = pd.DataFrame(
        {"volume_low_m3": [r[5][0] for r in rows], "volume_high_m3": [r[5][1] for r in rows]},
        index=pd.Index([r[0] for r in rows], name="segment"),
    ).iloc[::-1]
    figures = bench.score_trees(trees, raw, "foliage_envelope")
    assert figures["held_by_contact"] == {"0-0.03": [1, 1], "0.03-0.08": [0, 1], "0.08-1": [1, 2]}
    assert figures["held_unwidened_by_contact"] == {
        "0-0.03": [1, 1],
        "0.03-0.08": [0, 1],
        "0.08-1": [0, 2],
    }
    assert figures["interwoven_ratios"] == [1.5, 0.833]  # 45 / 30, 50 / 60
    assert (figures["held_good_iou"], figures["n_good_iou"]) == (1, 3)


def test_score_trees_without_a_cached_interval_scores_no_unwidened_figures(bench) -> None:
    trees = pd.DataFrame(
        {
            "segment": [0],
            "crown_contact": [0.2],
            "volume_foliage_envelope_m3": [10.0],
            "true_measurand_m3": [12.0],
            "volume_low_m3": [9.6],
            "volume_high_m3": [19.4],
            "truth_iou": [0.95],
        }
    )
    figures = bench.score_trees(trees, None, "foliage_envelope")
    assert figures["held_unwidened_by_contact"] is None
    assert figures["held_by_contact"]["0.08-1"] == [1, 1]


def test_unwidened_interval_reads_the_volume_stage_entry(bench, tmp_path: Path) -> None:
    import pickle
    from types import SimpleNamespace

    assert bench.unwidened_interval(tmp_path) is None  # no cache
    table = pd.DataFrame({"segment": [3, 7], "volume_low_m3": [1.0, 2.0], "volume_high_m3": [3, 4]})
    (tmp_path / ".cache").mkdir()
    with (tmp_path / ".cache" / "volumes-abc.pkl").open("wb") as fh:
        pickle.dump(SimpleNamespace(table=table), fh)
    raw = bench.unwidened_interval(tmp_path)
    assert raw.loc[7, "volume_low_m3"] == 2.0 and raw.loc[3, "volume_high_m3"] == 3
