"""Volume accuracy on trees the pipeline segments: a simulated session's map segmented with a
preset, each matched tree measured by the volume stage, whole and from each alley, against the
simulator's exact crown volume (benchmarks/bench_volume_matrix.py, tests/test_volume_accuracy.py).

A module of its own: it spans segmentation, the volume stage and scoring, which the volume
package itself must not import (tests/test_architecture.py).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.volume.envelope import MEASURANDS as ENVELOPE_MEASURANDS

# what an estimator that chooses its measurand per tree (``foliage_envelope``) may measure
MEASURANDS = tuple(m for m in ENVELOPE_MEASURANDS if m != "auto")


def segmented_session(
    sim_dir: str | Path, config: Any, reference_map: Any = None
) -> tuple[Any, Any, Any, Any]:
    """A simulated session's map (true poses unless ``reference_map`` is given, on map.laz's
    grid) segmented with ``config``'s segmenter as ``canopy-kit run`` does: the truth, the
    map, the segmentation and its score against the simulator's ``tree_id``."""
    from canopy_kit.evaluate.segmentation_score import score_point_labels
    from canopy_kit.evaluate.truth import load_truth
    from canopy_kit.evaluate.truth_map import truth_map
    from canopy_kit.io.las_write import on_las_grid
    from canopy_kit.segment.verb import make_segmenter, segment

    truth = load_truth(sim_dir)
    cloud = on_las_grid(
        reference_map if reference_map is not None else truth_map(sim_dir, voxel_size=0.05)
    )
    seg = segment(
        cloud,
        make_segmenter(config.segment.method, config.segment.params),
        config.preprocess,
        config.rows,
        seed=config.seed,
    )
    return truth, cloud, seg, score_point_labels(seg.labels, np.asarray(cloud.fields["tree_id"]))


def foliage_references(
    truth: Any,
    tree_ids: list[int],
    volume: Any,
    methods: list[str],
    measurands: Mapping[int, Collection[str]] | None = None,
    density: float | None = None,
) -> dict[int, dict[str, float]]:
    """Each method's volume of each tree's complete foliage (every leaf and crown-branch
    surface, seen or not: the world model's :meth:`complete_foliage`), thinned as the volume
    stage thins a tree. An estimator that chooses its measurand per tree
    (``foliage_envelope``) is measured as each of them (``<method>:<measurand>``), or, per
    tree id in ``measurands``, as those named only (the others are not computed).
    ``density``: points per m² of surface (the world model's default when None; any density
    that fills the volume stage's voxels gives the same volumes)."""
    from sklearn.base import clone

    from canopy_kit import plugins
    from canopy_kit.volume.verb import build_estimators, measured_points

    world = truth.world()
    foliage = world.complete_foliage() if density is None else world.complete_foliage(density)
    estimators = build_estimators(volume)
    out: dict[int, dict[str, float]] = {}
    for method in methods:  # an estimator measured beside the run's: its configured parameters
        if method not in estimators:
            estimators[method] = plugins.create("volumes", method, volume.params.get(method, {}))
    for tree_id in tree_ids:
        xyz = measured_points(np.asarray(foliage[tree_id]), volume)
        row = {}
        for method in methods:
            est = estimators[method]
            choices = getattr(est, "measurand", None)
            if choices is None:
                row[method] = _valid_volume(est(xyz))
                continue
            wanted = MEASURANDS if measurands is None else measurands[int(tree_id)]
            for measurand in wanted:
                forced = clone(est).set_params(measurand=measurand)
                row[f"{method}:{measurand}"] = _valid_volume(forced(xyz))
        out[int(tree_id)] = row
    return out


def _valid_volume(result: Any) -> float:
    return float(result.volume_m3) if result.valid else float("nan")


def reference_volume(refs: dict[str, float], method: str, kind: str) -> float:
    """The complete-foliage volume a scan's ``method`` volume is compared with: the measurand
    the scan took (a sparse crown's ellipsoid) for an estimator that chooses one."""
    if method in refs:
        return refs[method]
    from canopy_kit.volume.uncertainty import measurand_of_kind

    return refs.get(f"{method}:{measurand_of_kind(kind)}", np.nan)


def segmented_volume_errors(
    sim_dir: str | Path,
    config: Any,
    methods: list[str],
    reference_map: Any = None,
    reference: str = "envelope",
) -> tuple[Any, Any]:
    """Volume errors on the trees the pipeline segments, as trees.csv measures them.

    The map (true poses unless ``reference_map`` is given) is segmented with ``config``'s
    segmenter; each segment matched one-to-one to a simulated tree (IoU ≥ 0.5) is measured
    by the volume stage with ``config.volume`` whole (scan ``both``) and as a drive along
    one alley alone would have seen it (``left``, ``right``: :func:`one_alley_scans`).
    Returns one row per tree, scan and method (``interval`` rows say whether the recommended
    estimator's interval held the truth) and the segmentation score.

    ``reference``: ``envelope`` compares every method with the simulator's crown envelope
    volume; ``foliage`` with the same method on the tree's complete foliage
    (:func:`foliage_references`): the error the drive and the segmentation made.
    """
    import pandas as pd

    from canopy_kit.volume.verb import measure_trees

    truth, cloud, seg, score = segmented_session(sim_dir, config, reference_map)
    correct = score.trees[score.trees["status"] == "correct"]
    true_id_of = dict(zip(correct["segment_id"], correct["truth_id"], strict=True))
    true_volume = truth.trees.set_index("tree_id")["crown_volume_m3"]
    row_of_tree = truth.trees.set_index("tree_id")["row"]
    row_of_segment = {s: int(row_of_tree[t]) for s, t in true_id_of.items()}
    scans = [
        ("both", cloud, seg.labels),
        *one_alley_scans(sim_dir, cloud, seg.labels, row_of_segment),
    ]
    refs = None
    recommended = config.volume.recommended
    if reference == "foliage":
        measured = list(dict.fromkeys([*methods, recommended]))
        refs = foliage_references(truth, list(true_id_of.values()), config.volume, measured)
    elif reference != "envelope":
        raise ValueError(f"reference must be 'envelope' or 'foliage', got {reference!r}")
    rows = []
    for scan, scan_cloud, labels in scans:
        table = measure_trees(scan_cloud, labels, config.volume, ground_height=seg.ground.height)
        for tree in table.itertuples(index=False):
            true_id = true_id_of.get(int(tree.segment))
            if true_id is None:
                continue
            kind = str(tree.crown_kind)

            def truth_of(method: str, true_id: int = true_id, kind: str = kind) -> float:
                if refs is None:
                    return float(true_volume[true_id])
                return reference_volume(refs[true_id], method, kind)

            rows += _tree_error_rows(tree, scan, int(true_id), methods, recommended, truth_of)
    return pd.DataFrame(rows), score


def _tree_error_rows(
    tree: Any,
    scan: str,
    true_id: int,
    methods: list[str],
    recommended: str,
    truth_of: Callable[[str], float],
) -> list[dict[str, Any]]:
    """One measured tree's rows: each method's volume against its truth (``truth_of``), and
    whether the recommended estimator's interval held its truth (``interval``)."""
    from canopy_kit.volume.verb import volume_column

    base = {"scan": scan, "tree": true_id}
    rows = []
    for method in methods:
        v, t = float(getattr(tree, volume_column(method))), truth_of(method)
        rows.append(
            {**base, "true_volume_m3": t, "method": method, "volume_m3": v, "error": v / t - 1}
        )
    truth_v = truth_of(recommended)
    rows.append(
        {
            **base,
            "true_volume_m3": truth_v,
            "method": "interval",
            "volume_m3": np.nan,
            "error": np.nan,
            "covered": bool(tree.volume_low_m3 <= truth_v <= tree.volume_high_m3),
            "coverage": float(tree.scan_coverage),
            "fill": float(tree.surface_fill),
            "flags": str(tree.volume_interval_flags),
            "kind": str(tree.crown_kind),
        }
    )
    return rows


def one_alley_scans(
    sim_dir: str | Path, cloud: Any, labels: np.ndarray, row_of_segment: dict[int, int]
) -> list[tuple[str, Any, np.ndarray]]:
    """``(scan, map, labels)`` per row and side: the map of that alley's sweeps alone
    (:func:`canopy_kit.evaluate.truth_map.alley_maps`, true poses, on map.laz's grid) with the segment
    labels of ``cloud`` carried to its points (the nearest point of ``cloud`` within 0.1 m),
    kept for the segments of that row (``row_of_segment``) only. ``scan`` is ``left`` or
    ``right`` of the row line."""
    from scipy.spatial import cKDTree

    from canopy_kit.evaluate.truth_map import alley_maps
    from canopy_kit.io.las_write import on_las_grid

    labels = np.asarray(labels)
    index = cKDTree(cloud.xyz)
    out = []
    for (row, side), alley in sorted(alley_maps(sim_dir).items()):
        alley = on_las_grid(alley)
        dist, nearest = index.query(alley.xyz, distance_upper_bound=0.1, workers=-1)
        carried = np.full(len(alley), -1, dtype=labels.dtype)
        found = np.isfinite(dist)
        carried[found] = labels[nearest[found]]
        of_row = np.array([row_of_segment.get(int(s), -1) == row for s in np.unique(carried)])
        carried[~np.isin(carried, np.unique(carried)[of_row])] = -1
        out.append(("left" if side > 0 else "right", alley, carried))
    return out
