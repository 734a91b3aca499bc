"""A per-tree interval for a volume: calibrated ratios, widened for sparse or part-seen crowns.

The interval is ``[low, high] = volume × [r_lo, r_hi]`` with ``r`` the true / estimated
volume ratios measured on simulated crowns of every form (calibration seeds only,
benchmarks/bench_volume_matrix.py --calibrate, docs/VOLUMES.md "The interval"). Two measured
properties of the tree's points pick the ratios and widen them:

- ``surface_fill = n · s² / A`` (n points, s their median 8-NN spacing, A the area of their
  convex hull): 2.2-4.4 on simulated crowns whose foliage fills the envelope, 1.9-2.6 where the
  leaves lie in a thin shell, 1.3-2.0 on crowns deeply cut between lobes and 1.0-1.7 on sparse
  young trees whose few leaves do not outline the envelope (every estimator is then 40-60 %
  low). The fill alone cannot tell the last two apart, so it picks one of three calibrations:
  ``dense`` at or above ``MIN_FILL`` (2.0), ``sparse`` below ``SPARSE_FILL`` (1.2) and, between,
  ``mixed``: ratios measured on every calibration crown in that range, wide enough for both.
- ``scan_coverage``: the share of 16 azimuth sectors around the trunk (the median x, y of
  the lowest 10 % of the tree) that hold points (outer 70 % of its radius). Below
  ``min_coverage`` the crown was seen from one side: the upper bound is divided by the
  coverage (the unseen sectors may hold as much crown as the seen ones). This rule is not
  calibrated: the simulated one-sided scans see the crown all round (coverage ≥ 0.9).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from canopy_kit.volume.adaptive import SPARSE_FILL

# The per-tree table's interval columns (trees.csv), for the recommended estimator.
INTERVAL_COLUMNS = {
    "method": "volume_method",
    "low": "volume_low_m3",
    "high": "volume_high_m3",
    "coverage": "scan_coverage",
    "fill": "surface_fill",
    "flags": "volume_interval_flags",
    "kind": "crown_kind",
}
SECTORS = 16
MIN_COVERAGE = 0.75
MIN_FILL = 2.0  # at or above: a dense crown
# below SPARSE_FILL: a sparse crown (adaptive_alpha then takes the sample-corrected hull);
# between the two: either
TRUNK_SHARE = 0.1
INNER_RADIUS = 0.3  # points nearer the centre than this share of the crown radius are skipped
MARGIN = 0.02  # added on either side of the calibrated ratio quantiles (2 % and 98 %)
TUNED_ON = (401, 402)


@dataclass(frozen=True)
class Calibration:
    """True / estimated volume ratios (low, high) for dense, mixed and sparse crowns."""

    dense: tuple[float, float]
    mixed: tuple[float, float]
    sparse: tuple[float, float]

    def ratios(self, fill: float) -> tuple[str, tuple[float, float]]:
        """The kind of crown a surface fill says (:func:`crown_kind`) and its ratios."""
        kind = crown_kind(fill)
        return kind, getattr(self, kind)


CROWN_KINDS = ("dense", "mixed", "sparse")


def crown_kind(fill: float) -> str:
    """``dense`` at or above ``MIN_FILL``, ``sparse`` below ``SPARSE_FILL``, else ``mixed``."""
    if fill >= MIN_FILL:
        return "dense"
    return "mixed" if fill >= SPARSE_FILL else "sparse"


def calibrate_ratios(
    true_over_estimate: Any, fill: Any, kinds: Any = None
) -> dict[str, tuple[float, float]]:
    """Per kind of crown (``kinds``, the interval's own, else :func:`crown_kind` of ``fill``):
    the 2 % and 98 % quantiles of true / estimate ∓ ``MARGIN``, rounded as ``CALIBRATIONS``
    holds them."""
    ratio = np.asarray(true_over_estimate, dtype=float)
    by_fill = [crown_kind(f) for f in np.asarray(fill, dtype=float)]
    if kinds is None:
        kinds = by_fill
    else:  # a missing kind (NaN or empty) falls back on the fill's
        kinds = [k if isinstance(k, str) and k else f for k, f in zip(kinds, by_fill, strict=True)]
    kinds = np.asarray(kinds)
    out = {}
    for kind in CROWN_KINDS:
        if (kinds == kind).any():
            lo, hi = np.quantile(ratio[kinds == kind], [0.02, 0.98])
            out[kind] = (round(float(lo) - MARGIN, 3), round(float(hi) + MARGIN, 3))
    return out


# The widest of two calibrations on seeds 401-402 (2 % and 98 % quantiles of true/estimate
# per kind of crown, ∓ MARGIN), every crown form with default and harsher crowns (deep lobe
# hollows, leaves in a 0.3 m shell), both-sided and one-sided scans:
# - benchmarks/bench_volume_matrix.py --calibrate: VLP-16 and OS1-64, trees the adaptive
#   preset segments;
# - benchmarks/bench_adaptive_volume.py (the calibration it prints): 16 rings × 512 columns,
#   trees cut by the simulator's labels (coarser scans: it sets most dense upper bounds).
# Both take a one-sided scan as the map of that alley's sweeps alone
# (canopy_kit.truth_map.alley_maps); every bound was set again on 2026-12-05 when they did
# (before, a split of the whole map gave the second alley a thinner scan than a real drive:
# docs/VOLUMES.md, "One-sided scans from the alley maps").
CALIBRATIONS: dict[str, Calibration] = {
    "adaptive_alpha": Calibration(dense=(0.96, 1.064), mixed=(0.903, 2.941), sparse=(0.815, 2.307)),
    "alpha_shape": Calibration(  # α = 0.9 m
        dense=(1.007, 1.228), mixed=(0.934, 3.424), sparse=(1.61, 4.46)
    ),
    "convex_hull": Calibration(dense=(0.888, 1.115), mixed=(0.621, 3.213), sparse=(1.506, 3.975)),
}


@dataclass(frozen=True)
class Interval:
    """A volume's interval and the measurements that set it."""

    low_m3: float
    high_m3: float
    coverage: float
    fill: float
    flags: tuple[str, ...] = ()
    kind: str = ""  # the calibration it took: dense, mixed or sparse (CROWN_KINDS)


def trunk_centre(xyz: np.ndarray) -> np.ndarray:
    """Median x, y of the lowest 10 % of the tree's height (the trunk and the crown's base):
    unlike the median of all points it stays at the stem when one side of the crown is unseen."""
    z = xyz[:, 2]
    low = z <= z.min() + TRUNK_SHARE * (z.max() - z.min())
    return np.median(xyz[low, :2], axis=0)


def scan_coverage(
    xyz: np.ndarray, centre: np.ndarray | None = None, sectors: int = SECTORS
) -> float:
    """Share of ``sectors`` azimuth sectors around ``centre`` (default :func:`trunk_centre`)
    that hold points of the crown's outer part (at least 2, and 10 % of an even share)."""
    c = trunk_centre(xyz) if centre is None else np.asarray(centre, float)
    d = xyz[:, :2] - c
    r = np.hypot(d[:, 0], d[:, 1])
    if len(r) == 0 or float(np.quantile(r, 0.95)) <= 0:
        return 0.0
    keep = r > INNER_RADIUS * float(np.quantile(r, 0.95))
    az = np.arctan2(d[keep, 1], d[keep, 0])
    sector = np.floor((az + np.pi) / (2 * np.pi) * sectors).astype(int) % sectors
    counts = np.bincount(sector, minlength=sectors)
    return float((counts >= max(2.0, 0.1 * keep.sum() / sectors)).mean())


def surface_fill(xyz: np.ndarray, spacing: float | None = None) -> float:
    """``n · s² / A``: how well the points cover their convex hull's surface (2.2-4.4 on dense simulated crowns)."""
    from scipy.spatial import ConvexHull

    from canopy_kit.volume.adaptive import point_spacing

    s = point_spacing(xyz) if spacing is None else spacing
    return float(len(xyz) * s**2 / ConvexHull(xyz).area)


def volume_interval(
    xyz: np.ndarray,
    volume_m3: float,
    method: str,
    centre: np.ndarray | None = None,
    fill: float | None = None,
    kind: str | None = None,
) -> Interval | None:
    """The interval for ``method``'s ``volume_m3`` of the points ``xyz``; None when ``method``
    has no calibration (or the volume is not a positive number). ``fill``: the points'
    :func:`surface_fill` when the estimator has measured it already. ``kind``: the kind of
    crown (``CROWN_KINDS``) when the estimator knows better than the fill (adaptive_alpha's
    thinly scanned lobed crowns: ``mixed`` below ``SPARSE_FILL``)."""
    cal = CALIBRATIONS.get(method)
    if cal is None or not np.isfinite(volume_m3) or volume_m3 <= 0:
        return None
    coverage = scan_coverage(xyz, centre)
    fill = surface_fill(xyz) if fill is None else fill
    flags = []
    if kind is None:
        kind, (lo, hi) = cal.ratios(fill)
    elif kind in CROWN_KINDS:
        lo, hi = getattr(cal, kind)
    else:
        raise ValueError(f"kind must be one of {CROWN_KINDS}, got {kind!r}")
    if kind == "mixed" and fill < SPARSE_FILL:
        flags.append(
            f"deeply lobed crown scanned thinly (surface fill {fill:.2f} < {SPARSE_FILL}, but "
            f"its points are far from a sample of a convex body): wide interval"
        )
    elif kind == "sparse":
        flags.append(
            f"sparse crown (surface fill {fill:.2f} < {SPARSE_FILL}): the points do not "
            f"outline the envelope; on simulated sparse trees the true volume was "
            f"{lo:.2f}-{hi:.2f} × this estimate"
        )
    elif kind == "mixed":
        flags.append(
            f"sparse or deeply lobed crown (surface fill {fill:.2f}, between {SPARSE_FILL} "
            f"and {MIN_FILL}): wide interval"
        )
    if coverage < MIN_COVERAGE:
        hi = hi / max(coverage, 1.0 / SECTORS)
        flags.append(f"one-sided scan: points in {coverage:.0%} of the azimuth sectors")
    return Interval(volume_m3 * lo, volume_m3 * hi, coverage, fill, tuple(flags), kind)
