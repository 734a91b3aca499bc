"""IMU and GNSS measurements sampled from the true trajectory, with realistic errors."""

from __future__ import annotations

from dataclasses import dataclass

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
    t: np.ndarray
    local_xyz: np.ndarray  # noisy antenna positions in the local frame
    sigma_horizontal: float
    sigma_vertical: float
    status: int


def simulate_imu(trajectory: Trajectory, spec: ImuSpec, rng: np.random.Generator) -> ImuSamples:
    """IMU samples: true rates and specific force plus white noise and slowly wandering bias."""
    t = np.arange(trajectory.start_time, trajectory.end_time, 1.0 / spec.rate_hz)
    omega, force = trajectory.imu(t)
    n = len(t)
    sqrt_rate = np.sqrt(spec.rate_hz)
    gyro_bias = rng.normal(0, spec.gyro_bias_sigma, 3) + np.cumsum(
        rng.normal(0, spec.gyro_bias_sigma * 1e-3, (n, 3)), axis=0)
    accel_bias = rng.normal(0, spec.accel_bias_sigma, 3) + np.cumsum(
        rng.normal(0, spec.accel_bias_sigma * 1e-3, (n, 3)), axis=0)
    gyro = omega + gyro_bias + rng.normal(0, spec.gyro_noise * sqrt_rate, (n, 3))
    accel = force + accel_bias + rng.normal(0, spec.accel_noise * sqrt_rate, (n, 3))
    return ImuSamples(t, gyro, accel)


def simulate_gnss(trajectory: Trajectory, spec: GnssSpec, rng: np.random.Generator) -> GnssFixes:
    """GNSS fixes: a correlated (Gauss-Markov) error plus white noise, or RTK-grade noise."""
    t = np.arange(trajectory.start_time, trajectory.end_time, 1.0 / spec.rate_hz)
    pos = trajectory.antenna_positions(t)
    n = len(t)
    if spec.mode == "rtk":
        sh, sv = spec.rtk_sigma_horizontal, spec.rtk_sigma_vertical
        err = rng.normal(0, 1, (n, 3)) * np.array([sh, sh, sv])
        return GnssFixes(t, pos + err, sh, sv, status=2)
    sh, sv = spec.sigma_horizontal, spec.sigma_vertical
    phi = np.exp(-1.0 / (spec.rate_hz * spec.correlation_time))
    scale = np.array([sh, sh, sv])
    drive = rng.normal(0, 1, (n, 3)) * scale * np.sqrt(1 - phi**2)
    err = np.zeros((n, 3))
    err[0] = rng.normal(0, 1, 3) * scale
    for i in range(1, n):
        err[i] = phi * err[i - 1] + drive[i]
    err += rng.normal(0, 1, (n, 3)) * scale * 0.15
    return GnssFixes(t, pos + err, sh, sv, status=0)
