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

from dataclasses import dataclass, field
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


def appended_flags(flags: list[str], notes: list[str]) -> list[str]:
    """Each tree's ``volume_interval_flags`` text with its note added after "; " (the note
    alone where the text was empty), as the interval's own flags are joined."""
    return [f"{f}; {n}" if f else n for f, n in zip(flags, notes, strict=True)]


MIN_FILL = 2.0  # at or above: a dense crown
# below SPARSE_FILL: a sparse crown (adaptive_alpha then takes the sample-corrected hull);
# between the two: either
TRUNK_SHARE = 0.1
INNER_RADIUS = 0.3  # points nearer the centre than this share of the crown radius are skipped
CALIBRATED_HEIGHT_M = 10.0  # the tree families' crowns reach 9.7 m from their lowest to top point
ONE_SIDED = "/one"  # a calibration kind's suffix for trees seen from one side of their row
VOID_SHARE = 0.15  # enclosed empty space above this share of the volume: flagged, spanned
MARGIN = 0.02  # added on either side of the calibrated ratio quantiles (2 % and 98 %)
TUNED_ON = (401, 402)


@dataclass(frozen=True)
class Calibration:
    """True / estimated volume ratios (low, high) per kind of crown, and the parameters of
    the estimator they were measured with: an estimator run with other parameters measures
    something else, so it gets no interval (:func:`volume_interval`)."""

    kinds: dict[str, tuple[float, float]]
    params: dict[str, Any] = field(default_factory=dict)

    def ratios(self, fill: float) -> tuple[str, tuple[float, float]]:
        """The kind of crown a surface fill says (:func:`crown_kind`) and its ratios."""
        kind = crown_kind(fill)
        return kind, self.kinds[kind]

    def mismatch(self, params: dict[str, Any] | None) -> str | None:
        """Which calibrated parameter ``params`` set otherwise (None: none, or not given)."""
        if params is None:
            return None
        for key, value in self.params.items():
            if key in params and params[key] != value:
                return f"{key} = {params[key]!r} (calibrated at {value!r})"
        return None


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
    for kind in dict.fromkeys([*CROWN_KINDS, *kinds.tolist()]):
        if (kinds == kind).any():
            lo, hi = np.quantile(ratio[kinds == kind], [0.02, 0.98])
            out[kind] = (round(float(lo) - MARGIN, 3), round(float(hi) + MARGIN, 3))
    # A tall crown's risk is an unseen top (its upper bound); what puts an estimate above the
    # truth (range noise on the outermost leaves) is the same as on a dense crown, whose many
    # more scans set that bound better: the tall kinds share the dense kinds' lower bound.
    for kind, (lo, hi) in list(out.items()):
        dense = out.get(kind.replace("tall", "dense", 1)) if kind.startswith("tall") else None
        if dense is not None:
            out[kind] = (min(lo, dense[0]), hi)
    return out


# The widest of two calibrations on seeds 401-402 (2 % and 98 % quantiles of true/estimate
# per kind of crown, ∓ MARGIN), every crown form with default and harsher crowns (deep lobe
# hollows, leaves in a 0.3 m shell), both-sided and one-sided scans:
# - benchmarks/bench_volume_matrix.py --calibrate: VLP-16 and OS1-64, trees the adaptive
#   preset segments;
# - benchmarks/bench_adaptive_volume.py (the calibration it prints): 16 rings × 512 columns,
#   trees cut by the simulator's labels (coarser scans: it sets most dense upper bounds).
# Both take a one-sided scan as the map of that alley's sweeps alone
# (canopy_kit.evaluate.truth_map.alley_maps); every bound was set again on 2026-12-05 when they did
# (before, a split of the whole map gave the second alley a thinner scan than a real drive:
# docs/history/VOLUMES_LOG.md, "One-sided scans from the alley maps").
CALIBRATIONS: dict[str, Calibration] = {
    # the tree families' tuning seeds 1000-1001 (envelope, lobe_union, grown; four sensors;
    # both sides and one side: benchmarks/bench_volume_families.py report, "interval
    # calibration"); no family scan was too thin for the envelope's scale, so ``thin`` takes
    # the widest of the dense and small kinds (docs/VOLUMES.md, "Tree families"). ``tall``:
    # crowns over 4.5 m high, whose top a narrow field of view (HDL-32: +10.7°) may miss
    "foliage_envelope": Calibration(
        {
            "dense": (0.961, 1.098),
            "dense/one": (0.973, 1.246),
            "small": (0.894, 1.048),
            "small/one": (0.931, 1.225),
            "tall": (0.961, 1.717),
            "tall/one": (0.973, 1.982),
            "thin": (0.894, 1.246),
            "sparse": (0.936, 0.997),
            "sparse/one": (0.944, 1.033),
        },
        params={
            "alpha": 0.75,
            "spacing_factor": 5.0,
            "fill_voids": True,
            "sparse_fill": 1.2,
            "young_max_m3": 15.0,
            "measurand": "auto",
        },
    ),
    # ``wall``: trees cut from a fruiting wall at their trunks (the ``wall`` preset), against
    # their trunk-midpoint cut; looked-at seeds 0-2 of the fruiting-wall simulator, 2 x 10,
    # 59 trees one-to-one (benchmarks/bench_fruiting_wall.py; held-out seeds: docs/SEGMENTATION.md)
    "adaptive_alpha": Calibration(
        {
            "dense": (0.96, 1.064),
            "mixed": (0.903, 2.941),
            "sparse": (0.815, 2.307),
            "wall": (0.934, 1.171),
        },
        params={
            "alpha_factor": 4.0,
            "offset_factor": 0.425,
            "alpha_min": 0.3,
            "alpha_max": 1.5,
            "fill_voids": True,
            "sparse_fill": 1.2,
            "sample_cell": 0.2,
        },
    ),
    "alpha_shape": Calibration(
        {"dense": (1.007, 1.228), "mixed": (0.934, 3.424), "sparse": (1.61, 4.46)},
        params={"alpha": 0.9},
    ),
    "convex_hull": Calibration(
        {"dense": (0.888, 1.115), "mixed": (0.621, 3.213), "sparse": (1.506, 3.975)}
    ),
}


@dataclass(frozen=True)
class Disagreement:
    """Estimators of one tree that disagree beyond every tree family: why, and their span."""

    flag: str
    low: float
    high: float


#: Ratios (low, high) between two estimators of one tree, the widest seen on the tree
#: families' drives (every sensor and side, tuning seeds 1000-1001,
#: benchmarks/bench_volume_families.py), widened by 10 % either way, per measurand of the
#: first (``None``: any): a tree outside them is unlike every family.
AGREEMENT: dict[tuple[str, str, str | None], tuple[float, float]] = {
    ("foliage_envelope", "convex_hull", "envelope"): (0.51, 1.09),
    ("foliage_envelope", "convex_hull", "ellipsoid"): (1.45, 1.86),
    ("alpha_shape", "convex_hull", None): (0.61, 1.1),
}


def measurand_of_kind(kind: str) -> str:
    """The measurand ``foliage_envelope`` takes for a crown of this ``crown_kind``: a sparse
    young crown's enclosing ellipsoid, any other crown's foliage envelope."""
    return "ellipsoid" if kind == "sparse" else "envelope"


def disagreement(
    method: str, volume_m3: float, others: dict[str, float], kind: str = ""
) -> Disagreement | None:
    """A flag and the span of the estimators when any pair of :data:`AGREEMENT` disagrees
    beyond the families' range on this tree (``others``: the other estimators' volumes;
    ``kind``: the crown kind, ``sparse`` for a young crown's ellipsoid)."""
    volumes = {m: v for m, v in {**others, method: volume_m3}.items() if np.isfinite(v) and v > 0}
    measurand = measurand_of_kind(kind)
    bad, involved = [], set()
    for (a, b, of), (lo, hi) in AGREEMENT.items():
        if of not in (None, measurand if a == method else None) or a not in volumes:
            continue
        if b in volumes:
            ratio = volumes[a] / volumes[b]
            if not lo <= ratio <= hi:
                bad.append(f"{a} = {ratio:.2f} × {b} (tree families {lo:.2f}-{hi:.2f})")
                involved.update((a, b))
    if not bad:
        return None
    span = [volumes[m] for m in involved]
    low, high = min(span), max(span)
    return Disagreement(
        f"estimators disagree beyond every tree family: {'; '.join(bad)}; they span "
        f"{low:.1f}-{high:.1f} m³ (an interval takes that span)",
        low,
        high,
    )


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


def sides_seen(
    centre_xy: np.ndarray, sensor_xy: np.ndarray, crown_radius: float = 2.5, gap: float = 0.5
) -> int:
    """From how many sides of its row the drive saw a tree: 2 when the sensor passed on both
    sides of the line through ``centre_xy`` along the local driving direction, 1 when on one
    only, 0 when never near it. ``sensor_xy``: the sensor's positions (N, 2) in the tree's
    frame; positions within ``crown_radius`` + 4 m (at least 8 m) count, ``gap`` metres or more
    off the line. The driving direction is the principal axis of those positions."""
    c = np.asarray(centre_xy, float)[:2]
    p = np.asarray(sensor_xy, float)[:, :2] - c
    reach = max(8.0, float(crown_radius) + 4.0)
    p = p[np.einsum("ij,ij->i", p, p) <= reach * reach]
    if len(p) < 2:
        return 0
    axis = np.linalg.svd(p - p.mean(axis=0), full_matrices=False)[2][0]
    across = p @ np.array([-axis[1], axis[0]])
    return int((across > gap).any()) + int((across < -gap).any())


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
    params: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
    others: dict[str, float] | None = None,
    sides: int | None = None,
) -> Interval | None:
    """The interval for ``method``'s ``volume_m3`` of the points ``xyz``; None when ``method``
    has no calibration (or the volume is not a positive number).

    ``sides``: from how many sides of its row the drive saw the tree (:func:`sides_seen`);
    seen from one, the kind's one-sided calibration (``<kind>/one``) is taken where there is
    one.

    ``fill``: the points' :func:`surface_fill` when the estimator has measured it already.
    ``kind``: the kind of crown when the estimator knows it (``foliage_envelope``'s dense,
    thin or sparse; ``adaptive_alpha``'s thinly scanned lobed crowns: ``mixed``), else the
    fill says. ``params``: the estimator's parameters; set otherwise than the calibration's,
    the interval has NaN bounds and a flag saying why. ``extra``: the estimator's result
    extra (enclosed voids, :data:`VOID_SHARE`). ``others``: other estimators' volumes of the
    same tree (:func:`disagreement`).
    """
    cal = CALIBRATIONS.get(method)
    if cal is None or not np.isfinite(volume_m3) or volume_m3 <= 0:
        return None
    coverage = scan_coverage(xyz, centre)
    fill = surface_fill(xyz) if fill is None else fill
    mismatch = cal.mismatch(params)
    if mismatch is not None:
        flag = f"no interval: {method} was run with {mismatch}; its calibration does not hold"
        return Interval(np.nan, np.nan, coverage, fill, (flag,), "")
    if kind is None:
        kind = crown_kind(fill)
    elif kind not in cal.kinds:
        raise ValueError(f"kind must be one of {sorted(cal.kinds)}, got {kind!r}")
    ratios = cal.kinds[kind]
    one_sided = f"{kind}{ONE_SIDED}"
    if sides == 1 and one_sided in cal.kinds:
        ratios = cal.kinds[one_sided]
    height = float(np.ptp(np.asarray(xyz)[:, 2]))
    if height > CALIBRATED_HEIGHT_M and "convex_hull" not in (others or {}):
        from canopy_kit.volume.hull import hull_volume

        others = {**(others or {}), "convex_hull": hull_volume(xyz)}
    low, high, flags = interval_bounds(
        method, volume_m3, ratios, kind, fill, coverage, extra, others, height
    )
    if sides == 1:
        flags.insert(0, "seen from one side of its row only: the far side is estimated")
    return Interval(low, high, coverage, fill, tuple(flags), kind)


def interval_bounds(
    method: str,
    volume_m3: float,
    ratios: tuple[float, float],
    kind: str,
    fill: float,
    coverage: float,
    extra: dict[str, Any] | None = None,
    others: dict[str, float] | None = None,
    height_m: float = 0.0,
) -> tuple[float, float, list[str]]:
    """(low, high, flags) of the interval: ``volume_m3`` × the kind's ``ratios``, the upper
    bound raised for a one-sided scan (``coverage`` below ``MIN_COVERAGE``) and, for a crown
    taller than every calibration tree (``height_m`` above :data:`CALIBRATED_HEIGHT_M`: its
    top may be out of the sensor's view), up to the convex hull (``others``); the lower one
    down to the volume without enclosed empty space when that space is large
    (:data:`VOID_SHARE`); both out to the span of estimators that disagree beyond every tree
    family (:func:`disagreement`)."""
    lo, hi = ratios
    flags = _kind_flags(kind, fill, lo, hi, extra)
    if coverage < MIN_COVERAGE:
        hi = hi / max(coverage, 1.0 / SECTORS)
        flags.append(f"one-sided scan: points in {coverage:.0%} of the azimuth sectors")
    low, high = volume_m3 * lo, volume_m3 * hi
    void = float((extra or {}).get("void_m3", 0.0) or 0.0)
    if void > VOID_SHARE * volume_m3:  # the data cannot tell a leafless inside from an unseen one
        without = volume_m3 - void
        flags.append(
            f"enclosed empty space: {void:.1f} m³ ({void / volume_m3:.0%}) inside the foliage is "
            f"counted as crown; without it the volume is {without:.1f} m³ (the interval spans both)"
        )
        low = min(low, without * lo)
    hull = (others or {}).get("convex_hull", np.nan)
    if height_m > CALIBRATED_HEIGHT_M:
        flags.append(
            f"crown {height_m:.1f} m high, taller than every tree the interval was calibrated "
            f"on ({CALIBRATED_HEIGHT_M:g} m): its top may have been out of the sensor's view; "
            "the interval reaches the convex hull"
        )
        if np.isfinite(hull) and hull > high:
            high = hull
    disagree = disagreement(method, volume_m3, others or {}, kind)
    if disagree is not None:
        flags.append(disagree.flag)
        low, high = min(low, disagree.low), max(high, disagree.high)
    return low, high, flags


def _kind_flags(
    kind: str, fill: float, lo: float, hi: float, extra: dict[str, Any] | None
) -> list[str]:
    """The flag a kind of crown carries (none for a dense one)."""
    if kind == "thin":
        alpha = (extra or {}).get("alpha_used", float("nan"))
        return [
            f"scan too thin for the envelope's scale: the closing ball grew to {alpha:.2f} m "
            f"and bridges wider gaps (true volume {lo:.2f}-{hi:.2f} × this estimate on the "
            "tree families)"
        ]
    if kind == "mixed" and fill < SPARSE_FILL:
        return [
            f"deeply lobed crown scanned thinly (surface fill {fill:.2f} < {SPARSE_FILL}, but "
            f"its points are far from a sample of a convex body): wide interval"
        ]
    if kind == "sparse":
        return [
            f"sparse crown (surface fill {fill:.2f} < {SPARSE_FILL}): the points do not "
            f"outline a closed crown; the true volume was {lo:.2f}-{hi:.2f} × this estimate"
        ]
    if kind == "mixed":
        return [
            f"sparse or deeply lobed crown (surface fill {fill:.2f}, between {SPARSE_FILL} "
            f"and {MIN_FILL}): wide interval"
        ]
    return []
