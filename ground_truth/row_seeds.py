"""One seed per tree from the imagery alone: orchard rows in the canopy mask, trees along them.

In a hedgerow the crowns touch and interweave, so the local maxima of the canopy height
model are the tops of lobes rather than of trees (measured on simulated almond flights
of 4 rows × 8: 20 of 36 trees one-to-one). The rows, though, are plain to see from above,
and along a row the trees leave two traces: the crown surface dips between two trees
(a saddle of the ridge height) and the hedge narrows there (a waist). Trees also stand
at a planting distance that varies little within an orchard. So:

1. **Row direction**: the angle at which the canopy cells, projected across it, pile up
   most sharply (the sum of squared counts of 0.25 m bins, a discrete Radon transform).
2. **Rows**: peaks of that across-row profile at least ``min_row_spacing_m`` apart;
   every canopy cell belongs to the row whose band (between the profile's minima) holds it,
   and each row keeps its own centre line (median across-row offset per metre), so bowed
   rows are followed.
3. **Boundary evidence** along each row, per 0.2 m: how deep the bin lies in a valley of
   the ridge height and of the hedge width, each relative to the lower of the highest
   values within half a tree spacing on either side (0 on a plateau or a slope, about 0.3
   at a clear saddle, 2 in a gap between crowns); two empty bins split a row into stretches.
4. **Tree spacing**: given (the planting distance, ``tree_spacing_m``) or, where crowns
   touch, about a crown's width across the row (the 90th percentile of the hedge width).
5. **Trees**: each stretch is cut into segments by dynamic programming, minimising the
   squared deviation of the segment lengths from the spacing (in units of a quarter of
   it; looser for the end trees, whose crowns reach past their trunks) plus a cost for
   every cut that is not on a saddle. Each tree's crown is the canopy of its segment (the
   outer trees of a stretch reach to the middle of the gaps beside it); the segment's
   middle, on the row's centre line, is its seed position.

The seeds come from the photos only, so the crowns stay independent of the LiDAR.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ground_truth.raster import Grid

PROFILE_BIN_M = 0.2  # along-row bin of the boundary evidence
ACROSS_BIN_M = 0.25  # across-row bin of the row-direction and row-band profile
SADDLE_EVIDENCE = 0.3  # boundary evidence of a clear saddle (height and width dips summed)
CUT_COST = 2.0  # cost of a cut with no saddle under it (a length deviation of 0.35 spacing)


@dataclass(frozen=True)
class OrchardRow:
    """One row: its across-row offset, band, centre line and trees' stretches."""

    offset_m: float
    centre_along_m: np.ndarray  # along-row stations of the centre line
    centre_across_m: np.ndarray  # across-row offset of the centre line there
    band_m: tuple[float, float] = (-np.inf, np.inf)  # across-row offsets the row's cells lie in
    # per tree: along-row start and end of its stretch (the row's first and last: ±inf)
    segments_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def trees(self) -> int:
        return len(self.segments_m)

    def across_at(self, along: np.ndarray) -> np.ndarray:
        """The centre line's across-row offset at along-row positions."""
        return np.interp(along, self.centre_along_m, self.centre_across_m)


@dataclass(frozen=True)
class RowLayout:
    """Rows found in the canopy mask and the tree seeds placed along them."""

    direction: tuple[float, float]  # unit vector along the rows (x east, y north)
    origin: tuple[float, float]  # the point the along/across coordinates are measured from
    rows: list[OrchardRow]
    spacing_m: float
    spacing_source: str  # "given" or "hedge_width"
    seeds_xy: np.ndarray = field(repr=False)

    def tree_of(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Index of the seed (tree) whose row band and along-row segment hold each point, -1
        for points in no tree's segment."""
        u = np.asarray(self.direction)
        d = np.column_stack([np.ravel(x) - self.origin[0], np.ravel(y) - self.origin[1]])
        along, across = d @ u, d @ np.array([-u[1], u[0]])
        out = np.full(len(d), -1, int)
        first = 0
        for row in self.rows:
            inside = (across >= row.band_m[0]) & (across < row.band_m[1])
            starts, ends = row.segments_m[:, 0], row.segments_m[:, 1]
            k = np.searchsorted(starts, along, side="right") - 1
            ok = inside & (k >= 0)
            ok[ok] &= along[ok] < ends[k[ok]]
            out[ok] = first + k[ok]
            first += row.trees
        return out.reshape(np.shape(x))

    @property
    def bearing_deg(self) -> float:
        """Bearing of the rows from north, in [0, 180)."""
        return float(np.degrees(np.arctan2(self.direction[0], self.direction[1])) % 180.0)

    def to_dict(self) -> dict:
        """For ``report.json``."""
        return {
            "bearing_deg": round(self.bearing_deg, 2),
            "rows": len(self.rows),
            "trees_per_row": [r.trees for r in self.rows],
            "tree_spacing_m": round(self.spacing_m, 3),
            "tree_spacing_source": self.spacing_source,
        }


def _canopy_points(canopy: np.ndarray, grid: Grid, cell_m: float = 0.1) -> tuple[np.ndarray, int]:
    """(x, y) of canopy cells on a grid of about ``cell_m``, and the subsampling step."""
    step = max(int(round(cell_m / grid.resolution)), 1)
    x, y = grid.centers()
    sub = canopy[::step, ::step]
    return np.column_stack([x[::step, ::step][sub], y[::step, ::step][sub]]), step


def _projection_sharpness(d: np.ndarray, angles: np.ndarray, radius: float) -> np.ndarray:
    """Sum of squared across-row bin counts for each candidate row angle (radians)."""
    n_bins = int(np.ceil(2 * radius / ACROSS_BIN_M)) + 1
    out = np.empty(len(angles))
    for k, a in enumerate(angles):
        t = -d[:, 0] * np.sin(a) + d[:, 1] * np.cos(a)
        h = np.bincount(((t + radius) / ACROSS_BIN_M).astype(int), minlength=n_bins)
        out[k] = float(np.dot(h, h))
    return out


def row_direction_from_canopy(points: np.ndarray) -> float:
    """Angle (radians from east, in [0, π)) along which the canopy is arranged in rows."""
    d = points - points.mean(axis=0)
    radius = float(np.sqrt((d**2).sum(axis=1).max())) + ACROSS_BIN_M
    coarse = np.radians(np.arange(0.0, 180.0, 1.0))
    best = coarse[int(np.argmax(_projection_sharpness(d, coarse, radius)))]
    fine = best + np.radians(np.arange(-1.0, 1.0001, 0.05))
    return float(fine[int(np.argmax(_projection_sharpness(d, fine, radius)))] % np.pi)


def _smooth(values: np.ndarray, sigma_bins: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(values.astype(float), sigma_bins, mode="constant")


def _row_bands(across: np.ndarray, min_row_spacing_m: float) -> np.ndarray:
    """Band edges (across-row offsets) between the rows of the across-row profile."""
    from scipy.signal import find_peaks

    lo = float(across.min())
    h = np.bincount(((across - lo) / ACROSS_BIN_M).astype(int)).astype(float)
    hs = _smooth(h, 0.5 / ACROSS_BIN_M)
    peaks, _ = find_peaks(
        np.concatenate([[0.0], hs, [0.0]]),
        distance=max(int(min_row_spacing_m / ACROSS_BIN_M), 1),
        prominence=0.2 * hs.max(),
    )
    peaks = peaks - 1
    edges = [lo - 1.0]
    for a, b in zip(peaks[:-1], peaks[1:]):
        edges.append(lo + (a + int(np.argmin(hs[a : b + 1])) + 0.5) * ACROSS_BIN_M)
    edges.append(float(across.max()) + 1.0)
    return np.array(edges)


def _centre_line(along: np.ndarray, across: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median across-row offset per metre along the row, smoothed over 5 m."""
    from scipy.ndimage import median_filter

    stations = np.floor(along).astype(int)
    keys = np.unique(stations)
    med = np.array([np.median(across[stations == k]) for k in keys])
    if len(med) >= 5:
        med = median_filter(med, size=5, mode="nearest")
    return keys + 0.5, med


def _ridge_and_width(
    bins: np.ndarray, n: int, heights: np.ndarray, across: np.ndarray, cell: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per along-row bin: highest smoothed CHM and across-row extent of the canopy (0 if empty).

    The extent (not the cell count) so that bins holding two or three grid columns alike do
    not alias into a comb; both profiles smoothed over one bin.
    """
    height = np.zeros(n)
    np.maximum.at(height, bins, heights)
    hi = np.full(n, -np.inf)
    lo = np.full(n, np.inf)
    np.maximum.at(hi, bins, across)
    np.minimum.at(lo, bins, across)
    width = np.where(np.isfinite(hi), hi - lo + cell, 0.0)
    empty = width <= 0
    height, width = _smooth(height, 1.0), _smooth(width, 1.0)
    height[empty], width[empty] = 0.0, 0.0
    return height, width


def _valley_depth(values: np.ndarray, window_bins: int) -> np.ndarray:
    """Per bin: how far it lies below the lower of the highest values within ``window_bins``
    on its left and on its right, relative to that level (0 on slopes and plateaus)."""
    from scipy.ndimage import maximum_filter1d

    size = max(window_bins, 1) + 1
    # left[k] = max(values[k - w .. k]), right[k] = max(values[k .. k + w])
    left = maximum_filter1d(values, size, origin=(size - 1) // 2, mode="nearest")
    right = maximum_filter1d(values, size, origin=-(size // 2), mode="nearest")
    level = np.maximum(np.minimum(left, right), 1e-6)
    return np.clip(1.0 - values / level, 0.0, 1.0)


def crown_width(width: np.ndarray) -> float:
    """A crown's width across the row from a hedge-width profile: its 90th percentile over
    the bins with canopy (a crown's chords average π/4 of its width; the widest ones are it)."""
    return float(np.percentile(width[width > 0], 90))


def boundary_evidence(height: np.ndarray, width: np.ndarray, window_bins: int) -> np.ndarray:
    """Per along-row bin: how deep it lies in a valley of the ridge height and of the hedge
    width, summed.

    Each depth is relative to the lower of the highest values within ``window_bins`` on
    either side (a saddle between two crowns, not the slope up to a taller neighbour): 0 on
    a plateau or a slope, 2 in an empty bin (a gap between crowns).
    """
    evidence = _valley_depth(height, window_bins) + _valley_depth(width, window_bins)
    return np.clip(evidence, 0.0, 2.0)


def canopy_runs(empty: np.ndarray, min_gap_bins: int = 2) -> list[tuple[int, int]]:
    """Stretches ``[i, j)`` of a row's bins without a gap of ``min_gap_bins`` empty bins."""
    runs, start, gap = [], None, 0
    for k, e in enumerate(empty):
        if not e:
            if start is None:
                start = k
            last, gap = k, 0
        elif start is not None:
            gap += 1
            if gap >= min_gap_bins:
                runs.append((start, last + 1))
                start = None
    if start is not None:
        runs.append((start, last + 1))
    return runs


def cut_row(
    evidence: np.ndarray,
    spacing_m: float,
    crown_width_m: float,
    interior_sigma: float = 0.25,
    cut_cost: float = CUT_COST,
) -> list[tuple[int, int]]:
    """Segments ``[i, j)`` of a stretch of canopy's bins, one per tree (dynamic programming).

    Cost: Σ over segments of ((L − μ)/σ)² plus ``cut_cost`` · (1 − evidence /
    ``SADDLE_EVIDENCE``, clipped at 0) for every cut. Between two cuts μ = spacing and σ =
    ``interior_sigma`` · spacing; an end tree reaches from a cut to its crown's edge, μ =
    (spacing + ``crown_width_m``)/2; a lone tree, μ = ``crown_width_m``; σ = 0.35 μ for both.
    ``crown_width_m`` is the crown size the hedge shows across the row (``crown_width``).
    """
    n = len(evidence)
    spacing = spacing_m / PROFILE_BIN_M
    width = max(crown_width_m, PROFILE_BIN_M) / PROFILE_BIN_M
    max_len = max(int(np.ceil(2.5 * max(spacing, width))), 2)
    cost_of_cut = cut_cost * (1.0 - np.clip(evidence / SADDLE_EVIDENCE, 0.0, 1.0))

    def segment_cost(i: np.ndarray, j: int) -> np.ndarray:
        length = (j - i).astype(float)
        first, last = i == 0, j == n
        mu = np.where(first & last, width, np.where(first | last, 0.5 * (spacing + width), spacing))
        sigma = np.where(first | last, 0.35 * mu, interior_sigma * spacing)
        return ((length - mu) / sigma) ** 2

    best = np.full(n + 1, np.inf)
    best[0] = 0.0
    back = np.zeros(n + 1, int)
    for j in range(1, n + 1):
        i = np.arange(max(j - max_len, 0), j)
        total = best[i] + segment_cost(i, j) + (cost_of_cut[j] if j < n else 0.0)
        k = int(np.argmin(total))
        best[j], back[j] = total[k], i[k]
    segments, j = [], n
    while j > 0:
        segments.append((int(back[j]), j))
        j = int(back[j])
    return segments[::-1]


@dataclass
class _RowProfile:
    """One row band's along-row profiles (bins of ``PROFILE_BIN_M`` from ``start_m``)."""

    start_m: float
    height: np.ndarray
    width: np.ndarray
    stations: np.ndarray
    centre: np.ndarray
    offset_m: float
    band_m: tuple[float, float]

    @property
    def runs(self) -> list[tuple[int, int]]:
        return canopy_runs(self.width <= 0)

    def evidence(self, window_bins: int) -> np.ndarray:
        return boundary_evidence(self.height, self.width, window_bins)


def _row_profiles(
    along: np.ndarray, across: np.ndarray, heights: np.ndarray, cell: float, min_row_m: float
) -> list[_RowProfile]:
    edges = _row_bands(across, min_row_m)
    band = np.searchsorted(edges, across) - 1
    profiles = []
    for k in range(len(edges) - 1):
        sel = band == k
        if sel.sum() < 10:
            continue
        s0 = float(along[sel].min())
        bins = ((along[sel] - s0) / PROFILE_BIN_M).astype(int)
        height, width = _ridge_and_width(bins, int(bins.max()) + 1, heights[sel], across[sel], cell)
        stations, centre = _centre_line(along[sel], across[sel])
        profiles.append(
            _RowProfile(
                s0,
                height,
                width,
                stations,
                centre,
                float(np.median(across[sel])),
                (float(edges[k]), float(edges[k + 1])),
            )
        )
    return profiles


def row_seeds(
    canopy: np.ndarray,
    chm_smooth: np.ndarray,
    grid: Grid,
    spacing_m: float | None = None,
    min_row_spacing_m: float = 3.0,
    bearing_deg: float | None = None,
) -> RowLayout | None:
    """Rows in the canopy mask and one seed per tree along them; None without canopy.

    ``spacing_m``: the planting distance along the rows; unset, the crowns' width across
    the row (``crown_width`` of all rows' hedge widths): where crowns touch, trees stand
    about a crown width apart. (Tried and dropped: the lag of the autocorrelation of the
    boundary evidence; with spacing drawn from 3.5-6 m it picked multiples or noise on 3 of
    6 simulated almond flights, 20-27 of 36 trees found against 27 with the width.)
    ``bearing_deg``: the rows' bearing from north when known; unset, it is found in the
    canopy (:func:`row_direction_from_canopy`).
    """
    points, step = _canopy_points(canopy, grid)
    if len(points) < 10:
        return None
    angle = (
        row_direction_from_canopy(points)
        if bearing_deg is None
        else np.radians(90.0 - bearing_deg)  # x east, y north
    )
    u = np.array([np.cos(angle), np.sin(angle)])
    v = np.array([-u[1], u[0]])
    origin = points.mean(axis=0)
    d = points - origin
    heights = chm_smooth[::step, ::step][canopy[::step, ::step]]
    profiles = _row_profiles(d @ u, d @ v, heights, grid.resolution * step, min_row_spacing_m)
    if not profiles:
        return None
    source = "given"
    if spacing_m is None:  # touching crowns stand about a crown width apart
        spacing_m = crown_width(np.concatenate([p.width for p in profiles]))
        source = "hedge_width"
    window = max(int(round(0.5 * spacing_m / PROFILE_BIN_M)), 1)
    rows, seeds = [], []
    for p in profiles:
        evidence = p.evidence(window)
        width = crown_width(p.width)
        runs = p.runs
        # A stretch's outer trees own the canopy up to the middle of the gaps beside it (the
        # row's ends: all of it), so that no crown edge is left out of its tree.
        reach = [-np.inf] + [0.5 * (b0 + a1) for (_, b0), (a1, _) in zip(runs[:-1], runs[1:])]
        reach = reach + [np.inf]
        bounds, mids = [], []
        for k, (a, b) in enumerate(runs):
            cuts = cut_row(evidence[a:b], spacing_m, width)
            for i, j in cuts:
                mids.append(p.start_m + 0.5 * (a + i + a + j) * PROFILE_BIN_M)
                lo = reach[k] if i == 0 else a + i
                hi = reach[k + 1] if j == b - a else a + j
                bounds.append((p.start_m + lo * PROFILE_BIN_M, p.start_m + hi * PROFILE_BIN_M))
        bounds = np.array(bounds, float).reshape(-1, 2)
        along_mid = np.array(mids, float)
        row = OrchardRow(p.offset_m, p.stations, p.centre, p.band_m, bounds)
        rows.append(row)
        seeds.append(origin + np.outer(along_mid, u) + np.outer(row.across_at(along_mid), v))
    return RowLayout(
        (float(u[0]), float(u[1])),
        (float(origin[0]), float(origin[1])),
        rows,
        float(spacing_m),
        source,
        np.vstack(seeds),
    )
