"""Parallel odometry over time chunks (``canopy_kit.mapping.chunks``)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from canopy_kit.config import MappingConfig
from canopy_kit.evaluate.trajectory_error import evaluate_against_simulation
from canopy_kit.mapping import build_map
from canopy_kit.mapping.chunks import OVERLAP_SWEEPS, SKIP_COST, balanced_bounds, chunk_plan, tie
from canopy_kit.mapping.passone import SweepRecord
from canopy_kit.sim import load_sim_config, simulate_session


def _pose(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    out[:3, 3] = t
    return out


def test_chunks_cover_every_scan_once_and_start_in_step() -> None:
    cfg = MappingConfig(workers=3, odometry_chunk_sweeps=100, odometry_every=2)
    chunks = chunk_plan("bag", 1001, cfg)
    assert len(chunks) == 3
    owned = [(c.own, c.end if c.end is not None else 1001) for c in chunks]
    assert owned[0][0] == 0 and all(a[1] == b[0] for a, b in itertools.pairwise(owned))
    for c in chunks[1:]:
        assert c.first % cfg.odometry_every == 0  # registers the same sweeps as the chunk before
        assert OVERLAP_SWEEPS <= c.own - c.first < OVERLAP_SWEEPS + cfg.odometry_every
    # Too short a drive for two chunks of the minimum size: one process.
    assert len(chunk_plan("bag", 150, cfg)) == 1


@pytest.mark.parametrize(("n_scans", "n_chunks"), [(2370, 2), (5000, 3), (1001, 4), (900, 1)])
def test_chunk_borders_give_every_worker_the_same_work(n_scans, n_chunks) -> None:
    bounds = balanced_bounds(n_scans, n_chunks)
    assert bounds[0] == 0 and bounds[-1] == n_scans and np.all(np.diff(bounds) > 0)
    # Work of chunk k: its own scans, the overlap it repeats and the scans it skips undecoded.
    work = [
        b - a + (OVERLAP_SWEEPS + SKIP_COST * (a - OVERLAP_SWEEPS) if k else 0)
        for k, (a, b) in enumerate(itertools.pairwise(bounds))
    ]
    assert max(work) - min(work) <= 2
    if n_chunks > 1:
        assert bounds[1] > n_scans / n_chunks  # the first chunk, which skips nothing, owns more


def test_tie_recovers_the_transform_between_chunk_frames() -> None:
    rng = np.random.default_rng(3)
    truth = _pose(np.array([0.01, -0.02, 0.7]), np.array([5.0, -3.0, 0.2]))  # current -> previous
    previous, current = [], []
    for i in range(100, 140):
        world = _pose(rng.normal(0, 0.1, 3), np.array([0.5 * i, 0.0, 0.0]))
        noisy = world @ _pose(rng.normal(0, 2e-4, 3), rng.normal(0, 0.005, 3))
        previous.append(SweepRecord(i, float(i), world, 1.0, True, True))
        current.append(
            SweepRecord(i, float(i), np.linalg.inv(truth) @ noisy, 1.0, True, i % 2 == 0)
        )
    a = tie(previous, current, own=140)
    assert a is not None
    assert np.abs(a[:3, 3] - truth[:3, 3]).max() < 0.01
    assert (
        np.degrees(
            (
                Rotation.from_matrix(a[:3, :3]) * Rotation.from_matrix(truth[:3, :3]).inv()
            ).magnitude()
        )
        < 0.05
    )
    assert tie(previous[:4], current[:4], own=140) is None  # nothing to tie with


@pytest.mark.slow
def test_chunked_odometry_maps_as_accurately_as_one_process(tmp_path) -> None:
    cfg = load_sim_config("pistachio", {"seed": 12, "orchard": {"rows": 2, "trees_per_row": 3}})
    session = simulate_session(tmp_path / "p2x3", cfg)
    single = evaluate_against_simulation(
        build_map(session.bag, MappingConfig(workers=1)), session.root
    )
    chunked_result = build_map(session.bag, MappingConfig(workers=3, odometry_chunk_sweeps=150))
    chunked = evaluate_against_simulation(chunked_result, session.root)
    assert chunked_result.diagnostics["odometry_workers"] == 3
    assert chunked_result.diagnostics["sweeps_mapped"] == chunked_result.diagnostics["scans"]
    assert chunked_result.warnings == []
    assert chunked["ate_rmse_m"] < 0.08 and chunked["drift_percent"] <= 0.5
    # The seams cost little: within 2 cm of the single process's trajectory error.
    assert chunked["ate_rmse_m"] < single["ate_rmse_m"] + 0.02
    assert chunked["map_aligned"]["median_m"] < 0.05


@pytest.mark.parametrize(
    "setting", [{"odometry_every": 0}, {"odometry_chunk_sweeps": 0}, {"workers": -1}]
)
def test_bad_parallel_settings_are_named(setting: dict, tmp_path) -> None:
    from canopy_kit.errors import ConfigError

    name = next(iter(setting))
    with pytest.raises(ConfigError, match=f"mapping.{name}"):
        build_map(tmp_path / "never_read.bag", MappingConfig(**setting))


@pytest.mark.parametrize("fmt", ["ros2-mcap", "ros1", "ros2-sqlite3"])
def test_map_pass_on_several_workers_equals_one_process(sim_factory, fmt) -> None:
    """Workers seek to their own stretch of the bag; the merged map is the single process's."""
    from conftest import MICRO

    from canopy_kit.io.bag import open_bag
    from canopy_kit.mapping.assemble import assemble_map
    from canopy_kit.mapping.passone import odometry_pass
    from canopy_kit.mapping.trajectory import ContinuousTrajectory

    session = sim_factory("pistachio", fmt=fmt, overrides=MICRO)
    cfg = MappingConfig(workers=1)
    with open_bag(session.bag) as bag:
        one = odometry_pass(bag, cfg)
    reg = [r for r in one.records if r.registered]
    times, poses = np.array([r.t_ref for r in reg]), np.array([r.pose for r in reg])
    trajectory = ContinuousTrajectory(times, poses, times, poses)
    sweeps = {r.index: r.deskewed for r in one.records}
    assert len(one.scan_log_ns) == one.n_scans and np.all(np.diff(one.scan_log_ns) > 0)
    single = assemble_map(str(session.bag), one.topics.scans, sweeps, trajectory, cfg)
    split = assemble_map(
        str(session.bag),
        one.topics.scans,
        sweeps,
        trajectory,
        MappingConfig(workers=3),
        scan_log_ns=one.scan_log_ns,
    )
    unseeked = assemble_map(
        str(session.bag), one.topics.scans, sweeps, trajectory, MappingConfig(workers=2)
    )
    assert single[2] == split[2] == unseeked[2] > 0  # every point offered once
    for other in (split, unseeked):
        assert np.array_equal(other[0], single[0])
        assert other[1].keys() == single[1].keys()
        assert all(np.array_equal(other[1][k], single[1][k]) for k in single[1])
