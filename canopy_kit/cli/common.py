"""Helpers shared by CLI commands: console, progress bars, JSON output."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import typer
from rich.console import Console


def preset_help(extra: str = "") -> str:
    """The ``--preset`` help with the shipped presets' names (read from the package)."""
    from canopy_kit.config import preset_names

    return f"Preset name ({', '.join(preset_names())}) or TOML file{extra}"


RIG_OPTION = typer.Option(
    None,
    "--rig",
    help="Rig file (TOML: sensor frames and mounts) or shipped rig; "
    "gives or overrides the bag's /tf_static (docs/MAPPING.md, 'Sensor rigs')",
)
ASSUME_IDENTITY_OPTION = typer.Option(
    False,
    "--assume-identity-extrinsics",
    help="Take the LiDAR's and the IMU's frames for one when nothing relates them",
)
CALIBRATE_OPTION = typer.Option(
    False,
    "--calibrate-extrinsics",
    help="Estimate the IMU's mount from the drive and map with it (one more odometry pass)",
)


def make_console(**kwargs: Any) -> Console:
    """A stdout console: on a terminal lines wrap at its width; piped or redirected they
    stay whole, for logs and grep (tables: :mod:`canopy_kit.cli.tables`)."""
    con = Console(**kwargs)
    con.soft_wrap = not con.is_terminal
    return con


console = make_console()
err_console = Console(stderr=True)

ProgressCallback = Callable[[str, float, float], None]


@contextmanager
def progress_bar(transient: bool = False) -> Iterator[ProgressCallback]:
    """A rich progress display; yields a ``callback(task, done, total)`` for the library."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    tasks: dict[str, Any] = {}
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=transient,
    ) as progress:

        def callback(task: str, done: float, total: float) -> None:
            if task not in tasks:
                tasks[task] = progress.add_task(task, total=total or None)
            progress.update(tasks[task], completed=done, total=total or None)

        yield callback


def print_json(data: Any) -> None:
    """Print data as indented JSON on stdout (numpy scalars converted)."""
    from canopy_kit.io.atomic import to_json

    print(to_json(data), end="")


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["orchard.rows=3", "lidar.rings=16"]`` to a nested dict; values parsed as TOML."""
    import tomllib

    from canopy_kit.errors import ConfigError

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected section.key=value")
        try:
            value = tomllib.loads(f"v = {raw.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw.strip()
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out
