"""Helpers shared by CLI commands: console, progress bars, JSON output, output folders."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
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
err_console = make_console(stderr=True)

ProgressCallback = Callable[[str, float, float], None]


@contextmanager
def progress_bar(transient: bool = False) -> Iterator[ProgressCallback]:
    """A rich progress display; yields a ``callback(task, done, total)`` for the library.

    ``transient``: cleared when done; not shown at all when stderr is not a terminal."""
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
        # Off a terminal a transient display shows nothing but leaves an empty line on
        # stderr (above an error's one line): no display there.
        disable=transient and not err_console.is_terminal,
    ) as progress:

        def callback(task: str, done: float, total: float) -> None:
            if task not in tasks:
                tasks[task] = progress.add_task(task, total=total or None)
            progress.update(tasks[task], completed=done, total=total or None)

        yield callback


def print_json(data: Any) -> None:
    """Print data as indented JSON on stdout (numpy scalars converted)."""
    from canopy_kit.core.atomic import to_json

    print(to_json(data), end="")


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["orchard.rows=3", "lidar.rings=16"]`` to a nested dict; values parsed as TOML."""
    from canopy_kit.config import parse_settings

    return parse_settings(items, "--set")


# -- output folders and files ---------------------------------------------------------------
# What each guarded output holds when Ctrl-C stopped the command (read by cli.main, which
# prints the one "interrupted" line).
interrupt_notes: list[str] = []
CACHE_FOLDER = ".cache"  # a run's stage cache (canopy_kit.pipeline: OUT/.cache/<stage>-<key>.pkl)
LISTED = 8  # names an interrupt line lists before "and N more"


def _label(option: str | None, path: Path) -> str:
    return f"{option} {path}" if option else str(path)


def _in_the_way(path: Path, label: str) -> None:
    """InputError when a file stands where a folder above ``path`` is needed, or when the
    nearest existing folder above it cannot be written."""
    from canopy_kit.errors import InputError

    for parent in path.parents:
        if parent.is_dir():
            if not os.access(parent, os.W_OK | os.X_OK):
                raise InputError(f"{label}: {parent} is not writable")
            return
        if parent.exists() or parent.is_symlink():
            raise InputError(f"{label}: {parent} is a file, so no folder can be made in it")


def check_output_folder(path: Path, option: str | None = "--out") -> None:
    """InputError (exit 2, one line naming the path) unless ``path`` is an existing folder
    that can be written or a new one that can be made."""
    from canopy_kit.errors import InputError

    label = _label(option, path)
    if path.is_dir():
        if not os.access(path, os.W_OK | os.X_OK):
            raise InputError(f"{label}: folder is not writable")
        return
    if path.is_symlink() and not path.exists():
        raise InputError(f"{label}: a broken link, not a folder")
    if path.exists():
        raise InputError(f"{label}: this is a file, not a folder (give a new or existing folder)")
    _in_the_way(path, label)


def check_output_file(path: Path, option: str | None) -> None:
    """InputError (exit 2, one line naming the path) when ``path`` is a folder or cannot be
    made (a file where a folder above it is needed, a folder that cannot be written)."""
    from canopy_kit.errors import InputError

    label = _label(option, path)
    if path.is_dir():
        raise InputError(f"{label}: this is a folder, not a file")
    _in_the_way(path, label)


def _first_missing(path: Path) -> Path | None:
    """The outermost of ``path`` and its parents that does not exist (what making ``path``
    creates), or None when ``path`` exists."""
    missing = None
    for p in (path, *path.parents):
        if p.exists() or p.is_symlink():
            break
        missing = p
    return missing


def _entries(folder: Path) -> dict[str, tuple[int, int]]:
    """Name -> (modification time, size) of what ``folder`` holds (nothing when absent)."""
    found = {}
    try:
        for entry in os.scandir(folder):
            stat = entry.stat(follow_symlinks=False)
            found[entry.name] = (stat.st_mtime_ns, stat.st_size)
    except (FileNotFoundError, NotADirectoryError):
        pass
    return found


def _prune_empty(root: Path) -> None:
    """Remove the empty folders in and including ``root``, deepest first; never a file
    (``rmdir`` refuses a folder that holds anything)."""
    if root.is_symlink() or not root.is_dir():
        return
    for folder, _, _ in os.walk(root, topdown=False):
        with contextlib.suppress(OSError):
            os.rmdir(folder)


def _stages(cache: Path) -> list[str]:
    return sorted({p.name.split("-")[0] for p in cache.glob("*.pkl")})


def _kept_line(path: Path, names: list[str], existed: bool) -> str:
    """What an interrupted command left in ``path``: the new or rewritten ``names``."""
    if not names:
        return f"nothing was written in {path}" if existed else "nothing was written"
    shown = []
    for name in sorted(names, key=lambda n: (n == CACHE_FOLDER, n))[:LISTED]:
        entry = path / name
        if name == CACHE_FOLDER and entry.is_dir():
            stages = ", ".join(_stages(entry)) or "none"
            name = f"{name}/ (cached stages {stages}: the same command resumes from them)"
        elif entry.is_dir():
            name += "/"
        shown.append(name)
    more = f" and {len(names) - LISTED} more" if len(names) > LISTED else ""
    return f"kept in {path}: {', '.join(shown)}{more}"


@contextmanager
def output_folder(path: Path, option: str | None = "--out") -> Iterator[Path]:
    """Guard a command's output folder.

    Before: :func:`check_output_folder` (a file in the way is a user's mistake, exit 2, not
    a failure of the run). On failure or Ctrl-C: the folders the command made and left
    empty are removed (``path`` itself when it made it), never a file nor a folder that was
    there before; on Ctrl-C what ``path`` now holds that the command wrote goes into
    :data:`interrupt_notes` for the one ``interrupted`` line.
    """
    path = Path(path)
    check_output_folder(path, option)
    created = _first_missing(path)
    before = _entries(path)
    try:
        yield path
    except BaseException as exc:
        now = _entries(path)
        if created is not None:
            _prune_empty(created)
        else:  # only the folders it made inside the existing one
            for name in set(now) - set(before):
                _prune_empty(path / name)
        if isinstance(exc, KeyboardInterrupt):
            after = _entries(path)
            written = [n for n, stat in after.items() if before.get(n) != stat]
            interrupt_notes.append(_kept_line(path, written, created is None))
        raise


@contextmanager
def output_file(path: Path, option: str | None) -> Iterator[Path]:
    """Guard a command's output file (:func:`check_output_file`; on failure the folders
    made for it and left empty are removed; on Ctrl-C whether it was written)."""
    path = Path(path)
    check_output_file(path, option)
    created = _first_missing(path.parent)
    before = path.stat().st_mtime_ns if path.exists() else None
    try:
        yield path
    except BaseException as exc:
        if created is not None:
            _prune_empty(created)
        if isinstance(exc, KeyboardInterrupt):
            after = path.stat().st_mtime_ns if path.exists() else None
            interrupt_notes.append(f"kept {path}" if after != before else "nothing was written")
        raise


def interrupted_line() -> str:
    """The line Ctrl-C ends a command with: what its outputs hold (writes are atomic: a
    file is whole under its final name or absent)."""
    notes = list(dict.fromkeys(interrupt_notes)) or ["nothing was written"]
    if len(notes) > 1 and "nothing was written" in notes:
        notes.remove("nothing was written")
    return "interrupted: " + "; ".join(notes)
