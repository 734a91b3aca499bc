"""Point-cloud files by format: ``read_cloud`` / ``write_cloud`` choose a reader plugin.

Readers come from the ``canopy_kit.readers`` entry-point group; a reader is chosen by the
file's suffix first, then by asking each reader to sniff the content.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError, PluginError

# Coordinates beyond this distance from zero (e.g. UTM) are moved to a local frame.
LOCAL_LIMIT_M = 10_000.0
# Local origins are whole multiples of this, so offsets stay readable and grid-aligned.
ORIGIN_GRID_M = 1_000.0


def local_origin(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """A round origin that keeps local coordinates small.

    Per axis: the lower bound rounded down to a whole kilometre when the data lie more
    than 10 km from zero (projected coordinates), else 0 (data already local).
    """
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    far = np.maximum(np.abs(lower), np.abs(upper)) > LOCAL_LIMIT_M
    return np.where(far, np.floor(lower / ORIGIN_GRID_M) * ORIGIN_GRID_M, 0.0)


def check_input_file(path: str | Path, what: str = "point-cloud file") -> Path:
    """The path as a Path; InputError naming it when missing, a folder or empty."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file does not exist")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, expected a {what}")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: file is empty (0 bytes), not a {what}")
    return path


def reader_objects(broken: list[str] | None = None) -> list[Any]:
    """One instance of every registered reader plugin that loads, in name order.

    A reader that fails to load is skipped (one broken third-party package must not stop
    LAS files from being read); its error is appended to ``broken`` when given.
    """
    from canopy_kit import plugins

    out = []
    for name in plugins.names("readers"):
        try:
            out.append(plugins.create("readers", name))
        except PluginError as exc:
            if broken is not None:
                broken.append(str(exc))
    return out


def find_reader(path: str | Path, kind: str | None = None) -> Any:
    """The reader plugin for ``path``: by suffix, else by content; InputError when none fits.

    ``kind`` (``"cloud"``, ``"bag"``, ``"scans"``) restricts the choice to readers of that kind.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file or folder does not exist")
    if path.is_file() and path.stat().st_size == 0:
        raise InputError(f"{path}: file is empty (0 bytes)")
    broken: list[str] = []
    readers = reader_objects(broken)
    suffix = path.suffix.lower()
    chosen = None
    if path.is_file():
        chosen = next((r for r in readers if suffix in r.suffixes), None)
    if chosen is None:
        chosen = next((r for r in readers if _sniffs(r, path)), None)
    if chosen is None:
        known = sorted({s for r in readers for s in r.suffixes})
        note = f"; reader plugins that failed to load: {' | '.join(broken)}" if broken else ""
        raise InputError(
            f"{path}: unknown file format (suffix {suffix or 'none'!r}; readable: "
            f"{', '.join(known)}){note}"
        )
    if kind is not None and chosen.kind != kind:
        raise InputError(
            f"{path}: is a {chosen.kind} file ({chosen.name} reader), expected a {kind} file"
        )
    return chosen


def _sniffs(reader: Any, path: Path) -> bool:
    try:
        return bool(reader.sniff(path))
    except OSError:
        return False


def read_cloud(path: str | Path) -> PointCloud:
    """Read a LAS/LAZ/PLY/PCD (or any registered cloud format) file into a PointCloud."""
    path = check_input_file(path)
    return find_reader(path, kind="cloud").read(path)


def write_cloud(path: str | Path, cloud: PointCloud) -> Path:
    """Write a PointCloud in the format its suffix names (.las, .laz, .ply, .pcd), atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    writers = [r for r in reader_objects() if suffix in r.suffixes and hasattr(r, "write")]
    if not writers:
        known = sorted({s for r in reader_objects() if hasattr(r, "write") for s in r.suffixes})
        raise InputError(
            f"{path}: cannot write suffix {suffix or 'none'!r} (writable: {', '.join(known)})"
        )
    return writers[0].write(path, cloud)
