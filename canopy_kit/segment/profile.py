"""Along-row profiles of a canopy part: its principal axis and the bumps of its mass."""

from __future__ import annotations

import numpy as np


def principal_axis(xy: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted centroid and unit direction of largest spread of points ``xy`` (N, 2)."""
    xy = np.asarray(xy, dtype=np.float64)
    w = np.ones(len(xy)) if w is None else np.asarray(w, dtype=np.float64)
    c = np.average(xy, axis=0, weights=w)
    if len(xy) < 2:
        return c, np.array([1.0, 0.0])
    d = xy - c
    cov = (d * w[:, None]).T @ d / w.sum()
    vals, vecs = np.linalg.eigh(cov)
    v = vecs[:, int(np.argmax(vals))]
    return c, v if (v[1] > 0 or (v[1] == 0 and v[0] > 0)) else -v


def along_axis(xy: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates along and across the principal axis of ``xy``."""
    c, v = principal_axis(xy, w)
    d = np.asarray(xy, dtype=np.float64) - c
    return d @ v, d @ np.array([-v[1], v[0]])


def canopy_height_model(xyz: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Highest point per ``cell`` square (0 where empty) and the grid's lower-left corner."""
    lo = xyz[:, :2].min(axis=0)
    k = np.floor((xyz[:, :2] - lo) / cell).astype(np.int64)
    chm = np.zeros(tuple(k.max(axis=0) + 1))
    np.maximum.at(chm, (k[:, 0], k[:, 1]), xyz[:, 2])
    return chm, lo


def _radial_autocorrelation(a: np.ndarray, n: int) -> np.ndarray:
    pad = [2 * k for k in a.shape]
    f = np.fft.rfft2(a, pad)
    ac = np.fft.fftshift(np.fft.irfft2(f * np.conj(f), pad))
    yy, xx = np.indices(ac.shape)
    r = np.hypot(yy - pad[0] // 2, xx - pad[1] // 2).astype(int)
    sums = np.bincount(r.ravel(), ac.ravel())[:n]
    radial = sums / np.maximum(np.bincount(r.ravel())[:n], 1)
    return radial / radial[0] if radial[0] else radial


def chm_spacing(xyz: np.ndarray, cell: float, max_lag: float = 30.0, start: float = 10.0) -> float:
    """Typical distance between neighbouring crowns from the canopy height model alone.

    Crowns alternate with dips, so the autocorrelation of the height model, after removing
    trends longer than the crown scale, has its first minimum at about the crown spacing.
    The trend filter's width is itself that scale: start at ``start`` metres and iterate
    to the fixed point (a few steps, independent of the start). NaN if there is none.
    """
    from scipy.ndimage import gaussian_filter

    chm, _ = canopy_height_model(xyz, cell)
    if min(chm.shape) < 4:
        return float("nan")
    n = max(min(int(max_lag / cell), min(chm.shape)), 4)
    scale = start
    for _ in range(10):
        r = _radial_autocorrelation(chm - gaussian_filter(chm, scale / cell), n)
        mins = np.flatnonzero((r[1:-1] < r[:-2]) & (r[1:-1] <= r[2:])) + 1
        if len(mins) == 0:
            return float("nan")
        new = float(mins[0] * cell)
        if abs(new - scale) < 0.5 * cell:
            return new
        scale = new
    return scale


def chm_peaks(xyz: np.ndarray, cell: float, min_distance: float) -> np.ndarray:
    """Crown tops: local maxima of the smoothed canopy height model at least
    ``min_distance`` apart, as (x, y) positions."""
    from scipy.ndimage import gaussian_filter, maximum_filter

    chm, lo = canopy_height_model(xyz, cell)
    smooth = gaussian_filter(chm, 1.0)
    r = max(int(round(min_distance / cell)), 1)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disc = (yy**2 + xx**2) <= r * r
    peak = (smooth == maximum_filter(smooth, footprint=disc)) & (chm > 0)
    ij = np.argwhere(peak)
    return lo + (ij + 0.5) * cell
