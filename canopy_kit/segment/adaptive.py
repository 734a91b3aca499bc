"""``adaptive``: our segmenter, with the same settings for separated and interwoven crowns.

The paper splits a DBSCAN cluster into ``round(size / 45000)`` parts: a constant tuned per
orchard that swings the result. Here the number of trees in a canopy part and where they
stand are read from the data:

1. the canopy falls apart into connected parts at a link distance of a few point spacings
   (measured on the data); parts far lighter than a tree are crumbs of a nearby crown;
2. trunks are detected in the stem band under the canopy (``segment.stems``); a trunk
   with canopy above it is a tree of that canopy part;
3. the scale of one tree is measured, not assumed: the spacing between neighbouring
   trunks, the along-row length and canopy weight of parts holding one trunk (or, without
   trunks, of round isolated parts; or the rows' width);
4. stretches of a part without trunks (occluded or hidden trunks, a sensor that does not
   see low) get as many trees as the measured spacing fits in them, and a part without
   any trunk gets ``round((length - tree length) / spacing) + 1`` trees;
5. points go to the tree whose crown, an ellipsoid fitted to the tree's points, holds
   them closest to its shell (``segment.crowns``: a border that follows a small crown
   sitting half inside a big one), starting from the nearest tree position; crown tops of
   a stand seen from above keep the nearest top (shells need crowns seen from the side).
   With ``cut="trunk-midpoints"`` (fruiting walls and hedgerows, where a tree is defined
   as the wall between the midpoints to its neighbours' trunks) a point goes to the tree
   whose position is nearest along the row instead.

Trellis posts are columns in the stem band like trunks; one standing above the canopy is
left out of the trunks (``segment.posts``).

All lengths derive from the point spacing and the measured tree scale; nothing is set per
orchard.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from canopy_kit.plugins.params import Positive
from canopy_kit.segment.base import Segmenter, check_points, check_weight
from canopy_kit.segment.crowns import crown_split
from canopy_kit.segment.density import first_appearance_order, grid_dbscan
from canopy_kit.segment.posts import no_posts, split_posts
from canopy_kit.segment.profile import along_axis, chm_peaks, chm_spacing, principal_axis
from canopy_kit.segment.stems import StemDetections, detect_stems, no_stems

# Below this many canopy points the parts are split in this process: a forked worker
# costs more than it saves (the dense almond map's 800k crown points: 3.8 → 2.1 s).
PARALLEL_MIN_POINTS = 200_000


def each_part(
    split: Callable[[int], tuple[np.ndarray, np.ndarray]], members: list[np.ndarray]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[split(i) for i in range(len(members))]``, the parts shared among forked workers
    (balanced by their points) when there are many points and more than one core."""
    from canopy_kit.core.parallel import run_jobs, worker_count

    sizes = np.array([len(m) for m in members])
    n_workers = worker_count(0, len(members))
    if n_workers <= 1 or sizes.sum() < PARALLEL_MIN_POINTS:
        return [split(i) for i in range(len(members))]
    groups: list[list[int]] = [[] for _ in range(n_workers)]
    load = np.zeros(n_workers)
    for i in np.argsort(-sizes, kind="stable"):  # largest first onto the lightest worker
        k = int(np.argmin(load))
        groups[k].append(int(i))
        load[k] += sizes[i]

    def job(group: list[int], tick: Callable[[], None]) -> list[tuple[int, tuple]]:
        return [(i, split(i)) for i in group]

    done = run_jobs(job, [g for g in groups if g], "segment: crowns", 0, first_in_parent=True)
    results: dict[int, tuple[np.ndarray, np.ndarray]] = dict(r for part in done for r in part)
    return [results[i] for i in range(len(members))]


@dataclass(frozen=True)
class TreeScale:
    """What the data says about one tree: spacing in the row, crown length and weight."""

    spacing: float
    length: float
    weight: float
    source: str


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


def nearest_along_row(xy: np.ndarray, w: np.ndarray, markers: np.ndarray) -> np.ndarray:
    """Per point: the marker nearest to it along the part's row line (its principal axis),
    so that each tree owns the row between the midpoints to its neighbours."""
    centre, axis = principal_axis(xy, w)
    marker_along = (markers - centre) @ axis
    order = np.argsort(marker_along, kind="stable")
    cuts = 0.5 * (marker_along[order][1:] + marker_along[order][:-1])
    return order[np.searchsorted(cuts, (xy - centre) @ axis)]


def _extent(a: np.ndarray) -> float:
    return float(np.percentile(a, 99) - np.percentile(a, 1)) if len(a) else 0.0


class AdaptiveSegmenter(Segmenter):
    """Trees from canopy parts, trunks and the measured tree scale (module docstring).

    Parameters
    ----------
    link_factor : float, default 2.0
        Canopy points closer than this many point spacings are connected.
    crumb_fraction : float, default 0.1
        Parts lighter than this fraction of a tree (and without a trunk) are crumbs.
    crumb_reach : float, default 0.25
        A crumb joins the nearest part within this many tree spacings, else it is noise.
    use_stems : bool, default True
        Use trunk detections when stem points are given.
    stem_search_radius : float, default 1.0
        A trunk belongs to the canopy part above it within this horizontal distance (m).
    crown_split : bool, default True
        Split a part between its trees by fitted crowns (``segment.crowns``); else by the
        nearest tree position in the horizontal plane.
    cut : {"crowns", "trunk-midpoints"}, default "crowns"
        What a tree is where crowns touch: its own crown (``crown_split`` decides how it is
        found), or the row between the midpoints to its neighbours' trunks (fruiting walls).
    random_state : int, default 0
        Seed of the point-spacing sample.
    """

    def __init__(
        self,
        link_factor: Positive = 2.0,
        crumb_fraction: Positive = 0.1,
        crumb_reach: Positive = 0.25,
        use_stems: bool = True,
        stem_search_radius: Positive = 1.0,
        crown_split: bool = True,
        cut: Literal["crowns", "trunk-midpoints"] = "crowns",
        random_state: int = 0,
    ) -> None:
        self.link_factor = link_factor
        self.crown_split = crown_split
        self.cut = cut
        self.crumb_fraction = crumb_fraction
        self.crumb_reach = crumb_reach
        self.use_stems = use_stems
        self.stem_search_radius = stem_search_radius
        self.random_state = random_state

    def fit(
        self,
        X: np.ndarray,
        y: None = None,
        sample_weight: np.ndarray | None = None,
        stem_xyz: np.ndarray | None = None,
    ) -> AdaptiveSegmenter:
        """Segment canopy points ``X`` (x, y, height above ground); sets ``labels_`` etc.

        Fitted: ``labels_``, ``n_clusters_``, ``stems_`` (trunks used), ``posts_`` (trellis
        posts found among the detections, :class:`~canopy_kit.segment.posts.Posts`),
        ``markers_`` (tree positions), ``scale_`` (:class:`TreeScale`), ``point_spacing_``.
        """
        self.validate_params()
        xyz = check_points(X)
        w = check_weight(sample_weight, len(xyz))
        n = len(xyz)
        self.labels_ = np.full(n, -1, dtype=np.int64)
        self.stems_ = no_stems()
        self.posts_ = no_posts()
        self.markers_ = np.zeros((0, 2))
        self.scale_ = TreeScale(np.nan, np.nan, np.nan, "none")
        self.point_spacing_ = point_spacing(xyz, seed=self.random_state)
        if n == 0:
            self.n_clusters_ = 0
            return self
        parts = connected_parts(xyz, self.link_factor * self.point_spacing_, w)
        wall = self.cut == "trunk-midpoints"
        stems, self.posts_ = (
            split_posts(detect_stems(stem_xyz, close_trunks=wall), xyz, through_canopy=wall)
            if (self.use_stems and stem_xyz is not None)
            else (no_stems(), no_posts())
        )
        stem_part = self._stems_to_parts(xyz, w, parts, stems)
        keep = stem_part >= 0
        stems = stems.select(keep)
        stem_part = stem_part[keep]
        n_parts = int(parts.max()) + 1
        part_weight = np.bincount(parts[parts >= 0], weights=w[parts >= 0], minlength=n_parts)
        stems_per_part = np.bincount(stem_part, minlength=n_parts)
        scale = self._tree_scale(xyz, w, parts, part_weight, stems, stems_per_part)
        parts = self._merge_crumbs(xyz, parts, part_weight, stems_per_part, scale)
        labels = np.full(n, -1, dtype=np.int64)
        markers_all = []
        next_label = 0
        order = np.argsort(parts, kind="stable")
        valid = order[parts[order] >= 0]
        ids, starts = np.unique(parts[valid], return_index=True)
        ends = np.append(starts[1:], len(valid))
        members_of = [valid[a:b] for a, b in zip(starts, ends)]

        def split(part: int) -> tuple[np.ndarray, np.ndarray]:
            members, p = members_of[part], ids[part]
            return self._split_part(xyz[members], w[members], stems.xy[stem_part == p], scale)

        for members, (markers, sub) in zip(members_of, each_part(split, members_of)):
            labels[members] = sub + next_label
            next_label += len(markers)
            markers_all.append(markers)
        self.stems_ = stems
        self.scale_ = scale
        self.markers_ = np.concatenate(markers_all) if markers_all else np.zeros((0, 2))
        self.labels_ = first_appearance_order(labels)
        self.n_clusters_ = int(self.labels_.max()) + 1
        return self

    def _split_part(
        self, xyz: np.ndarray, w: np.ndarray, stems: np.ndarray, scale: TreeScale
    ) -> tuple[np.ndarray, np.ndarray]:
        """The tree positions (K, 2) of one canopy part and each of its points' tree (0..K-1)."""
        markers, tops = self._markers(xyz, w, stems, scale)
        if len(markers) <= 1:
            return markers, np.zeros(len(xyz), dtype=np.int64)
        if self.cut == "trunk-midpoints" and not tops:
            return markers, nearest_along_row(xyz[:, :2], w, markers)
        if self.crown_split and not tops:
            # Crown shells need crowns seen from the side (trunks, rows); crown tops of
            # a stand seen from above keep the nearest top.
            return markers, crown_split(xyz, markers)
        _, sub = cKDTree(markers).query(xyz[:, :2], workers=-1)
        return markers, sub

    # ------------------------------------------------------------------------------------
    def _stems_to_parts(
        self, xyz: np.ndarray, w: np.ndarray, parts: np.ndarray, stems: StemDetections
    ) -> np.ndarray:
        """The canopy part above each trunk (-1: no canopy above it, not a tree's trunk)."""
        out = np.full(len(stems), -1, dtype=np.int64)
        valid = parts >= 0
        if len(stems) == 0 or not valid.any():
            return out
        tree = cKDTree(xyz[valid, :2])
        vparts, vw = parts[valid], w[valid]
        for i, near in enumerate(tree.query_ball_point(stems.xy, self.stem_search_radius)):
            if near:
                out[i] = np.bincount(vparts[near], weights=vw[near]).argmax()
        return out

    def _tree_scale(
        self,
        xyz: np.ndarray,
        w: np.ndarray,
        parts: np.ndarray,
        part_weight: np.ndarray,
        stems: StemDetections,
        stems_per_part: np.ndarray,
    ) -> TreeScale:
        """Spacing, crown length and weight of one tree, from trunks or isolated crowns."""
        heavy = part_weight >= 0.05 * part_weight.max()
        geometry = {}
        for p in np.flatnonzero(heavy)[np.argsort(-part_weight[heavy])][:300]:
            m = parts == p
            along, across = along_axis(xyz[m, :2], w[m])
            centre = np.average(xyz[m, :2], axis=0, weights=w[m])
            geometry[p] = (_extent(along), _extent(across), centre)
        if len(stems) >= 2:
            # Upper quartile of the trunks' nearest-neighbour distances: trees planted
            # close together (doubled, replanted) must not shrink the row's spacing.
            d, _ = cKDTree(stems.xy).query(stems.xy, k=2)
            spacing = float(np.percentile(d[:, 1], 75))
            single = [p for p in geometry if stems_per_part[p] == 1]
            if single:
                length = float(np.median([geometry[p][0] for p in single]))
            else:  # every crown touches another: a row part reaches half a crown past its end trunks
                length = spacing
            with_stems = np.flatnonzero(stems_per_part > 0)
            weight = float(np.median(part_weight[with_stems] / stems_per_part[with_stems]))
            return TreeScale(spacing, length, weight, "trunks")
        round_parts = [p for p, (ln, wd, _) in geometry.items() if ln <= 1.5 * max(wd, 1e-9)]
        if len(round_parts) >= 3:
            centres = np.array([geometry[p][2] for p in round_parts])
            d, _ = cKDTree(centres).query(centres, k=2)
            length = float(np.median([geometry[p][0] for p in round_parts]))
            spacing = max(float(np.median(d[:, 1])), length)
            weight = float(np.median(part_weight[round_parts]))
            return TreeScale(spacing, length, weight, "isolated crowns")
        heaviest = int(np.argmax(part_weight))
        ln, wd, _ = geometry[heaviest]
        if ln < 2.0 * wd:
            # Crowns merged in two dimensions (a stand, not rows): the canopy's own rhythm.
            m = parts == heaviest
            cell = max(self.point_spacing_, 0.25)
            spacing = chm_spacing(xyz[m], cell)
            if np.isfinite(spacing):
                return TreeScale(
                    spacing,
                    spacing,
                    float(part_weight[heaviest]) * (spacing / max(ln, 1e-9)) ** 2,
                    "canopy height rhythm",
                )
        # Crowns merged into rows and no trunks: a crown is about as long as the row is wide.
        widths = [wd for (_, wd, _) in geometry.values()]
        width = float(np.median(widths)) if widths else 3.0
        n_trees = max(1.0, round(geometry[heaviest][0] / width))
        return TreeScale(width, width, float(part_weight[heaviest] / n_trees), "row width")

    def _merge_crumbs(
        self,
        xyz: np.ndarray,
        parts: np.ndarray,
        part_weight: np.ndarray,
        stems_per_part: np.ndarray,
        scale: TreeScale,
    ) -> np.ndarray:
        """Parts far lighter than a tree join the nearest real part, or become noise."""
        crumbs = (part_weight < self.crumb_fraction * scale.weight) & (stems_per_part == 0)
        if not crumbs.any():
            return parts
        is_crumb = (parts >= 0) & crumbs[np.maximum(parts, 0)]
        solid = (parts >= 0) & ~is_crumb
        out = parts.copy()
        out[is_crumb] = -1
        if not solid.any():
            return out
        crumb_idx = np.flatnonzero(is_crumb)
        solid_idx = np.flatnonzero(solid)
        dist, nearest = cKDTree(xyz[solid]).query(
            xyz[crumb_idx], distance_upper_bound=self.crumb_reach * scale.spacing, workers=-1
        )
        # A crumb joins the part its closest point is nearest to (the whole crumb moves).
        cp = parts[crumb_idx]
        best = np.full(len(part_weight), np.inf)
        target = np.full(len(part_weight), -1, dtype=np.int64)
        ok = np.isfinite(dist)
        order = np.argsort(dist[ok])[::-1]  # the closest written last wins
        cpo, do, no = cp[ok][order], dist[ok][order], nearest[ok][order]
        best[cpo] = do
        target[cpo] = parts[solid_idx[no]]
        out[crumb_idx] = target[cp]
        return out

    def _markers(
        self, xyz: np.ndarray, w: np.ndarray, stems: np.ndarray, scale: TreeScale
    ) -> tuple[np.ndarray, bool]:
        """Tree positions (x, y) in one canopy part: its trunks plus trees without one;
        and whether they are crown tops of a patch that is not a row."""
        centre, axis = principal_axis(xyz[:, :2], w)
        along = (xyz[:, :2] - centre) @ axis
        lo, hi = np.percentile(along, 1), np.percentile(along, 99)
        s, half = scale.spacing, 0.5 * scale.length
        if len(stems) == 0:
            across = (xyz[:, :2] - centre) @ np.array([-axis[1], axis[0]])
            width = np.percentile(across, 99) - np.percentile(across, 1)
            stand = scale.source == "canopy height rhythm"
            if hi - lo < 2.0 * width and hi - lo > (1.0 if stand else 1.5) * scale.length:
                # Not a row but a patch of merged crowns: one tree per crown top.
                tops = chm_peaks(xyz, max(self.point_spacing_, 0.25), 0.4 * s)
                if len(tops):
                    return tops, True
            n = max(1, int(round((hi - lo - scale.length) / s)) + 1)
            spots = [0.5 * (lo + hi)] if n == 1 else np.linspace(lo + half, hi - half, n)
            return self._on_canopy(xyz, w, along, np.asarray(spots, float), s), False
        if self.cut == "trunk-midpoints":
            # On a wall a tree is its trunk: a stretch without one is a missing tree (the
            # detector sees the wall's foot from both alleys) or the wall's end, not a
            # hidden trunk.
            return stems, False
        stem_along = np.sort((stems - centre) @ axis)
        spots: list[float] = []
        for a, b in zip(stem_along[:-1], stem_along[1:]):
            k = int(round((b - a) / s)) - 1
            spots.extend(np.linspace(a, b, k + 2)[1:-1].tolist() if k > 0 else [])
        # Beyond the end trunks a part reaches half a crown; more than that holds trees.
        for end, reach in (
            (stem_along[0], stem_along[0] - lo),
            (stem_along[-1], hi - stem_along[-1]),
        ):
            k = int(round((reach - half) / s))
            sign = -1.0 if end == stem_along[0] and reach == stem_along[0] - lo else 1.0
            spots.extend((end + sign * s * np.arange(1, k + 1)).tolist() if k > 0 else [])
        if not spots:
            return stems, False
        return np.concatenate([stems, self._on_canopy(xyz, w, along, np.array(spots), s)]), False

    @staticmethod
    def _on_canopy(
        xyz: np.ndarray, w: np.ndarray, along: np.ndarray, spots: np.ndarray, spacing: float
    ) -> np.ndarray:
        """Positions at along-axis ``spots``: the centroid of the canopy within half a spacing
        (follows a curved row), or the nearest canopy point when the slice is empty."""
        out = []
        for a in spots:
            m = np.abs(along - a) <= 0.5 * spacing
            if m.any():
                out.append(np.average(xyz[m, :2], axis=0, weights=w[m]))
            else:
                out.append(xyz[int(np.argmin(np.abs(along - a))), :2])
        return np.array(out)
