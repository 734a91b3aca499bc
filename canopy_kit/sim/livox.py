"""Simulated Livox LiDARs: non-repetitive scan patterns written as the drivers write them.

Livox sensors do not spin a column of rings. Their patterns are proprietary; these models
keep what matters to mapping (field of view, point rate, beams, how a frame fills the view
and that the next frame falls elsewhere) and say so:

- ``livox-mid360``: 360° around, ``lidar.vertical_fov`` (-7..52°) up and down, 200,000
  points/s in 4 beams (``line`` 0-3). The head turns once per 0.1 s while the beams nod
  through the vertical field in a triangle wave at 421.37 Hz, a quarter period apart:
  a 0.1 s frame is a zig-zag about 1° apart, sparse and irregular; since 42.137 nods do
  not fit a frame whole, the next frame's zig-zag falls between this one's
  (non-repetitive: coverage grows with integration time).
- ``livox-avia``: forward-looking (+x), a 70.4° circular field, 240,000 points/s in 6
  beams; each beam draws a rosette (two counter-rotating prisms, 80.3 and 64.9 Hz), the
  beams a little apart, so a frame is petals through the centre, densest there.

Every point is cast at its own firing time from the sensor's pose at that time and given
in the sensor frame of that time (motion distortion, as a real driver does). Frames are
``lidar.rate_hz`` long; a frame's ``timebase`` is its first point's time in ns and each
point's ``offset_time`` counts ns from it. ``lidar.output`` ``livox_custom`` writes
livox_ros_driver2 ``CustomMsg``; ``points`` the driver2 PointCloud2 layout (x, y, z,
intensity, tag, line, float64 ``timestamp`` in ns) plus, for evaluation, ``tree_id``.
A CustomMsg has no room for ``tree_id``: those sessions are scored by crown footprints.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from canopy_kit.io.livox import POINT_RECORD

if TYPE_CHECKING:
    from canopy_kit.io.bag_writer import BagWriter
    from canopy_kit.sim.lidar import SimulatedScan, SpinningLidar


@dataclass(frozen=True)
class LivoxPattern:
    """A Livox model's scan pattern (see the module notes)."""

    name: str
    point_rate: float  # points/s over all beams
    lines: int
    forward: bool  # True: a cone about +x (Avia); False: 360° around z (Mid-360)
    half_angle_deg: float = 35.2  # forward: the cone's half angle
    spin_hz: float = 10.0  # around: turns of the head per second
    nod_hz: float = 421.37  # around: beam nods per second (triangle wave)
    prism_hz: tuple[float, float] = (80.3, 64.9)  # forward: the two prisms' rates
    beam_spread_deg: float = 0.8  # forward: angle between neighbouring beams


PATTERNS = {
    "livox-mid360": LivoxPattern("livox-mid360", 200_000.0, 4, forward=False),
    "livox-avia": LivoxPattern("livox-avia", 240_000.0, 6, forward=True),
}


def pattern_directions(
    pattern: LivoxPattern, t: np.ndarray, vertical_fov: tuple[float, float] = (-7.0, 52.0)
) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (N, 3) in the sensor frame and the beam (``line``) of the points fired
    at times ``t`` (s since the sensor started), point k by beam k mod lines."""
    n = len(t)
    line = (np.arange(n) % pattern.lines).astype(np.uint8)
    if pattern.forward:
        r = np.radians(pattern.half_angle_deg) / 2.0
        w1, w2 = 2 * np.pi * np.asarray(pattern.prism_hz)
        a = r * (np.cos(w1 * t) + np.cos(w2 * t))
        b = r * (np.sin(w1 * t) - np.sin(w2 * t))
        spread = np.radians(pattern.beam_spread_deg) * (line - (pattern.lines - 1) / 2.0)
        b = b + spread  # beams side by side, clipped to the field
        theta = np.minimum(np.hypot(a, b), np.radians(pattern.half_angle_deg))
        phi = np.arctan2(b, a)
        dirs = np.column_stack(
            [np.cos(theta), np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi)]
        )
        return dirs, line
    lo, hi = np.radians(vertical_fov[0]), np.radians(vertical_fov[1])
    u = pattern.nod_hz * t + line / pattern.lines
    tri = 2.0 * np.abs(u - np.floor(u + 0.5))  # triangle wave in [0, 1]
    elevation = lo + (hi - lo) * tri
    azimuth = 2 * np.pi * pattern.spin_hz * t
    ce = np.cos(elevation)
    dirs = np.column_stack([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)])
    return dirs, line


@dataclass
class LivoxMessage:
    """One frame as a CustomMsg: its timebase (ns) and points (POINT_RECORD)."""

    timebase_ns: int
    points: np.ndarray

    def write(self, writer: BagWriter, topic: str, frame_id: str) -> None:
        writer.write_livox_custom(topic, self.timebase_ns, self.points, frame_id)


class LivoxFiring:
    """The firing of a :class:`~canopy_kit.sim.lidar.SpinningLidar` whose ``lidar.firing``
    is a Livox model; its ray casting stays the lidar's."""

    def __init__(self, lidar: SpinningLidar) -> None:
        self.lidar = lidar
        self.pattern = PATTERNS[lidar.spec.firing]
        self.start_ns = round(lidar.trajectory.start_time * 1e9)
        self.step_ns = 1e9 / self.pattern.point_rate

    def sweep(self, stamp: float) -> SimulatedScan:
        """The frame that starts at ``stamp``: points fired in [stamp, stamp + period)."""
        from canopy_kit.sim.lidar import SimulatedScan

        lidar, sp = self.lidar, self.lidar.spec
        first = int(np.ceil((round(stamp * 1e9) - self.start_ns) / self.step_ns))
        end = int(
            np.ceil((round((stamp + lidar.sweep_period) * 1e9) - self.start_ns) / self.step_ns)
        )
        k = np.arange(first, end, dtype=np.int64)
        fire_ns = self.start_ns + np.round(k * self.step_ns).astype(np.int64)
        since_start = (fire_ns - self.start_ns) * 1e-9
        dirs, line = pattern_directions(self.pattern, since_start, tuple(sp.vertical_fov))
        times = fire_ns * 1e-9
        pos, mats = lidar.poses_at(times)
        world_dirs = np.einsum("nij,nj->ni", mats, dirs)
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = pos
        rays[:, 3:] = world_dirs
        idx, ranges, prim, intensity = lidar.cast(rays, world_dirs)
        xyz = (dirs[idx] * ranges[:, None]).astype(np.float32)
        timebase = int(fire_ns[0])
        points = np.zeros(len(idx), POINT_RECORD)
        points["offset_time"] = fire_ns[idx] - timebase
        points["x"], points["y"], points["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        points["reflectivity"] = np.clip(np.round(intensity), 0, 255).astype(np.uint8)
        points["line"] = line[idx]
        columns: dict[str, np.ndarray] = {
            "x": xyz[:, 0],
            "y": xyz[:, 1],
            "z": xyz[:, 2],
            "intensity": points["reflectivity"].astype(np.float32),
            "tag": points["tag"],
            "line": points["line"],
            "timestamp": fire_ns[idx].astype(np.float64),  # driver2: absolute ns as float64
        }
        if lidar.truth_field:
            columns["tree_id"] = lidar.scene.tree_id[prim].astype(np.int32)
        message = LivoxMessage(timebase, points) if sp.output == "livox_custom" else None
        return SimulatedScan(timebase * 1e-9, columns, livox=message)
