"""Simulated drone photo flight: a nadir lawn-mower survey over the orchard (oblique
patterns: :mod:`canopy_kit.sim.drone_patterns`).

Flight lines run along the rows at a constant altitude above the take-off point, spaced
for the side overlap; photos along a line are spaced for the forward overlap. Each
photo is ray-cast from the same scene as the LiDAR (see ``drone_render``), saved as a
JPEG with GPS (noisy, as a receiver reports it) and focal-length EXIF and a DJI-style XMP
packet (gimbal attitude, heading, height above take-off), and the true camera poses go to
``truth/drone_cameras.csv``.

Camera convention (as COLMAP): x right, y down, z along the viewing direction; the
stored rotation maps camera to world (local frame: x east, y north, z up).
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.core.atomic import atomic_write_bytes, atomic_write_text
from canopy_kit.core.extras import needs_extra
from canopy_kit.core.gimbal import compass_heading_deg, gimbal_angles
from canopy_kit.evaluate.truth import write_csv
from canopy_kit.io.session_layout import SIM_CONFIG, drone_dir, truth_dir
from canopy_kit.sim.config import DroneSpec
from canopy_kit.sim.dji_xmp import dji_xmp
from canopy_kit.sim.drone_render import DroneRenderer, PinholeView
from canopy_kit.sim.orchard import Orchard
from canopy_kit.sim.scene import Scene

Progress = Callable[[str, float, float], None]
FLIGHT_START = datetime(2024, 6, 18, 11, 0, 0)
CAMERA_MAKE = "canopy-kit"
CAMERA_MODEL = "simulated nadir camera"


@dataclass(frozen=True)
class DroneShot:
    """One planned and flown photo: true pose, line number and time since take-off."""

    name: str
    line: int
    time_s: float
    view: PinholeView


@dataclass
class DroneFlight:
    """What a simulated flight wrote: image folder, camera table and the flight summary."""

    images_dir: Path
    cameras: pd.DataFrame
    summary: dict


def focal_px(spec: DroneSpec) -> float:
    """Focal length in pixels from the lens focal length and the sensor width."""
    return spec.focal_length_mm / spec.sensor_width_mm * spec.image_width


def ground_footprint(spec: DroneSpec) -> tuple[float, float]:
    """(across-track, along-track) ground size of a photo at flight altitude over flat ground."""
    f = focal_px(spec)
    return spec.altitude * spec.image_width / f, spec.altitude * spec.image_height / f


def line_positions(lo: float, hi: float, step: float) -> np.ndarray:
    """Positions spaced by at most ``step`` covering [lo, hi], centred on it."""
    n = max(int(np.ceil((hi - lo) / step - 1e-9)) + 1, 2)
    span = (n - 1) * step
    return (lo + hi) / 2 + np.linspace(-span / 2, span / 2, n)


TURN_S = 4.0  # seconds to turn onto a new flight line


def crown_area(orchard: Orchard, margin: float) -> tuple[float, float, float, float]:
    """(along_lo, along_hi, across_lo, across_hi) of every crown plus ``margin``."""
    corners = []
    for tree in orchard.trees:
        lo, hi = tree.crown.bounds
        corners.extend([(lo[0], lo[1]), (lo[0], hi[1]), (hi[0], lo[1]), (hi[0], hi[1])])
    ac = orchard.to_orchard(np.asarray(corners))
    a_lo, c_lo = ac.min(axis=0) - margin
    a_hi, c_hi = ac.max(axis=0) + margin
    return float(a_lo), float(a_hi), float(c_lo), float(c_hi)


class FlightRecorder:
    """Shots in flying order, each as flown (the plan plus position and attitude noise), with
    the clock: cruise at ``flight_speed`` between photos, ``TURN_S`` per turn onto a new line."""

    def __init__(self, spec: DroneSpec, rng: np.random.Generator) -> None:
        self.spec, self.rng = spec, rng
        self.shots: list[DroneShot] = []
        self.t = 0.0
        self.prev: tuple[np.ndarray, int] | None = None

    def add(self, position: np.ndarray, rotation: np.ndarray, line: int) -> None:
        """Fly to the planned ``position`` with the planned camera ``rotation`` and shoot."""
        from scipy.spatial.transform import Rotation

        spec, rng = self.spec, self.rng
        pos = np.array(position, float)
        pos[:2] += rng.normal(0.0, spec.position_jitter_horizontal, 2)
        pos[2] += rng.normal(0.0, spec.position_jitter_vertical)
        tilt = np.radians(
            [
                rng.normal(0.0, spec.attitude_sigma_deg),
                rng.normal(0.0, spec.attitude_sigma_deg),
                rng.normal(0.0, spec.yaw_sigma_deg),
            ]
        )
        rotation = rotation @ Rotation.from_rotvec(tilt).as_matrix()
        if self.prev is not None:
            self.t += float(np.linalg.norm(pos - self.prev[0])) / spec.flight_speed + (
                TURN_S if self.prev[1] != line else 0.0
            )
        self.prev = (pos, line)
        view = PinholeView(pos, rotation, focal_px(spec), spec.image_width, spec.image_height)
        self.shots.append(DroneShot(f"IMG_{len(self.shots) + 1:04d}.jpg", line, self.t, view))


def plan_flight(orchard: Orchard, spec: DroneSpec, rng: np.random.Generator) -> list[DroneShot]:
    """Lawn-mower photo positions over the crowns (plus ``area_margin``), with true-pose noise."""
    a_lo, a_hi, c_lo, c_hi = crown_area(orchard, spec.area_margin)
    across_size, along_size = ground_footprint(spec)
    lines = line_positions(c_lo, c_hi, across_size * (1 - spec.side_overlap))
    stations = line_positions(a_lo, a_hi, along_size * (1 - spec.forward_overlap))
    centre = orchard.to_local(np.array((a_lo + a_hi) / 2), np.array((c_lo + c_hi) / 2))
    z_fly = float(orchard.terrain.height(centre[0], centre[1])) + spec.altitude
    flight = FlightRecorder(spec, rng)
    for k, across in enumerate(lines):
        forward = 1.0 if k % 2 == 0 else -1.0
        heading = forward * np.append(orchard.row_direction, 0.0)
        x_cam = np.cross(heading, [0.0, 0.0, 1.0])  # image right: to the right of the heading
        y_cam = -heading  # image down: backwards, so the image top looks ahead
        nominal = np.column_stack([x_cam, y_cam, [0.0, 0.0, -1.0]])
        for along in stations if forward > 0 else stations[::-1]:
            xy = orchard.to_local(np.array(along), np.array(across))
            flight.add(np.array([xy[0], xy[1], z_fly]), nominal, k)
    return flight.shots


def plan_shots(orchard: Orchard, spec: DroneSpec, rng: np.random.Generator) -> list[DroneShot]:
    """The photos of ``spec.pattern``: the nadir survey, or an oblique double grid or orbits."""
    if spec.pattern == "nadir":
        return plan_flight(orchard, spec, rng)
    from canopy_kit.sim import drone_patterns

    planner = {
        "double-grid": drone_patterns.plan_double_grid,
        "single-grid": drone_patterns.plan_single_grid,
        "orbit": drone_patterns.plan_orbits,
    }
    return planner[spec.pattern](orchard, spec, rng)


def _rational(value: float, denominator: int) -> tuple[int, int]:
    return int(round(value * denominator)), denominator


def _dms(value: float) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    value = abs(value)
    deg = int(value)
    minutes = int((value - deg) * 60)
    seconds = (value - deg - minutes / 60.0) * 3600.0
    return (deg, 1), (minutes, 1), _rational(seconds, 100000)


def exif_bytes(spec: DroneSpec, lat: float, lon: float, altitude: float, when: datetime) -> bytes:
    """EXIF block with GPS position, time and the focal length / focal-plane resolution."""
    with needs_extra("aerial"):
        import piexif

    stamp = when.strftime("%Y:%m:%d %H:%M:%S").encode()
    px_per_cm = spec.image_width / (spec.sensor_width_mm / 10.0)
    zeroth = {
        piexif.ImageIFD.Make: CAMERA_MAKE.encode(),
        piexif.ImageIFD.Model: CAMERA_MODEL.encode(),
        piexif.ImageIFD.DateTime: stamp,
        piexif.ImageIFD.Orientation: 1,
    }
    exif = {
        piexif.ExifIFD.DateTimeOriginal: stamp,
        piexif.ExifIFD.FocalLength: _rational(spec.focal_length_mm, 1000),
        piexif.ExifIFD.FocalLengthIn35mmFilm: int(
            round(spec.focal_length_mm * 36.0 / spec.sensor_width_mm)
        ),
        piexif.ExifIFD.FocalPlaneXResolution: _rational(px_per_cm, 1000),
        piexif.ExifIFD.FocalPlaneYResolution: _rational(px_per_cm, 1000),
        piexif.ExifIFD.FocalPlaneResolutionUnit: 3,  # centimetres
        piexif.ExifIFD.PixelXDimension: spec.image_width,
        piexif.ExifIFD.PixelYDimension: spec.image_height,
    }
    gps = {
        piexif.GPSIFD.GPSVersionID: (2, 3, 0, 0),
        piexif.GPSIFD.GPSLatitudeRef: b"N" if lat >= 0 else b"S",
        piexif.GPSIFD.GPSLatitude: _dms(lat),
        piexif.GPSIFD.GPSLongitudeRef: b"E" if lon >= 0 else b"W",
        piexif.GPSIFD.GPSLongitude: _dms(lon),
        piexif.GPSIFD.GPSAltitudeRef: 0 if altitude >= 0 else 1,
        piexif.GPSIFD.GPSAltitude: _rational(abs(altitude), 1000),
        piexif.GPSIFD.GPSMapDatum: b"WGS-84",
    }
    return piexif.dump({"0th": zeroth, "Exif": exif, "GPS": gps, "1st": {}, "thumbnail": None})


def encode_jpeg(image: np.ndarray, exif: bytes, quality: int, xmp: bytes = b"") -> bytes:
    """JPEG bytes of an (H, W, 3) uint8 image carrying ``exif`` (and an ``xmp`` packet)."""
    from PIL import Image

    buf = io.BytesIO()
    extra = {"xmp": xmp} if xmp else {}
    Image.fromarray(image).save(
        buf, format="JPEG", quality=quality, exif=exif, subsampling=0, **extra
    )
    return buf.getvalue()


def shot_xmp(
    shot: DroneShot, previous: DroneShot | None, take_off_z: float
) -> Callable[[float], bytes]:
    """The DJI XMP of a photo, given its GPS altitude: the true gimbal attitude, the heading
    flown from the photo before (the gimbal's on the first) and the height above take-off."""
    gimbal = gimbal_angles(shot.view.rotation)
    heading = gimbal[0]
    if previous is not None and previous.line == shot.line:
        step = shot.view.position[:2] - previous.view.position[:2]
        if np.hypot(*step) > 1e-6:
            heading = compass_heading_deg(step)
    relative = float(shot.view.position[2] - take_off_z)
    return lambda altitude: dji_xmp(gimbal, (heading, 0.0, 0.0), relative, altitude)


def simulate_drone_flight(
    orchard: Orchard,
    scene: Scene,
    spec: DroneSpec,
    drone_dir: str | Path,
    truth_dir: str | Path,
    rng: np.random.Generator,
    progress: Progress | None = None,
) -> DroneFlight:
    """Fly, render and write the photos to ``drone_dir`` and the true cameras to ``truth_dir``."""
    report = progress or (lambda *_: None)
    drone_dir, truth_dir = Path(drone_dir), Path(truth_dir)
    drone_dir.mkdir(parents=True, exist_ok=True)
    shots = plan_shots(orchard, spec, rng)
    renderer = DroneRenderer(
        scene,
        orchard.terrain,
        (orchard.right_direction, orchard.row_offsets),
        spec.sun_elevation_deg,
        spec.sun_azimuth_deg,
    )
    offset = np.array(
        [
            *rng.normal(0.0, spec.gps_offset_sigma_horizontal, 2),
            rng.normal(0.0, spec.gps_offset_sigma_vertical),
        ]
    )
    rows = []
    first = shots[0].view.position if shots else np.zeros(3)
    take_off_z = float(orchard.terrain.height(first[0], first[1]))
    report("Drone photos", 0, len(shots))
    for k, shot in enumerate(shots):
        xmp = shot_xmp(shot, shots[k - 1] if k else None, take_off_z)
        rows.append(_take_photo(shot, renderer, orchard, spec, offset, rng, drone_dir, xmp))
        report("Drone photos", k + 1, len(shots))
    cameras = pd.DataFrame(rows)
    truth_dir.mkdir(parents=True, exist_ok=True)
    write_csv(cameras, truth_dir / "drone_cameras.csv", float_format="%.9f")
    summary = _flight_summary(spec, cameras, offset, shots)
    atomic_write_text(truth_dir / "drone_flight.json", json.dumps(summary, indent=2) + "\n")
    return DroneFlight(drone_dir, cameras, summary)


def _take_photo(
    shot: DroneShot,
    renderer: DroneRenderer,
    orchard: Orchard,
    spec: DroneSpec,
    offset: np.ndarray,
    rng: np.random.Generator,
    drone_dir: Path,
    xmp: Callable[[float], bytes],
) -> dict[str, Any]:
    """Render one shot and write it as a JPEG with the receiver's GPS position (the flight's
    ``offset`` plus noise) in its EXIF and ``xmp(altitude)`` as its XMP packet; returns the
    true camera's row of drone_cameras.csv."""
    from scipy.spatial.transform import Rotation

    view = shot.view
    gps = (
        view.position
        + offset
        + np.array(
            [
                *rng.normal(0.0, spec.gps_sigma_horizontal, 2),
                rng.normal(0.0, spec.gps_sigma_vertical),
            ]
        )
    )
    lat, lon, alt = (float(v[0]) for v in orchard.frame.to_wgs84(gps[None, :]))
    image = renderer.render(view, rng)
    when = FLIGHT_START + timedelta(seconds=round(shot.time_s))
    atomic_write_bytes(
        drone_dir / shot.name,
        encode_jpeg(image, exif_bytes(spec, lat, lon, alt, when), spec.jpeg_quality, xmp(alt)),
    )
    q = Rotation.from_matrix(view.rotation).as_quat()
    return {
        "image": shot.name,
        "line": shot.line,
        "time_s": shot.time_s,
        "x": view.position[0],
        "y": view.position[1],
        "z": view.position[2],
        "qw": q[3],
        "qx": q[0],
        "qy": q[1],
        "qz": q[2],
        "gps_x": gps[0],
        "gps_y": gps[1],
        "gps_z": gps[2],
        "lat": lat,
        "lon": lon,
        "altitude": alt,
        "focal_px": view.focal_px,
        "cx": view.width / 2.0,
        "cy": view.height / 2.0,
        "width": view.width,
        "height": view.height,
    }


def _flight_summary(
    spec: DroneSpec, cameras: pd.DataFrame, offset: np.ndarray, shots: list[DroneShot]
) -> dict[str, Any]:
    """What drone_flight.json records: images, flight lines, altitude, ground sampling,
    footprint and overlaps, camera, the receiver's offset and the sun."""
    across, along = ground_footprint(spec)
    return {
        "pattern": spec.pattern,
        "gimbal_pitch_deg": -90.0 if spec.pattern == "nadir" else spec.gimbal_pitch_deg,
        "flight_time_s": shots[-1].time_s if shots else 0.0,
        "images": len(shots),
        "lines": int(cameras["line"].max()) + 1 if len(cameras) else 0,
        "altitude_m": spec.altitude,
        "gsd_m": spec.altitude / focal_px(spec),
        "footprint_m": [across, along],
        "forward_overlap": spec.forward_overlap,
        "side_overlap": spec.side_overlap,
        "focal_px": focal_px(spec),
        "image_size": [spec.image_width, spec.image_height],
        "camera_convention": "x right, y down, z viewing direction; quaternion camera-to-world",
        "gps_offset_m": offset.tolist(),
        "sun_elevation_deg": spec.sun_elevation_deg,
        "sun_azimuth_deg": spec.sun_azimuth_deg,
    }


def simulate_drone_session(
    out: str | Path,
    config,
    progress: Progress | None = None,
) -> DroneFlight:
    """A drone-only session, no LiDAR bag: ``out/drone/`` photos and ``out/truth/`` tables.

    The orchard, scene and random streams are those ``simulate_session`` would use for the
    same config, so the photos match a full session with the same seed.
    """
    from canopy_kit.config import write_config
    from canopy_kit.sim.session import build_world
    from canopy_kit.sim.truth import tree_table

    root = Path(out)
    orchard, _, scene, rngs = build_world(config)
    truth = truth_dir(root)
    truth.mkdir(parents=True, exist_ok=True)
    write_csv(tree_table(orchard), truth / "trees.csv")
    atomic_write_text(
        truth / "frame.json",
        json.dumps({"frame": orchard.frame.to_dict()}, indent=2, sort_keys=True) + "\n",
    )
    write_config(config, truth / SIM_CONFIG)
    return simulate_drone_flight(
        orchard, scene, config.drone, drone_dir(root), truth, rngs["drone"], progress=progress
    )
