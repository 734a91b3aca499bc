"""Segmentation, step by step, on synthetic inputs with known answers (fast)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from fixtures_sim import synthetic_orchard
from sklearn.base import clone
from sklearn.cluster import DBSCAN
from sklearn.metrics import adjusted_rand_score

from canopy_kit import plugins
from canopy_kit.config import PreprocessConfig, RowsConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.core.voxel import voxel_centroids
from canopy_kit.errors import ConfigError, InputError, PluginError
from canopy_kit.evaluate.segmentation_score import score_footprints, score_point_labels
from canopy_kit.segment.density import first_appearance_order, grid_dbscan, weighted_dbscan
from canopy_kit.segment.ground import fit_ground, ransac_plane
from canopy_kit.segment.preprocess import prepare
from canopy_kit.segment.rows import (
    assign_rows,
    bearing_to_vector,
    default_direction,
    driving_direction_from_trajectory,
)
from canopy_kit.segment.spectral import spectral_split
from canopy_kit.segment.stems import detect_stems
from canopy_kit.segment.verb import make_segmenter, segment


def blobs(seed: int = 0, n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = np.array([[0, 0, 2], [4, 0, 2], [0, 5, 2.5]])
    return np.concatenate(
        [c + rng.normal(0, 0.4, (n, 3)) for c in centres] + [rng.uniform(-3, 8, (30, 3))]
    )


# -- ground and preprocessing ---------------------------------------------------------------
def test_ransac_plane_recovers_a_plane_among_outliers() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-2, 2, (200, 2))
    z = 0.1 * xy[:, 0] - 0.05 * xy[:, 1] + 3.0
    z[:40] += rng.uniform(1, 3, 40)  # crown bottoms taken for ground candidates
    coef, inliers = ransac_plane(np.column_stack([xy, z]), 0.05, rng)
    assert np.allclose(coef, [0.1, -0.05, 3.0], atol=1e-6)
    assert inliers.sum() == 160


@pytest.mark.parametrize("slope", [0.0, 6.0])
def test_ground_model_follows_slopes_and_bumps_under_crowns(slope: float) -> None:
    orch = synthetic_orchard(rows=2, trees_per_row=3, slope_deg=slope)
    model = fit_ground(orch.cloud.xyz, cell_size=4.0, threshold=0.15)
    g = orch.cloud.fields["tree_id"] < 0
    xy = orch.cloud.xyz[:, :2]
    err = model.height(xy) - orch.ground(xy[:, 0], xy[:, 1])
    assert np.percentile(np.abs(err[g]), 95) < 0.12
    assert np.abs(np.median(err)) < 0.05


def test_ground_model_messages() -> None:
    with pytest.raises(InputError, match="no points"):
        fit_ground(np.zeros((0, 3)))
    with pytest.raises(InputError, match="cell_size"):
        fit_ground(np.zeros((5, 3)), cell_size=0)


def test_prepare_bands_heights_and_weighs_voxels() -> None:
    orch = synthetic_orchard(rows=1, trees_per_row=2)
    cfg = PreprocessConfig()
    prep = prepare(orch.cloud, cfg)
    crown = orch.cloud.fields["tree_id"] >= 0
    canopy = np.zeros(len(orch.cloud), bool)
    canopy[prep.canopy_index] = True
    assert canopy[crown].mean() > 0.99  # crowns kept
    assert not canopy[~crown & (prep.height < 0.5)].any()  # ground and grass removed
    # each voxel weighs the map points it holds
    assert prep.seen_weight.sum() == len(prep.canopy_index)
    assert np.array_equal(np.bincount(prep.canopy_to_seen), prep.seen_weight.astype(int))
    after = prepare(orch.cloud, PreprocessConfig(voxelize="after_clustering"))
    assert len(after.seen_index) == len(after.canopy_index) and (after.seen_weight == 1).all()


@pytest.mark.parametrize(
    "field,value,message",
    [
        ("stem_band", [0.8, 0.3], "preprocess.stem_band"),
        ("voxel_size", 0.0, "preprocess.voxel_size"),
        ("max_canopy_height", 0.5, "preprocess.min_canopy_height"),  # under the 0.8 floor
        ("min_canopy_height", -1.0, "preprocess.min_canopy_height"),
    ],
)
def test_preprocess_config_errors_name_the_setting(field: str, value: object, message: str) -> None:
    orch = synthetic_orchard(rows=1, trees_per_row=1)
    cfg = PreprocessConfig(**{field: value})
    with pytest.raises(ConfigError, match=message):
        prepare(orch.cloud, cfg)


# -- DBSCAN implementations -----------------------------------------------------------------
@pytest.mark.parametrize("weighted", [False, True])
def test_exact_dbscan_equals_scikit_learn(weighted: bool) -> None:
    xyz = blobs()
    w = np.random.default_rng(3).integers(1, 5, len(xyz)).astype(float) if weighted else None
    ours, core = weighted_dbscan(xyz, 0.5, 25, w, target_points=300)
    ref = DBSCAN(eps=0.5, min_samples=25).fit(xyz, sample_weight=w)
    assert np.array_equal(core, np.isin(np.arange(len(xyz)), ref.core_sample_indices_))
    assert adjusted_rand_score(ours, ref.labels_) > 0.99


def test_lattice_dbscan_agrees_with_scikit_learn() -> None:
    xyz = blobs(n=800)
    ours, _ = grid_dbscan(xyz, 0.8, 40, tile_size=3.0)  # small tiles: labels joined across them
    ref = DBSCAN(eps=0.8, min_samples=40).fit_predict(xyz)
    assert ours.max() == ref.max() == 2
    assert adjusted_rand_score(ours, ref) > 0.98


def test_dbscan_edge_cases() -> None:
    assert len(weighted_dbscan(np.zeros((0, 3)), 1.0, 5)[0]) == 0
    assert len(grid_dbscan(np.zeros((0, 3)), 1.0, 5)[0]) == 0
    with pytest.raises(InputError, match="eps"):
        grid_dbscan(np.zeros((3, 3)), 0.0, 5)
    with pytest.raises(InputError, match="sample_weight"):
        weighted_dbscan(np.zeros((3, 3)), 1.0, 5, np.ones(2))
    assert first_appearance_order(np.array([5, -1, 2, 5, 9])).tolist() == [0, -1, 1, 0, 2]


# -- the segmenter contract (every registered plugin) --------------------------------------
@pytest.mark.parametrize("name", plugins.names("segmenters"))
def test_every_segmenter_honours_the_scikit_learn_contract(name: str) -> None:
    cls = plugins.load("segmenters", name)
    est = cls()
    params = est.get_params()
    assert params and all(not k.endswith("_") for k in params)
    assert not [k for k in vars(est) if k.endswith("_")], "work done in __init__"
    assert clone(est).get_params() == params
    xyz = blobs()
    labels = est.fit_predict(xyz)
    assert labels.shape == (len(xyz),) and labels.dtype.kind == "i" and labels.min() >= -1
    assert est.n_clusters_ == labels.max() + 1
    assert np.array_equal(est.labels_, labels)
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        cls().fit_predict(np.zeros((4, 2)))
    assert len(cls().fit_predict(np.zeros((0, 3)))) == 0


def test_paper_segmenters_count_map_points_not_voxels() -> None:
    xyz = blobs(n=200)
    # 200 points per blob in a 0.8 m ball: no core points with N_min = 1300 ...
    assert make_segmenter("dbscan").fit_predict(xyz).max() == -1
    # ... unless each point stands for 10 map points, as a voxel of a dense map does.
    labels = make_segmenter("dbscan").fit_predict(xyz, sample_weight=np.full(len(xyz), 10.0))
    assert labels.max() == 2


def test_spectral_splits_clusters_by_size() -> None:
    rng = np.random.default_rng(0)
    # one DBSCAN cluster: three touching blobs in a row
    xyz = np.concatenate([rng.normal([x, 0, 2], [0.7, 0.5, 0.5], (600, 3)) for x in (0, 2.2, 4.4)])
    seg = make_segmenter("dbscan_spectral", {"min_samples": 20, "max_cluster_size": 600})
    labels = seg.fit_predict(xyz)
    assert seg.splits_ == {0: 3} and labels.max() == 2
    truth = np.repeat([0, 1, 2], 600)
    assert adjusted_rand_score(truth, labels) > 0.6


def test_spectral_split_on_graph_cells() -> None:
    rng = np.random.default_rng(1)
    xyz = np.concatenate([rng.normal([x, 0, 2], [0.7, 0.5, 0.5], (600, 3)) for x in (0, 2.2, 4.4)])
    seg = make_segmenter(
        "dbscan_spectral",
        {"min_samples": 20, "max_cluster_size": 600, "graph_cell": 0.3, "n_neighbors": 15},
    )
    labels = seg.fit_predict(xyz)
    assert seg.splits_ == {0: 3} and labels.max() == 2
    assert adjusted_rand_score(np.repeat([0, 1, 2], 600), labels) > 0.6
    # every point of the split cluster takes its cell's part (cells from the cluster's corner)
    member = labels >= 0
    _, cell = voxel_centroids(xyz[member], 0.3)
    per_cell = pd.Series(labels[member]).groupby(cell).nunique()
    assert (per_cell == 1).all()
    with pytest.raises(InputError, match="graph_cell"):
        make_segmenter("dbscan_spectral", {"graph_cell": -0.3}).fit_predict(xyz)
    with pytest.raises(ConfigError, match="graph_cell"):
        spectral_split(xyz, 3, graph_cell=-0.3)


def test_voxel_centroids_by_hand() -> None:
    xyz = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [1.2, 0.0, 0.0], [0.0, 0.0, 0.0]])
    centroids, cell = voxel_centroids(xyz, 1.0)
    assert cell[0] == cell[1] == cell[3] != cell[2]
    np.testing.assert_allclose(centroids[cell[0]], [0.4 / 3, 0.2 / 3, 0.2 / 3])
    np.testing.assert_allclose(centroids[cell[2]], [1.2, 0.0, 0.0])


def test_make_segmenter_errors() -> None:
    with pytest.raises(PluginError, match="no segmenters plugin named 'kmeans'"):
        make_segmenter("kmeans")
    with pytest.raises(ConfigError, match="segmenter 'dbscan' has no parameter 'epsilon'"):
        make_segmenter("dbscan", {"epsilon": 0.8})


# -- trunks and the adaptive segmenter ------------------------------------------------------
def test_stems_found_under_crowns_and_grass_ignored() -> None:
    orch = synthetic_orchard(rows=2, trees_per_row=3, row_spacing=5.0)
    prep = prepare(orch.cloud, PreprocessConfig())
    stems = detect_stems(prep.normalized(orch.cloud, prep.stem_index))
    assert len(stems) == 6
    d = np.linalg.norm(stems.xy[:, None] - orch.centres[None], axis=2).min(axis=0)
    assert d.max() < 0.1


@pytest.mark.parametrize("trunks", [True, False])
def test_adaptive_splits_touching_crowns_in_a_hedgerow(trunks: bool) -> None:
    # crowns 3.6 m wide every 3 m: DBSCAN sees one cluster per row
    orch = synthetic_orchard(
        rows=2,
        trees_per_row=5,
        spacing=3.0,
        row_spacing=6.0,
        trunks=trunks,
        bearing_deg=25.0,
        density=150,
    )
    truth = orch.cloud.fields["tree_id"]
    seg = segment(orch.cloud, make_segmenter("adaptive"))
    score = score_point_labels(seg.labels, truth)
    # with trunks every tree is found; without, the count comes from the rows' width
    assert score.success_rate >= (1.0 if trunks else 0.6)
    paper = segment(orch.cloud, make_segmenter("dbscan", {"min_samples": 100}))
    assert score_point_labels(paper.labels, truth).n_merged >= 8


def test_parts_split_in_forked_workers_give_the_labels_of_one_process(monkeypatch) -> None:
    """The canopy parts shared among workers (adaptive.each_part) give every point the tree
    it gets when the parts are split one after the other, and the trees are still found."""
    import canopy_kit.segment.adaptive as adaptive

    orch = synthetic_orchard(
        rows=3, trees_per_row=4, spacing=3.0, row_spacing=6.0, bearing_deg=25.0, density=150
    )
    monkeypatch.setattr(adaptive, "PARALLEL_MIN_POINTS", 10**12)
    serial = segment(orch.cloud, make_segmenter("adaptive"))
    monkeypatch.setattr(adaptive, "PARALLEL_MIN_POINTS", 0)
    monkeypatch.setattr("canopy_kit.core.parallel.worker_count", lambda setting, most: min(2, most))
    forked = segment(orch.cloud, make_segmenter("adaptive"))
    assert np.array_equal(forked.labels, serial.labels)
    assert score_point_labels(forked.labels, orch.cloud.fields["tree_id"]).success_rate == 1.0


# -- rows and labels --------------------------------------------------------------------------
@pytest.mark.parametrize("bearing", [0.0, 30.0, 95.0, 200.0, 315.0])
@pytest.mark.parametrize("bow", [0.0, 1.0])
def test_rows_and_labels_at_any_bearing_and_curvature(bearing: float, bow: float) -> None:
    orch = synthetic_orchard(
        rows=4, trees_per_row=7, bearing_deg=bearing, bow=bow, trunks=False, density=5
    )
    rng = np.random.default_rng(2)
    xy = orch.centres + rng.normal(0, 0.2, orch.centres.shape)
    perm = rng.permutation(len(xy))
    result = assign_rows(xy[perm], RowsConfig(), driving_direction=bearing_to_vector(bearing))
    assert result.row.tolist() == orch.rows[perm].tolist()
    assert result.index_in_row.tolist() == orch.index_in_row[perm].tolist()
    expected = [
        f"{'L' if r % 2 == 0 else 'R'}{i}" for r, i in zip(orch.rows[perm], orch.index_in_row[perm])
    ]
    assert result.labels == expected
    assert len(set(result.tree_ids)) == len(xy)
    assert not result.warnings


@pytest.mark.parametrize("bearing", [0.0, 45.0])
def test_stray_segments_between_rows_do_not_renumber_the_rows(bearing: float) -> None:
    """Two stray segments in the alleys (measured on a simulated almond drive: lines of 6, 1,
    7, 1, 7 trees) are labelled apart; the real rows keep their numbers and labels."""
    spacing = 6.0
    orch = synthetic_orchard(
        rows=3, trees_per_row=7, row_spacing=spacing, bearing_deg=bearing, trunks=False, density=5
    )
    d = bearing_to_vector(bearing)
    right = np.array([d[1], -d[0]])
    first = orch.centres[orch.rows == 0].mean(axis=0)
    # one alone, and two pieces 5 m apart in the other alley (a "row" of two between rows)
    strays = np.array(
        [
            first + 0.5 * spacing * right + 2.0 * d,
            first + 1.5 * spacing * right - 3.0 * d,
            first + 1.5 * spacing * right + 4.0 * d,
        ]
    )
    xy = np.vstack([orch.centres, strays])
    result = assign_rows(xy, RowsConfig(), driving_direction=d)
    assert result.row[:-3].tolist() == orch.rows.tolist()
    assert result.labels[:-3] == [
        f"{'L' if r % 2 == 0 else 'R'}{i}" for r, i in zip(orch.rows, orch.index_in_row)
    ]
    assert result.row[-3:].tolist() == [-1, -1, -1]
    assert result.labels[-3:] == ["T1", "T0", "T2"]  # numbered along the driving direction
    assert len(result.lines) == 3 and len(set(result.tree_ids)) == len(xy)
    assert (
        len(result.warnings) == 1
        and "3 of 24 trees stand in the alleys between the 3 rows" in result.warnings[0]
    )


def test_a_short_row_where_a_row_fits_stays_a_row() -> None:
    """Six rows 6 m apart, the fourth cut short (12 of 30 trees): still row 3, and the rows
    after it keep their numbers; the same 12 trees in an alley half-way between two rows
    are strays."""
    rows = []
    for r in range(6):
        n = 12 if r == 3 else 30
        rows.append(np.column_stack([np.full(n, 6.0 * r), 5.0 * np.arange(n)]))
    xy = np.vstack(rows)
    truth = np.repeat(np.arange(6), [30, 30, 30, 12, 30, 30])
    d = np.array([0.0, 1.0])
    result = assign_rows(xy, RowsConfig(), driving_direction=d)
    assert result.row.tolist() == truth.tolist() and not result.warnings
    alley = xy.copy()
    alley[truth == 3, 0] = 3.0  # into the alley between rows 0 and 1, the rows after it closing up
    alley[truth > 3, 0] -= 6.0
    moved = assign_rows(alley, RowsConfig(), driving_direction=d)
    assert (moved.row[truth == 3] == -1).all()
    assert (
        moved.row[truth != 3].tolist() == np.where(truth > 3, truth - 1, truth)[truth != 3].tolist()
    )


def test_the_first_trees_on_both_sides_of_an_alley_are_two_rows() -> None:
    """A streamed drive emits the first trees on both sides of the alley first: two or three
    trees across it are two rows along the driving direction, not one row across."""
    d = bearing_to_vector(30.0)
    right = np.array([d[1], -d[0]])
    xy = np.array([-3.5 * right, 3.5 * right + 0.5 * d, -3.5 * right + 5.0 * d])
    two = assign_rows(xy[:2], RowsConfig(), driving_direction=d)
    assert two.labels == ["L0", "R0"] and two.row.tolist() == [0, 1]
    three = assign_rows(xy, RowsConfig(), driving_direction=d)
    assert three.labels == ["L0", "R0", "L1"] and not three.warnings


def test_rows_default_direction_and_trajectory() -> None:
    assert np.allclose(
        default_direction(np.array([0.2, -1.0])), np.array([-0.2, 1.0]) / np.hypot(0.2, 1)
    )
    assert default_direction(np.array([-1.0, 0.0])).tolist() == [1.0, 0.0]
    traj = np.array([[0, 0], [0, 0], [0.1, 2], [0.2, 6], [1, 10]])
    d = driving_direction_from_trajectory(traj)
    assert d[1] > 0.99
    with pytest.raises(InputError, match="never moves"):
        driving_direction_from_trajectory(np.zeros((10, 2)))
    # driving the other way mirrors the labels: the last tree becomes index 0
    orch = synthetic_orchard(rows=2, trees_per_row=4, trunks=False, density=5)
    fwd = assign_rows(orch.centres)
    back = assign_rows(orch.centres, driving_direction=np.array([0.0, -1.0]))
    assert fwd.direction_source.startswith("default")
    assert back.index_in_row.tolist() == (3 - fwd.index_in_row).tolist()
    assert back.row.tolist() == (1 - fwd.row).tolist()


def test_rows_give_up_clearly_on_a_forest_and_handle_tiny_inputs() -> None:
    xy = np.random.default_rng(0).uniform(0, 90, (150, 2))
    result = assign_rows(xy)
    assert result.warnings and "no rows detected" in result.warnings[0]
    assert result.labels[0].startswith("T") and (result.row == -1).all()
    # it says which sign of an orchard is missing, not a contradiction ("159 of 169 in rows")
    reasons = result.warnings[0].removeprefix("no rows detected: ").split("; ")[:-1]
    assert reasons and all(
        r.startswith(("only ", "trees stand a median", "the candidate rows are")) for r in reasons
    )
    one = assign_rows(np.array([[3.0, 4.0]]))
    assert one.labels == ["L0"] and not one.warnings
    empty = assign_rows(np.zeros((0, 2)))
    assert empty.labels == [] and "no trees" in empty.warnings[0]


# -- evaluation -----------------------------------------------------------------------------
def test_point_scores_classify_merges_splits_and_misses() -> None:
    truth = np.repeat([0, 1, 2, 3, 4, -1], 100)
    pred = truth.copy()
    pred[100:300] = 7  # trees 1 and 2 merged
    pred[300:335], pred[335:370], pred[370:400] = 8, 9, 11  # tree 3 split in three
    pred[400:500] = -1  # tree 4 missed
    pred[500:], pred[500:520] = 10, 7  # a segment of non-tree points; the merge takes some
    s = score_point_labels(pred, truth)
    assert (s.n_truth, s.n_correct, s.n_merged, s.n_split, s.n_missed) == (5, 1, 2, 1, 1)
    assert s.n_predicted == 6 and s.n_false_segments == 2  # the merged one and the non-tree one
    assert s.precision == pytest.approx(1 / 6) and s.recall == pytest.approx(0.2)
    # IoU exactly 0.5 counts (>=): two halves of one tree, one of them matches
    half = truth.copy()
    half[:50] = 20
    assert score_point_labels(half, truth).n_correct == 5
    perfect = score_point_labels(truth, truth)
    assert perfect.success_rate == 1.0 and perfect.f1 == 1.0
    with pytest.raises(InputError, match="predicted labels"):
        score_point_labels(pred[:5], truth)


def test_failures_to_pick_from_and_one_at_a_time() -> None:
    truth = np.repeat([0, 1, 2, 3, 4], 100)
    pred = truth.copy()
    pred[100:300] = 7  # trees 1 and 2 merged
    pred[400:500] = -1  # tree 4 missed
    tl = pd.DataFrame({"row": [0] * 5, "label": [f"L{i}" for i in range(5)]}, index=range(5))
    s = score_point_labels(pred, truth, truth_labels=tl)
    picks = s.failures()
    assert list(picks.values())[0] == 4  # the missed tree, IoU 0, first
    assert sorted(picks.values()) == sorted(s.trees.loc[s.trees["status"] != "correct", "truth_id"])
    assert len(picks) == s.n_truth - s.n_correct
    assert "tree 4 (r0-L4): missed, IoU 0.00" in picks
    one = s.only(picks["tree 4 (r0-L4): missed, IoU 0.00"])
    assert list(one.trees["truth_id"]) == [4] and one.n_correct == s.n_correct
    assert score_point_labels(truth, truth).failures() == {}


def test_label_correctness_and_footprint_scores() -> None:
    square = lambda x, y, r: np.array(  # noqa: E731
        [[x - r, y - r], [x + r, y - r], [x + r, y + r], [x - r, y + r]]
    )
    truth = {0: square(0, 0, 1), 1: square(5, 0, 1), 2: square(10, 0, 1)}
    pred = {10: square(0.1, 0, 1), 11: square(7.5, 0, 3.6)}  # 1 and 2 merged
    tl = pd.DataFrame({"row": [0, 0, 0], "label": ["L0", "L1", "L2"]}, index=[0, 1, 2])
    pl = pd.DataFrame({"row": [0, 0], "label": ["L0", "L1"]}, index=[10, 11])
    s = score_footprints(pred, truth, truth_labels=tl, pred_labels=pl)
    assert (s.n_correct, s.n_merged, s.n_label_correct) == (1, 2, 1)
    assert s.trees.loc[0, "iou"] == pytest.approx(3.8 / 4.2, abs=0.04)


# -- the verb, bad input and the run folder ---------------------------------------------------
def test_segment_verb_bad_input_messages() -> None:
    with pytest.raises(InputError, match="map has no points"):
        segment(PointCloud(np.zeros((0, 3))), "adaptive")
    rng = np.random.default_rng(0)
    flat = PointCloud(np.column_stack([rng.uniform(0, 30, (5000, 2)), rng.normal(0, 0.02, 5000)]))
    with pytest.raises(InputError, match="is it all ground"):
        segment(flat, "dbscan")
    with pytest.raises(InputError, match="has no fit_predict"):
        segment(flat, object())


def test_segment_one_tree_and_no_rows() -> None:
    one = synthetic_orchard(rows=1, trees_per_row=1)
    seg = segment(one.cloud, "adaptive")
    assert seg.n_trees == 1 and seg.trees[0].label == "L0" and seg.trees[0].tree_id == "r0-L0"
    assert not seg.warnings
    assert score_point_labels(seg.labels, one.cloud.fields["tree_id"]).success_rate == 1.0
    # trees scattered at random: segmented, but labelled T0.. with a clear warning
    rng = np.random.default_rng(4)
    parts = []
    for k, c in enumerate(rng.uniform(0, 40, (12, 2))):
        o = synthetic_orchard(rows=1, trees_per_row=1, seed=k, ground_extent=0.5)
        xyz = o.cloud.xyz.copy()
        xyz[:, :2] += c
        parts.append(xyz)
    scattered = PointCloud(np.concatenate(parts))
    seg = segment(scattered, "adaptive")
    assert seg.warnings and "no rows detected" in seg.warnings[0]


def test_write_and_read_a_run_folder(tmp_path) -> None:
    from canopy_kit.segment.export import read_segmentation, write_segmentation

    orch = synthetic_orchard(rows=2, trees_per_row=2, density=100)
    seg = segment(orch.cloud, "adaptive")
    paths = write_segmentation(tmp_path / "run", seg, orch.cloud)
    assert {p.name for p in paths.values()} >= {"segmented.laz", "trees.csv", "trees.geojson"}
    pos = json.loads(paths["positions"].read_text())
    assert "crs" not in pos  # RFC 7946: WGS84 lon/lat (tests/test_gis_outputs.py checks them)
    lon0, lat0, _ = pos["features"][0]["geometry"]["coordinates"]
    assert -180 <= lon0 <= 180 and -90 <= lat0 <= 90
    run = read_segmentation(tmp_path / "run")
    assert run.trees["tree_id"].tolist() == [t.tree_id for t in seg.trees]
    assert np.allclose(run.cloud.xyz, orch.cloud.xyz, atol=0.002)
    assert np.array_equal(run.cloud.fields["segment_id"], seg.labels)
    assert set(run.footprints) == {t.segment_id for t in seg.trees}
    with pytest.raises(InputError, match="not a segmentation folder"):
        read_segmentation(tmp_path)


def test_results_table_pivots_long_form_runs(tmp_path) -> None:
    from canopy_kit.paper.segmentation_results import results_table, success_table

    runs = pd.DataFrame(
        {
            "method": ["dbscan", "dbscan", "adaptive", "adaptive"],
            "orchard": ["almond", "pistachio", "almond", "pistachio"],
            "success_points": [0.4, 0.9, 0.9, 1.0],
            "variant": "default",
        }
    )
    table = success_table(runs)
    assert table.loc["adaptive", ("mean", "almond")] == 0.9
    assert list(table.index) == ["dbscan", "adaptive"]
    runs.to_csv(tmp_path / "r.csv", index=False)
    assert results_table(tmp_path / "r.csv").equals(table)
    with pytest.raises(InputError, match="no segmentation results"):
        results_table(tmp_path / "missing.csv")


def test_plots_top_view_and_failure_gallery() -> None:
    import matplotlib

    matplotlib.use("Agg")
    from canopy_kit.segment.plots import plot_failure_gallery, plot_top_view

    orch = synthetic_orchard(rows=2, trees_per_row=3, spacing=3.0, density=100)
    truth = orch.cloud.fields["tree_id"]
    seg = segment(orch.cloud, make_segmenter("dbscan", {"min_samples": 60}))
    fig = plot_top_view(orch.cloud, seg)
    assert len(fig.axes[0].texts) == seg.n_trees + 1  # labels and the direction arrow
    score = score_point_labels(seg.labels, truth)
    gallery = plot_failure_gallery(orch.cloud, seg, score, truth, max_panels=3)
    assert gallery is not None and len(gallery.axes) == 2 * min(3, score.n_truth - score.n_correct)
    good = segment(orch.cloud, "adaptive")
    assert (
        plot_failure_gallery(orch.cloud, good, score_point_labels(good.labels, truth), truth)
        is None
    )


def test_top_view_image_shows_the_highest_point_of_each_pixel() -> None:
    from canopy_kit.segment.plots import segment_colours, top_view_image

    # Two points share the pixel at (0.05, 0.05): the higher one (label 2) is seen from above.
    xy = np.array([[0.05, 0.05], [0.06, 0.04], [0.37, 0.15]])
    labels = np.array([1, 2, -1])
    height = np.array([1.0, 3.0, 0.5])
    image, extent = top_view_image(xy, labels, height, pixel=0.1)
    assert image.shape == (2, 4, 4)  # rows: y pixels, columns: x pixels
    assert np.allclose(extent, [0.05, 0.45, 0.04, 0.24])
    colours = segment_colours(np.array([2, -1]))
    assert np.allclose(image[0, 0], colours[0]) and np.allclose(image[1, 3], colours[1])
    assert image[0, 1:, 3].max() == 0 and image[1, :3, 3].max() == 0  # no point: transparent


def test_cli_segment_bad_maps_give_one_line_messages(cli_server, tmp_path) -> None:
    """Empty and all-ground maps: exit code 2 and a message; one tree and no rows: results.
    The commands run on the module's command server (conftest.py ``cli_server``)."""
    from canopy_kit.io.clouds import write_cloud

    rng = np.random.default_rng(0)
    flat = PointCloud(np.column_stack([rng.uniform(0, 30, (5000, 2)), rng.normal(0, 0.02, 5000)]))
    one = synthetic_orchard(rows=1, trees_per_row=1, density=150).cloud
    scattered = []
    for k, c in enumerate(rng.uniform(0, 40, (8, 2))):
        xyz = synthetic_orchard(
            rows=1, trees_per_row=1, seed=k, ground_extent=0.5, density=150
        ).cloud.xyz.copy()
        xyz[:, :2] += c
        scattered.append(xyz)
    maps = {
        "flat": flat,
        "one": PointCloud(one.xyz),
        "scattered": PointCloud(np.concatenate(scattered)),
    }
    res = {}
    for name, cloud in maps.items():
        path = write_cloud(tmp_path / f"{name}.laz", cloud)
        res[name] = cli_server.run(
            [
                "segment",
                str(path),
                "--preset",
                "adaptive",
                "--out",
                str(tmp_path / name),
                "--no-cloud",
            ]
        )
    assert res["flat"].returncode == 2
    assert res["flat"].stderr.strip().startswith("error: map has no points more than 0.8 m above")
    assert "Traceback" not in res["flat"].stderr
    assert res["one"].returncode == 0 and "segmented 1 trees in 1 rows" in res["one"].stdout
    assert res["scattered"].returncode == 0, res["scattered"].stderr
    assert "warning: no rows detected" in " ".join(res["scattered"].stdout.split())
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = [0.01, 0.01, 0.01]
    laspy.LasData(header).write(tmp_path / "empty.laz")
    bad = cli_server.run(["segment", str(tmp_path / "empty.laz"), "--out", str(tmp_path / "e")])
    assert bad.returncode == 2 and bad.stderr.strip().endswith("LAS file has no points")


def test_reproduction_table_pools_trees_and_sets_the_paper_beside(tmp_path) -> None:
    from canopy_kit.paper.segmentation_results import reproduction_results, reproduction_table

    runs = pd.DataFrame(
        {
            "method": ["dbscan", "dbscan", "adaptive", "dbscan", "dbscan"],
            "orchard": ["almond", "almond", "almond", "pistachio", "almond-paper"],
            "seed": [201, 202, 201, 201, 511],
            "n_truth": [10, 20, 10, 18, 17],
            "success_points": [0.5, 0.25, 1.0, 17 / 18, 8 / 17],
            "variant": "default",
        }
    )
    t = reproduction_table(runs).set_index(["orchard", "method"])
    assert list(t.index) == [
        ("pistachio", "dbscan"),
        ("almond", "dbscan"),
        ("almond", "adaptive"),
        ("almond-paper", "dbscan"),
    ]
    assert t.loc[("almond-paper", "dbscan"), "paper"] == 0.46  # a preset of kind almond
    assert (
        t.loc[("almond", "dbscan"), "correct"] == 10 and t.loc[("almond", "dbscan"), "trees"] == 30
    )
    assert t.loc[("almond", "dbscan"), "success"] == pytest.approx(1 / 3)
    assert t.loc[("almond", "dbscan"), "seeds"] == "201 202"
    assert t.loc[("almond", "dbscan"), "paper"] == 0.46
    assert t.loc[("pistachio", "dbscan"), "paper"] == 0.93
    assert t.loc[("almond", "adaptive"), "target"] == 0.95
    runs.to_csv(tmp_path / "r.csv", index=False)
    only = reproduction_results(tmp_path / "r.csv", seeds=[202])
    assert len(only) == 1 and only.iloc[0]["success"] == 0.25
    assert t.loc[("almond-paper", "dbscan"), "correct"] == 8
    with pytest.raises(InputError, match="column 'seed' missing"):
        reproduction_table(runs.drop(columns="seed"))


def test_segment_colours_are_never_the_grey_of_unlabelled_points() -> None:
    from canopy_kit.segment.plots import NOISE_RGBA, segment_colours

    labels = np.arange(-1, 60)
    rgba = segment_colours(labels)
    assert tuple(rgba[0]) == NOISE_RGBA
    trees = rgba[1:, :3]
    assert np.all(np.ptp(trees, axis=1) > 0.1)  # saturated: no grey (r = g = b) among trees
    assert np.all(np.any(np.abs(np.diff(trees, axis=0)) > 0.1, axis=1))  # neighbours differ


def test_first_minimum_and_voxel_representatives_match_a_plain_loop() -> None:
    from canopy_kit.core.voxel import first_minimum, voxel_representatives

    rng = np.random.default_rng(5)
    groups = rng.integers(0, 50, 2000)
    values = rng.integers(0, 20, 2000).astype(float)  # many ties
    expected = [
        min(np.flatnonzero(groups == g), key=lambda i: (values[i], i)) for g in np.unique(groups)
    ]
    assert first_minimum(groups, values).tolist() == expected
    xyz = (
        np.round(rng.uniform(0, 1, (3000, 3)) * 64) / 64
    )  # binary lattice: exact distances, true ties
    reps, inverse = voxel_representatives(xyz, 0.25)
    for v, rep in enumerate(reps):
        members = np.flatnonzero(inverse == v)
        centre = np.floor((xyz[rep] - xyz.min(axis=0)) / 0.25) * 0.25 + 0.125 + xyz.min(axis=0)
        dist = np.sum((xyz[members] - centre) ** 2, axis=1)
        best = members[dist == dist.min()]
        assert rep == min(
            best, key=lambda i: tuple(xyz[i])
        )  # nearest the centre, then smallest x, y, z


def test_first_minimum_skips_groups_without_a_minimum_as_numpy_does() -> None:
    """A group with a NaN value has no minimum (``np.minimum`` propagates NaN); an infinite
    value is one; a group number with no point has none."""
    from canopy_kit.core.voxel import first_minimum

    groups = np.array([0, 0, 2, 2, 3, 3, 5])
    values = np.array([2.0, np.nan, np.inf, np.inf, -np.inf, 1.0, 4.0])
    assert first_minimum(groups, values).tolist() == [2, 4, 6]
    assert first_minimum(np.zeros(0, np.int64), np.zeros(0)).tolist() == []


def test_column_extremes_equal_numpys_reduction_over_rows() -> None:
    from canopy_kit.core.cloud import column_max, column_min

    rng = np.random.default_rng(2)
    for a in (rng.normal(size=(1000, 3)), rng.integers(-50, 50, (1000, 2))):
        assert np.array_equal(column_min(a), a.min(axis=0))
        assert np.array_equal(column_max(a), a.max(axis=0))
        assert column_min(a).dtype == a.dtype


def test_crowns_far_wider_or_smaller_than_the_others_are_flagged() -> None:
    """Two neighbours merged into one segment measure about twice the typical crown; a
    piece of a crown a fraction of it. Ordinary variation (±25 %) is not flagged."""
    from canopy_kit.segment.qa import crown_outliers

    rng = np.random.default_rng(4)
    diameters = rng.uniform(3.3, 4.4, 12)
    diameters[[3, 8]] = [9.1, 1.4]  # two trees in one segment; a fragment
    trees = pd.DataFrame(
        {"tree_id": [f"r0-L{i}" for i in range(12)], "crown_diameter_m": diameters}
    )
    notes = crown_outliers(trees)
    assert [i for i, n in enumerate(notes) if n] == [3, 8]
    assert "two or more trees" in notes[3] and "fragment" in notes[8]
    assert not crown_outliers(trees.head(3)).str.len().any()  # too few trees to judge
    assert not crown_outliers(trees.drop(index=[3, 8])).str.len().any()
    # Rows of six or more trees are their own reference: a younger row is not flagged, a
    # merge in it is; trees in no row and short rows are compared with all trees.
    young = pd.DataFrame(
        {
            "row": [0] * 8 + [1] * 8 + [-1, 2, 2],
            "crown_diameter_m": [4.0] * 8 + [1.8] * 7 + [3.7, 4.2, 3.9, 9.0],
        }
    )
    flagged = [i for i, n in enumerate(crown_outliers(young)) if n]
    assert flagged == [15, 18] and "its row" in crown_outliers(young)[15]
    assert "all trees" in crown_outliers(young)[18]

    # A small crown over a trunk of its own is a small (young, replanted) tree; one with no
    # trunk, or over two, is still suspect.
    replanted = trees.assign(n_trunks=1)
    replanted.loc[3, "n_trunks"] = 2
    assert [i for i, n in enumerate(crown_outliers(replanted)) if n] == [3]
    for trunks in (0, 2):
        piece = replanted.assign(n_trunks=1)
        piece.loc[8, "n_trunks"] = trunks
        assert "fragment" in crown_outliers(piece)[8]


def test_crowns_reaching_max_canopy_height_are_named_in_a_warning() -> None:
    """Crowns 3.9 m tall under a 3.5 m ceiling: every tree is named as cut, with the setting
    to raise; with the ceiling from the data (default), no warning; points above the ceiling
    outside every crown (a wire) are not counted."""
    orch = synthetic_orchard(rows=1, trees_per_row=3)
    low = segment(orch.cloud, "adaptive", PreprocessConfig(max_canopy_height=3.5))
    cut = [w for w in low.warnings if "max_canopy_height" in w]
    assert len(cut) == 1 and cut[0].startswith("3 tree(s) reach preprocess.max_canopy_height")
    assert all(t.tree_id in cut[0] for t in low.trees)
    assert low.summary()["carried_warnings"] == cut  # its check carries it (results.checks)
    assert not [w for w in segment(orch.cloud, "adaptive").warnings if "max_canopy_height" in w]
    # a wire above the ceiling beside the row, outside every crown: the same points counted
    wire = np.column_stack([np.linspace(-3, 13, 400), np.full(400, 3.0), np.full(400, 4.5)])
    with_wire = PointCloud(np.vstack([orch.cloud.xyz, wire]), crs=orch.cloud.crs)
    again = segment(with_wire, "adaptive", PreprocessConfig(max_canopy_height=3.5))
    assert [w for w in again.warnings if "max_canopy_height" in w] == cut


def test_tall_crowns_are_kept_whole_and_a_set_limit_below_them_warns() -> None:
    """Trees 18 m tall (crowns 2-18 m, walnut- or pine-like heights): the default canopy band
    follows the data and keeps every crown whole (tops at the true 18 m, volumes uncut), while
    an overhead wire 3 m clear above the tops is left out; a user's 12 m limit names every
    tree as cut."""
    from canopy_kit.segment.preprocess import canopy_ceiling

    orch = synthetic_orchard(
        rows=1, trees_per_row=3, crown_radius=2.0, crown_aspect=4.0, crown_base=2.0, spacing=5.0
    )
    true_top = 2.0 + 2 * 4.0 * 2.0  # crown base + height
    tops = [orch.cloud.xyz[orch.cloud.fields["tree_id"] == k, 2].max() for k in range(3)]
    wire = np.column_stack([np.linspace(-4, 14, 600), np.full(600, 0.5), np.full(600, 21.0)])
    cloud = PointCloud(np.vstack([orch.cloud.xyz, wire]), crs=orch.cloud.crs)
    seg = segment(cloud, "adaptive")
    assert len(seg.trees) == 3
    for tree, top in zip(sorted(seg.trees, key=lambda t: t.tree_id), tops, strict=True):
        assert abs(tree.crown_top_height_m - top) < 0.1 and top > true_top - 0.4
    assert not [w for w in seg.warnings if "max_canopy_height" in w]
    height = seg.height
    assert np.all(seg.labels[height > 20.0] == -1)  # the wire is no tree's
    assert canopy_ceiling(height, 0.8) < 19.0
    # a corrupt point 1e9 m up neither sizes the height bins nor moves the ceiling
    wild = np.r_[height, 1e9]
    assert canopy_ceiling(wild, 0.8) == canopy_ceiling(height, 0.8)
    limited = segment(cloud, "adaptive", PreprocessConfig(max_canopy_height=12.0))
    cut = [w for w in limited.warnings if "max_canopy_height" in w]
    assert len(cut) == 1 and cut[0].startswith("3 tree(s) reach preprocess.max_canopy_height = 12")


def test_crowns_reaching_the_maps_edge_are_named() -> None:
    """A whole orchard scanned with ground 6 m round it: no crown at the map's edge; the
    same map clipped through the last tree (a plot cut from a larger scan): that tree, and
    only it, reaches the edge."""
    from canopy_kit.segment.layout import crowns_at_map_edge

    orch = synthetic_orchard(rows=1, trees_per_row=3)
    seg = segment(orch.cloud, "adaptive")
    assert crowns_at_map_edge(orch.cloud.xyz[:, :2], seg) == ()
    y_last = orch.centres[-1, 1]
    keep = orch.cloud.xyz[:, 1] < y_last  # the scan ends half way through the last crown
    clipped = PointCloud(orch.cloud.xyz[keep], crs=orch.cloud.crs)
    cut = segment(clipped, "adaptive")
    last = max(cut.trees, key=lambda t: t.y)
    assert crowns_at_map_edge(clipped.xyz[:, :2], cut) == (last.tree_id,)
