"""Simulate a whole field session: orchard, LiDAR/IMU/GNSS bag, truth, optional drone photos."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.config import from_dict, read_toml, write_config
from canopy_kit.core.atomic import atomic_write_text
from canopy_kit.errors import InputError
from canopy_kit.evaluate.truth import write_csv
from canopy_kit.io.bag_writer import BagWriter, bag_path_for
from canopy_kit.io.imu_units import STANDARD_GRAVITY
from canopy_kit.io.session_layout import BAG_NAME, SIM_CONFIG, find_bag, sim_config_path, truth_dir
from canopy_kit.io.session_layout import drone_dir as drone_folder
from canopy_kit.sim.config import SimConfig, validate
from canopy_kit.sim.inertial import GnssFixes, ImuSamples, simulate_gnss, simulate_imu
from canopy_kit.sim.lidar import SpinningLidar
from canopy_kit.sim.orchard import Orchard, generate_orchard
from canopy_kit.sim.rig import SensorMounts, sensor_mounts
from canopy_kit.sim.scene import Scene, build_scene
from canopy_kit.sim.trajectory import Trajectory
from canopy_kit.sim.truth import tree_table

__all__ = [
    "BAG_NAME",
    "SimulatedSession",
    "build_world",
    "find_bag",
    "load_sim_config_of",
    "regenerate_orchard",
    "simulate_session",
]

Progress = Callable[[str, float, float], None]
SESSION_EPOCH = 1_700_000_000.0


@dataclass
class SimulatedSession:
    """Paths and objects of a simulated session."""

    root: Path
    bag: Path
    truth_dir: Path
    orchard: Orchard
    trajectory: Trajectory
    n_scans: int
    n_points: int
    drone_dir: Path | None = None


def _streams(seed: int, session_seed: int | None = None) -> dict[str, np.random.Generator]:
    names = ["orchard", "scene", "drive", "lidar", "imu", "gnss", "drone"]
    children = np.random.SeedSequence(seed).spawn(len(names))
    rngs = {n: np.random.default_rng(c) for n, c in zip(names, children)}
    if session_seed is not None:  # another visit of the same orchard: new drive and noise
        visit = np.random.SeedSequence([seed, session_seed]).spawn(len(names))
        rngs.update(
            {
                n: np.random.default_rng(c)
                for n, c in zip(names, visit)
                if n not in ("orchard", "scene")
            }
        )
    return rngs


def build_world(
    config: SimConfig,
) -> tuple[Orchard, Trajectory, Scene, dict[str, np.random.Generator]]:
    """The orchard, the drive and the scene mesh for a config (deterministic in its seed)."""
    validate(config)
    rngs = _streams(config.seed, config.session_seed)
    orchard = generate_orchard(config.orchard, rngs["orchard"])
    trajectory = Trajectory(
        orchard,
        config.drive,
        config.lidar.mount_height,
        rngs["drive"],
        t0=SESSION_EPOCH,
        mount_pitch_deg=config.lidar.mount_pitch_deg,
        mounts=sensor_mounts(config),
    )
    t = np.linspace(trajectory.start_time, trajectory.end_time, 2000)
    path, _ = trajectory.poses(t)
    scene = build_scene(orchard, rngs["scene"], (path.min(axis=0), path.max(axis=0)))
    return orchard, trajectory, scene, rngs


def simulate_session(
    out: str | Path,
    config: SimConfig,
    fmt: str = "ros2-mcap",
    truth_field: bool = True,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> SimulatedSession:
    """Write a complete simulated session into folder ``out``.

    Layout: ``session.bag`` (ROS1) or ``session/`` (ROS2), ``truth/`` (trees.csv,
    trajectory.csv, frame.json, sim_config.toml) and, when ``config.drone.enabled``,
    ``drone/`` with geotagged JPEGs. The session is written into ``.<name>.partial`` beside
    ``out`` and renamed when complete: an interrupted run leaves no half-written session
    (and, with ``overwrite``, the old one stays until the new one is done).
    """
    final = Path(out).absolute()
    if final.exists() and any(final.iterdir()) and not overwrite:
        raise InputError(
            f"{final}: output folder is not empty (--overwrite, or overwrite=True from Python, replaces it)"
        )
    root = final.with_name(f".{final.name}.partial")
    if root.exists():  # left by an interrupted run
        shutil.rmtree(root)
    root.mkdir(parents=True)
    try:
        orchard, trajectory, n_sweeps, n_points = _write_session(
            root, config, fmt, truth_field, progress
        )
    except BaseException:
        shutil.rmtree(root, ignore_errors=True)
        raise
    if final.exists():
        shutil.rmtree(final)
    root.rename(final)
    return SimulatedSession(
        final,
        bag_path_for(final / BAG_NAME, fmt),
        truth_dir(final),
        orchard,
        trajectory,
        n_sweeps,
        n_points,
        drone_folder(final) if config.drone.enabled else None,
    )


def _write_session(
    root: Path, config: SimConfig, fmt: str, truth_field: bool, progress: Progress | None
) -> tuple[Orchard, Trajectory, int, int]:
    """Simulate and write the session's files into ``root``: (orchard, trajectory, sweeps,
    points)."""
    bag_path = bag_path_for(root / BAG_NAME, fmt)
    report = progress or (lambda *_: None)
    orchard, trajectory, scene, rngs = build_world(config)
    mounts = sensor_mounts(config)
    truth_folder = truth_dir(root)
    _write_truth(truth_folder, config, orchard, trajectory, fmt, truth_field, mounts)
    lidar = SpinningLidar(config.lidar, scene, trajectory, rngs["lidar"], truth_field)
    sweeps = lidar.sweep_times()
    imu = simulate_imu(trajectory, config.imu, rngs["imu"]) if config.imu.enabled else None
    gnss = simulate_gnss(trajectory, config.gnss, rngs["gnss"]) if config.gnss.enabled else None
    if gnss is not None:  # where the receiver lost its fix or jumped
        atomic_write_text(
            truth_folder / "gnss_events.json", json.dumps(gnss.events, indent=2) + "\n"
        )
    n_points = 0
    with BagWriter(bag_path, fmt) as writer:
        if mounts.tf_static:
            writer.write_tf_static(
                trajectory.start_time, [(t.parent, t.child, t.matrix) for t in mounts.tf_static]
            )
        streams = _SensorStreams(writer, config, mounts, orchard, trajectory, lidar, imu, gnss)
        for k, stamp in enumerate(sweeps):
            streams.write_until(stamp + lidar.sweep_period)
            scan = lidar.sweep(stamp)
            n_points += scan.n_points
            scan.write(writer, config.lidar.topic, mounts.lidar_frame)
            report("LiDAR sweeps", k + 1, len(sweeps))
        streams.write_until(trajectory.end_time + 1.0)
    if lidar.ouster is not None:  # the metadata beside the bag too, as older drivers kept it
        atomic_write_text(root / "ouster_metadata.json", lidar.ouster.metadata + "\n")
    if config.drone.enabled:
        from canopy_kit.sim.drone import simulate_drone_flight

        simulate_drone_flight(
            orchard, scene, config.drone, drone_folder(root), truth_folder, rngs["drone"], report
        )
    return orchard, trajectory, len(sweeps), n_points


class _SensorStreams:
    """The IMU, GNSS and odometry messages of a drive, written in time order between the
    LiDAR sweeps: each call writes those stamped before ``until`` not written yet."""

    def __init__(
        self,
        writer: BagWriter,
        config: SimConfig,
        mounts: SensorMounts,
        orchard: Orchard,
        trajectory: Trajectory,
        lidar: SpinningLidar,
        imu: ImuSamples | None,
        gnss: GnssFixes | None,
    ) -> None:
        self.writer, self.config, self.mounts = writer, config, mounts
        self.orchard, self.trajectory, self.lidar = orchard, trajectory, lidar
        self.imu, self.gnss = imu, gnss
        self.odo_t = np.arange(
            trajectory.start_time, trajectory.end_time, 1.0 / config.drive.odometry_rate_hz
        )
        self.next_imu = self.next_gnss = self.next_odom = 0

    def write_until(self, until: float) -> None:
        """Every message stamped before ``until`` not written yet: IMU, GNSS, odometry."""
        if self.imu is not None:
            self._write_imu(until)
        if self.gnss is not None:
            self._write_gnss(until)
        self._write_odometry(until)

    def _write_imu(self, until: float) -> None:
        imu, mounts, config = self.imu, self.mounts, self.config
        accel_unit = 1 / STANDARD_GRAVITY if config.imu.acceleration_unit == "g" else 1.0
        i = self.next_imu
        while i < len(imu.t) and imu.t[i] < until:
            if config.imu.output == "ouster_packets":  # the Ouster's own IMU packets (sim.ouster)
                stamp, packet = self.lidar.ouster.imu_packet(  # type: ignore[union-attr]
                    imu.t[i] + mounts.imu_time_offset,
                    imu.angular_velocity[i],
                    imu.linear_acceleration[i],
                )
                self.writer.write_ouster_packets(config.imu.topic, [stamp], [packet])
            else:
                self.writer.write_imu(
                    config.imu.topic,
                    imu.t[i] + mounts.imu_time_offset,
                    imu.angular_velocity[i],
                    imu.linear_acceleration[i] * accel_unit,
                    None,
                    mounts.imu_frame,
                )
            i += 1
        self.next_imu = i

    def _write_gnss(self, until: float) -> None:
        gnss = self.gnss
        i = self.next_gnss
        while i < len(gnss.t) and gnss.t[i] < until:
            lat, lon, h = self.orchard.frame.to_wgs84(gnss.local_xyz[i : i + 1])
            self.writer.write_fix(
                self.config.gnss.topic,
                gnss.t[i],
                lat[0],
                lon[0],
                h[0],
                gnss.sigma_horizontal[i],
                gnss.sigma_vertical[i],
                gnss.status[i],
                self.mounts.gnss_frame,
                gnss.covariance_type,
            )
            i += 1
        self.next_gnss = i

    def _write_odometry(self, until: float) -> None:
        odo_t = self.odo_t
        i = j = self.next_odom
        while j < len(odo_t) and odo_t[j] < until:
            j += 1
        if j > i:
            pos, rot = self.trajectory.poses(odo_t[i:j])
            quat = rot.as_quat()
            for k in range(j - i):
                self.writer.write_odometry(
                    self.config.drive.odometry_topic,
                    odo_t[i + k],
                    pos[k],
                    quat[k],
                    "map",
                    self.mounts.lidar_frame,
                )
        self.next_odom = j


def _pose_frame(t: np.ndarray, pos: np.ndarray, rot: object) -> pd.DataFrame:
    q = rot.as_quat()  # type: ignore[attr-defined]
    return pd.DataFrame(
        {
            "time": t,
            "x": pos[:, 0],
            "y": pos[:, 1],
            "z": pos[:, 2],
            "qx": q[:, 0],
            "qy": q[:, 1],
            "qz": q[:, 2],
            "qw": q[:, 3],
        }
    )


def _write_truth(
    truth_dir: Path,
    config: SimConfig,
    orchard: Orchard,
    trajectory: Trajectory,
    fmt: str,
    truth_field: bool,
    mounts: SensorMounts,
) -> None:
    truth_dir.mkdir(parents=True, exist_ok=True)
    write_csv(tree_table(orchard), truth_dir / "trees.csv")
    t = np.arange(trajectory.start_time, trajectory.end_time, 1.0 / config.drive.odometry_rate_hz)
    write_csv(
        _pose_frame(t, *trajectory.poses(t)), truth_dir / "trajectory.csv", float_format="%.9f"
    )
    if not mounts.identity:  # the vehicle frame's poses, which a rig-aware mapping reports
        base = trajectory.mounted_poses(t, np.eye(4))
        write_csv(_pose_frame(t, *base), truth_dir / "base_trajectory.csv", float_format="%.9f")
    info = {
        "frame": orchard.frame.to_dict(),
        "row_direction": orchard.row_direction.tolist(),
        "right_direction": orchard.right_direction.tolist(),
        "row_offsets": orchard.row_offsets.tolist(),
        "path_length_m": trajectory.length,
        "duration_s": trajectory.duration,
        "start_time": trajectory.start_time,
        "sensor_frame": mounts.lidar_frame,
        "base_frame": mounts.base_frame if not mounts.identity else mounts.lidar_frame,
        "rig": dict(mounts.to_dict(), name=config.rig.name),
        "label_convention": "rows numbered left to right along the first pass; "
        "even rows L, odd rows R; index along the row direction",
    }
    atomic_write_text(truth_dir / "frame.json", json.dumps(info, indent=2, sort_keys=True) + "\n")
    recording = {"bag_format": fmt, "truth_field": truth_field}
    atomic_write_text(truth_dir / "recording.json", json.dumps(recording, indent=2) + "\n")
    write_config(config, truth_dir / SIM_CONFIG)


def regenerate_orchard(sim_dir: str | Path) -> Orchard:
    """Rebuild the orchard of a simulated session from its stored config and seed."""
    cfg_path = sim_config_path(sim_dir)
    config = from_dict(SimConfig, read_toml(cfg_path), str(cfg_path))
    return generate_orchard(config.orchard, _streams(config.seed)["orchard"])


def load_sim_config_of(sim_dir: str | Path) -> SimConfig:
    """The config a simulated session was made with."""
    cfg_path = sim_config_path(sim_dir)
    return from_dict(SimConfig, read_toml(cfg_path), str(cfg_path))
