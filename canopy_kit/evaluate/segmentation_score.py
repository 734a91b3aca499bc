"""Scoring a segmentation against truth: per-tree success, over/under-segmentation, labels.

A true tree is correctly segmented when exactly one predicted segment matches it one to
one with IoU >= ``min_iou`` (0.5): point IoU when the map carries per-point truth labels,
else the IoU of the crown footprints in the horizontal plane. With IoU > 0.5 a match is
necessarily unique; matches are still made greedily by decreasing IoU, one to one.

Failures are classified from the overlap of each true tree with the segments:
``merged`` (under-segmentation: its best segment is also the best segment of another true
tree), ``split`` (over-segmentation: two or more segments each hold at least
``min_fraction`` of its points and have it as their main tree), ``missed`` (no segment
holds ``min_fraction`` of it), ``other`` (poorly delineated).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.errors import InputError

STATUSES = ("correct", "merged", "split", "missed", "other")


@dataclass
class SegmentationScore:
    """Scores of one segmentation; ``trees`` has one row per true tree."""

    mode: str  # "points" or "footprints"
    n_truth: int
    n_predicted: int
    n_correct: int
    n_merged: int
    n_split: int
    n_missed: int
    n_other: int
    n_false_segments: int
    n_label_correct: int
    trees: pd.DataFrame = field(repr=False)
    min_iou: float = 0.5

    @property
    def success_rate(self) -> float:
        """Fraction of true trees correctly segmented (the paper's figure)."""
        return self.n_correct / self.n_truth if self.n_truth else 0.0

    @property
    def precision(self) -> float:
        return self.n_correct / self.n_predicted if self.n_predicted else 0.0

    @property
    def recall(self) -> float:
        return self.success_rate

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r else 0.0

    @property
    def label_accuracy(self) -> float:
        """Among correctly segmented trees, the fraction with the true row and label."""
        return self.n_label_correct / self.n_correct if self.n_correct else 0.0

    def failures(self) -> dict[str, int]:
        """Trees not correctly segmented, lowest IoU first, as ``{description: truth id}``
        (e.g. ``"tree 7 (r0-L3): merged, IoU 0.31"``), for a picker."""
        bad = self.trees[self.trees["status"] != "correct"].sort_values(
            ["iou", "truth_id"], kind="stable"
        )
        out = {}
        for row in bad.to_dict("records"):
            label = row.get("truth_label")
            where = (
                f" (r{int(row['truth_row'])}-{label})"
                if isinstance(label, str) and pd.notna(row.get("truth_row"))
                else ""
            )
            out[f"tree {row['truth_id']}{where}: {row['status']}, IoU {row['iou']:.2f}"] = int(
                row["truth_id"]
            )
        return out

    def only(self, truth_ids: Any) -> SegmentationScore:
        """This score with its per-tree table cut to ``truth_ids`` (counts unchanged): to
        show a few trees, e.g. one failure at a time."""
        from dataclasses import replace

        keep = self.trees["truth_id"].isin(list(np.atleast_1d(truth_ids)))
        return replace(self, trees=self.trees[keep].reset_index(drop=True))

    def to_dict(self) -> dict[str, Any]:
        """Plain numbers (for JSON), without the per-tree table."""
        return {
            "mode": self.mode,
            "min_iou": self.min_iou,
            "n_truth": self.n_truth,
            "n_predicted": self.n_predicted,
            "n_correct": self.n_correct,
            "success_rate": self.success_rate,
            "precision": self.precision,
            "recall": self.recall,
            "f1": self.f1,
            "n_merged": self.n_merged,
            "n_split": self.n_split,
            "n_missed": self.n_missed,
            "n_other": self.n_other,
            "n_false_segments": self.n_false_segments,
            "n_label_correct": self.n_label_correct,
            "label_accuracy": self.label_accuracy,
        }


def _match(iou: np.ndarray, min_iou: float) -> np.ndarray:
    """Greedy one-to-one matching by decreasing IoU: segment index per truth (-1 none)."""
    match = np.full(iou.shape[0], -1, dtype=np.int64)
    if iou.size == 0:
        return match
    t_idx, s_idx = np.nonzero(iou >= min_iou)
    used_t, used_s = set(), set()
    for k in np.argsort(-iou[t_idx, s_idx], kind="stable"):
        t, s = int(t_idx[k]), int(s_idx[k])
        if t not in used_t and s not in used_s:
            match[t] = s
            used_t.add(t)
            used_s.add(s)
    return match


def _classify(
    overlap: np.ndarray, truth_size: np.ndarray, match: np.ndarray, min_fraction: float
) -> list[str]:
    """Failure class of each true tree from the overlap matrix (truth x segments)."""
    n_t, n_s = overlap.shape
    best_seg = overlap.argmax(axis=1) if n_s else np.full(n_t, -1)
    best_tree = overlap.argmax(axis=0) if n_t else np.zeros(0, int)
    out = []
    for t in range(n_t):
        if match[t] >= 0:
            out.append("correct")
            continue
        frac = overlap[t] / max(truth_size[t], 1)
        if n_s == 0 or frac.max() < min_fraction:
            out.append("missed")
            continue
        s = best_seg[t]
        shared = [
            u
            for u in range(n_t)
            if u != t and best_seg[u] == s and overlap[u, s] >= min_fraction * truth_size[u]
        ]
        pieces = np.flatnonzero((best_tree == t) & (frac >= min_fraction))
        if shared:
            out.append("merged")
        elif len(pieces) >= 2:
            out.append("split")
        else:
            out.append("other")
    return out


def _score(
    overlap: np.ndarray,
    truth_size: np.ndarray,
    pred_size: np.ndarray,
    truth_ids: np.ndarray,
    pred_ids: np.ndarray,
    mode: str,
    min_iou: float,
    min_fraction: float,
    truth_labels: pd.DataFrame | None,
    pred_labels: pd.DataFrame | None,
) -> SegmentationScore:
    union = truth_size[:, None] + pred_size[None, :] - overlap
    iou = np.where(union > 0, overlap / np.maximum(union, 1e-12), 0.0)
    match = _match(iou, min_iou)
    status = _classify(overlap, truth_size, match, min_fraction)
    rows = []
    n_label = 0
    for t, tid in enumerate(truth_ids):
        s = match[t]
        best = int(iou[t].argmax()) if iou.shape[1] else -1
        row: dict[str, Any] = {
            "truth_id": int(tid),
            "status": status[t],
            "segment_id": int(pred_ids[s]) if s >= 0 else -1,
            "iou": float(iou[t, s]) if s >= 0 else (float(iou[t, best]) if best >= 0 else 0.0),
            "best_segment_id": int(pred_ids[best]) if best >= 0 else -1,
        }
        if truth_labels is not None and tid in truth_labels.index:
            row["truth_row"] = int(truth_labels.loc[tid, "row"])
            row["truth_label"] = str(truth_labels.loc[tid, "label"])
        if pred_labels is not None and s >= 0 and pred_ids[s] in pred_labels.index:
            row["pred_row"] = int(pred_labels.loc[pred_ids[s], "row"])
            row["pred_label"] = str(pred_labels.loc[pred_ids[s], "label"])
            if "truth_row" in row and (row["pred_row"], row["pred_label"]) == (
                row["truth_row"],
                row["truth_label"],
            ):
                n_label += 1
        rows.append(row)
    trees = pd.DataFrame(rows)
    dominant = overlap.max(axis=0) if overlap.shape[0] else np.zeros(overlap.shape[1])
    n_false = int(np.sum(dominant < 0.5 * np.maximum(pred_size, 1)))
    counts = {s: status.count(s) for s in STATUSES}
    return SegmentationScore(
        mode,
        len(truth_ids),
        len(pred_ids),
        counts["correct"],
        counts["merged"],
        counts["split"],
        counts["missed"],
        counts["other"],
        n_false,
        n_label,
        trees,
        min_iou,
    )


def score_point_labels(
    predicted: np.ndarray,
    truth: np.ndarray,
    min_iou: float = 0.5,
    min_fraction: float = 0.1,
    truth_labels: pd.DataFrame | None = None,
    pred_labels: pd.DataFrame | None = None,
) -> SegmentationScore:
    """Score per-point predicted segment ids against per-point true tree ids (-1 = none).

    ``truth_labels`` / ``pred_labels``: tables indexed by tree id / segment id with
    ``row`` and ``label`` columns, for the label check.
    """
    predicted = np.asarray(predicted).astype(np.int64).ravel()
    truth = np.asarray(truth).astype(np.int64).ravel()
    if predicted.shape != truth.shape:
        raise InputError(f"{len(predicted)} predicted labels for {len(truth)} truth labels")
    truth_ids, t_inv = np.unique(truth, return_inverse=True)
    pred_ids, p_inv = np.unique(predicted, return_inverse=True)
    keep_t, keep_p = truth_ids >= 0, pred_ids >= 0
    t_map = np.cumsum(keep_t) - 1
    p_map = np.cumsum(keep_p) - 1
    ti, pi = t_map[t_inv.ravel()], p_map[p_inv.ravel()]
    has_t, has_p = truth[...] >= 0, predicted >= 0
    n_t, n_p = int(keep_t.sum()), int(keep_p.sum())
    overlap = np.zeros((n_t, n_p))
    both = has_t & has_p
    np.add.at(overlap, (ti[both], pi[both]), 1.0)
    truth_size = np.bincount(ti[has_t], minlength=n_t).astype(float)
    pred_size = np.bincount(pi[has_p], minlength=n_p).astype(float)
    return _score(
        overlap,
        truth_size,
        pred_size,
        truth_ids[keep_t],
        pred_ids[keep_p],
        "points",
        min_iou,
        min_fraction,
        truth_labels,
        pred_labels,
    )


def polygon_mask(
    poly: np.ndarray, origin: np.ndarray, shape: tuple[int, int], cell: float
) -> np.ndarray:
    """Boolean raster of a polygon (M, 2) on a grid with lower-left ``origin``."""
    from skimage.draw import polygon

    mask = np.zeros(shape, bool)
    if len(poly) >= 3:
        rr, cc = polygon((poly[:, 0] - origin[0]) / cell, (poly[:, 1] - origin[1]) / cell, shape)
        mask[rr, cc] = True
    return mask


def score_footprints(
    predicted: dict[int, np.ndarray],
    truth: dict[int, np.ndarray],
    min_iou: float = 0.5,
    min_fraction: float = 0.1,
    cell: float = 0.05,
    truth_labels: pd.DataFrame | None = None,
    pred_labels: pd.DataFrame | None = None,
) -> SegmentationScore:
    """Score predicted crown footprints against true ones (polygons in the same frame)."""
    t_ids = np.array(sorted(truth), dtype=np.int64)
    p_ids = np.array(sorted(predicted), dtype=np.int64)
    polys = [truth[i] for i in t_ids] + [predicted[i] for i in p_ids]
    pts = np.concatenate([p for p in polys if len(p)]) if polys else np.zeros((0, 2))
    if len(pts) == 0:
        return _score(
            np.zeros((len(t_ids), len(p_ids))),
            np.zeros(len(t_ids)),
            np.zeros(len(p_ids)),
            t_ids,
            p_ids,
            "footprints",
            min_iou,
            min_fraction,
            truth_labels,
            pred_labels,
        )
    lo = pts.min(axis=0) - cell
    shape = tuple(np.ceil((pts.max(axis=0) + cell - lo) / cell).astype(int) + 1)
    # One label raster per side would lose overlaps between true crowns; keep sparse masks.
    t_masks = [np.flatnonzero(polygon_mask(truth[i], lo, shape, cell)) for i in t_ids]
    p_masks = [np.flatnonzero(polygon_mask(predicted[i], lo, shape, cell)) for i in p_ids]
    overlap = np.zeros((len(t_ids), len(p_ids)))
    p_centres = [p.mean(axis=0) if len(p) else np.zeros(2) for p in (predicted[i] for i in p_ids)]
    for a, tm in enumerate(t_masks):
        tc = truth[t_ids[a]].mean(axis=0)
        reach = np.ptp(truth[t_ids[a]], axis=0).max() if len(truth[t_ids[a]]) else 0
        for b, pm in enumerate(p_masks):
            pr = np.ptp(predicted[p_ids[b]], axis=0).max() if len(predicted[p_ids[b]]) else 0
            if np.linalg.norm(p_centres[b] - tc) <= reach + pr:
                overlap[a, b] = len(np.intersect1d(tm, pm, assume_unique=True))
    area = cell * cell
    return _score(
        overlap * area,
        np.array([len(m) for m in t_masks]) * area,
        np.array([len(m) for m in p_masks]) * area,
        t_ids,
        p_ids,
        "footprints",
        min_iou,
        min_fraction,
        truth_labels,
        pred_labels,
    )


def truth_footprints(sim_dir: str | Path) -> dict[int, np.ndarray]:
    """Exact crown footprints of a simulated session, regenerated from its stored config;
    discs of the mean crown diameter from ``trees.csv`` when it cannot be regenerated."""
    from canopy_kit.evaluate.truth import load_truth

    truth = load_truth(sim_dir)
    try:
        orchard = truth.orchard()
        return {t.tree_id: t.crown.footprint() for t in orchard.trees}
    except Exception:
        ang = np.linspace(0, 2 * np.pi, 72, endpoint=False)
        out = {}
        for _, r in truth.trees.iterrows():
            rad = 0.5 * float(r["crown_diameter_mean_m"])
            out[int(r["tree_id"])] = np.column_stack(
                [r["crown_x"] + rad * np.cos(ang), r["crown_y"] + rad * np.sin(ang)]
            )
        return out


def envelope_ceiling(xyz: np.ndarray, sim_dir: str | Path, min_height: float = 0.8) -> np.ndarray:
    """Per-point tree ids from the simulator's exact crown envelopes: an upper bound.

    Each point at least ``min_height`` above the true terrain goes to the crown that holds
    it deepest towards its own shell (foliage is densest there), or, outside every crown,
    to the crown it is relatively closest to. Where crowns interweave, no segmenter that
    sees only point positions can do much better; scoring these labels shows the ceiling
    a session allows.
    """
    from canopy_kit.evaluate.truth import load_truth

    orchard = load_truth(sim_dir).orchard()
    xyz = np.asarray(xyz, dtype=np.float64)
    out = np.full(len(xyz), -1, dtype=np.int64)
    hag = xyz[:, 2] - orchard.terrain.height(xyz[:, 0], xyz[:, 1])
    idx = np.flatnonzero(hag >= min_height)
    if len(idx) == 0 or not orchard.trees:
        return out
    p = xyz[idx]
    depth = np.full((len(p), len(orchard.trees)), np.inf)
    for k, tree in enumerate(orchard.trees):
        a = max(tree.crown.semi_axes) * 1.6
        near = np.all(np.abs(p[:, :2] - np.asarray(tree.crown.center[:2])) <= a, axis=1)
        depth[near, k] = tree.crown.relative_depth(p[near])
    inside = np.where(depth <= 1.02, depth, -np.inf)
    has_inside = np.isfinite(inside.max(axis=1))
    best = np.where(has_inside, inside.argmax(axis=1), depth.argmin(axis=1))
    ids = np.array([t.tree_id for t in orchard.trees])
    near_any = has_inside | (depth.min(axis=1) <= 1.5)
    out[idx[near_any]] = ids[best[near_any]]
    return out


def evaluate_run(
    run_dir: str | Path, sim_dir: str | Path, min_iou: float = 0.5, mode: str = "auto"
) -> SegmentationScore:
    """Score a ``canopy-kit segment`` or ``canopy-kit run`` folder against a simulated session's truth.

    ``mode``: ``points`` (needs the truth field ``truth_tree_id`` in the segmented map),
    ``footprints``, or ``auto`` (points when possible).
    """
    from canopy_kit.evaluate.truth import load_truth
    from canopy_kit.segment.export import read_segmentation
    from canopy_kit.segment.labelled import truth_ids

    if mode not in ("auto", "points", "footprints"):
        raise InputError(f"evaluation mode must be auto, points or footprints, got {mode!r}")
    run = read_segmentation(run_dir, with_cloud=mode != "footprints")
    truth = load_truth(sim_dir)
    truth_labels = truth.trees.set_index("tree_id")[["row", "label"]]
    pred_labels = run.trees.set_index("segment_id")[["row", "label"]]
    shift = _frame_shift(run.summary, truth.frame.origin, truth.frame.crs)
    truth_field = truth_ids(run.cloud) if run.cloud is not None else None
    if mode == "points" or (mode == "auto" and truth_field is not None):
        if truth_field is None:
            raise InputError(
                f"{run_dir}: the segmented map has no per-point truth field "
                "'truth_tree_id'; use footprints mode"
            )
        observed = set(np.unique(truth_field[truth_field >= 0]).tolist())
        labels = truth_labels.loc[sorted(observed & set(truth_labels.index))]
        return score_point_labels(
            run.cloud.fields["segment_id"],
            truth_field,
            min_iou,
            truth_labels=labels,
            pred_labels=pred_labels,
        )
    pred = {k: v + shift for k, v in run.footprints.items()}
    return score_footprints(
        pred, truth_footprints(sim_dir), min_iou, truth_labels=truth_labels, pred_labels=pred_labels
    )


def _frame_shift(summary: dict[str, Any], truth_origin: np.ndarray, truth_crs: str) -> np.ndarray:
    """xy offset from the run's local frame to the truth's (same CRS required)."""
    crs = summary.get("crs")
    origin = np.asarray(summary.get("origin", [0, 0, 0]), float)
    if crs and truth_crs and crs != truth_crs:
        raise InputError(f"segmentation CRS {crs} differs from the truth's {truth_crs}")
    return (origin - np.asarray(truth_origin, float))[:2]
