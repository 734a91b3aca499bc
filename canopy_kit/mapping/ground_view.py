"""Does the LiDAR see the ground beside the robot? The ``"auto"`` of ``mapping.odometry_map_skipped``.

A sensor whose lowest beams stay close to the horizon (a Livox Mid-360 looks from -7°)
reaches the ground only far from the robot, sees no trunks near it, and registers on foliage
alone; KISS-ICP's local map lagging the sensor by the unregistered sweeps then shortens the
distance driven (docs/MAPPING.md, "Livox Mid-360 trajectory error"). Putting those sweeps
into the local map fixes most of it and costs +14-19 % of the mapping's CPU, which on a
spinning sensor that sees the ground buys 0.1-0.5 cm only. The decision is read from the
data: how far below the vehicle's horizontal plane the lowest returns of the first scans lie.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canopy_kit.config import MappingConfig
from canopy_kit.io.bag import open_bag
from canopy_kit.mapping.filters import range_mask
from canopy_kit.mapping.sensors import SensorTopics, sensor_messages

# Scans read at the start of the bag (1 s at 10 Hz; the robot usually stands still then, the
# beams' angles do not depend on it).
VIEW_SCANS = 10
# The elevation of "the lowest returns": this quantile of the returns' elevations, so that up
# to 1 % of stray points (noise, a part of the robot past ``min_range``) do not decide. A
# 128-ring sensor's lowest ring holds 0.8 % of its points: the quantile lands in the next one.
LOW_ELEVATION_QUANTILE = 0.01
# Put the unregistered sweeps into the local map when the lowest returns lie above this many
# degrees below the vehicle's horizontal plane. A beam at -a deg reaches the ground h / tan(a)
# from a LiDAR h above it: at the simulator's 1.8 m, 15 m away for the Mid-360's -7 deg (past
# the neighbouring rows), 6.7 m for a VLP-16's -15 deg, 3.0 m for an HDL-32's -31 deg. Chosen on
# the seed-11 pistachio drives alone (lowest returns, 1 % quantile of the first 10 scans:
# Mid-360 -6.9, VLP-16 -15.0, HDL-32 -30.7, default 32-ring -45.0 deg): halfway between the
# Mid-360 and the flattest spinning sensor, 4 deg of margin either way (a LiDAR mounted a few
# degrees off the base frame it is given in, or the spread of a real sensor's beam angles).
MAP_SKIPPED_ABOVE_DEG = -11.0


@dataclass(frozen=True)
class GroundView:
    """The lowest returns of the first scans, seen from the vehicle's horizontal plane."""

    lowest_elevation_deg: float  # NaN: no point within the range limits
    scans: int
    points: int


def lowest_elevation_deg(xyz: np.ndarray, up: np.ndarray) -> float:
    """The :data:`LOW_ELEVATION_QUANTILE` of the elevations (deg) of the points ``xyz`` (LiDAR
    frame) above the plane normal to ``up`` (the vehicle's z axis in the LiDAR frame); NaN
    for no points."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    r = np.linalg.norm(xyz, axis=1)
    ok = r > 0
    if not ok.any():
        return float("nan")
    up = np.asarray(up, float) / np.linalg.norm(up)
    sin_el = np.clip(xyz[ok] @ up / r[ok], -1.0, 1.0)
    return float(np.degrees(np.arcsin(np.quantile(sin_el, LOW_ELEVATION_QUANTILE))))


def ground_view(
    bag_path: str | Path,
    topics: SensorTopics,
    lidar_from_base: np.ndarray,
    config: MappingConfig,
    n_scans: int = VIEW_SCANS,
) -> GroundView:
    """The lowest returns (within ``config``'s range limits) of the bag's first ``n_scans``
    scans, against the vehicle's horizontal plane (``lidar_from_base``: the rig's). The bag
    is opened on its own, so the odometry's reading of it counts every message once."""
    points = []
    scans = 0
    with open_bag(bag_path, config.ouster_metadata or None) as bag:
        for scan in sensor_messages(bag, topics, end_scan=n_scans):
            scans += 1
            points.append(scan.xyz[range_mask(scan.xyz, config.min_range, config.max_range)])
    xyz = np.concatenate(points) if points else np.zeros((0, 3))
    up = np.asarray(lidar_from_base, float)[:3, 2]
    return GroundView(lowest_elevation_deg(xyz, up), scans, len(xyz))


def map_skipped_decision(setting: bool | str, view: GroundView | None) -> dict:
    """Whether the unregistered sweeps go into the local map, and why (for the diagnostics).

    ``setting``: ``mapping.odometry_map_skipped``; ``view`` is needed only for ``"auto"``
    (None there: the first scans could not be read; off)."""
    if setting is True or setting is False:
        return {"setting": setting, "on": setting, "reason": "set explicitly"}
    out: dict = {"setting": setting, "threshold_deg": MAP_SKIPPED_ABOVE_DEG}
    if view is None:
        return out | {"on": False, "reason": "the first scans could not be read: left off"}
    if not np.isfinite(view.lowest_elevation_deg):
        return out | {"on": False, "reason": "no returns in the first scans: left off"}
    low = view.lowest_elevation_deg
    on = bool(low > MAP_SKIPPED_ABOVE_DEG)
    reason = (
        f"lowest returns at {low:.1f} deg, above {MAP_SKIPPED_ABOVE_DEG:g}: no ground beside "
        "the robot"
        if on
        else f"lowest returns at {low:.1f} deg, at or below {MAP_SKIPPED_ABOVE_DEG:g}: the "
        "LiDAR sees the ground beside the robot"
    )
    return out | {
        "on": on,
        "lowest_elevation_deg": round(low, 2),
        "scans_read": view.scans,
        "points_read": view.points,
        "reason": reason,
    }
