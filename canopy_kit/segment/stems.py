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


def no_stems() -> StemDetections:
    """An empty detection."""
    return StemDetections(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0), np.zeros(0))


def detect_stems(
    stem_xyz: np.ndarray | None,
    slice_height: float = 0.3,
    cell: float = 0.05,
    max_radius: float = 0.3,
    min_coverage: float = 0.6,
    merge_distance: float = 0.8,
    foot_height: float = 0.1,
    min_share: float = 0.4,
    ring_radius: float = 0.7,
    max_clutter: float = 0.1,
) -> StemDetections:
    """Trunks among height-normalised stem-band points ``(x, y, height above ground)``.

    Candidates are compact groups of points in the lowest ``foot_height`` of the slice
    (where leaves of a low crown rarely reach); a candidate is a trunk when the column of
    radius ``max_radius`` above it fills ``min_coverage`` of the slice's 5 cm layers,
    stands free at its foot (the ring around it out to ``ring_radius`` has at most
    ``max_clutter`` of the foot's point density) and has at least ``min_share`` of the
    median trunk's points and foot radius.
    """
    if stem_xyz is None or len(stem_xyz) < 3:
        return no_stems()
    p = np.asarray(stem_xyz, dtype=np.float64)
    z0 = np.percentile(p[:, 2], 1)
    p = p[(p[:, 2] >= z0) & (p[:, 2] < z0 + slice_height)]
    foot = p[p[:, 2] < z0 + foot_height]
    if len(foot) < 3:
        return no_stems()
    lo = foot[:, :2].min(axis=0) - 2 * cell
    keys = np.floor((foot[:, :2] - lo) / cell).astype(np.int64)
    occ = np.zeros(tuple(keys.max(axis=0) + 3), bool)
    occ[keys[:, 0], keys[:, 1]] = True
    # Cells one apart belong together (a sparse trunk seen from two sides).
    blobs, n = ndimage.label(
        ndimage.binary_dilation(occ, np.ones((3, 3), bool)), np.ones((3, 3), bool)
    )
    lab = blobs[keys[:, 0], keys[:, 1]] - 1
    n_layers = max(int(round(slice_height / 0.05)), 1)
    layer = np.minimum(((p[:, 2] - z0) / 0.05).astype(int), n_layers - 1)
    column_tree = cKDTree(p[:, :2])
    foot_tree = cKDTree(foot[:, :2])
    xy, npts, rad, cov = [], [], [], []
    for b in range(n):
        q = foot[lab == b]
        if len(q) < 2:
            continue
        c = q[:, :2].mean(axis=0)
        r = float(np.percentile(np.linalg.norm(q[:, :2] - c, axis=1), 90))
        if r > max_radius:
            continue
        reach = max(2 * r, 0.1) + cell
        column = column_tree.query_ball_point(c, reach)
        coverage = len(np.unique(layer[column])) / n_layers
        if coverage >= min_coverage and _clutter(foot_tree, c, reach, ring_radius) <= max_clutter:
            xy.append(c)
            npts.append(len(column))
            rad.append(r)
            cov.append(coverage)
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


def _clutter(foot_tree: cKDTree, centre: np.ndarray, reach: float, ring_radius: float) -> float:
    """Point density in the ring ``reach``..``ring_radius`` around a foot, relative to the
    foot's own (0: free-standing; about 1: inside foliage)."""
    if ring_radius <= reach:
        return 0.0
    n_foot = foot_tree.query_ball_point(centre, reach, return_length=True)
    n_ring = foot_tree.query_ball_point(centre, ring_radius, return_length=True) - n_foot
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
