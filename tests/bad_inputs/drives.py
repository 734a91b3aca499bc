"""Small synthetic drives through a two-row orchard, written straight to a bag.

No ray casting: each sweep samples the orchard's points within a short range of the
sensor, each point seen from the sensor pose at its own firing time, so deskew, IMU and
GNSS are all consistent. A ``fault`` hook rewrites or drops single sweeps to build the bad
inputs of the catalogue (dropouts, empty scans, NaN points, repeated or backwards stamps).
Writing a 12 s drive takes about a second.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canopy_kit.core.geo import LocalFrame
from canopy_kit.io.bag_writer import BagWriter

T0 = 1_700_000_000.0
FRAME = LocalFrame.at(38.5400, -121.7500, 20.0)  # a pistachio block near Davis, CA
SENSOR_HEIGHT = 1.6
ALLEY_X = 3.0  # the alley between the rows at x = 0 and x = 6
SWEEP = 0.1  # s per revolution (10 Hz)
POINTS_TOPIC, IMU_TOPIC, GNSS_TOPIC = "/points", "/imu/data", "/gps/fix"

Columns = dict[str, np.ndarray]
# (index, stamp, columns) -> the messages to write instead: (header stamp, columns, log time)
Fault = Callable[[int, float, Columns], list[tuple[float, Columns, float]]]


@dataclass
class Drive:
    """A written drive: the bag and what was put in it."""

    path: Path
    fmt: str
    n_scans: int  # sweeps written
    scan_stamps: np.ndarray
    tree_xy: np.ndarray  # (n, 2) crown centres in the local frame
    start_y: float
    speed: float
    standstill: float


@functools.lru_cache(maxsize=4)
def orchard_points(trees_per_row: int = 4, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Ground, trunks and crown shells of two rows (x = 0 and 6 m, trees 5 m apart along y)."""
    from fixtures_sim import synthetic_orchard

    orch = synthetic_orchard(
        rows=2,
        trees_per_row=trees_per_row,
        spacing=5.0,
        row_spacing=6.0,
        crown_radius=1.6,
        density=120.0,
        seed=seed,
        ground_extent=9.0,
    )
    return orch.cloud.xyz, orch.centres


def _position(
    t: np.ndarray, start_y: float, speed: float, standstill: float, accel: float = 1.0
) -> np.ndarray:
    """Sensor position at ``t`` s after the start: at rest, then accelerating along +y."""
    tau = np.clip(t - standstill, 0.0, None)
    ramp = speed / accel if speed > 0 else 0.0
    y = np.where(tau < ramp, 0.5 * accel * tau**2, 0.5 * accel * ramp**2 + speed * (tau - ramp))
    return np.column_stack([np.full_like(t, ALLEY_X), start_y + y, np.full_like(t, SENSOR_HEIGHT)])


def _acceleration(t: np.ndarray, speed: float, standstill: float, accel: float = 1.0) -> np.ndarray:
    tau = t - standstill
    moving = (tau >= 0) & (tau < (speed / accel if speed > 0 else 0.0))
    return np.where(moving, accel, 0.0)


def write_drive(
    path: str | Path,
    fmt: str = "ros2-mcap",
    *,
    duration: float = 12.0,
    speed: float = 1.5,
    standstill: float = 1.5,
    imu: bool = True,
    gnss: bool = True,
    points_per_scan: int = 2500,
    view_range: float = 9.0,
    trees_per_row: int = 4,
    fault: Fault | None = None,
    seed: int = 0,
    imu_frame: str = "lidar",
) -> Drive:
    """Write a drive of ``duration`` s (``standstill`` s at rest first) and return it."""
    rng = np.random.default_rng(seed)
    world, centres = orchard_points(trees_per_row, seed)
    start_y = -4.0
    stamps = T0 + np.arange(0.0, duration, SWEEP)
    written = []
    with BagWriter(path, fmt) as w:
        if imu:
            t_imu = np.arange(0.0, duration + SWEEP, 0.01)
            acc = _acceleration(t_imu, speed, standstill)
            noise = rng.normal(0.0, 0.002, (len(t_imu), 6))
        if gnss:
            t_fix = np.arange(0.0, duration + SWEEP, 0.2)
            fixes = _position(t_fix, start_y, speed, standstill) + rng.normal(
                0, 0.02, (len(t_fix), 3)
            )
            lat, lon, alt = FRAME.to_wgs84(fixes)
        k_imu = k_fix = 0
        for i, stamp in enumerate(stamps):
            rel = stamp - T0
            # IMU and GNSS up to the end of this sweep first (log-time order, as drivers do).
            while imu and k_imu < len(t_imu) and t_imu[k_imu] < rel + SWEEP:
                w.write_imu(
                    IMU_TOPIC,
                    T0 + t_imu[k_imu],
                    noise[k_imu, :3],
                    (noise[k_imu, 3], acc[k_imu] + noise[k_imu, 4], 9.81 + noise[k_imu, 5]),
                    frame_id=imu_frame,
                )
                k_imu += 1
            while gnss and k_fix < len(t_fix) and t_fix[k_fix] < rel + SWEEP:
                w.write_fix(
                    GNSS_TOPIC,
                    T0 + t_fix[k_fix],
                    lat[k_fix],
                    lon[k_fix],
                    alt[k_fix],
                    sigma_h=0.05,
                    sigma_v=0.1,
                    status=2,
                )
                k_fix += 1
            columns = sweep_columns(
                world, rel, start_y, speed, standstill, points_per_scan, view_range, rng
            )
            for header_stamp, cols, log_time in (
                [(stamp, columns, stamp)] if fault is None else fault(i, stamp, columns)
            ):
                write_points_logged(w, header_stamp, cols, log_time)
                written.append(header_stamp)
    return Drive(w.path, fmt, len(written), np.array(written), centres, start_y, speed, standstill)


def write_points_logged(writer: BagWriter, stamp: float, columns: Columns, log_time: float) -> None:
    """A PointCloud2 whose header stamp (sensor clock) differs from its log time (arrival)."""
    from canopy_kit.io import pointcloud2 as pc2

    msg = pc2.build_message(writer.typestore, columns, stamp, "lidar", writer.ros1)
    writer._write(POINTS_TOPIC, "sensor_msgs/msg/PointCloud2", msg, log_time)


def sweep_columns(
    world: np.ndarray,
    rel: float,
    start_y: float,
    speed: float,
    standstill: float,
    n: int,
    view_range: float,
    rng: np.random.Generator,
) -> dict[str, np.ndarray]:
    """One sweep starting ``rel`` s into the drive: x, y, z, intensity and Ouster-style ``t``."""
    centre = _position(np.array([rel]), start_y, speed, standstill)[0]
    near = np.flatnonzero(np.sum((world - centre) ** 2, axis=1) <= view_range**2)
    pick = rng.choice(near, size=min(n, len(near)), replace=False)
    local = world[pick] - centre
    azimuth = np.arctan2(local[:, 1], local[:, 0])
    order = np.argsort(azimuth, kind="stable")
    pick, azimuth = pick[order], azimuth[order]
    offset = (azimuth + np.pi) / (2 * np.pi) * SWEEP * 0.999
    # Each point as seen from where the sensor was when it fired.
    xyz = world[pick] - _position(rel + offset, start_y, speed, standstill)
    return {
        "x": xyz[:, 0].astype(np.float32),
        "y": xyz[:, 1].astype(np.float32),
        "z": xyz[:, 2].astype(np.float32),
        "intensity": rng.uniform(0, 255, len(pick)).astype(np.float32),
        "t": np.round(offset * 1e9).astype(np.uint32),
    }


# -- faults: each returns a ``fault`` hook for :func:`write_drive` -----------------------------
def _same(stamp: float, columns: Columns) -> list[tuple[float, Columns, float]]:
    return [(stamp, columns, stamp)]


def dropout(first: int, last: int) -> Fault:
    """The LiDAR is silent for sweeps ``first..last-1`` (IMU and GNSS keep coming)."""
    return lambda i, stamp, cols: [] if first <= i < last else _same(stamp, cols)


def repeated(*indices: int) -> Fault:
    """Sweeps published twice (same header stamp, logged 1 ms apart), as a restarted driver does."""
    return lambda i, stamp, cols: (
        [(stamp, cols, stamp), (stamp, cols, stamp + 0.001)] if i in indices else _same(stamp, cols)
    )


def stamped_back(index: int, by: float) -> Fault:
    """One sweep whose header stamp is ``by`` s in the past (sensor clock jump), logged in order."""
    return lambda i, stamp, cols: [(stamp - by if i == index else stamp, cols, stamp)]


def emptied(indices: Iterable[int] | None = None) -> Fault:
    """Sweeps with zero points (all sweeps when ``indices`` is None)."""
    chosen = None if indices is None else set(indices)

    def fault(i: int, stamp: float, cols: Columns) -> list[tuple[float, Columns, float]]:
        if chosen is None or i in chosen:
            cols = {k: v[:0] for k, v in cols.items()}
        return _same(stamp, cols)

    return fault


def nonfinite(every: int = 7, all_nan_sweep: int = 40) -> Fault:
    """NaN and +Inf coordinates in every ``every``-th point, and one sweep that is all NaN."""

    def fault(i: int, stamp: float, cols: Columns) -> list[tuple[float, Columns, float]]:
        cols = dict(cols)
        x, y = cols["x"].copy(), cols["y"].copy()
        x[::every] = np.nan
        y[3::every] = np.inf
        cols["x"], cols["y"] = x, y
        if i == all_nan_sweep:
            cols["z"] = np.full_like(cols["z"], np.nan)
        return _same(stamp, cols)

    return fault


def write_without_points(path: str | Path, fmt: str = "ros2-mcap") -> Path:
    """A bag with IMU and GNSS but no PointCloud2 topic (the LiDAR driver never started)."""
    lat, lon, alt = FRAME.to_wgs84(np.array([[ALLEY_X, 0.0, SENSOR_HEIGHT]]))
    with BagWriter(path, fmt) as w:
        for k in range(50):
            w.write_imu(IMU_TOPIC, T0 + 0.01 * k, (0, 0, 0), (0, 0, 9.81))
        for k in range(3):
            w.write_fix(GNSS_TOPIC, T0 + 0.2 * k, lat[0], lon[0], alt[0])
    return w.path


def write_wrong_payload(path: str | Path, fmt: str = "ros2-mcap") -> Path:
    """A topic declared PointCloud2 whose messages are serialized Imu messages."""
    from canopy_kit.io import pointcloud2 as pc2

    with BagWriter(path, fmt) as w:
        t = w.typestore.types
        imu = t["sensor_msgs/msg/Imu"](
            header=pc2.make_header(w.typestore, T0, "imu", w.ros1, 0),
            orientation=w._quat((0, 0, 0, 1)),
            orientation_covariance=np.zeros(9),
            angular_velocity=w._vec3((0, 0, 0)),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=w._vec3((0, 0, 9.81)),
            linear_acceleration_covariance=np.zeros(9),
        )
        msgtype = "sensor_msgs/msg/Imu"
        raw = (
            w.typestore.serialize_ros1(imu, msgtype)
            if w.ros1
            else w.typestore.serialize_cdr(imu, msgtype)
        )
        conn = w._writer.add_connection(
            POINTS_TOPIC, "sensor_msgs/msg/PointCloud2", typestore=w.typestore
        )
        for k in range(3):
            w._writer.write(conn, int((T0 + 0.1 * k) * 1e9), raw)
    return w.path
