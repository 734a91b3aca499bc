"""Frames, rig files, /tf_static, the IMU moved into the LiDAR frame and the hand-eye estimate,
each checked against hand-computed values or an independent computation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from canopy_kit.config.rig import (
    extrinsics_mode,
    load_rig,
    parse_rig,
    rig_overrides,
    rig_preset_names,
)
from canopy_kit.core.frames import (
    FrameGraph,
    FrameTransform,
    from_rpy,
    invert,
    rigid,
    rotation_angle_deg,
    rpy_deg,
)
from canopy_kit.errors import ConfigError, InputError


# -- frames -------------------------------------------------------------------------------
def test_rpy_follows_the_ros_convention() -> None:
    # Fixed axes, R = Rz(yaw) Ry(pitch) Rx(roll): roll 90 deg takes y onto z, yaw 90 deg x onto y.
    assert np.allclose(from_rpy([0, 0, 0], [90, 0, 0])[:3, :3] @ [0, 1, 0], [0, 0, 1])
    assert np.allclose(from_rpy([0, 0, 0], [0, 0, 90])[:3, :3] @ [1, 0, 0], [0, 1, 0])
    # roll then yaw (fixed axes): x stays x under the roll, then goes to y.
    r = from_rpy([0, 0, 0], [90, 0, 90])[:3, :3]
    assert np.allclose(r @ [1, 0, 0], [0, 1, 0]) and np.allclose(r @ [0, 1, 0], [0, 0, 1])
    assert np.allclose(rpy_deg(from_rpy([1, 2, 3], [10, -20, 30])), [10, -20, 30])


def test_frame_graph_composes_chains_in_either_direction() -> None:
    # base -> mast: up 1.5 m; mast -> lidar: 0.5 m up, yawed 90 deg; base -> imu: 1 m forward.
    g = FrameGraph(
        [
            FrameTransform("base", "mast", rigid(translation=[0, 0, 1.5]), "tf_static"),
            FrameTransform("mast", "lidar", from_rpy([0, 0, 0.5], [0, 0, 90]), "rig file"),
            FrameTransform("base", "imu", rigid(translation=[1, 0, 0]), "tf_static"),
        ]
    )
    # A point 1 m along the LiDAR's x lies 1 m along the base's y, 2 m up.
    base_from_lidar = g.transform("base", "lidar")
    assert np.allclose(base_from_lidar @ [1, 0, 0, 1], [0, 1, 2, 1])
    # The IMU's origin seen from the LiDAR: 1 m forward in base = -1 m along the LiDAR's y, 2 m down.
    lidar_from_imu = g.transform("lidar", "imu")
    assert np.allclose(lidar_from_imu @ [0, 0, 0, 1], [0, -1, -2, 1])
    assert np.allclose(lidar_from_imu @ g.transform("imu", "lidar"), np.eye(4))
    assert g.sources("lidar", "imu") == ["tf_static", "rig file"]  # along the path from the IMU
    assert g.sources("imu", "imu") == []


def test_frame_graph_names_unconnected_frames() -> None:
    g = FrameGraph([FrameTransform("base", "lidar", np.eye(4), "tf_static")])
    assert g.try_transform("lidar", "gps") is None
    with pytest.raises(InputError, match="'gps' and 'lidar'"):
        g.transform("lidar", "gps")


def test_later_edge_to_the_same_child_replaces_the_first() -> None:
    g = FrameGraph([FrameTransform("base", "imu", rigid(translation=[1, 0, 0]), "tf_static")])
    g.add(FrameTransform("base", "imu", rigid(translation=[2, 0, 0]), "rig file"))
    assert np.allclose(g.transform("base", "imu")[:3, 3], [2, 0, 0]) and len(g) == 1


# -- rig files ----------------------------------------------------------------------------
def test_rig_file_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    path.write_text(
        '[rig]\nbase_frame = "base_link"\nimu_frame = "imu"\n'
        "[frames.velodyne]\ntranslation = [0.3, 0, 1.9]\nrpy_deg = [0, 12, 180]\n"
        '[frames.imu]\nparent = "velodyne"\nquaternion = [1, 0, 0, 0]\n'
    )
    rig = load_rig(path)
    assert rig.base_frame == "base_link" and rig.imu_frame == "imu"
    lidar = rig.frame("velodyne")
    assert lidar is not None and lidar.parent == "base_link" and lidar.source == "rig file"
    assert np.allclose(rpy_deg(lidar.matrix), [0, 12, 180]) or np.allclose(
        Rotation.from_matrix(lidar.matrix[:3, :3]).as_euler("xyz", degrees=True), [0, 12, 180]
    )
    imu = rig.frame("imu")
    assert imu is not None and imu.parent == "velodyne"
    assert np.allclose(imu.matrix[:3, :3], np.diag([1, -1, -1]))  # 180 deg about x


@pytest.mark.parametrize(
    "text, message",
    [
        ("[frames.lidar]\nrpy_deg = [0, 0]\n", r"frames.lidar.rpy_deg: expected a list of 3"),
        ("[frames.lidar]\nrpy_deg = [0, 0, 0]\nquaternion = [0, 0, 0, 1]\n", "not both"),
        ("[frames.lidar]\nquaternion = [0, 0, 0, 0]\n", "no direction"),
        ("[frames.lidar]\nshift = [0, 0, 0]\n", r"frames.lidar.shift: unknown key"),
        ('[rig]\nbase = "x"\n', r"rig.base is not a rig setting"),
        ('[frames.lidar]\nparent = "lidar"\n', "its own parent"),
        ("[sensors]\n", "unknown table 'sensors'"),
    ],
)
def test_bad_rig_files_name_the_file_and_key(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        load_rig(path)
    assert str(path) in str(info.value)


def test_shipped_rigs_parse_and_name_their_sensors() -> None:
    from canopy_kit.config.rig import rig_data

    assert {"tower", "imu-flipped", "yawed-lever", "side-tilt"} <= set(rig_preset_names())
    for name in rig_preset_names():
        rig = parse_rig(*rig_data(name))
        g = FrameGraph(rig.transforms)
        for frame in (rig.lidar_frame, rig.imu_frame, rig.gnss_frame):
            assert g.try_transform(rig.base_frame, frame) is not None, (name, frame)


def test_rig_overrides_embed_the_rig_and_flags_exclude_each_other() -> None:
    over = rig_overrides("tower", "calibrate")
    assert over["mapping"]["rig"]["rig"]["lidar_frame"] == "velodyne"
    assert over["mapping"]["rig_name"] == "tower" and over["mapping"]["extrinsics"] == "calibrate"
    assert extrinsics_mode(False, False) is None and extrinsics_mode(True, False) == "identity"
    with pytest.raises(ConfigError, match="exclude each other"):
        extrinsics_mode(True, True)


# -- /tf_static in bags -------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite3", "ros2-mcap"])
def test_tf_static_and_static_tf_are_read_back(tmp_path: Path, fmt: str) -> None:
    from canopy_kit.io.bag import open_bag
    from canopy_kit.io.bag_writer import BagWriter
    from canopy_kit.io.tf import read_transforms

    lidar = from_rpy([0.3, 0.0, 1.9], [0, 12, 180])
    imu = from_rpy([0.3, 0.0, 1.55], [180, 0, 90])
    with BagWriter(tmp_path / "b", fmt) as w:
        w.write_tf_static(10.0, [("base_link", "velodyne", lidar), ("base_link", "imu_link", imu)])
        for k in range(5):  # /tf: a mount published as dynamic, and the robot's motion
            odom = rigid(translation=[0.5 * k, 0, 0])
            w.write_tf_static(
                10.0 + k,
                [
                    ("base_link", "gps", rigid(translation=[0, 0, 2.8])),
                    ("odom", "base_link", odom),
                    ("base_link", "wheel", rigid(Rotation.from_euler("y", 10 * k, degrees=True))),
                ],
                topic="/tf",
            )
        w.write_points(
            "/points",
            10.0,
            {
                "x": np.zeros(3, np.float32),
                "y": np.zeros(3, np.float32),
                "z": np.zeros(3, np.float32),
            },
            "velodyne",
        )
    with open_bag(w.path) as bag:
        rec = read_transforms(bag)
    found = {t.child: t for t in rec.transforms}
    assert set(found) == {
        "velodyne",
        "imu_link",
        "gps",
    }  # odom -> base_link and the turning wheel are not mounts
    assert np.allclose(found["velodyne"].matrix, lidar) and found["velodyne"].source == "tf_static"
    assert np.allclose(found["imu_link"].matrix, imu)
    assert found["gps"].source == "tf" and np.allclose(found["gps"].matrix[:3, 3], [0, 0, 2.8])
    assert any("base_link -> wheel" in n for n in rec.notes)


# -- the IMU in the LiDAR frame -----------------------------------------------------------
def test_imu_mounting_reproduces_what_an_imu_at_the_lidar_would_measure() -> None:
    """The simulator's trajectory measured at two mounts (finite differences of each mount's
    own poses) is the independent truth for the rotation and the lever-arm terms."""
    from canopy_kit.mapping.imu_mounting import ImuMounting
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.session import build_world

    cfg = load_sim_config(
        "pistachio",
        {"seed": 3, "orchard": {"rows": 1, "trees_per_row": 2}, "drive": {"vibration_deg": 0.3}},
    )
    _, traj, _, _ = build_world(cfg)
    lidar_mount = from_rpy([0.3, 0.0, 1.9], [0, 12, 180])
    imu_mount = from_rpy([-0.2, 0.4, 0.5], [180, 0, 90])  # 1.4 m below, 0.5 m aside
    t = np.arange(traj.move_start + 2.0, traj.move_end - 2.0, 1 / 400)
    traj.base_from_imu = imu_mount
    w_imu, f_imu = traj.imu(t)
    traj.base_from_imu = lidar_mount
    w_lidar, f_lidar = traj.imu(t)
    mount = ImuMounting(*_split(invert(lidar_mount) @ imu_mount))
    tt, w, f = mount.apply(t, w_imu, f_imu)
    assert np.allclose(tt, t)
    assert np.abs(w - w_lidar).max() < 1e-6

    # What the pose graph integrates: velocity increments over half-second spans.
    def increments(force: np.ndarray) -> np.ndarray:
        c = np.cumsum(force, axis=0) / 400
        return c[200::200] - c[:-200:200]

    truth = increments(f_lidar)
    rotated_only = np.linalg.norm(increments(f_imu @ mount.rotation.T) - truth, axis=1)
    compensated = np.linalg.norm(increments(f) - truth, axis=1)
    assert (
        np.median(rotated_only) > 0.03
    )  # the 1.5 m lever arm matters on this drive (vibration, turns)
    assert np.median(compensated) < 0.1 * np.median(rotated_only)
    assert np.percentile(compensated, 90) < 0.1 * np.percentile(rotated_only, 90)


def _split(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return m[:3, :3], m[:3, 3]


def test_imu_mounting_moves_the_clock() -> None:
    from canopy_kit.mapping.imu_mounting import ImuMounting

    m = ImuMounting(np.eye(3), np.zeros(3), 0.025)
    t, _, _ = m.apply(np.array([1.0, 2.0]), np.zeros((2, 3)), np.zeros((2, 3)))
    assert np.allclose(t, [0.975, 1.975]) and not m.is_identity
    assert ImuMounting(np.eye(3), np.zeros(3)).is_identity


# -- hand-eye -----------------------------------------------------------------------------
def test_kabsch_recovers_a_mount_from_noisy_increments() -> None:
    from canopy_kit.mapping.handeye import fit_rotation

    rng = np.random.default_rng(0)
    truth = Rotation.from_euler("xyz", [180, 3, 90], degrees=True).as_matrix()
    b = rng.normal(0, 0.05, (400, 3))  # gyro increments (rad), every axis excited
    a = b @ truth.T + rng.normal(0, 0.002, (400, 3))
    a[:10] += 0.3  # bad registrations
    r, sigma, residual, keep = fit_rotation(a, b)
    assert rotation_angle_deg(r, truth) < 0.2
    assert keep[:10].sum() == 0 and keep.sum() >= 380
    assert np.all(sigma < 0.2) and 0.05 < residual < 0.3


def test_yaw_only_increments_leave_the_rotation_about_up_unobservable() -> None:
    from canopy_kit.mapping.handeye import fit_rotation

    rng = np.random.default_rng(1)
    b = np.column_stack(
        [rng.normal(0, 1e-4, 300), rng.normal(0, 1e-4, 300), rng.normal(0, 0.1, 300)]
    )
    a = b + rng.normal(0, 0.002, (300, 3))
    _, sigma, _, _ = fit_rotation(a, b)
    # Turning about z fixes where z goes (the rotation about x and y), not the rotation about z.
    assert sigma[0] < 0.2 and sigma[1] < 0.2 and sigma[2] > 1.0


def test_shipped_presets_know_the_rig_settings() -> None:
    from canopy_kit.config import MappingConfig, from_dict

    cfg = from_dict(MappingConfig, {"extrinsics": "calibrate", "base_frame": "base_link"})
    assert cfg.extrinsics == "calibrate"
    with pytest.raises(ConfigError, match="mapping.extrinsics"):
        from_dict(MappingConfig, {"extrinsics": "guess"}, "mapping")


# -- the report ---------------------------------------------------------------------------
def test_report_shows_the_rig_and_checks_the_imu_mount() -> None:
    from canopy_kit.mapping.extrinsics import SensorRig
    from canopy_kit.report.html import render_report
    from canopy_kit.report.rig import rig_section
    from canopy_kit.results.checks import imu_mount_check as rig_check

    base_from_lidar = from_rpy([0.3, 0, 1.9], [0, 12, 180])
    base_from_imu = from_rpy([0.3, 0, 1.55], [180, 0, 90])
    rig = SensorRig(
        "velodyne",
        "imu_link",
        "gps",
        "base_link",
        invert(base_from_lidar) @ base_from_imu,
        invert(base_from_lidar) @ rigid(translation=[0.3, 0, 2.8]),
        invert(base_from_lidar),
        {"imu": "tf_static", "gnss": "rig file", "base": "tf_static"},
        tf_topics=["/tf_static"],
    )
    diag = {
        "rig": rig.to_dict(),
        "extrinsics": {
            "mode": "auto",
            "difference_deg": 2.6,
            "tolerance_deg": 2.0,
            "estimated": {"rpy_deg": [1, 2, 3], "sigma_deg": [0.1, 0.1, 0.3]},
        },
    }
    section = rig_section(diag)
    table = section.table.set_index("sensor")
    # Each sensor's mount on the vehicle, as the rig gives it, whatever frame the odometry ran in.
    assert table.loc["IMU", "position in base_link [m]"] == "0.300, 0.000, 1.550"
    assert (
        table.loc["IMU", "roll, pitch, yaw [deg]"] == "180.00, 0.00, 90.00"
        or table.loc["IMU", "roll, pitch, yaw [deg]"] == "-180.00, 0.00, 90.00"
    )
    assert table.loc["GNSS antenna", "source"] == "rig file"
    assert table.loc["LiDAR", "roll, pitch, yaw [deg]"] in (
        "0.00, 12.00, 180.00",
        "0.00, 12.00, -180.00",
    )
    assert "2.60 deg from the given mount" in section.text
    check = rig_check(diag)
    assert check is not None and check.status == "fail" and check.threshold == "fail > 2°"
    assert (
        rig_check({**diag, "extrinsics": {**diag["extrinsics"], "difference_deg": 0.4}}).status
        == "pass"
    )
    page = render_report("r", {}, section.table, [section], [check], "")
    assert "Sensor rig" in page and "imu_link" in page and "IMU mount agrees with the drive" in page


def test_a_tilted_lidar_keeps_the_odometry_in_one_process() -> None:
    from canopy_kit.mapping.chunks import MAX_CHUNKED_TILT_DEG, lidar_tilt_deg
    from canopy_kit.mapping.extrinsics import SensorRig

    def tilt(rpy: list[float]) -> float:
        return lidar_tilt_deg(
            SensorRig("lidar", lidar_from_base=invert(from_rpy([0.3, 0, 1.9], rpy)))
        )

    assert tilt([0, 12, 180]) == pytest.approx(12.0) and tilt([20, 0, 0]) == pytest.approx(20.0)
    assert tilt([0, 0, 137]) == pytest.approx(0.0, abs=1e-6)  # a yawed LiDAR is still level
    assert tilt([0, 12, 180]) > MAX_CHUNKED_TILT_DEG > tilt([2, 2, 90])
    assert lidar_tilt_deg(None) == 0.0
