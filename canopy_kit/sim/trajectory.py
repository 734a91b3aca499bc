"""The robot's drive: alleys joined by U-turns at the headlands, with a smooth speed profile.

The path is analytic (straight lines and half circles), the speed follows cruise, turn and
acceleration limits with a gentle variation, and the vehicle's roll and pitch follow the
terrain under its wheels plus a small vibration. Poses can be evaluated at any time, so
scans, IMU, GNSS and ground truth are all sampled from the same motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from canopy_kit.sim.config import DriveSpec
from canopy_kit.sim.orchard import Orchard
from canopy_kit.sim.rig import SensorMounts, legacy_lidar_mount

GRAVITY = 9.80665


@dataclass(frozen=True)
class _Line:
    start: np.ndarray
    direction: np.ndarray
    length: float

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy = self.start + s[:, None] * self.direction
        heading = np.full(len(s), np.arctan2(self.direction[1], self.direction[0]))
        return xy, heading

    def reversed(self) -> _Line:
        return _Line(self.start + self.length * self.direction, -self.direction, self.length)


@dataclass(frozen=True)
class _Arc:
    center: np.ndarray
    radius: float
    start_angle: float
    turn: float  # +1 counter-clockwise, -1 clockwise

    @property
    def length(self) -> float:
        return np.pi * self.radius

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ang = self.start_angle + self.turn * s / self.radius
        xy = self.center + self.radius * np.column_stack([np.cos(ang), np.sin(ang)])
        return xy, ang + self.turn * np.pi / 2

    def reversed(self) -> _Arc:
        return _Arc(self.center, self.radius, self.start_angle + self.turn * np.pi, -self.turn)


class Trajectory:
    """Vehicle and sensor poses over time for one session (local frame).

    The vehicle frame has its origin on the ground midway between the wheels; ``mounts``
    place the LiDAR, the IMU and the antenna on it (default: all three at one point,
    ``mount_height`` above the ground, pitched ``mount_pitch_deg``). :meth:`poses` gives
    the LiDAR's poses, :meth:`imu` what the IMU measures in its own frame.
    """

    def __init__(
        self,
        orchard: Orchard,
        spec: DriveSpec,
        mount_height: float,
        rng: np.random.Generator,
        t0: float = 1.7e9,
        mount_pitch_deg: float = 0.0,
        mounts: SensorMounts | None = None,
    ) -> None:
        self.orchard = orchard
        self.spec = spec
        self.mount_height = mount_height
        self.t0 = t0
        if mounts is None:
            lidar = legacy_lidar_mount(mount_height, mount_pitch_deg)
            self.base_from_lidar, self.base_from_imu, self.base_from_antenna = lidar, lidar, lidar
        else:
            self.base_from_lidar = mounts.base_from_lidar
            self.base_from_imu = mounts.base_from_imu
            self.base_from_antenna = mounts.base_from_antenna
        self.segments, self.turn_flags = _plan_segments(orchard, spec)
        starts = np.concatenate([[0.0], np.cumsum([seg.length for seg in self.segments])])
        self._seg_start = starts
        self.length = float(starts[-1])
        self._build_timing(rng)
        self._vib = [
            (rng.uniform(1.0, 4.0), rng.uniform(0, 2 * np.pi), rng.normal(0, 1)) for _ in range(12)
        ]

    # -- timing ---------------------------------------------------------------------------
    def _speed_profile(self, s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        sp = self.spec
        on_turn = np.zeros(len(s), bool)
        for k, is_turn in enumerate(self.turn_flags):
            if is_turn:
                on_turn |= (s >= self._seg_start[k]) & (s < self._seg_start[k + 1])
        lam = rng.uniform(12.0, 25.0)
        phase = rng.uniform(0, 2 * np.pi)
        cruise = sp.cruise_speed + sp.speed_variation * np.sin(2 * np.pi * s / lam + phase)
        ds = s[1] - s[0]
        # Smooth the targets so speed changes ramp instead of stepping.
        from scipy.ndimage import gaussian_filter1d

        v = gaussian_filter1d(
            np.where(on_turn, sp.turn_speed, cruise), sigma=1.5 / ds, mode="nearest"
        )
        # Acceleration limits: forward and backward passes on v² (v dv/ds <= a).
        v[0] = 0.0
        for i in range(1, len(v)):
            v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * sp.acceleration * ds))
        v[-1] = 0.0
        for i in range(len(v) - 2, -1, -1):
            v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * sp.acceleration * ds))
        return v

    def _build_timing(self, rng: np.random.Generator) -> None:
        ds = 0.01
        s = np.arange(0.0, self.length + ds, ds)
        s[-1] = min(s[-1], self.length)
        v = self._speed_profile(s, rng)
        dt = 2 * ds / (v[:-1] + v[1:])
        t_moving = np.concatenate([[0.0], np.cumsum(dt)])
        self.start_time = self.t0
        self.move_start = self.t0 + self.spec.start_still
        self.move_end = self.move_start + float(t_moving[-1])
        self.end_time = self.move_end + self.spec.end_still
        self._t_of_s = self.move_start + t_moving
        self._s = s
        # A C2 spline of s(t), so the IMU's finite differences see a smooth acceleration.
        from scipy.interpolate import CubicSpline

        self._s_of_t = CubicSpline(self._t_of_s, s)

    @property
    def duration(self) -> float:
        return self.end_time - self.start_time

    def arc_length(self, t: np.ndarray) -> np.ndarray:
        """Distance travelled along the path at times ``t``."""
        t = np.asarray(t, float)
        return np.where(
            t <= self.move_start,
            0.0,
            np.where(
                t >= self.move_end,
                self.length,
                self._s_of_t(np.clip(t, self.move_start, self.move_end)),
            ),
        )

    # -- geometry -------------------------------------------------------------------------
    def _xy_heading(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy = np.zeros((len(s), 2))
        heading = np.zeros(len(s))
        k = np.clip(
            np.searchsorted(self._seg_start, s, side="right") - 1, 0, len(self.segments) - 1
        )
        for j in np.unique(k):
            m = k == j
            xy[m], heading[m] = self.segments[j].at(s[m] - self._seg_start[j])
        return xy, heading

    def _vibration(self, t: np.ndarray) -> np.ndarray:
        out = np.zeros((len(t), 3))
        amp = np.radians(self.spec.vibration_deg)
        moving = np.clip((t - self.move_start) / 1.0, 0, 1) * np.clip(
            (self.move_end - t) / 1.0, 0, 1
        )
        for i, (f, ph, a) in enumerate(self._vib):
            out[:, i % 3] += amp * a * np.sin(2 * np.pi * f * (t - self.t0) + ph) / 2.0
        return out * moving[:, None]

    def poses(self, t: np.ndarray) -> tuple[np.ndarray, Rotation]:
        """LiDAR positions (N, 3) and orientations at times ``t`` (seconds, absolute)."""
        return self.mounted_poses(t, self.base_from_lidar)

    def mounted_poses(
        self, t: np.ndarray, base_from_sensor: np.ndarray
    ) -> tuple[np.ndarray, Rotation]:
        """Positions and orientations of a frame mounted on the vehicle at ``base_from_sensor``."""
        position, body = self.vehicle_poses(t)
        mount = np.asarray(base_from_sensor, float)
        return position + body.apply(mount[:3, 3]), body * Rotation.from_matrix(mount[:3, :3])

    def antenna_positions(self, t: np.ndarray) -> np.ndarray:
        """Positions (N, 3) of the GNSS antenna's phase centre."""
        return self.mounted_poses(t, self.base_from_antenna)[0]

    def vehicle_poses(self, t: np.ndarray) -> tuple[np.ndarray, Rotation]:
        """The vehicle frame (origin on the ground between the wheels): positions and orientations."""
        t = np.atleast_1d(np.asarray(t, float))
        s = self.arc_length(t)
        xy, heading = self._xy_heading(s)
        terrain = self.orchard.terrain
        c, sn = np.cos(heading), np.sin(heading)
        half_wb, half_tr = self.spec.wheelbase / 2, self.spec.track / 2
        z_front = terrain.height(xy[:, 0] + c * half_wb, xy[:, 1] + sn * half_wb)
        z_rear = terrain.height(xy[:, 0] - c * half_wb, xy[:, 1] - sn * half_wb)
        z_left = terrain.height(xy[:, 0] - sn * half_tr, xy[:, 1] + c * half_tr)
        z_right = terrain.height(xy[:, 0] + sn * half_tr, xy[:, 1] - c * half_tr)
        pitch = -np.arctan2(z_front - z_rear, self.spec.wheelbase)
        roll = np.arctan2(z_left - z_right, self.spec.track)
        vib = self._vibration(t)
        body = Rotation.from_euler(
            "ZYX", np.column_stack([heading + vib[:, 2], pitch + vib[:, 1], roll + vib[:, 0]])
        )
        return np.column_stack([xy, 0.25 * (z_front + z_rear + z_left + z_right)]), body

    def imu(self, t: np.ndarray, h: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """True angular velocity (rad/s) and specific force (m/s²) in the IMU's frame at times ``t``.

        The IMU's own motion: away from the rotation centre it feels the centripetal and
        tangential accelerations of the vehicle's turns and vibration."""
        t = np.atleast_1d(np.asarray(t, float))
        p_m, r_m = self.mounted_poses(t - h, self.base_from_imu)
        p_0, r_0 = self.mounted_poses(t, self.base_from_imu)
        p_p, r_p = self.mounted_poses(t + h, self.base_from_imu)
        omega = (r_m.inv() * r_p).as_rotvec() / (2 * h)
        acc = (p_p - 2 * p_0 + p_m) / h**2
        specific = r_0.inv().apply(acc + np.array([0.0, 0.0, GRAVITY]))
        return omega, specific


def _plan_segments(orchard: Orchard, spec: DriveSpec) -> tuple[list, list[bool]]:
    """Alleys in serpentine order joined by half-circle U-turns beyond the row ends."""
    osp = orchard.spec
    n_rows = osp.rows
    ks = list(range(n_rows + 1)) if spec.alleys == "all" or n_rows < 2 else list(range(1, n_rows))
    offsets = [(k - 0.5) * osp.row_spacing for k in ks]
    reach = max((max(t.crown.semi_axes[:2]) for t in orchard.trees), default=2.0)
    a_start = orchard.along_range[0] - reach - 3.0
    a_end = orchard.along_range[1] + reach + 3.0
    d, right = orchard.row_direction, orchard.right_direction
    segments: list = []
    flags: list[bool] = []
    for i, off in enumerate(offsets):
        forward = i % 2 == 0
        a0, a1 = (a_start, a_end) if forward else (a_end, a_start)
        start = orchard.to_local(np.array(a0), np.array(off))
        direction = d if forward else -d
        segments.append(_Line(start, direction, abs(a1 - a0)))
        flags.append(False)
        if i + 1 < len(offsets):
            radius = (offsets[i + 1] - off) / 2
            center = orchard.to_local(np.array(a1), np.array(off + radius))
            # Turning right (towards higher across-row offsets): clockwise when driving along d.
            start_vec = -right
            start_angle = float(np.arctan2(start_vec[1], start_vec[0]))
            turn = -1.0 if forward else 1.0
            segments.append(_Arc(center, radius, start_angle, turn))
            flags.append(True)
    if spec.reverse:  # the same path driven from its far end
        segments, flags = [seg.reversed() for seg in reversed(segments)], flags[::-1]
    if spec.lead_in > 0:  # start farther out, driving straight into the first alley
        first = segments[0]
        segments[0] = _Line(
            first.start - spec.lead_in * first.direction,
            first.direction,
            first.length + spec.lead_in,
        )
    return segments, flags
