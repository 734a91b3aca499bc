"""``mapping.odometry_map_skipped = "auto"``: on for a LiDAR that sees no ground beside the
robot (a Livox Mid-360, lowest beam -7 deg), off for a spinning sensor that does.

The truth the decision is checked against is the simulated sensor's own lowest beam
(``lidar.vertical_fov``), not the elevations the code measures.
"""

from __future__ import annotations

import numpy as np
import pytest

from canopy_kit.config import MappingConfig, from_dict
from canopy_kit.errors import ConfigError
from canopy_kit.mapping.ground_view import (
    MAP_SKIPPED_ABOVE_DEG,
    GroundView,
    ground_view,
    lowest_elevation_deg,
    map_skipped_decision,
)

SHORT_DRIVE = {"orchard": {"rows": 2, "trees_per_row": 6}, "gnss": {"mode": "standard"}}


def test_lowest_elevation_by_hand() -> None:
    # 1000 points: 980 on the horizon, 20 at -20 deg (a lowest ring of 2 % of the points):
    # the 1 % quantile falls among those 20.
    az = np.linspace(0, 2 * np.pi, 1000, endpoint=False)
    el = np.zeros(1000)
    el[::50] = np.radians(-20.0)
    xyz = 5.0 * np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    assert lowest_elevation_deg(xyz, np.array([0.0, 0.0, 1.0])) == pytest.approx(-20.0, abs=1e-6)
    # Five stray points below them do not decide (under 1 % of the points).
    stray = np.vstack([xyz, [[0.0, 0.0, -3.0]] * 5])
    assert lowest_elevation_deg(stray, np.array([0.0, 0.0, 1.0])) > -21.0
    # The vehicle's "up" in the LiDAR frame (a LiDAR pitched 10 deg about y): elevations are
    # measured from the vehicle's horizontal plane, not the sensor's.
    pitch = np.radians(10.0)
    up = np.array([np.sin(pitch), 0.0, np.cos(pitch)])
    flat = 5.0 * np.column_stack([np.cos(az), np.sin(az), np.zeros(1000)])
    assert lowest_elevation_deg(flat, up) == pytest.approx(-10.0, abs=0.1)
    assert np.isnan(lowest_elevation_deg(np.zeros((0, 3)), up))


def test_decision_from_the_lowest_returns() -> None:
    low = MAP_SKIPPED_ABOVE_DEG
    assert map_skipped_decision("auto", GroundView(low + 4.0, 10, 1000))["on"] is True
    assert map_skipped_decision("auto", GroundView(low - 4.0, 10, 1000))["on"] is False
    assert map_skipped_decision("auto", GroundView(float("nan"), 0, 0))["on"] is False
    assert map_skipped_decision("auto", None)["on"] is False
    # explicit settings override whatever the data says
    for setting in (True, False):
        decision = map_skipped_decision(setting, GroundView(low + 4.0, 10, 1000))
        assert decision == {"setting": setting, "on": setting, "reason": "set explicitly"}


@pytest.mark.parametrize("value", ["yes", "on", 1, 0.0, None])
def test_odometry_map_skipped_is_validated(value) -> None:
    with pytest.raises(
        ConfigError, match=r'mapping\.odometry_map_skipped: expected true, false or "auto"'
    ):
        from_dict(MappingConfig, {"odometry_map_skipped": value}, "mapping")
    with pytest.raises(ConfigError, match=r"mapping\.odometry_map_skipped"):
        MappingConfig(odometry_map_skipped=value)


def test_odometry_map_skipped_accepts_auto_and_booleans() -> None:
    assert MappingConfig().odometry_map_skipped == "auto"
    for value in ("auto", True, False):
        config = from_dict(MappingConfig, {"odometry_map_skipped": value}, "mapping")
        assert config.odometry_map_skipped == value


@pytest.mark.parametrize(("sensor", "on"), [("livox-mid360", True), ("vlp16", False)])
def test_auto_decision_on_a_simulated_drive(sim_factory, sensor: str, on: bool) -> None:
    """The first scans of a 2 x 6 drive: the lowest returns are the sensor's lowest beam, and
    the decision is on exactly for the sensor whose lowest beam is above the threshold."""
    from canopy_kit.io.bag import open_bag
    from canopy_kit.mapping.extrinsics import resolve_rig
    from canopy_kit.mapping.sensors import topics_for
    from canopy_kit.sim.session import load_sim_config_of

    sim = sim_factory("pistachio", seed=5, overrides=SHORT_DRIVE, sensor=sensor)
    lowest_beam = load_sim_config_of(sim.root).lidar.vertical_fov[0]  # the truth
    config = MappingConfig()
    with open_bag(sim.bag) as bag:
        topics = topics_for(bag, config)
        rig = resolve_rig(bag, topics, config)
    view = ground_view(sim.bag, topics, rig.lidar_from_base, config)
    assert view.scans == 10 and view.points > 1000
    assert view.lowest_elevation_deg == pytest.approx(lowest_beam, abs=0.5)
    assert (lowest_beam > MAP_SKIPPED_ABOVE_DEG) is on
    decision = map_skipped_decision("auto", view)
    assert decision["on"] is on
    assert decision["lowest_elevation_deg"] == pytest.approx(lowest_beam, abs=0.5)
