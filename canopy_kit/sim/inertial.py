"""IMU and GNSS measurements sampled from the true trajectory, with realistic errors."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from canopy_kit.sim.config import GnssSpec, ImuSpec
from canopy_kit.sim.trajectory import Trajectory


@dataclass
class ImuSamples:
    t: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray


@dataclass
class GnssFixes:
    """Fixes as the receiver reports them (NaN position where an outage writes NaN)."""

    t: np.ndarray
    local_xyz: np.ndarray  # reported antenna positions in the local frame
    sigma_horizontal: np.ndarray  # (N,) reported 1-sigma
    sigma_vertical: np.ndarray  # (N,)
    status: np.ndarray  # (N,) NavSatStatus: -1 NO_FIX, 0 FIX, 1 SBAS, 2 GBAS (RTK)
    covariance_type: int = 2  # NavSatFix position_covariance_type
    events: dict = field(default_factory=dict)  # outages, jumps, RTK intervals: the truth


def simulate_imu(trajectory: Trajectory, spec: ImuSpec, rng: np.random.Generator) -> ImuSamples:
    """IMU samples: true rates and specific force plus white noise and slowly wandering bias."""
    t = np.arange(trajectory.start_time, trajectory.end_time, 1.0 / spec.rate_hz)
    omega, force = trajectory.imu(t)
    n = len(t)
    sqrt_rate = np.sqrt(spec.rate_hz)
    gyro_bias = rng.normal(0, spec.gyro_bias_sigma, 3) + np.cumsum(
        rng.normal(0, spec.gyro_bias_sigma * 1e-3, (n, 3)), axis=0
    )
    accel_bias = rng.normal(0, spec.accel_bias_sigma, 3) + np.cumsum(
        rng.normal(0, spec.accel_bias_sigma * 1e-3, (n, 3)), axis=0
    )
    gyro = omega + gyro_bias + rng.normal(0, spec.gyro_noise * sqrt_rate, (n, 3))
    accel = force + accel_bias + rng.normal(0, spec.accel_noise * sqrt_rate, (n, 3))
    return ImuSamples(t, gyro, accel)


def simulate_gnss(trajectory: Trajectory, spec: GnssSpec, rng: np.random.Generator) -> GnssFixes:
    """GNSS fixes: a correlated (Gauss-Markov) error plus white noise, or RTK-grade noise,
    then the receiver's RTK intervals, jumps and outages where ``spec`` asks for them."""
    t = np.arange(trajectory.start_time, trajectory.end_time, 1.0 / spec.rate_hz)
    pos = trajectory.antenna_positions(t)
    n = len(t)
    if spec.mode == "rtk":
        fixes = _fixes(t, pos + _rtk_error(n, spec, rng), spec, rtk=np.ones(n, bool))
    else:
        err = _standalone_error(n, spec, rng)
        rtk = _inside(t - trajectory.start_time, spec.rtk_intervals)
        if (
            rtk.any()
        ):  # drawn after the standalone error: sessions without RTK intervals are unchanged
            err[rtk] = _rtk_error(n, spec, rng)[rtk]
        fixes = _fixes(t, pos + err, spec, rtk)
    return _receiver_events(fixes, spec, rng, trajectory.start_time, trajectory.duration)


def _rtk_error(n: int, spec: GnssSpec, rng: np.random.Generator) -> np.ndarray:
    sh, sv = spec.rtk_sigma_horizontal, spec.rtk_sigma_vertical
    return rng.normal(0, 1, (n, 3)) * np.array([sh, sh, sv])


def _standalone_error(n: int, spec: GnssSpec, rng: np.random.Generator) -> np.ndarray:
    """Gauss-Markov wander (``correlation_time``) plus 15 % white noise."""
    sh, sv = spec.sigma_horizontal, spec.sigma_vertical
    phi = np.exp(-1.0 / (spec.rate_hz * spec.correlation_time))
    scale = np.array([sh, sh, sv])
    drive = rng.normal(0, 1, (n, 3)) * scale * np.sqrt(1 - phi**2)
    err = np.zeros((n, 3))
    err[0] = rng.normal(0, 1, 3) * scale
    for i in range(1, n):
        err[i] = phi * err[i - 1] + drive[i]
    return err + rng.normal(0, 1, (n, 3)) * scale * 0.15


def _fixes(t: np.ndarray, xyz: np.ndarray, spec: GnssSpec, rtk: np.ndarray) -> GnssFixes:
    """Reported sigmas and status per fix: RTK where ``rtk``, standalone elsewhere."""
    sh = np.where(rtk, spec.rtk_sigma_horizontal, spec.sigma_horizontal)
    sv = np.where(rtk, spec.rtk_sigma_vertical, spec.sigma_vertical)
    status = np.where(rtk, 2, spec.standalone_status).astype(int)
    return GnssFixes(t, xyz, sh, sv, status, spec.covariance_type)


def _inside(rel: np.ndarray, intervals: list[list[float]]) -> np.ndarray:
    """Which times (s from the drive start) fall in any ``[start_s, duration_s, ...]``."""
    out = np.zeros(len(rel), bool)
    for item in intervals:
        out |= (rel >= item[0]) & (rel < item[0] + item[1])
    return out


def _random_intervals(
    rng: np.random.Generator,
    count: int,
    durations: list[float],
    drive: float,
    taken: list[list[float]],
) -> list[list[float]]:
    """``count`` intervals in the middle 70 % of the drive, clear of ``taken`` and of each other."""
    out: list[list[float]] = []
    for _ in range(count):
        for _attempt in range(100):
            d = float(rng.uniform(*durations))
            s = float(rng.uniform(0.15 * drive, max(0.85 * drive - d, 0.15 * drive)))
            if all(s + d + 1.0 < a or s > a + b + 1.0 for a, b, *_ in taken + out):
                out.append([round(s, 3), round(d, 3)])
                break
    return out


def _receiver_events(
    fixes: GnssFixes, spec: GnssSpec, rng: np.random.Generator, t0: float, drive: float
) -> GnssFixes:
    """Jumps, then outages applied to ``fixes``; what happened where goes to ``fixes.events``."""
    rel = fixes.t - t0
    outages = [list(o) for o in spec.outages]
    jumps = [list(j) for j in spec.jumps]
    for s, d in _random_intervals(
        rng, spec.jump_count, spec.jump_duration_range, drive, outages + jumps
    ):
        jumps.append([s, d, round(float(rng.uniform(*spec.jump_offset_range)), 3)])
    outages += _random_intervals(
        rng, spec.outage_count, spec.outage_duration_range, drive, outages + jumps
    )
    jump_table = []
    for s, d, offset in jumps:
        angle = rng.uniform(0, 2 * np.pi)
        shift = offset * np.array([np.cos(angle), np.sin(angle)])
        fixes.local_xyz[_inside(rel, [[s, d]]), :2] += shift
        jump_table.append([s, d, float(shift[0]), float(shift[1])])
    out = _inside(rel, outages)
    fixes.status[out] = spec.outage_status
    jumped = _inside(rel, jumps) & ~out
    if spec.outage_fill == "nan":
        fixes.local_xyz[out] = np.nan
    elif spec.outage_fill == "last":
        _hold_last(fixes.local_xyz, out)
    else:
        _drop(fixes, ~out)
    rtk_intervals = (
        [[0.0, float(drive)]] if spec.mode == "rtk" else [list(r) for r in spec.rtk_intervals]
    )
    fixes.events = {
        "time_origin": "s from the drive start (frame.json start_time)",
        "start_time": float(t0),
        "outages": outages,
        "outage_fill": spec.outage_fill,
        "outage_status": spec.outage_status,
        "outage_fixes": int(out.sum()),
        "jumps": jump_table,
        "jump_fixes": int(jumped.sum()),
        "rtk_intervals": rtk_intervals,
        "covariance_type": spec.covariance_type,
        "fixes_written": len(fixes.t),
    }
    return fixes


def _hold_last(xyz: np.ndarray, out: np.ndarray) -> None:
    """Repeat the last position before each run of ``out`` through it (NaN at the very start)."""
    for i in np.flatnonzero(out):
        xyz[i] = xyz[i - 1] if i > 0 else np.nan


def _drop(fixes: GnssFixes, keep: np.ndarray) -> None:
    """Keep only the fixes ``keep`` (a receiver that sends nothing during an outage)."""
    fixes.t, fixes.local_xyz, fixes.status = (
        fixes.t[keep],
        fixes.local_xyz[keep],
        fixes.status[keep],
    )
    fixes.sigma_horizontal, fixes.sigma_vertical = (
        fixes.sigma_horizontal[keep],
        fixes.sigma_vertical[keep],
    )
