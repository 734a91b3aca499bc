"""An interrupted ``canopy-kit run`` leaves no partial output, and the next run resumes.

1. SIGKILL from outside once the mapping stage is in the stage cache (a power cut mid-run):
   no output under a final name, every cache entry complete; the same command again reuses
   the cached mapping and writes the same ``trees.csv`` as an uninterrupted run.
2. SIGKILL at the moment an output file is about to be renamed onto its final name (the
   process kills itself inside ``os.replace``, so the moment is exact): the file is not
   under its final name, only as a hidden temporary; the files renamed before it are
   complete; the next run reuses every stage and writes the same ``trees.csv``.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_server import CliServer
from test_cli_foundation import cli_command

OUTPUTS = (
    "trees.csv",
    "trees.parquet",
    "trees.geojson",
    "map.laz",
    "trajectory.csv",
    "config.toml",
    "metrics.json",
    "report.html",
)


def _args(session, out: Path) -> list[str]:
    return [
        "run",
        str(session.bag),
        "--out",
        str(out),
        "--preset",
        "adaptive",
        "--truth",
        str(session.root),
    ]


def _finish(cli: CliServer, args: list[str]) -> subprocess.CompletedProcess:
    """The same command again, to its end (on the module's command server: conftest.py)."""
    result = cli.run(args, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    return result


def _visible(out: Path) -> set[str]:
    return {p.name for p in out.iterdir() if not p.name.startswith(".")}


def _check_cache_entries(out: Path) -> list[str]:
    """Every ``.pkl`` in the cache loads; the stages they hold."""
    stages = []
    for entry in sorted((out / ".cache").glob("*.pkl")):
        with entry.open("rb") as fh:
            pickle.load(fh)
        stages.append(entry.name.split("-")[0])
    return stages


@pytest.fixture(scope="module")
def reference_csv(tiny_pistachio_run) -> str:
    """``trees.csv`` of the uninterrupted run of the same command (conftest's cached run), as
    the run writes it (rounded: ``canopy_kit.io.csv_table``)."""
    from canopy_kit.io.csv_table import csv_text

    return csv_text(tiny_pistachio_run.trees)


def test_killed_after_mapping_leaves_no_output_and_resumes(
    tiny_pistachio, reference_csv, cli_server, tmp_path
):
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [*cli_command(), *_args(tiny_pistachio, out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    deadline = time.monotonic() + 600
    try:
        while not list((out / ".cache").glob("map-*.pkl")):
            assert proc.poll() is None, (
                f"run ended before the map was cached: {proc.stderr.read()[-3000:]}"
            )
            assert time.monotonic() < deadline, "no map stage in the cache after 600 s"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert not _visible(out), f"outputs of a run killed during segmentation: {_visible(out)}"
    assert "map" in _check_cache_entries(out)

    result = _finish(cli_server, _args(tiny_pistachio, out))
    metrics = json.loads((out / "metrics.json").read_text())
    ate = metrics["evaluation"]["mapping"]["ate_rmse_m"]
    assert (
        f"trajectory vs truth: ATE {ate:.3f} m" in result.stdout
    )  # printed, not only in the report
    assert "map" in metrics["cached_stages"]
    assert "map" not in metrics["stage_timings"]  # not recomputed
    assert {"segment", "volumes"} <= set(metrics["stage_timings"])
    assert (out / "trees.csv").read_text() == reference_csv
    assert set(OUTPUTS) <= _visible(out)
    assert not list(out.glob(".*.tmp*")), "temporary files left after a complete run"


# Runs the CLI with os.replace wrapped: SIGKILL to itself just before renaming onto ``target``.
_KILL_AT_RENAME = """
import os, signal, sys
from pathlib import Path
target = sys.argv.pop(1)
real = os.replace
def replace(src, dst, *a, **k):
    if Path(dst).name == target:
        os.kill(os.getpid(), signal.SIGKILL)
    return real(src, dst, *a, **k)
os.replace = replace
from canopy_kit.cli import main
sys.argv[0] = "canopy-kit"
main()
"""


@pytest.mark.parametrize("target", ["metrics.json", "report.html"])
def test_killed_while_writing_outputs_leaves_no_partial_file(
    target, tiny_pistachio, tiny_pistachio_run, reference_csv, cli_server, tmp_path
):
    out = tmp_path / "run"
    # Start from the reference run's stage cache: the killed run goes straight to the outputs.
    shutil.copytree(tiny_pistachio_run.out_dir / ".cache", out / ".cache")
    result = subprocess.run(
        [sys.executable, "-c", _KILL_AT_RENAME, target, *_args(tiny_pistachio, out)],
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert result.returncode == -signal.SIGKILL, result.stderr[-3000:]
    visible = _visible(out)
    assert target not in visible
    assert "trees.csv" in visible  # written (and renamed) before the kill
    leftovers = [p.name for p in out.glob(f".{target}.*.tmp*")]
    assert len(leftovers) == 1, list(out.iterdir())  # the complete file, never renamed
    # What is under a final name is whole.
    assert (out / "trees.csv").read_text() == reference_csv
    if "metrics.json" in visible:
        json.loads((out / "metrics.json").read_text())
    assert set(_check_cache_entries(out)) == {"map", "segment", "volumes"}

    _finish(cli_server, _args(tiny_pistachio, out))
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["cached_stages"]) == {"map", "segment", "volumes"}
    assert (out / "trees.csv").read_text() == reference_csv
    assert set(OUTPUTS) <= _visible(out)
