"""``segment(cloud, segmenter)``: the verb that owns the bookkeeping around a segmenter.

Preprocess (ground, bands, voxel grid), run the segmenter on height-normalised canopy
points, carry its labels back to every map point, describe each tree, find the rows and
label the trees; a trellis's posts and wires (``segment.trellis_filter``) leave the trees.
The segmenter only does the maths (lidR's verb/algorithm split).
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from canopy_kit import plugins
from canopy_kit.config import PreprocessConfig, RowsConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError, ProcessingError
from canopy_kit.segment.classes import classify_points
from canopy_kit.segment.density import first_appearance_order
from canopy_kit.segment.preprocess import prepare
from canopy_kit.segment.result import Segmentation, TreeRecord
from canopy_kit.segment.rows import assign_rows
from canopy_kit.segment.trellis_filter import trellis_in_segments
from canopy_kit.segment.trunk_feet import TrunkFeet, trunk_feet
from canopy_kit.volume.metrics import horizontal_hull, polygon_area, widest_extents

Progress = Callable[[str, float, float], None]


def make_segmenter(method: str, params: dict[str, Any] | None = None) -> Any:
    """Instantiate the segmenter plugin ``method`` with keyword ``params`` (checked)."""
    return plugins.create("segmenters", method, params, where="segment.params")


def _fit_params(segmenter: Any) -> set[str]:
    try:
        sig = inspect.signature(segmenter.fit)
    except (AttributeError, TypeError, ValueError):
        return set()
    if any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values()):
        return {"sample_weight", "stem_xyz"}
    return set(sig.parameters) & {"sample_weight", "stem_xyz"}


def segment(
    cloud: PointCloud,
    segmenter: Any,
    preprocess_config: PreprocessConfig | None = None,
    rows_config: RowsConfig | None = None,
    driving_direction: np.ndarray | None = None,
    direction_source: str | None = None,
    seed: int = 0,
    progress: Progress | None = None,
) -> Segmentation:
    """Segment a map into trees; labels per point of ``cloud`` plus per-tree records.

    ``segmenter`` is a segmenter object (``DBSCANSegmenter(...)``) or a plugin name.
    ``driving_direction`` (xy vector), e.g. from a trajectory, orders and labels the trees.
    """
    pre = preprocess_config or PreprocessConfig()
    if isinstance(segmenter, str):
        segmenter = make_segmenter(segmenter)
    if not hasattr(segmenter, "fit_predict"):
        raise InputError(f"segmenter {segmenter!r} has no fit_predict(points) method")
    report = progress or (lambda *_: None)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    prepared = prepare(cloud, pre, seed=seed, progress=report)
    timings["preprocess"] = time.perf_counter() - t0
    if len(prepared.canopy_index) == 0:
        band = (
            f"more than {pre.min_canopy_height:g} m above the ground (preprocess.min_canopy_height)"
            if pre.max_canopy_height is None
            else f"{pre.min_canopy_height:g}-{pre.max_canopy_height:g} m above the ground "
            "(preprocess.min_canopy_height/max_canopy_height)"
        )
        raise InputError(f"map has no points {band}: is it all ground?")
    xyz = prepared.normalized(cloud, prepared.seen_index)
    kwargs: dict[str, Any] = {}
    accepted = _fit_params(segmenter)
    if "sample_weight" in accepted:
        kwargs["sample_weight"] = prepared.seen_weight
    if "stem_xyz" in accepted:
        kwargs["stem_xyz"] = prepared.normalized(cloud, prepared.stem_index)
    report("segment", 0, 1)
    t0 = time.perf_counter()
    seen_labels = np.asarray(segmenter.fit_predict(xyz, **kwargs))
    timings["segmenter"] = time.perf_counter() - t0
    report("segment", 1, 1)
    if seen_labels.shape != (len(xyz),):
        raise ProcessingError(
            f"segmenter {type(segmenter).__name__} returned "
            f"{seen_labels.shape} labels for {len(xyz)} points"
        )
    labels = np.full(len(cloud), -1, dtype=np.int64)
    labels[prepared.canopy_index] = seen_labels[prepared.canopy_to_seen]
    labels = first_appearance_order(labels)
    t0 = time.perf_counter()
    describe = (cloud, prepared, segmenter, rows_config, driving_direction, direction_source)
    seg = _describe(labels, *describe)
    # a fruiting wall's posts and wires are no tree (issue 52): the row profile's rule
    segment_row = np.array([t.row for t in sorted(seg.trees, key=lambda t: t.segment_id)])
    trellis = trellis_in_segments(
        cloud.xyz[:, :2], prepared.height, seg.labels, seg.rows, segment_row
    )
    posts = getattr(segmenter, "posts_", None)
    if posts is not None and len(posts):  # the posts found among the trunks, to their tops
        trellis |= (seg.labels >= 0) & posts.on_post(cloud.xyz[:, :2], prepared.height)
    if trellis.any():
        labels = first_appearance_order(np.where(trellis, -1, seg.labels))
        seg = _describe(labels, *describe)
    timings["rows"] = time.perf_counter() - t0
    seg.canopy_band_m = (float(pre.min_canopy_height), float(prepared.ceiling))
    seg.ceiling_source = "data" if pre.max_canopy_height is None else "preprocess.max_canopy_height"
    if pre.max_canopy_height is not None:  # a ceiling from the data stands above a gap
        cut, lost = crowns_cut_at_the_ceiling(
            seg, cloud.xyz[:, :2], prepared.height, prepared.ceiling
        )
        if cut:
            seg.cut_at_ceiling = cut
            seg.ceiling_warning = ceiling_warning(cut, lost, prepared.ceiling)
            seg.warnings.append(seg.ceiling_warning)
    if getattr(segmenter, "cut", None) == "trunk-midpoints" and hasattr(segmenter, "stems_"):
        feet = wall_trunk_feet(seg, cloud.xyz, segmenter.stems_.xy)
        seg.trunk_feet = feet.as_dict()
        if feet.warning:
            seg.warnings.append(feet.warning)
    seg.timings = timings
    seg.classification = classify_points(
        seg.labels, seg.height, pre.ground_ransac_threshold, pre.min_canopy_height
    )
    return seg


def wall_trunk_feet(seg: Segmentation, xyz: np.ndarray, trunks_xy: np.ndarray) -> TrunkFeet:
    """Whether the trunks ``trunks_xy`` of a wall cut at their midpoints are complete, row
    by row (``segment.trunk_feet``), from the map points ``xyz`` and their heights."""
    return trunk_feet(
        xyz,
        seg.height,
        trunks_xy,
        seg.rows,
        [t.tree_id for t in seg.trees],
        np.array([t.row for t in seg.trees], dtype=np.int64),
    )


def crowns_cut_at_the_ceiling(
    seg: Segmentation, xy: np.ndarray, height: np.ndarray, ceiling: float, margin: float = 0.3
) -> tuple[list[str], int]:
    """The trees whose crown reaches ``ceiling`` (``preprocess.max_canopy_height``) while
    map points stand above it inside their footprint (their tops, and volumes, are cut), and
    how many such points were left out. Points above the ceiling elsewhere (wires,
    buildings) are not counted."""
    from matplotlib.path import Path as Polygon

    above = xy[height > ceiling]
    cut: list[str] = []
    lost = 0
    if not len(above):
        return cut, lost
    for tree in seg.trees:
        footprint = seg.footprints.get(tree.segment_id)
        if tree.crown_top_height_m < ceiling - margin or footprint is None or len(footprint) < 3:
            continue
        inside = int(Polygon(footprint).contains_points(above).sum())
        if inside >= MIN_POINTS_ABOVE:
            cut.append(tree.tree_id)
            lost += inside
    return cut, lost


def ceiling_warning(cut: list[str], lost: int, ceiling: float) -> str:
    """The warning naming the trees cut at a set ceiling and the setting to change."""
    return (
        f"{len(cut)} tree(s) reach preprocess.max_canopy_height = {ceiling:g} m and {lost} map "
        f"points above it in their footprints were left out ({', '.join(cut[:8])}"
        f"{', ...' if len(cut) > 8 else ''}): their tops and volumes are cut; raise "
        "max_canopy_height or leave it unset to follow the trees "
        "(--set preprocess.max_canopy_height=...)"
    )


MIN_POINTS_ABOVE = 10  # points above the ceiling in a footprint that make a crown cut


def _describe(
    labels: np.ndarray,
    cloud: PointCloud,
    prepared: Any,
    segmenter: Any,
    rows_config: RowsConfig | None,
    driving_direction: np.ndarray | None,
    direction_source: str | None,
) -> Segmentation:
    n_seg = int(labels.max()) + 1 if len(labels) else 0
    idx = np.flatnonzero(labels >= 0)
    order = idx[np.argsort(labels[idx], kind="stable")]
    bounds = np.searchsorted(labels[order], np.arange(n_seg + 1))
    stats, hulls = [], []
    for s in range(n_seg):
        members = order[bounds[s] : bounds[s + 1]]
        xyz = cloud.xyz[members]
        h = prepared.height[members]
        hull = horizontal_hull(xyz[:, :2])
        stats.append(
            (
                xyz.mean(axis=0),
                len(members),
                float(h.max()),
                float(np.percentile(h, 1)),
                widest_extents(hull)[0],
                polygon_area(hull),
            )
        )
        hulls.append(hull)
    centroids = np.array([s[0][:2] for s in stats]).reshape(-1, 2)
    rows = assign_rows(centroids, rows_config, driving_direction, direction_source)
    # Stable numbering: segment ids follow the (row, index in row) order.
    rank = np.lexsort((rows.index_in_row, rows.row)) if n_seg else np.zeros(0, int)
    new_id = np.empty(n_seg, dtype=np.int64)
    new_id[rank] = np.arange(n_seg)
    out = np.where(labels >= 0, new_id[np.maximum(labels, 0)], -1) if n_seg else labels.copy()
    trees, footprints = [], {}
    tree_ids = rows.tree_ids
    for old in rank:
        c, n, top, base, diam, area = stats[old]
        sid = int(new_id[old])
        trees.append(
            TreeRecord(
                sid,
                tree_ids[old],
                int(rows.row[old]),
                rows.labels[old],
                int(rows.index_in_row[old]),
                float(c[0]),
                float(c[1]),
                float(c[2]),
                int(n),
                top,
                base,
                diam,
                area,
            )
        )
        footprints[sid] = hulls[old]
    params = segmenter.get_params() if hasattr(segmenter, "get_params") else {}
    warnings = list(rows.warnings)
    if n_seg == 0:
        warnings = [
            f"no trees found: the segmenter {type(segmenter).__name__} labelled all "
            f"{len(prepared.seen_index)} canopy points as noise"
        ]
    return Segmentation(
        out,
        trees,
        footprints,
        rows,
        prepared.ground,
        prepared.height,
        type(segmenter).__name__,
        params,
        cloud.crs,
        cloud.origin.copy(),
        warnings,
    )
