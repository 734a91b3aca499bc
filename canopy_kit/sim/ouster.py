"""A simulated Ouster OS0/OS1 that records its raw lidar packets (``lidar.output = "ouster_packets"``).

The lidar mode is ``lidar.columns`` x ``lidar.rate_hz`` (512/1024/2048 x 10/20), the UDP
profile ``lidar.ouster_profile``, 16 columns a packet. Beams: ``lidar.rings`` altitudes
spread over ``lidar.vertical_fov`` (top beam first, as Ouster numbers them) with an OS1's
staggered beam azimuths (±1.055°, ±3.164°) and beam origins 15.806 mm (OS1) or 27.67 mm (OS0,
FOV over 80°) off the axis; ``lidar_to_sensor_transform`` is the OS sensors' (yaw 180°,
36.18 mm up). Column ``m`` of rotation ``k`` fires at ``start + (kW + m) / (W·fps)`` at encoder
angle ``2π(1 − m/W)``; every ray is cast from the beam origin along the direction the decoder
(:mod:`canopy_kit.io.ouster`) reconstructs, so decoded points lie on the scene's surfaces,
off only by the range noise and the 1 mm range unit. The sensor clock counts ns from a boot
:data:`BOOT_S` before the drive; each packet is logged at its last column's time. With
``imu.output = "ouster_packets"`` the IMU samples go out as the sensor's LEGACY IMU packets,
each logged :data:`IMU_SEND_NS` after its reading.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from canopy_kit.io.ouster import OusterInfo, column_xyz_tables

if TYPE_CHECKING:
    from canopy_kit.sim.config import LidarSpec
    from canopy_kit.sim.lidar import SimulatedScan, SpinningLidar

BOOT_S = 1234.5  # the sensor was switched on this long before the drive started
IMU_SEND_NS = 52_000  # from an IMU packet's gyro reading to its sending (and logging)
COLUMNS_PER_PACKET = 16
OS1_AZIMUTH_DEG = (3.164, 1.055, -1.055, -3.164)


@dataclass
class OusterPackets:
    """One rotation's lidar packets: log times (s, each packet's last column) and (P, bytes)
    data; ``xyz``/``times``/``ring`` are the simulator's own returns (sensor frame) for checks."""

    stamps: np.ndarray
    data: np.ndarray
    returns: int
    metadata: str
    xyz: np.ndarray
    times: np.ndarray
    ring: np.ndarray


def sensor_info(lidar_spec: LidarSpec) -> OusterInfo:
    """The metadata of the simulated sensor (see the module notes)."""
    rings = int(lidar_spec.rings)
    lo, hi = lidar_spec.vertical_fov
    width, fps = int(lidar_spec.columns), int(round(lidar_spec.rate_hz))
    os0 = hi - lo > 80.0
    to_sensor = np.diag([-1.0, -1.0, 1.0, 1.0])
    to_sensor[2, 3] = 36.18
    return OusterInfo(
        lidar_mode=f"{width}x{fps}",
        profile=lidar_spec.ouster_profile,
        imu_profile="LEGACY",
        columns_per_frame=width,
        fps=fps,
        columns_per_packet=COLUMNS_PER_PACKET,
        pixels_per_column=rings,
        column_window=(0, width - 1),
        beam_altitude_deg=np.linspace(hi, lo, rings) if rings > 1 else np.array([lo]),
        beam_azimuth_deg=np.resize(np.array(OS1_AZIMUTH_DEG), rings),
        beam_origin_mm=27.67 if os0 else 15.806,
        beam_z_mm=0.0,
        lidar_to_sensor=to_sensor,
        imu_to_sensor=np.eye(4),
        prod_line=f"OS-{0 if os0 else 1}-{rings}",
        source="simulated sensor",
    )


def encode_packets(
    info: OusterInfo,
    frame_id: int,
    timestamp_ns: np.ndarray,
    range_mm: np.ndarray,
    reflectivity: np.ndarray,
    signal: np.ndarray,
) -> np.ndarray:
    """A whole rotation's packets, (W / 16, packet_bytes) uint8: column ``m`` fired at
    ``timestamp_ns[m]`` (sensor clock) with per-beam ``range_mm`` (0: no return) etc., (W, H)."""
    p = info.layout
    width, h, cpp = info.columns_per_frame, info.pixels_per_column, info.columns_per_packet
    n_pkt = width // cpp
    out = np.zeros((n_pkt, info.packet_bytes), np.uint8)
    cols = out[:, p.packet_header : p.packet_header + cpp * info.column_bytes].reshape(
        n_pkt, cpp, info.column_bytes
    )

    def put(block: np.ndarray, offset: int, dtype: str, value: np.ndarray) -> None:
        size = np.dtype(dtype).itemsize
        block[..., offset : offset + size] = (
            np.ascontiguousarray(value, dtype).view(np.uint8).reshape(*value.shape, size)
        )

    mid = np.arange(width).reshape(n_pkt, cpp)
    put(cols, 0, "<u8", timestamp_ns.reshape(n_pkt, cpp).astype(np.uint64))
    put(cols, 8, "<u2", mid.astype(np.uint16))
    if info.profile == "LEGACY":
        put(cols, 10, "<u2", np.full((n_pkt, cpp), frame_id % 65536, np.uint16))
        put(cols, 12, "<u4", (mid * 90112 // width).astype(np.uint32))  # encoder ticks
        put(cols, info.column_bytes - 4, "<u4", np.full((n_pkt, cpp), 0xFFFFFFFF, np.uint32))
    else:
        put(out, 0, "<u2", np.ones(n_pkt, np.uint16))  # packet type 1: lidar data
        put(out, 2, "<u2", np.full(n_pkt, frame_id % 65536, np.uint16))
        put(cols, 10, "<u2", np.ones((n_pkt, cpp), np.uint16))  # status bit 0: valid
    chan = cols[..., p.column_header : p.column_header + h * p.channel].reshape(
        n_pkt, cpp, h, p.channel
    )
    shape = (n_pkt, cpp, h)
    units = np.rint(range_mm / p.range_unit_mm).astype(np.uint32).reshape(shape)
    if np.any(units >= 1 << p.range_bits):
        raise ValueError(f"{info.profile}: a range is beyond its {p.range_bits}-bit field")
    put(chan, 0, "<u2" if p.channel == 4 else "<u4", units)
    put(chan, p.reflectivity[0], p.reflectivity[1], reflectivity.reshape(shape))
    if p.signal is not None:
        put(chan, p.signal, "<u2", signal.reshape(shape))
    return out


def check_spec(spec: LidarSpec) -> list[tuple[str, str]]:
    """(setting, problem) for each ``lidar`` setting an Ouster cannot have."""
    problems = []
    mode = f"{spec.columns}x{spec.rate_hz:g}"
    if mode not in ("512x10", "512x20", "1024x10", "1024x20", "2048x10"):
        problems.append(
            (
                "lidar.columns/rate_hz",
                f"an Ouster lidar mode is 512, 1024 or 2048 x 10 or 20 "
                f"(2048 at 10 only), got {mode}",
            )
        )
    if spec.rings not in (16, 32, 64, 128):
        problems.append(("lidar.rings", f"an Ouster has 16, 32, 64 or 128 beams, got {spec.rings}"))
    if spec.frame_id != "os_sensor":
        problems.append(
            (
                "lidar.frame_id",
                "Ouster packets carry no frame; they decode in ouster_ros's "
                f"'os_sensor': set lidar.frame_id = 'os_sensor' (got {spec.frame_id!r})",
            )
        )
    return problems


class OusterFiring:
    """The firing of a :class:`~canopy_kit.sim.lidar.SpinningLidar` set to
    ``output = "ouster_packets"``; its ray casting stays the lidar's."""

    def __init__(self, lidar: SpinningLidar) -> None:
        from canopy_kit.io.ouster import metadata_json

        self.lidar = lidar
        self.info = sensor_info(lidar.spec)
        self.metadata = metadata_json(self.info)
        self.start = lidar.trajectory.start_time
        self.direction, self.offset = column_xyz_tables(self.info)  # sensor frame, (W, H, 3)
        self.beam_origin_m = self.info.beam_origin_mm * 1e-3

    def imu_packet(
        self, t: float, angular_velocity: np.ndarray, linear_acceleration: np.ndarray
    ) -> tuple[float, np.ndarray]:
        """The LEGACY IMU packet of a sample taken at ``t`` (rad/s, m/s² in os_sensor, which
        the simulated IMU's frame is): its log time and 48 bytes (times in ns on the sensor
        clock, acceleration in g, angular velocity in deg/s, float32)."""
        gyro_ts = int(round((t - self.start + BOOT_S) * 1e9))
        times = np.array([gyro_ts + IMU_SEND_NS, gyro_ts, gyro_ts], "<u8")
        values = np.concatenate(
            [np.asarray(linear_acceleration) / 9.80665, np.rad2deg(angular_velocity)]
        ).astype("<f4")
        packet = np.concatenate([times.view(np.uint8), values.view(np.uint8)])
        return t + IMU_SEND_NS * 1e-9, packet

    def sweep(self, stamp: float) -> SimulatedScan:
        """The packets of the rotation that starts at ``stamp``."""
        from canopy_kit.sim.lidar import SimulatedScan

        info, lidar = self.info, self.lidar
        width, h = info.columns_per_frame, info.pixels_per_column
        rate = width * info.fps  # columns per second
        frame = int(round((stamp - self.start) * info.fps))
        first = frame * width
        elapsed = (first + np.arange(width)) / rate  # s since the drive started
        times = self.start + elapsed
        pos, mats = lidar.poses_at(times)
        # a ray starts at the beam origin: the decoder's point minus (r - n) along the beam
        origin = self.offset + self.direction * self.beam_origin_m
        to_world = mats.transpose(0, 2, 1)  # row vectors: p @ R.T
        world_origin = pos[:, None, :] + np.matmul(origin, to_world)
        world_dirs = np.matmul(self.direction, to_world).reshape(-1, 3)
        rays = np.empty((width * h, 6), np.float32)
        rays[:, :3] = world_origin.reshape(-1, 3)
        rays[:, 3:] = world_dirs
        idx, ranges, _, intensity = lidar.cast(rays, world_dirs)
        range_mm = np.zeros(width * h)
        range_mm[idx] = np.maximum(np.rint((ranges + self.beam_origin_m) * 1000.0), 1.0)
        level = np.zeros(width * h)
        level[idx] = np.rint(intensity)
        sensor_ns = np.rint((elapsed + BOOT_S) * 1e9).astype(np.int64)
        data = encode_packets(
            info, frame, sensor_ns, range_mm.reshape(width, h), level.reshape(width, h), level
        )
        last = np.arange(COLUMNS_PER_PACKET - 1, width, COLUMNS_PER_PACKET)
        stamps = self.start + elapsed[last]
        col, beam = np.divmod(idx, h)
        xyz = (
            self.direction[col, beam] * (ranges + self.beam_origin_m)[:, None]
            + self.offset[col, beam]
        )
        packets = OusterPackets(
            stamps, data, len(idx), self.metadata, xyz, times[col], beam.astype(np.uint16)
        )
        return SimulatedScan(float(times[0]), {}, packets)
