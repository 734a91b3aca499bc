"""Bags of raw Velodyne packets (``velodyne_msgs/VelodyneScan``) read like PointCloud2 bags.

Truth comes from outside the decoder: the sensor manuals' tables and timing (typed here),
the real capture's pcap records parsed here and the project's pcap reader (checked against
VeloView in test_velodyne_pcap.py), the md5sums real bags carry, and the simulator's scene
mesh and true trajectory.
"""

from __future__ import annotations

import itertools
import sqlite3
import struct
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from canopy_kit.config import MappingConfig
from canopy_kit.errors import ConfigError, InputError
from canopy_kit.io.bag import VELODYNE_SCAN, open_bag
from canopy_kit.io.bag_writer import BagWriter
from canopy_kit.io.info import describe_path
from canopy_kit.io.velodyne import HDL32E, VLP32C, decode_packets, encode_packets
from canopy_kit.io.velodyne_pcap import scans as pcap_scans
from canopy_kit.io.velodyne_ros import scan_from_packets
from canopy_kit.mapping.sensors import resolve_topics, sensor_messages
from canopy_kit.sim import load_sim_config, simulate_session

# VLP-16 manual: elevation by laser id, firing timing, 2 mm range unit.
MANUAL_ELEVATION = np.array([-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15], float)
RING_OF_LASER = np.argsort(np.argsort(MANUAL_ELEVATION))  # the ROS driver's ring: 0 = lowest beam
LASER_US, FIRING_US, BLOCK_US = 2.304, 55.296, 110.592
HOUR_US = 3_600_000_000
TOPIC = "/velodyne_packets"
SAMPLE_HOUR = datetime(2018, 8, 1, 8, tzinfo=UTC).timestamp()  # the capture's sensor clock hour
HOUR0 = 1_699_999_200.0  # a whole hour (epoch s) for synthetic sessions


def read_scans(path: Path, topic: str = "") -> list:
    """The scans the mapping reads (its pass 1: topic resolution, then ``decode_scan``)."""
    with open_bag(path) as bag:
        return list(sensor_messages(bag, resolve_topics(bag, topic)))


def write_packet_bag(path: Path, fmt: str, messages: list[tuple[np.ndarray, object]]) -> Path:
    with BagWriter(path, fmt) as w:
        for stamps, packets in messages:
            w.write_velodyne_scan(TOPIC, stamps, packets)
    return w.path


def test_velodyne_msgs_definitions_are_the_drivers() -> None:
    """Bags written here carry the ROS driver's md5sums (those of real VelodyneScan bags)."""
    from rosbags.typesys import Stores, get_typestore

    from canopy_kit.io.velodyne_ros import register_velodyne_types

    store = get_typestore(Stores.ROS1_NOETIC)
    register_velodyne_types(store)
    assert store.generate_msgdef(VELODYNE_SCAN)[1] == "50804fc9533a0e579e6322c04ae70566"
    assert (
        store.generate_msgdef("velodyne_msgs/msg/VelodynePacket")[1]
        == "ae4f90a23256f44e82baa08dd45c3456"
    )


# -- a synthetic VLP-16 sweep built from the manual --------------------------------------------
def room_sweep(first_counter: int = HOUR_US - 50_000, packets: int = 76, rate_hz: float = 10.0):
    """A VLP-16 turning at ``rate_hz`` in a 4 m x 4 m room (floor 1 m below, ceiling 1.2 m above,
    an open window in the +x wall), made from the manual's timing: the packets' fields, each
    packet's stamp and every slot's exact time, direction (REP 103 frame) and range (0: none).
    The first counter lies 50 ms before the sensor's hour restarts."""
    counter = first_counter + np.arange(packets) * 1_327_104 // 1000  # integer µs, unwrapped
    block, slot = np.arange(12)[None, :, None], np.arange(32)[None, None, :]
    firing, laser = slot // 16, slot % 16
    t_us = counter[:, None, None] + block * BLOCK_US + firing * FIRING_US + laser * LASER_US
    spin = 2 * np.pi * rate_hz * 1e-6
    alpha = spin * (t_us - first_counter)  # clockwise seen from above, 0 along +x
    omega = np.deg2rad(MANUAL_ELEVATION[laser])
    d = np.stack(
        np.broadcast_arrays(
            np.cos(omega) * np.cos(alpha), -np.cos(omega) * np.sin(alpha), np.sin(omega)
        ),
        axis=-1,
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = np.where(d != 0, np.where(d > 0, [2.0, 2.0, 1.2], [-2.0, -2.0, -1.0]) / d, np.inf)
    ranges = t_wall.min(axis=-1)
    hit = d * ranges[..., None]
    window = (
        (t_wall.argmin(axis=-1) == 0)
        & (d[..., 0] > 0)
        & (np.abs(hit[..., 1]) < 0.5)
        & (hit[..., 2] > 0)
    )
    ranges[window] = 0.0
    block_azimuth = (
        np.rint(
            np.rad2deg(spin * (counter[:, None] + np.arange(12) * BLOCK_US - first_counter)) * 100
        )
        % 36000
    )
    reflectivity = np.broadcast_to((7 * laser + block) % 200, ranges.shape)
    data = encode_packets(counter, block_azimuth, ranges, reflectivity)
    return {
        "stamps": HOUR0 + counter * 1e-6,
        "data": data,
        "time": HOUR0 + t_us * 1e-6,
        "xyz": hit,
        "range": ranges,
        "laser": np.broadcast_to(laser, ranges.shape),
        "reflectivity": reflectivity,
    }


def test_synthetic_sweep_round_trip(tmp_path: Path) -> None:
    """(a) Encode, write, read, decode: the points within 2 mm, the times within 1 µs, across
    the hour at which the sensor's microsecond counter restarts."""
    sweep = room_sweep()
    bag = write_packet_bag(tmp_path / "room", "ros2-mcap", [(sweep["stamps"], sweep["data"])])
    (scan,) = read_scans(bag)
    got = sweep["range"].reshape(-1) > 0
    assert 0 < got.sum() < got.size and len(scan) == got.sum()  # the window returns nothing
    error = np.linalg.norm(scan.xyz - sweep["xyz"].reshape(-1, 3)[got], axis=1)
    assert error.max() < 0.002  # 1 mm range rounding, 0.005° azimuth rounding at 3 m
    assert np.abs(scan.times - sweep["time"].reshape(-1)[got]).max() < 1e-6
    assert scan.times[-1] - scan.times[0] > 0.05  # the sweep crosses the counter's restart
    np.testing.assert_array_equal(
        scan.fields["ring"], RING_OF_LASER[sweep["laser"].reshape(-1)[got]]
    )
    np.testing.assert_array_equal(scan.fields["intensity"], sweep["reflectivity"].reshape(-1)[got])
    assert scan.stamp == scan.times[0] and scan.frame_id == "velodyne"
    np.testing.assert_allclose(scan.fields["time"], scan.times - scan.stamp, atol=1e-6)


def write_pcap(path: Path, stamps: np.ndarray, payloads: list[bytes]) -> Path:
    """A classic pcap of the packets as the sensor sends them (Ethernet, IPv4, UDP to 2368)."""
    records = [struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)]
    for t, payload in zip(stamps, payloads, strict=True):
        udp = struct.pack(">HHHH", 2368, 2368, 8 + len(payload), 0) + payload
        ip = struct.pack(
            ">BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0, 64, 17, 0, bytes(4), bytes(4)
        )
        frame = bytes(12) + b"\x08\x00" + ip + udp
        usec = round(t * 1e6)
        records.append(
            struct.pack("<IIII", usec // 1_000_000, usec % 1_000_000, len(frame), len(frame))
        )
        records.append(frame)
    path.write_bytes(b"".join(records))
    return path


def test_pcap_and_bag_of_the_same_packets_agree_across_the_hour(tmp_path: Path) -> None:
    """One decoder: the pcap reader and the VelodyneScan reader give the same returns (in their
    two frames), both counting on across the sensor counter's hourly restart."""
    sweep = room_sweep()
    pcap = write_pcap(
        tmp_path / "room.pcap", sweep["stamps"], [bytes(row) for row in sweep["data"]]
    )
    from_pcap = list(pcap_scans(pcap))
    times = np.concatenate([s.times for s in from_pcap])
    got = sweep["range"].reshape(-1) > 0
    assert np.abs(times - sweep["time"].reshape(-1)[got]).max() < 1e-6
    assert np.concatenate([s.fields["timestamp_us"] for s in from_pcap]).max() < HOUR_US
    xyz = np.concatenate([s.xyz for s in from_pcap])
    from_bag = scan_from_packets(sweep["stamps"], sweep["data"].tobytes(), "velodyne", "room", 0)
    np.testing.assert_allclose(
        from_bag.xyz, np.column_stack([xyz[:, 1], -xyz[:, 0], xyz[:, 2]]), atol=1e-9
    )
    np.testing.assert_allclose(from_bag.times, times, atol=1e-6)


# -- the real capture wrapped into bags ----------------------------------------------------------
@pytest.fixture(scope="module")
def capture(shared_data: Path) -> dict:
    """The sample pcap's VLP-16 data packets (parsed here) and the pcap reader's points."""
    path = shared_data / "mtls_vlp16_apple" / "velodyne_data_20frames_sample.pcap"
    raw = path.read_bytes()
    assert raw[:4] == b"\xd4\xc3\xb2\xa1"  # little-endian, microsecond capture times
    pos, times, payloads = 24, [], []
    while pos + 16 <= len(raw):
        sec, usec, incl, _ = struct.unpack_from("<IIII", raw, pos)
        frame = raw[pos + 16 : pos + 16 + incl]
        pos += 16 + incl
        if incl == 14 + 20 + 8 + 1206 and struct.unpack(">H", frame[36:38])[0] == 2368:
            times.append(sec + usec * 1e-6)
            payloads.append(frame[42:])
    assert len(payloads) == 1516  # shared data README
    reference = list(pcap_scans(path))
    return {
        "capture": np.array(times),
        "sensor": SAMPLE_HOUR
        + np.array([struct.unpack("<I", p[1200:1204])[0] for p in payloads]) * 1e-6,
        "payloads": payloads,
        "xyz": np.concatenate([s.xyz for s in reference]),
        "times": np.concatenate([s.times for s in reference]),
        "laser": np.concatenate([s.fields["ring"] for s in reference]),
        "intensity": np.concatenate([s.fields["intensity"] for s in reference]),
        "timestamp_us": np.concatenate([s.fields["timestamp_us"] for s in reference]),
    }


@pytest.mark.parametrize("fmt", ["ros1", "ros2-mcap"])
@pytest.mark.parametrize("clock", ["capture", "sensor"])
def test_real_capture_in_a_bag_decodes_as_the_pcap_reader(
    tmp_path: Path, capture: dict, fmt: str, clock: str
) -> None:
    """(b) The capture's packets, 76 to a message as the driver records them, stamped with the
    capture times (the driver's default) or the sensor's own clock (its gps_time mode)."""
    stamps, payloads = capture[clock], capture["payloads"]
    messages = [(stamps[i : i + 76], payloads[i : i + 76]) for i in range(0, len(payloads), 76)]
    scans = read_scans(write_packet_bag(tmp_path / "capture", fmt, messages))
    assert len(scans) == len(messages) == 20
    xyz = np.concatenate([s.xyz for s in scans])
    assert len(xyz) == len(capture["xyz"]) == 403_495
    # the same returns in the same order: intensity, range, elevation, ring
    np.testing.assert_array_equal(
        np.concatenate([s.fields["intensity"] for s in scans]), capture["intensity"]
    )
    np.testing.assert_array_equal(
        np.concatenate([s.fields["ring"] for s in scans]), RING_OF_LASER[capture["laser"]]
    )
    np.testing.assert_allclose(
        np.linalg.norm(xyz, axis=1), np.linalg.norm(capture["xyz"], axis=1), rtol=1e-12
    )
    np.testing.assert_allclose(xyz[:, 2], capture["xyz"][:, 2], atol=1e-12)
    # REP 103 frame: VeloView's (x, y) is (-y, x) here
    ros = np.column_stack([capture["xyz"][:, 1], -capture["xyz"][:, 0], capture["xyz"][:, 2]])
    error = np.linalg.norm(xyz - ros, axis=1)
    # A message's last block has no next block to interpolate towards (the pcap reader takes
    # the next message's first): it repeats its own last step instead, and its returns turn by
    # at most the difference of the two steps (times the firing's share of the block, < 0.82).
    last = np.zeros(len(xyz), bool)
    step_change = 0.0
    for (_, packets_m), (_, following) in itertools.pairwise(messages):
        before, final = (
            struct.unpack_from("<H", packets_m[-1], 1002)[0],
            struct.unpack_from("<H", packets_m[-1], 1102)[0],
        )
        after = struct.unpack_from("<H", following[0], 2)[0]
        step_change = max(step_change, abs((after - final) % 36000 - (final - before) % 36000))
        t0 = struct.unpack_from("<I", packets_m[-1], 1200)[0] + 11 * BLOCK_US
        last |= (capture["timestamp_us"] >= t0 - 1e-6) & (capture["timestamp_us"] < t0 + BLOCK_US)
    assert 0 < last.sum() < 0.001 * len(last) and 1 <= step_change <= 5  # in 0.01°
    assert error[~last].max() < 1e-9
    turn = error[last] / np.linalg.norm(ros[last], axis=1)
    assert 0 < turn.max() <= np.deg2rad(0.82 * step_change * 0.01)
    # times: relative times exact; absolute on the clock of the packet stamps
    times = np.concatenate([s.times for s in scans])
    if clock == "sensor":
        assert np.abs(times - capture["times"]).max() < 1e-6
    else:
        clock_offset = np.median(capture["capture"] - capture["sensor"])  # 2.99 s: the PC clock
        assert 2.9 < clock_offset < 3.1
        start = 0
        for scan in scans:
            diff = scan.times - capture["times"][start : start + len(scan)]
            start += len(scan)
            assert np.ptp(diff) < 1e-6
            assert abs(np.median(diff) - clock_offset) < 0.001
    assert all(b.stamp > a.stamp for a, b in itertools.pairwise(scans))
    assert all(s.frame_id == "velodyne" for s in scans)


@pytest.mark.parametrize("removed", ["every type", "velodyne_msgs only"])
def test_ros2_sqlite3_without_message_definitions(tmp_path: Path, removed: str) -> None:
    """Older rosbag2 sqlite3 bags store no definitions: velodyne_msgs must come from canopy-kit."""
    sweep = room_sweep(first_counter=1_000_000)
    with BagWriter(tmp_path / "old", "ros2-sqlite3") as w:
        w.write_imu("/imu", HOUR0, (0, 0, 0), (0, 0, 9.81))
        w.write_velodyne_scan(TOPIC, sweep["stamps"], sweep["data"])
    (db,) = w.path.glob("*.db3")
    with sqlite3.connect(db) as con:
        where = "" if removed == "every type" else " WHERE topic_type LIKE 'velodyne_msgs/%'"
        assert con.execute(f"DELETE FROM message_definitions{where}").rowcount >= 1
    (scan,) = read_scans(w.path)
    assert len(scan) == (sweep["range"] > 0).sum()


# -- which topic is the LiDAR --------------------------------------------------------------------
def test_pointcloud2_is_preferred_and_a_named_velodyne_topic_is_read(tmp_path: Path) -> None:
    sweep = room_sweep(first_counter=1_000_000)
    with BagWriter(tmp_path / "both", "ros2-mcap") as w:
        w.write_velodyne_scan(TOPIC, sweep["stamps"], sweep["data"])
        w.write_points("/velodyne_points", HOUR0 + 1, {k: np.ones(3, np.float32) for k in "xyz"})
    with open_bag(w.path) as bag:
        assert resolve_topics(bag).scans == "/velodyne_points"
        assert resolve_topics(bag, TOPIC).scans == TOPIC
    assert len(read_scans(w.path, TOPIC)[0]) == (sweep["range"] > 0).sum()
    facts = describe_path(w.path)
    assert facts["lidar_topic"] == "/velodyne_points"
    assert {t["name"]: t["role"] for t in facts["topics"]} == {
        TOPIC: "lidar",
        "/velodyne_points": "lidar",
    }


def test_bag_of_packets_only_shows_its_lidar_topic(tmp_path: Path) -> None:
    sweep = room_sweep(first_counter=1_000_000)
    bag = write_packet_bag(tmp_path / "packets", "ros1", [(sweep["stamps"], sweep["data"])])
    facts = describe_path(bag)
    assert facts["lidar_topic"] == TOPIC
    assert facts["topics"] == [{"name": TOPIC, "type": VELODYNE_SCAN, "count": 1, "role": "lidar"}]
    from rich.console import Console

    from canopy_kit.cli.info import grids
    from canopy_kit.cli.tables import print_grid

    console = Console(width=120, record=True, force_terminal=True, color_system=None)
    for grid in grids(facts):
        print_grid(grid, console)
    text = console.export_text()
    assert "lidar_topic" in text and "velodyne_msgs/msg/VelodyneScan" in text and "lidar" in text


def test_no_lidar_topic_names_both_types(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "imu_only", "ros2-mcap") as w:
        w.write_imu("/imu", HOUR0, (0, 0, 0), (0, 0, 9.81))
    with open_bag(w.path) as bag, pytest.raises(InputError) as err:
        resolve_topics(bag)
    assert (
        "no sensor_msgs/msg/PointCloud2 topic (or velodyne_msgs/msg/VelodyneScan, "
        "ouster_sensor_msgs/msg/PacketMsg (lidar))"
    ) in str(err.value)
    with open_bag(w.path) as bag, pytest.raises(InputError) as err:
        resolve_topics(bag, "/imu")
    assert (
        "carries sensor_msgs/msg/Imu, expected sensor_msgs/msg/PointCloud2 (or "
        "velodyne_msgs/msg/VelodyneScan, ouster_sensor_msgs/msg/PacketMsg (lidar))"
    ) in str(err.value)


# -- malformed packets ----------------------------------------------------------------------------
def _three_messages() -> list[tuple[np.ndarray, list[bytes]]]:
    sweep = room_sweep(first_counter=1_000_000, packets=12)
    packets = [bytes(row) for row in sweep["data"]]
    return [(sweep["stamps"][i : i + 4], packets[i : i + 4]) for i in (0, 4, 8)]


def _corrupt(messages: list, packet: int, offset: int, value: bytes) -> list:
    stamps, packets = messages[1]
    bad = bytearray(packets[packet])
    bad[offset : offset + len(value)] = value
    return [
        messages[0],
        (stamps, packets[:packet] + [bytes(bad)] + packets[packet + 1 :]),
        messages[2],
    ]


@pytest.mark.parametrize(
    ("packet", "offset", "value", "says"),
    [
        (
            2,
            1205,
            b"\x55",
            "packet 2: product byte 0x55 is not a sensor this decoder knows (VLP-16 0x22",
        ),
        (
            1,
            4 * 100,
            b"\x12\x34",
            "packet 1, block 4 starts with bytes 12 34, not the block flag FF EE",
        ),
        (3, 1204, b"\x39", "packet 3: dual-return packets (return mode 0x39) are not decoded yet"),
    ],
)
def test_malformed_packet_is_a_clear_error(
    tmp_path: Path, packet: int, offset: int, value: bytes, says: str
) -> None:
    """(d) The error names the bag, the topic, the message and the packet, and what is wrong."""
    bag = write_packet_bag(
        tmp_path / "bad", "ros2-mcap", _corrupt(_three_messages(), packet, offset, value)
    )
    with pytest.raises(InputError) as err:
        read_scans(bag)
    # one of three messages unusable: more than the 20 % a topic may lose (a few would be dropped)
    assert f"{bag}: topic '{TOPIC}': 1 of 3 scans unusable" in str(err.value)
    assert f"message 1: {says}" in str(err.value)


def test_packet_of_the_wrong_length_is_a_clear_error(tmp_path: Path) -> None:
    """A bag whose own VelodynePacket has a variable-length ``data`` (a fork) and a short packet."""
    from rosbags.typesys import get_types_from_msg

    messages = _three_messages()
    stamps, packets = messages[1]
    messages[1] = (stamps, packets[:3] + [packets[3][:1000]])
    with BagWriter(tmp_path / "fork", "ros1") as w:
        types = get_types_from_msg("time stamp\nuint8[] data\n", "velodyne_msgs/msg/VelodynePacket")
        types.update(
            get_types_from_msg(
                "std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets\n", VELODYNE_SCAN
            )
        )
        w.typestore.register(types)  # the bag's own definition, which the reader then uses
        for s, p in messages:
            w.write_velodyne_scan(TOPIC, s, p)
    with pytest.raises(InputError) as err:
        read_scans(w.path)
    assert f"{w.path}: topic '{TOPIC}': 1 of 3 scans unusable" in str(err.value)
    assert "message 1: packet 3 has 1000 bytes; a Velodyne data packet has 1206" in str(err.value)


# -- the other sensors the decoder knows -----------------------------------------------------------
def _one_return(product: int, block: int, channel: int, raw_distance: int) -> bytes:
    """A packet (timestamp 1 s past the hour) whose blocks step by 0.20° from 100.00°, with one return."""
    packet = bytearray(1206)
    for b in range(12):
        struct.pack_into("<HH", packet, b * 100, 0xEEFF, 10_000 + 20 * b)
    struct.pack_into("<HB", packet, block * 100 + 4 + 3 * channel, raw_distance, 77)
    struct.pack_into("<IBB", packet, 1200, 1_000_000, 0x37, product)
    return bytes(packet)


@pytest.mark.parametrize(
    ("channel", "elevation", "azimuth_offset"),
    [
        (0, -25.0, 1.4),
        (1, -1.0, -4.2),
        (31, -1.333, -1.4),
    ],
)
def test_vlp32c_return(channel: int, elevation: float, azimuth_offset: float) -> None:
    """VLP-32C manual: one firing per block (55.296 µs), lasers in pairs 2.304 µs apart, 4 mm
    range unit; elevations and azimuth offsets of VeloView's VLP-32c calibration (offset = -rotCorrection)."""
    points = decode_packets(_one_return(0x28, 5, channel, 2500), "VLP-32C")
    i = 5 * 32 + channel
    assert points["distance"][i] == pytest.approx(2500 * 0.004)
    assert points["time_us"][i] == pytest.approx(1_000_000 + 5 * 55.296 + (channel // 2) * 2.304)
    assert points["elevation"][i] == elevation
    step = 20 * (channel // 2) * 2.304 / 55.296  # towards the next block, by firing time
    assert points["azimuth"][i] == pytest.approx(10_000 + 20 * 5 + step + 100 * azimuth_offset)
    assert VLP32C.name == "VLP-32C"


@pytest.mark.parametrize(
    ("channel", "elevation"), [(0, -30.67), (1, -9.33), (15, 0.0), (31, 10.67)]
)
def test_hdl32e_return(channel: int, elevation: float) -> None:
    """HDL-32E manual: 32 lasers per block fired 1.152 µs apart, blocks 46.08 µs apart, 2 mm unit;
    in the REP 103 frame the return lies along its azimuth, clockwise from +x."""
    data = _one_return(0x21, 7, channel, 5000)
    points = decode_packets(data, "HDL-32E")
    i = 7 * 32 + channel
    assert points["time_us"][i] == pytest.approx(1_000_000 + 7 * 46.08 + channel * 1.152)
    assert points["elevation"][i] == elevation and points["distance"][i] == pytest.approx(10.0)
    azimuth = 100.0 + 0.2 * 7 + 0.2 * channel * 1.152 / 46.08  # degrees
    assert points["azimuth"][i] == pytest.approx(azimuth * 100)
    scan = scan_from_packets(np.array([HOUR0 + 1.0]), data, "velodyne", "HDL-32E", 0)
    a, e = np.deg2rad(azimuth), np.deg2rad(elevation)
    np.testing.assert_allclose(
        scan.xyz[0],
        10 * np.array([np.cos(e) * np.cos(a), -np.cos(e) * np.sin(a), np.sin(e)]),
        atol=1e-9,
    )
    assert scan.fields["ring"][0] == np.argsort(np.argsort(HDL32E.elevation_deg))[channel]


# -- the simulated VLP-16 -------------------------------------------------------------------------
def test_simulated_vlp16_fires_like_the_manual_and_decodes_onto_the_scene() -> None:
    """(a) Noise-free simulated packets: the manual's packet timing and azimuth steps, and every
    decoded point, placed with the true pose at its own time, on the scene's surfaces."""
    import open3d as o3d

    from canopy_kit.sim.lidar import SpinningLidar
    from canopy_kit.sim.session import build_world

    cfg = load_sim_config(
        "pistachio",
        {
            "seed": 5,
            "orchard": {"rows": 1, "trees_per_row": 2},
            "lidar": {
                "output": "velodyne_packets",
                "range_noise": 0.0,
                "dropout": 0.0,
                "frame_id": "velodyne",
            },
        },
        sensor="vlp16",
    )
    _, trajectory, scene, rngs = build_world(cfg)
    lidar = SpinningLidar(cfg.lidar, scene, trajectory, rngs["lidar"])
    surfaces = scene.raycasting_scene()
    stamps = lidar.sweep_times()
    for stamp in stamps[[5, len(stamps) // 2, len(stamps) // 2 + 1]]:  # standing still, driving
        packets = lidar.sweep(stamp).packets
        counters = np.array([struct.unpack("<I", bytes(p[1200:1204]))[0] for p in packets.data])
        assert len(counters) in (75, 76)  # 754 packets per second, 10 turns
        assert set(np.diff(counters)) <= {1327, 1328}  # 24 firings of 55.296 µs
        assert packets.stamps[0] >= stamp and packets.stamps[0] - stamp < 0.0014
        assert set(bytes(packets.data[:, 1204])) == {0x37} and set(
            bytes(packets.data[:, 1205])
        ) == {0x22}
        azimuth = (
            packets.data[:, :1200].reshape(-1, 12, 100)[:, :, 2:4].copy().view("<u2").reshape(-1)
        )
        steps = np.diff(azimuth.astype(int)) % 36000  # 3600°/s x 110.592 µs = 0.398°, in 0.01°
        assert set(steps) <= {39, 40, 41} and abs(steps.mean() - 39.81) < 0.05  # ± integer µs times
        scan = scan_from_packets(packets.stamps, packets.data.tobytes(), "velodyne", "sim", 0)
        assert len(scan) == packets.returns > 5000
        pos, rot = trajectory.poses(scan.times)
        world = np.einsum("nij,nj->ni", rot.as_matrix(), scan.xyz) + pos
        off = surfaces.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
        assert np.median(off) < 0.0005 and off.max() < 0.0015  # ranges in 2 mm units: 1 mm


def test_simulator_vlp16_settings_are_checked() -> None:
    cfg = load_sim_config("pistachio", {"lidar": {"output": "velodyne_packets"}}, sensor="vlp16")
    assert (cfg.lidar.output, cfg.lidar.firing) == (
        "velodyne_packets",
        "columns",
    )  # packets imply vlp16
    with pytest.raises(ConfigError, match="lidar.rate_hz: a VLP-16 turns at 5-20 Hz"):
        load_sim_config("pistachio", {"lidar": {"firing": "vlp16", "rate_hz": 25.0}})
    with pytest.raises(ConfigError, match="lidar.max_range"):
        load_sim_config("pistachio", {"lidar": {"output": "velodyne_packets", "max_range": 200.0}})


# -- (c) a simulated session written both ways maps the same ---------------------------------------
@pytest.fixture(scope="module")
def twin_maps(tmp_path_factory) -> dict:
    """One row of three pistachio trees seen by a simulated VLP-16, written as raw packets and as
    the PointCloud2 of the same packets (same seed), each mapped."""
    from canopy_kit.mapping import build_map
    from canopy_kit.mapping.trajectory_error import evaluate_against_simulation

    out = {}
    for output in ("velodyne_packets", "points"):
        cfg = load_sim_config(
            "pistachio",
            {
                "seed": 23,
                "orchard": {"rows": 1, "trees_per_row": 3},
                "lidar": {"firing": "vlp16", "output": output},
            },
            sensor="vlp16",
        )
        sim = simulate_session(tmp_path_factory.mktemp(output) / "s", cfg)
        result = build_map(sim.bag, MappingConfig())
        out[output] = (sim, result, evaluate_against_simulation(result, sim.root))
    return out


@pytest.mark.slow
def test_packets_and_points_of_one_session_map_alike(twin_maps: dict) -> None:
    packets_sim, packets, packets_ev = twin_maps["velodyne_packets"]
    points_sim, points, points_ev = twin_maps["points"]
    with open_bag(packets_sim.bag) as bag:
        assert {t.msgtype for t in bag.topics() if t.name == "/points"} == {VELODYNE_SCAN}
    assert packets_sim.n_points == points_sim.n_points
    assert packets.warnings == points.warnings == []
    # measured: ATE 2.14 cm both (trajectories 4 µm apart), 555,366 and 555,364 map points
    assert packets_ev["ate_rmse_m"] <= 0.10 and points_ev["ate_rmse_m"] <= 0.10
    assert abs(packets_ev["ate_rmse_m"] - points_ev["ate_rmse_m"]) < 0.01
    a, b = packets.trajectory, points.trajectory
    assert len(a) == len(b)
    assert np.abs(a[["x", "y", "z"]].to_numpy() - b[["x", "y", "z"]].to_numpy()).max() < 0.01
    assert abs(len(packets.map.xyz) - len(points.map.xyz)) < 1e-4 * len(points.map.xyz)
    assert packets_ev["map_aligned"]["median_m"] < 0.02
