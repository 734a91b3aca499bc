"""Trunk detection below the canopy: compact, vertical clusters in the stem band.

A trunk seen from the alleys is a narrow vertical column of points between the grass and
the crown; grass is too low to fill the lower part of the band, a crown that hangs into
the band is wide and fills only its top. So only the lowest ``slice_height`` of the stem
band is used: points there are grouped in the horizontal plane (cells of ``cell``), and a
group is a trunk when it is narrow (``max_radius``) and fills most of the slice's height
(``min_coverage`` of its 5 cm layers). Trunks closer than ``merge_distance`` are one tree
(a forked trunk or one trunk split by occlusion).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


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


def detect_stems(stem_xyz: np.ndarray | None, slice_height: float = 0.3, cell: float = 0.05,
                 max_radius: float = 0.3, min_coverage: float = 0.6,
                 merge_distance: float = 0.5) -> StemDetections:
    """Trunks among height-normalised stem-band points ``(x, y, height above ground)``."""
    if stem_xyz is None or len(stem_xyz) < 3:
        return no_stems()
    p = np.asarray(stem_xyz, dtype=np.float64)
    z0 = np.percentile(p[:, 2], 1)
    p = p[(p[:, 2] >= z0) & (p[:, 2] < z0 + slice_height)]
    if len(p) < 3:
        return no_stems()
    lo = p[:, :2].min(axis=0) - 2 * cell
    keys = np.floor((p[:, :2] - lo) / cell).astype(np.int64)
    shape = tuple(keys.max(axis=0) + 3)
    occ = np.zeros(shape, bool)
    occ[keys[:, 0], keys[:, 1]] = True
    # Cells one apart belong together (a sparse trunk seen from two sides).
    grown = ndimage.binary_dilation(occ, np.ones((3, 3), bool))
    blobs, n = ndimage.label(grown, np.ones((3, 3), bool))
    lab = blobs[keys[:, 0], keys[:, 1]] - 1
    n_layers = max(int(round(slice_height / 0.05)), 1)
    layer = np.minimum(((p[:, 2] - z0) / 0.05).astype(int), n_layers - 1)
    order = np.argsort(lab, kind="stable")
    bounds = np.searchsorted(lab[order], np.arange(n + 1))
    xy, npts, rad, cov = [], [], [], []
    for b in range(n):
        members = order[bounds[b]:bounds[b + 1]]
        if len(members) < 3:
            continue
        q = p[members]
        c = q[:, :2].mean(axis=0)
        r = float(np.percentile(np.linalg.norm(q[:, :2] - c, axis=1), 90))
        coverage = len(np.unique(layer[members])) / n_layers
        if r <= max_radius and coverage >= min_coverage:
            xy.append(c)
            npts.append(len(members))
            rad.append(r)
            cov.append(coverage)
    if not xy:
        return no_stems()
    return _merge_close(np.array(xy), np.array(npts), np.array(rad), np.array(cov), merge_distance)


def _merge_close(xy: np.ndarray, npts: np.ndarray, rad: np.ndarray, cov: np.ndarray,
                 distance: float) -> StemDetections:
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(xy).query_pairs(distance, output_type="ndarray")
    from scipy import sparse

    g = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                          shape=(len(xy), len(xy)))
    n, comp = connected_components(g, directed=False)
    w = npts.astype(float)
    out_xy = np.array([np.average(xy[comp == k], axis=0, weights=w[comp == k]) for k in range(n)])
    return StemDetections(out_xy, np.bincount(comp, weights=w).astype(int),
                          np.array([rad[comp == k].max() for k in range(n)]),
                          np.array([cov[comp == k].max() for k in range(n)]))
