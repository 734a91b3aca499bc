"""IMU samples moved from the IMU's own frame into the LiDAR frame the odometry runs in.

A rigid body has one angular velocity, so the gyro only turns: ``w_L = R w_I``. The
accelerometer measures the specific force at its own position; at the LiDAR origin,
``r = -t`` away (``t``: the IMU origin in the LiDAR frame), the body's rotation adds the
tangential and centripetal terms ``a x r + w x (w x r)``. The angular acceleration ``a``
comes from a Savitzky-Golay derivative of the gyro over ``DERIVATIVE_WINDOW_S`` (a plain
finite difference would turn the gyro's white noise into decimetres per s² at 0.35 m).
A clock offset between the IMU and the LiDAR moves the IMU's stamps onto the LiDAR clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DERIVATIVE_WINDOW_S = 0.05  # s: keeps vibration up to ~10 Hz, averages the gyro noise


@dataclass(frozen=True)
class ImuMounting:
    """Where the IMU sits in the LiDAR frame and how far its clock is off the LiDAR's."""

    rotation: np.ndarray  # (3, 3) lidar_from_imu
    imu_position: np.ndarray  # (3,) IMU origin in the LiDAR frame, m
    time_offset: float = 0.0  # s, IMU clock minus LiDAR clock

    @property
    def is_identity(self) -> bool:
        """True when the samples need no change."""
        return (
            np.allclose(self.rotation, np.eye(3), atol=1e-12)
            and not np.any(self.imu_position)
            and self.time_offset == 0.0
        )

    def apply(
        self, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times on the LiDAR clock, angular rate and specific force at the LiDAR origin, LiDAR axes."""
        t = np.asarray(t, float) - self.time_offset
        w = np.asarray(gyro, float) @ self.rotation.T
        f = np.asarray(accel, float) @ self.rotation.T
        r = -np.asarray(self.imu_position, float)
        if np.any(r) and len(t) >= 3:
            alpha = angular_acceleration(t, w)
            f = f + np.cross(alpha, r) + np.cross(w, np.cross(w, r))
        return t, w, f


def angular_acceleration(
    t: np.ndarray, omega: np.ndarray, window_s: float = DERIVATIVE_WINDOW_S
) -> np.ndarray:
    """Time derivative of sampled angular rates (rad/s²), smoothed over ``window_s``."""
    from scipy.signal import savgol_filter

    n = len(t)
    if n < 3:
        return np.zeros_like(omega)
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        return np.zeros_like(omega)
    window = max(5, int(round(window_s / dt)) | 1)
    if window > n:
        window = n if n % 2 else n - 1
    if window < 3:
        return np.gradient(omega, t, axis=0)
    order = min(2, window - 1)
    return savgol_filter(omega, window, order, deriv=1, delta=dt, axis=0, mode="interp")
