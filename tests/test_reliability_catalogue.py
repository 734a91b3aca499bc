"""Every case of the bad-input catalogue through the command line a user runs.

Each case builds its input, runs ``canopy-kit`` in a process of its own and checks the
behaviour the catalogue promises: exit 2/3 with one ``error:`` line naming the input and the
problem, or exit 0 with a finite map, the warnings and the quality flags. Never a traceback.
The commands run two at a time (both cores) in one fixture; each case is its own test. Each
command runs in a child forked from a server that imported the library once (cli_server.py:
the console script's entry point, its own standard output, error and exit code), instead of
a new interpreter importing it again for each of the 85 commands (3-10 s each).
"""

from __future__ import annotations

import json
import queue
import re
import subprocess
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from bad_inputs.catalogue import CASES, Case
from cli_server import CliServer
from test_cli_foundation import cli_command

REPO = Path(__file__).resolve().parents[1]


Run = Callable[[list[str]], subprocess.CompletedProcess]


@pytest.fixture(scope="module")
def cli(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    """``run(args)``: ``canopy-kit args`` (COLUMNS=400), on whichever of two servers is free."""
    servers = [CliServer(tmp_path_factory.mktemp("cli"), env={"COLUMNS": "400"}) for _ in "ab"]
    free: queue.Queue[CliServer] = queue.Queue()
    for server in servers:
        free.put(server)

    def run(args: list[str]) -> subprocess.CompletedProcess:
        server = free.get()
        try:
            result = server.run(args, timeout=600)
        finally:
            free.put(server)
        return subprocess.CompletedProcess(
            [*cli_command(), *args], result.returncode, result.stdout, result.stderr
        )

    yield run
    for server in servers:
        server.close()


def _selected(request: pytest.FixtureRequest) -> list[Case]:
    """The cases whose tests this session runs (all when a test needs every outcome), so
    that ``-k las-`` does not map every bag first."""
    wanted = set()
    for item in request.session.items:
        if getattr(item, "module", None) is not request.module:
            continue  # other modules' tests may have a parameter called "case" too
        callspec = getattr(item, "callspec", None)
        case = callspec.params.get("case") if callspec is not None else None
        if isinstance(case, Case):
            wanted.add(case.id)
        elif "outcomes" in getattr(item, "fixturenames", ()):
            return list(CASES)
    return [c for c in CASES if c.id in wanted]


@pytest.fixture(scope="module")
def outcomes(
    tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest, cli: Run
) -> dict[str, tuple]:
    built = {}
    for case in _selected(request):
        root = tmp_path_factory.mktemp(case.id)
        built[case.id] = (root, *case.build(root))
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = {k: pool.submit(cli, args) for k, (_, args, _) in built.items()}
        return {k: (built[k][0], built[k][2], f.result()) for k, f in futures.items()}


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_catalogue_case(case: Case, outcomes: dict[str, tuple]) -> None:
    root, named, result = outcomes[case.id]
    report = f"exit {result.returncode}\nstdout: {result.stdout[-2000:]}\nstderr: {result.stderr[-3000:]}"
    assert "Traceback" not in result.stderr, report
    assert result.returncode == case.exit_code, report
    if case.exit_code:
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), report
        assert named in lines[0], f"{named!r} not named\n{report}"
        for fragment in case.expect:
            assert fragment in lines[0], f"{fragment!r} missing\n{report}"
        return
    if result.args[len(cli_command())] in CLOUD_COMMANDS:
        _check_cloud_result(case, result, report)
        return
    # A result: the mapping report carries the warnings and the quality flags.
    mapping = json.loads((root / "out" / "mapping.json").read_text())
    warnings = mapping["warnings"]
    for fragment in case.expect:
        assert any(fragment in w for w in warnings), f"{fragment!r} not warned: {warnings}"
        assert fragment in re.sub(r"\s+", " ", result.stdout), report  # and shown to the user
    flags = set(mapping["diagnostics"]["quality_flags"])
    assert set(case.flags) <= flags, flags
    assert not set(case.absent_flags) & flags, flags
    from canopy_kit.io.las import read_las

    cloud = read_las(root / "out" / "map.laz")
    assert len(cloud) > 10_000 and np.isfinite(cloud.xyz).all()
    assert not list((root / "out").glob(".*.tmp*"))


CLOUD_COMMANDS = ("info", "volume")  # read one point-cloud file: warnings on stderr or stdout


def _check_cloud_result(case: Case, result: subprocess.CompletedProcess[str], report: str) -> None:
    """A point-cloud file read with warnings: every stderr line is one ``warning:``, and the
    fragments (warnings, true bounds) are in what the user sees."""
    assert all(line.startswith("warning: ") for line in result.stderr.splitlines()), report
    shown = re.sub(r"\s+", " ", result.stdout + result.stderr)
    for fragment in case.expect:
        assert fragment in shown, f"{fragment!r} not shown\n{report}"
    assert not re.search(r"\b(nan|inf)\b", shown.lower()), report  # finite bounds and volumes


def test_clean_drive_has_no_warnings_or_flags(tmp_path: Path, cli: Run) -> None:
    """The fault-free drive maps without warnings: each flag above comes from its fault."""
    from bad_inputs.drives import write_drive

    drive = write_drive(tmp_path / "drive", duration=6.0)
    result = cli(["map", str(drive.path), "--out", str(tmp_path / "out"), "--no-plots"])
    assert result.returncode == 0, result.stderr
    mapping = json.loads((tmp_path / "out" / "mapping.json").read_text())
    assert mapping["warnings"] == [] and mapping["diagnostics"]["quality_flags"] == []
    assert mapping["diagnostics"]["sweeps_mapped"] == drive.n_scans


def test_corrupt_bytes_do_not_move_the_trajectory(
    outcomes: dict[str, tuple], tmp_path: Path, cli: Run
) -> None:
    """The damaged drives of ``bag-corrupt-bytes-*`` map like the undamaged drive: no silently
    wrong poses (before the fix one scrambled point time moved them by 2-2.6 m)."""
    import pandas as pd
    from bad_inputs.catalogue import _drive

    clean = _drive(tmp_path)
    result = cli(["map", str(clean), "--out", str(tmp_path / "out"), "--no-plots"])
    assert result.returncode == 0, result.stderr
    ref = pd.read_csv(tmp_path / "out" / "trajectory.csv")
    for fmt in ("ros1", "sqlite3", "mcap"):
        root = outcomes[f"bag-corrupt-bytes-{fmt}"][0]
        got = pd.read_csv(root / "out" / "trajectory.csv")
        both = pd.merge_asof(
            ref.sort_values("time"),
            got.sort_values("time"),
            on="time",
            direction="nearest",
            tolerance=0.02,
            suffixes=("", "_bad"),
        )
        assert both["x_bad"].notna().sum() >= len(ref) - 2, fmt  # a scan or two lost at most
        err = np.hypot(both["x"] - both["x_bad"], both["y"] - both["y_bad"])
        assert err.max() < 0.05, (fmt, float(err.max()))


def test_reliability_doc_lists_the_catalogue() -> None:
    text = (REPO / "docs" / "RELIABILITY.md").read_text()
    assert f"{len(CASES)} cases" in text
    missing = [c.id for c in CASES if f"`{c.id}`" not in text]
    assert not missing, missing
    assert len({c.id for c in CASES}) == len(CASES)


def test_reliability_doc_table_is_generated_from_the_catalogue() -> None:
    """docs/RELIABILITY.md holds exactly what scripts/reliability_doc.py makes of CASES."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "reliability_doc", REPO / "scripts" / "reliability_doc.py"
    )
    doc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(doc)
    text = (REPO / "docs" / "RELIABILITY.md").read_text()
    block = doc.catalogue_block(CASES)
    assert block in text, "docs/RELIABILITY.md is out of step: run scripts/reliability_doc.py"
    assert doc.render(text, block) == text
