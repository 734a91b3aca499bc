"""A spinning multi-beam LiDAR ray-cast against the orchard scene, with motion distortion.

Each firing column has its own time and sensor pose, and its points are expressed in the
sensor frame *at that time* (as a real driver does), so a moving robot produces skewed
sweeps that deskewing must undo. Range noise, random dropouts, a minimum and maximum range
and an intensity model (material reflectivity times incidence) are applied.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from canopy_kit.core.extras import needs_extra
from canopy_kit.sim.config import LidarSpec
from canopy_kit.sim.scene import FOLIAGE, GRASS, GROUND, TRELLIS, WOOD, Scene
from canopy_kit.sim.trajectory import Trajectory

if TYPE_CHECKING:
    from canopy_kit.io.bag_writer import BagWriter
    from canopy_kit.sim.livox import LivoxMessage
    from canopy_kit.sim.ouster import OusterPackets
    from canopy_kit.sim.velodyne import VelodynePackets

REFLECTIVITY = {GROUND: 0.30, GRASS: 0.45, WOOD: 0.35, FOLIAGE: 0.60, TRELLIS: 0.40}


@dataclass
class SimulatedScan:
    """One sweep: header stamp (sweep start) and the per-point columns to publish, or the raw
    packets of a simulated Velodyne (``lidar.output = "velodyne_packets"``)."""

    stamp: float
    columns: dict[str, np.ndarray]
    packets: VelodynePackets | OusterPackets | None = None
    livox: LivoxMessage | None = None  # a Livox CustomMsg (canopy_kit.sim.livox)

    @property
    def n_points(self) -> int:
        return self.packets.returns if self.packets is not None else len(self.columns["x"])

    def write(self, writer: BagWriter, topic: str, frame_id: str) -> None:
        """Write the sweep to a bag: a PointCloud2, the packets as one VelodyneScan or as
        Ouster PacketMsgs (one a packet), or a Livox CustomMsg."""
        from canopy_kit.sim.ouster import OusterPackets

        if isinstance(self.packets, OusterPackets):  # its frame is os_sensor, not in the packets
            p = self.packets
            writer.write_ouster_packets(topic, p.stamps, p.data, p.metadata)
        elif self.packets is not None:
            writer.write_velodyne_scan(topic, self.packets.stamps, self.packets.data, frame_id)
        elif self.livox is not None:
            self.livox.write(writer, topic, frame_id)
        else:
            writer.write_points(topic, self.stamp, self.columns, frame_id)


class SpinningLidar:
    """Ray-casts sweeps of a spinning LiDAR moving along a trajectory."""

    def __init__(
        self,
        spec: LidarSpec,
        scene: Scene,
        trajectory: Trajectory,
        rng: np.random.Generator,
        truth_field: bool = True,
    ) -> None:
        self.spec = spec
        self.scene = scene
        self.trajectory = trajectory
        self.rng = rng
        self.truth_field = truth_field
        self._raycaster = scene.raycasting_scene()
        lo, hi = spec.vertical_fov
        self.elevations = np.radians(np.linspace(lo, hi, spec.rings) if spec.rings > 1 else [lo])
        az = 2 * np.pi * np.arange(spec.columns) / spec.columns
        ce = np.cos(self.elevations)
        # (columns, rings, 3) unit directions in the sensor frame.
        self.directions = np.stack(
            [
                np.cos(az)[:, None] * ce[None, :],
                np.sin(az)[:, None] * ce[None, :],
                np.broadcast_to(np.sin(self.elevations), (spec.columns, spec.rings)),
            ],
            axis=-1,
        )
        self._reflectivity = np.array(
            [REFLECTIVITY[m] for m in range(len(REFLECTIVITY))], np.float32
        )
        self._vlp16 = None  # fires like a VLP-16 (canopy_kit.sim.velodyne) instead of in columns
        if spec.firing == "vlp16" or spec.output == "velodyne_packets":
            from canopy_kit.sim.velodyne import Vlp16Firing

            self._vlp16 = Vlp16Firing(self)
        if spec.firing.startswith("livox"):  # a non-repetitive Livox pattern instead
            from canopy_kit.sim.livox import LivoxFiring

            self._vlp16 = LivoxFiring(self)  # type: ignore[assignment]
        self.ouster = None  # records Ouster packets (canopy_kit.sim.ouster)
        if spec.output == "ouster_packets":
            from canopy_kit.sim.ouster import OusterFiring

            self.ouster = OusterFiring(self)

    @property
    def sweep_period(self) -> float:
        return 1.0 / self.spec.rate_hz

    def sweep_times(self) -> np.ndarray:
        """Start times of all complete sweeps within the trajectory."""
        period = self.sweep_period
        n = int(np.floor((self.trajectory.end_time - self.trajectory.start_time) / period)) - 1
        return self.trajectory.start_time + period * np.arange(max(n, 0))

    def _column_poses(self, stamp: float, knots: int = 33) -> tuple[np.ndarray, np.ndarray]:
        """Pose of every firing column: exact at ``knots`` times, linear in between.

        Within 3 ms the robot turns by far less than a milliradian, so interpolating
        rotation matrices element-wise is exact to ~1e-7.
        """
        n_col = self.spec.columns
        col_t = stamp + np.arange(n_col) * (self.sweep_period / n_col)
        return interpolated_poses(self.trajectory, col_t, knots)

    def poses_at(self, times: np.ndarray, knots: int = 33) -> tuple[np.ndarray, np.ndarray]:
        """Sensor positions and rotation matrices at sorted firing ``times`` (as for columns)."""
        return interpolated_poses(self.trajectory, times, knots)

    def cast(
        self, rays: np.ndarray, world_dirs: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Cast (N, 6) float32 rays (origin, unit direction; ``world_dirs`` the directions in
        float64): indices of the rays that return, their noisy ranges, scene primitives and
        intensities (0-255). Range noise, range limits and dropouts are applied here."""
        with needs_extra("open3d"):
            import open3d as o3d

        sp = self.spec
        hit = self._raycaster.cast_rays(o3d.core.Tensor(rays))
        t_hit = hit["t_hit"].numpy().astype(np.float64)
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        normals = hit["primitive_normals"].numpy()
        rng = self.rng
        rng_noise = rng.normal(0.0, sp.range_noise, t_hit.shape)
        ranges = t_hit + rng_noise
        valid = np.isfinite(t_hit) & (ranges >= sp.min_range) & (ranges <= sp.max_range)
        valid &= rng.random(t_hit.shape) >= sp.dropout
        idx = np.flatnonzero(valid)
        ranges = ranges[idx]
        prim = prim[idx]
        material = self.scene.material[prim]
        cos_inc = np.abs(np.sum(normals[idx] * world_dirs[idx], axis=1))
        intensity = self._reflectivity[material] * (0.35 + 0.65 * cos_inc) * self.scene.shade[prim]
        intensity = intensity * 255.0 / (1.0 + (ranges / 40.0) ** 2)
        intensity = np.clip(intensity + rng.normal(0, 2.0, len(idx)), 0, 255).astype(np.float32)
        return idx, ranges, prim, intensity

    def sweep(self, stamp: float) -> SimulatedScan:
        """Simulate the sweep that starts at ``stamp``."""
        if self._vlp16 is not None:
            return self._vlp16.sweep(stamp)
        if self.ouster is not None:
            return self.ouster.sweep(stamp)
        sp = self.spec
        n_col, n_ring = sp.columns, sp.rings
        _, _, idx, ranges, prim, intensity = self._cast_columns(stamp)
        dirs_local = self.directions.reshape(-1, 3)[idx]
        xyz = (dirs_local * ranges[:, None]).astype(np.float32)
        col = idx // n_ring
        ring = (idx % n_ring).astype(np.uint16)
        dt = col * (self.sweep_period / n_col)
        columns: dict[str, np.ndarray] = {
            "x": xyz[:, 0],
            "y": xyz[:, 1],
            "z": xyz[:, 2],
            "intensity": intensity,
        }
        if sp.time_field == "t":
            columns["t"] = np.round(dt * 1e9).astype(np.uint32)
        elif sp.time_field == "time":
            columns["time"] = dt.astype(np.float32)
        else:
            columns["timestamp"] = (stamp + dt).astype(np.float64)
        columns["ring"] = ring
        if self.truth_field:
            columns["tree_id"] = self.scene.tree_id[prim].astype(np.int32)
        return SimulatedScan(stamp, columns)

    def _cast_columns(
        self, stamp: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Cast the columns of the sweep at ``stamp``: ray origins (columns, 3), world
        directions (columns · rings, 3) and :meth:`cast`'s returns, column-major (time
        increases with the index)."""
        n_col, n_ring = self.spec.columns, self.spec.rings
        pos, mats = self._column_poses(stamp)
        world_dirs = np.matmul(self.directions, mats.transpose(0, 2, 1))
        rays = np.empty((n_col, n_ring, 6), np.float32)
        rays[..., :3] = pos[:, None, :]
        rays[..., 3:] = world_dirs
        world_dirs = world_dirs.reshape(-1, 3)
        return (pos, world_dirs, *self.cast(rays.reshape(-1, 6), world_dirs))

    def sweep_world(self, stamp: float) -> tuple[np.ndarray, np.ndarray]:
        """The sweep at ``stamp`` as world points (N, 3) and the scene primitive each hit:
        no sensor frame, no deskewing (for truth-labelled scans; firing in columns)."""
        pos, world_dirs, idx, ranges, prim, _ = self._cast_columns(stamp)
        origin = pos[idx // self.spec.rings]
        return origin + world_dirs[idx] * ranges[:, None], prim


def interpolated_poses(
    trajectory: Trajectory, times: np.ndarray, knots: int = 33
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 3) and rotation matrices (N, 3, 3) at sorted ``times``: exact at ``knots``
    times spread over them, linear in between (see ``SpinningLidar._column_poses``)."""
    knot_t = np.linspace(times[0], times[-1], knots)
    pos_k, rot_k = trajectory.poses(knot_t)
    mats_k = rot_k.as_matrix().reshape(knots, 9)
    pos = np.column_stack([np.interp(times, knot_t, pos_k[:, i]) for i in range(3)])
    mats = np.column_stack([np.interp(times, knot_t, mats_k[:, i]) for i in range(9)])
    return pos, mats.reshape(len(times), 3, 3)
