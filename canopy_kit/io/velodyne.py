"""Velodyne data packets (VLP-16, VLP-32C, HDL-32E): the one decoder behind the pcap reader
(:mod:`canopy_kit.io.velodyne_pcap`) and ``velodyne_msgs/VelodyneScan`` bags
(:mod:`canopy_kit.io.velodyne_ros`), and the packet encoder of the simulator.

A 1206-byte data packet holds 12 blocks of (bytes FF EE, azimuth in 0.01°, 32 × (distance,
reflectivity)), then a 4-byte timestamp (µs past the hour of the sensor's clock) and two
factory bytes (return mode, product). A block's azimuth is that of its first firing; the
others are interpolated by firing time towards the next block's azimuth (VLP-16 manual §9).

| sensor | product | lasers | a block holds | return time in the block | distance unit |
|---|---|---|---|---|---|
| VLP-16 | 0x22 | 16 | two firings | firing × 55.296 µs + laser × 2.304 µs (block 110.592 µs) | 2 mm |
| VLP-32C | 0x28 | 32 | one firing, lasers in pairs | (channel // 2) × 2.304 µs (block 55.296 µs) | 4 mm |
| HDL-32E | 0x21 | 32 | one firing | channel × 1.152 µs (block 46.08 µs) | 2 mm |

The VLP-32C's lasers also point up to 4.2° off the block azimuth (its manual's azimuth
offsets). Two frame conventions exist for the same return: Velodyne's manual and VeloView
(x = d·cos ω·sin α, y = d·cos ω·cos α: azimuth 0 along +y) and the ROS driver's REP 103
frame (x = d·cos ω·cos α, y = −d·cos ω·sin α: azimuth 0 along +x, the sensor's front).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from canopy_kit.errors import InputError

DATA_PACKET_BYTES = 1206
BLOCKS = 12  # per packet
CHANNELS = 32  # returns per block
SLOTS = BLOCKS * CHANNELS  # returns per packet
BLOCK_FLAG = 0xEEFF  # the bytes FF EE, read little-endian
RETURN_MODES = {0x37: "strongest", 0x38: "last", 0x39: "dual"}
DUAL_RETURN = 0x39
HOUR_US = 3_600_000_000

_BLOCK_DTYPE = np.dtype(
    [
        ("flag", "<u2"),
        ("azimuth", "<u2"),
        ("returns", [("distance", "<u2"), ("reflectivity", "u1")], (CHANNELS,)),
    ]
)
PACKET_DTYPE = np.dtype(
    [
        ("blocks", _BLOCK_DTYPE, (BLOCKS,)),
        ("timestamp", "<u4"),
        ("return_mode", "u1"),
        ("product", "u1"),
    ]
)
assert PACKET_DTYPE.itemsize == DATA_PACKET_BYTES


@dataclass(frozen=True)
class VelodyneModel:
    """One sensor's packet layout: which laser each of a block's 32 returns is, when it fires."""

    name: str
    product: int
    elevation_deg: tuple[float, ...]  # by laser id
    azimuth_offset_deg: tuple[
        float, ...
    ]  # by laser id: where the laser points off the block azimuth
    distance_unit_m: float
    block_us: float  # time from one block to the next
    slot_laser: tuple[int, ...]  # laser id of each of a block's 32 returns
    slot_us: tuple[float, ...]  # firing time of each return after the block's first firing

    @property
    def lasers(self) -> int:
        return len(self.elevation_deg)

    @property
    def ring_of_laser(self) -> np.ndarray:
        """Ring number by laser id: 0 for the lowest beam, as the ROS driver numbers them."""
        return np.argsort(np.argsort(self.elevation_deg, kind="stable"), kind="stable").astype(
            np.uint16
        )

    def slot_offsets_us(self) -> np.ndarray:
        """(12, 32) firing time of every return of a packet after the packet's timestamp."""
        return np.arange(BLOCKS)[:, None] * self.block_us + np.asarray(self.slot_us)[None, :]


_VLP16_ELEVATION = (
    -15,
    1,
    -13,
    3,
    -11,
    5,
    -9,
    7,
    -7,
    9,
    -5,
    11,
    -3,
    13,
    -1,
    15,
)  # manual table 9-1
VLP16 = VelodyneModel(
    "VLP-16",
    0x22,
    tuple(float(e) for e in _VLP16_ELEVATION),
    (0.0,) * 16,
    0.002,
    110.592,
    tuple(list(range(16)) * 2),
    tuple(f * 55.296 + laser * 2.304 for f in range(2) for laser in range(16)),
)
# VLP-32C manual, vertical angle and azimuth offset by laser id (VeloView's VLP-32c.xml has the same,
# its rotCorrection being minus the offset).
_VLP32C = (
    (-25, 1.4),
    (-1, -4.2),
    (-1.667, 1.4),
    (-15.639, -1.4),
    (-11.31, 1.4),
    (0, -1.4),
    (-0.667, 4.2),
    (-8.843, -1.4),
    (-7.254, 1.4),
    (0.333, -4.2),
    (-0.333, 1.4),
    (-6.148, -1.4),
    (-5.333, 4.2),
    (1.333, -1.4),
    (0.667, 4.2),
    (-4, -1.4),
    (-4.667, 1.4),
    (1.667, -4.2),
    (1, 1.4),
    (-3.667, -4.2),
    (-3.333, 4.2),
    (3.333, -1.4),
    (2.333, 1.4),
    (-2.667, -1.4),
    (-3, 1.4),
    (7, -1.4),
    (4.667, 1.4),
    (-2.333, -4.2),
    (-2, 4.2),
    (15, -1.4),
    (10.333, 1.4),
    (-1.333, -1.4),
)
VLP32C = VelodyneModel(
    "VLP-32C",
    0x28,
    tuple(float(e) for e, _ in _VLP32C),
    tuple(float(a) for _, a in _VLP32C),
    0.004,
    55.296,
    tuple(range(32)),
    tuple((c // 2) * 2.304 for c in range(32)),
)
# HDL-32E manual: lasers 0..31 alternate between the lower and the upper half of the fan.
_HDL32E_ELEVATION = (
    -30.67,
    -9.33,
    -29.33,
    -8.0,
    -28.0,
    -6.67,
    -26.67,
    -5.33,
    -25.33,
    -4.0,
    -24.0,
    -2.67,
    -22.67,
    -1.33,
    -21.33,
    0.0,
    -20.0,
    1.33,
    -18.67,
    2.67,
    -17.33,
    4.0,
    -16.0,
    5.33,
    -14.67,
    6.67,
    -13.33,
    8.0,
    -12.0,
    9.33,
    -10.67,
    10.67,
)
HDL32E = VelodyneModel(
    "HDL-32E",
    0x21,
    _HDL32E_ELEVATION,
    (0.0,) * 32,
    0.002,
    46.08,
    tuple(range(32)),
    tuple(c * 1.152 for c in range(32)),
)
MODELS: dict[int, VelodyneModel] = {m.product: m for m in (VLP16, VLP32C, HDL32E)}


def _known_products() -> str:
    return ", ".join(f"{m.name} 0x{m.product:02X}" for m in MODELS.values())


def packet_array(data: bytes, where: str = "Velodyne", first_packet: int = 0) -> np.ndarray:
    """Data packets as a structured array, checked: whole packets, FF EE block flags, one known
    sensor, single return. ``first_packet`` numbers the packets in error messages."""
    if len(data) % DATA_PACKET_BYTES:
        raise InputError(
            f"{where}: {len(data)} bytes are not whole {DATA_PACKET_BYTES}-byte "
            "Velodyne data packets"
        )
    packets = np.frombuffer(data, dtype=PACKET_DTYPE)
    if not len(packets):
        return packets
    flags = packets["blocks"]["flag"]
    bad = np.argwhere(flags != BLOCK_FLAG)
    if len(bad):
        p, b = (int(v) for v in bad[0])
        flag = int(flags[p, b])
        raise InputError(
            f"{where}: packet {first_packet + p}, block {b} starts with bytes "
            f"{flag & 0xFF:02X} {flag >> 8:02X}, not the block flag FF EE (not a Velodyne data "
            "packet, or a corrupt one)"
        )
    products = packets["product"]
    unknown = np.flatnonzero(~np.isin(products, list(MODELS)))
    if len(unknown):
        p = int(unknown[0])
        raise InputError(
            f"{where}: packet {first_packet + p}: product byte 0x{int(products[p]):02X} "
            f"is not a sensor this decoder knows ({_known_products()})"
        )
    if np.any(products != products[0]):
        names = sorted({MODELS[int(v)].name for v in products})
        raise InputError(
            f"{where}: packets of different sensors ({', '.join(names)}) in one stream"
        )
    dual = np.flatnonzero(packets["return_mode"] == DUAL_RETURN)
    if len(dual):
        raise InputError(
            f"{where}: packet {first_packet + int(dual[0])}: dual-return packets "
            f"(return mode 0x{DUAL_RETURN:02X}) are not decoded yet"
        )
    return packets


def packet_model(packets: np.ndarray) -> VelodyneModel:
    """The sensor of checked packets (see :func:`packet_array`)."""
    return MODELS[int(packets["product"][0])] if len(packets) else VLP16


def firing_azimuths(
    block_azimuth: np.ndarray,
    model: VelodyneModel,
    returns: np.ndarray | None = None,
    next_azimuth: float | None = None,
) -> np.ndarray:
    """Azimuth (0.01°, in [0, 36000)) of every return, (P, 12, 32), from the (P, 12) blocks'
    azimuths; or of the returns at the flat indices ``returns`` only.

    Each return's azimuth is its block's plus the step to the next block in proportion to its
    firing time; the last block steps towards ``next_azimuth`` (the block after the packets)
    or, when None, takes the step before it. A step of more than 10° (a gap in the packets)
    takes the median step instead.
    """
    az = np.asarray(block_azimuth, np.float64).reshape(-1)
    gap = np.empty_like(az)
    gap[:-1] = np.mod(az[1:] - az[:-1], 36000.0)
    if next_azimuth is not None:
        gap[-1:] = np.mod(next_azimuth - az[-1:], 36000.0)
    else:
        gap[-1:] = gap[-2] if len(gap) > 1 else 0.0
    jumps = gap > 1000.0
    if jumps.any():  # a jump is not a step
        gap[jumps] = np.median(gap)
    index = np.arange(az.size * CHANNELS) if returns is None else returns
    block, slot = index // CHANNELS, index % CHANNELS
    fraction = np.asarray(model.slot_us) / model.block_us
    offset = 100.0 * np.asarray(model.azimuth_offset_deg)[list(model.slot_laser)]
    azimuth = np.mod(az[block] + gap[block] * fraction[slot] + offset[slot], 36000.0)
    return azimuth.reshape(-1, BLOCKS, CHANNELS) if returns is None else azimuth


def decode_packets(
    payloads: bytes | Sequence[bytes],
    where: str = "Velodyne",
    first_packet: int = 0,
    next_azimuth: float | None = None,
) -> dict[str, np.ndarray]:
    """Per-return arrays of Velodyne data packets in firing order, zero ranges (no return)
    kept; see :func:`decode_array` (packets checked by :func:`packet_array`)."""
    data = payloads if isinstance(payloads, bytes | bytearray) else b"".join(payloads)
    return decode_array(packet_array(bytes(data), where, first_packet), next_azimuth=next_azimuth)


def decode_array(
    packets: np.ndarray, returns_only: bool = False, next_azimuth: float | None = None
) -> dict[str, np.ndarray]:
    """Per-return arrays of checked packets in firing order: ``time_us`` (µs past the hour,
    sensor clock), ``azimuth`` (0.01°), ``distance`` (m), ``laser`` (id), ``ring`` (by
    elevation), ``elevation`` (°), ``intensity`` (reflectivity) and ``packet`` (index of its
    packet); every slot, or with ``returns_only`` the returns with a range. ``next_azimuth``:
    see :func:`firing_azimuths`."""
    model = packet_model(packets)
    returns = packets["blocks"]["returns"].reshape(-1)
    raw = returns["distance"]
    index = np.flatnonzero(raw) if returns_only else np.arange(len(raw))
    packet, slot = index // SLOTS, index % CHANNELS
    laser = np.asarray(model.slot_laser, np.uint8)[slot]
    time_us = (
        packets["timestamp"].astype(np.float64)[packet]
        + model.slot_offsets_us().reshape(-1)[index % SLOTS]
    )
    return {
        "time_us": time_us,
        "azimuth": firing_azimuths(packets["blocks"]["azimuth"], model, index, next_azimuth),
        "distance": raw[index].astype(np.float64) * model.distance_unit_m,
        "laser": laser,
        "ring": model.ring_of_laser[laser],
        "elevation": np.asarray(model.elevation_deg)[laser],
        "intensity": returns["reflectivity"][index],
        "packet": packet,
    }


def xyz_from(
    azimuth_cdeg: np.ndarray,
    elevation_deg: np.ndarray,
    distance: np.ndarray,
    frame: Literal["velodyne", "ros"] = "velodyne",
) -> np.ndarray:
    """(N, 3) float64 coordinates of returns: ``velodyne`` is the manual's and VeloView's frame
    (azimuth 0 along +y), ``ros`` the ROS driver's REP 103 frame (azimuth 0 along +x)."""
    omega = np.deg2rad(elevation_deg)
    alpha = np.deg2rad(np.asarray(azimuth_cdeg) * 0.01)
    flat = distance * np.cos(omega)
    a, b = flat * np.sin(alpha), flat * np.cos(alpha)
    x, y = (a, b) if frame == "velodyne" else (b, -a)
    return np.column_stack([x, y, distance * np.sin(omega)])


def hour_base(reference_time: float, us_past_hour: float) -> float:
    """Epoch seconds of the hour the sensor's timestamp counts from (the one that puts it
    nearest ``reference_time``, e.g. the capture or message time)."""
    base = np.floor(reference_time / 3600.0) * 3600.0
    offset = reference_time - (base + us_past_hour * 1e-6)
    if offset > 1800:
        base += 3600.0
    elif offset < -1800:
        base -= 3600.0
    return float(base)


def encode_packets(
    timestamp_us: np.ndarray,
    block_azimuth: np.ndarray,
    distance_m: np.ndarray,
    reflectivity: np.ndarray,
    model: VelodyneModel = VLP16,
    return_mode: int = 0x37,
) -> np.ndarray:
    """(P, 1206) uint8 data packets from per-packet timestamps (µs past the hour), (P, 12)
    block azimuths (0.01°) and (P, 12, 32) distances (m, 0 = no return; rounded to the
    sensor's unit) and reflectivities (0-255)."""
    p = len(timestamp_us)
    packets = np.zeros(p, PACKET_DTYPE)
    blocks = packets["blocks"]
    blocks["flag"] = BLOCK_FLAG
    blocks["azimuth"] = np.mod(np.asarray(block_azimuth, np.int64), 36000)
    raw = np.rint(np.asarray(distance_m, np.float64) / model.distance_unit_m)
    if np.any(raw > 0xFFFF):
        raise ValueError(
            f"encode_packets: distances beyond the {model.name}'s "
            f"{0xFFFF * model.distance_unit_m:.1f} m cannot be encoded"
        )
    blocks["returns"]["distance"] = raw.astype(np.uint16)
    blocks["returns"]["reflectivity"] = np.clip(np.rint(reflectivity), 0, 255).astype(np.uint8)
    packets["timestamp"] = np.mod(np.asarray(timestamp_us, np.int64), HOUR_US)
    packets["return_mode"] = return_mode
    packets["product"] = model.product
    return packets.view(np.uint8).reshape(p, DATA_PACKET_BYTES)
