"""Trunk detection below the canopy: compact, vertical clusters in the stem band.

A trunk seen from the alleys is a narrow vertical column of points between the grass and
the crown; grass is too low to reach the stem band, and a crown that hangs into the band
rarely reaches its foot. So trunks are looked for in the lowest ``slice_height`` of the
band: compact groups of points at its foot (cells of ``cell``) whose column fills most of
the slice's height (``min_coverage`` of its 5 cm layers). A trunk stands free at its
foot: where a crown's skirt reaches the ground, its foliage makes trunk-like columns too,
but with foliage all around them, so a candidate whose surrounding ring (out to
``ring_radius``) holds more than ``max_clutter`` of its own point density is no trunk
(the trunk hidden in such a skirt is left to the tree spacing). Trunks closer than
``merge_distance`` are one tree (a forked trunk or one trunk split by occlusion).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class StemDetections:
    """Detected trunks: position (x, y), points, radius and height coverage of each."""

    xy: np.ndarray
    n_points: np.ndarray
    radius: np.ndarray
    coverage: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)

    def select(self, keep: np.ndarray) -> StemDetections:
        """The detections where ``keep`` (a boolean mask or indices) says."""
        return StemDetections(
            self.xy[keep], self.n_points[keep], self.radius[keep], self.coverage[keep]
        )


def no_stems() -> StemDetections:
    """An empty detection."""
    return StemDetections(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0), np.zeros(0))


def detect_stems(
    stem_xyz: np.ndarray | None,
    slice_height: float = 0.3,
    cell: float = 0.05,
    max_radius: float = 0.3,
    min_coverage: float = 0.6,
    merge_distance: float | None = None,
    foot_height: float = 0.1,
    min_share: float = 0.4,
    ring_radius: float = 0.7,
    max_clutter: float = 0.1,
    close_trunks: bool = False,
) -> StemDetections:
    """Trunks among height-normalised stem-band points ``(x, y, height above ground)``.

    Candidates are compact groups of points in the lowest ``foot_height`` of the slice
    (where leaves of a low crown rarely reach); a candidate is a trunk when the column of
    radius ``max_radius`` above it fills ``min_coverage`` of the slice's 5 cm layers,
    stands free at its foot (the ring around it out to ``ring_radius`` has at most
    ``max_clutter`` of the foot's point density) and has at least ``min_share`` of the
    median trunk's points and foot radius.

    ``close_trunks`` (a fruiting wall: trunks 0.6-1.5 m apart, a drip line along their feet,
    leaves hanging low): the foot holds only points standing in a column from the slice's
    bottom layer up (:func:`column_run`), a wide group is split into its columns that fill
    the slice, the next trunk (a group of its own) is no clutter, and trunks merge within
    ``merge_distance`` = 0.4 m (the pieces of one trunk) instead of 0.8 m.
    """
    if stem_xyz is None or len(stem_xyz) < 3:
        return no_stems()
    p = np.asarray(stem_xyz, dtype=np.float64)
    z0 = np.percentile(p[:, 2], 1)
    p = p[(p[:, 2] >= z0) & (p[:, 2] < z0 + slice_height)]
    n_layers = max(int(round(slice_height / 0.05)), 1)
    layer = np.minimum(((p[:, 2] - z0) / 0.05).astype(int), n_layers - 1)
    if merge_distance is None:
        merge_distance = 0.4 if close_trunks else 0.8
    run = column_run(p, layer, n_layers, cell) if close_trunks else np.full(len(p), n_layers)
    in_foot = (p[:, 2] < z0 + foot_height) & (run >= min_coverage * n_layers)
    foot, foot_run = p[in_foot], run[in_foot]
    if len(foot) < 3:
        return no_stems()
    column_tree = cKDTree(p[:, :2])
    groups = []  # (foot indices, centre, radius) of the compact groups
    for g, alone in _foot_groups(foot, foot_run, n_layers, cell, max_radius, close_trunks):
        core = g[foot_run[g] >= n_layers]  # the columns that fill the slice: the trunk
        g = core if len(core) >= 2 else g
        c = foot[g, :2].mean(axis=0)
        r = float(np.percentile(np.linalg.norm(foot[g, :2] - c, axis=1), 90))
        if r <= max_radius:
            groups.append((g, c, r, alone))
    # Clutter is foliage standing on the ground all round a foot (a skirt); not the next
    # trunk of a close row (a group of its own; columns split out of a wide group stand in
    # foliage and count).
    owner = np.full(len(foot), -1)
    for k, (g, _, _, alone) in enumerate(groups):
        owner[g] = k if (alone and close_trunks) else -1
    foot_tree = cKDTree(foot[:, :2])
    xy, npts, rad, cov, free = [], [], [], [], []
    for k, (_, c, r, _) in enumerate(groups):
        reach = max(2 * r, 0.1) + cell
        column = column_tree.query_ball_point(c, reach)
        coverage = len(np.unique(layer[column])) / n_layers
        if coverage < min_coverage:
            continue
        foliage = (owner < 0) | (owner == k)
        xy.append(c)
        npts.append(len(column))
        rad.append(r)
        cov.append(coverage)
        free.append(_clutter(foot_tree, foliage, c, reach, ring_radius) <= max_clutter)
    keep = np.array(free, bool)
    if close_trunks and len(xy):
        # A wall tree's trunk in a skirt that reaches the ground: the densest column of its
        # skirt (none denser within ``ring_radius``) is the trunk; a stretch without a trunk
        # would otherwise join two trees.
        centres, weight = np.array(xy), np.array(npts)
        for i, near in enumerate(cKDTree(centres).query_ball_point(centres, ring_radius)):
            keep[i] |= weight[i] >= weight[near].max()
    xy, npts, rad, cov = (list(np.array(v)[keep]) for v in (xy, npts, rad, cov))
    if not xy:
        return no_stems()
    npts_a, rad_a = np.array(npts), np.array(rad)
    # A few leaves hanging to the foot make a column too, but a thinner one, of fewer
    # points than the trunks of the same scan.
    solid = np.ones(len(npts_a), bool)
    if len(npts_a) >= 3:
        solid = (npts_a >= min_share * np.median(npts_a)) & (rad_a >= min_share * np.median(rad_a))
    return _merge_close(
        np.array(xy)[solid], npts_a[solid], rad_a[solid], np.array(cov)[solid], merge_distance
    )


def _blobs(points: np.ndarray, cell: float) -> tuple[np.ndarray, int]:
    """Labels of the groups of ``cell`` cells that points occupy (cells one apart belong
    together: a sparse trunk seen from two sides)."""
    lo = points[:, :2].min(axis=0) - 2 * cell
    keys = np.floor((points[:, :2] - lo) / cell).astype(np.int64)
    occ = np.zeros(tuple(keys.max(axis=0) + 3), bool)
    occ[keys[:, 0], keys[:, 1]] = True
    blobs, n = ndimage.label(
        ndimage.binary_dilation(occ, np.ones((3, 3), bool)), np.ones((3, 3), bool)
    )
    return blobs[keys[:, 0], keys[:, 1]] - 1, n


def _foot_groups(
    foot: np.ndarray,
    run: np.ndarray,
    n_layers: int,
    cell: float,
    max_radius: float,
    split_wide: bool,
) -> list[tuple[np.ndarray, bool]]:
    """The trunk candidates among the foot points (index arrays, and whether the group stands
    alone): groups of cells, and with ``split_wide``, where a group is wider than
    ``max_radius`` (a skirt, or trunks joined by low leaves), the groups of its columns that
    fill every layer (without, a wide group is left out)."""
    out = []
    lab, n = _blobs(foot, cell)
    for b in range(n):
        idx = np.flatnonzero(lab == b)
        if len(idx) < 2:
            continue
        q = foot[idx, :2]
        if np.percentile(np.linalg.norm(q - q.mean(axis=0), axis=1), 90) <= max_radius:
            out.append((idx, True))
            continue
        if not split_wide:
            continue
        full = idx[run[idx] >= n_layers]
        if len(full) < 2:
            continue
        sub, k = _blobs(foot[full], cell)
        out.extend((g, False) for g in (full[sub == j] for j in range(k)) if len(g) >= 2)
    return out


def column_run(p: np.ndarray, layer: np.ndarray, n_layers: int, cell: float) -> np.ndarray:
    """Per point: how many of the slice's ``n_layers`` layers, from the bottom one up without a
    break, its ``cell`` (with the cells around it) holds points in. A trunk stands on the
    ground and fills them all.

    A drip line, a low wire or a fallen branch runs through the foot of the slice but fills
    one or two layers, and a crown hanging low above it fills the layers above: such a
    column does not start at the bottom layer (without this rule a drip line under a low
    wall joins every trunk along a row into one blob).
    """
    keys = np.floor((p[:, :2] - p[:, :2].min(axis=0)) / cell).astype(np.int64) + 1
    shape = tuple(keys.max(axis=0) + 2)
    bits = np.zeros(shape, np.int64)
    np.bitwise_or.at(bits, (keys[:, 0], keys[:, 1]), np.left_shift(1, layer.astype(np.int64)))
    spread = np.zeros_like(bits)  # OR over the 3 x 3 cells around each cell
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            spread |= np.roll(np.roll(bits, dx, axis=0), dy, axis=1)
    standing = np.ones(shape, bool)
    run = np.zeros(shape, np.int64)
    for k in range(n_layers):
        standing &= ((spread >> k) & 1).astype(bool)
        run += standing
    return run[keys[:, 0], keys[:, 1]]


def _clutter(
    tree: cKDTree, counted: np.ndarray, centre: np.ndarray, reach: float, ring_radius: float
) -> float:
    """Density of the ``counted`` points of ``tree`` in the ring ``reach``..``ring_radius``
    around a foot, relative to the foot's own (0: free-standing; about 1: inside foliage)."""
    if ring_radius <= reach:
        return 0.0
    foot = tree.query_ball_point(centre, reach)
    ring = np.setdiff1d(tree.query_ball_point(centre, ring_radius), foot).astype(np.int64)
    n_foot, n_ring = len(foot), int(counted[ring].sum())
    ring_area = np.pi * (ring_radius**2 - reach**2)
    return float((n_ring / ring_area) / max(n_foot / (np.pi * reach**2), 1e-12))


def _merge_close(
    xy: np.ndarray, npts: np.ndarray, rad: np.ndarray, cov: np.ndarray, distance: float
) -> StemDetections:
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(xy).query_pairs(distance, output_type="ndarray")
    from scipy import sparse

    g = sparse.coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(xy), len(xy))
    )
    n, comp = connected_components(g, directed=False)
    w = npts.astype(float)
    out_xy = np.array([np.average(xy[comp == k], axis=0, weights=w[comp == k]) for k in range(n)])
    return StemDetections(
        out_xy,
        np.bincount(comp, weights=w).astype(int),
        np.array([rad[comp == k].max() for k in range(n)]),
        np.array([cov[comp == k].max() for k in range(n)]),
    )
