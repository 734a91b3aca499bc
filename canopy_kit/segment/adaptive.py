"""``adaptive``: our segmenter, the same settings for separated and for interwoven crowns.

The paper splits DBSCAN clusters into ``round(size / 45000)`` parts: a constant that has to
be tuned per orchard and swings the result. Here the number of trees in a canopy cluster
and where they stand are read from the data:

1. the canopy falls apart into connected parts at a link distance derived from the point
   spacing; tiny parts are crumbs of a nearby crown;
2. trunks are detected in the stem band under the canopy (``segment.stems``); each trunk
   standing under a part is one tree of it;
3. the typical tree spacing is the median distance between neighbouring trunks (or, with
   too few trunks, the along-row length of parts that hold one tree), and a part's
   along-row mass profile has one bump per crown: where trunks are missing (occlusion,
   a sensor with a narrow field of view), bumps of the profile fill in the trees (gaps
   between trunks much longer than the spacing, parts without trunks much longer than a
   tree);
4. the part is split among its trees by assigning each point to the nearest tree centre,
   the centres starting at the trunks and moving to the crowns' centroids (crowns lean).

Every length is derived from the point spacing and the detected trunks and spacing; no
parameter is set per orchard.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from canopy_kit.segment.base import Segmenter, check_points, check_weight
from canopy_kit.segment.density import first_appearance_order, grid_dbscan
from canopy_kit.segment.profile import along_axis, profile_peaks
from canopy_kit.segment.stems import StemDetections, detect_stems, no_stems


def point_spacing(xyz: np.ndarray, k: int = 4, sample: int = 20000, seed: int = 0) -> float:
    """Typical point spacing: the median distance to the ``k``-th nearest neighbour.

    (The nearest neighbour alone understates it: voxel representatives pair up across
    voxel faces.)
    """
    if len(xyz) <= k:
        return 0.1
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(xyz), min(sample, len(xyz)), replace=False)
    d, _ = cKDTree(xyz).query(xyz[idx], k=k + 1)
    return float(np.median(d[:, k]))


def connected_parts(xyz: np.ndarray, link: float, weight: np.ndarray | None = None) -> np.ndarray:
    """Labels of the parts that chains of points at most ``link`` apart connect."""
    labels, _ = grid_dbscan(xyz, link, 0.0, weight, cell=link / 2.0)
    return labels


class AdaptiveSegmenter(Segmenter):
    """Trees from canopy parts, trunks and crown profiles (see the module docstring).

    ``link_factor``: parts are linked at this many point spacings. ``crumb_fraction``:
    parts lighter than this fraction of a typical tree are crumbs, merged into the nearest
    part within ``crumb_reach`` typical spacings. ``use_stems``: use trunk detections
    when stem points are given. The remaining settings are ratios to the detected tree
    spacing and are not orchard-specific.
    """

    def __init__(self, link_factor: float = 2.0, crumb_fraction: float = 0.1,
                 crumb_reach: float = 0.25, use_stems: bool = True,
                 gap_ratio: float = 1.6, min_peak_ratio: float = 0.55,
                 stem_search_radius: float = 1.0, refine_iterations: int = 3,
                 random_state: int = 0) -> None:
        self.link_factor = link_factor
        self.crumb_fraction = crumb_fraction
        self.crumb_reach = crumb_reach
        self.use_stems = use_stems
        self.gap_ratio = gap_ratio
        self.min_peak_ratio = min_peak_ratio
        self.stem_search_radius = stem_search_radius
        self.refine_iterations = refine_iterations
        self.random_state = random_state

    # ------------------------------------------------------------------------------------
    def fit(self, X: np.ndarray, y: None = None, sample_weight: np.ndarray | None = None,  # noqa: N803
            stem_xyz: np.ndarray | None = None) -> "AdaptiveSegmenter":
        """Segment canopy points ``X`` (x, y, height above ground); sets ``labels_`` etc."""
        xyz = check_points(X)
        w = check_weight(sample_weight, len(xyz))
        n = len(xyz)
        self.labels_ = np.full(n, -1, dtype=np.int64)
        self.stems_ = no_stems()
        self.markers_ = np.zeros((0, 2))
        if n == 0:
            self.n_clusters_ = 0
            return self
        self.point_spacing_ = point_spacing(xyz, seed=self.random_state)
        self.link_distance_ = self.link_factor * self.point_spacing_
        parts = connected_parts(xyz, self.link_distance_, w)
        stems = detect_stems(stem_xyz) if (self.use_stems and stem_xyz is not None) else no_stems()
        stem_part = self._stems_to_parts(xyz, w, parts, stems)
        keep = stem_part >= 0
        stems = StemDetections(stems.xy[keep], stems.n_points[keep], stems.radius[keep],
                               stems.coverage[keep])
        stem_part = stem_part[keep]
        self.stems_ = stems
        n_parts = int(parts.max()) + 1
        part_weight = np.bincount(parts[parts >= 0], weights=w[parts >= 0], minlength=n_parts)
        stems_per_part = np.bincount(stem_part, minlength=n_parts)
        spacing, tree_weight, tree_length = self._typical_tree(xyz, w, parts, part_weight,
                                                               stems, stem_part, stems_per_part)
        self.tree_spacing_ = spacing
        self.tree_weight_ = tree_weight
        parts = self._merge_crumbs(xyz, w, parts, part_weight, stems_per_part, tree_weight,
                                   spacing)
        labels = np.full(n, -1, dtype=np.int64)
        markers_all = []
        next_label = 0
        for p in np.unique(parts[parts >= 0]):
            members = np.flatnonzero(parts == p)
            own_stems = stems.xy[stem_part == p] if len(stems) else np.zeros((0, 2))
            markers = self._markers(xyz[members], w[members], own_stems, spacing, tree_length)
            sub = self._split(xyz[members], w[members], markers, spacing)
            labels[members] = sub + next_label
            next_label += int(sub.max()) + 1
            markers_all.append(markers)
        self.markers_ = np.concatenate(markers_all) if markers_all else np.zeros((0, 2))
        self.labels_ = first_appearance_order(labels)
        self.n_clusters_ = int(self.labels_.max()) + 1 if n else 0
        return self

    # ------------------------------------------------------------------------------------
    def _stems_to_parts(self, xyz: np.ndarray, w: np.ndarray, parts: np.ndarray,
                        stems: StemDetections) -> np.ndarray:
        """The canopy part above each trunk (-1: no canopy above it, not a tree's trunk)."""
        out = np.full(len(stems), -1, dtype=np.int64)
        if len(stems) == 0:
            return out
        valid = parts >= 0
        tree = cKDTree(xyz[valid, :2])
        vparts = parts[valid]
        vw = w[valid]
        for i, s in enumerate(stems.xy):
            near = tree.query_ball_point(s, self.stem_search_radius)
            if near:
                out[i] = np.bincount(vparts[near], weights=vw[near]).argmax()
        return out

    def _typical_tree(self, xyz: np.ndarray, w: np.ndarray, parts: np.ndarray,
                      part_weight: np.ndarray, stems: StemDetections, stem_part: np.ndarray,
                      stems_per_part: np.ndarray) -> tuple[float, float, float]:
        """Typical spacing between trees, canopy weight and along-row length of one tree."""
        width = self._crown_width(xyz, w, parts, part_weight)
        spacing = np.nan
        if len(stems) >= 3:
            d, _ = cKDTree(stems.xy).query(stems.xy, k=2)
            spacing = float(np.median(d[:, 1]))
        single = np.flatnonzero(stems_per_part == 1)
        if len(single):
            lengths = []
            for p in single[np.argsort(-part_weight[single])][:50]:
                m = parts == p
                a, _ = along_axis(xyz[m, :2], w[m])
                lengths.append(np.percentile(a, 98) - np.percentile(a, 2))
            tree_length = float(np.median(lengths))
        else:
            tree_length = spacing if np.isfinite(spacing) else width
        with_stems = np.flatnonzero(stems_per_part > 0)
        if len(with_stems):
            tree_weight = float(np.median(part_weight[with_stems] / stems_per_part[with_stems]))
        else:
            # Without trunks: the part a typical point lies in, cut into crown-sized pieces.
            order = np.argsort(part_weight)
            cum = np.cumsum(part_weight[order])
            typical = order[np.searchsorted(cum, 0.5 * cum[-1])]
            m = parts == typical
            a, _ = along_axis(xyz[m, :2], w[m])
            pieces = max(1.0, round((np.percentile(a, 98) - np.percentile(a, 2)) / width))
            tree_weight = float(part_weight[typical] / pieces)
        if not np.isfinite(spacing):
            spacing = tree_length
        return spacing, tree_weight, tree_length

    @staticmethod
    def _crown_width(xyz: np.ndarray, w: np.ndarray, parts: np.ndarray,
                     part_weight: np.ndarray) -> float:
        """Across-row width of the heaviest parts: a crown's size when trees merge in rows."""
        widths = []
        for p in np.argsort(-part_weight)[:10]:
            m = parts == p
            if m.sum() < 10:
                continue
            _, across = along_axis(xyz[m, :2], w[m])
            widths.append(np.percentile(across, 98) - np.percentile(across, 2))
        return float(np.median(widths)) if widths else 3.0

    def _merge_crumbs(self, xyz: np.ndarray, w: np.ndarray, parts: np.ndarray,
                      part_weight: np.ndarray, stems_per_part: np.ndarray, tree_weight: float,
                      spacing: float) -> np.ndarray:
        """Parts far lighter than a tree join the nearest real part, or become noise."""
        crumbs = (part_weight < self.crumb_fraction * tree_weight) & (stems_per_part == 0)
        if not crumbs.any():
            return parts
        is_crumb = crumbs[np.maximum(parts, 0)] & (parts >= 0)
        solid = (parts >= 0) & ~is_crumb
        out = parts.copy()
        if not solid.any():
            return out
        dist, nearest = cKDTree(xyz[solid]).query(xyz[is_crumb],
                                                  distance_upper_bound=self.crumb_reach * spacing)
        solid_idx = np.flatnonzero(solid)
        crumb_idx = np.flatnonzero(is_crumb)
        # A crumb joins the part its closest point is nearest to (the whole crumb moves).
        target = np.full(len(part_weight), -1, dtype=np.int64)
        best = np.full(len(part_weight), np.inf)
        cp = parts[crumb_idx]
        for i in np.flatnonzero(np.isfinite(dist)):
            if dist[i] < best[cp[i]]:
                best[cp[i]] = dist[i]
                target[cp[i]] = parts[solid_idx[nearest[i]]]
        out[crumb_idx] = target[cp]
        return out

    def _markers(self, xyz: np.ndarray, w: np.ndarray, stems: np.ndarray, spacing: float,
                 tree_length: float) -> np.ndarray:
        """Tree positions (x, y) in one canopy part: its trunks plus crowns without one."""
        along, _ = along_axis(xyz[:, :2], w)
        axis_origin, axis_dir = _axis_frame(xyz[:, :2], w)
        lo, hi = np.percentile(along, 1), np.percentile(along, 99)
        length = hi - lo
        if len(stems) == 0 and length <= self.gap_ratio * max(tree_length, spacing):
            return np.array([np.average(xyz[:, :2], axis=0, weights=w)])
        peaks = profile_peaks(along, w, self.min_peak_ratio * spacing)
        if len(stems) == 0:
            pos = peaks if len(peaks) else np.array([0.5 * (lo + hi)])
            return axis_origin + pos[:, None] * axis_dir
        s_along = np.sort((stems - axis_origin) @ axis_dir)
        extra = []
        # Long stretches without a trunk (between trunks and beyond the end ones) take
        # the profile's bumps there, at least a spacing's distance from any trunk.
        bounds = np.concatenate([[lo - 0.5 * spacing], s_along, [hi + 0.5 * spacing]])
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - a < self.gap_ratio * spacing:
                continue
            cand = peaks[(peaks > a + self.min_peak_ratio * spacing)
                         & (peaks < b - self.min_peak_ratio * spacing)]
            extra.extend(cand.tolist())
        if extra:
            return np.concatenate([stems, axis_origin + np.array(extra)[:, None] * axis_dir])
        return stems

    def _split(self, xyz: np.ndarray, w: np.ndarray, markers: np.ndarray,
               spacing: float) -> np.ndarray:
        """Assign points to the nearest tree centre; centres move from trunks to crowns."""
        if len(markers) <= 1:
            return np.zeros(len(xyz), dtype=np.int64)
        centres = markers.astype(float).copy()
        xy = xyz[:, :2]
        labels = np.zeros(len(xyz), dtype=np.int64)
        limit = 0.25 * spacing
        for _ in range(max(self.refine_iterations, 0) + 1):
            _, labels = cKDTree(centres).query(xy)
            new = centres.copy()
            for k in range(len(centres)):
                m = labels == k
                if m.any():
                    new[k] = np.average(xy[m], axis=0, weights=w[m])
            move = new - markers
            dist = np.linalg.norm(move, axis=1, keepdims=True)
            centres = markers + move * np.minimum(1.0, limit / np.maximum(dist, 1e-12))
        _, labels = cKDTree(centres).query(xy)
        return first_appearance_order(labels)


def _axis_frame(xy: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from canopy_kit.segment.profile import principal_axis

    return principal_axis(xy, w)
