"""IMU helpers: standstill detection, gravity alignment, gyro bias and a rotation track.

The IMU gives (1) the direction of gravity while the robot stands still, so the map is
z-up from the first scan, (2) the rotation between any two instants over short spans
(deskew within a sweep and the rotation prior between sweeps). Integrated gyro heading
drifts (bias error of ~1e-3 rad/s after a 2 s standstill), so long-term attitude comes
from the LiDAR, the GNSS and the accelerometer in the pose graph, not from the gyro alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from canopy_kit.errors import InputError
from canopy_kit.io.bag import ImuSeries
from canopy_kit.mapping import quaternions as quat
from canopy_kit.mapping.kernels import integrate_gyro

GRAVITY = 9.80665


@dataclass
class Standstill:
    """What the IMU says about the robot's first still period."""

    start: float
    end: float
    gravity_body: np.ndarray  # mean specific force (m/s²) in the IMU frame
    gyro_bias: np.ndarray  # mean angular rate (rad/s)
    accel_norm: float
    found: bool  # False: no standstill, values from the first second of data

    @property
    def duration(self) -> float:
        return self.end - self.start

    def level_rotation(self) -> Rotation:
        """Rotation (yaw 0) that turns the IMU frame z-up: maps measured gravity onto +z."""
        return level_rotation(self.gravity_body)


def level_rotation(specific_force: np.ndarray) -> Rotation:
    """Roll/pitch-only rotation mapping the specific-force direction onto +z (yaw kept 0)."""
    f = np.asarray(specific_force, float)
    norm = float(np.linalg.norm(f))
    if not np.isfinite(norm) or norm < 1e-3:  # no direction: the rotation would be NaN
        raise InputError(
            f"IMU: the specific force averages {norm:.3g} m/s² where the robot stands "
            "still, so it gives no direction of gravity (a dead accelerometer, or "
            "linear_acceleration not filled in?); map without it: --set mapping.use_imu=false"
        )
    f = f / norm
    roll = np.arctan2(f[1], f[2])
    pitch = np.arctan2(-f[0], np.hypot(f[1], f[2]))
    return Rotation.from_euler("YX", [pitch, roll])


def _moving_mean(x: np.ndarray, n: int) -> np.ndarray:
    n = max(1, min(n, len(x)))
    c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x]), axis=0)
    out = (c[n:] - c[:-n]) / n
    pad = np.repeat(out[:1], n - 1, axis=0)
    return np.vstack([pad, out])


def detect_standstill(
    imu: ImuSeries,
    window: float = 0.5,
    gyro_threshold: float = 0.03,
    accel_threshold: float = 0.25,
    max_duration: float = 30.0,
    min_duration: float = 0.5,
) -> Standstill:
    """The initial standstill: smoothed gyro rate and specific force stay near their start values.

    Per-sample IMU noise is large (0.4 m/s² on a typical MEMS unit at 200 Hz), so the
    thresholds apply to ``window``-second moving means.
    """
    t = imu.t
    if len(t) < 10:
        raise InputError(f"IMU topic has only {len(t)} samples; cannot align gravity")
    rate = 1.0 / max(np.median(np.diff(t)), 1e-6)
    n = max(int(round(window * rate)), 1)
    gyro_m = _moving_mean(imu.angular_velocity, n)
    acc_m = _moving_mean(imu.linear_acceleration, n)
    first = min(len(t), 2 * n)
    acc0 = acc_m[first - 1]
    gyro0 = gyro_m[first - 1]
    still = (
        (np.linalg.norm(gyro_m - gyro0, axis=1) < gyro_threshold)
        & (np.linalg.norm(acc_m - acc0, axis=1) < accel_threshold)
        & (t - t[0] <= max_duration)
    )
    end = len(t) if still.all() else int(np.argmin(still))
    end = max(end - n, 0)  # the moving mean lags by one window
    found = end > 0 and t[end - 1] - t[0] >= min_duration
    if not found:
        end = int(np.searchsorted(t, t[0] + 1.0)) or len(t)
    acc = imu.linear_acceleration[:end]
    gyro = imu.angular_velocity[:end]
    gravity = acc.mean(axis=0)
    return Standstill(
        float(t[0]),
        float(t[end - 1]),
        gravity,
        gyro.mean(axis=0) if found else np.zeros(3),
        float(np.linalg.norm(gravity)),
        bool(found),
    )


class RotationTrack:
    """Orientation from integrated (bias-corrected) gyro rates, relative to the first sample.

    Only relative rotations over short spans are meant to be used (see module note).
    Samples can be appended while streaming (:meth:`extend`).
    """

    def __init__(self, imu: ImuSeries, gyro_bias: np.ndarray | None = None) -> None:
        self.bias = np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, float)
        self._t = np.zeros(64)
        self._q = np.zeros((64, 4))
        self._n = 0
        self._omega_last = np.zeros(3)
        self.extend(imu.t, imu.angular_velocity)

    @property
    def t(self) -> np.ndarray:
        return self._t[: self._n]

    @property
    def _quat(self) -> np.ndarray:
        return self._q[: self._n]

    def _append(self, t: np.ndarray, q: np.ndarray) -> None:
        need = self._n + len(t)
        if need > len(self._t):
            cap = max(need, 2 * len(self._t))
            self._t = np.resize(self._t, cap)
            self._q = np.resize(self._q, (cap, 4))
        self._t[self._n : need] = t
        self._q[self._n : need] = q
        self._n = need

    def extend(self, t: np.ndarray, angular_velocity: np.ndarray) -> None:
        """Append gyro samples; samples not after the previous one are dropped."""
        t = np.asarray(t, float).ravel()
        omega = np.asarray(angular_velocity, float).reshape(-1, 3) - self.bias
        last = self._t[self._n - 1] if self._n else -np.inf
        keep = t > np.maximum.accumulate(np.r_[last, t])[:-1]
        t, omega = t[keep], omega[keep]
        if len(t) == 0:
            return
        if self._n == 0:
            self._append(t[:1], np.array([[0.0, 0.0, 0.0, 1.0]]))
            self._omega_last = omega[0]
            t, omega = t[1:], omega[1:]
            if len(t) == 0:
                return
        # Midpoint rule between samples, chained sample by sample (a compiled loop).
        self._append(
            t,
            integrate_gyro(
                self._q[self._n - 1],
                float(self._t[self._n - 1]),
                np.ascontiguousarray(self._omega_last, np.float64),
                np.ascontiguousarray(t),
                np.ascontiguousarray(omega),
            ),
        )
        self._omega_last = omega[-1]

    @property
    def start(self) -> float:
        return float(self.t[0])

    @property
    def end(self) -> float:
        return float(self.t[-1])

    def covers(self, t0: float, t1: float) -> bool:
        """True when ``[t0, t1]`` lies within the IMU's time span."""
        return self.start <= t0 and t1 <= self.end

    def quaternions(self, times: np.ndarray) -> np.ndarray:
        """Orientations (xyzw) at ``times`` (clipped to the IMU span), normalised lerp."""
        times = np.atleast_1d(np.asarray(times, float))
        if self._n < 2:
            return np.tile([0.0, 0.0, 0.0, 1.0], (len(times), 1))
        times = np.clip(times, self.t[0], self.t[-1])
        i = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, len(self.t) - 2)
        frac = ((times - self.t[i]) / (self.t[i + 1] - self.t[i]))[:, None]
        return quat.nlerp(self._quat[i], self._quat[i + 1], frac[:, 0])  # samples ms apart

    def at(self, times: np.ndarray) -> Rotation:
        """Orientations at ``times`` as a scipy Rotation."""
        return Rotation.from_quat(self.quaternions(times))

    def relative_rotvecs(self, t_ref: float, times: np.ndarray) -> np.ndarray:
        """Rotation vectors of ``R(t_ref)^T R(t)``: body at ``t`` seen from the body at ``t_ref``."""
        q_ref = quat.conjugate(self.quaternions(np.array([t_ref])))
        return quat.to_rotvec(quat.multiply(q_ref, self.quaternions(times)))

    def relative(self, t_ref: float, times: np.ndarray) -> Rotation:
        """Rotations ``R(t_ref)^T R(t)`` as a scipy Rotation."""
        return Rotation.from_rotvec(self.relative_rotvecs(t_ref, times))
