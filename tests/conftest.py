"""Shared fixtures: small simulated sessions, made once per test run and cached."""

from __future__ import annotations

import fcntl
import os
import pickle
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("CANOPY_KIT_SHARED_DATA", REPO.parent / "shared" / "data"))

# A small but complete session: U-turns, every alley, the default 32-ring sensor at a
# reduced horizontal resolution to keep the suite fast.
TINY = {"orchard": {"rows": 2, "trees_per_row": 3}, "lidar": {"columns": 512}}
# The smallest session that still has a U-turn: for format and determinism checks.
MICRO = {"orchard": {"rows": 1, "trees_per_row": 2}, "lidar": {"columns": 256, "rings": 16}}
# sim_factory keys (orchard, format, seed, repr(overrides), truth field, sensor) of sessions
# that many files use: simulated once per test run, shared by every xdist worker.
SHARED_SESSIONS = {("pistachio", "ros2-mcap", 0, repr(TINY), True, None): "tiny_pistachio"}
# TINY with a drone flight (12 photos): the session and the adaptive run with its photos,
# made once per test run for every file that needs them (the SfM is most of the time).
TINY_DRONE = {**TINY, "drone": {"enabled": True}}
TINY_DRONE_SEED = 4


# Each test file's seconds (setup + call + teardown of its tests, one worker) as last
# measured: ``make test-durations`` rewrites it. The longest files go first, so that with one
# file per worker (make test: --dist loadfile, --no-loadscope-reorder) no worker is left
# finishing a long file after the others are done; a file not yet measured counts as the
# median one.
FILE_SECONDS = Path(__file__).with_name("file_seconds.json")
_seconds_by_file: dict[str, float] = {}


def pytest_addoption(parser):
    parser.addoption(
        "--record-file-seconds",
        metavar="PATH",
        help="write each test file's seconds (setup + call + teardown) to PATH as JSON",
    )


def pytest_collection_modifyitems(config, items):
    import json
    import statistics

    seconds = json.loads(FILE_SECONDS.read_text())["seconds"] if FILE_SECONDS.exists() else {}
    typical = statistics.median(seconds.values()) if seconds else 0.0

    def longest_first(item) -> tuple[float, str]:
        name = item.path.relative_to(REPO).as_posix()
        return (-seconds.get(name, typical), name)

    items.sort(key=longest_first)  # stable: the order within a file is kept


def pytest_sessionfinish(session, exitstatus):
    path = session.config.getoption("--record-file-seconds")
    if path and not hasattr(session.config, "workerinput"):  # the controller has every report
        import json

        ranked = dict(sorted(_seconds_by_file.items(), key=lambda kv: -kv[1]))
        record = {
            "how": "make test-durations (tests/conftest.py --record-file-seconds)",
            "seconds": {name: round(s, 1) for name, s in ranked.items()},
        }
        tmp = Path(path).with_suffix(".tmp")
        tmp.write_text(json.dumps(record, indent=1) + "\n")
        tmp.replace(path)


# Disk: simulated sessions are 20-160 MB each and the suite makes dozens (5.4 GB by the end
# when every folder was kept, and a CI machine once ran out of space). Each test file's
# temporary folders are removed when the file is done, unless one of its tests failed;
# folders of session-wide fixtures (``_KEPT``, and those every worker shares: shared_base)
# stay for the whole run.
_KEPT: set[Path] = set()
_FAILED_FILES: set[str] = set()


def pytest_runtest_logreport(report):
    name = report.nodeid.split("::")[0]
    _seconds_by_file[name] = _seconds_by_file.get(name, 0.0) + report.duration
    if report.failed:
        _FAILED_FILES.add(name)


@pytest.fixture(scope="module", autouse=True)
def _free_disk_after_each_file(request, tmp_path_factory, sim_factory):
    """Remove the temporary folders a test file made once it is done (kept if it failed)."""
    base = tmp_path_factory.getbasetemp()
    before = set(base.iterdir())
    yield
    if request.node.nodeid in _FAILED_FILES:
        return
    for path in set(base.iterdir()) - before - _KEPT:
        shutil.rmtree(path, ignore_errors=True)
    sim_factory.forget_removed()


@pytest.fixture(scope="session")
def sim_factory(tmp_path_factory):
    """``make(orchard, fmt="ros2-mcap", seed=0, **overrides) -> SimulatedSession`` (cached)."""
    from canopy_kit.config import merge
    from canopy_kit.sim import load_sim_config, simulate_session

    cache: dict = {}

    def make(
        orchard: str = "pistachio",
        fmt: str = "ros2-mcap",
        seed: int = 0,
        overrides: dict | None = None,
        truth_field: bool = True,
        sensor: str | None = None,
    ):
        key = (orchard, fmt, seed, repr(overrides), truth_field, sensor)
        if key not in cache:
            cfg = load_sim_config(orchard, merge({"seed": seed}, overrides or {}), sensor=sensor)
            if key in SHARED_SESSIONS:  # made once for every worker
                cache[key] = shared_object(
                    tmp_path_factory,
                    SHARED_SESSIONS[key],
                    lambda folder: simulate_session(
                        folder / "sim", cfg, fmt=fmt, truth_field=truth_field
                    ),
                )
            else:
                out = tmp_path_factory.mktemp(f"sim_{orchard}_{seed}")
                cache[key] = simulate_session(
                    out, cfg, fmt=fmt, truth_field=truth_field, overwrite=True
                )
        return cache[key]

    def forget_removed() -> None:
        """Drop cached sessions whose folder was removed (they are made again if asked for)."""
        for key in [k for k, session in cache.items() if not Path(session.root).exists()]:
            del cache[key]

    make.forget_removed = forget_removed
    return make


@pytest.fixture(scope="session")
def tiny_pistachio(sim_factory):
    """A 2-row x 3-tree pistachio session (ROS2 mcap, truth field on), made once per test
    run for every worker (read only)."""
    return sim_factory("pistachio", overrides=TINY)


@pytest.fixture(scope="module")
def cli_server(tmp_path_factory) -> Iterator[Any]:
    """A ``canopy-kit`` command server for one test file (tests/cli_server.py: each command
    runs in a process forked from one that imported the library once; COLUMNS=400), for files
    whose commands would otherwise spend seconds each importing it."""
    from cli_server import CliServer

    server = CliServer(tmp_path_factory.mktemp("cli"), env={"COLUMNS": "400"})
    yield server
    server.close()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The public data folder (skips the test when it is absent)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} not present")
    return SHARED_DATA


@pytest.fixture(scope="session")
def tiny_pistachio_run(tiny_pistachio, tmp_path_factory):
    """The adaptive pipeline run on ``tiny_pistachio``, checked against its truth, made once
    per test run for every worker (read only: a test that writes runs into its own folder)."""
    from canopy_kit.config import load_preset
    from canopy_kit.pipeline import run

    def build(folder: Path):
        return run(
            load_preset("adaptive"), tiny_pistachio.bag, folder / "run", truth=tiny_pistachio.root
        )

    return shared_object(tmp_path_factory, "tiny_pistachio_run", build)


# -- made once per test run, shared by every xdist worker --------------------------------------
def shared_base(tmp_path_factory) -> Path:
    """A folder every worker of this test run sees, in the run's base temporary folder (each
    xdist worker's own base is a subfolder of it, emptied file by file); without xdist, in
    this process's base, kept for the whole run."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return base.parent / "shared"
    _KEPT.add(base / "shared")  # kept when each file's folders are removed
    return base / "shared"


@contextmanager
def _exclusive(lock: Path) -> Iterator[None]:
    with lock.open("a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def built_once(folder: Path, build: Callable[[Path], None]) -> Path:
    """``folder`` as ``build(folder)`` makes it, built by the first worker that asks while the
    others wait on a file lock; a build that failed leaves no folder behind, so the next
    worker tries again (and fails the same way, in its own test)."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    done = folder / ".built"
    with _exclusive(folder.with_name(f".{folder.name}.lock")):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            try:
                build(folder)
            except BaseException:
                shutil.rmtree(folder, ignore_errors=True)
                raise
            done.touch()
    return folder


def shared_object(tmp_path_factory, name: str, make: Callable[[Path], Any]) -> Any:
    """What ``make(folder)`` returns (a simulated session, a run's results: files in
    ``folder`` and the object naming them), made once per test run for every worker and
    handed to each as a pickled copy."""

    def build(folder: Path) -> None:
        (folder / "object.pickle").write_bytes(pickle.dumps(make(folder)))

    folder = built_once(shared_base(tmp_path_factory) / name, build)
    return pickle.loads((folder / "object.pickle").read_bytes())


@dataclass(frozen=True)
class SharedDroneSession:
    """A simulated session with a drone flight (``root``, ``bag``, ``drone_dir``: read only)
    and the adaptive pipeline run on it with its photos (``run_dir``, its stage cache too)."""

    root: Path
    bag: Path
    drone_dir: Path
    run_dir: Path

    def run_into(self, out: Path):
        """``canopy_kit.pipeline.run`` of the adaptive preset on this session with its photos
        into ``out``, starting from a copy of the shared run's folder: every stage comes from
        its cache (the same keys: the same bag, photos and preset), every output is written
        anew."""
        from canopy_kit.config import load_preset
        from canopy_kit.pipeline import run

        shutil.copytree(self.run_dir, out, dirs_exist_ok=True)
        return run(
            load_preset("adaptive"), self.bag, out, drone_images=self.drone_dir, sfm_threads=1
        )


@pytest.fixture(scope="session")
def tiny_drone_session(tmp_path_factory) -> SharedDroneSession:
    """The 2 x 3 pistachio session with a drone flight (seed 4) and its adaptive run, made
    once per test run and shared by every worker (the run's SfM is most of the time)."""

    def build(folder: Path) -> None:
        from canopy_kit.config import load_preset, merge
        from canopy_kit.pipeline import run
        from canopy_kit.sim import load_sim_config, simulate_session

        cfg = load_sim_config("pistachio", merge({"seed": TINY_DRONE_SEED}, TINY_DRONE))
        sim = simulate_session(folder / "sim", cfg)
        # SfM on one thread: the same reconstruction in every test run (COLMAP's several
        # threads do not repeat bit for bit)
        run(
            load_preset("adaptive"),
            sim.bag,
            folder / "run",
            drone_images=sim.drone_dir,
            sfm_threads=1,
        )

    folder = built_once(shared_base(tmp_path_factory) / "tiny_drone_session", build)
    sim = folder / "sim"
    bag = next(p for p in sim.iterdir() if p.name.startswith("session"))
    return SharedDroneSession(sim, bag, sim / "drone", folder / "run")
