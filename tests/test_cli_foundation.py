"""The ``canopy-kit`` command as a user meets it: --help without heavy imports, none on
``import canopy_kit``, ``info`` on a LAZ and a bag, one-line errors with exit code 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from canopy_kit.core.cloud import PointCloud
from canopy_kit.io.bag_writer import BagWriter
from canopy_kit.io.las import write_las

HEAVY = ("open3d", "pycolmap", "pyvista")


def cli_command() -> list[str]:
    """The installed console script next to this interpreter, else the same entry via -c."""
    script = Path(sys.executable).with_name("canopy-kit")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "from canopy_kit.cli import main; main()"]


def run_cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*cli_command(), *args], check=False, capture_output=True, text=True, timeout=timeout
    )


def test_help_answers_without_loading_heavy_libraries() -> None:
    """``--help`` lists the commands and imports none of the heavy libraries (their import
    is what made it slow; a wall-clock limit here failed on loaded machines, so the
    property is checked instead of a time)."""
    result = run_cli("--help")
    assert result.returncode == 0, result.stderr
    assert "info" in result.stdout and "plugins" in result.stdout
    help_code = (
        "from typer.testing import CliRunner\n"
        "from canopy_kit.cli import app\n"
        "assert CliRunner().invoke(app, ['--help']).exit_code == 0\n"
    )
    assert heavy_modules_after(help_code) == []


def heavy_modules_after(code: str) -> list[str]:
    """The HEAVY modules loaded after running ``code`` in a fresh interpreter."""
    probe = (
        f"{code}\nimport sys, json\nprint(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], check=False, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_import_does_not_load_heavy_libraries() -> None:
    code = (
        "import canopy_kit, canopy_kit.cli, canopy_kit.io.clouds, canopy_kit.io.las\n"
        "import canopy_kit.io.open3d_clouds, canopy_kit.io.info, canopy_kit.io.bag\n"
    )
    assert heavy_modules_after(code) == []


def test_the_check_above_would_see_a_heavy_import() -> None:
    """Guard against a vacuous test: reading a PLY really does import open3d."""
    code = (
        "import numpy as np, tempfile, os\n"
        "from canopy_kit.core.cloud import PointCloud\n"
        "from canopy_kit.io.clouds import write_cloud\n"
        "d = tempfile.mkdtemp(); write_cloud(os.path.join(d, 'a.ply'), PointCloud(np.eye(3)))\n"
    )
    assert "open3d" in heavy_modules_after(code)


@pytest.fixture
def small_laz(tmp_path: Path) -> Path:
    rng = np.random.default_rng(5)
    cloud = PointCloud(
        np.round(rng.uniform(0, 50, (321, 3)), 3),
        {
            "intensity": rng.integers(0, 4000, 321).astype(np.uint16),
            "treeID": rng.integers(1, 9, 321).astype(np.float64),
        },
        crs="EPSG:32611",
        origin=np.array([400000.0, 4000000.0, 0.0]),
    )
    return write_las(tmp_path / "orchard.laz", cloud)


def test_info_on_laz(small_laz: Path) -> None:
    result = run_cli("info", str(small_laz))
    assert result.returncode == 0, result.stderr
    for text in ("321", "EPSG:32611", "treeID", "intensity", "LAZ", "bounds"):
        assert text in result.stdout
    as_json = run_cli("info", str(small_laz), "--json")
    facts = json.loads(as_json.stdout)
    assert facts["points"] == 321 and facts["crs"] == "EPSG:32611"
    assert {"name": "treeID", "dtype": "float64", "extra": True} in facts["attributes"]
    assert 400000.0 <= facts["bounds"]["min"][0] <= facts["bounds"]["max"][0] <= 400050.0


@pytest.mark.parametrize("fmt", ["ros1", "ros2-mcap"])
def test_info_on_bag(tmp_path: Path, fmt: str) -> None:
    with BagWriter(tmp_path / "drive", fmt) as w:
        for k in range(3):
            w.write_points(
                "/lidar/points",
                10.0 + k * 0.1,
                {
                    "x": np.zeros(5, np.float32),
                    "y": np.ones(5, np.float32),
                    "z": np.full(5, 2, np.float32),
                },
            )
        for k in range(7):
            w.write_imu("/imu", 10.0 + k * 0.05, (0, 0, 0), (0, 0, 9.81))
    result = run_cli("info", str(w.path), "--json")
    assert result.returncode == 0, result.stderr
    facts = json.loads(result.stdout)
    topics = {t["name"]: (t["type"], t["count"]) for t in facts["topics"]}
    assert topics == {
        "/lidar/points": ("sensor_msgs/msg/PointCloud2", 3),
        "/imu": ("sensor_msgs/msg/Imu", 7),
    }
    assert facts["duration_s"] == pytest.approx(0.3, abs=1e-6)
    table = run_cli("info", str(w.path))
    assert table.returncode == 0 and "/lidar/points" in table.stdout and "topics" in table.stdout


@pytest.mark.parametrize("kind", ["missing", "empty", "not a cloud"])
def test_info_bad_input_is_one_line_exit_2(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "input.laz"
    if kind == "empty":
        path.touch()
    elif kind == "not a cloud":
        path.write_text("hello")
    result = run_cli("info", str(path))
    assert result.returncode == 2
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ") and str(path) in lines[0]
    assert "Traceback" not in result.stderr


def test_usage_error_exits_2() -> None:
    result = run_cli("info")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr


def test_unexpected_failure_is_one_line_exit_3(monkeypatch, capsys) -> None:
    """A bug inside a command gives one ``error:`` line and exit 3, the traceback on request."""
    import canopy_kit.cli as cli

    def broken() -> None:
        raise ZeroDivisionError("division by zero in a stage")

    monkeypatch.setattr(cli, "app", broken)
    monkeypatch.delenv("CANOPY_KIT_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: processing failed (ZeroDivisionError")
    monkeypatch.setenv("CANOPY_KIT_DEBUG", "1")
    with pytest.raises(ZeroDivisionError):
        cli.main()


def test_a_library_message_with_escapes_and_lines_is_printed_as_one_plain_line(
    monkeypatch, capsys
) -> None:
    """Open3D and other C++ libraries write coloured, multi-line text; the CLI prints one line."""
    import canopy_kit.cli as cli
    from canopy_kit.errors import InputError

    def failing() -> None:
        raise InputError(
            "tree.ply: \x1b[1;31m[Open3D WARNING]\x1b[0m Read PLY failed:\n"
            "  unable to read file: /src/io/FilePLY.cpp:42"
        )

    monkeypatch.setattr(cli, "app", failing)
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err == (
        "error: tree.ply: [Open3D WARNING] Read PLY failed: unable to read file: "
        "/src/io/FilePLY.cpp:42\n"
    )


def test_version_and_help_name_what_is_shipped() -> None:
    from canopy_kit import __version__
    from canopy_kit.config import preset_names

    version = run_cli("--version")
    assert version.returncode == 0 and version.stdout.strip() == f"canopy-kit {__version__}"
    for command in ("run", "segment"):
        text = " ".join(run_cli(command, "--help").stdout.split())
        assert all(name in text for name in preset_names()), text
    assert "[[session]]" in " ".join(run_cli("batch", "--help").stdout.split())
