"""Orchard field-session simulator with exact per-tree truth.

``simulate_session(out, load_sim_config("almond", overrides), fmt="ros2-mcap")`` writes a
bag with LiDAR (``/points``), IMU (``/imu/data``), GNSS (``/gps/fix``) and true poses
(``/ground_truth/odom``), plus ``truth/`` tables and, optionally, drone photos.
"""

from canopy_kit.sim.config import SimConfig, load_sim_config, sim_preset_names
from canopy_kit.sim.session import build_world, find_bag, simulate_session
from canopy_kit.sim.truth import load_truth

__all__ = [
    "SimConfig",
    "build_world",
    "find_bag",
    "load_sim_config",
    "load_truth",
    "sim_preset_names",
    "simulate_session",
]
