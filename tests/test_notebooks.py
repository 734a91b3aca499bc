"""Every notebook runs headless as a plain script on a small simulated session."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import REPO

NOTEBOOKS = sorted((REPO / "notebooks").glob("*.py"))
SESSION_NOTEBOOKS = [
    "explore_session.py",
    "segmentation.py",
    "volumes.py",
    "mapping.py",
    "aerial_truth.py",
]


def _run(path, *args):
    return subprocess.run(
        [sys.executable, str(path), "--", *args],
        check=False,
        capture_output=True,
        text=True,
        timeout=900,
        cwd=REPO,
    )


def test_every_notebook_is_covered():
    known = set(SESSION_NOTEBOOKS) | {"paper_reproduction.py", "orchard_over_time.py"}
    assert {p.name for p in NOTEBOOKS} <= known, "add new notebooks to tests/test_notebooks.py"


@pytest.mark.slow
@pytest.mark.parametrize("name", SESSION_NOTEBOOKS)
def test_session_notebook_runs(name, tiny_pistachio, tiny_pistachio_run):
    args = (
        ["--bag", str(tiny_pistachio.bag)]
        if name == "explore_session.py"
        else ["--session", str(tiny_pistachio.root), "--run", str(tiny_pistachio_run.out_dir)]
    )
    result = _run(REPO / "notebooks" / name, *args)
    assert result.returncode == 0, result.stderr[-3000:]


def test_paper_notebook_runs():
    result = _run(REPO / "notebooks" / "paper_reproduction.py")
    assert result.returncode == 0, result.stderr[-3000:]


def test_orchard_notebook_runs():  # without --store it makes a small synthetic store
    result = _run(REPO / "notebooks" / "orchard_over_time.py")
    assert result.returncode == 0, result.stderr[-3000:]
