"""Oblique drone flights: a single or double grid with a tilted camera, and an orbit per row.

A nadir flight does not see what lies below a crown's widest level, nor the gaps between
touching crowns along a row (docs/GROUND_TRUTH.md). Surveyors add oblique photos:

- ``double-grid``: two lawn-mower grids, one along the rows and one across them, the camera
  pitched to ``gimbal_pitch_deg`` (-90: straight down) and looking ahead along the flight
  line; the lines are serpentine, so every side of every crown is seen. Photos are placed
  so the image centre sweeps the nadir flight's area (each station is set back by the
  distance the tilted view reaches ahead).
- ``single-grid``: the first of those grids alone (lines along the rows, flown both ways):
  half the photos and flight time, and crown sides seen from two bearings only, along the
  row (a grid mission with a tilted camera, as survey apps fly it).
- ``orbit``: per row, a racetrack around it (two straight legs beside the row, half
  circles round its ends) at the distance from which the pitched camera's centre ray meets
  the row's line at mid-crown height; the camera always aims at the nearest point of that
  line.

Spacing on a line is the nadir flight's (``forward_overlap``, ``side_overlap``), so an
oblique photo overlaps its neighbours at least as much. Time per flight: cruise at
``flight_speed`` plus 4 s per turn onto a new line, as for the nadir flight.
"""

from __future__ import annotations

import numpy as np

from canopy_kit.core.gimbal import camera_rotation, compass_heading_deg
from canopy_kit.sim.config import DroneSpec
from canopy_kit.sim.drone import (
    DroneShot,
    FlightRecorder,
    crown_area,
    ground_footprint,
    line_positions,
)
from canopy_kit.sim.orchard import Orchard


def plan_double_grid(
    orchard: Orchard, spec: DroneSpec, rng: np.random.Generator
) -> list[DroneShot]:
    """Two serpentine grids (along, then across the rows) with the camera pitched ahead."""
    return _plan_grids(orchard, spec, rng, (True, False))


def plan_single_grid(
    orchard: Orchard, spec: DroneSpec, rng: np.random.Generator
) -> list[DroneShot]:
    """One serpentine grid along the rows with the camera pitched ahead."""
    return _plan_grids(orchard, spec, rng, (True,))


def _plan_grids(
    orchard: Orchard, spec: DroneSpec, rng: np.random.Generator, grids: tuple[bool, ...]
) -> list[DroneShot]:
    """Serpentine grids, each along (True) or across (False) the rows, camera pitched ahead."""
    a_lo, a_hi, c_lo, c_hi = crown_area(orchard, spec.area_margin)
    centre = orchard.to_local(np.array((a_lo + a_hi) / 2), np.array((c_lo + c_hi) / 2))
    z_fly = float(orchard.terrain.height(centre[0], centre[1])) + spec.altitude
    reach = spec.altitude / np.tan(np.radians(-spec.gimbal_pitch_deg))  # centre ray, ahead
    across_size, along_size = ground_footprint(spec)
    flight = FlightRecorder(spec, rng)
    line = 0
    for along_rows in grids:  # along: lines spaced across the rows
        (s_lo, s_hi), (l_lo, l_hi) = ((a_lo, a_hi), (c_lo, c_hi))[:: 1 if along_rows else -1]
        lines = line_positions(l_lo, l_hi, across_size * (1 - spec.side_overlap))
        stations = line_positions(s_lo, s_hi, along_size * (1 - spec.forward_overlap))
        for k, offset in enumerate(lines):
            forward = 1.0 if k % 2 == 0 else -1.0
            for s in stations if forward > 0 else stations[::-1]:
                pos_s = s - forward * reach  # set back: the centre ray meets the ground at s
                a, c = (pos_s, offset) if along_rows else (offset, pos_s)
                xy = orchard.to_local(np.array(a), np.array(c))
                direction = orchard.row_direction if along_rows else orchard.right_direction
                yaw = compass_heading_deg(forward * direction)
                rotation = camera_rotation(yaw, spec.gimbal_pitch_deg)
                flight.add(np.array([xy[0], xy[1], z_fly]), rotation, line)
            line += 1
    return flight.shots


def _stadium(a_lo: float, a_hi: float, radius: float, step: float) -> np.ndarray:
    """(along, across) points every ``step`` round a segment on the along axis at ``radius``,
    anticlockwise from its start's right-hand side."""
    length = a_hi - a_lo
    perimeter = 2 * length + 2 * np.pi * radius
    n = max(int(np.ceil(perimeter / step)), 8)
    s = np.arange(n) * perimeter / n
    out = np.empty((n, 2))
    for i, d in enumerate(s):
        if d < length:  # leg on the right-hand side (across = +radius), forwards
            out[i] = (a_lo + d, radius)
        elif d < length + np.pi * radius:  # half circle round the end
            phi = (d - length) / radius
            out[i] = (a_hi + radius * np.sin(phi), radius * np.cos(phi))
        elif d < 2 * length + np.pi * radius:  # leg on the left-hand side, back
            out[i] = (a_hi - (d - length - np.pi * radius), -radius)
        else:  # half circle round the start
            phi = (d - 2 * length - np.pi * radius) / radius
            out[i] = (a_lo - radius * np.sin(phi), -radius * np.cos(phi))
    return out


def plan_orbits(orchard: Orchard, spec: DroneSpec, rng: np.random.Generator) -> list[DroneShot]:
    """A racetrack round each row, the camera aimed at the row's line at mid-crown height."""
    flight = FlightRecorder(spec, rng)
    step = ground_footprint(spec)[1] * (1 - spec.forward_overlap)
    rows = sorted({t.row for t in orchard.trees})
    for line, row in enumerate(rows):
        trees = [t for t in orchard.trees if t.row == row]
        ac = orchard.to_orchard(np.array([t.base[:2] for t in trees]))
        a_lo, a_hi = float(ac[:, 0].min()), float(ac[:, 0].max())
        across = float(np.median(ac[:, 1]))
        ground = np.array([t.base[2] for t in trees])
        mid = np.array([np.mean(t.crown.z_range) for t in trees])
        aim_height = float(np.median(mid - ground))
        base = float(np.median(ground))
        radius = max(spec.altitude - aim_height, 1.0) / np.tan(np.radians(-spec.gimbal_pitch_deg))
        for a, c in _stadium(a_lo, a_hi, radius, step):
            xy = orchard.to_local(np.array(a), np.array(across + c))
            aim_a = float(np.clip(a, a_lo, a_hi))
            aim_xy = orchard.to_local(np.array(aim_a), np.array(across))
            z = float(orchard.terrain.height(xy[0], xy[1])) + spec.altitude
            aim = np.array([aim_xy[0], aim_xy[1], base + aim_height])
            look = aim - np.array([xy[0], xy[1], z])
            yaw = compass_heading_deg(look[:2])
            pitch = float(np.degrees(np.arctan2(look[2], np.hypot(look[0], look[1]))))
            flight.add(np.array([xy[0], xy[1], z]), camera_rotation(yaw, pitch), line)
    return flight.shots
