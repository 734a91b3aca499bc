"""Faults inside a simulated drive's messages, judged against the simulator's per-tree truth.

One row of three pistachio trees (46 s, 460 scans, 9240 IMU samples): the clean drive maps to
the three true trees one-to-one. Each fault below must give the same three trees (with the
warning and the quality flag that say what was worked around) or stop with exit 2 naming the
topic, the field and the message. Measured before these checks: one NaN/Inf gyro sample
aborted the process (exit 134, ``SOPHUS_ENSURE failed``), a halved PointCloud2 width gave 5
trees and no warning, a 15 s clock jump gave 6 trees, two PointCloud2 topics left
``pointcloud_topic = ""`` in config.toml.

The commands run on a command server (conftest.py ``cli_server``): each in a process of its
own, forked from one that imported the library once.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from bad_inputs import messages
from cli_server import CliServer

from canopy_kit.config import MappingConfig

ONE_ROW = {"orchard": {"rows": 1, "trees_per_row": 3}, "lidar": {"columns": 512}}
NAN_GYRO = (1e308, float("inf"), 0.0)
POSITION_TOL_M = 0.3  # a tree of a faulty drive lies this close to the clean drive's


@pytest.fixture(scope="module")
def session(sim_factory):
    return sim_factory("pistachio", overrides=ONE_ROW)


def _run(cli: CliServer, *args: str) -> subprocess.CompletedProcess[str]:
    """``canopy-kit args`` on the module's command server."""
    return cli.run(list(args), timeout=600)


def _pipeline(
    cli: CliServer, bag: Path, out: Path, session, *extra: str
) -> tuple[subprocess.CompletedProcess[str], dict]:
    result = _run(cli, "run", str(bag), "--out", str(out), "--truth", str(session.root), *extra)
    metrics = json.loads((out / "metrics.json").read_text()) if result.returncode == 0 else {}
    return result, metrics


@pytest.fixture(scope="module")
def clean_out(session, tmp_path_factory, cli_server) -> Path:
    """The folder of ``canopy-kit run`` (the adaptive preset) on the clean drive."""
    out = tmp_path_factory.mktemp("clean") / "out"
    result, _ = _pipeline(cli_server, session.bag, out, session)
    assert result.returncode == 0, result.stderr
    return out


@pytest.fixture(scope="module")
def clean(clean_out) -> tuple[pd.DataFrame, dict]:
    """The clean drive's trees and metrics."""
    metrics = json.loads((clean_out / "metrics.json").read_text())
    return pd.read_csv(clean_out / "trees.csv"), metrics


def _assert_true_trees(
    trees: pd.DataFrame, metrics: dict, clean: tuple[pd.DataFrame, dict]
) -> None:
    """The three true trees, one-to-one, where the clean drive put them."""
    reference, _ = clean
    seg = metrics["evaluation"]["segmentation"]
    assert seg["n_truth"] == 3 and seg["n_correct"] == 3, seg
    assert sorted(trees["truth_tree_id"]) == sorted(reference["truth_tree_id"])
    both = trees.merge(reference, on="truth_tree_id", suffixes=("", "_clean"))
    shift = np.hypot(both["x"] - both["x_clean"], both["y"] - both["y_clean"])
    assert shift.max() < POSITION_TOL_M, shift.tolist()


def test_clean_drive_is_three_true_trees_without_warnings(clean) -> None:
    trees, metrics = clean
    _assert_true_trees(trees, metrics, clean)
    assert metrics["warnings"] == [] and metrics["mapping"]["quality_flags"] == []


# -- IMU ------------------------------------------------------------------------------------------
def test_nonfinite_imu_sample_is_dropped_and_the_trajectory_unchanged(
    session, clean_out, tmp_path: Path
) -> None:
    """Library: one (1e308, inf, 0) gyro sample is dropped and counted; the ATE is the clean drive's."""
    import pickle

    from canopy_kit.config import load_preset
    from canopy_kit.evaluate.trajectory_error import evaluate_against_simulation
    from canopy_kit.mapping import build_map

    bag = messages.rewrite_bag(session.bag, tmp_path / "nan", messages.imu_sample(4000, NAN_GYRO))
    res = build_map(bag, MappingConfig())
    # The clean drive's build_map under the same settings: the clean run's map stage.
    assert load_preset("adaptive").mapping == MappingConfig()
    (entry,) = (clean_out / ".cache").glob("map-*.pkl")
    ref = pickle.loads(entry.read_bytes())
    assert res.diagnostics["inputs"]["imu"]["dropped"] == 1
    assert res.diagnostics["inputs"]["imu"]["used"] == ref.diagnostics["inputs"]["imu"]["used"] - 1
    assert "imu_samples_dropped" in res.diagnostics["quality_flags"]
    assert any(
        "1 of 9240 IMU samples dropped" in w and "message 4000" in w for w in res.warnings
    ), res.warnings
    ate, ate_ref = (evaluate_against_simulation(r, session.root)["ate_rmse_m"] for r in (res, ref))
    assert abs(ate - ate_ref) < 0.01, (ate, ate_ref)


def test_nonfinite_imu_sample_cli_gives_the_true_trees(
    session, clean, cli_server, tmp_path: Path
) -> None:
    bag = messages.rewrite_bag(session.bag, tmp_path / "nan", messages.imu_sample(4000, NAN_GYRO))
    result, metrics = _pipeline(cli_server, bag, tmp_path / "out", session)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr
    assert "IMU samples dropped" in " ".join(result.stdout.split())
    assert metrics["mapping"]["quality_flags"] == ["imu_samples_dropped"]
    _assert_true_trees(pd.read_csv(tmp_path / "out" / "trees.csv"), metrics, clean)


# -- PointCloud2 and clocks -------------------------------------------------------------------------
def test_few_malformed_scans_and_one_late_stamp_give_the_true_trees(
    session, clean, cli_server, tmp_path: Path
) -> None:
    """4 scans whose x has an unknown datatype, 2 with extra bytes, 1 stamped 15 s back: the
    rest maps to the same trees, and each fault is named."""
    bad = messages.cloud_header(fields=messages.field_changed("x", datatype=11))
    long = messages.padded_data(n_bytes=96)
    late = messages.clock_jump(0.0, -15.0, ("/points",))

    def edit(t: str, i: int, log_ns: int, msg: object) -> list | None:
        if t == "/points":
            for edit_, picked in ((bad, (50, 150, 250, 350)), (long, (100, 300)), (late, (200,))):
                if i in picked:
                    return edit_(t, 0, log_ns, msg)
        return None

    bag = messages.rewrite_bag(session.bag, tmp_path / "faults", edit)
    result, metrics = _pipeline(cli_server, bag, tmp_path / "out", session)
    assert result.returncode == 0, result.stderr
    text = " ".join(metrics["warnings"])
    assert (
        "4 of 460 scans dropped" in text and "message 50: field 'x' has unknown datatype 11" in text
    )
    assert "2 of 460 scans hold more data than their header describes (192 bytes ignored)" in text
    assert "1 scans stamped at or before" in text
    assert {"scans_malformed", "scan_bytes_ignored", "scans_out_of_order"} <= set(
        metrics["mapping"]["quality_flags"]
    )
    _assert_true_trees(pd.read_csv(tmp_path / "out" / "trees.csv"), metrics, clean)


@pytest.mark.parametrize(
    ("case", "edit", "says"),
    [
        (
            "half-width",
            messages.cloud_header(width=lambda w: w // 2, row_step=lambda r: r // 2),
            "hold more data than their header describes; first: message 0",
        ),
        ("clock-jump", messages.clock_jump(25.0, -15.0), "header stamps jump back"),
    ],
)
def test_header_that_lies_or_clock_that_jumps_is_a_clear_error(
    session, cli_server, tmp_path: Path, case: str, edit: messages.Edit, says: str
) -> None:
    """Before: 5 trees (half width) and 6 trees (15 s back) instead of 3. Now exit 2, early."""
    bag = messages.rewrite_bag(session.bag, tmp_path / case, edit)
    result = _run(cli_server, "run", str(bag), "--out", str(tmp_path / "out"))
    lines = result.stderr.strip().splitlines()
    assert (
        result.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"error: {bag}: topic '")
    ), result.stderr
    assert says in lines[0]
    assert not (tmp_path / "out" / "trees.csv").exists()


# -- topics -------------------------------------------------------------------------------------
def test_topic_chosen_among_two_is_named_and_reproduced_by_the_saved_config(
    session, cli_server, tmp_path: Path
) -> None:
    bag = messages.rewrite_bag(session.bag, tmp_path / "two", messages.second_cloud())
    first = _run(cli_server, "run", str(bag), "--out", str(tmp_path / "a"))
    assert first.returncode == 0, first.stderr
    metrics = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert any(
        "2 sensor_msgs/msg/PointCloud2 topics" in w and "read '/points'" in w
        for w in metrics["warnings"]
    )
    config = (tmp_path / "a" / "config.toml").read_text()
    assert 'pointcloud_topic = "/points"' in config and 'imu_topic = "/imu/data"' in config
    inputs = metrics["mapping"]["inputs"]
    assert (
        inputs["pointcloud"]["topic"] == "/points" and inputs["pointcloud"]["frame_id"] == "lidar"
    )
    assert inputs["pointcloud"]["used"] == 460 and inputs["imu"]["duration_s"] > 45
    # The report says which topic it chose among two (its config block names the topic
    # whatever happened: the warning is what shows the choice).
    assert "2 sensor_msgs/msg/PointCloud2 topics" in (tmp_path / "a" / "report.html").read_text()
    again = _run(
        cli_server,
        "run",
        str(bag),
        "--out",
        str(tmp_path / "b"),
        "--preset",
        str(tmp_path / "a" / "config.toml"),
    )
    assert again.returncode == 0, again.stderr
    assert (tmp_path / "b" / "trees.csv").read_bytes() == (
        tmp_path / "a" / "trees.csv"
    ).read_bytes()
    assert (
        json.loads((tmp_path / "b" / "metrics.json").read_text())["warnings"] == []
    )  # named: no choice


# -- batch ------------------------------------------------------------------------------------------
def test_batch_reports_input_faults_per_session_and_maps_the_nan_imu(
    session, tmp_path: Path
) -> None:
    """A session whose IMU has a NaN maps (with its warning); one whose PointCloud2 header lies
    fails alone, named with its stage and cause, without a retry or a killed worker."""
    from canopy_kit.pipeline.batch import load_manifest, run_batch

    nan = messages.rewrite_bag(session.bag, tmp_path / "nan", messages.imu_sample(4000, NAN_GYRO))
    lie = messages.rewrite_bag(
        session.bag,
        tmp_path / "lie",
        messages.cloud_header(width=lambda w: w // 2, row_step=lambda r: r // 2),
    )
    (tmp_path / "sessions.toml").write_text(
        'orchard = "row"\nreport = false\n'
        f'[[session]]\nid = "nan-imu"\nbag = "{nan}"\ndate = 2025-04-01\n'
        f'[[session]]\nid = "lying-header"\nbag = "{lie}"\ndate = 2025-04-02\n'
    )
    report = run_batch(load_manifest(tmp_path / "sessions.toml"), tmp_path / "out", n_workers=2)
    ok = report.outcomes["nan-imu"]
    assert ok.ok and ok.summary["n_trees"] == 3
    assert any("IMU samples dropped" in w for w in ok.summary["warnings"])
    assert set(report.failures) == {"lying-header"}
    error = report.failures["lying-header"]
    assert (
        error.startswith("InputError in stage 'mapping: odometry': ")
        and f"{lie}: topic '/points'" in error
    )
    assert "KilledWorker" not in error
    assert not (tmp_path / "out" / "sessions" / "lying-header" / "worker.log").exists()


def _crashing_worker() -> str:
    """Make this Dask worker's sessions die as a C++ assertion does (runs on the workers)."""
    import os as os_

    import canopy_kit.pipeline.batch as batch

    def crash(spec, config, out, progress=None):
        progress("mapping: odometry", 0, 1)
        os_.write(2, b"SOPHUS_ENSURE failed: R is not orthogonal\n")
        os_.abort()

    batch._run_one = crash
    return "patched"


def test_batch_worker_crash_is_reported_with_stage_and_signal_and_not_retried(
    session, tmp_path: Path
) -> None:
    """Before: Dask re-ran the session on 4 workers and said ``KilledWorker``, naming neither."""
    import logging

    from distributed import Client, LocalCluster

    from canopy_kit.pipeline.batch import load_manifest, run_batch

    (tmp_path / "sessions.toml").write_text(
        f'orchard = "row"\nreport = false\n[[session]]\nid = "crash"\nbag = "{session.bag}"\ndate = 2025-04-01\n'
    )
    with LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=logging.CRITICAL,
    ) as cluster:
        with Client(cluster) as client:
            client.run(_crashing_worker)
        report = run_batch(
            load_manifest(tmp_path / "sessions.toml"),
            tmp_path / "out",
            scheduler=cluster.scheduler_address,
            store="",
        )
    error = report.failures["crash"]
    assert (
        "SIGABRT during stage 'mapping: odometry'" in error and "SOPHUS_ENSURE failed" in error
    ), error
    assert str(session.bag) in error and "not run again" in error
    assert (tmp_path / "out" / "sessions" / "crash" / "worker.log").exists()  # the evidence stays
