"""The IMU's rotation in the LiDAR frame, estimated from the drive (hand-eye on rotations).

Both sensors see every rotation of the vehicle. Over the same stretch of time, the LiDAR
odometry's rotation increment ``a`` (rotation vector, LiDAR frame) and the gyro's integral
``b`` (IMU frame) are related by ``a = R b``, ``R`` the mount (lidar_from_imu), because
``R_L = R R_I R^T``. ``R`` is the weighted least-squares (Wahba/Kabsch) solution over the
drive's increments (the odometry's error grows with the rotation it registers), re-weighted
against bad registrations. The turns at the row ends are mostly
about the vertical, which fixes where the IMU's "up" goes but not the rotation about it;
the vehicle's roll and pitch on uneven ground and its vibration fix that one. The 1-sigma
per LiDAR axis says how well each is determined. A clock offset between the two sensors
delays ``b`` against ``a`` and is found by a search over offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.io.bag import ImuSeries
from canopy_kit.mapping import quaternions as quat
from canopy_kit.mapping.imu import RotationTrack, detect_standstill

SPANS_S = (0.3, 1.0)  # increments between registered sweeps about this far apart
MAX_SPAN_S = 2.5  # longer increments (a gap in the registrations) are left out
MIN_INCREMENTS = 30
OBSERVABLE_SIGMA_DEG = (
    0.5  # an axis known better than this is well determined (within 1 deg at 2 sigma)
)
JITTER_RAD = 0.002  # the odometry's rotation error per increment that does not grow with the turn
PROPORTIONAL_ERROR = 0.02  # and the part that does (a share of the increment's rotation)
OFFSET_COARSE_S = 0.01
OFFSET_FINE_S = 0.001


@dataclass
class RotationEstimate:
    """The estimated mount and how well the drive determines it."""

    rotation: np.ndarray  # (3, 3) lidar_from_imu
    sigma_deg: np.ndarray  # (3,) 1-sigma of the rotation about the LiDAR's x, y and z axes
    residual_deg: float  # robust RMS of the increments' misfit
    increments: int  # increments used (after the robust re-weighting)
    time_offset_s: float = (
        0.0  # IMU clock minus LiDAR clock, beyond what the series was corrected by
    )

    @property
    def observable(self) -> bool:
        """True when the drive determines the rotation about every axis."""
        return bool(np.all(self.sigma_deg < OBSERVABLE_SIGMA_DEG))

    def to_dict(self) -> dict:
        """Figures for mapping.json."""
        from canopy_kit.core.frames import rpy_deg

        return {
            "rpy_deg": [round(v, 3) for v in rpy_deg(self.rotation)],
            "sigma_deg": [round(float(v), 4) for v in self.sigma_deg],
            "residual_deg": round(self.residual_deg, 4),
            "increments": self.increments,
            "time_offset_s": round(self.time_offset_s, 4),
            "observable": self.observable,
        }


def increment_pairs(
    times: np.ndarray, spans: tuple[float, ...] = SPANS_S
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)``, ``times[j] - times[i]`` about each span, consecutive within a span."""
    t = np.asarray(times, float)
    first, last = [], []
    for span in spans:
        i = 0
        while i < len(t) - 1:
            j = int(np.searchsorted(t, t[i] + span, side="left"))
            j = min(max(j, i + 1), len(t) - 1)
            if t[j] - t[i] <= MAX_SPAN_S:
                first.append(i)
                last.append(j)
            i = j
    return np.array(first, np.int64), np.array(last, np.int64)


def lidar_increments(poses: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Rotation vectors of ``R_i^T R_j`` (the rotation from sweep i to sweep j, in sweep i's frame)."""
    q = quat.from_matrix(poses[:, :3, :3])
    return quat.to_rotvec(quat.multiply(quat.conjugate(q[i]), q[j]))


def gyro_increments(track: RotationTrack, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Rotation vectors of the integrated gyro from ``t0`` to ``t1`` (the gyro's frame at ``t0``)."""
    return quat.to_rotvec(
        quat.multiply(quat.conjugate(track.quaternions(t0)), track.quaternions(t1))
    )


def kabsch(a: np.ndarray, b: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """The rotation ``R`` minimising ``sum w |a - R b|^2``."""
    w = np.ones(len(a)) if w is None else w
    h = (w[:, None, None] * b[:, :, None] * a[:, None, :]).sum(axis=0)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def increment_weights(b: np.ndarray) -> np.ndarray:
    """Weights ``1 / sigma^2`` of increments: the odometry's jitter plus an error that grows
    with the rotation (measured: a LiDAR pitched 12 deg registers the U-turns' rotation with
    its axis tilted by about 1 %; with equal weights that bias reached 1.2 deg of the mount)."""
    return 1.0 / (JITTER_RAD**2 + (PROPORTIONAL_ERROR * np.linalg.norm(b, axis=1)) ** 2)


def fit_rotation(
    a: np.ndarray, b: np.ndarray, rounds: int = 4
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Robust weighted Kabsch: rotation, 1-sigma per axis (deg), RMS misfit (deg), inlier mask."""
    w = increment_weights(b)
    keep = np.ones(len(a), bool)
    r = kabsch(a, b, w)
    for _ in range(rounds):
        res = np.linalg.norm(a - b @ r.T, axis=1) * np.sqrt(
            w / w.mean()
        )  # in units of a typical sigma
        scale = 1.4826 * float(np.median(res[keep])) + 1e-9
        new = res <= max(3.0 * scale, np.radians(0.02))
        if new.sum() < 3:
            break
        keep = new
        r = kabsch(a[keep], b[keep], w[keep])
    a, b, w = a[keep], b[keep], w[keep]
    res = np.linalg.norm(a - b @ r.T, axis=1)
    dof = max(3 * len(a) - 3, 1)
    s2 = float(np.sum(w * res**2)) / dof  # unit-weight variance of one component
    c = b @ r.T
    info = (
        w[:, None, None]
        * (np.einsum("ij,ij->i", c, c)[:, None, None] * np.eye(3) - c[:, :, None] * c[:, None, :])
    ).sum(axis=0)
    try:
        cov = s2 * np.linalg.inv(info)
        sigma = np.degrees(np.sqrt(np.clip(np.diag(cov), 0.0, None)))
    except np.linalg.LinAlgError:
        sigma = np.full(3, np.inf)
    return r, sigma, float(np.degrees(np.sqrt(np.mean(res**2)))), keep


def estimate_imu_rotation(
    times: np.ndarray, poses: np.ndarray, imu: ImuSeries, max_time_offset: float = 0.0
) -> RotationEstimate | None:
    """The rotation taking the IMU's axes (as in ``imu``) into the LiDAR's, from the drive.

    ``times``/``poses`` are the registered LiDAR odometry sweeps (any gravity-aligned or not
    frame: only increments are used). With ``max_time_offset`` > 0 the IMU clock's offset
    within that bound is searched too. None when the drive has too few usable increments.
    """
    times = np.asarray(times, float)
    order = np.argsort(times)
    times, poses = times[order], np.asarray(poses)[order]
    i, j = increment_pairs(times)
    inside = (times[i] - max_time_offset >= imu.t[0]) & (times[j] + max_time_offset <= imu.t[-1])
    i, j = i[inside], j[inside]
    if len(i) < MIN_INCREMENTS:
        return None
    still = detect_standstill(imu)
    track = RotationTrack(imu, still.gyro_bias)
    a = lidar_increments(poses, i, j)
    t0, t1 = times[i], times[j]

    def fit(offset: float) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        return fit_rotation(a, gyro_increments(track, t0 + offset, t1 + offset))

    offset = 0.0
    if max_time_offset > 0:

        def cost(o: float) -> float:
            r = fit(o)[0]
            res = np.linalg.norm(a - gyro_increments(track, t0 + o, t1 + o) @ r.T, axis=1)
            return float(np.median(res))

        grid = np.arange(-max_time_offset, max_time_offset + 1e-12, OFFSET_COARSE_S)
        best = float(grid[int(np.argmin([cost(o) for o in grid]))])
        fine = np.arange(best - OFFSET_COARSE_S, best + OFFSET_COARSE_S + 1e-12, OFFSET_FINE_S)
        offset = float(fine[int(np.argmin([cost(o) for o in fine]))])
    r, sigma, residual, keep = fit(offset)
    return RotationEstimate(r, sigma, residual, int(keep.sum()), offset)
