"""A continuous-time trajectory: fused keyframe poses, filled in between with odometry and gyro.

Between keyframes ``a`` and ``b`` the pose at ``t`` is ``K_a · rel(t) · Exp(s · Log(M))``:
``rel`` is the odometry motion since ``a`` (its rotation from the gyro when there is an
IMU), ``M`` the small mismatch that makes the path end exactly at ``K_b`` and
``s = (t - t_a) / (t_b - t_a)``. Used for the per-sweep output poses and for deskewing
every point with its own time.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from canopy_kit.mapping import quaternions as quat
from canopy_kit.mapping.imu import RotationTrack


class ContinuousTrajectory:
    """Poses at any time from keyframes plus a dense reference motion (see module doc)."""

    def __init__(
        self,
        key_times: np.ndarray,
        key_poses: np.ndarray,
        sweep_times: np.ndarray,
        sweep_odometry: np.ndarray,
        rotations: RotationTrack | None = None,
    ) -> None:
        self.key_times = np.asarray(key_times, float)
        self.key_poses = np.asarray(key_poses, float)
        self._key_p = self.key_poses[:, :3, 3]
        self._key_q = quat.from_matrix(self.key_poses[:, :3, :3])
        self.sweep_times = np.asarray(sweep_times, float)
        self._odo_p = np.asarray(sweep_odometry[:, :3, 3], float)
        self._odo_q = quat.from_matrix(sweep_odometry[:, :3, :3])
        self.rotations = rotations
        # Per-segment mismatch M = rel_b^-1 K_a^-1 K_b as (rotation vector, translation).
        n = len(self.key_times)
        self._m_rot = np.zeros((max(n - 1, 0), 3))
        self._m_tr = np.zeros((max(n - 1, 0), 3))
        if n > 1:
            seg = np.arange(n - 1)
            rel_q, rel_t = self._relative(seg, self.key_times[1:])
            ka_inv = quat.conjugate(self._key_q[:-1])
            k_rel_q = quat.multiply(ka_inv, self._key_q[1:])
            k_rel_t = quat.rotate(ka_inv, self._key_p[1:] - self._key_p[:-1])
            rel_inv = quat.conjugate(rel_q)
            self._m_rot = quat.to_rotvec(quat.multiply(rel_inv, k_rel_q))
            self._m_tr = quat.rotate(rel_inv, k_rel_t - rel_t)

    def _odometry_at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = self.sweep_times
        if len(t) == 1:
            return np.repeat(self._odo_p, len(times), 0), np.repeat(self._odo_q, len(times), 0)
        i = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
        s = (times - t[i]) / (t[i + 1] - t[i])
        p = self._odo_p[i] + s[:, None] * (self._odo_p[i + 1] - self._odo_p[i])
        # Rotation: held outside the sweeps' span.
        return p, quat.nlerp(self._odo_q[i], self._odo_q[i + 1], np.clip(s, 0.0, 1.0))

    def _relative(self, seg: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Odometry motion from keyframe ``seg`` to ``times``: quaternions and translations."""
        ta = self.key_times[seg]
        pa, qa = self._odometry_at(ta)
        pt, qt = self._odometry_at(times)
        qa_inv = quat.conjugate(qa)
        trans = quat.rotate(qa_inv, pt - pa)
        if self.rotations is not None:
            rot = quat.multiply(
                quat.conjugate(self.rotations.quaternions(ta)), self.rotations.quaternions(times)
            )
        else:
            rot = quat.multiply(qa_inv, qt)
        return rot, trans

    def quaternions_at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 3) and orientations (N, 4, xyzw), world_from_sensor, at ``times``."""
        times = np.atleast_1d(np.asarray(times, float))
        kt = self.key_times
        if len(kt) == 1:
            seg = np.zeros(len(times), np.int64)
            s = np.zeros(len(times))
        else:
            seg = np.clip(np.searchsorted(kt, times, side="right") - 1, 0, len(kt) - 2)
            s = np.clip((times - kt[seg]) / (kt[seg + 1] - kt[seg]), 0.0, 1.0)
        rel_q, rel_t = self._relative(seg, times)
        if len(kt) > 1:
            rel_t = rel_t + quat.rotate(rel_q, self._m_tr[seg] * s[:, None])
            rel_q = quat.multiply(rel_q, quat.from_rotvec(self._m_rot[seg] * s[:, None]))
        kq = self._key_q[seg]
        return self._key_p[seg] + quat.rotate(kq, rel_t), quat.normalize(quat.multiply(kq, rel_q))

    def at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 3) and rotation matrices (N, 3, 3), world_from_sensor, at ``times``."""
        pos, q = self.quaternions_at(times)
        return pos, quat.to_matrix(q)

    def matrices(self, times: np.ndarray) -> np.ndarray:
        """Poses (N, 4, 4) at ``times``."""
        pos, rot = self.at(times)
        out = np.tile(np.eye(4), (len(pos), 1, 1))
        out[:, :3, :3] = rot
        out[:, :3, 3] = pos
        return out

    def table(self, times: np.ndarray | None = None) -> pd.DataFrame:
        """Poses as a table: time, x, y, z, qx, qy, qz, qw (at the sweep times by default)."""
        times = self.sweep_times if times is None else np.asarray(times, float)
        return pose_table(times, self.matrices(times))


def pose_table(times: np.ndarray, poses: np.ndarray) -> pd.DataFrame:
    """time, x, y, z, qx, qy, qz, qw columns from (N, 4, 4) poses."""
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    return pd.DataFrame(
        {
            "time": times,
            "x": poses[:, 0, 3],
            "y": poses[:, 1, 3],
            "z": poses[:, 2, 3],
            "qx": q[:, 0],
            "qy": q[:, 1],
            "qz": q[:, 2],
            "qw": q[:, 3],
        }
    )
