"""The truth format and session layout (canopy_kit.evaluate.truth, canopy_kit.io.session_layout),
read without the simulator."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from canopy_kit.core.geo import LocalFrame
from canopy_kit.errors import InputError
from canopy_kit.evaluate.truth import TREE_COLUMNS, load_truth, load_world, write_csv
from canopy_kit.io.session_layout import find_bag, sim_config_path, truth_dir


def _truth_folder(root):
    """A hand-written truth folder: the three tables, no generator's files."""
    truth = truth_dir(root)
    truth.mkdir(parents=True)
    write_csv(pd.DataFrame([dict.fromkeys(TREE_COLUMNS, 1)]), truth / "trees.csv")
    write_csv(
        pd.DataFrame(
            {
                "time": [0.0, 1.0],
                "x": [0.0, 1.0],
                "y": 0.0,
                "z": 0.0,
                "qx": 0.0,
                "qy": 0.0,
                "qz": 0.0,
                "qw": 1.0,
            }
        ),
        truth / "trajectory.csv",
    )
    frame = LocalFrame(32610, 500000.0, 4100000.0, 50.0)
    info = {"frame": frame.to_dict(), "sensor_frame": "lidar"}
    (truth / "frame.json").write_text(json.dumps(info))


def test_a_truth_folder_reads_without_the_simulator(tmp_path):
    _truth_folder(tmp_path)
    truth = load_truth(tmp_path)
    assert list(truth.trees.columns) == TREE_COLUMNS
    assert truth.trajectory_of("lidar") is truth.trajectory
    # Exact geometry needs the generator's files; a folder without them says which.
    with pytest.raises(InputError, match="sim_config.toml"):
        load_world(tmp_path)
    assert not sim_config_path(tmp_path).exists()
    with pytest.raises(InputError, match="no simulated bag"):
        find_bag(tmp_path)
    (tmp_path / "session.bag").write_bytes(b"")
    assert find_bag(tmp_path) == tmp_path / "session.bag"


def test_a_folder_that_is_not_truth_names_the_missing_table(tmp_path):
    with pytest.raises(InputError, match="no trees.csv"):
        load_truth(tmp_path)
