"""The session-folder layout: where a field session keeps its bag, drone photos and truth.

A session folder, simulated or recorded and laid out alike, holds::

    session.bag | session/    the drive (ROS1 bag file, or a ROS2 bag folder)
    drone/                    geotagged drone photos (optional)
    truth/                    per-tree truth tables (optional, see :mod:`canopy_kit.evaluate.truth`)

The simulator writes this layout and every stage reads it through this module, so neither
owns it (issue 28).
"""

from __future__ import annotations

from pathlib import Path

from canopy_kit.errors import InputError

BAG_NAME = "session"
DRONE_DIR = "drone"
TRUTH_DIR = "truth"
SIM_CONFIG = "sim_config.toml"  # the simulator's config, inside truth/


def find_bag(session_dir: str | Path) -> Path:
    """The bag inside a session folder (``session.bag`` or ``session/``)."""
    root = Path(session_dir)
    for candidate in (root / f"{BAG_NAME}.bag", root / BAG_NAME):
        if candidate.exists():
            return candidate
    raise InputError(f"{root}: no simulated bag ({BAG_NAME}.bag or {BAG_NAME}/) in this folder")


def truth_dir(session_dir: str | Path) -> Path:
    """The truth folder of a session folder (``SESSION/truth``)."""
    return Path(session_dir) / TRUTH_DIR


def drone_dir(session_dir: str | Path) -> Path:
    """The drone-photo folder of a session folder (``SESSION/drone``)."""
    return Path(session_dir) / DRONE_DIR


def sim_config_path(session_dir: str | Path) -> Path:
    """Where a simulated session keeps the config it was made with."""
    return truth_dir(session_dir) / SIM_CONFIG
