"""GNSS jumps: fixes that the LiDAR odometry contradicts, found before the pose graph.

Multipath under canopy moves a fix by metres for a few seconds. The odometry is good to
centimetres over such spans, so the residual fix minus odometry (odometry fitted onto the
fixes by yaw and shift over the 20 s either side of each second) is the receiver's own
error: a slowly wandering bias plus white noise. A Kalman filter on that residual tests
each fix against the state of one second before (chi-square, 3 degrees of freedom, 99.9 %)
and rejects the fixes that do not fit; they neither update the filter nor reach the graph.
A change of receiver mode (RTK lost: a new constant offset) re-opens the bias; a run of
rejections longer than ``MAX_JUMP_S`` is taken for a new level and accepted.

Measured (docs/MAPPING.md, "GNSS as a receiver gives it"): a robust loss in the graph
instead (Cauchy) also ignored jumps, but switched GNSS off where the odometry drifts.
"""

from __future__ import annotations

import numpy as np

from canopy_kit.mapping.fusion import MIN_HEADING_BASELINE, heading_alignment
from canopy_kit.mapping.gnss import quality_changed, white_scatter

JUMP_CHI2 = 16.27  # chi-square, 3 degrees of freedom, 99.9 %
TRIM = 0.7  # share of the fixes an alignment is fitted to
LOCAL_WINDOW_S = 20.0  # s either side: the odometry is fitted onto the fixes over this window
# A run of rejected fixes longer than this is taken for a new level (the receiver's bias
# or the odometry stepped), not a jump: the test re-starts from the fix that ends it.
MAX_JUMP_S = 10.0
JUMP_LAG_S = 1.0  # a fix is tested against the filter as it stood this long before


def odometry_outliers(
    t: np.ndarray,
    xyz: np.ndarray,
    sigma: np.ndarray,
    status: np.ndarray,
    odo_t: np.ndarray,
    odo_xyz: np.ndarray,
    correlation_time: float,
    white_fraction: float,
    odometry_sigma: float = 0.015,
    odometry_drift: float = 0.01,
) -> np.ndarray:
    """Fixes the odometry contradicts (jumps): True where a fix is rejected.

    ``xyz`` are local fix positions at ``t`` with their sigma and status, ``odo_xyz``
    odometry positions at ``odo_t`` (any frame: fitted onto the fixes around each second).
    The fix-minus-odometry residual is the receiver's bias: a Gauss-Markov process
    (``correlation_time``, the correlated share of ``sigma``) plus white noise (the
    ``white_fraction`` of ``sigma`` or the scatter seen, if larger), odometry jitter
    ``odometry_sigma`` and drift ``odometry_drift`` per metre travelled.
    """
    flagged = np.zeros(len(t), bool)
    inside = np.flatnonzero((t >= odo_t[0]) & (t <= odo_t[-1]))
    if len(inside) < 3 or len(odo_t) < 2:
        return flagged
    pred = np.column_stack([np.interp(t[inside], odo_t, odo_xyz[:, k]) for k in range(3)])
    aligned = _local_alignment(t[inside], pred, xyz[inside], sigma[inside], status[inside])
    if aligned is None:
        return flagged
    residual = xyz[inside] - aligned
    travelled = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pred, axis=0), axis=1))]
    f = float(np.clip(white_fraction, 0.01, 1.0))
    scatter = white_scatter(t, xyz, status)[inside]
    flagged[inside] = _innovation_test(
        t[inside],
        residual,
        sigma[inside],
        scatter,
        status[inside],
        travelled,
        correlation_time,
        f,
        odometry_sigma,
        odometry_drift,
    )
    return flagged


def _rotation_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _robust_fit(
    pred: np.ndarray, fixes: np.ndarray, sigma: np.ndarray, yaw: float | None = None
) -> tuple[float, np.ndarray]:
    """Yaw + shift placing ``pred`` on ``fixes`` (weights 1/sigma²), trimmed: refitted to the
    ``TRIM`` share of fixes that fit best, a few times (jumps stay out of the fit even when
    they are a fifth of the fixes); with ``yaw`` given only the shift is fitted."""
    w = 1.0 / np.maximum(sigma[:, 0], 1e-3) ** 2
    keep = np.ones(len(pred), bool)
    fit_yaw = yaw
    for _ in range(3):
        if yaw is None:
            fit_yaw, shift = heading_alignment(pred[keep], fixes[keep], w[keep])
        else:
            shift = np.average(
                fixes[keep] - pred[keep] @ _rotation_z(yaw).T, axis=0, weights=w[keep]
            )
        placed = pred @ _rotation_z(float(fit_yaw)).T + shift
        norm = np.linalg.norm((fixes - placed)[:, :2], axis=1) / np.maximum(sigma[:, 0], 1e-3)
        cut = int(TRIM * (len(norm) - 1))
        keep = norm <= max(float(np.partition(norm, cut)[cut]), 1.0)
    return float(fit_yaw), shift


def _local_alignment(
    t: np.ndarray,
    pred: np.ndarray,
    fixes: np.ndarray,
    sigma: np.ndarray,
    status: np.ndarray,
    half_window: float = LOCAL_WINDOW_S,
) -> np.ndarray | None:
    """``pred`` placed on ``fixes`` by a fit over the ``half_window`` seconds around each
    second of the drive, to the fixes of the same receiver status only (an RTK fix would
    outweigh every standalone one beside it): a drifting odometry heading stays out of the
    residual. None when the whole drive is too short for a heading."""
    if np.ptp(pred[:, :2], axis=0).max() < MIN_HEADING_BASELINE:
        return None
    global_yaw, _ = _robust_fit(pred, fixes, sigma)
    placed = np.empty_like(pred)
    second = np.floor(t - t[0]).astype(np.int64)
    starts = np.searchsorted(second, np.arange(second[-1] + 2))  # fixes of each second
    for k in np.unique(second):
        centre = t[0] + k + 0.5
        lo, hi = np.searchsorted(t, [centre - half_window, centre + half_window])
        for code in np.unique(status[starts[k] : starts[k + 1]]):
            near = lo + np.flatnonzero(status[lo:hi] == code)
            turns = np.ptp(pred[near, :2], axis=0).max() >= MIN_HEADING_BASELINE
            yaw, shift = _robust_fit(
                pred[near], fixes[near], sigma[near], None if turns else global_yaw
            )
            here = starts[k] + np.flatnonzero(status[starts[k] : starts[k + 1]] == code)
            placed[here] = pred[here] @ _rotation_z(yaw).T + shift
    return placed


def _innovation_test(
    t: np.ndarray,
    r: np.ndarray,
    sigma: np.ndarray,
    scatter: np.ndarray,
    status: np.ndarray,
    travelled: np.ndarray,
    tau: float,
    f: float,
    s_odo: float,
    drift: float,
) -> np.ndarray:
    """Kalman filter on the residual ``r`` (per axis); True where a fix is rejected.

    Each fix is tested against the filter as it stood ``JUMP_LAG_S`` earlier: a filter
    tested against its latest state follows a slow ramp (a receiver repeating its last
    position while the robot drives on) fix by fix and never rejects it.
    """
    out = np.zeros(len(t), bool)
    s_corr = sigma * np.sqrt(max(1.0 - f**2, 1e-4))
    s_white = np.maximum(f * sigma, scatter)

    def predict(state: tuple[int, np.ndarray, np.ndarray], i: int) -> tuple[np.ndarray, np.ndarray]:
        """A state (fix index, bias, variance) carried forward to fix ``i``."""
        j, b, p = state
        if quality_changed(int(status[j]), float(sigma[j, 0]), int(status[i]), float(sigma[i, 0])):
            return np.zeros(3), s_corr[i] ** 2  # a new receiver mode: its own offset
        phi = np.exp(-(t[i] - t[j]) / tau)
        q = s_corr[i] ** 2 * (1 - phi**2) + (drift * (travelled[i] - travelled[j])) ** 2
        return phi * b, phi**2 * p + q

    history = [(0, np.zeros(3), s_corr[0] ** 2)]  # the state after each accepted fix
    times = np.empty(len(t) + 1)  # their times
    times[0] = t[0]
    run_start: int | None = None  # the first fix of the current run of rejected ones
    for i in range(len(t)):
        back = int(np.searchsorted(times[: len(history)], t[i] - JUMP_LAG_S, side="right")) - 1
        lagged = history[max(back, 0)]
        b_test, p_test = predict(lagged, i)
        nu = r[i] - b_test
        if float(np.sum(nu**2 / (p_test + s_white[i] ** 2 + s_odo**2))) > JUMP_CHI2:
            run_start = i if run_start is None else run_start
            if t[i] - t[run_start] <= MAX_JUMP_S:
                out[i] = True
                continue
            # Too long for a jump: a new level (the bias or the odometry stepped). Its fixes
            # are good; the filter starts again from this one.
            out[run_start:i] = False
            history, times[0] = [(i, r[i].copy(), s_corr[i] ** 2)], t[i]
            run_start = None
            continue
        run_start = None
        b, p = predict(history[-1], i)
        k = p / (p + s_white[i] ** 2 + s_odo**2)
        history.append((i, b + k * (r[i] - b), (1 - k) * p))
        times[len(history) - 1] = t[i]
    return out
