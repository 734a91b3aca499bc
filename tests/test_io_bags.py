"""ROS1 / ROS2-sqlite3 / ROS2-mcap bags: write small real bags, read them back exactly,
and check that bad input gives an error naming the file and what is wrong."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from canopy_kit.errors import InputError
from canopy_kit.io.bag import open_bag
from canopy_kit.io.bag_writer import BAG_FORMATS, BagWriter

# Dyadic fractions of a second: exactly representable, so stamps survive sec/nanosec.
T0 = 1_700_000_000.0
SCAN_DT = 0.125
N_POINTS = 96
# float64 seconds near 1.7e9 resolve 2.4e-7 s; allow a few ulp.
TIME_TOL = 1e-6


def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


def _ouster_columns(i: int) -> dict[str, np.ndarray]:
    """Ouster convention: ``t`` uint32 nanoseconds after the header stamp."""
    rng = _rng(i)
    return {
        "x": rng.uniform(-30, 30, N_POINTS).astype(np.float32),
        "y": rng.uniform(-30, 30, N_POINTS).astype(np.float32),
        "z": rng.uniform(-2, 8, N_POINTS).astype(np.float32),
        "intensity": rng.uniform(0, 1000, N_POINTS).astype(np.float32),
        "t": np.sort(rng.integers(0, 100_000_000, N_POINTS)).astype(np.uint32),
        "ring": (np.arange(N_POINTS) % 32).astype(np.uint16),
    }


def _velodyne_columns(i: int) -> dict[str, np.ndarray]:
    """Velodyne convention: ``time`` float32 seconds relative to the stamp (here negative:
    the stamp marks the end of the sweep)."""
    rng = _rng(100 + i)
    return {
        "x": rng.uniform(-20, 20, N_POINTS).astype(np.float32),
        "y": rng.uniform(-20, 20, N_POINTS).astype(np.float32),
        "z": rng.uniform(-2, 6, N_POINTS).astype(np.float32),
        "intensity": rng.uniform(0, 255, N_POINTS).astype(np.float32),
        "ring": (np.arange(N_POINTS) % 16).astype(np.uint16),
        "time": np.linspace(-0.1, 0.0, N_POINTS).astype(np.float32),
    }


def _hesai_columns(i: int, stamp: float) -> dict[str, np.ndarray]:
    """Hesai convention: ``timestamp`` float64 absolute seconds."""
    rng = _rng(200 + i)
    return {
        "x": rng.uniform(-10, 10, N_POINTS).astype(np.float32),
        "y": rng.uniform(-10, 10, N_POINTS).astype(np.float32),
        "z": rng.uniform(-1, 4, N_POINTS).astype(np.float32),
        "timestamp": stamp + np.linspace(0.0, 0.1, N_POINTS),
    }


IMU = [
    (
        T0 + k * 0.0625,
        (0.01 * k, -0.02 * k, 0.5),
        (0.1, -0.2 * k, 9.81),
        (0.0, 0.0, np.sin(k / 10), np.cos(k / 10)),
    )
    for k in range(12)
]
FIXES = [(T0 + k * 0.5, 41.6671 + 1e-6 * k, 0.4576 - 2e-6 * k, 283.5 + 0.01 * k) for k in range(4)]
ODOM = [
    (T0 + k * 0.25, (1.5 * k, -0.25 * k, 0.1), (0.0, 0.0, np.sin(k / 8), np.cos(k / 8)))
    for k in range(5)
]


def write_full_bag(path: Path, fmt: str) -> Path:
    """A bag with three PointCloud2 time conventions, Imu, NavSatFix and Odometry."""
    with BagWriter(path, fmt) as w:
        for i in range(3):
            w.write_points(
                "/ouster/points", T0 + i * SCAN_DT, _ouster_columns(i), frame_id="os_lidar"
            )
        for i in range(2):
            w.write_points(
                "/velodyne_points", T0 + i * SCAN_DT, _velodyne_columns(i), frame_id="velodyne"
            )
        w.write_points("/hesai/pandar", T0, _hesai_columns(0, T0), frame_id="hesai")
        for stamp, gyro, acc, quat in IMU:
            w.write_imu("/imu/data", stamp, gyro, acc, quat, frame_id="imu")
        for stamp, lat, lon, alt in FIXES:
            w.write_fix("/gps/fix", stamp, lat, lon, alt, sigma_h=0.02, sigma_v=0.05, status=2)
        for stamp, pos, quat in ODOM:
            w.write_odometry("/odom", stamp, pos, quat)
    return w.path


@pytest.fixture(scope="module", params=BAG_FORMATS)
def full_bag(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_full_bag(tmp_path_factory.mktemp(request.param) / "session", request.param)


def test_topics_types_and_counts(full_bag: Path) -> None:
    with open_bag(full_bag) as bag:
        topics = {t.name: (t.msgtype, t.count) for t in bag.topics()}
        assert topics == {
            "/ouster/points": ("sensor_msgs/msg/PointCloud2", 3),
            "/velodyne_points": ("sensor_msgs/msg/PointCloud2", 2),
            "/hesai/pandar": ("sensor_msgs/msg/PointCloud2", 1),
            "/imu/data": ("sensor_msgs/msg/Imu", len(IMU)),
            "/gps/fix": ("sensor_msgs/msg/NavSatFix", len(FIXES)),
            "/odom": ("nav_msgs/msg/Odometry", len(ODOM)),
        }
        assert bag.start_time == pytest.approx(T0, abs=TIME_TOL)
        last = max([r[0] for r in IMU + FIXES + ODOM] + [T0 + 2 * SCAN_DT])
        assert bag.end_time == pytest.approx(last, abs=TIME_TOL)  # ROS2 adds 1 ns


def test_ouster_scans_round_trip(full_bag: Path) -> None:
    with open_bag(full_bag) as bag:
        scans = bag.scans()  # auto-detected: the busiest PointCloud2 topic
        assert not isinstance(scans, list)  # streamed, not loaded whole
        scans = list(scans)
    assert [s.index for s in scans] == [0, 1, 2]
    for i, scan in enumerate(scans):
        cols = _ouster_columns(i)
        stamp = T0 + i * SCAN_DT
        assert scan.frame_id == "os_lidar"
        assert abs(scan.stamp - stamp) < TIME_TOL
        assert scan.xyz.dtype == np.float64
        np.testing.assert_array_equal(
            scan.xyz, np.column_stack([cols[c] for c in "xyz"]).astype(np.float64)
        )
        assert set(scan.fields) == {"intensity", "t", "ring"}
        for name in ("intensity", "t", "ring"):
            assert scan.fields[name].dtype == cols[name].dtype
            np.testing.assert_array_equal(scan.fields[name], cols[name])
        expected = stamp + cols["t"].astype(np.float64) * 1e-9
        assert np.max(np.abs(scan.times - expected)) < TIME_TOL
        # times span the hand-made offsets: up to 0.1 s after the stamp, never before
        assert scan.times.min() >= stamp - TIME_TOL and scan.times.max() <= stamp + 0.1 + TIME_TOL


def test_velodyne_relative_float_seconds(full_bag: Path) -> None:
    with open_bag(full_bag) as bag:
        scans = list(bag.scans("/velodyne_points"))
    assert len(scans) == 2
    for i, scan in enumerate(scans):
        cols = _velodyne_columns(i)
        stamp = T0 + i * SCAN_DT
        np.testing.assert_array_equal(scan.fields["time"], cols["time"])
        np.testing.assert_array_equal(scan.fields["ring"], cols["ring"])
        expected = stamp + cols["time"].astype(np.float64)
        assert np.max(np.abs(scan.times - expected)) < TIME_TOL
        assert scan.times[0] == pytest.approx(stamp - 0.1, abs=1e-6)  # sweep ends at the stamp


def test_absolute_float64_timestamps(full_bag: Path) -> None:
    with open_bag(full_bag) as bag:
        (scan,) = list(bag.scans("/hesai/pandar"))
    cols = _hesai_columns(0, T0)
    np.testing.assert_array_equal(scan.times, cols["timestamp"])  # absolute: passed through
    np.testing.assert_array_equal(scan.xyz[:, 2], cols["z"].astype(np.float64))


def test_imu_gnss_odometry_round_trip(full_bag: Path) -> None:
    with open_bag(full_bag) as bag:
        imu = bag.imu()
        fix = bag.gnss()
        odom = bag.odometry()
    assert imu is not None and fix is not None and odom is not None
    assert np.max(np.abs(imu.t - [r[0] for r in IMU])) < TIME_TOL
    np.testing.assert_array_equal(imu.angular_velocity, [r[1] for r in IMU])
    np.testing.assert_array_equal(imu.linear_acceleration, [r[2] for r in IMU])
    np.testing.assert_array_equal(imu.orientation, [r[3] for r in IMU])
    assert imu.frame_id == "imu"
    np.testing.assert_array_equal(fix.latitude, [r[1] for r in FIXES])
    np.testing.assert_array_equal(fix.longitude, [r[2] for r in FIXES])
    np.testing.assert_array_equal(fix.altitude, [r[3] for r in FIXES])
    np.testing.assert_array_equal(fix.status, [2] * len(FIXES))
    np.testing.assert_allclose(fix.covariance[0], np.diag([0.02**2, 0.02**2, 0.05**2]).ravel())
    np.testing.assert_array_equal(odom.position, [r[1] for r in ODOM])
    np.testing.assert_array_equal(odom.orientation, [r[2] for r in ODOM])
    assert (odom.frame_id, odom.child_frame_id) == ("map", "lidar")


def test_bag_without_imu_gnss_gives_none(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "only_points", "ros2-mcap") as w:
        w.write_points("/points", T0, _ouster_columns(0))
    with open_bag(w.path) as bag:
        assert bag.imu() is None and bag.gnss() is None and bag.odometry() is None
        with pytest.raises(InputError, match="no topic '/imu'"):
            bag.imu("/imu")


# --- PointCloud2 built by hand: row padding, height > 1, both byte orders -------------

ROWS, COLS, POINT_STEP, ROW_PAD = 3, 4, 16, 8


def _hand_built_cloud(typestore: object, ros1: bool, big_endian: bool) -> tuple[object, np.ndarray]:
    """A 3x4 organised cloud: x,y,z float32 + intensity uint8 at 12, 3 pad bytes per point
    and 8 pad bytes per row, all padding filled with 0xAB so a wrong stride shows."""
    e = ">" if big_endian else "<"
    xyz = np.arange(ROWS * COLS * 3, dtype=np.float64).reshape(-1, 3) * 0.5 - 3.0
    intensity = (np.arange(ROWS * COLS) * 7 % 251).astype(np.uint8)
    row_step = COLS * POINT_STEP + ROW_PAD
    data = bytearray(b"\xab" * (row_step * ROWS))
    for k in range(ROWS * COLS):
        r, c = divmod(k, COLS)
        base = r * row_step + c * POINT_STEP
        data[base : base + 12] = np.asarray(xyz[k], dtype=e + "f4").tobytes()
        data[base + 12] = int(intensity[k])
    t = typestore.types  # type: ignore[attr-defined]
    pf = t["sensor_msgs/msg/PointField"]
    fields = [
        pf(name="x", offset=0, datatype=7, count=1),
        pf(name="y", offset=4, datatype=7, count=1),
        pf(name="z", offset=8, datatype=7, count=1),
        pf(name="intensity", offset=12, datatype=2, count=1),
    ]
    stamp = t["builtin_interfaces/msg/Time"](sec=int(T0), nanosec=250_000_000)
    header = (
        t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="organised")
        if ros1
        else t["std_msgs/msg/Header"](stamp=stamp, frame_id="organised")
    )
    msg = t["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=ROWS,
        width=COLS,
        fields=fields,
        is_bigendian=big_endian,
        point_step=POINT_STEP,
        row_step=row_step,
        data=np.frombuffer(bytes(data), np.uint8),
        is_dense=True,
    )
    return msg, np.column_stack([xyz, intensity])


@pytest.mark.parametrize("fmt", ["ros1", "ros2-mcap"])
@pytest.mark.parametrize("big_endian", [False, True])
def test_padded_organised_pointcloud2(tmp_path: Path, fmt: str, big_endian: bool) -> None:
    from rosbags.typesys import Stores, get_typestore

    ros1 = fmt == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    msg, expected = _hand_built_cloud(ts, ros1, big_endian)
    msgtype = "sensor_msgs/msg/PointCloud2"
    if ros1:
        from rosbags.rosbag1 import Writer

        path = tmp_path / "organised.bag"
        with Writer(path) as w:
            conn = w.add_connection("/organised", msgtype, typestore=ts)
            w.write(conn, int(T0 * 1e9), ts.serialize_ros1(msg, msgtype))
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        path = tmp_path / "organised"
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conn = w.add_connection("/organised", msgtype, typestore=ts)
            w.write(conn, int(T0 * 1e9), ts.serialize_cdr(msg, msgtype))
    with open_bag(path) as bag:
        (scan,) = list(bag.scans())
    assert len(scan) == ROWS * COLS
    np.testing.assert_array_equal(scan.xyz, expected[:, :3])  # row-major order, padding skipped
    np.testing.assert_array_equal(scan.fields["intensity"], expected[:, 3].astype(np.uint8))
    assert scan.times is None  # no per-point time field
    assert scan.stamp == pytest.approx(T0 + 0.25, abs=TIME_TOL)


# --- bad input -----------------------------------------------------------------------


def _bag_file(path: Path) -> Path:
    """The file holding a bag's messages (ROS1: the bag; ROS2: the storage file)."""
    return (
        path if path.is_file() else next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    )


@pytest.mark.parametrize("fmt", BAG_FORMATS)
def test_truncated_bag(tmp_path: Path, fmt: str) -> None:
    """Cut in the middle: the messages before the cut are read, with a warning naming the
    file (more cases in test_reliability_bags.py); cut before the first message: an error."""
    path = write_full_bag(tmp_path / "whole", fmt)
    storage = _bag_file(path)
    data = storage.read_bytes()
    storage.write_bytes(data[: len(data) // 2])  # cut a real bag in the middle
    with open_bag(path) as bag:
        assert 0 < len(list(bag.scans())) <= 3
        assert bag.recovered and str(path) in bag.warnings[0] and "cut short" in bag.warnings[0]
    storage.write_bytes(data[:40])
    with pytest.raises(InputError) as err, open_bag(path) as bag:
        list(bag.scans())
    message = str(err.value)
    assert str(path) in message
    assert "cannot open bag" in message


def test_bag_without_pointcloud2(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "imu_only", "ros2-sqlite3") as w:
        w.write_imu("/imu", T0, (0, 0, 0), (0, 0, 9.81))
    with open_bag(w.path) as bag, pytest.raises(InputError) as err:
        next(bag.scans())
    assert str(w.path) in str(err.value)
    assert "no sensor_msgs/msg/PointCloud2 topic" in str(err.value)


@pytest.mark.parametrize("fmt", ["ros1", "ros2-mcap"])
def test_pointcloud2_without_xyz(tmp_path: Path, fmt: str) -> None:
    cols = {"range": np.ones(10, np.float32), "azimuth": np.zeros(10, np.float32)}
    with BagWriter(tmp_path / "no_xyz", fmt) as w:
        w.write_points("/points", T0, cols)
    with open_bag(w.path) as bag, pytest.raises(InputError) as err:
        next(bag.scans())
    message = str(err.value)
    assert str(w.path) in message and "'/points'" in message and "message 0" in message
    assert "no x/y/z field" in message and "range, azimuth" in message


def test_pointcloud2_missing_only_z(tmp_path: Path) -> None:
    cols = {"x": np.ones(4, np.float32), "y": np.zeros(4, np.float32)}
    with BagWriter(tmp_path / "no_z", "ros2-mcap") as w:
        w.write_points("/points", T0, cols)
    with open_bag(w.path) as bag, pytest.raises(InputError, match="no z field"):
        next(bag.scans())


@pytest.mark.parametrize("name", ["empty.bag", "empty.mcap", "empty.db3"])
def test_empty_bag_file(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.touch()
    with pytest.raises(InputError) as err:
        open_bag(path)
    assert str(path) in str(err.value) and "empty" in str(err.value)


def test_a_bag_named_without_its_suffix_is_pointed_at(tmp_path: Path) -> None:
    from canopy_kit.io.bag import require_bag

    (tmp_path / "drive.bag").write_bytes(b"#ROSBAG V2.0\n")
    (tmp_path / "drive.mcap").write_bytes(b"\x89MCAP0\r\n")
    (tmp_path / "drive.txt").write_text("notes")  # not a bag: not offered
    with pytest.raises(InputError) as err:
        require_bag(tmp_path / "drive")
    message = str(err.value)
    assert message.startswith(f"{tmp_path / 'drive'}: bag does not exist")
    assert "did you mean drive.bag, drive.mcap in" in message and "drive.txt" not in message
    with pytest.raises(InputError) as err:
        require_bag(tmp_path / "elsewhere" / "drive")
    assert str(err.value).endswith("bag does not exist")  # no folder, no guess
    assert require_bag(str(tmp_path / "drive.bag")) == tmp_path / "drive.bag"


def test_missing_bag_path(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.bag"
    with pytest.raises(InputError) as err:
        open_bag(path)
    assert str(path) in str(err.value) and "does not exist" in str(err.value)


def test_not_a_bag(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("hello")
    with pytest.raises(InputError, match="not a ROS1 .bag file or a ROS2 bag folder"):
        open_bag(path)


def test_named_topic_of_wrong_type(full_bag: Path) -> None:
    with open_bag(full_bag) as bag, pytest.raises(InputError) as err:
        next(bag.scans("/imu/data"))
    assert "carries sensor_msgs/msg/Imu, expected sensor_msgs/msg/PointCloud2" in str(err.value)
