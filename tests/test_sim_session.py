"""Simulated sessions: determinism, bags readable by canopy_kit.io, physics of the sensors."""

from __future__ import annotations

import filecmp

import numpy as np
import pytest
from conftest import MICRO
from scipy.spatial.transform import Rotation

from canopy_kit.io.bag import open_bag
from canopy_kit.sim import load_truth
from canopy_kit.sim.session import load_sim_config_of
from canopy_kit.sim.trajectory import GRAVITY

TRUTH_FILES = ["trees.csv", "trajectory.csv", "frame.json", "sim_config.toml"]


def test_same_seed_gives_identical_truth_files(sim_factory):
    # The same seed written as two bag formats: the truth must be byte-identical.
    one = sim_factory("pistachio", fmt="ros1", overrides=MICRO)
    two = sim_factory("pistachio", fmt="ros2-sqlite3", overrides=MICRO)
    for name in TRUTH_FILES:
        assert filecmp.cmp(one.truth_dir / name, two.truth_dir / name, shallow=False), name
    assert one.n_points == two.n_points
    different = sim_factory("pistachio", seed=1, overrides=MICRO)
    assert not filecmp.cmp(
        one.truth_dir / "trees.csv", different.truth_dir / "trees.csv", shallow=False
    )


@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite3", "ros2-mcap"])
def test_bag_reads_back_through_canopy_kit_io(sim_factory, fmt):
    session = sim_factory("pistachio", fmt=fmt, overrides=MICRO)
    cfg = load_sim_config_of(session.root)
    with open_bag(session.bag) as bag:
        topics = {t.name: t for t in bag.topics()}
        assert set(topics) == {"/points", "/imu/data", "/gps/fix", "/ground_truth/odom"}
        assert topics["/points"].count == session.n_scans
        duration = session.trajectory.duration
        assert topics["/imu/data"].count == pytest.approx(duration * cfg.imu.rate_hz, abs=2)
        assert topics["/gps/fix"].count == pytest.approx(duration * cfg.gnss.rate_hz, abs=2)
        period = 1.0 / cfg.lidar.rate_hz
        n_points = 0
        for scan in bag.scans():
            n_points += len(scan)
            assert len(scan) <= cfg.lidar.rings * cfg.lidar.columns
            assert set(scan.fields) == {"intensity", "t", "ring", "tree_id"}
            assert scan.times.min() >= scan.stamp - 1e-9
            assert scan.times.max() < scan.stamp + period
            assert np.all(np.diff(scan.times) >= 0)  # firing order
            assert scan.fields["ring"].max() < cfg.lidar.rings
        assert n_points == session.n_points


def test_points_lie_on_the_true_scene(tiny_pistachio):
    """Each point, placed with the true pose at its own time, lies on a scene surface."""
    from canopy_kit.sim.session import build_world

    cfg = load_sim_config_of(tiny_pistachio.root)
    _, trajectory, scene, _ = build_world(cfg)
    raycaster = scene.raycasting_scene()
    import open3d as o3d

    with open_bag(tiny_pistachio.bag) as bag:
        for scan in bag.scans():
            if scan.index not in (40, 400):
                continue
            pos, rot = trajectory.poses(scan.times)
            world = rot.apply(scan.xyz) + pos
            dist = raycaster.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
            noise = cfg.lidar.range_noise
            assert np.median(dist) < 2 * noise
            assert np.quantile(dist, 0.95) < 4 * noise
            # Ignoring motion (one pose for the whole sweep) must be visibly worse while moving.
            p0, r0 = trajectory.poses(np.array([scan.stamp]))
            skewed = Rotation.from_quat(np.repeat(r0.as_quat(), len(scan), 0)).apply(scan.xyz) + p0
            d_skew = raycaster.compute_distance(o3d.core.Tensor(skewed.astype(np.float32))).numpy()
            if scan.index == 400:
                assert np.quantile(d_skew, 0.9) > 3 * np.quantile(dist, 0.9)


def test_truth_labels_belong_to_their_crowns(tiny_pistachio):
    truth = load_truth(tiny_pistachio.root)
    orchard = truth.orchard()  # rebuilt by the simulator's world model, named by truth/
    from canopy_kit.sim.world import SimulatedWorld

    assert isinstance(truth.world(), SimulatedWorld)
    pose = _truth_pose(truth)
    with open_bag(tiny_pistachio.bag) as bag:
        hits = {t.tree_id: 0 for t in orchard.trees}
        for scan in bag.scans():
            if scan.index % 20:
                continue
            pos, rot = pose(scan.times)
            world = rot.apply(scan.xyz) + pos
            tid = scan.fields["tree_id"]
            for tree in orchard.trees:
                mine = world[tid == tree.tree_id]
                if len(mine):
                    hits[tree.tree_id] += len(mine)
                    # Foliage and branches sit inside the envelope (allow range noise).
                    c = np.asarray(tree.crown.center)
                    shrunk = c + (mine - c) * 0.98
                    assert tree.crown.contains(shrunk).mean() > 0.98
        assert all(v > 100 for v in hits.values()), hits


def _truth_pose(truth):
    from scipy.spatial.transform import Slerp

    traj = truth.trajectory
    t = traj["time"].to_numpy()
    slerp = Slerp(t, Rotation.from_quat(traj[["qx", "qy", "qz", "qw"]].to_numpy()))
    pos = traj[["x", "y", "z"]].to_numpy()

    def at(times):
        tt = np.clip(times, t[0], t[-1])
        return np.column_stack([np.interp(tt, t, pos[:, k]) for k in range(3)]), slerp(tt)

    return at


def test_imu_and_gnss_are_consistent_with_the_motion(tiny_pistachio):
    truth = load_truth(tiny_pistachio.root)
    cfg = load_sim_config_of(tiny_pistachio.root)
    with open_bag(tiny_pistachio.bag) as bag:
        imu, gnss = bag.imu(), bag.gnss()
    still = imu.t < imu.t[0] + cfg.drive.start_still - 0.2
    # Standing still: the accelerometer measures gravity (plus bias), the gyro almost nothing.
    assert np.linalg.norm(imu.linear_acceleration[still].mean(axis=0)) == pytest.approx(
        GRAVITY, abs=0.2
    )
    assert np.abs(imu.angular_velocity[still].mean(axis=0)).max() < 0.01
    # Integrated yaw rate follows the true heading change over the first U-turn.
    traj = truth.trajectory
    yaw = Rotation.from_quat(traj[["qx", "qy", "qz", "qw"]].to_numpy()).as_euler("ZYX")[:, 0]
    t_true = traj["time"].to_numpy()
    dyaw_true = np.unwrap(yaw)
    dt = np.diff(imu.t, prepend=imu.t[0])
    bias = imu.angular_velocity[still, 2].mean()
    integrated = np.cumsum((imu.angular_velocity[:, 2] - bias) * dt)
    change = np.interp(imu.t, t_true, dyaw_true) - dyaw_true[0]
    i_turn = np.argmax(np.abs(change))  # end of the first U-turn: about -pi
    assert abs(change[i_turn]) == pytest.approx(np.pi, abs=0.1)
    assert integrated[i_turn] == pytest.approx(change[i_turn], abs=0.05)
    # GNSS: metre-level error around the true antenna (= LiDAR) position.
    local = truth.frame.to_local(gnss.latitude, gnss.longitude, gnss.altitude)
    true_pos = np.column_stack([np.interp(gnss.t, t_true, traj[c]) for c in ("x", "y", "z")])
    err = np.linalg.norm((local - true_pos)[:, :2], axis=1)
    assert 0.05 < np.sqrt(np.mean(err**2)) < 3 * cfg.gnss.sigma_horizontal


def test_truth_table_describes_each_tree(tiny_pistachio):
    trees = load_truth(tiny_pistachio.root).trees
    assert len(trees) == 6
    assert list(trees["label"]) == ["L0", "L1", "L2", "R0", "R1", "R2"]
    assert np.allclose(trees["sphere_volume_m3"], np.pi * trees["crown_diameter_m"] ** 3 / 6)
    assert (trees["crown_diameter_m"] >= trees["crown_diameter_mean_m"]).all()
    assert (trees["crown_diameter_m"].between(2.5, 5.0)).all()
    assert (trees["tree_height_m"] > trees["crown_base_height_m"]).all()


def test_time_field_conventions(sim_factory):
    """Velodyne-style float seconds (``time``) also round-trip as absolute point times."""
    session = sim_factory(
        "pistachio", overrides={**MICRO, "lidar": {"columns": 256}}, sensor="vlp16", fmt="ros1"
    )
    with open_bag(session.bag) as bag:
        scan = next(iter(bag.scans()))
        assert "time" in scan.fields and "t" not in scan.fields
        assert scan.times.min() >= scan.stamp and scan.times.max() < scan.stamp + 0.1
        assert scan.fields["ring"].max() == 15


def test_interpolated_column_poses_match_exact_poses(tiny_pistachio):
    """The 33 pose knots per sweep place every firing column within a millimetre of its
    exact pose (the simulator's speed trick, benchmarked against exact poses)."""
    from types import SimpleNamespace

    from canopy_kit.sim.lidar import SpinningLidar

    traj = tiny_pistachio.trajectory
    spec = load_sim_config_of(tiny_pistachio.root).lidar
    fake = SimpleNamespace(spec=spec, sweep_period=1.0 / spec.rate_hz, trajectory=traj)
    # sweeps in a straight stretch and in the U-turn (the fastest heading change)
    stamps = np.linspace(traj.start_time + 1, traj.end_time - 1, 12)
    for stamp in stamps:
        pos, mats = SpinningLidar._column_poses(fake, stamp)
        exact_pos, exact_mats = SpinningLidar._column_poses(fake, stamp, spec.columns)
        assert np.abs(pos - exact_pos).max() < 1e-3
        # a direction at 30 m range moves by less than a millimetre
        assert 30 * np.abs(mats - exact_mats).max() < 1e-3


def test_an_interrupted_simulation_leaves_no_session_and_keeps_the_old_one(tmp_path):
    """The session is written beside its folder and renamed when done: stopped half-way
    (here by the progress callback), nothing appears under the name, the old session given
    to ``overwrite`` is untouched, and a complete run then replaces it."""
    from canopy_kit.config import merge
    from canopy_kit.errors import InputError
    from canopy_kit.sim import load_sim_config, simulate_session

    class Stop(Exception):
        pass

    def stop_after_two_sweeps(stage, done, total):
        if stage == "LiDAR sweeps" and done == 2:
            raise Stop

    out = tmp_path / "session"
    config = load_sim_config("pistachio", merge({"seed": 0}, MICRO))
    with pytest.raises(Stop):
        simulate_session(out, config, fmt="ros1", progress=stop_after_two_sweeps)
    assert not out.exists() and list(tmp_path.iterdir()) == []
    first = simulate_session(out, config, fmt="ros1")
    before = (first.truth_dir / "trees.csv").read_bytes()
    with pytest.raises(InputError, match="not empty"):
        simulate_session(out, config, fmt="ros1")
    with pytest.raises(Stop):
        simulate_session(out, config, fmt="ros1", overwrite=True, progress=stop_after_two_sweeps)
    assert (first.truth_dir / "trees.csv").read_bytes() == before and first.bag.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session"]
    again = simulate_session(out, config, fmt="ros1", overwrite=True)
    assert again.root == out and again.bag.exists() and again.n_scans == first.n_scans
