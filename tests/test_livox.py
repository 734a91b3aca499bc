"""Livox LiDARs: the drivers' CustomMsg and driver2 PointCloud2 layout read, their IMU in g
converted, and a simulated Mid-360 mapped and segmented against the simulator's truth.

Truth comes from outside the reader: hand-built messages whose coordinates and times are
computed here with integers, rosbags' own (de)serialiser of the drivers' message
definitions, the livox_ros_driver2 source's PointCloud2 layout (offsets 0-18, 26 bytes a
point) and the simulator's trees and trajectory.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from canopy_kit.errors import InputError
from canopy_kit.io.bag import POINTCLOUD2, open_bag
from canopy_kit.io.bag_writer import BagWriter
from canopy_kit.io.livox import CUSTOM_MSG, CUSTOM_MSG_V1, POINT_RECORD
from canopy_kit.mapping.sensors import ImuBuffer, resolve_topics, sensor_messages

TOPIC = "/livox/lidar"
TIMEBASE = 1_700_000_123_456_789_012  # ns


def read_scans(path: Path) -> list:
    """The scans the mapping reads (topic resolution, then ``decode_scan``)."""
    with open_bag(path) as bag:
        return list(sensor_messages(bag, resolve_topics(bag)))


def hand_points(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = np.zeros(n, POINT_RECORD)
    p["offset_time"] = np.sort(rng.integers(0, 100_000_000, n))  # a 0.1 s frame
    p["x"], p["y"], p["z"] = (rng.uniform(-30, 30, (3, n))).astype(np.float32)
    p["reflectivity"] = rng.integers(0, 256, n)
    p["tag"] = rng.choice([0, 16, 32], n)
    p["line"] = np.arange(n) % 4
    return p


@pytest.mark.parametrize("fmt", ["ros1", "ros2-mcap", "ros2-sqlite3"])
@pytest.mark.parametrize("msgtype", [CUSTOM_MSG, CUSTOM_MSG_V1])
def test_custom_msg_decodes_to_exact_coordinates_and_times(
    tmp_path: Path, fmt: str, msgtype: str
) -> None:
    frames = [hand_points(n, seed) for seed, n in enumerate((5, 1, 0, 300))]
    bases = [TIMEBASE + k * 100_000_000 for k in range(len(frames))]
    with BagWriter(tmp_path / "b", fmt) as w:
        for base, pts in zip(bases, frames):
            w.write_livox_custom(TOPIC, base, pts, "livox_frame", msgtype)
    scans = read_scans(w.path)
    assert [s.index for s in scans] == [0, 1, 2, 3]
    for scan, base, pts in zip(scans, bases, frames):
        assert scan.frame_id == "livox_frame"
        assert scan.stamp == pytest.approx(base * 1e-9, abs=1e-6)
        xyz = np.column_stack([pts["x"], pts["y"], pts["z"]]).astype(np.float64)
        assert np.array_equal(scan.xyz, xyz)  # float32 values carried exactly
        # times: timebase + offset_time in integer ns, compared at float64's resolution
        expected = np.array([(base + int(o)) / 1e9 for o in pts["offset_time"]])
        assert scan.times is not None and np.all(np.abs(scan.times - expected) < 5e-7)
        assert np.array_equal(scan.fields["line"], pts["line"])
        assert np.array_equal(scan.fields["tag"], pts["tag"])
        assert np.array_equal(scan.fields["intensity"], pts["reflectivity"].astype(np.float32))
        assert "ring" not in scan.fields


def test_custom_msg_topic_is_found_and_described(tmp_path: Path) -> None:
    from canopy_kit.io.info import describe_path

    with BagWriter(tmp_path / "b.bag", "ros1") as w:
        w.write_livox_custom(TOPIC, TIMEBASE, hand_points(10, 0))
    facts = describe_path(w.path)
    assert facts["lidar_topic"] == TOPIC
    assert facts["topics"] == [{"name": TOPIC, "type": CUSTOM_MSG, "count": 1, "role": "lidar"}]


def test_rosbags_deserialised_custom_msg_decodes_alike(tmp_path: Path) -> None:
    """The fallback (rosbags' objects, one per point) and the numpy view give one scan."""
    from canopy_kit.io.livox import scan_fields

    pts = hand_points(50, 3)
    with BagWriter(tmp_path / "b", "ros2-mcap") as w:
        w.write_livox_custom(TOPIC, TIMEBASE, pts)
    with open_bag(w.path) as bag:
        conn = next(c for c in bag.reader.connections if c.topic == TOPIC)
        _, _, raw = next(iter(bag.reader.messages(connections=[conn])))
        fast = scan_fields(bag.reader.deserialize(raw, CUSTOM_MSG), "x")
        objects = bag.reader.typestore.deserialize_cdr(raw, CUSTOM_MSG)
    # rosbags gives one object per point: the comparison is not numpy against itself
    assert not isinstance(objects.points, np.ndarray)
    slow = scan_fields(objects, "x")
    assert fast[0] == slow[0]
    assert np.array_equal(fast[1], slow[1]) and np.array_equal(fast[3], slow[3])
    for key in fast[2]:
        assert np.array_equal(fast[2][key], slow[2][key])


@pytest.mark.parametrize("clock_start", [1_700_000_000.0, 100.0])
def test_driver2_pointcloud2_layout_reads_exactly(tmp_path: Path, clock_start: float) -> None:
    """livox_ros_driver2's PointCloud2 (PointXYZRTLT): 26-byte points, float64 ``timestamp``
    in absolute ns, also on a bag clock started near zero (1e11 ns, not 1e11 s)."""
    n = 40
    pts = hand_points(n, 7)
    base_ns = int(round(clock_start * 1e9))
    ts_ns = (base_ns + pts["offset_time"].astype(np.int64)).astype(np.float64)
    columns = {
        "x": pts["x"],
        "y": pts["y"],
        "z": pts["z"],
        "intensity": pts["reflectivity"].astype(np.float32),
        "tag": pts["tag"],
        "line": pts["line"],
        "timestamp": ts_ns,
    }
    with BagWriter(tmp_path / "b", "ros2-mcap") as w:
        w.write_points(TOPIC, clock_start, columns, "livox_frame")
    with open_bag(w.path) as bag:
        conn = next(c for c in bag.reader.connections if c.topic == TOPIC)
        _, _, raw = next(iter(bag.reader.messages(connections=[conn])))
        msg = bag.reader.deserialize(raw, conn.msgtype)
    # the driver's layout (lddc.cpp InitPointcloud2MsgHeader)
    assert msg.point_step == 26
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
        ("x", 0, 7),
        ("y", 4, 7),
        ("z", 8, 7),
        ("intensity", 12, 7),
        ("tag", 16, 2),
        ("line", 17, 2),
        ("timestamp", 18, 8),
    ]
    (scan,) = read_scans(w.path)
    assert np.array_equal(scan.xyz[:, 0], pts["x"].astype(np.float64))
    assert np.array_equal(scan.xyz[:, 2], pts["z"].astype(np.float64))
    expected = np.array([(base_ns + int(o)) / 1e9 for o in pts["offset_time"]])
    assert np.abs(scan.times - expected).max() < 5e-7
    assert np.array_equal(scan.fields["line"], pts["line"])


def test_point_num_disagreeing_with_the_points_stops_the_run(tmp_path: Path) -> None:
    from test_cli_foundation import run_cli

    with BagWriter(tmp_path / "b.bag", "ros1") as w:
        for k in range(3):
            base = TIMEBASE + k * 100_000_000
            w.write_livox_custom(TOPIC, base, hand_points(20, k), point_num=25 if k == 1 else None)
    bad_t = (TIMEBASE + 100_000_000) * 1e-9
    with pytest.raises(InputError, match=rf"topic '{TOPIC}'.*t={bad_t:.3f} s.*point_num says 25"):
        read_scans(w.path)
    cli = run_cli("map", str(w.path), "--out", str(tmp_path / "m"))
    assert cli.returncode == 2, cli.stderr
    assert TOPIC in cli.stderr and "point_num" in cli.stderr
    assert not (tmp_path / "m").exists()


def test_a_cut_custom_msg_is_an_input_error(tmp_path: Path) -> None:
    from canopy_kit.io.livox import parse_custom_msg, serialize_custom_msg

    raw = serialize_custom_msg(TIMEBASE, hand_points(30, 1), "livox_frame", ros2=True)
    from canopy_kit.errors import MessageError

    with pytest.raises(MessageError, match="end before the message does"):
        parse_custom_msg(raw[:-40], ros2=True)


# -- IMU in g ---------------------------------------------------------------------------------
def _imu_buffer(accel: np.ndarray) -> ImuBuffer:
    buf = ImuBuffer(source="bag: topic '/livox/imu'")
    for k, a in enumerate(accel):
        buf.append(k * 0.005, (0.0, 0.0, 0.0), tuple(a))
    return buf


def test_imu_in_g_is_converted_with_a_warning_naming_the_topic() -> None:
    rng = np.random.default_rng(0)
    g_units = np.array([0.02, -0.01, 1.0]) + rng.normal(0, 0.01, (400, 3))
    buf = _imu_buffer(g_units)
    series = buf.series()
    assert np.allclose(series.linear_acceleration, g_units * 9.80665)
    assert len(buf.warnings) == 1 and "'/livox/imu'" in buf.warnings[0] and " g" in buf.warnings[0]
    assert np.allclose(buf.series(100).linear_acceleration, g_units[100:] * 9.80665)  # slices too


def test_imu_in_g_is_known_after_a_start_up_of_zeros() -> None:
    """A driver's first all-zero samples neither decide the unit nor count in the median."""
    g_units = np.vstack([np.zeros((30, 3)), np.tile([0.0, 0.0, 1.0], (25, 1))])
    buf = _imu_buffer(g_units)
    assert np.array_equal(buf.series().linear_acceleration[30:], g_units[30:] * 9.80665)
    assert len(buf.warnings) == 1 and "median magnitude 1.000" in buf.warnings[0]


@pytest.mark.parametrize("tilt_deg", [0.0, 90.0, 180.0])
def test_a_normal_imu_is_left_alone(tilt_deg: float) -> None:
    """m/s² at rest in any orientation, and a drive that brakes and turns hard, stay as they are."""
    rng = np.random.default_rng(1)
    t = np.radians(tilt_deg)
    gravity = 9.81 * np.array([np.sin(t), 0.0, np.cos(t)])
    accel = gravity + rng.normal(0, 2.0, (400, 3))  # ±2 m/s² of vehicle motion
    buf = _imu_buffer(accel)
    assert np.array_equal(buf.series().linear_acceleration, accel)
    assert buf.warnings == []


def test_bag_imu_in_g_is_converted(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "b", "ros2-mcap") as w:
        for k in range(50):
            w.write_imu("/livox/imu", 1_700_000_000 + k * 0.005, (0, 0, 0), (0.0, 0.0, 1.0))
    with open_bag(w.path) as bag:
        imu = bag.imu()
        assert np.allclose(imu.linear_acceleration, [0.0, 0.0, 9.80665])
        assert any("'/livox/imu'" in x and "in g" in x for x in bag.warnings)


def test_a_cut_ros1_bag_of_custom_msgs_is_recovered(tmp_path: Path) -> None:
    """A ROS 1 bag cut short is read record by record (rosbags refuses it); its CustomMsgs
    still decode through the numpy reader."""
    frames = [hand_points(3000, k) for k in range(20)]
    with BagWriter(tmp_path / "b.bag", "ros1") as w:
        for k, pts in enumerate(frames):
            w.write_livox_custom(TOPIC, TIMEBASE + k * 100_000_000, pts)
    data = w.path.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with open_bag(cut) as bag:
        scans = list(sensor_messages(bag, resolve_topics(bag)))
        assert bag.recovered
    assert 5 <= len(scans) < 20
    for scan, pts in zip(scans, frames):
        assert np.array_equal(scan.xyz[:, 1], pts["y"].astype(np.float64))


# -- simulated Livox sensors --------------------------------------------------------------------
def _angles(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (
        np.degrees(np.arctan2(dirs[:, 1], dirs[:, 0])),
        np.degrees(np.arcsin(np.clip(dirs[:, 2], -1, 1))),
    )


def test_mid360_pattern_fills_its_field_and_does_not_repeat() -> None:
    from canopy_kit.sim.livox import PATTERNS, pattern_directions

    p = PATTERNS["livox-mid360"]
    t = np.arange(40_000) / p.point_rate  # two 0.1 s frames at 200,000 points/s
    dirs, line = pattern_directions(p, t, (-7.0, 52.0))
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    az, el = _angles(dirs)
    assert el.min() >= -7.0 - 1e-9 and el.max() <= 52.0 + 1e-9
    assert set(np.unique(line)) == {0, 1, 2, 3}
    first, second = slice(0, 20_000), slice(20_000, 40_000)
    # one frame reaches every 10° x 10° cell of the field, all the way round
    cells = np.histogram2d(az[first], el[first], bins=[36, 6], range=[[-180, 180], [-7, 53]])[0]
    assert (cells > 0).all()
    # the next frame falls elsewhere: its points are not the first frame's again
    from scipy.spatial import cKDTree

    gap, _ = cKDTree(dirs[first]).query(dirs[second])
    assert np.median(np.degrees(gap)) > 0.1
    fine = [-180, 180], [-7, 53]
    one = (np.histogram2d(az[first], el[first], bins=[720, 120], range=fine)[0] > 0).sum()
    two = (np.histogram2d(az, el, bins=[720, 120], range=fine)[0] > 0).sum()
    assert two > 1.5 * one  # coverage grows with integration time


def test_avia_pattern_is_a_forward_rosette() -> None:
    from canopy_kit.sim.livox import PATTERNS, pattern_directions

    p = PATTERNS["livox-avia"]
    t = np.arange(24_000) / p.point_rate
    dirs, line = pattern_directions(p, t)
    off_axis = np.degrees(np.arccos(np.clip(dirs[:, 0], -1, 1)))
    assert off_axis.max() <= 35.2 + 1e-9 and np.percentile(off_axis, 99) > 30.0
    assert set(np.unique(line)) == set(range(6))
    # densest at the centre (petals cross there): points per solid angle fall outwards
    inner = (off_axis < 10).sum() / (1 - np.cos(np.radians(10)))
    outer = ((off_axis > 25) & (off_axis < 35)).sum() / (
        np.cos(np.radians(25)) - np.cos(np.radians(35))
    )
    assert inner > 2 * outer


def test_livox_settings_are_checked() -> None:
    from canopy_kit.errors import ConfigError
    from canopy_kit.sim import load_sim_config

    cfg = load_sim_config("pistachio", sensor="livox-mid360")
    assert cfg.lidar.output == "livox_custom" and cfg.imu.acceleration_unit == "g"
    with pytest.raises(ConfigError, match="lidar.output"):
        load_sim_config("pistachio", {"lidar": {"output": "livox_custom"}})
    with pytest.raises(ConfigError, match="lidar.output"):
        load_sim_config("pistachio", {"lidar": {"output": "velodyne_packets"}}, "livox-mid360")


@pytest.mark.parametrize(
    ("sensor", "output", "rate", "lines"),
    [
        ("livox-mid360", "livox_custom", 200_000, 4),
        ("livox-mid360", "points", 200_000, 4),
        ("livox-avia", "livox_custom", 240_000, 6),
    ],
)
def test_simulated_livox_frames_read_back(
    tmp_path: Path, sensor: str, output: str, rate: int, lines: int
) -> None:
    """A few frames of a simulated Livox (CustomMsg or driver2 PointCloud2) read back with
    the driver's timing: points within their 0.1 s frame at the sensor's rate, IMU in g."""
    from canopy_kit.sim import load_sim_config, simulate_session

    cfg = load_sim_config(
        "pistachio",
        {
            "seed": 3,
            "orchard": {"rows": 1, "trees_per_row": 1},
            "drive": {"start_still": 1.0, "end_still": 0.2},
            "lidar": {"output": output},
        },
        sensor=sensor,
    )
    sim = simulate_session(tmp_path / "s", cfg)
    with open_bag(sim.bag) as bag:
        lidar = next(t for t in bag.topics() if t.name == "/livox/lidar")
        assert lidar.msgtype == (CUSTOM_MSG if output == "livox_custom" else POINTCLOUD2)
        topics = resolve_topics(bag)
        buf = ImuBuffer(source="imu")
        scans = []
        for scan in sensor_messages(bag, topics, buf):
            scans.append(scan)
            if len(scans) == 5:
                break
    for scan in scans:
        assert scan.frame_id == "livox_frame" and "ring" not in scan.fields
        assert scan.times.min() >= scan.stamp - 1e-6 and scan.times.max() < scan.stamp + 0.1
        # fired 1/rate apart (returns only), to float64's 0.24 µs at the epoch
        steps = np.diff(scan.times - scan.stamp) * rate
        assert np.all(np.abs(steps - np.round(steps)) < 0.15)
        assert set(np.unique(scan.fields["line"])) <= set(range(lines))
        assert ("tree_id" in scan.fields) == (output == "points")
    assert np.allclose(np.diff([s.stamp for s in scans]), 0.1, atol=1e-6)
    assert np.median(np.linalg.norm(buf.series().linear_acceleration, axis=1)) == pytest.approx(
        9.81, abs=0.1
    )
    assert buf.warnings and "in g" in buf.warnings[0]


# -- end to end: a simulated Mid-360 drive mapped, segmented and measured -----------------------
# The orchard of the comparison: one row of three pistachios, driven on both sides. A
# CustomMsg has no room for the simulator's per-point tree_id, so the run is scored by crown
# footprints, placed in the truth's frame by the drive's alignment to the true poses: a
# standard (metre-level) receiver, whose offset once put two of these three crowns below IoU
# 0.5 when footprints were placed through the georeference (trees and volumes right).
E2E = {"orchard": {"rows": 1, "trees_per_row": 3}, "gnss": {"mode": "standard"}}


def _run(sim, out: Path):
    from canopy_kit.config import load_preset
    from canopy_kit.pipeline import run

    return run(load_preset("adaptive"), sim.bag, out, truth=sim.root)


@pytest.fixture(scope="module")
def mid360_run(sim_factory, tmp_path_factory):
    sim = sim_factory("pistachio", seed=5, overrides=E2E, sensor="livox-mid360")
    return sim, _run(sim, tmp_path_factory.mktemp("mid360_run"))


def test_mid360_session_maps_segments_and_measures_against_truth(mid360_run) -> None:
    """CustomMsg scans (no rings, per-point times) and an IMU in g, through the whole run."""
    sim, r = mid360_run
    with open_bag(sim.bag) as bag:
        assert {t.name: t.msgtype for t in bag.topics()}["/livox/lidar"] == CUSTOM_MSG
    ev = r.metrics["evaluation"]
    assert ev["mapping"]["ate_rmse_m"] <= 0.10
    assert ev["mapping"]["drift_percent"] < 0.5
    seg = ev["segmentation"]
    assert seg["n_truth"] == 3 and seg["success_rate"] >= 0.98 and seg["label_accuracy"] == 1.0
    assert r.metrics["flagged_segments"] == 0
    # the yardstick test_pipeline.py holds a 32-ring session to: within 10 % of the true crowns
    assert ev["volumes"]["convex_hull"]["mape_pct"] < 10.0
    assert ev["volumes"]["alpha_shape"]["mape_pct"] < 10.0
    (warning,) = [w for w in r.metrics["warnings"] if "in g" in w]
    assert "'/livox/imu'" in warning


@pytest.mark.slow
def test_mid360_maps_and_segments_as_well_as_a_vlp16_of_the_same_orchard(
    mid360_run, sim_factory, tmp_path_factory
) -> None:
    sim, livox = mid360_run
    vlp = sim_factory("pistachio", seed=5, overrides=E2E, sensor="vlp16")
    velodyne = _run(vlp, tmp_path_factory.mktemp("vlp16_run"))
    a, b = livox.metrics["evaluation"], velodyne.metrics["evaluation"]
    assert a["mapping"]["ate_rmse_m"] <= max(0.10, 1.5 * b["mapping"]["ate_rmse_m"])
    assert a["segmentation"]["success_rate"] >= b["segmentation"]["success_rate"]
    for method in ("convex_hull", "alpha_shape"):
        assert a["volumes"][method]["mape_pct"] <= b["volumes"][method]["mape_pct"] + 3.0


def test_truth_map_reads_a_custom_msg_session(mid360_run) -> None:
    """The map from true poses (the volume studies' yardstick) reads CustomMsg scans too:
    every true crown holds mapped points, and no point floats far above the crowns."""
    import pandas as pd

    from canopy_kit.evaluate.truth_map import truth_map

    sim, _ = mid360_run
    reference = truth_map(sim.root, voxel_size=0.1, every=5)
    trees = pd.read_csv(sim.truth_dir / "trees.csv")
    xyz = reference.xyz
    for tree in trees.itertuples():
        inside = (
            np.hypot(xyz[:, 0] - tree.crown_x, xyz[:, 1] - tree.crown_y)
            < 0.5 * tree.crown_diameter_m
        ) & (xyz[:, 2] > tree.z_ground + tree.crown_base_height_m + 0.2)
        assert inside.sum() > 500, tree.label
    assert xyz[:, 2].max() < trees["z_ground"].max() + trees["tree_height_m"].max() + 0.5


@pytest.mark.slow
def test_mid360_pointcloud2_layout_session_maps_segments_and_measures(
    sim_factory, tmp_path_factory
) -> None:
    """livox_ros_driver2's PointCloud2 layout (float64 ``timestamp`` per point, no rings)
    through the whole run, scored by the per-point truth it can carry."""
    overrides = {**E2E, "lidar": {"output": "points"}}
    sim = sim_factory("pistachio", seed=5, overrides=overrides, sensor="livox-mid360")
    with open_bag(sim.bag) as bag:
        assert {t.name: t.msgtype for t in bag.topics()}["/livox/lidar"].endswith("PointCloud2")
    r = _run(sim, tmp_path_factory.mktemp("mid360_points_run"))
    ev = r.metrics["evaluation"]
    assert ev["mapping"]["ate_rmse_m"] <= 0.10
    seg = ev["segmentation"]
    assert seg["n_truth"] == 3 and seg["success_rate"] >= 0.98 and seg["label_accuracy"] == 1.0
    assert ev["volumes"]["convex_hull"]["mape_pct"] < 10.0
    assert ev["volumes"]["alpha_shape"]["mape_pct"] < 10.0
