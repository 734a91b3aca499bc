"""Point records of text-headed cloud files (PLY, PCD) turned into a PointCloud.

Shared by :mod:`canopy_kit.io.ply` and :mod:`canopy_kit.io.pcd`, which check the header
against the file and hand over columns: the header lines, the rows of an ASCII body, the
cast of a parsed column to its declared type, and the cloud itself, with the points whose
coordinates are not finite dropped and the warnings (:class:`InputWarning`) of a partial read.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError, InputWarning
from canopy_kit.io.clouds import local_origin

MAX_HEADER_BYTES = 1 << 16


def header_lines(path: Path, end: bytes, what: str) -> tuple[list[str], int]:
    """Header lines up to and including the first line starting with ``end``; and the byte
    where the data start. InputError when no such line is in the first 64 KiB."""
    with path.open("rb") as fh:
        head = fh.read(MAX_HEADER_BYTES)
    lines: list[str] = []
    pos = 0
    while (nl := head.find(b"\n", pos)) >= 0:
        line = head[pos:nl].rstrip(b"\r")
        pos = nl + 1
        lines.append(line.decode("ascii", "replace").strip())
        if line.lstrip().startswith(end):
            return lines, pos
    raise InputError(
        f"{path}: {what} header is incomplete (no {end.decode()!r} line in the "
        f"first {min(len(head), MAX_HEADER_BYTES)} bytes)"
    )


def ascii_rows(
    path: Path, start: int, skip: int, rows: int, columns: int, what: str
) -> tuple[np.ndarray, str | None]:
    """``rows`` lines of ``columns`` numbers after ``skip`` lines from byte ``start``; fewer
    when the file ends first. A last line without its line end counts only when whole, and
    then with a note (it may be cut inside its last number).

    InputError naming the line when a value is not a number or a line has another length.
    """
    if rows == 0:
        return np.zeros((0, columns)), None
    with path.open("rb") as fh:
        fh.seek(start)
        body = fh.read()
    newlines = np.flatnonzero(np.frombuffer(body, np.uint8) == ord("\n"))
    if skip == 0:
        begin = 0
    else:
        begin = int(newlines[skip - 1]) + 1 if skip <= len(newlines) else len(body)
    last = skip + rows - 1
    end = int(newlines[last]) + 1 if last < len(newlines) else len(body)
    text = body[begin:end].decode("ascii", "replace")
    note = None
    tail = text.rsplit("\n", 1)[-1]
    if tail.strip():  # the file ends inside this line
        if len(tail.split()) == columns:
            note = (
                f"{path}: the last {what} data line has no line end; the file may be cut "
                "short inside it"
            )
        else:
            text = text[: len(text) - len(tail)]
    if not text.strip():
        return np.zeros((0, columns)), note
    try:
        values = np.loadtxt(io.StringIO(text), dtype=np.float64, comments=None, ndmin=2)
    except ValueError as exc:
        reason = str(exc).split("; use `usecols`")[0]  # numpy's advice does not apply here
        raise InputError(
            f"{path}: {what} data (rows counted from 0 at line {skip + 1} of the data): {reason}"
        ) from None
    if values.shape[1] != columns:
        raise InputError(
            f"{path}: {what} data lines have {values.shape[1]} values, the header "
            f"declares {columns}"
        )
    return values, note


def cast_column(path: Path, name: str, values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """A parsed float64 column as its declared type; InputError when an integer column
    holds a fraction, a non-finite value or a value out of the type's range."""
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        return values.astype(dtype)
    info = np.iinfo(dtype)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(values) | (values != np.round(values))
        bad |= (values < info.min) | (values > info.max)
    if bad.any():
        flat, bad = values.reshape(len(values), -1), bad.reshape(len(values), -1)
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        value = float(flat[row][np.flatnonzero(bad[row])[0]])
        raise InputError(
            f"{path}: field {name!r} ({dtype}) holds {value!r} at point {row}, not a {dtype} value"
        )
    return values.astype(dtype)


def cut_short_warning(path: Path, found: int, declared: int) -> str:
    """The warning for a file holding fewer points than its header declares."""
    return (
        f"{path}: only {found} of {declared} points are in the file (cut short, or the "
        "header's point count is wrong); read those"
    )


def build_cloud(
    path: Path,
    fmt: str,
    xyz: np.ndarray,
    fields: dict[str, np.ndarray],
    declared: int,
    notes: list[str],
) -> PointCloud:
    """The cloud of absolute ``xyz`` with its fields, re-localised; points with a non-finite
    coordinate dropped. Warns with ``notes``, when fewer than ``declared`` points were in the
    file and when some were dropped (only once the cloud is whole); InputError when no point
    is left."""
    notes = list(notes)
    if len(xyz) < declared:
        notes.insert(0, cut_short_warning(path, len(xyz), declared))
    if len(xyz) == 0:
        raise InputError(
            f"{path}: {fmt} file has no points"
            if declared == 0
            else f"{path}: {fmt} file is truncated: no complete point (header declares {declared})"
        )
    xyz = np.asarray(xyz, dtype=np.float64)
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        dropped = int((~finite).sum())
        if dropped == len(xyz):
            raise InputError(
                f"{path}: all {dropped} points have non-finite coordinates (NaN or infinite x/y/z)"
            )
        notes.append(
            f"{path}: dropped {dropped} of {len(xyz)} points with non-finite "
            "coordinates (NaN or infinite x/y/z)"
        )
        xyz = xyz[finite]
        fields = {k: v[finite] for k, v in fields.items()}
    origin = local_origin(xyz.min(axis=0), xyz.max(axis=0))
    cloud = PointCloud(
        xyz - origin, {k: fields[k] for k in sorted(fields)}, crs=None, origin=origin
    )
    for note in notes:
        warnings.warn(InputWarning(note), stacklevel=3)
    return cloud


def group_columns(
    columns: dict[str, np.ndarray], groups: dict[str, tuple[str, str, str]]
) -> dict[str, np.ndarray]:
    """Columns with each complete group (e.g. nx, ny, nz) stacked into one (N, 3) field."""
    out = dict(columns)
    for field, names in groups.items():
        if all(n in out for n in names) and all(out[n].ndim == 1 for n in names):
            out[field] = np.column_stack([out.pop(n) for n in names])
    return out
