"""Issue 48: every user mistake is exit code 2 and one line, a refused run leaves nothing
behind, Ctrl-C says what was kept, help texts read cleanly at any width, and ``info`` says
when ``run`` cannot use a bag."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
from test_cli_foundation import run_cli

from canopy_kit.io.bag_writer import BagWriter


# -- helpers ----------------------------------------------------------------------------------
def cli(monkeypatch, capsys, *args: object) -> tuple[int, str, str]:
    """``canopy-kit ARGS`` in this process through the console script's ``main``: (exit
    code, stdout, stderr). In-process so a test can monkeypatch a stage."""
    from canopy_kit.cli import main

    monkeypatch.setattr(sys, "argv", ["canopy-kit", *map(str, args)])
    monkeypatch.delenv("CANOPY_KIT_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_info:
        main()
    out = capsys.readouterr()
    return exit_info.value.code, out.out, out.err


def one_error_line(err: str) -> str:
    """The one ``error:`` line of stderr (and nothing else on it, not even an empty line)."""
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


@pytest.fixture
def imu_bag(tmp_path: Path) -> Path:
    """A ROS1 bag with an IMU topic only: no LiDAR for ``run`` or ``map``."""
    with BagWriter(tmp_path / "imu_only", "ros1") as w:
        for k in range(7):
            w.write_imu("/imu", 10.0 + k * 0.05, (0, 0, 0), (0, 0, 9.81))
    return Path(w.path)


@pytest.fixture
def lidar_bag(tmp_path: Path) -> Path:
    with BagWriter(tmp_path / "drive", "ros2-mcap") as w:
        for k in range(3):
            xyz = {c: np.full(5, v, np.float32) for c, v in zip("xyz", (0, 1, 2), strict=True)}
            w.write_points("/lidar/points", 10.0 + k * 0.1, xyz)
        w.write_imu("/imu", 10.0, (0, 0, 0), (0, 0, 9.81))
    return Path(w.path)


@pytest.fixture
def a_file(tmp_path: Path) -> Path:
    path = tmp_path / "results"
    path.write_text("a file the user has\n")
    return path


@pytest.fixture
def no_heavy_work(monkeypatch):
    """Every long job a command could start fails the test: the check must come first."""
    import canopy_kit.paper.experiments as experiments
    import canopy_kit.pipeline as pipeline
    import canopy_kit.sim as sim

    def must_not_run(*_a, **_k):
        raise AssertionError("a long job started before the output was checked")

    monkeypatch.setattr(experiments, "run_experiments", must_not_run)
    monkeypatch.setattr(pipeline, "run", must_not_run)
    monkeypatch.setattr(sim, "simulate_session", must_not_run)


# -- 1. an output path of the wrong kind ------------------------------------------------------
def _commands_with_outputs(tmp_path: Path, bag: Path, a_file: Path) -> dict[str, list]:
    photos = tmp_path / "photos"
    photos.mkdir()
    manifest = tmp_path / "sessions.toml"
    manifest.write_text(
        f'[[session]]\nid = "a"\nbag = "{bag}"\norchard = "o"\ndate = "2024-05-01"\n'
    )
    cloud = tmp_path / "map.laz"
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.io.las import write_las

    write_las(cloud, PointCloud(np.random.default_rng(1).uniform(0, 10, (200, 3))))
    return {
        "run": ["run", bag, "--out", a_file],
        "run --stream": ["run", bag, "--stream", "--out", a_file],
        "segment": ["segment", cloud, "--out", a_file],
        "map": ["map", bag, "--out", a_file],
        "ground-truth": ["ground-truth", photos, "--out", a_file],
        "simulate": ["simulate", a_file],
        "demo": ["demo", "--out", a_file],
        "batch": ["batch", manifest, "--out", a_file],
        "paper experiments": ["paper", "experiments", "--out", a_file],
        "paper experiments --work": [
            "paper", "experiments", "--out", tmp_path / "new", "--work", a_file,
        ],
    }  # fmt: skip


COMMANDS = [
    "run",
    "run --stream",
    "segment",
    "map",
    "ground-truth",
    "simulate",
    "demo",
    "batch",
    "paper experiments",
    "paper experiments --work",
]


@pytest.mark.parametrize("command", COMMANDS)
def test_an_output_folder_that_is_a_file_is_one_line_exit_2(
    command, lidar_bag, a_file, tmp_path, monkeypatch, capsys, no_heavy_work
) -> None:
    args = _commands_with_outputs(tmp_path, lidar_bag, a_file)[command]
    code, out, err = cli(monkeypatch, capsys, *args)
    assert code == 2, err
    line = one_error_line(err)
    assert str(a_file) in line and "is a file, not a folder" in line, line
    assert "processing failed" not in line and "report" not in line
    assert out == ""
    assert a_file.read_text() == "a file the user has\n"  # untouched


def test_a_file_above_the_output_folder_is_named(lidar_bag, a_file, monkeypatch, capsys) -> None:
    code, _, err = cli(monkeypatch, capsys, "run", lidar_bag, "--out", a_file / "run" / "one")
    assert code == 2
    line = one_error_line(err)
    assert f"{a_file} is a file, so no folder can be made in it" in line, line


def test_store_outputs_of_the_wrong_kind(tmp_path, a_file, monkeypatch, capsys) -> None:
    folder = tmp_path / "a_folder"
    folder.mkdir()
    code, _, err = cli(monkeypatch, capsys, "store", "export", tmp_path / "x.duckdb", folder)
    assert code == 2 and f"{folder}: this is a folder, not a file" in one_error_line(err)
    target = a_file / "growth.csv"
    code, _, err = cli(monkeypatch, capsys, "store", "export", tmp_path / "x.duckdb", target)
    assert code == 2 and f"{a_file} is a file" in one_error_line(err)


def test_a_path_error_the_command_could_not_foresee_is_exit_2(monkeypatch, capsys) -> None:
    """An OSError about a path's kind or permissions names the path: exit 2, not 'report it'."""
    import canopy_kit.cli as cli_module

    def denied() -> None:
        raise PermissionError(13, "Permission denied", "/srv/orchard/out")

    monkeypatch.setattr(cli_module, "app", denied)
    with pytest.raises(SystemExit) as exit_info:
        cli_module.main()
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == "error: /srv/orchard/out: Permission denied\n"


def test_a_negative_sfm_thread_count_names_the_option(
    lidar_bag, tmp_path, monkeypatch, capsys
) -> None:
    """``run --sfm-threads -1`` is refused by the option itself (exit 2, naming
    ``--sfm-threads``), before any folder is made."""
    out = tmp_path / "run"
    code, _, err = cli(
        monkeypatch, capsys, "run", lidar_bag, "--out", out, "--drone-images", tmp_path,
        "--sfm-threads", -1,
    )  # fmt: skip
    assert code == 2 and "--sfm-threads" in err, err
    assert not out.exists()


# -- 2. a refused run leaves nothing behind ---------------------------------------------------
@pytest.mark.parametrize("stream", [False, True])
def test_a_refused_run_leaves_no_folder(imu_bag, tmp_path, stream) -> None:
    out = tmp_path / "new" / "run"
    args = ["run", str(imu_bag), "--out", str(out)] + (["--stream"] if stream else [])
    result = run_cli(*args)
    assert result.returncode == 2, result.stderr
    line = one_error_line(result.stderr)  # no empty line from a progress display either
    assert str(imu_bag) in line and "PointCloud2" in line
    assert result.stdout == ""
    assert not (tmp_path / "new").exists()  # nor the parent it made for it


def test_a_refused_ground_truth_leaves_no_folder(tmp_path, monkeypatch, capsys) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    out = tmp_path / "aerial"
    code, _, err = cli(monkeypatch, capsys, "ground-truth", photos, "--out", out)
    assert code == 2 and "JPEG" in one_error_line(err)
    assert not out.exists()


@pytest.mark.parametrize("stream", [False, True])
def test_a_refused_run_keeps_an_existing_folder_and_what_it_holds(
    imu_bag, tmp_path, monkeypatch, capsys, stream
) -> None:
    out = tmp_path / "mine"
    (out / "notes").mkdir(parents=True)
    (out / "notes" / "field.txt").write_text("row 3 replanted\n")
    (out / "empty").mkdir()
    args = ["run", imu_bag, "--out", out] + (["--stream"] if stream else [])
    code, _, err = cli(monkeypatch, capsys, *args)
    assert code == 2 and "PointCloud2" in one_error_line(err)
    assert sorted(p.name for p in out.iterdir()) == ["empty", "notes"]  # no .cache left
    assert (out / "notes" / "field.txt").read_text() == "row 3 replanted\n"


# -- 3. Ctrl-C says what was kept -------------------------------------------------------------
def _interrupt(*_a, **_k):
    raise KeyboardInterrupt


def test_interrupt_before_anything_is_written(imu_bag, tmp_path, monkeypatch, capsys) -> None:
    import canopy_kit.pipeline as pipeline

    monkeypatch.setattr(pipeline, "map_stage", _interrupt)
    out = tmp_path / "run"
    code, _, err = cli(monkeypatch, capsys, "run", imu_bag, "--out", out)
    assert code == 130
    assert err == "interrupted: nothing was written\n"
    assert not out.exists()


def test_interrupt_names_what_was_kept(imu_bag, tmp_path, monkeypatch, capsys) -> None:
    """Stopped in segmentation: the mapping's cache entry stays (the same command resumes
    from it) and the line says so; no temporary file is left."""
    import canopy_kit.pipeline as pipeline

    monkeypatch.setattr(pipeline, "map_stage", lambda *_a, **_k: {"a": "picklable map"})
    monkeypatch.setattr(pipeline, "segment_stage", _interrupt)
    out = tmp_path / "run"
    code, _, err = cli(monkeypatch, capsys, "run", imu_bag, "--out", out)
    assert code == 130
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"interrupted: kept in {out}: .cache/ (cached stages map")
    assert len(list((out / ".cache").glob("map-*.pkl"))) == 1
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


def test_interrupt_keeps_an_existing_folder(imu_bag, tmp_path, monkeypatch, capsys) -> None:
    import canopy_kit.pipeline as pipeline

    monkeypatch.setattr(pipeline, "map_stage", _interrupt)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me\n")
    code, _, err = cli(monkeypatch, capsys, "run", imu_bag, "--out", out)
    assert code == 130
    assert err == f"interrupted: nothing was written in {out}\n"
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    assert (out / "notes.txt").read_text() == "keep me\n"


def test_interrupt_of_a_command_that_writes_nothing(lidar_bag, monkeypatch, capsys) -> None:
    import canopy_kit.io.info as io_info

    monkeypatch.setattr(io_info, "describe_path", _interrupt)
    code, out, err = cli(monkeypatch, capsys, "info", lidar_bag)
    assert code == 130 and err == "interrupted: nothing was written\n" and out == ""


def test_an_interrupted_atomic_write_leaves_no_temporary(tmp_path, monkeypatch) -> None:
    """Ctrl-C inside the write, and between the temporary's creation and its use: the old
    file stays, no temporary is left."""
    from canopy_kit.core.atomic import atomic_path

    path = tmp_path / "trees.csv"
    path.write_text("old\n")
    with pytest.raises(KeyboardInterrupt), atomic_path(path) as tmp:
        tmp.write_text("half")
        raise KeyboardInterrupt
    real_close = os.close

    def close_then_interrupt(fd: int) -> None:
        real_close(fd)
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "close", close_then_interrupt)
    with pytest.raises(KeyboardInterrupt), atomic_path(path):
        pass
    monkeypatch.setattr(os, "close", real_close)
    assert [p.name for p in tmp_path.iterdir()] == ["trees.csv"]
    assert path.read_text() == "old\n"


# -- 4. help texts ----------------------------------------------------------------------------
def _command_paths() -> list[list[str]]:
    import typer

    from canopy_kit.cli import app

    paths = [[]]

    def walk(command, prefix: list[str]) -> None:
        if hasattr(command, "commands"):  # a group (typer's own click: no isinstance)
            for name, sub in command.commands.items():
                paths.append([*prefix, name])
                walk(sub, [*prefix, name])

    walk(typer.main.get_command(app), [])
    return paths


def _description(text: str) -> list[list[str]]:
    """The paragraphs of a help page's prose (after Usage, before the first section)."""
    lines = text.splitlines()
    prose = []
    for line in lines[1:]:
        if line and not line.startswith(" "):  # "Arguments:", "Options:", "Commands:"
            break
        prose.append(line)
    paragraphs, current = [], []
    for line in prose:
        if line.strip():
            current.append(line)
        elif current:
            paragraphs.append(current)
            current = []
    return paragraphs + ([current] if current else [])


@pytest.mark.parametrize("columns", [60, 80, 120])
def test_help_texts_read_cleanly_at_any_width(columns: int, monkeypatch, capsys) -> None:
    """Every command's help at COLUMNS=60/80/120 (through main: typer's CliRunner forces 80)."""
    monkeypatch.setenv("COLUMNS", str(columns))
    width = max(min(columns, 80) - 2, 50)  # click's help width
    paths = _command_paths()
    assert ["ground-truth"] in paths and ["paper", "experiments"] in paths
    for path in paths:
        code, text, err = cli(monkeypatch, capsys, *path, "--help")
        name = " ".join(["canopy-kit", *path])
        assert code == 0 and not err, (name, err)
        assert "`" not in text, f"{name}: RST/markdown backticks in the help"
        assert "\\[" not in text and "[/" not in text, f"{name}: markup in the help"
        if "Commands:" in text:  # each summary whole, not cut with "..."
            assert "..." not in text.split("Commands:")[1], name
        for line in text.splitlines():
            assert len(line) <= columns, f"{name} at {columns} columns: {line!r}"
        for paragraph in _description(text):
            for line, following in zip(paragraph, paragraph[1:], strict=False):
                word = following.split()[0]
                assert len(line) + 1 + len(word) > width, (
                    f"{name} at {columns} columns breaks mid-sentence after {line!r}"
                )


def test_help_shows_square_brackets_as_written() -> None:
    ground_truth = " ".join(run_cli("ground-truth", "--help").stdout.split())
    assert "its [ground_truth] table is used" in ground_truth
    assert "TOML ([[session]] tables)" in " ".join(run_cli("batch", "--help").stdout.split())


def test_the_command_list_shows_whole_summaries() -> None:
    """click cut each summary at 45 characters or at the first full stop ('Abedi et al.')."""
    text = " ".join(run_cli("--help").stdout.split("Commands:")[1].split())
    assert "Reproduce the results of Abedi et al. 2025 (Table I; experiments on" in text
    assert "..." not in text


# -- 5. info says when run cannot use a bag ---------------------------------------------------
def test_info_says_run_cannot_use_a_bag_without_lidar(imu_bag) -> None:
    result = run_cli("info", str(imu_bag))
    assert result.returncode == 0, result.stderr
    last = result.stdout.strip().splitlines()[-1]
    assert last.startswith("canopy-kit run cannot use this bag: it has no LiDAR topic"), last
    assert "sensor_msgs/msg/PointCloud2" in last and "VelodyneScan" in last


def test_info_has_no_such_line_for_a_bag_with_lidar(lidar_bag, monkeypatch, capsys) -> None:
    code, out, _ = cli(monkeypatch, capsys, "info", lidar_bag)
    assert code == 0 and "/lidar/points" in out and "cannot use" not in out


def test_info_says_one_sweep_is_too_few(tmp_path) -> None:
    from canopy_kit.cli.info import why_run_cannot_use

    facts = {
        "kind": "bag",
        "lidar_topic": "/points",
        "topics": [{"name": "/points", "type": "sensor_msgs/msg/PointCloud2", "count": 1}],
    }
    assert why_run_cannot_use(facts) == (
        "its LiDAR topic /points has 1 message; mapping needs at least 2 sweeps"
    )
    assert why_run_cannot_use({"kind": "cloud"}) is None
