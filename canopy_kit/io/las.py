"""Reading LAS/LAZ through laspy (LAZ via lazrs): float64 coordinates, every dimension kept.

The header is checked against the file first (:mod:`canopy_kit.io.las_header`); the points
present are then read a million at a time. Coordinates become local (``xyz = absolute -
origin``, origin from :func:`las_origin` on the points' bounds), every standard and
extra-bytes dimension becomes a ``PointCloud.fields`` entry, and a float extra dimension's
declared no-data value (e.g. DBL_MAX in lidR's ``treeID``) becomes NaN. ``gps_time`` in
Adjusted Standard GPS Time (global encoding bit 0 set) becomes Unix seconds, the clock
of a bag and of ``gps_time`` in the pipeline, when they hold it exactly (every file
canopy-kit writes; :func:`~canopy_kit.io.las_write.cloud_gps_time`); GPS week seconds and
finer times are kept as stored. Writing is :mod:`canopy_kit.io.las_write`.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError, InputWarning, foreign_message
from canopy_kit.io.clouds import LOCAL_LIMIT_M, check_input_file, local_origin
from canopy_kit.io.las_header import LAS_MAGIC, LasLayout, read_las_layout
from canopy_kit.io.las_write import choose_point_format, cloud_gps_time, las_ready, write_las

__all__ = [
    "LasReader",
    "choose_point_format",
    "describe_las",
    "las_origin",
    "las_ready",
    "read_las",
    "write_las",
]

READ_CHUNK = 1_000_000  # points per laspy read: memory follows the points really decoded
# lazrs' parallel reader sizes a buffer by the LASzip chunk size (a damaged one asked for
# 3 GB and aborted the process): parallel only for chunks up to this many bytes.
PARALLEL_CHUNK_BYTES = 64 << 20


def _open_error(path: Path, exc: Exception) -> InputError:
    return InputError(
        f"{path}: cannot read the LAS/LAZ data; the file is corrupt or truncated "
        f"({type(exc).__name__}: {foreign_message(str(exc))})"
    )


def _is_las(path: Path) -> bool:
    with path.open("rb") as fh:
        return fh.read(4) == LAS_MAGIC


def _checked(path: str | Path) -> LasLayout:
    """The header checked against the file (:mod:`canopy_kit.io.las_header`)."""
    return read_las_layout(check_input_file(path, "LAS/LAZ file"))


@contextmanager
def _las_reader(layout: LasLayout) -> Iterator[Any]:
    """laspy's reader on a checked file, its errors as InputError (its log lines held back:
    what they say about a damaged file is in our errors and warnings)."""
    import laspy

    log = logging.getLogger("laspy")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        with laspy.open(layout.path, laz_backend=_read_backend(layout)) as reader:
            yield reader
    except InputError:
        raise
    except Exception as exc:  # laspy/lazrs raise LaspyException, LazrsError, ValueError, OSError...
        raise _open_error(layout.path, exc) from None
    finally:
        log.setLevel(level)


def _read_backend(layout: LasLayout) -> Any:
    """lazrs on every core for LAZ whose chunk size is known and modest, else one core."""
    import laspy

    if not layout.compressed:
        return None
    chunk = layout.laz_chunk_points
    parallel = chunk is not None and chunk * layout.record_length <= PARALLEL_CHUNK_BYTES
    for backend in (laspy.LazBackend.LazrsParallel, laspy.LazBackend.Lazrs):
        if backend.is_available() and (parallel or backend is laspy.LazBackend.Lazrs):
            return backend
    return None


def _point_chunks(reader: Any, layout: LasLayout) -> Iterator[Any]:
    """The point records present in the file, at most READ_CHUNK at a time."""
    remaining = layout.points_in_file
    while remaining > 0:
        n = min(READ_CHUNK, remaining)
        chunk = reader.read_points(n)
        if len(chunk) != n:
            raise InputError(
                f"{layout.path}: cannot read the LAS/LAZ data; the file is corrupt or "
                f"truncated ({len(chunk)} of {n} points read)"
            )
        remaining -= n
        yield chunk


def cut_short_warning(layout: LasLayout) -> str:
    """The warning for a LAS file holding fewer point records than its header declares."""
    return (
        f"{layout.path}: only {layout.points_in_file} of {layout.point_count} points are in "
        "the file (cut short, or the header's point count is wrong); read those"
    )


def crs_string(crs: Any) -> str | None:
    """``EPSG:xxxx`` for a pyproj CRS with an EPSG code, else its WKT; None for None."""
    if crs is None:
        return None
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg is not None else crs.to_wkt()


def _parse_crs(header: Any, path: Path) -> str | None:
    try:
        return crs_string(header.parse_crs())
    except Exception as exc:  # pyproj and laspy raise several types for odd CRS records
        reason = f"{type(exc).__name__}: {foreign_message(str(exc))}"
        raise InputError(f"{path}: CRS record cannot be parsed ({reason})") from None


def _no_data_values(header: Any) -> dict[str, float]:
    """Declared no-data values of single-valued extra-bytes dimensions, by name."""
    out: dict[str, float] = {}
    for vlr in header.vlrs:
        for struct in getattr(vlr, "extra_bytes_structs", ()):
            if struct.options & 1 and struct.no_data is not None:
                name = struct.name.rstrip(b"\0").decode("ascii", "replace")
                out[name] = float(struct.no_data[0])
    return out


def las_origin(offsets: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Per axis: the header offset when the points lie within 10 km of it, else a round origin.

    ``lower``/``upper`` are the points' bounds (never the header's: some writers leave them 0).
    Keeping the offset makes a re-write at the same scale reproduce the file's integers.
    """
    offsets = np.asarray(offsets, dtype=np.float64)
    near = np.maximum(np.abs(lower - offsets), np.abs(upper - offsets)) <= LOCAL_LIMIT_M
    return np.where(near, offsets, local_origin(lower, upper)) + 0.0


def _integer_bounds(chunks: Iterator[Any]) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest stored X, Y, Z integers over the chunks."""
    lo = np.full(3, np.iinfo(np.int64).max)
    hi = np.full(3, np.iinfo(np.int64).min)
    for chunk in chunks:
        for axis, name in enumerate("XYZ"):
            values = np.asarray(chunk[name])
            lo[axis] = min(lo[axis], int(values.min()))
            hi[axis] = max(hi[axis], int(values.max()))
    return lo, hi


def _scaled(layout: LasLayout, integers: np.ndarray) -> np.ndarray:
    return integers * np.asarray(layout.scales) + np.asarray(layout.offsets)


def read_las(path: str | Path) -> PointCloud:
    """Read a LAS/LAZ file: local float64 xyz, origin, CRS and every dimension as a field.

    A file holding fewer point records than its header declares gives the records present
    and an :class:`InputWarning` saying how many.
    """
    import laspy

    layout = _checked(path)
    with _las_reader(layout) as reader:
        header = reader.header
        chunks = [c.array for c in _point_chunks(reader, layout)]
        points = laspy.ScaleAwarePointRecord(
            chunks[0] if len(chunks) == 1 else np.concatenate(chunks),
            header.point_format,
            header.scales,
            header.offsets,
        )
        crs = _parse_crs(header, layout.path)
        no_data = _no_data_values(header)
        # Adjusted Standard GPS Time in the standard dimension (not an extra one so named)
        to_unix = header.global_encoding.gps_time_type == 1 and any(
            d.name == "gps_time" and d.is_standard for d in header.point_format.dimensions
        )
    raw = np.column_stack([np.asarray(points[c]) for c in ("X", "Y", "Z")])
    origin = las_origin(
        layout.offsets, _scaled(layout, raw.min(axis=0)), _scaled(layout, raw.max(axis=0))
    )
    xyz = raw * np.asarray(layout.scales) + (np.asarray(layout.offsets) - origin)
    fields: dict[str, np.ndarray] = {}
    for name in points.point_format.dimension_names:
        if name in ("X", "Y", "Z"):
            continue
        values = np.array(points[name])
        if name in no_data and values.dtype.kind == "f":
            values[values == no_data[name]] = np.nan
        if name == "gps_time" and to_unix:
            values = cloud_gps_time(values)
        fields[name] = values
    if layout.cut_short:
        warnings.warn(InputWarning(cut_short_warning(layout)), stacklevel=2)
    return PointCloud(xyz, fields, crs=crs, origin=origin)


def _header_bounds_note(layout: LasLayout, lo: np.ndarray, hi: np.ndarray) -> str | None:
    """A warning when the header's min/max differ from the points' by more than a step."""
    head_lo, head_hi = np.asarray(layout.header_min), np.asarray(layout.header_max)
    tol = np.asarray(layout.scales) + 1e-9 * np.maximum(np.abs(lo), np.abs(hi))
    if np.all(np.abs(head_lo - lo) <= tol) and np.all(np.abs(head_hi - hi) <= tol):
        return None

    def span(a: np.ndarray, b: np.ndarray) -> str:
        return ", ".join(f"{axis} {x:.10g}..{y:.10g}" for axis, x, y in zip("xyz", a, b))

    return (
        f"{layout.path}: the header's bounds ({span(head_lo, head_hi)}) disagree with the "
        f"points' ({span(lo, hi)}); the bounds shown are the points'"
    )


def describe_las(path: str | Path) -> dict[str, Any]:
    """Facts of a LAS/LAZ file: header fields, and bounds computed from its points (read in
    chunks); :class:`InputWarning` when the header's bounds or point count are wrong."""
    layout = _checked(path)
    with _las_reader(layout) as reader:
        header = reader.header
        lo_int, hi_int = _integer_bounds(_point_chunks(reader, layout))
        crs = _parse_crs(header, layout.path)
    lo, hi = _scaled(layout, lo_int), _scaled(layout, hi_int)
    attributes = []
    for dim in header.point_format.dimensions:
        if dim.name in ("X", "Y", "Z"):
            continue
        dtype = dim.dtype if dim.dtype is not None else np.dtype("u1")  # bit fields
        if dim.is_scaled:
            dtype = np.dtype("f8")
        attributes.append(
            {"name": dim.name, "dtype": str(np.dtype(dtype)), "extra": not dim.is_standard}
        )
    notes = [cut_short_warning(layout)] if layout.cut_short else []
    notes += [n for n in [_header_bounds_note(layout, lo, hi)] if n]
    for note in notes:
        warnings.warn(InputWarning(note), stacklevel=2)
    return {
        "path": str(layout.path),
        "format": "LAZ" if layout.compressed else "LAS",
        "version": layout.version,
        "point_format": layout.point_format,
        "points": layout.points_in_file,
        "points_declared": layout.point_count,
        "attributes": attributes,
        "bounds": {"min": lo.tolist(), "max": hi.tolist()},
        "header_bounds": {"min": list(layout.header_min), "max": list(layout.header_max)},
        "scale": list(layout.scales),
        "offset": [v + 0.0 for v in layout.offsets],
        "crs": crs,
    }


class LasReader:
    """Reader plugin for LAS/LAZ files (``canopy_kit.readers`` entry point ``las``)."""

    name = "las"
    kind = "cloud"
    suffixes = (".las", ".laz")

    def sniff(self, path: Path) -> bool:
        """True when the file starts with the LAS signature."""
        path = Path(path)
        return path.is_file() and _is_las(path)

    def describe(self, path: Path) -> dict[str, Any]:
        """Header facts: point count, attributes with dtypes, bounds, CRS."""
        return describe_las(path)

    def read(self, path: Path) -> PointCloud:
        """The whole file as a PointCloud."""
        return read_las(path)

    def write(self, path: Path, cloud: PointCloud) -> Path:
        """Write with default settings (smallest point format, 1 mm scale)."""
        return write_las(path, cloud)
