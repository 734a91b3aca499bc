"""Where the drone crowns and the LiDAR trees sit against the simulator's truth (issue 30).

In simulated runs the drone crowns sat 0.1-0.9 m off the LiDAR trees, one translation per
session. Measured per stage (docs/GROUND_TRUTH.md, "Drone vs LiDAR positions"): the drone
crowns are on the true crown centres; the LiDAR trees are on the true crowns *of the mapped
drive*, and the mapped drive is off by the standalone GNSS error averaged over the drive
(Gauss-Markov, 20 s correlation: one random translation per session, zero over many seeds).
These tests pin each stage on one small flight: 6 trees, per-tree scatter about 0.1 m per
axis, so a mean is known to about 0.04 m, and 0.1 m is 2.5 standard errors while still a
third of the 0.3 m offset the issue reported.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from canopy_kit.core.geo import LocalFrame

pytestmark = pytest.mark.slow
BOUND_M = 0.1  # on the mean signed offset per axis (east, north), 6 trees


@pytest.fixture(scope="module")
def drone_run(tiny_drone_session, tmp_path_factory):
    """The 2 x 3 pistachio session with drone photos (seed 4), run with its photos (the
    session and the run's stages shared with the other files that use them, conftest.py)."""
    out = tmp_path_factory.mktemp("offset_run")
    results = tiny_drone_session.run_into(out)
    return tiny_drone_session.root, out, results.metrics


def _truth(sim):
    frame = LocalFrame.from_dict(json.loads((sim / "truth" / "frame.json").read_text())["frame"])
    return frame, pd.read_csv(sim / "truth" / "trees.csv")


def _offsets(frame: LocalFrame, table: pd.DataFrame, truth: pd.DataFrame) -> np.ndarray:
    """(east, north) of each row's lat/lon from the nearest true crown centre (within 1.5 m)."""
    xy = frame.to_local(table["lat"].to_numpy(float), table["lon"].to_numpy(float))[:, :2]
    centres = truth[["crown_x", "crown_y"]].to_numpy()
    d = xy[:, None, :] - centres[None, :, :]
    nearest = np.linalg.norm(d, axis=2).argmin(axis=1)
    off = d[np.arange(len(xy)), nearest]
    return off[np.linalg.norm(off, axis=1) < 1.5]


def _map_offset(sim, out, frame: LocalFrame) -> np.ndarray:
    """Mean (east, north) of the mapped LiDAR trajectory from the true one: the map's
    georeferencing error."""
    trees = pd.read_csv(out / "trees.csv")
    to_truth = (
        frame.to_local(trees["lat"].to_numpy(), trees["lon"].to_numpy())[:, :2]
        - trees[["x", "y"]].to_numpy()
    ).mean(axis=0)  # run frame -> truth frame
    true = pd.read_csv(sim / "truth" / "trajectory.csv")
    mapped = pd.read_csv(out / "trajectory.csv")
    tx, ty = (
        np.interp(mapped["time"], true["time"], true["x"]),
        np.interp(mapped["time"], true["time"], true["y"]),
    )
    return np.array(
        [(mapped["x"] + to_truth[0] - tx).mean(), (mapped["y"] + to_truth[1] - ty).mean()]
    )


def test_drone_crowns_are_on_the_true_crown_centres(drone_run):
    sim, out, _ = drone_run
    frame, truth = _truth(sim)
    off = _offsets(frame, pd.read_csv(out / "aerial" / "crowns.csv"), truth)
    assert len(off) == 6
    assert np.abs(off.mean(axis=0)).max() < BOUND_M, off.mean(axis=0)


def test_lidar_trees_are_on_the_true_crowns_of_the_mapped_drive(drone_run):
    """The LiDAR positions (medians of each tree's points) carry no bias of their own; their
    offset from the truth is the map's georeferencing error, i.e. the drive's mean GNSS error."""
    sim, out, _ = drone_run
    frame, truth = _truth(sim)
    off = _offsets(frame, pd.read_csv(out / "trees.csv"), truth)
    assert len(off) == 6
    drift = _map_offset(sim, out, frame)
    assert np.abs(off.mean(axis=0) - drift).max() < BOUND_M, (off.mean(axis=0), drift)


def test_the_run_measures_the_lidar_maps_offset_from_the_drone(drone_run):
    """``seed_offset`` (crowns minus LiDAR trees) is minus the map's georeferencing error."""
    sim, out, metrics = drone_run
    frame, _ = _truth(sim)
    offset = metrics["aerial"]["seed_offset"]
    assert offset["pairs"] == 6
    drift = _map_offset(sim, out, frame)
    assert [offset["east_m"], offset["north_m"]] == pytest.approx(-drift, abs=BOUND_M)
    report = json.loads((out / "aerial" / "report.json").read_text())
    assert report["seed_offset"]["east_m"] == offset["east_m"]


def test_the_shared_run_reconstructed_the_photos_on_one_thread(drone_run) -> None:
    """The tests' shared drone run asks for one SfM thread (``run(sfm_threads=1)``), so every
    test run gets the same reconstruction, and its aerial report says so."""
    _, out, _ = drone_run
    report = json.loads((out / "aerial" / "report.json").read_text())
    assert report["sfm_threads"] == 1
