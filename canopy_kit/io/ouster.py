"""Ouster lidar packets and the sensor metadata JSON that decodes them, in numpy.

Follows Ouster's published packet format (firmware user manual, "Lidar data format"; the
same layout as ``ouster-sdk``'s ``PacketFormat``, checked against ouster-sdk 1.0.1 in
docs/DATASETS.md, "Ouster packet bags"). ``ouster-sdk`` itself is not used: its wheel pins rosbags 0.9,
click < 8.1.8 and flask, which would downgrade this project's rosbags 0.11.

A packet holds ``columns_per_packet`` columns (measurement blocks), each a column header
(timestamp in ns on the sensor's clock, ``measurement_id`` = column index 0..W-1, status)
and ``pixels_per_column`` channel blocks (range in mm, reflectivity, signal, near-IR):

=========================  =============  =============  =============  ===========
profile                    packet header  column header  channel block  col. footer
=========================  =============  =============  =============  ===========
LEGACY                     0              16 (+frame_id)  12 (range 20b)  4 (status)
RNG19_RFL8_SIG16_NIR16     32 (frame_id)  12 (status)    12 (range 19b)  0 (+32 pkt)
RNG15_RFL8_NIR8            32             12             4 (range 15b,  0 (+32 pkt)
                                                         8 mm units)
=========================  =============  =============  =============  ===========

A point is placed as ``ouster-sdk``'s ``XYZLut`` places it: with encoder angle
``θ = 2π(1 − m/W)``, beam azimuth ``α = −beam_azimuth_angles`` and altitude
``φ = beam_altitude_angles`` (degrees), and ``n = lidar_origin_to_beam_origin_mm``, the
lidar-frame point is ``(r − n)·(cos(θ+α)cos φ, sin(θ+α)cos φ, sin φ) + (n cos θ, n sin θ, dz)``
(``dz`` the beam_to_lidar_transform's z offset), then ``lidar_to_sensor_transform`` (mm)
takes it into the sensor frame (``os_sensor``, the frame ouster_ros publishes points in).
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.errors import InputError

LIDAR_MODES = ("512x10", "512x20", "1024x10", "1024x20", "2048x10", "4096x5")


@dataclass(frozen=True)
class Profile:
    """Byte layout of one UDP lidar profile (see the module table)."""

    packet_header: int
    column_header: int
    column_footer: int
    packet_footer: int
    channel: int
    range_bits: int
    range_unit_mm: int
    reflectivity: tuple[int, str]  # offset in the channel block, numpy dtype
    signal: int | None  # offset of the u16 signal photons, None when the profile has none
    near_ir: tuple[int, str] | None


PROFILES = {
    "LEGACY": Profile(0, 16, 4, 0, 12, 20, 1, (4, "<u2"), 6, (8, "<u2")),
    "RNG19_RFL8_SIG16_NIR16": Profile(32, 12, 0, 32, 12, 19, 1, (4, "u1"), 6, (8, "<u2")),
    "RNG15_RFL8_NIR8": Profile(32, 12, 0, 32, 4, 15, 8, (2, "u1"), None, (3, "u1")),
}


@dataclass(frozen=True)
class OusterInfo:
    """What decoding needs from the sensor metadata JSON."""

    lidar_mode: str  # "1024x10"
    profile: str
    imu_profile: str  # udp_profile_imu ("LEGACY": 48-byte packets)
    columns_per_frame: int
    fps: int
    columns_per_packet: int
    pixels_per_column: int
    column_window: tuple[int, int]
    beam_altitude_deg: np.ndarray
    beam_azimuth_deg: np.ndarray
    beam_origin_mm: float  # lidar_origin_to_beam_origin_mm
    beam_z_mm: float  # beam_to_lidar_transform's z offset (0 on OS0/OS1/OS2)
    lidar_to_sensor: np.ndarray  # 4x4, translation in mm
    imu_to_sensor: np.ndarray  # 4x4, translation in mm
    prod_line: str
    source: str  # the file or topic it came from, for messages

    @property
    def layout(self) -> Profile:
        return PROFILES[self.profile]

    @property
    def column_bytes(self) -> int:
        p = self.layout
        return p.column_header + self.pixels_per_column * p.channel + p.column_footer

    @property
    def packet_bytes(self) -> int:
        p = self.layout
        return p.packet_header + self.columns_per_packet * self.column_bytes + p.packet_footer

    @functools.cached_property
    def xyz_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`column_xyz_tables`, computed once per metadata."""
        return column_xyz_tables(self)

    def describe(self) -> str:
        return f"{self.lidar_mode} {self.profile}, {self.pixels_per_column} beams"


def _find(meta: dict[str, Any], key: str, groups: tuple[str, ...]) -> Any:
    """``key`` at the top (the legacy flat metadata) or in one of ``groups`` (the newer one)."""
    if key in meta:
        return meta[key]
    for g in groups:
        if isinstance(meta.get(g), dict) and key in meta[g]:
            return meta[g][key]
    return None


def parse_metadata(text: str, source: str) -> OusterInfo:
    """The sensor metadata JSON (flat legacy or nested ``sensor_info``/``lidar_data_format``
    layout) as :class:`OusterInfo`; an InputError naming ``source`` when it does not fit."""
    try:
        meta = json.loads(text)
    except ValueError as exc:
        raise InputError(f"{source}: Ouster metadata is not JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise InputError(f"{source}: Ouster metadata is not a JSON object")
    fmt = _find(meta, "data_format", ()) or _find(meta, "lidar_data_format", ()) or {}
    mode = _find(meta, "lidar_mode", ("config_params",))
    if mode not in LIDAR_MODES:
        raise InputError(
            f"{source}: Ouster metadata: lidar_mode {mode!r} is not one of {', '.join(LIDAR_MODES)}"
        )
    width, fps = (int(v) for v in mode.split("x"))
    profile = fmt.get("udp_profile_lidar") or _find(meta, "udp_profile_lidar", ("config_params",))
    profile = profile or "LEGACY"
    if profile not in PROFILES:
        raise InputError(
            f"{source}: Ouster metadata: udp_profile_lidar {profile!r} is not supported "
            f"(supported: {', '.join(PROFILES)})"
        )
    groups = ("beam_intrinsics", "lidar_intrinsics", "imu_intrinsics", "sensor_info")
    altitude = np.asarray(_find(meta, "beam_altitude_angles", groups) or [], float)
    azimuth = np.asarray(_find(meta, "beam_azimuth_angles", groups) or [], float)
    pixels = int(fmt.get("pixels_per_column", len(altitude)))
    if len(altitude) != pixels or len(azimuth) != pixels or pixels == 0:
        raise InputError(
            f"{source}: Ouster metadata: {len(altitude)} beam_altitude_angles and {len(azimuth)} "
            f"beam_azimuth_angles for {pixels} pixels_per_column"
        )
    window = fmt.get("column_window", [0, width - 1])
    beam_to_lidar = _find(meta, "beam_to_lidar_transform", groups)
    origin = _find(meta, "lidar_origin_to_beam_origin_mm", groups)

    def matrix(key: str) -> np.ndarray:
        value = _find(meta, key, groups)
        m = np.eye(4) if value is None else np.asarray(value, float).reshape(4, 4)
        return m

    return OusterInfo(
        lidar_mode=mode,
        profile=profile,
        imu_profile=str(
            fmt.get("udp_profile_imu")
            or _find(meta, "udp_profile_imu", ("config_params",))
            or "LEGACY"
        ),
        columns_per_frame=int(fmt.get("columns_per_frame", width)),
        fps=fps,
        columns_per_packet=int(fmt.get("columns_per_packet", 16)),
        pixels_per_column=pixels,
        column_window=(int(window[0]), int(window[1])),
        beam_altitude_deg=altitude,
        beam_azimuth_deg=azimuth,
        beam_origin_mm=float(origin if origin is not None else 0.0),
        beam_z_mm=float(np.asarray(beam_to_lidar, float).reshape(4, 4)[2, 3])
        if beam_to_lidar is not None
        else 0.0,
        lidar_to_sensor=matrix("lidar_to_sensor_transform"),
        imu_to_sensor=matrix("imu_to_sensor_transform"),
        prod_line=str(_find(meta, "prod_line", ("sensor_info",)) or ""),
        source=source,
    )


def read_metadata(path: str | Path) -> OusterInfo:
    """The metadata JSON file at ``path`` (``mapping.ouster_metadata``)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the Ouster metadata file ({exc.strerror})") from None
    return parse_metadata(text, str(path))


def metadata_json(info: OusterInfo) -> str:
    """``info`` as the nested metadata JSON ouster_ros publishes on ``/ouster/metadata``."""
    width = int(info.lidar_mode.split("x")[0])
    beam_to_lidar = np.eye(4)
    beam_to_lidar[0, 3], beam_to_lidar[2, 3] = info.beam_origin_mm, info.beam_z_mm
    return json.dumps(
        {
            "sensor_info": {"prod_line": info.prod_line, "prod_sn": "0", "build_rev": "v2.5.3"},
            "calibration_status": {},
            "config_params": {
                "lidar_mode": info.lidar_mode,
                "udp_profile_lidar": info.profile,
                "udp_profile_imu": info.imu_profile,
                "columns_per_packet": info.columns_per_packet,
                "timestamp_mode": "TIME_FROM_INTERNAL_OSC",
            },
            "beam_intrinsics": {
                "beam_altitude_angles": [float(v) for v in info.beam_altitude_deg],
                "beam_azimuth_angles": [float(v) for v in info.beam_azimuth_deg],
                "lidar_origin_to_beam_origin_mm": info.beam_origin_mm,
                "beam_to_lidar_transform": [float(v) for v in beam_to_lidar.ravel()],
            },
            "lidar_intrinsics": {
                "lidar_to_sensor_transform": [float(v) for v in info.lidar_to_sensor.ravel()]
            },
            "imu_intrinsics": {
                "imu_to_sensor_transform": [float(v) for v in info.imu_to_sensor.ravel()]
            },
            "lidar_data_format": {
                "columns_per_frame": width,
                "columns_per_packet": info.columns_per_packet,
                "pixels_per_column": info.pixels_per_column,
                "column_window": list(info.column_window),
                "fps": info.fps,
                "udp_profile_lidar": info.profile,
                "udp_profile_imu": info.imu_profile,
            },
        },
        indent=1,
    )


def packet_shape_guess(size: int, columns_per_packet: int) -> str:
    """What a lidar packet of ``size`` bytes may be (profile and beams), for messages."""
    guesses = []
    for name, p in PROFILES.items():
        body = size - p.packet_header - p.packet_footer
        if body <= 0 or body % columns_per_packet:
            continue
        column = body // columns_per_packet - p.column_header - p.column_footer
        if column > 0 and column % p.channel == 0 and column // p.channel in (16, 32, 64, 128):
            guesses.append(f"{name} with {column // p.channel} beams")
    return " or ".join(guesses) if guesses else "no known profile"


def column_xyz_tables(info: OusterInfo) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions and offsets (m) in the sensor frame, each (W, H, 3): a return of range
    ``r`` (m) in column ``m``, beam ``b`` lies at ``direction[m, b] * r + offset[m, b]``."""
    width = info.columns_per_frame
    encoder = 2 * np.pi * (1.0 - np.arange(width) / width)[:, None]
    azimuth = -np.deg2rad(info.beam_azimuth_deg)[None, :]
    altitude = np.deg2rad(info.beam_altitude_deg)[None, :]
    direction = np.stack(
        [
            np.cos(encoder + azimuth) * np.cos(altitude),
            np.sin(encoder + azimuth) * np.cos(altitude),
            np.broadcast_to(np.sin(altitude), (width, len(info.beam_altitude_deg))),
        ],
        axis=-1,
    )
    n = info.beam_origin_mm
    if info.beam_z_mm != 0.0:
        n = float(np.hypot(info.beam_origin_mm, info.beam_z_mm))
    base = np.stack(
        [
            np.broadcast_to(info.beam_origin_mm * np.cos(encoder), direction.shape[:2]),
            np.broadcast_to(info.beam_origin_mm * np.sin(encoder), direction.shape[:2]),
            np.full(direction.shape[:2], info.beam_z_mm),
        ],
        axis=-1,
    )
    offset = base - direction * n  # mm, lidar frame
    rot, shift = info.lidar_to_sensor[:3, :3], info.lidar_to_sensor[:3, 3]
    return direction @ rot.T, (offset @ rot.T + shift) * 1e-3


@dataclass
class Columns:
    """The valid columns of some packets: per column time (ns, sensor clock), id and frame;
    per pixel range (m, 0 = no return), reflectivity, signal and near-IR (C, H)."""

    timestamp_ns: np.ndarray
    measurement_id: np.ndarray
    frame_id: np.ndarray
    packet: np.ndarray  # index of the packet each column came in
    range_m: np.ndarray
    reflectivity: np.ndarray
    signal: np.ndarray
    near_ir: np.ndarray


def frame_ids(info: OusterInfo, packets: np.ndarray) -> np.ndarray:
    """The frame (rotation) counter of each packet of a (P, packet_bytes) uint8 array."""
    where = 10 if info.profile == "LEGACY" else 2  # first column header / packet header
    return packets[:, where : where + 2].copy().view("<u2").reshape(-1)


def decode_columns(info: OusterInfo, packets: np.ndarray) -> Columns:
    """Decode (P, packet_bytes) uint8 packets into their valid columns (:class:`Columns`)."""
    p = info.layout
    n_pkt, cpp, h = len(packets), info.columns_per_packet, info.pixels_per_column
    body = packets[:, p.packet_header : p.packet_header + cpp * info.column_bytes]
    cols = body.reshape(n_pkt, cpp, info.column_bytes)

    def field(block: np.ndarray, offset: int, dtype: str) -> np.ndarray:
        size = np.dtype(dtype).itemsize
        return block[..., offset : offset + size].copy().view(dtype)[..., 0]

    ts = field(cols, 0, "<u8")
    mid = field(cols, 8, "<u2")
    if info.profile == "LEGACY":
        frame = field(cols, 10, "<u2")
        status = field(cols, info.column_bytes - 4, "<u4")
        valid = status == 0xFFFFFFFF
    else:
        frame = np.broadcast_to(frame_ids(info, packets)[:, None], (n_pkt, cpp))
        valid = (field(cols, 10, "<u2") & 1) == 1
    chan = cols[..., p.column_header : p.column_header + h * p.channel].reshape(
        n_pkt, cpp, h, p.channel
    )
    if p.channel == 4:  # RNG15: the range is the low 15 bits of a u16
        raw_range = field(chan, 0, "<u2").astype(np.uint32)
    else:
        raw_range = field(chan, 0, "<u4")
    rng = (raw_range & ((1 << p.range_bits) - 1)).astype(np.float64) * (p.range_unit_mm * 1e-3)
    refl = field(chan, *p.reflectivity)
    signal = field(chan, p.signal, "<u2") if p.signal is not None else np.zeros_like(refl)
    nir = field(chan, *p.near_ir) if p.near_ir is not None else np.zeros_like(refl)
    packet = np.broadcast_to(np.arange(n_pkt)[:, None], (n_pkt, cpp))
    return Columns(
        ts[valid],
        mid[valid].astype(np.int64),
        np.asarray(frame)[valid],
        packet[valid],
        rng[valid],
        refl[valid],
        signal[valid],
        nir[valid],
    )
