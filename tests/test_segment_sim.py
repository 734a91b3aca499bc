"""Segmentation of small simulated sessions, scored against the simulator's truth.

Maps are built from the true poses (the mapping stage is tested elsewhere). The sessions
are small (2 rows x 3 trees, half the horizontal resolution), so rates move in steps of
one tree in six; the assertions are the paper's findings and our targets, each with the
ceiling that the exact crown envelopes allow where crowns interweave.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fixtures_sim import truth_map_of

from canopy_kit.config import load_preset
from canopy_kit.evaluate.segmentation_score import envelope_ceiling, score_point_labels
from canopy_kit.segment.rows import driving_direction_from_trajectory
from canopy_kit.segment.verb import make_segmenter, segment
from canopy_kit.sim.truth import load_truth

pytestmark = pytest.mark.slow

SMALL = {"orchard": {"rows": 2, "trees_per_row": 3}, "lidar": {"columns": 512}}
PAPER = {
    "dbscan": {"eps": 0.8, "min_samples": 1300},
    "dbscan_spectral": {
        "eps": 0.8,
        "min_samples": 1300,
        "max_cluster_size": 45000,
        "n_neighbors": 10,
    },
    "adaptive": {},
}
#: the paper's almond method at our map's scale, as the shipped preset sets it
SCALED = load_preset("almond-scaled").segment


@pytest.fixture(scope="module")
def sessions(sim_factory):
    """{orchard: (session, map)} for a small pistachio, almond and paper-like almond session."""
    out = {}
    for orchard, seed in (("pistachio", 0), ("almond", 3), ("almond-paper", 0)):
        s = sim_factory(orchard, seed=seed, overrides=SMALL)
        out[orchard] = (s, truth_map_of(s))
    return out


class _Scores(dict):
    """``{(orchard, method): (score, segmentation)}`` and ``(orchard, "ceiling")``, each
    computed when a test first asks for it (6 of the 18 no test reads)."""

    def __init__(self, sessions: dict) -> None:
        super().__init__()
        self.sessions = sessions

    def __missing__(self, key: tuple[str, str]):
        orchard, method = key
        s, cloud = self.sessions[orchard]
        if method == "ceiling":
            value = score_point_labels(envelope_ceiling(cloud.xyz, s.root), cloud.fields["tree_id"])
        else:
            truth = load_truth(s.root)
            direction = driving_direction_from_trajectory(truth.trajectory[["x", "y"]].to_numpy())
            tl = truth.trees.set_index("tree_id")[["row", "label"]]
            runs = {m: (m, p) for m, p in PAPER.items()}
            runs["scaled"] = (SCALED.method, SCALED.params)
            runs["scaled_points"] = (SCALED.method, {**SCALED.params, "graph_cell": 0.0})
            name, params = runs[method]
            seg = segment(cloud, make_segmenter(name, params), driving_direction=direction)
            pl = seg.table().set_index("segment_id")[["row", "label"]]
            value = (
                score_point_labels(
                    seg.labels, cloud.fields["tree_id"], truth_labels=tl, pred_labels=pl
                ),
                seg,
            )
        self[key] = value
        return value


@pytest.fixture(scope="module")
def scores(sessions) -> _Scores:
    """{(orchard, method): (score, segmentation)} and the envelope ceiling per orchard, for
    the methods of PAPER, "scaled" and "scaled_points" (each made on first use)."""
    return _Scores(sessions)


def test_paper_dbscan_works_on_pistachio_and_merges_almond_rows(scores) -> None:
    pist, _ = scores["pistachio", "dbscan"]
    almond, _ = scores["almond", "dbscan"]
    assert pist.success_rate >= 0.8
    assert almond.success_rate <= 0.5 and almond.n_merged >= almond.n_truth // 2


def test_paper_spectral_split_improves_almond(scores) -> None:
    plain, _ = scores["almond", "dbscan"]
    hybrid, seg = scores["almond", "dbscan_spectral"]
    assert hybrid.success_rate > plain.success_rate
    assert seg.n_trees > scores["almond", "dbscan"][1].n_trees


def test_adaptive_targets_with_the_same_settings_on_both_orchards(scores) -> None:
    pist, seg = scores["pistachio", "adaptive"]
    assert pist.success_rate == 1.0 and pist.label_accuracy == 1.0
    almond, _ = scores["almond", "adaptive"]
    ceiling = scores["almond", "ceiling"]
    # At most one tree below what exact knowledge of the crowns would allow.
    assert almond.n_correct >= ceiling.n_correct - 1
    assert almond.success_rate >= max(
        scores["almond", m][0].success_rate for m in ("dbscan", "dbscan_spectral")
    )
    assert seg.rows.direction_source == "given" and len(seg.rows.lines) == 2


def test_adaptive_almond_target_on_the_paper_like_orchard(scores) -> None:
    """On ``almond-paper`` (crowns calibrated so that the paper's DBSCAN scores about its
    46 %) adaptive meets the 95 % target over 519 never-seen trees (docs/SEGMENTATION.md); on
    one small session: every tree the exact crown envelopes separate, at most one missed."""
    adaptive, seg = scores["almond-paper", "adaptive"]
    ceiling = scores["almond-paper", "ceiling"]
    assert adaptive.n_truth >= 5
    assert adaptive.n_correct >= ceiling.n_correct - 1 and adaptive.success_rate >= 0.8
    assert adaptive.label_accuracy == 1.0 and len(seg.rows.lines) == 2
    assert (
        scores["almond-paper", "dbscan_spectral"][0].n_correct
        >= scores["almond-paper", "dbscan"][0].n_correct
    )


def test_paper_method_at_our_map_scale_reaches_the_paper_on_the_paper_like_orchard(scores) -> None:
    """The ``almond-scaled`` preset (split threshold = a typical tree's map points, kNN graph
    on 0.3 m cells) gets 81-90 % of never-seen almond-paper trees per set (88.1 % of 519,
    docs/SEGMENTATION.md); on
    one small session: within one tree of the envelope ceiling, better than the paper's
    literal settings and no worse than the same settings on the point graph, and it still
    leaves every pistachio tree whole."""
    scaled, _ = scores["almond-paper", "scaled"]
    literal, _ = scores["almond-paper", "dbscan_spectral"]
    ceiling = scores["almond-paper", "ceiling"]
    assert scaled.n_correct >= ceiling.n_correct - 1 and scaled.n_correct > literal.n_correct
    # no worse than the same threshold and k on the point graph (on 7 trees they may tie;
    # over 102 calibration trees the cells gave 79 against 73; that the cells are used at
    # all is test_segment_units.test_spectral_split_on_graph_cells)
    assert scaled.n_correct >= scores["almond-paper", "scaled_points"][0].n_correct
    assert scores["pistachio", "scaled"][0].success_rate == 1.0


def test_adaptive_crown_split_no_worse_than_the_nearest_trunk(sessions, scores) -> None:
    """The crown-following split (segment.crowns) against the straight 2-D border between
    the same trees, on the almond session: at least as many trees right, and most of them."""
    s, cloud = sessions["almond"]
    truth = load_truth(s.root)
    direction = driving_direction_from_trajectory(truth.trajectory[["x", "y"]].to_numpy())
    flat = segment(
        cloud, make_segmenter("adaptive", {"crown_split": False}), driving_direction=direction
    )
    flat_score = score_point_labels(flat.labels, cloud.fields["tree_id"])
    crowns, _ = scores["almond", "adaptive"]
    assert crowns.n_correct >= flat_score.n_correct
    assert crowns.success_rate >= 0.8


def test_cli_segment_and_evaluate_round_trip(sessions, tmp_path: Path) -> None:
    from canopy_kit.io.clouds import write_cloud
    from canopy_kit.segment.export import _las_compatible

    s, cloud = sessions["pistachio"]
    map_path = write_cloud(tmp_path / "map.laz", _las_compatible(cloud))
    out = tmp_path / "run"
    exe = [str(Path(sys.executable).parent / "canopy-kit")]
    res = subprocess.run(
        exe
        + [
            "segment",
            str(map_path),
            "--preset",
            "almond",
            "--method",
            "adaptive",
            "--out",
            str(out),
            "--trajectory",
            str(s.root / "truth" / "trajectory.csv"),
        ],
        check=False,
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, res.stderr
    assert "segmented 6 trees in 2 rows (adaptive" in res.stdout
    summary = json.loads((out / "segmentation.json").read_text())
    assert summary["driving_direction_source"] == "trajectory trajectory.csv"
    assert "adaptive" in (out / "config.toml").read_text()
    for mode in ("points", "footprints"):
        res = subprocess.run(
            exe + ["evaluate", str(out), "--truth", str(s.root), "--json", "--mode", mode],
            check=False,
            capture_output=True,
            text=True,
        )
        assert res.returncode == 0, res.stderr
        data = json.loads(res.stdout)
        assert data["mode"] == mode and data["n_truth"] == 6 and data["success_rate"] == 1.0
        assert data["label_accuracy"] == 1.0
    bad = subprocess.run(
        exe + ["evaluate", str(tmp_path), "--truth", str(s.root)],
        check=False,
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "not a segmentation folder" in bad.stderr


def test_labels_survive_voxelisation_after_clustering(sessions) -> None:
    from canopy_kit.config import PreprocessConfig

    _, cloud = sessions["pistachio"]
    sub = cloud.select(np.arange(0, len(cloud), 3))
    a = segment(sub, "adaptive", PreprocessConfig(voxelize="before_clustering"))
    b = segment(sub, "adaptive", PreprocessConfig(voxelize="after_clustering"))
    assert a.n_trees == b.n_trees == 6
    sa = score_point_labels(a.labels, sub.fields["tree_id"]).success_rate
    sb = score_point_labels(b.labels, sub.fields["tree_id"]).success_rate
    assert sa == sb == 1.0


def test_scaled_spectral_split_does_not_depend_on_the_voxel_order(sessions, scores) -> None:
    """On 0.3 m graph cells the split sees about the same graph whether the 0.1 m grid comes
    before the clustering (the paper's text) or after it (its Fig. 3), so the same trees come
    out (the literal point graph loses most of them on the finer points: docs/SEGMENTATION.md)."""
    from canopy_kit.config import PreprocessConfig

    _, cloud = sessions["almond-paper"]
    after = segment(
        cloud,
        make_segmenter(SCALED.method, SCALED.params),
        PreprocessConfig(voxelize="after_clustering"),
        driving_direction=scores["almond-paper", "scaled"][1].rows.direction,
    )
    score = score_point_labels(after.labels, cloud.fields["tree_id"])
    assert score.n_correct == scores["almond-paper", "scaled"][0].n_correct
