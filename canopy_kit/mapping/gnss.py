"""GNSS fixes in the local metric frame, with the error model the pose graph uses.

A standalone receiver's error is not white: it wanders by decimetres to metres over tens
of seconds (multipath, atmosphere). Treating 10 Hz fixes as independent would let that
slow wander bend the trajectory. Fixes are therefore averaged into epochs (``epoch``
seconds) and carry a Gauss-Markov bias state in the graph (see :mod:`.fusion`); only the
white part of the error shrinks with averaging.

A real receiver under canopy also loses its fix, reports NaN, jumps by metres for a few
seconds and switches between standalone, SBAS and RTK (DESIGN.md, "Real robots"). Here:

- a fix is rejected when its status is NO_FIX, its position is not finite or out of range
  (:func:`rejection_reasons`);
- its covariance is used only when ``position_covariance_type`` says it means something
  (1-3) and its diagonal is finite and positive; otherwise the configured default sigmas
  stand in (:func:`reported_sigmas`);
- a fix the LiDAR odometry contradicts (a jump) is found by
  :func:`canopy_kit.mapping.gnss_jumps.odometry_outliers`;
- an epoch averages only fixes of the quality of its best one (no RTK fix averaged with a
  standalone one).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from canopy_kit.core.geo import LocalFrame, utm_epsg
from canopy_kit.errors import InputError
from canopy_kit.io.bag import GnssSeries

NO_FIX = -1  # sensor_msgs/NavSatStatus STATUS_NO_FIX
STATUS_NAMES = {-1: "no_fix", 0: "fix", 1: "sbas", 2: "gbas"}
COVARIANCE_TYPES = {0: "unknown", 1: "approximated", 2: "diagonal_known", 3: "known"}
DIAGONAL_KNOWN = 2  # what a series without covariance types is taken to carry
REJECT_REASONS = ("no_fix", "non_finite", "out_of_range", "jump")
ALTITUDE_RANGE = (-1000.0, 10000.0)  # m: where a ground robot's antenna can be
# Fixes of one epoch within this factor of its best sigma (and of the same status) are
# averaged; a larger change of sigma between epochs counts as a change of receiver mode.
QUALITY_RATIO = 3.0
OUTAGE_MIN_S = 1.0  # a gap between usable fixes longer than this (and 3 fix periods) is an outage


@dataclass
class GnssEpochs:
    """Epoch-averaged GNSS positions in a local frame."""

    t: np.ndarray  # (M,) epoch times, s
    xyz: np.ndarray  # (M, 3) local positions (antenna)
    sigma: np.ndarray  # (M, 3) reported 1-sigma per axis (east, north, up)
    count: np.ndarray  # (M,) fixes per epoch
    frame: LocalFrame
    n_fixes: int  # fixes used
    n_rejected: int  # fixes rejected (any reason)
    status: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # (M,) receiver status
    n_superseded: int = 0  # usable fixes left out of an epoch for better ones beside them
    # (M, 3) white noise of a single fix as seen in the data (see white_scatter)
    scatter: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def covariance_types(gnss: GnssSeries) -> np.ndarray:
    """``position_covariance_type`` per fix; a series that carries none counts as diagonal known."""
    n = len(gnss.t)
    types = np.asarray(gnss.covariance_type)
    return types.astype(int) if types.shape == (n,) else np.full(n, DIAGONAL_KNOWN)


def rejection_reasons(gnss: GnssSeries) -> np.ndarray:
    """Why each fix cannot be used (``no_fix``, ``non_finite``, ``out_of_range``), "" if it can.

    Out of range: latitude beyond ±90°, longitude beyond ±180°, altitude outside
    ``ALTITUDE_RANGE``, or exactly 0°, 0° (what some receivers send before their first fix).
    """
    lat, lon, alt = (np.asarray(a, float) for a in (gnss.latitude, gnss.longitude, gnss.altitude))
    finite = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt)
    with np.errstate(invalid="ignore"):
        in_range = (
            (np.abs(lat) <= 90)
            & (np.abs(lon) <= 180)
            & (alt >= ALTITUDE_RANGE[0])
            & (alt <= ALTITUDE_RANGE[1])
            & ~((lat == 0) & (lon == 0))
        )
    no_fix = np.asarray(gnss.status) <= NO_FIX
    return np.where(
        no_fix, "no_fix", np.where(~finite, "non_finite", np.where(~in_range, "out_of_range", ""))
    ).astype("<U12")


def _no_fix_message(reasons: np.ndarray) -> str:
    counts = ", ".join(
        f"{int((reasons == r).sum())} {r.replace('_', ' ')}"
        for r in REJECT_REASONS
        if (reasons == r).any()
    )
    return f"no usable fix among {len(reasons)} ({counts})"


def local_frame_for(gnss: GnssSeries) -> LocalFrame:
    """A UTM-based local frame whose origin is the first valid fix, rounded to whole metres."""
    reasons = rejection_reasons(gnss)
    ok = reasons == ""
    if not ok.any():
        raise InputError(_no_fix_message(reasons))
    i = int(np.flatnonzero(ok)[0])
    lat, lon, alt = float(gnss.latitude[i]), float(gnss.longitude[i]), float(gnss.altitude[i])
    exact = LocalFrame.at(lat, lon, alt)
    return LocalFrame(
        utm_epsg(lat, lon),
        float(np.round(exact.origin_easting)),
        float(np.round(exact.origin_northing)),
        float(np.round(alt)),
    )


def covariance_used(gnss: GnssSeries) -> np.ndarray:
    """Per fix: does its covariance set its weight (type 1-3, diagonal finite and positive)?"""
    n = len(gnss.t)
    cov = np.asarray(gnss.covariance, float)
    if cov.shape != (n, 9):
        return np.zeros(n, bool)
    diag = cov[:, [0, 4, 8]]
    with np.errstate(invalid="ignore"):
        meaningful = np.all(np.isfinite(diag) & (diag > 0), axis=1)
    return meaningful & np.isin(covariance_types(gnss), (1, 2, 3))


def reported_sigmas(
    gnss: GnssSeries, default_horizontal: float, default_vertical: float
) -> np.ndarray:
    """Per-fix 1-sigma (east, north, up): the covariance's diagonal where it is meaningful
    (:func:`covariance_used`), the defaults elsewhere (type 0 unknown, zeros, NaN)."""
    n = len(gnss.t)
    out = np.tile([default_horizontal, default_horizontal, default_vertical], (n, 1)).astype(float)
    used = covariance_used(gnss)
    out[used] = np.sqrt(np.asarray(gnss.covariance, float)[used][:, [0, 4, 8]])
    return out


def best_quality(
    t: np.ndarray, sigma_h: np.ndarray, status: np.ndarray, epoch: float
) -> tuple[np.ndarray, np.ndarray]:
    """Which fixes an epoch averages: those of the status of its best (smallest sigma) fix,
    within ``QUALITY_RATIO`` of that sigma. Returns (keep mask, epoch index per fix)."""
    bins = np.floor((t - t[0]) / epoch).astype(np.int64)
    _, first, inverse = np.unique(bins, return_index=True, return_inverse=True)
    best = np.minimum.reduceat(sigma_h, first)[inverse]
    at_best = np.flatnonzero(sigma_h == best)
    _, pick = np.unique(inverse[at_best], return_index=True)
    best_status = np.asarray(status)[at_best[pick]]
    keep = (sigma_h <= QUALITY_RATIO * best) & (status == best_status[inverse])
    return keep, bins


def gnss_epochs(
    gnss: GnssSeries,
    frame: LocalFrame,
    epoch: float = 1.0,
    default_horizontal: float = 1.0,
    default_vertical: float = 2.0,
    exclude: np.ndarray | None = None,
) -> GnssEpochs:
    """Valid fixes (less ``exclude``, e.g. jumps) converted to ``frame`` and averaged over
    ``epoch``-second bins, each bin from fixes of one quality (:func:`best_quality`)."""
    reasons = rejection_reasons(gnss)
    if exclude is not None:
        reasons[np.asarray(exclude, bool) & (reasons == "")] = "jump"
    ok = reasons == ""
    n_rejected = int((~ok).sum())
    if not ok.any():
        raise InputError(_no_fix_message(reasons))
    t = gnss.t[ok]
    xyz = frame.to_local(gnss.latitude[ok], gnss.longitude[ok], gnss.altitude[ok])
    sigma = reported_sigmas(gnss, default_horizontal, default_vertical)[ok]
    status = np.asarray(gnss.status)[ok]
    scatter = white_scatter(t, xyz, status)
    keep, bins = best_quality(t, sigma[:, 0], status, epoch)
    _, start, count = np.unique(bins[keep], return_index=True, return_counts=True)
    columns = np.column_stack([t[keep], xyz[keep], sigma[keep], scatter[keep]])
    sums = np.add.reduceat(columns, start, axis=0)
    mean = sums / count[:, None]
    return GnssEpochs(
        mean[:, 0],
        mean[:, 1:4],
        mean[:, 4:7],
        count,
        frame,
        int(keep.sum()),
        n_rejected,
        status[keep][start],
        int((~keep).sum()),
        mean[:, 7:10],
    )


def quality_changed(status_a: int, sigma_a: float, status_b: int, sigma_b: float) -> bool:
    """Did the receiver change mode (status, or sigma by more than ``QUALITY_RATIO``)?

    Each mode has its own constant offset (RTK lost: the standalone bias appears)."""
    ratio = max(sigma_a, sigma_b) / max(min(sigma_a, sigma_b), 1e-9)
    return bool(status_a != status_b or ratio > QUALITY_RATIO)


def white_scatter(
    t: np.ndarray, xyz: np.ndarray, status: np.ndarray, min_triples: int = 20
) -> np.ndarray:
    """The white noise of the fixes per axis and receiver status, from the robust spread of
    second differences of consecutive fixes (the motion's share is millimetres at 10 Hz).

    The nominal white fraction of the reported sigma can underrate it (the simulator's RTK
    fixes are white); 0 where a status has too few consecutive fixes to tell.
    """
    out = np.zeros((len(t), 3))
    if len(t) < 3:
        return out
    dt = np.diff(t)
    even = (dt[1:] < 1.0) & (np.abs(dt[1:] - dt[:-1]) <= 0.2 * dt[:-1])  # evenly spaced triples
    second = np.diff(xyz, n=2, axis=0)  # x(i+1) - 2 x(i) + x(i-1)
    for code in np.unique(status):
        triple = even & (status[2:] == code) & (status[1:-1] == code) & (status[:-2] == code)
        if triple.sum() >= min_triples:
            d = second[triple]
            mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
            out[status == code] = 1.4826 * mad / np.sqrt(6)
    return out


def gaps(
    t: np.ndarray, span: tuple[float, float] | None = None, min_gap: float = OUTAGE_MIN_S
) -> list[tuple[float, float]]:
    """(start, duration) of every stretch longer than ``min_gap`` (and 3 fix periods)
    without a time in ``t``, including before the first and after the last within ``span``."""
    t = np.sort(np.asarray(t, float))
    if span is not None:
        t_all = np.r_[span[0], t[(t >= span[0]) & (t <= span[1])], span[1]]
    else:
        t_all = t
    if len(t_all) < 2:
        return []
    period = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    limit = max(min_gap, 3.0 * period)
    d = np.diff(t_all)
    return [(float(t_all[i]), float(d[i])) for i in np.flatnonzero(d > limit)]


def runs(t: np.ndarray, mask: np.ndarray) -> list[tuple[float, float]]:
    """(start, duration) of each run of consecutive fixes where ``mask`` is True."""
    m = np.r_[False, np.asarray(mask, bool), False]
    edges = np.flatnonzero(np.diff(m.astype(int)))
    return [(float(t[a]), float(t[b - 1] - t[a])) for a, b in zip(edges[::2], edges[1::2])]


# -- diagnostics ------------------------------------------------------------------------------
REJECTED_SHARE_WARN = 0.10  # warn when more of the fixes than this were rejected
OUTAGE_WARN_S = 3.0  # or when the longest outage is longer than this
LISTED = 20  # intervals listed in the diagnostics


def fix_report(
    gnss: GnssSeries, reasons: np.ndarray, span: tuple[float, float] | None = None
) -> dict:
    """What the receiver sent and what was rejected: counts by status, by reason and by
    covariance type, the outages (no usable fix) and jumps, times in s from ``span[0]``
    (the first LiDAR sweep) or from the first fix."""
    status = np.asarray(gnss.status)
    usable = reasons == ""
    origin = span[0] if span is not None else float(gnss.t[0]) if len(gnss.t) else 0.0
    outages = gaps(gnss.t[usable | (reasons == "jump")], span)  # a jump is not an outage
    jumps = runs(gnss.t, reasons == "jump")
    n = len(gnss.t)
    rejected = {r: int((reasons == r).sum()) for r in REJECT_REASONS}
    return {
        "messages": n,
        "by_status": _counts([STATUS_NAMES.get(int(s), "other") for s in status]),
        "covariance_types": _counts(
            [COVARIANCE_TYPES.get(int(c), "other") for c in covariance_types(gnss)]
        ),
        "sigma_from_covariance": int((covariance_used(gnss) & usable).sum()),
        "sigma_default": int((~covariance_used(gnss) & usable).sum()),
        "rejected": rejected,
        "rejected_share": float(sum(rejected.values()) / n) if n else 0.0,
        "outages": _intervals(outages, origin),
        "jumps": _intervals(jumps, origin),
        "time_origin": "first LiDAR sweep" if span is not None else "first fix",
    }


def _counts(names: list[str]) -> dict[str, int]:
    values, counts = np.unique(np.asarray(names, dtype=str), return_counts=True)
    return {str(v): int(c) for v, c in zip(values, counts)}


def _intervals(items: list[tuple[float, float]], origin: float) -> dict:
    longest = max(items, key=lambda x: x[1]) if items else None
    return {
        "count": len(items),
        "longest_s": round(longest[1], 3) if longest else 0.0,
        "longest_at_s": round(longest[0] - origin, 3) if longest else None,
        "total_s": round(float(sum(d for _, d in items)), 3),
        "intervals": [[round(s - origin, 3), round(d, 3)] for s, d in items[:LISTED]],
    }


def report_warning(topic: str, report: dict) -> str | None:
    """One line for the user when many fixes were rejected or the longest outage is long."""
    share, outages = report["rejected_share"], report["outages"]
    if share <= REJECTED_SHARE_WARN and outages["longest_s"] <= OUTAGE_WARN_S:
        return None
    reasons = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in report["rejected"].items() if v)
    text = f"GNSS topic {topic!r}: {100 * share:.0f} % of {report['messages']} fixes rejected" + (
        f" ({reasons})" if reasons else ""
    )
    if outages["count"]:
        text += (
            f"; {outages['count']} outage(s), the longest {outages['longest_s']:.1f} s at "
            f"{outages['longest_at_s']:.1f} s after the {report['time_origin']}"
        )
    return text + "; the trajectory there rests on the LiDAR/IMU odometry alone"


def invalid_fix_warning(topic: str, gnss: GnssSeries, reasons: np.ndarray) -> str | None:
    """One line on fixes the receiver sent with numbers no position has (non-finite, out of
    range) and on covariances it said were known that cannot be (non-finite, not positive):
    the former dropped, the latter replaced by the default sigmas. None when there are none."""
    bad = np.flatnonzero(np.isin(reasons, ("non_finite", "out_of_range")))
    claimed = np.isin(covariance_types(gnss), (1, 2, 3)) & (reasons == "")
    broken_cov = int((claimed & ~covariance_used(gnss)).sum())
    parts = []
    if len(bad):
        parts.append(
            f"{len(bad)} of {len(reasons)} fixes had a non-finite or impossible latitude, "
            f"longitude or altitude and were dropped (first: fix {int(bad[0])} at "
            f"t={float(gnss.t[bad[0]]):.3f} s)"
        )
    if broken_cov:
        parts.append(
            f"{broken_cov} fixes claimed a covariance whose diagonal is not finite and positive; "
            "the default sigmas stood in"
        )
    return f"GNSS topic {topic!r}: " + "; ".join(parts) if parts else None
