"""Bags of raw Ouster packets (ouster_ros ``PacketMsg`` + metadata JSON) read as scans.

Truth comes from outside the decoder: packets written and decoded by ouster-sdk 1.0.1's
own packet writer and XYZLut (data/samples/ouster_sdk_reference.npz, made by
scripts/make_ouster_reference.py), the simulator's ray hits and firing times, its scene
mesh and true trajectory, and its per-tree truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from canopy_kit.errors import ConfigError, InputError
from canopy_kit.io.bag import open_bag
from canopy_kit.io.bag_writer import BagWriter
from canopy_kit.io.ouster import frame_ids, parse_metadata
from canopy_kit.io.ouster_bag import OUSTER_LIDAR, OusterRotation, scan_from_rotation
from canopy_kit.mapping.sensors import resolve_topics, sensor_messages
from canopy_kit.sim import load_sim_config

REFERENCE = Path(__file__).parents[1] / "data" / "samples" / "ouster_sdk_reference.npz"
TOPIC = "/ouster/lidar_packets"


def packet_lidar(columns: int, rate_hz: float, profile: str, **more: object) -> dict:
    """The simulator's lidar settings of an Ouster writing packets in a lidar mode/profile."""
    return {
        "output": "ouster_packets",
        "frame_id": "os_sensor",
        "topic": TOPIC,
        "columns": columns,
        "rate_hz": rate_hz,
        "ouster_profile": profile,
        **more,
    }


RNG19 = "RNG19_RFL8_SIG16_NIR16"
OLD_TYPE = "ouster_ros/msg/PacketMsg"  # ouster_ros before 0.11


def ouster_config(columns: int, rate_hz: int, profile: str, **lidar: object) -> object:
    """A simulated OS0-32 recording packets of lidar mode ``columns`` x ``rate_hz``."""
    return load_sim_config(
        "pistachio",
        {
            "seed": 5,
            "orchard": {"rows": 1, "trees_per_row": 2},
            "lidar": packet_lidar(columns, rate_hz, profile, **lidar),
        },
        sensor="os0-32",
    )


def rotations(columns: int, rate_hz: int, profile: str, n: int = 3, **lidar: object):
    """``n`` consecutive noise-free rotations mid-drive: (rotations, trajectory, scene)."""
    from canopy_kit.sim.lidar import SpinningLidar
    from canopy_kit.sim.session import build_world

    cfg = ouster_config(columns, rate_hz, profile, range_noise=0.0, dropout=0.0, **lidar)
    _, trajectory, scene, rngs = build_world(cfg)
    lidar_sim = SpinningLidar(cfg.lidar, scene, trajectory, rngs["lidar"])
    stamps = lidar_sim.sweep_times()
    mid = len(stamps) // 2
    return [lidar_sim.sweep(s).packets for s in stamps[mid : mid + n]], trajectory, scene


def write_bag(path: Path, fmt: str, packets: list, metadata: bool = True) -> Path:
    with BagWriter(path, fmt) as w:
        for p in packets:
            w.write_ouster_packets(TOPIC, p.stamps, p.data, p.metadata if metadata else None)
    return w.path


def read_scans(path: Path, metadata_file: Path | None = None) -> list:
    """The scans the mapping reads (its pass 1: topic resolution, then ``decode_scan``)."""
    with open_bag(path, metadata_file) as bag:
        return list(sensor_messages(bag, resolve_topics(bag)))


# -- the decoder against ouster-sdk ---------------------------------------------------------------
@pytest.mark.parametrize("profile", ["LEGACY", RNG19])
def test_decoder_places_points_as_ouster_sdk_does(profile: str) -> None:
    """Packets made by ouster-sdk's own writer decode to ouster-sdk's XYZLut points (in the
    sensor frame), beams and frame id."""
    ref = np.load(REFERENCE)
    info = parse_metadata(str(ref[f"{profile}_metadata"]), "ouster-sdk metadata")
    assert info.profile == profile
    packets = ref[f"{profile}_packets"]
    assert packets.shape[1] == info.packet_bytes
    assert set(frame_ids(info, packets)) == {321}
    rotation = OusterRotation(
        [10**9 + k for k in range(len(packets))],
        [bytes(p) for p in packets],
        info,
        TOPIC,
        None,  # type: ignore[arg-type]
    )
    scan = scan_from_rotation(rotation, "reference", 0)
    range_mm = ref[f"{profile}_range_mm"]  # (beams, columns)
    beam, column = np.nonzero(range_mm.T > 0)[1], np.nonzero(range_mm.T > 0)[0]
    sdk_xyz = ref[f"{profile}_xyz"][beam, column]
    assert len(scan) == len(sdk_xyz) > 500
    np.testing.assert_array_equal(scan.fields["ring"], beam)
    assert np.abs(scan.xyz - sdk_xyz).max() < 1e-9


# -- simulated packets ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("columns", "rate_hz", "profile", "fmt"),
    [(1024, 10, RNG19, "ros2-mcap"), (512, 20, "LEGACY", "ros1")],
)
def test_simulated_rotation_decodes_onto_the_simulators_points(
    tmp_path: Path, columns: int, rate_hz: int, profile: str, fmt: str
) -> None:
    """Each rotation is W/16 packets of one frame id; the bag's decoded scans hold the
    simulator's returns (to the 1 mm range unit) at their exact firing times, and every
    point, placed with the true pose at its own time, lies on the scene's surfaces."""
    import open3d as o3d

    sim, trajectory, scene = rotations(columns, rate_hz, profile)
    info = parse_metadata(sim[0].metadata, "sim")
    assert info.lidar_mode == f"{columns}x{rate_hz}" and info.profile == profile
    for p in sim:
        assert p.data.shape == (columns // 16, info.packet_bytes)
        assert len(set(frame_ids(info, p.data))) == 1
    bag = write_bag(tmp_path / "ouster", fmt, sim)
    with open_bag(bag) as b:
        types = {t.name: (t.msgtype, t.count) for t in b.topics()}
    assert types[TOPIC] == (OUSTER_LIDAR, 3)  # rotations, from 3 x W / 16 packets
    assert types["/ouster/metadata"] == ("std_msgs/msg/String", 1)
    scans = read_scans(bag)
    assert [s.frame_id for s in scans] == ["os_sensor"] * 3
    surfaces = scene.raycasting_scene()
    for scan, truth in zip(scans, sim, strict=True):
        assert len(scan) == truth.returns > 5000
        ours = np.lexsort((scan.fields["ring"], scan.times))
        theirs = np.lexsort((truth.ring, truth.times))
        np.testing.assert_array_equal(scan.fields["ring"][ours], truth.ring[theirs])
        assert np.abs(scan.times[ours] - truth.times[theirs]).max() < 1e-6  # float64 epoch s
        assert np.linalg.norm(scan.xyz[ours] - truth.xyz[theirs], axis=1).max() < 0.001
        assert scan.stamp == pytest.approx(truth.times.min(), abs=1e-6)
        assert np.ptp(scan.times) == pytest.approx(1.0 / rate_hz, rel=0.01)
        pos, rot = trajectory.poses(scan.times)
        world = np.einsum("nij,nj->ni", rot.as_matrix(), scan.xyz) + pos
        off = surfaces.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
        assert np.median(off) < 0.0005 and off.max() < 0.002


def test_metadata_from_a_file_decodes_like_the_topic(tmp_path: Path) -> None:
    """Without a metadata topic the bag stops with how to give the metadata; the file given
    decodes exactly what the topic does."""
    sim, _, _ = rotations(512, 10, RNG19, n=2)
    with_topic = read_scans(write_bag(tmp_path / "a", "ros2-mcap", sim))
    bare = write_bag(tmp_path / "b", "ros2-mcap", sim, metadata=False)
    with pytest.raises(InputError, match=r"no Ouster metadata topic.*mapping\.ouster_metadata="):
        read_scans(bare)
    meta = tmp_path / "metadata.json"
    meta.write_text(sim[0].metadata)
    from_file = read_scans(bare, meta)
    assert len(from_file) == len(with_topic) == 2
    for a, b in zip(from_file, with_topic, strict=True):
        np.testing.assert_array_equal(a.xyz, b.xyz)
        np.testing.assert_array_equal(a.times, b.times)


def _metadata_for(tmp_path: Path, columns: int, rate_hz: int, profile: str) -> Path:
    from canopy_kit.io.ouster import metadata_json
    from canopy_kit.sim.ouster import sensor_info

    spec = ouster_config(columns, rate_hz, profile).lidar
    path = tmp_path / f"meta_{columns}x{rate_hz}_{profile}.json"
    path.write_text(metadata_json(sensor_info(spec)))
    return path


@pytest.mark.parametrize(
    ("packets", "metadata", "says"),
    [
        (
            (1024, 10, RNG19),
            (1024, 10, "LEGACY"),
            r"packets of 6400 bytes \(RNG19_RFL8_SIG16_NIR16 "
            r"with 32 beams\).*1024x10 LEGACY, 32 beams packets have 6464 bytes",
        ),
        ((1024, 10, RNG19), (512, 10, RNG19), r"column ids up to 1023.*512x10 RNG19"),
        (
            (512, 20, RNG19),
            (1024, 10, RNG19),
            r"rotations of 512 columns \(packets look like "
            r"512x20\).*1024x10 RNG19",
        ),
        (
            (1024, 10, RNG19),
            (2048, 10, RNG19),
            r"a column every 97\.7 µs \(expected 48\.8\) "
            r"\(packets look like 1024x10\).*2048x10 RNG19",
        ),
    ],
)
def test_metadata_of_another_mode_is_named(tmp_path: Path, packets, metadata, says: str) -> None:
    sim, _, _ = rotations(*packets)
    bag = write_bag(tmp_path / "bag", "ros2-mcap", sim, metadata=False)
    meta = _metadata_for(tmp_path, *metadata)
    with pytest.raises(InputError, match=says) as err:
        read_scans(bag, meta)
    assert str(meta) in str(err.value) and TOPIC in str(err.value)


def test_cli_without_metadata_exits_2_and_writes_nothing(tmp_path: Path) -> None:
    from test_cli_foundation import run_cli

    sim, _, _ = rotations(512, 10, RNG19, n=2)
    bag = write_bag(tmp_path / "bag", "ros2-mcap", sim, metadata=False)
    out = tmp_path / "run"
    cli = run_cli("run", str(bag), "--out", str(out))
    assert cli.returncode == 2, cli.stderr
    assert "no Ouster metadata topic" in cli.stderr and "mapping.ouster_metadata" in cli.stderr
    assert not (out / "trees.csv").exists() and not (out / "map.laz").exists()
    wrong = _metadata_for(tmp_path, 512, 10, "LEGACY")
    cli = run_cli("map", str(bag), "--out", str(out), "--set", f"mapping.ouster_metadata={wrong}")
    assert cli.returncode == 2 and "512x10 LEGACY" in cli.stderr and str(wrong) in cli.stderr


def test_simulator_ouster_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match=r"lidar.columns/rate_hz: .*got 4096x5"):
        ouster_config(4096, 5, RNG19)
    with pytest.raises(ConfigError, match=r"lidar.frame_id: .*'os_sensor'"):
        ouster_config(1024, 10, RNG19, frame_id="lidar")
    with pytest.raises(ConfigError, match=r"lidar.rings: an Ouster has 16, 32, 64 or 128 beams"):
        ouster_config(1024, 10, RNG19, rings=40)


# -- simulated sessions through the pipeline ------------------------------------------------------
def _session_run(tmp_path_factory, columns: int, rate_hz: int, profile: str, imu_topic: str):
    from canopy_kit.config import load_preset
    from canopy_kit.pipeline import run
    from canopy_kit.sim import simulate_session

    cfg = load_sim_config(
        "pistachio",
        {
            "seed": 11,
            "orchard": {"rows": 1, "trees_per_row": 3},
            "imu": {  # /ouster/imu_packets: the sensor's own IMU packets, at its 100 Hz
                "topic": imu_topic,
                "output": "ouster_packets" if "ouster" in imu_topic else "imu",
                "rate_hz": 100.0 if "ouster" in imu_topic else 200.0,
            },
            "lidar": packet_lidar(columns, rate_hz, profile),
        },
        sensor="os0-32",
    )
    sim = simulate_session(tmp_path_factory.mktemp(f"ouster{columns}") / "s", cfg)
    result = run(load_preset("adaptive"), sim.bag, tmp_path_factory.mktemp("run"), truth=sim.root)
    return sim, result


def _judge(sim, result) -> dict:
    """ATE, and the trees matched one-to-one with the truth (positions brought into the truth
    frame by the trajectory alignment; packets carry no tree ids) with volume errors."""
    from scipy.optimize import linear_sum_assignment

    mapping = result.metrics["evaluation"]["mapping"]
    align = np.asarray(mapping["alignment"])
    truth = pd.read_csv(sim.truth_dir / "trees.csv")
    trees = result.trees
    xy = trees[["x", "y"]].to_numpy() @ align[:2, :2].T + align[:2, 3]
    distance = np.linalg.norm(xy[:, None] - truth[["x", "y"]].to_numpy()[None], axis=2)
    rows, cols = linear_sum_assignment(distance)
    pct = {
        col: 100
        * np.abs(trees[col].to_numpy()[rows] / truth["crown_volume_m3"].to_numpy()[cols] - 1)
        for col in ("volume_convex_hull_m3", "volume_alpha_m3")
    }
    return {
        "ate": mapping["ate_rmse_m"],
        "found": len(trees),
        "truth": len(truth),
        "match_m": distance[rows, cols],
        "volume_pct": pct,
    }


@pytest.mark.parametrize(
    ("columns", "rate_hz", "profile", "imu_topic"),
    [
        (1024, 10, RNG19, "/ouster/imu_packets"),
        pytest.param(512, 20, "LEGACY", "/imu/data", marks=pytest.mark.slow),
    ],
)
def test_simulated_ouster_session_maps_and_measures_its_trees(
    tmp_path_factory, columns: int, rate_hz: int, profile: str, imu_topic: str
) -> None:
    """An OS0-32 drive along one row of three pistachio trees, recorded as packets (the IMU too,
    in the 1024x10 session), the IMU read and no warning: ATE within
    0.10 m, the three trees found one-to-one within 0.5 m, and each tree's convex-hull and alpha
    volume within 10 % of its true crown (test_pipeline's bound for the same estimators)."""
    sim, result = _session_run(tmp_path_factory, columns, rate_hz, profile, imu_topic)
    mapping = result.metrics["mapping"]
    assert mapping["topics"]["imu"] == imu_topic and mapping["imu"]["standstill_found"]
    assert result.metrics["warnings"] == []
    got = _judge(sim, result)
    assert got["ate"] <= 0.10
    assert got["found"] == got["truth"] == 3
    assert got["match_m"].max() < 0.5
    for col, pct in got["volume_pct"].items():
        assert pct.max() < 10.0, col


def _flat_metadata(nested: str) -> str:
    """The same sensor in the flat metadata layout of older firmware and drivers."""
    meta = json.loads(nested)
    flat = {
        **meta["sensor_info"],
        "lidar_mode": meta["config_params"]["lidar_mode"],
        **meta["beam_intrinsics"],
        **meta["lidar_intrinsics"],
        **meta["imu_intrinsics"],
        "data_format": meta["lidar_data_format"],
    }
    del flat["beam_to_lidar_transform"]
    return json.dumps(flat)


def test_older_driver_bag_with_flat_metadata_and_lost_packets(tmp_path: Path) -> None:
    """A ROS 1 bag of ``ouster_ros/PacketMsg`` with the metadata as a flat JSON file and a
    few packets lost: the same points as the complete bag, less the lost columns."""
    sim, _, _ = rotations(512, 10, "LEGACY", n=3)
    complete = read_scans(write_bag(tmp_path / "complete", "ros1", sim))
    keep = np.ones(len(sim[1].data), bool)
    keep[[3, 4, 20]] = False  # UDP packets the recorder never saw
    with BagWriter(tmp_path / "old", "ros1") as w:
        for k, p in enumerate(sim):
            rows = keep if k == 1 else slice(None)
            w.write_ouster_packets(TOPIC, p.stamps[rows], p.data[rows], None, msgtype=OLD_TYPE)
    meta = tmp_path / "os-992109000123.json"
    meta.write_text(_flat_metadata(sim[0].metadata))
    info = parse_metadata(meta.read_text(), str(meta))
    assert (info.lidar_mode, info.profile, info.beam_origin_mm) == ("512x10", "LEGACY", 27.67)
    with open_bag(w.path) as bag:
        assert {t.name: t.msgtype for t in bag.topics()} == {TOPIC: OUSTER_LIDAR}
    old = read_scans(w.path, meta)
    assert len(old) == 3
    for k in (0, 2):
        np.testing.assert_array_equal(old[k].xyz, complete[k].xyz)
    lost_columns = np.flatnonzero(np.repeat(~keep, 16))
    time_of = complete[1].times
    column = np.rint((time_of - time_of.min()) * 512 * 10).astype(int)
    assert len(old[1]) == np.isin(column, lost_columns, invert=True).sum() < len(complete[1])
    np.testing.assert_array_equal(old[1].xyz, complete[1].xyz[~np.isin(column, lost_columns)])


def test_imu_packets_read_as_imu_samples(tmp_path: Path) -> None:
    """LEGACY IMU packets (layout checked against ouster-sdk 1.0.1's PacketFormat: sys, accel
    and gyro times in ns, acceleration in g, angular velocity in deg/s, float32) become IMU
    samples in SI units on the bag's clock, read by the mapping beside the packets' scans."""
    import struct

    from canopy_kit.mapping.sensors import ImuBuffer

    sim, _, _ = rotations(512, 10, RNG19, n=2)
    start, end = sim[0].stamps[0], sim[1].stamps[-1]
    log = np.arange(start, end, 0.01)  # 100 Hz
    delay_ns = 52_000  # from the gyro's reading to the packet's sending
    gyro_deg = np.array([5.0, -10.0, 20.0])
    acc_g = np.array([0.01, 0.02, 1.0])
    with BagWriter(tmp_path / "bag", "ros2-mcap") as w:
        for p in sim:
            w.write_ouster_packets(TOPIC, p.stamps, p.data, p.metadata)
        for k, t in enumerate(log):
            gyro_ts = 7_000_000_000 + k * 10_000_000
            packet = struct.pack(
                "<QQQ6f", gyro_ts + delay_ns, gyro_ts - 1000, gyro_ts, *acc_g, *gyro_deg
            )
            w.write_ouster_packets("/ouster/imu_packets", [t], [np.frombuffer(packet, np.uint8)])
    with open_bag(w.path) as bag:
        topics = resolve_topics(bag)
        assert topics.imu == "/ouster/imu_packets" and topics.scans == TOPIC
        series = bag.imu()
        buffer = ImuBuffer()
        scans = list(sensor_messages(bag, topics, buffer))
    assert len(scans) == 2 and series is not None and len(series.t) == len(log)
    expected_t = np.array([round(t * 1e9) - delay_ns for t in log]) * 1e-9
    assert np.abs(series.t - expected_t).max() < 1e-6
    np.testing.assert_allclose(
        series.angular_velocity, np.tile(np.deg2rad(gyro_deg), (len(log), 1)), rtol=1e-6
    )
    np.testing.assert_allclose(
        series.linear_acceleration, np.tile(acc_g * 9.80665, (len(log), 1)), rtol=1e-6
    )
    assert series.frame_id == "os_sensor" == scans[0].frame_id
    assert len(buffer) == len(log)
