"""Unit tests of the mapping stage's pieces on small synthetic inputs (fast)."""

from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from canopy_kit.config import MappingConfig
from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.evaluate.trajectory_error import segment_drift, trajectory_errors
from canopy_kit.io.bag import GnssSeries, ImuSeries
from canopy_kit.mapping import quaternions as quat
from canopy_kit.mapping.accumulate import MapAccumulator, VoxelKeySet, voxel_hash
from canopy_kit.mapping.assemble import merge_partial_maps, stretches, transform_binned
from canopy_kit.mapping.deskew import deskew_points, reference_time
from canopy_kit.mapping.filters import check_point_count, fit_ground_plane, ground_mask, range_mask
from canopy_kit.mapping.fusion import FusionSettings, fuse_trajectory, heading_alignment
from canopy_kit.mapping.gnss import gnss_epochs, local_frame_for
from canopy_kit.mapping.ground import GroundHeightGrid, apply_ground_correction, ground_correction
from canopy_kit.mapping.imu import GRAVITY, RotationTrack, detect_standstill, level_rotation
from canopy_kit.mapping.kernels import rotate_and_shift
from canopy_kit.mapping.outputs import read_tum, tum_text
from canopy_kit.mapping.trajectory import ContinuousTrajectory, pose_table

RNG = np.random.default_rng(7)


def _poses(pos: np.ndarray, rot: Rotation) -> np.ndarray:
    out = np.tile(np.eye(4), (len(pos), 1, 1))
    out[:, :3, :3] = rot.as_matrix()
    out[:, :3, 3] = pos
    return out


# -- filters ---------------------------------------------------------------------------
def _ground_scene(tilt_deg: float = 0.0, n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """Ground 1.8 m below a (tilted) sensor plus tree-like blobs; returns points and a ground mask."""
    xy = RNG.uniform(-25, 25, (n, 2))
    ground = np.column_stack([xy, np.full(n, -1.8) + RNG.normal(0, 0.01, n)])
    blobs = RNG.normal(0, 1.0, (n // 2, 3)) + np.array([4.0, 3.0, 1.0])
    pts = np.vstack([ground, blobs])
    truth = np.r_[np.ones(n, bool), np.zeros(n // 2, bool)]
    r = Rotation.from_euler("xy", [tilt_deg, -tilt_deg / 2], degrees=True)
    return r.apply(pts), truth


@pytest.mark.parametrize("tilt", [0.0, 4.0])
def test_ground_plane_fit_finds_the_ground_under_a_tilted_sensor(tilt: float) -> None:
    pts, truth = _ground_scene(tilt)
    plane = fit_ground_plane(pts)
    assert plane is not None
    normal_true = Rotation.from_euler("xy", [tilt, -tilt / 2], degrees=True).apply([0, 0, 1.0])
    assert np.degrees(np.arccos(np.clip(plane[:3] @ normal_true, -1, 1))) < 0.5
    assert abs(plane[3] - 1.8) < 0.05
    mask = ground_mask(pts, 0.15, plane)
    assert mask[truth].mean() > 0.99
    assert mask[~truth].mean() < 0.05


def test_ground_plane_none_without_ground() -> None:
    assert fit_ground_plane(RNG.normal(0, 1, (500, 3)) + [0, 0, 3.0]) is None
    assert not ground_mask(RNG.normal(0, 1, (500, 3)) + [0, 0, 3.0], 0.15).any()


def test_range_mask_and_point_count_message() -> None:
    pts = np.array([[0.5, 0, 0], [2.0, 0, 0], [70.0, 0, 0], [np.nan, 0, 0]])
    assert range_mask(pts, 1.0, 60.0).tolist() == [False, True, False, False]
    with pytest.raises(
        InputError, match=r"bag.bag: topic '/p': only 12 valid points.*at least 500"
    ):
        check_point_count(12, 500, "bag.bag: topic '/p'")


def test_range_mask_is_the_numpy_expression_on_every_kind_of_point() -> None:
    """The compiled range filter against numpy's squared norm, bounds included exactly."""
    pts = RNG.normal(0, 30, (20_000, 3)).astype(np.float32).astype(np.float64)
    pts[::97] = [3.0, 4.0, 0.0]  # exactly 5 m away: on the bound
    pts[::101, 1] = np.nan
    pts[::103, 2] = np.inf
    pts[::107, 0] = -np.inf
    r2 = np.einsum("ij,ij->i", pts, pts)
    with np.errstate(invalid="ignore"):
        expected = np.isfinite(r2) & (r2 >= 25.0) & (r2 <= 3600.0)
    assert np.array_equal(range_mask(pts, 5.0, 60.0), expected)
    assert range_mask(pts[:, :3][::2], 5.0, 60.0).tolist() == expected[::2].tolist()  # strided
    assert range_mask(np.zeros((0, 3)), 1.0, 2.0).shape == (0,)


# -- IMU -------------------------------------------------------------------------------
def _imu(
    rate: float = 200.0, still: float = 2.0, duration: float = 6.0, tilt=(0.05, -0.03)
) -> ImuSeries:
    t = np.arange(0.0, duration, 1.0 / rate)
    r = Rotation.from_euler("xy", tilt)
    f = r.inv().apply([0.0, 0.0, GRAVITY])
    acc = np.tile(f, (len(t), 1)) + RNG.normal(0, 0.4, (len(t), 3))
    acc[t > still, 0] += 0.5  # starts accelerating forward
    gyro = np.tile([0.001, -0.002, 0.003], (len(t), 1)) + RNG.normal(0, 0.04, (len(t), 3))
    gyro[t > still, 2] += 0.2
    return ImuSeries(t, gyro, acc, np.tile([0, 0, 0, 1.0], (len(t), 1)))


def test_standstill_gravity_and_gyro_bias() -> None:
    imu = _imu()
    st = detect_standstill(imu)
    assert st.found and 1.2 < st.end <= 2.05
    assert np.allclose(st.gyro_bias, [0.001, -0.002, 0.003], atol=0.006)
    up = st.level_rotation().apply(st.gravity_body)
    assert np.degrees(np.arctan2(np.hypot(up[0], up[1]), up[2])) < 0.3


def test_level_rotation_maps_gravity_to_z() -> None:
    r = Rotation.from_euler("xyz", [0.1, -0.2, 0.7])
    f = r.inv().apply([0, 0, GRAVITY])
    assert np.allclose(level_rotation(f).apply(f), [0, 0, GRAVITY], atol=1e-9)


def test_rotation_track_integrates_and_extends() -> None:
    t = np.arange(0.0, 5.0, 0.005)
    w = np.column_stack([0.2 * np.sin(t), 0.1 * np.ones_like(t), -0.3 * np.cos(2 * t)])
    imu = ImuSeries(t, w, np.zeros_like(w), np.zeros((len(t), 4)))
    whole = RotationTrack(imu)
    part = RotationTrack(ImuSeries(t[:10], w[:10], w[:10], w[:10]))
    for k in range(10, len(t), 37):
        part.extend(t[k : k + 37], w[k : k + 37])
    assert np.allclose(whole.quaternions(t), part.quaternions(t), atol=1e-12)
    # Constant rate about z: the relative rotation is omega * dt.
    imu_z = ImuSeries(
        t, np.tile([0, 0, 0.5], (len(t), 1)), np.zeros((len(t), 3)), np.zeros((len(t), 4))
    )
    rv = RotationTrack(imu_z).relative_rotvecs(1.0, np.array([1.1, 0.9]))
    assert np.allclose(rv, [[0, 0, 0.05], [0, 0, -0.05]], atol=1e-9)


# -- deskew and quaternions --------------------------------------------------------------
def test_deskew_undoes_constant_motion() -> None:
    """Points of a static scene seen by a sensor turning and moving during the sweep."""
    world = RNG.uniform(-20, 20, (3000, 3))
    times = np.sort(RNG.uniform(0.0, 0.1, len(world)))
    w = np.array([0.0, 0.0, 0.4])
    v = np.array([1.5, 0.0, 0.0])
    t_ref = reference_time(times, 0.0)
    # Sensor pose at t relative to t_ref: rotation w(t - t_ref), translation v(t - t_ref).
    dt = times - t_ref
    rot = Rotation.from_rotvec(dt[:, None] * w)
    sensor = rot.inv().apply(world - dt[:, None] * v)
    fixed = deskew_points(sensor, times, t_ref, v, w)
    assert np.abs(fixed - world).max() < 2e-3
    assert np.abs(sensor - world).max() > 0.1


def test_quaternion_helpers_match_scipy() -> None:
    r = Rotation.random(20, random_state=3)
    v = RNG.normal(size=(20, 3))
    assert np.allclose(quat.rotate(r.as_quat(), v), r.apply(v))
    assert np.allclose(quat.to_matrix(r.as_quat()), r.as_matrix())
    prod = quat.multiply(r.as_quat(), r[::-1].as_quat())
    assert np.allclose(Rotation.from_quat(prod).as_matrix(), (r * r[::-1]).as_matrix())
    assert np.allclose(quat.cross(v, v[::-1]), np.cross(v, v[::-1]))
    small = RNG.normal(0, 0.02, (20, 3))
    bins = RNG.integers(0, 20, 20)
    dt, velocity = RNG.normal(0, 0.05, 20), np.array([1.5, -0.2, 0.1])
    moved = rotate_and_shift(v, bins, small, dt, velocity)
    expected = Rotation.from_rotvec(small[bins]).apply(v) + dt[:, None] * velocity
    assert np.abs(moved - expected).max() < 1e-4  # second order in angles of ~0.03 rad


# -- map accumulation ----------------------------------------------------------------------
def test_voxel_key_set_reports_new_keys_once() -> None:
    s = VoxelKeySet(capacity_bits=4)
    a = np.arange(0, 1000, 3, dtype=np.int64)
    assert s.insert(a).all()
    b = np.arange(0, 2000, 5, dtype=np.int64)
    new = s.insert(b)
    assert np.array_equal(b[new], np.setdiff1d(b, a))
    assert s.size == len(np.union1d(a, b))


def test_voxel_key_set_counts_a_key_repeated_in_one_insert_at_its_first_occurrence() -> None:
    s = VoxelKeySet(capacity_bits=2)  # grows on the way
    s.insert(np.array([5, 9], np.int64))
    new = s.insert(np.array([7, 5, 7, 11, 9, 11, 7], np.int64))
    assert new.tolist() == [True, False, False, True, False, False, False]
    assert s.size == 4


def test_voxel_hash_packs_floor_of_coordinates_over_voxel_size() -> None:
    xyz = np.array([[0.0, 0.0, 0.0], [0.049, -0.001, 0.05], [-52_000.01, 52_000.01, 1.01]])
    k = np.array([[0, 0, 0], [0, -1, 1], [-1_040_001, 1_040_000, 20]]) + (1 << 20)  # by hand
    assert voxel_hash(xyz, 0.05).tolist() == ((k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]).tolist()
    for bad in ([53_000.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.0, -np.inf, 0.0], [0.0, 0.0, 1e300]):
        with pytest.raises(InputError, match="voxel grid range"):
            voxel_hash(np.array([bad]), 0.05)


def test_transform_binned_applies_each_points_own_pose() -> None:
    rot = Rotation.random(8, random_state=3)
    t = RNG.normal(0, 5, (8, 3))
    xyz = RNG.normal(0, 10, (500, 3))
    bins = RNG.integers(0, 8, 500)  # not sorted
    expected = rot[bins].apply(xyz) + t[bins]
    assert np.allclose(transform_binned(xyz, bins, rot.as_matrix(), t), expected, atol=1e-12)
    with pytest.raises(ValueError, match="bins"):
        transform_binned(xyz, bins + 1, rot.as_matrix(), t)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_points_binned_while_placed_equal_the_numpy_binning_to_the_bit(dtype) -> None:
    """The map pass's one-pass kernel gives the bins and products of the numpy steps it
    replaced (``times[keep]``, the bin expression, ``transform_binned``), bit for bit."""
    from canopy_kit.mapping.assemble import POSE_BINS
    from canopy_kit.mapping.kernels import kept_time_span, place_kept_binned

    rot = Rotation.random(POSE_BINS, random_state=4).as_matrix()
    shift = RNG.normal(0, 50, (POSE_BINS, 3))
    xyz = RNG.normal(0, 20, (4000, 3)).astype(dtype)
    for times in (1.7e9 + np.sort(RNG.uniform(0, 0.1, 4000)), np.full(4000, 1.7e9 + 0.05)):
        keep = np.flatnonzero(RNG.uniform(size=4000) < 0.8)
        t = times[keep]
        lo, hi = float(t.min()), float(t.max())
        assert kept_time_span(times, keep) == (lo, hi)
        span = max(hi - lo, 1e-12)
        bins = np.clip(((t - lo) / span * (POSE_BINS - 1) + 0.5).astype(np.int64), 0, POSE_BINS - 1)
        want = transform_binned(xyz[keep], bins, rot, shift)
        got = place_kept_binned(xyz, keep, times, lo, span, rot, shift)
        assert np.array_equal(got, want)


def test_accumulator_keeps_first_point_per_voxel_with_fields_untouched() -> None:
    acc = MapAccumulator(0.1)
    p1 = np.array([[0.01, 0.01, 0.01], [0.5, 0.5, 0.5], [0.02, 0.02, 0.02]])
    f1 = {
        "tree_id": np.array([7, 8, 9], np.int32),
        "intensity": np.array([1.5, 2.5, 3.5], np.float32),
    }
    acc.add(p1, f1)
    acc.add(
        np.array([[0.03, 0.03, 0.03], [1.0, 1.0, 1.0]]),
        {"tree_id": np.array([1, 2], np.int32), "intensity": np.array([4.0, 5.0], np.float32)},
    )
    cloud = acc.cloud()
    assert len(cloud) == 3
    assert cloud.fields["tree_id"].tolist() == [7, 8, 2]
    assert cloud.fields["tree_id"].dtype == np.int32
    assert np.array_equal(cloud.xyz[0], p1[0])


def test_add_sweeps_gathers_fields_of_kept_points_only_and_equals_add() -> None:
    sweeps = [RNG.uniform(0, 2, (300, 3)) for _ in range(5)] + [np.zeros((0, 3))]
    fields = [{"order": np.arange(len(p)) + 1000 * i} for i, p in enumerate(sweeps)]
    one_by_one = MapAccumulator(0.25)
    for p, f in zip(sweeps, fields, strict=True):
        one_by_one.add(p, f)
    asked: list[int] = []

    def fields_of(f: dict[str, np.ndarray]):
        def gather(indices: np.ndarray) -> dict[str, np.ndarray]:
            asked.append(len(indices))
            return {k: v[indices] for k, v in f.items()}

        return gather

    batched_acc = MapAccumulator(0.25)
    batched_acc.add_sweeps([(p, fields_of(f)) for p, f in zip(sweeps, fields, strict=True)])
    a, b = one_by_one.cloud(), batched_acc.cloud()
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.fields["order"], b.fields["order"])
    assert batched_acc.n_offered == one_by_one.n_offered == 1500
    assert sum(asked) == len(b) < 1500  # only the points that took a voxel were gathered


def test_parallel_merge_equals_single_accumulator() -> None:
    pts = [RNG.uniform(0, 3, (400, 3)) for _ in range(7)]
    single = MapAccumulator(0.2)
    parts = [MapAccumulator(0.2) for _ in range(3)]
    for i, p in enumerate(pts):  # three consecutive stretches of the drive: sweeps 0-2, 3-5, 6
        order = (np.int64(i) << 24) | np.arange(len(p), dtype=np.int64)
        single.add(p, {"order": order})
        parts[i // 3].add(p, {"order": order})
    xyz, fields = merge_partial_maps([(a.cloud().xyz, a.cloud().fields) for a in parts], 0.2)
    ref = single.cloud()
    assert np.array_equal(xyz, ref.xyz)
    assert np.array_equal(fields["order"], ref.fields["order"])
    assert len(np.unique(voxel_hash(xyz, 0.2))) == len(xyz)


def test_stretches_cover_every_sweep_once_and_start_where_the_bag_can_be_seeked() -> None:
    log_ns = np.array([0, 10, 20, 20, 20, 30, 40, 50, 60, 70, 80, 90], np.int64)
    indices = [i for i in range(12) if i != 5]
    runs = stretches(indices, 3, log_ns)
    assert runs[0][0] == 0 and runs[-1][1] is None
    assert all(a[1] == b[0] for a, b in itertools.pairwise(runs))  # consecutive, no gap
    for first, _ in runs[1:]:  # never inside a run of equal log times
        assert log_ns[first] > log_ns[first - 1]
    sizes = [sum(1 for i in indices if a <= i < (b if b is not None else 99)) for a, b in runs]
    assert sum(sizes) == len(indices) and max(sizes) - min(sizes) <= 3


# -- ground refinement ---------------------------------------------------------------------
def test_ground_correction_recovers_height_and_tilt() -> None:
    grid = GroundHeightGrid()
    xy = RNG.uniform(-15, 15, (20000, 2))
    grid.add(np.column_stack([xy, 0.02 * xy[:, 0]]))  # a 2 % slope
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 1.8]
    local = np.column_stack([RNG.uniform(-12, 12, (3000, 2)), np.zeros(3000)])
    local[:, 2] = -1.8 + 0.02 * (local[:, 0] + 1.0)
    true_world = local + pose[:3, 3]
    wrong = pose.copy()
    wrong[:3, 3] += [0.0, 0.0, 0.07]
    wrong[:3, :3] = Rotation.from_euler("y", -0.004).as_matrix()
    seen = local @ wrong[:3, :3].T + wrong[:3, 3]
    coef = ground_correction(seen, wrong[:2, 3], grid)
    assert coef is not None
    fixed = apply_ground_correction(wrong, coef)
    fixed_world = local @ fixed[:3, :3].T + fixed[:3, 3]
    assert np.abs(fixed_world[:, 2] - true_world[:, 2]).max() < 0.01


# -- trajectory and fusion -----------------------------------------------------------------
def test_continuous_trajectory_passes_through_keyframes() -> None:
    t = np.arange(0.0, 10.0, 0.1)
    odo = _poses(
        np.column_stack([1.5 * t, np.sin(t), 0 * t]),
        Rotation.from_rotvec(np.outer(0.1 * t, [0, 0, 1])),
    )
    key = np.arange(0, len(t), 5)
    fused = odo[key].copy()
    fused[:, 1, 3] += np.linspace(0, 0.5, len(key))
    traj = ContinuousTrajectory(t[key], fused, t, odo)
    assert np.allclose(traj.matrices(t[key]), fused, atol=1e-9)
    mid = traj.matrices(t[2:3])[0]
    assert abs(mid[1, 3] - (odo[2, 1, 3] + 0.5 * 0.4 / (len(key) - 1))) < 1e-3
    tab = traj.table()
    assert list(tab.columns) == ["time", "x", "y", "z", "qx", "qy", "qz", "qw"]
    assert np.allclose(read_tum_roundtrip(tab)[["x", "y", "qw"]], tab[["x", "y", "qw"]], atol=1e-6)


def read_tum_roundtrip(table: pd.DataFrame) -> pd.DataFrame:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "t.tum"
        path.write_text(tum_text(table))
        return read_tum(path)


def test_heading_alignment_recovers_yaw_and_shift() -> None:
    p = RNG.uniform(-30, 30, (50, 3))
    yaw = 0.7
    q = Rotation.from_euler("z", yaw).apply(p) + [5.0, -3.0, 1.0]
    est, shift = heading_alignment(p, q)
    assert abs(est - yaw) < 1e-9 and np.allclose(shift, [5.0, -3.0, 1.0])


def _gnss_series(
    frame_lat: float, frame_lon: float, local: np.ndarray, t: np.ndarray, sigma: float
) -> GnssSeries:
    from canopy_kit.core.geo import LocalFrame

    frame = LocalFrame.at(frame_lat, frame_lon, 50.0)
    lat, lon, h = frame.to_wgs84(local)
    cov = np.zeros((len(t), 9))
    cov[:, [0, 4, 8]] = sigma**2
    return GnssSeries(t, lat, lon, h, np.zeros(len(t), int), cov)


def test_gnss_bounds_drift_and_georeferences() -> None:
    """A serpentine drive; odometry with a slow heading drift in an unknown heading; GNSS fixes."""
    t = np.arange(0.0, 130.0, 0.1)
    s = 1.5 * t
    lane = np.floor(s / 60.0)
    along = np.where(lane % 2 == 0, s % 60.0, 60.0 - s % 60.0)
    pos = np.column_stack([lane * 6.0, along, np.zeros_like(t)])
    truth = _poses(
        pos, Rotation.from_euler("z", np.where(lane % 2 == 0, np.pi / 2, -np.pi / 2)[:, None])
    )
    # Odometry: the true steps with 0.03 deg of heading drift per metre, started 30 deg off.
    odo = truth.copy()
    odo[0, :3, :3] = Rotation.from_euler("z", np.pi / 2 + 0.5).as_matrix()
    odo[0, :3, 3] = 0.0
    steps = np.linalg.inv(truth[:-1]) @ truth[1:]
    bend = Rotation.from_euler("z", np.radians(0.03) * 0.15).as_matrix()
    for k in range(1, len(t)):
        step = steps[k - 1].copy()
        step[:3, :3] = bend @ step[:3, :3]
        odo[k] = odo[k - 1] @ step
    noisy = pos + RNG.normal(0, 0.05, pos.shape)
    series = _gnss_series(37.0, -120.0, noisy, t, 0.05)
    epochs = gnss_epochs(series, local_frame_for(series))
    fused = fuse_trajectory(t, odo, FusionSettings(odometry_drift_rotation=0.001), gnss=epochs)
    est = pose_table(t, ContinuousTrajectory(fused.times, fused.poses, t, odo).matrices(t))
    ref = pose_table(t, truth)
    err = trajectory_errors(est, ref)
    odo_err = trajectory_errors(pose_table(t, odo), ref)
    assert err["ate_rmse_m"] < 0.1 < odo_err["ate_rmse_m"]
    assert abs(fused.diagnostics["initial_heading_deg"] + np.degrees(0.5)) < 5.0


def test_segment_drift_of_a_scaled_path() -> None:
    t = np.arange(0, 300.0)
    ref = _poses(np.column_stack([t, 0 * t, 0 * t]), Rotation.identity(len(t)))
    est = ref.copy()
    est[:, 0, 3] *= 1.01
    drift = segment_drift(est, ref, lengths=(50.0, 100.0))
    assert drift["50m"] == pytest.approx(1.0, rel=0.02) and drift["100m"] == pytest.approx(
        1.0, rel=0.02
    )


def test_trajectory_errors_after_rigid_motion_are_zero() -> None:
    t = np.arange(0.0, 60.0, 0.1)
    truth = _poses(
        np.column_stack([np.cos(t / 10) * 20, np.sin(t / 10) * 20, 0.1 * np.sin(t)]),
        Rotation.from_euler("z", (t / 10 + np.pi / 2)[:, None]),
    )
    moved = np.einsum(
        "ij,njk->nik",
        _poses(np.array([[3.0, -2.0, 1.0]]), Rotation.from_euler("z", [0.3]))[0],
        truth,
    )
    r = trajectory_errors(pose_table(t, moved), pose_table(t, truth))
    assert r["ate_rmse_m"] < 1e-6 and r["drift_percent"] < 1e-4 and r["rotation_rmse_deg"] < 1e-4


def test_mapping_config_defaults_are_valid() -> None:
    from canopy_kit.mapping.pipeline import _check_config

    _check_config(MappingConfig())
    from canopy_kit.errors import ConfigError

    with pytest.raises(ConfigError, match="mapping.min_range/max_range"):
        _check_config(MappingConfig(min_range=5.0, max_range=2.0))
    with pytest.raises(ConfigError, match="mapping.gnss_lever_arm"):
        _check_config(MappingConfig(gnss_lever_arm=[0.0, 1.0]))
    with pytest.raises(
        ConfigError, match=r"mapping.map_max_range: must be above min_range \(2.0 m\)"
    ):
        _check_config(MappingConfig(min_range=2.0, map_max_range=1.5))


def test_map_range_is_the_nearer_limit_and_selects_by_distance() -> None:
    from canopy_kit.mapping.filters import map_range, map_range_subset

    assert map_range(MappingConfig()) == 30.0
    assert map_range(MappingConfig(max_range=20.0)) == 20.0  # never beyond the odometry's
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-50, 50, (500, 3))
    keep = rng.random(500) < 0.7
    sel = map_range_subset(xyz, keep, 30.0)
    kept_idx = np.flatnonzero(keep)
    expected = [i for i, k in enumerate(kept_idx) if np.sqrt((xyz[k] ** 2).sum()) <= 30.0]
    assert sel.tolist() == expected and 0 < len(sel) < keep.sum()


def test_map_points_of_a_sweep_keep_indices_and_ground_flags_aligned() -> None:
    from canopy_kit.io.bag import Scan
    from canopy_kit.mapping.frontend import FrontendSweep, map_points

    rng = np.random.default_rng(4)
    raw = rng.uniform(-40, 40, (400, 3))
    keep = range_mask(raw, 1.0, 35.0)
    ground = rng.random(int(keep.sum())) < 0.3
    deskewed = raw[keep] + 0.01  # the deskew moves points a little; ranges come from the scan
    sweep = FrontendSweep(
        Scan(0.0, raw, {}, None, "lidar", 0), 0.0, np.eye(4), keep, deskewed, ground, True
    )
    xyz, kept, flags = map_points(sweep, 20.0)
    near = np.linalg.norm(raw, axis=1) <= 20.0
    assert kept.tolist() == np.flatnonzero(keep & near).tolist()
    assert np.allclose(xyz, raw[kept] + 0.01)
    assert flags.tolist() == ground[np.isin(np.flatnonzero(keep), kept)].tolist()


def test_point_cloud_of_accumulator_carries_crs_and_origin() -> None:
    acc = MapAccumulator(0.05)
    acc.add(np.zeros((1, 3)), {"a": np.ones(1)})
    cloud = acc.cloud(crs="EPSG:32610", origin=np.array([1.0, 2.0, 3.0]))
    assert isinstance(cloud, PointCloud) and cloud.crs == "EPSG:32610"
    assert np.allclose(cloud.absolute_xyz, [[1.0, 2.0, 3.0]])


# -- decoding ----------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite3", "ros2-mcap"])
def test_imu_fields_read_in_place_match_a_full_deserialisation(tmp_path, fmt: str) -> None:
    from canopy_kit.io.bag import open_bag
    from canopy_kit.io.bag_writer import BagWriter
    from canopy_kit.mapping.sensors import imu_fields

    # Frame ids of every length mod 8 exercise the CDR alignment after the string.
    frames = ["", "a", "imu", "lidar", "base_imu", "imu_link_long", "x" * 14, "ü_frame"]
    with BagWriter(tmp_path / "b", fmt) as writer:
        for i, frame in enumerate(frames):
            writer.write_imu(
                "/imu",
                100.0 + 0.005 * i + 1e-9 * i,
                RNG.normal(size=3),
                RNG.normal(size=3),
                None,
                frame,
            )
    n = 0
    with open_bag(writer.path) as bag:
        reader = bag.reader
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            got = imu_fields(raw, reader.is2)
            assert got is not None
            stamp = float(msg.header.stamp.sec) + float(msg.header.stamp.nanosec) * 1e-9
            w, a = msg.angular_velocity, msg.linear_acceleration
            assert got == (stamp, msg.header.frame_id, (w.x, w.y, w.z), (a.x, a.y, a.z))
            n += 1
    assert n == len(frames)
    assert (
        imu_fields(b"\x00\x00\x00\x00" + bytes(300), True) is None
    )  # big-endian CDR: rosbags decodes
    assert imu_fields(b"\x00\x01\x00\x00" + bytes(8), True) is None  # cut short


def test_sweeps_are_left_unregistered_only_while_the_predicted_motion_is_small() -> None:
    from types import SimpleNamespace

    from canopy_kit.io.bag import Scan
    from canopy_kit.mapping.frontend import SKIP_MAX_SHIFT_M, SKIP_MAX_TURN_DEG, LidarFrontend

    config = MappingConfig(odometry_every=3, odometry_map_skipped=True)
    front = LidarFrontend(config, imu=None, keep_all_points=False)
    added: list[np.ndarray] = []  # the poses sweeps were added to the local map at
    front._odometry = SimpleNamespace(
        pose=np.eye(4), extend_map=lambda points, pose: added.append(pose)
    )
    front._history.append((0.0, np.eye(4)))  # last registered sweep at t = 0
    n = 1000
    scan = Scan(0.1, RNG.uniform(-10, 10, (n, 3)), {}, np.linspace(0.05, 0.15, n), "lidar", 1)
    keep = np.ones(n, bool)
    dt = 0.1  # the sweep's reference time is the middle of its points' times

    def skipped(speed: float, turn_rate_deg: float) -> bool:
        front._velocity = np.array([speed, 0.0, 0.0])
        front._omega = np.array([0.0, 0.0, np.radians(turn_rate_deg)])
        return front._unregistered(scan, keep) is not None

    assert skipped(1.5, 10.0)  # driving along a row
    assert not skipped(1.05 * SKIP_MAX_SHIFT_M / dt, 0.0)  # too fast: register it
    assert not skipped(0.5, 1.05 * SKIP_MAX_TURN_DEG / dt)  # a tight turn: register it
    assert front.state.sweeps == 1  # only the skipped sweep was counted
    # and only it went into the local map, at its predicted pose (1.5 m/s for 0.1 s)
    assert len(added) == 1 and np.allclose(added[0][:3, 3], [0.15, 0.0, 0.0])
