"""Robots whose sensors sit in their own frames, simulated and mapped, judged against the
simulator's truth: the same drive with every sensor in one frame is the yardstick.

Seed 41 was not used while developing the rig handling (that used 701 and 900-902).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from canopy_kit.config import MappingConfig
from canopy_kit.core.frames import from_rpy, invert, rotation_angle_deg
from canopy_kit.errors import InputError
from canopy_kit.evaluate.trajectory_error import evaluate_against_simulation
from canopy_kit.mapping import MappingResult, build_map
from canopy_kit.sim.truth import load_truth

SMALL = {"orchard": {"rows": 2, "trees_per_row": 3}, "lidar": {"columns": 512}}


def _session(sim_factory, rig: str, seed: int = 41, **rig_settings):
    return sim_factory(
        "pistachio", seed=seed, overrides={**SMALL, "rig": {"name": rig, **rig_settings}}
    )


def _true_lidar_from_imu(sim_dir: Path) -> np.ndarray:
    rig = load_truth(sim_dir).info["rig"]
    mount = {
        k: from_rpy(rig[k]["translation"], rig[k]["rpy_deg"])
        for k in ("base_from_lidar", "base_from_imu")
    }
    return invert(mount["base_from_lidar"]) @ mount["base_from_imu"]


@pytest.fixture(scope="module")
def rig_map(sim_factory) -> Callable[[str], MappingResult]:
    """``rig_map(rig)``: ``build_map`` of the rig's seed-41 drive (with /tf_static) under the
    default mapping settings, made once per module for every test that maps that drive so."""
    maps: dict[str, MappingResult] = {}

    def make(rig: str) -> MappingResult:
        if rig not in maps:
            maps[rig] = build_map(_session(sim_factory, rig).bag, MappingConfig())
        return maps[rig]

    return make


@pytest.fixture(scope="module")
def identity_run(sim_factory, rig_map):
    sim = _session(sim_factory, "identity")
    res = rig_map("identity")
    return sim, res, evaluate_against_simulation(res, sim.root)


@pytest.mark.slow
@pytest.mark.parametrize("rig", ["tower", "imu-flipped"])
def test_a_rig_maps_the_drive_as_well_as_one_frame(
    sim_factory, identity_run, rig_map, rig: str
) -> None:
    sim = _session(sim_factory, rig)
    res = rig_map(rig)
    ev = evaluate_against_simulation(res, sim.root)
    base = identity_run[2]
    assert res.trajectory_frame == "base_link" and ev["trajectory_frame"] == "base_link"
    assert res.warnings == []
    assert ev["ate_rmse_m"] <= 0.10 and ev["ate_rmse_m"] <= 1.5 * base["ate_rmse_m"] + 0.005
    assert ev["drift_percent"] <= 0.5
    assert ev["map_aligned"]["median_m"] <= 1.5 * base["map_aligned"]["median_m"] + 0.005
    # The mount the odometry used is the true one, and the drive agrees with it.
    assert rotation_angle_deg(res.rig.lidar_from_imu, _true_lidar_from_imu(sim.root)) < 1e-6
    assert res.diagnostics["extrinsics"]["difference_deg"] < 1.0
    assert res.rig.sources == {"base": "tf_static", "imu": "tf_static", "gnss": "tf_static"}


def test_different_frames_and_no_extrinsics_stop_with_both_frames_named(
    sim_factory, tmp_path
) -> None:
    from test_cli_foundation import run_cli

    sim = _session(sim_factory, "tower", write_tf_static=False)
    with pytest.raises(
        InputError,
        match=r"frame 'velodyne'.*frame 'imu_link'.*--rig FILE.*"
        r"--calibrate-extrinsics.*--assume-identity-extrinsics",
    ):
        build_map(sim.bag, MappingConfig())
    cli = run_cli("map", str(sim.bag), "--out", str(tmp_path / "m"))
    assert cli.returncode == 2 and "'velodyne'" in cli.stderr and "'imu_link'" in cli.stderr
    assert not (tmp_path / "m").exists()


@pytest.mark.slow
def test_calibrate_extrinsics_estimates_the_imu_mount_within_a_degree(
    sim_factory, identity_run
) -> None:
    sim = _session(sim_factory, "tower", write_tf_static=False)
    res = build_map(sim.bag, MappingConfig(extrinsics="calibrate"))
    error = rotation_angle_deg(res.rig.lidar_from_imu, _true_lidar_from_imu(sim.root))
    assert error < 1.0
    assert res.rig.sources["imu"] == "estimated from the drive"
    ev = evaluate_against_simulation(res, sim.root)
    # No /tf_static: the trajectory is the LiDAR's (no base frame known), and it is right.
    assert ev["trajectory_frame"] == "velodyne"
    assert ev["ate_rmse_m"] <= 0.10 and ev["drift_percent"] <= 0.5
    assert ev["map_aligned"]["median_m"] <= 1.5 * identity_run[2]["map_aligned"]["median_m"] + 0.005
    assert "estimated" in res.diagnostics["extrinsics"]


@pytest.mark.slow
def test_a_rig_file_wrong_by_five_degrees_is_named_with_its_angle(sim_factory, tmp_path) -> None:
    from canopy_kit.config.rig import rig_data, rig_overrides

    sim = _session(sim_factory, "tower", write_tf_static=False)
    data, _ = rig_data("tower")
    data["frames"]["imu_link"]["rpy_deg"][2] += 5.0  # yaw 90 -> 95 deg: 5 deg off the truth
    import tomlkit

    wrong = tmp_path / "wrong_rig.toml"
    wrong.write_text(tomlkit.dumps(data))
    res = build_map(sim.bag, MappingConfig(**rig_overrides(wrong)["mapping"]))
    warning = [w for w in res.warnings if w.startswith("extrinsics:")]
    assert len(warning) == 1
    assert "'imu_link'" in warning[0] and "'velodyne'" in warning[0] and "rig file" in warning[0]
    angle = float(warning[0].split(" deg from")[0].rsplit(" ", 1)[1])
    assert 3.5 <= angle <= 6.5  # the file is 5 deg off
    assert res.diagnostics["extrinsics"]["difference_deg"] == pytest.approx(angle, abs=0.05)
    assert rotation_angle_deg(
        res.rig.lidar_from_imu, _true_lidar_from_imu(sim.root)
    ) == pytest.approx(5.0, abs=1e-6)


@pytest.mark.slow
def test_a_rig_file_supplies_what_the_bag_lacks(sim_factory, rig_map, tmp_path) -> None:
    """The bag without /tf_static plus the rig file maps as the bag with it does."""
    import pandas as pd
    from test_cli_foundation import run_cli

    without = _session(sim_factory, "tower", write_tf_static=False)
    a = rig_map("tower")  # the bag with /tf_static
    cli = run_cli(
        "map",
        str(without.bag),
        "--out",
        str(tmp_path / "m"),
        "--rig",
        "tower",
        "--no-plots",
        timeout=600,
    )
    assert cli.returncode == 0, cli.stderr
    b = pd.read_csv(tmp_path / "m" / "trajectory.csv")
    assert np.allclose(a.trajectory[["x", "y", "z"]], b[["x", "y", "z"]], atol=2e-3)
    rig_text = (tmp_path / "m" / "rig.toml").read_text()
    assert 'lidar_frame = "velodyne"' in rig_text and "[frames.imu_link]" in rig_text
    report = json.loads((tmp_path / "m" / "mapping.json").read_text())
    assert report["diagnostics"]["rig"]["sources"]["imu"] == "rig file"
    assert report["diagnostics"]["trajectory_frame"] == "base_link"
    assert "rig_name" in (tmp_path / "m" / "mapping_config.toml").read_text()


@pytest.mark.slow
def test_a_rig_finds_the_same_trees_with_the_same_volumes(
    sim_factory, rig_map, tmp_path_factory
) -> None:
    """The whole pipeline on the same drive recorded by the identity and the tower rig: the
    same trees, and each tree's volume within 2 % of the identity rig's (sums within 2 %).
    The map stage is ``build_map(bag, preset.mapping)``: the preset's mapping settings are the
    defaults ``rig_map`` used, so its map goes into the run's stage cache (under the key the
    run computes) and the run maps nothing; segmentation and volumes run anew."""
    from canopy_kit.config import load_preset
    from canopy_kit.core.cache import StageCache, fingerprint, stage_key
    from canopy_kit.pipeline import run

    config = load_preset("adaptive")
    assert config.mapping == MappingConfig()
    tables = {}
    for rig in ("identity", "tower"):
        sim = _session(sim_factory, rig)
        out = tmp_path_factory.mktemp(f"run_{rig}")
        key = stage_key("map", fingerprint(sim.bag), config.mapping)
        StageCache(out / ".cache").get_or_compute("map", key, lambda rig=rig: rig_map(rig))
        res = run(config, sim.bag, out, truth=sim.root)
        assert res.cache_hits == ["map"], res.cache_hits
        seg = res.metrics["evaluation"]["segmentation"]
        assert seg["n_correct"] == seg["n_truth"] == len(res.trees), rig
        tables[rig] = res.trees.set_index("truth_tree_id")
    a, b = tables["tower"], tables["identity"]
    assert sorted(a.index) == sorted(b.index)
    for col in ("volume_convex_hull_m3", "volume_alpha_m3"):
        ratio = a.loc[b.index, col] / b[col]
        assert abs(a[col].sum() / b[col].sum() - 1) < 0.02, col
        assert (ratio - 1).abs().mean() < 0.02, (col, ratio.round(3).tolist())


@pytest.mark.slow
def test_streaming_uses_the_rig(sim_factory, tmp_path) -> None:
    """Streaming reads the same frames: a tower session streams its six trees (with the IMU
    taken as in the LiDAR's frame the window never closed: 17 "trees", a 4 M point window)."""
    from canopy_kit.config import load_preset
    from canopy_kit.streaming import run_stream

    sim = _session(sim_factory, "tower")
    res = run_stream(load_preset("adaptive"), sim.bag, tmp_path / "s")
    assert len(res.trees) == len(load_truth(sim.root).trees)
    with pytest.raises(InputError, match="does not stream"):
        run_stream(
            load_preset("adaptive", {"mapping": {"extrinsics": "calibrate"}}),
            sim.bag,
            tmp_path / "c",
        )
