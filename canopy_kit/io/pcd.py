"""PCD files (PCL's format) read with numpy after the header is checked against the file.

Open3D's PCD reader trusts the header: ``binary_compressed`` data of 0 bytes gave
uninitialised memory as points, a lone ``normal_x`` field crashed the process. Here every
header field is checked (FIELDS/SIZE/TYPE/COUNT agree, WIDTH x HEIGHT = POINTS, DATA ascii,
binary or binary_compressed, the compressed and uncompressed sizes fit the file and the
points), the points present are read (fewer than declared: an :class:`InputWarning`), and the
fields become what Open3D makes of them: ``normal_x/y/z`` -> ``normals``, a packed ``rgb`` or
``rgba`` -> ``colors`` (N, 3) uint8; a field with COUNT k > 1 is an (N, k) field.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.io.cloud_records import (
    ascii_rows,
    build_cloud,
    cast_column,
    group_columns,
    header_lines,
)
from canopy_kit.io.lzf import lzf_decompress

TYPE_SIZES = {"F": (4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
ENCODINGS = ("ascii", "binary", "binary_compressed")
KEYS = (
    "VERSION",
    "FIELDS",
    "SIZE",
    "TYPE",
    "COUNT",
    "WIDTH",
    "HEIGHT",
    "VIEWPOINT",
    "POINTS",
    "DATA",
)
GROUPS = {"normals": ("normal_x", "normal_y", "normal_z")}
PADDING = "_"  # PCL's name for padding bytes
MAX_POINT_BYTES = 1 << 20  # a point of more than a MiB is a damaged SIZE or COUNT
LZF_MAX_RATIO = 88  # LZF's longest back reference: 264 bytes from 3


@dataclass(frozen=True)
class PcdField:
    """One field: name, numpy dtype (little-endian) and values per point."""

    name: str
    dtype: str
    count: int


@dataclass(frozen=True)
class PcdHeader:
    """A checked PCD header."""

    fields: tuple[PcdField, ...]
    points: int
    encoding: str
    data_start: int

    @property
    def point_bytes(self) -> int:
        """Bytes per point in the binary layouts."""
        return sum(np.dtype(f.dtype).itemsize * f.count for f in self.fields)


def _ints(path: Path, key: str, words: list[str], minimum: int) -> list[int]:
    if not words or not all(w.isdigit() for w in words) or min(int(w) for w in words) < minimum:
        raise InputError(
            f"{path}: PCD header field {key} {' '.join(words)!r} is not a list of "
            f"integers >= {minimum}"
        )
    return [int(w) for w in words]


def _fields(path: Path, keys: dict[str, list[str]]) -> tuple[PcdField, ...]:
    names = keys.get("FIELDS", [])
    sizes = _ints(path, "SIZE", keys.get("SIZE", []), 1)
    types = keys.get("TYPE", [])
    counts = _ints(path, "COUNT", keys["COUNT"], 1) if "COUNT" in keys else [1] * len(names)
    if not names or not len(names) == len(sizes) == len(types) == len(counts):
        raise InputError(
            f"{path}: PCD header fields FIELDS ({len(names)}), SIZE ({len(sizes)}), "
            f"TYPE ({len(types)}) and COUNT ({len(counts)}) do not list one value "
            "per field"
        )
    out = []
    for name, size, kind, count in zip(names, sizes, types, counts):
        if size not in TYPE_SIZES.get(kind, ()):
            raise InputError(
                f"{path}: PCD field {name!r} has TYPE {kind!r} SIZE {size} (types: "
                "F 4/8, I and U 1/2/4/8)"
            )
        out.append(PcdField(name, f"<{kind.lower()}{size}", count))
    real = [f.name for f in out if f.name != PADDING]
    if len(set(real)) != len(real):
        raise InputError(f"{path}: PCD header repeats a field name ({' '.join(names)})")
    missing = [c for c in "xyz" if c not in real]
    if missing:
        raise InputError(f"{path}: PCD file has no {'/'.join(missing)} field")
    point_bytes = sum(size * count for size, count in zip(sizes, counts))
    if point_bytes > MAX_POINT_BYTES:
        raise InputError(
            f"{path}: PCD header SIZE x COUNT makes {point_bytes} bytes a point "
            f"(more than {MAX_POINT_BYTES}); the header is corrupt"
        )
    if any(f.count != 1 for f in out if f.name in ("x", "y", "z")):
        raise InputError(
            f"{path}: PCD fields x, y, z must have COUNT 1 (COUNT {' '.join(map(str, counts))})"
        )
    return tuple(out)


def read_pcd_header(path: Path) -> PcdHeader:
    """Parse and check a PCD header; InputError naming the field that is wrong."""
    lines, data_start = header_lines(path, b"DATA", "PCD")
    keys: dict[str, list[str]] = {}
    for line in lines:
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        key = words[0].upper()
        if key not in KEYS:
            raise InputError(f"{path}: PCD header has an unknown line {line[:60]!r}")
        keys[key] = words[1:]
    fields = _fields(path, keys)
    width = _ints(path, "WIDTH", keys.get("WIDTH", ["0"]), 0)[0]
    height = _ints(path, "HEIGHT", keys.get("HEIGHT", ["1"]), 0)[0]
    points = _ints(path, "POINTS", keys["POINTS"], 0)[0] if "POINTS" in keys else width * height
    if "WIDTH" in keys and width * height != points:
        raise InputError(
            f"{path}: PCD header WIDTH x HEIGHT ({width} x {height}) differs from POINTS ({points})"
        )
    encoding = keys["DATA"][0].lower() if keys.get("DATA") else ""
    if encoding not in ENCODINGS:
        raise InputError(
            f"{path}: PCD header DATA {encoding!r} is not one of {', '.join(ENCODINGS)}"
        )
    return PcdHeader(fields, points, encoding, data_start)


def _binary_columns(path: Path, header: PcdHeader) -> tuple[dict[str, np.ndarray], list[str]]:
    """Columns of the points present in a binary (row-major) body."""
    dtype = np.dtype(
        [
            (f"{f.name}{i}" if f.name == PADDING else f.name, f.dtype, (f.count,))
            for i, f in enumerate(header.fields)
        ]
    )
    size = path.stat().st_size - header.data_start
    present = min(header.points, size // dtype.itemsize)
    rows = (
        np.fromfile(path, dtype=dtype, count=present, offset=header.data_start)
        if present
        else (np.zeros(0, dtype))
    )
    return {f.name: rows[f.name] for f in header.fields if f.name != PADDING}, []


def _compressed_columns(path: Path, header: PcdHeader) -> tuple[dict[str, np.ndarray], list[str]]:
    """Columns of a binary_compressed body: LZF of the points stored field by field."""
    size = path.stat().st_size - header.data_start
    with path.open("rb") as fh:
        fh.seek(header.data_start)
        sizes = fh.read(8)
        if len(sizes) < 8:
            raise InputError(
                f"{path}: PCD binary_compressed data is truncated (no compressed and "
                "uncompressed sizes after DATA)"
            )
        compressed, uncompressed = struct.unpack("<II", sizes)
        expected = header.points * header.point_bytes
        if uncompressed != expected:
            raise InputError(
                f"{path}: PCD binary_compressed uncompressed size is {uncompressed} "
                f"bytes; {header.points} points of {header.point_bytes} bytes make "
                f"{expected}"
            )
        if not 0 < compressed <= size - 8:
            raise InputError(
                f"{path}: PCD binary_compressed compressed size is {compressed} "
                f"bytes; the file holds {size - 8} after the sizes; it is "
                "corrupt or truncated"
            )
        if uncompressed > LZF_MAX_RATIO * compressed + 32:
            raise InputError(
                f"{path}: PCD binary_compressed uncompressed size {uncompressed} "
                f"bytes cannot come from {compressed} compressed bytes (LZF expands "
                f"at most {LZF_MAX_RATIO} times); the file is corrupt"
            )
        data = lzf_decompress(fh.read(compressed), uncompressed)
    if data is None:
        raise InputError(
            f"{path}: PCD binary_compressed data do not decompress to "
            f"{uncompressed} bytes; the file is corrupt"
        )
    out, pos = {}, 0
    for f in header.fields:
        n = header.points * f.count * np.dtype(f.dtype).itemsize
        if f.name != PADDING:
            out[f.name] = data[pos : pos + n].view(f.dtype).reshape(header.points, f.count)
        pos += n
    return out, []


def _ascii_columns(path: Path, header: PcdHeader) -> tuple[dict[str, np.ndarray], list[str]]:
    width = sum(f.count for f in header.fields)
    values, note = ascii_rows(path, header.data_start, 0, header.points, width, "PCD")
    out, col = {}, 0
    for f in header.fields:
        if f.name != PADDING:
            out[f.name] = cast_column(path, f.name, values[:, col : col + f.count], f.dtype)
        col += f.count
    return out, [note] if note else []


def _colors(packed: np.ndarray) -> np.ndarray:
    """PCL's packed rgb/rgba (4 bytes: b, g, r, a) as (N, 3) uint8 red, green, blue."""
    raw = np.ascontiguousarray(packed).view(np.uint8).reshape(len(packed), 4)
    return raw[:, 2::-1].copy()


def read_pcd(path: Path) -> PointCloud:
    """Read a checked PCD file: float64 xyz (local, with origin) and every field; fewer points
    than declared or non-finite ones give an InputWarning."""
    header = read_pcd_header(path)
    read = {
        "ascii": _ascii_columns,
        "binary": _binary_columns,
        "binary_compressed": _compressed_columns,
    }[header.encoding]
    raw, notes = read(path, header)
    columns = {k: v[:, 0] if v.ndim == 2 and v.shape[1] == 1 else v for k, v in raw.items()}
    xyz = np.column_stack([columns.pop(c) for c in "xyz"]).astype(np.float64)
    for name in ("rgb", "rgba"):
        if name in columns and columns[name].ndim == 1 and columns[name].dtype.itemsize == 4:
            columns["colors"] = _colors(columns.pop(name))
    fields = {
        k: v.astype(v.dtype.newbyteorder("=")) for k, v in group_columns(columns, GROUPS).items()
    }
    return build_cloud(path, "PCD", xyz, fields, header.points, notes)
