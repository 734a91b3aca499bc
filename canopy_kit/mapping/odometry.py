"""LiDAR odometry: KISS-ICP's registration and local map, driven with our own motion prior.

``kiss_icp.kiss_icp.KissICP.register_frame`` deskews with a constant-velocity model and
predicts the next pose the same way. Here the sweep arrives already deskewed (with the
gyro when there is an IMU) and the prediction uses the gyro's rotation, so only KISS-ICP's
voxelisation, adaptive threshold, point-to-point ICP and voxel-hash local map are used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.core.extras import needs_extra
from canopy_kit.errors import ProcessingError


@dataclass
class OdometrySettings:
    """The KISS-ICP parameters the mapping stage exposes."""

    voxel_size: float = 1.0
    max_range: float = 60.0
    min_range: float = 1.0
    max_points_per_voxel: int = 20
    max_threads: int = 0  # 0: all cores
    convergence_criterion: float = 1e-4


class LidarOdometry:
    """Scan-to-local-map registration (KISS-ICP core) with an external initial guess."""

    def __init__(self, settings: OdometrySettings, initial_pose: np.ndarray | None = None) -> None:
        with needs_extra("mapping"):
            from kiss_icp.config import KISSConfig
            from kiss_icp.kiss_icp import KissICP

        config = KISSConfig()
        config.data.max_range = settings.max_range
        config.data.min_range = settings.min_range
        config.data.deskew = False
        config.mapping.voxel_size = settings.voxel_size
        config.mapping.max_points_per_voxel = settings.max_points_per_voxel
        config.registration.max_num_threads = settings.max_threads
        config.registration.convergence_criterion = settings.convergence_criterion
        self._kiss = KissICP(config)
        self.pose = np.eye(4) if initial_pose is None else np.array(initial_pose, float)
        self._kiss.last_pose = self.pose.copy()
        self.n_frames = 0
        self.failed = False  # the last alignment gave no valid pose (the guess stands in)

    def register(self, points: np.ndarray, initial_guess: np.ndarray) -> np.ndarray:
        """Register deskewed sensor-frame ``points`` starting from ``initial_guess``; the new pose."""
        pose = self.align(points, initial_guess)
        self.commit(pose)
        return pose

    def align(self, points: np.ndarray, initial_guess: np.ndarray) -> np.ndarray:
        """ICP of ``points`` against the local map (no state change until :meth:`commit`)."""
        kiss = self._kiss
        points = np.asarray(points, np.float64)
        self._source, self._frame_downsample = kiss.voxelize(
            points[np.isfinite(points).all(axis=1)]
        )
        self._guess = checked_pose(initial_guess, "the initial guess")
        self.failed = False
        if self.n_frames == 0 or kiss.local_map.empty():
            return self._guess.copy()
        sigma = kiss.adaptive_threshold.get_threshold()
        if not (np.isfinite(sigma) and sigma > 0):
            self.failed = True
            return self._guess.copy()
        pose = kiss.registration.align_points_to_map(
            points=self._source,
            voxel_map=kiss.local_map,
            initial_guess=self._guess,
            max_correspondance_distance=3 * sigma,
            kernel=sigma,
        )
        if not np.isfinite(pose).all():  # a failed registration: the prediction stands in
            self.failed = True
            return self._guess.copy()
        return checked_pose(pose, "the registration")

    def extend_map(self, points: np.ndarray, pose: np.ndarray) -> None:
        """Add deskewed sensor-frame ``points`` seen from ``pose`` to the local map without
        registering them (the threshold model and the last pose stay as they are). The caller
        thins them to the map's resolution (KISS-ICP's voxelisation is not repeated)."""
        points = np.asarray(points, np.float64)
        points = points[np.isfinite(points).all(axis=1)]
        self._kiss.local_map.update(points, checked_pose(pose, "the predicted pose"))

    def commit(self, pose: np.ndarray) -> None:
        """Accept ``pose`` for the last aligned sweep: threshold model and local map updated."""
        kiss = self._kiss
        pose = checked_pose(pose, "the committed pose")
        if self.n_frames > 0:
            kiss.adaptive_threshold.update_model_deviation(np.linalg.inv(self._guess) @ pose)
        kiss.local_map.update(self._frame_downsample, pose)
        kiss.last_delta = np.linalg.inv(kiss.last_pose) @ pose
        kiss.last_pose = pose
        self.pose = pose
        self.n_frames += 1


def checked_pose(pose: np.ndarray, what: str) -> np.ndarray:
    """A 4x4 pose safe to hand to KISS-ICP (Sophus aborts the process on a rotation that is not
    orthogonal): finite, its rotation re-orthonormalised when rounding has bent it; a
    :class:`ProcessingError` for a non-finite one."""
    pose = np.array(pose, np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ProcessingError(
            f"odometry: {what} is not a finite 4x4 pose; registration cannot go on"
        )
    r = pose[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-9 or np.linalg.det(r) < 0:
        u, _, vt = np.linalg.svd(r)
        r = u @ vt
        if np.linalg.det(r) < 0:
            r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
        pose[:3, :3] = r
    pose[3] = (0.0, 0.0, 0.0, 1.0)
    return pose
