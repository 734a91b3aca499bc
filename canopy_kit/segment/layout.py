"""The planting layout measured from the map alone: row spacing, tree spacing along the row
and the trunks each segment holds.

Trunks are found in the stem band of the whole map (``segment.stems``), whatever segmenter
ran, so they are a count of trees that does not depend on the segmentation: a segment that
holds several trunks, or whose crown spans several trunk spacings, holds several trees.
The tree spacing comes from consecutive trunks along each fitted row; without trunks it
falls back to consecutive segment centres (which a merge inflates: say so in ``source``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from canopy_kit.segment.rows import RowAssignment
from canopy_kit.segment.stems import StemDetections, detect_stems

MIN_GAP = 0.8  # metres: closer trunks are one tree (segment.stems merge_distance)


@dataclass(frozen=True)
class Layout:
    """Spacings (NaN when unknown) and the trunks found, with the segment each stands in."""

    row_spacing_m: float
    tree_spacing_m: float
    tree_spacing_source: str  # "trunks", "segments" or "none"
    stems: StemDetections
    stem_segment: np.ndarray  # per trunk: segment id, -1 under no segment
    at_map_edge: tuple[str, ...] = ()  # trees whose crown reaches the map's edge (cut there?)

    def trunks_per_segment(self, segment_ids: np.ndarray) -> np.ndarray:
        """Number of detected trunks under each of ``segment_ids``."""
        ids = np.asarray(segment_ids, dtype=np.int64)
        inside = self.stem_segment[self.stem_segment >= 0]
        counts = np.bincount(inside, minlength=int(ids.max()) + 1 if len(ids) else 0)
        return counts[ids] if len(ids) else np.zeros(0, int)

    def as_dict(self) -> dict[str, Any]:
        """Plain data for metrics.json."""

        def num(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {
            "row_spacing_m": num(self.row_spacing_m),
            "tree_spacing_m": num(self.tree_spacing_m),
            "tree_spacing_source": self.tree_spacing_source,
            "trunks": len(self.stems),
            "trunks_under_a_segment": int((self.stem_segment >= 0).sum()),
            "trees_at_map_edge": list(self.at_map_edge),
        }


def row_spacing(rows: RowAssignment) -> float:
    """Median distance between neighbouring fitted rows (NaN with fewer than two rows)."""
    if len(rows.lines) < 2:
        return float("nan")
    along = float(np.mean([0.5 * sum(line.along_range) for line in rows.lines]))
    # offset() of a point on the row axis (across = 0) is minus the row's position across it
    offsets = np.sort([-line.offset(along * line.direction)[0] for line in rows.lines])
    gaps = np.diff(offsets)
    gaps = gaps[gaps > MIN_GAP]
    return float(np.median(gaps)) if len(gaps) else float("nan")


def spacing_along_rows(xy: np.ndarray, rows: RowAssignment, max_offset: float = 1.5) -> float:
    """Median gap between consecutive points ``xy`` along each fitted row (points within
    ``max_offset`` of it); NaN when no row holds two points."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    gaps: list[np.ndarray] = []
    for line in rows.lines:
        near = np.abs(line.offset(xy)) <= max_offset if len(xy) else np.zeros(0, bool)
        along = np.sort(xy[near] @ line.direction)
        step = np.diff(along)
        gaps.append(step[step > MIN_GAP])
    gaps_all = np.concatenate(gaps) if gaps else np.zeros(0)
    return float(np.median(gaps_all)) if len(gaps_all) else float("nan")


def stems_under_segments(
    stems: StemDetections, footprints: dict[int, np.ndarray], centres: dict[int, np.ndarray]
) -> np.ndarray:
    """The segment whose footprint (convex hull) holds each trunk, the nearest centre of
    those when several overlap; -1 under none."""
    from matplotlib.path import Path

    out = np.full(len(stems), -1, dtype=np.int64)
    if not len(stems) or not footprints:
        return out
    ids = np.array(sorted(footprints))
    inside = np.array(
        [
            Path(footprints[s]).contains_points(stems.xy)
            if len(footprints[s]) >= 3
            else np.zeros(len(stems), bool)
            for s in ids
        ]
    )  # (segments, trunks)
    centre = np.array([centres[s] for s in ids])
    dist = np.linalg.norm(stems.xy[None, :, :] - centre[:, None, :], axis=2)
    dist[~inside] = np.inf
    best = np.argmin(dist, axis=0)
    hit = np.isfinite(dist[best, np.arange(len(stems))])
    out[hit] = ids[best[hit]]
    return out


def measure_layout(
    xyz: np.ndarray,
    height: np.ndarray,
    segmentation: Any,
    stem_band: tuple[float, float] = (0.3, 0.8),
) -> Layout:
    """The layout of a segmented map: map points ``xyz`` with their ``height`` above ground."""
    band = (height >= stem_band[0]) & (height < stem_band[1])
    stem_xyz = np.column_stack([xyz[band, :2], height[band]])
    stems = detect_stems(stem_xyz)
    rows = segmentation.rows
    centres = {t.segment_id: np.array([t.x, t.y]) for t in segmentation.trees}
    owner = stems_under_segments(stems, segmentation.footprints, centres)
    spacing, source = spacing_along_rows(stems.xy, rows), "trunks"
    if not np.isfinite(spacing):
        xy = np.array(list(centres.values())).reshape(-1, 2)
        spacing, source = spacing_along_rows(xy, rows), "segments"
    if not np.isfinite(spacing):
        source = "none"
    edge = crowns_at_map_edge(xyz[:, :2], segmentation)
    return Layout(row_spacing(rows), spacing, source, stems, owner, edge)


EDGE_DISTANCE_M = 0.5  # a crown this close to the map's outline may run on beyond it
EDGE_SAMPLE = 200_000  # map points the outline is drawn round (a hull needs few)


def crowns_at_map_edge(
    xy: np.ndarray, segmentation: Any, distance: float = EDGE_DISTANCE_M
) -> tuple[str, ...]:
    """The trees whose crown footprint comes within ``distance`` of the map's outline (the
    convex hull of its points, seen from above): the map may end inside them, cutting their
    crowns and volumes (a plot clipped from a larger scan, a drive that stopped short)."""
    from scipy.spatial import ConvexHull, QhullError

    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 3 or not segmentation.trees:
        return ()
    step = max(1, len(xy) // EDGE_SAMPLE)
    try:
        hull = ConvexHull(xy[::step])
    except QhullError:
        return ()
    # Hull facets as a·p + b <= 0 inside; -(a·p + b) is the distance to each edge's line.
    normals, offsets = hull.equations[:, :2], hull.equations[:, 2]
    names = []
    for tree in segmentation.trees:
        ring = segmentation.footprints.get(tree.segment_id)
        if ring is None or not len(ring):
            continue
        inside = -(np.asarray(ring) @ normals.T + offsets)  # (vertices, edges)
        if float(inside.min()) < distance:
            names.append(tree.tree_id)
    return tuple(names)
