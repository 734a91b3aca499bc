"""A simulated VLP-16 that fires like the real one and can record its raw packets.

The firing model is the VLP-16 manual's, with the decoder's tables
(:data:`canopy_kit.io.velodyne.VLP16`): the 16 lasers fire one after another 2.304 µs
apart in the decoder's laser order and elevations, a firing lasts 55.296 µs, a block holds
two firings and a packet 12 blocks (1.327 ms, integer µs timestamps); the head turns at
``lidar.rate_hz`` from azimuth 0 at the start of the drive, so the azimuth advances by
360° × rate × 55.296 µs per firing (0.2° at 10 Hz). A packet carries its blocks' azimuths
in 0.01°: every ray is cast at the time and along the direction the decoder reconstructs
from them (its azimuth interpolation, the REP 103 frame of
:mod:`canopy_kit.io.velodyne_ros`), so the decoded points lie on the scene's surfaces, off
only by the range noise and the 2 mm range unit. One sweep is the packets whose first
firing falls within it (75 or 76 at 10 Hz), stamped with that firing's time.

With ``lidar.output = "points"`` the sweep is written as the PointCloud2 the project's
decoder makes of the same packets (fields intensity, ring, time and, for evaluation,
tree_id), so the two outputs of one seed hold the same points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from canopy_kit.io.velodyne import BLOCKS, VLP16, encode_packets, firing_azimuths
from canopy_kit.io.velodyne_ros import scan_from_packets

if TYPE_CHECKING:
    from canopy_kit.sim.lidar import SimulatedScan, SpinningLidar

PACKET_NS = 1_327_104  # 24 firings of 55.296 µs (rate and range limits: sim.config.validate)


@dataclass
class VelodynePackets:
    """One sweep's data packets: stamps (s, each packet's first firing) and (P, 1206) bytes."""

    stamps: np.ndarray
    data: np.ndarray
    returns: int  # ranges that came back (points once decoded)


class Vlp16Firing:
    """The firing sequence of a :class:`~canopy_kit.sim.lidar.SpinningLidar` set to
    ``firing = "vlp16"`` (or ``output = "velodyne_packets"``); its ray casting stays the lidar's."""

    def __init__(self, lidar: SpinningLidar) -> None:
        self.lidar = lidar
        self.start = lidar.trajectory.start_time
        self._hour = float(np.floor(self.start / 3600.0) * 3600.0)
        self._start_us = round((self.start - self._hour) * 1e6)  # the first packet's counter
        elevation = np.deg2rad(np.asarray(VLP16.elevation_deg)[list(VLP16.slot_laser)])
        self._cos_el, self._sin_el = np.cos(elevation), np.sin(elevation)

    def packets_in(self, stamp: float, period: float) -> tuple[int, int]:
        """First and end index of the packets whose first firing lies in [stamp, stamp + period)."""

        def first_at(t: float) -> int:  # the first packet p with floor(p × 1327.104 µs) ≥ t
            elapsed_ns = round((t - self.start) * 1e6) * 1000
            return -(-elapsed_ns // PACKET_NS)

        return first_at(stamp), first_at(stamp + period)

    def counters(self, first: int, end: int) -> np.ndarray:
        """Sensor timestamps (integer µs since the hour the drive starts in) of packets first..end-1."""
        return self._start_us + np.arange(first, end, dtype=np.int64) * PACKET_NS // 1000

    def sweep(self, stamp: float) -> SimulatedScan:
        """The packets of the sweep that starts at ``stamp``: raw, or decoded into columns."""
        from canopy_kit.sim.lidar import SimulatedScan

        lidar, sp = self.lidar, self.lidar.spec
        counter = self.counters(*self.packets_in(stamp, lidar.sweep_period))
        n_packets = len(counter)
        elapsed_us = (counter - self._start_us)[:, None] + np.arange(BLOCKS) * VLP16.block_us
        block_azimuth = np.mod(np.rint(elapsed_us * 1e-6 * sp.rate_hz * 36000.0), 36000).astype(
            np.int64
        )
        alpha = np.deg2rad(firing_azimuths(block_azimuth, VLP16) * 0.01).reshape(-1, 32)
        times = (
            self._hour + (counter[:, None, None] + VLP16.slot_offsets_us()[None]).reshape(-1) * 1e-6
        )
        flat = self._cos_el[None, :]
        dirs = np.stack(
            [
                flat * np.cos(alpha),
                -flat * np.sin(alpha),
                np.broadcast_to(self._sin_el, alpha.shape),
            ],
            axis=-1,
        ).reshape(-1, 3)
        pos, mats = lidar.poses_at(times)
        world_dirs = np.einsum("nij,nj->ni", mats, dirs)
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = pos
        rays[:, 3:] = world_dirs
        idx, ranges, prim, intensity = lidar.cast(rays, world_dirs)  # idx in firing order
        distance = np.zeros(len(dirs))
        distance[idx] = ranges
        reflectivity = np.zeros(len(dirs))
        reflectivity[idx] = intensity
        shape = (n_packets, BLOCKS, 32)
        data = encode_packets(
            counter, block_azimuth, distance.reshape(shape), reflectivity.reshape(shape)
        )
        stamps = self._hour + counter * 1e-6
        if sp.output == "velodyne_packets":
            return SimulatedScan(float(stamps[0]), {}, VelodynePackets(stamps, data, len(idx)))
        scan = scan_from_packets(stamps, data.tobytes(), sp.frame_id, "simulated VLP-16", 0)
        columns: dict[str, np.ndarray] = {
            "x": scan.xyz[:, 0].astype(np.float32),
            "y": scan.xyz[:, 1].astype(np.float32),
            "z": scan.xyz[:, 2].astype(np.float32),
            **scan.fields,
        }
        if lidar.truth_field:  # the decoder keeps the returns in firing order, as idx lists them
            columns["tree_id"] = lidar.scene.tree_id[prim].astype(np.int32)
        return SimulatedScan(scan.stamp, columns)
