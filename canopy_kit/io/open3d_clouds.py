"""PLY and PCD through Open3D's tensor I/O (``open3d.t.io``), every vertex property kept.

Open3D reads a truncated PLY or ASCII PCD without failing (the missing points come back
as zeros), so the header is checked first: the point count it declares must fit the
file's size. Open3D maps ``nx/ny/nz`` to ``normals`` and ``red/green/blue`` (PCD ``rgb``)
to ``colors``; these stay (N, 3) fields. Other fields are (N,) arrays.

PLY cannot store int8/int16/uint32/int64/uint64 through Open3D; the writer widens them
to int32, or float64 when int32 cannot hold the values (exact up to 2**53). Files are
written binary: Open3D's ASCII PLY keeps 6 significant digits (metres lost on UTM
coordinates) and its ASCII PCD 8. Coordinates are written as absolute float64; note
that Open3D's legacy ``open3d.io`` PCD reader (and PCL's float point types) read
double-precision x/y/z PCD fields as zeros or not at all, while PLY doubles are widely read.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.io.atomic import atomic_path
from canopy_kit.io.clouds import check_input_file, local_origin

PLY_SIZES = {
    "char": 1,
    "int8": 1,
    "uchar": 1,
    "uint8": 1,
    "short": 2,
    "int16": 2,
    "ushort": 2,
    "uint16": 2,
    "int": 4,
    "int32": 4,
    "uint": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}
PLY_WRITABLE = {"u1", "u2", "i4", "f4", "f8"}
VECTOR_FIELDS = ("normals", "colors")  # Open3D's (N, 3) attributes
MAX_HEADER_BYTES = 1 << 16


@dataclass
class CloudHeader:
    """What a PLY/PCD header declares: encoding, point count, whether the size fits."""

    encoding: str
    points: int
    complete: bool
    detail: str = ""


def _header_lines(path: Path, end: tuple[bytes, ...]) -> tuple[list[str], int]:
    """Header lines up to and including the first line starting with one of ``end``."""
    lines: list[str] = []
    with path.open("rb") as fh:
        head = fh.read(MAX_HEADER_BYTES)
    pos = 0
    while pos < len(head):
        nl = head.find(b"\n", pos)
        if nl < 0:
            break
        line = head[pos:nl].rstrip(b"\r")
        pos = nl + 1
        lines.append(line.decode("ascii", "replace"))
        if line.startswith(end):
            return lines, pos
    raise InputError(f"{path}: header is incomplete (no {end[0].decode()!r} line)")


def _count_data_lines(path: Path, start: int) -> int:
    with path.open("rb") as fh:
        fh.seek(start)
        return sum(1 for line in fh if line.strip())


def ply_header(path: Path) -> CloudHeader:
    """Parse a PLY header and check the file is long enough for its vertices."""
    if not PlyReader().sniff(path):
        raise InputError(f"{path}: not a PLY file (first line is not 'ply')")
    lines, body = _header_lines(path, (b"end_header",))
    encoding, elements = "", []  # elements: [name, count, property sizes or None for lists]
    for line in lines[1:]:
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) >= 2:
            encoding = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                elements.append([words[1], int(words[2]), []])
            except ValueError:
                raise InputError(f"{path}: bad PLY element line {line!r}") from None
        elif words[0] == "property" and elements:
            size = None if words[1] == "list" else PLY_SIZES.get(words[1])
            elements[-1][2].append(size)
    vertex = next((e for e in elements if e[0] == "vertex"), None)
    if vertex is None:
        raise InputError(f"{path}: PLY file has no 'vertex' element")
    count = vertex[1]
    size = path.stat().st_size - body
    if encoding == "ascii":
        before = sum(e[1] for e in elements[: elements.index(vertex)])
        lines_found = _count_data_lines(path, body)
        return CloudHeader(
            encoding,
            count,
            lines_found >= before + count,
            f"{lines_found} data lines for {before + count} declared",
        )
    if elements[0] is vertex and None not in vertex[2]:
        needed = count * sum(vertex[2])
        return CloudHeader(encoding, count, size >= needed, f"{size} data bytes, {needed} needed")
    return CloudHeader(encoding, count, True)


def pcd_header(path: Path) -> CloudHeader:
    """Parse a PCD header and check the file is long enough for its points."""
    if not PcdReader().sniff(path):
        raise InputError(f"{path}: not a PCD file (no '# .PCD', VERSION or FIELDS header)")
    lines, body = _header_lines(path, (b"DATA",))
    keys: dict[str, list[str]] = {}
    for line in lines:
        words = line.split()
        if words and not words[0].startswith("#"):
            keys[words[0].upper()] = words[1:]
    if "FIELDS" not in keys or "DATA" not in keys:
        raise InputError(f"{path}: not a PCD file (no FIELDS or DATA line)")
    try:
        if "POINTS" in keys:
            count = int(keys["POINTS"][0])
        else:
            count = int(keys["WIDTH"][0]) * int(keys.get("HEIGHT", ["1"])[0])
        sizes = [int(v) for v in keys.get("SIZE", [])]
        counts = [int(v) for v in keys.get("COUNT", ["1"] * len(sizes))]
    except (ValueError, IndexError, KeyError):
        raise InputError(f"{path}: PCD header has a bad POINTS/WIDTH/SIZE/COUNT line") from None
    encoding = keys["DATA"][0] if keys["DATA"] else ""
    size = path.stat().st_size - body
    if encoding == "ascii":
        found = _count_data_lines(path, body)
        return CloudHeader(
            encoding, count, found >= count, f"{found} data lines for {count} points"
        )
    if encoding == "binary" and sizes:
        needed = count * sum(s * c for s, c in zip(sizes, counts))
        return CloudHeader(encoding, count, size >= needed, f"{size} data bytes, {needed} needed")
    if encoding == "binary_compressed":
        with path.open("rb") as fh:
            fh.seek(body)
            sizes_raw = fh.read(8)
        compressed = int.from_bytes(sizes_raw[:4], "little") if len(sizes_raw) == 8 else -1
        return CloudHeader(
            encoding,
            count,
            0 <= compressed <= size - 8,
            f"{size - 8} data bytes, {compressed} compressed bytes declared",
        )
    return CloudHeader(encoding, count, True)


def _read_open3d(path: Path, header: CloudHeader, fmt: str) -> PointCloud:
    """Read with open3d.t.io after the header check; fields as numpy arrays."""
    if header.points == 0:
        raise InputError(f"{path}: {fmt} file has no points")
    if not header.complete:
        raise InputError(f"{path}: {fmt} file is truncated or corrupt ({header.detail})")
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        try:
            pcd = o3d.t.io.read_point_cloud(str(path), format=fmt.lower())  # not by suffix
        except Exception as exc:
            raise InputError(
                f"{path}: {fmt} file cannot be read ({type(exc).__name__}: {exc})"
            ) from None
    if "positions" not in pcd.point or len(pcd.point.positions) != header.points:
        got = len(pcd.point.positions) if "positions" in pcd.point else 0
        raise InputError(
            f"{path}: {fmt} file cannot be read (header declares {header.points} "
            f"points, Open3D read {got}; is it corrupt or missing x/y/z?)"
        )
    absolute = pcd.point.positions.numpy().astype(np.float64)
    origin = local_origin(absolute.min(axis=0), absolute.max(axis=0))
    fields: dict[str, np.ndarray] = {}
    for name in sorted(
        pcd.point
    ):  # Open3D's attribute order is not the file's; sort for stable output
        if name == "positions":
            continue
        values = pcd.point[name].numpy()
        fields[name] = (
            values[:, 0].copy() if values.ndim == 2 and values.shape[1] == 1 else values.copy()
        )
    return PointCloud(absolute - origin, fields, crs=None, origin=origin)


def _ply_dtype(name: str, values: np.ndarray, path: Path) -> np.ndarray:
    """Widen a field to a dtype Open3D's PLY writer supports, keeping values exact."""
    code = values.dtype.str[1:]
    if values.dtype.kind == "b":
        return values.astype(np.uint8)
    if code in PLY_WRITABLE:
        return values
    if values.dtype.kind in "iu":
        if values.size == 0 or (values.min() >= -(2**31) and values.max() <= 2**31 - 1):
            return values.astype(np.int32)
        if np.abs(values.astype(np.float64)).max() <= 2**53:
            return values.astype(np.float64)
    if values.dtype.kind == "f":
        return values.astype(np.float64)
    raise InputError(f"{path}: field {name!r} ({values.dtype}) cannot be stored exactly in PLY")


def _write_open3d(path: Path, cloud: PointCloud, fmt: str) -> Path:
    if len(cloud) == 0:
        raise InputError(f"{path}: refusing to write a point cloud with no points")
    import open3d as o3d

    o3c = o3d.core
    pcd = o3d.t.geometry.PointCloud()
    pcd.point.positions = o3c.Tensor(np.ascontiguousarray(cloud.absolute_xyz))
    for name, values in cloud.fields.items():
        values = np.asarray(values)
        if values.dtype.kind not in "biuf":
            raise InputError(
                f"{path}: field {name!r} has dtype {values.dtype}; {fmt} holds numbers only"
            )
        if name == "positions":
            raise InputError(f"{path}: field name 'positions' is reserved for the coordinates")
        columns: dict[str, np.ndarray]
        if name in VECTOR_FIELDS and values.ndim == 2 and values.shape[1] == 3:
            columns = {name: values}
        elif values.ndim == 1:
            columns = {name: values[:, None]}
        elif values.ndim == 2:
            columns = {f"{name}_{i}": values[:, i : i + 1] for i in range(values.shape[1])}
        else:
            raise InputError(
                f"{path}: field {name!r} has shape {values.shape}; expected (N,) or (N, k)"
            )
        for key, col in columns.items():
            col = (
                _ply_dtype(key, col, path)
                if fmt == "PLY"
                else (col.astype(np.uint8) if col.dtype.kind == "b" else col)
            )
            pcd.point[key] = o3c.Tensor(np.ascontiguousarray(col))
    with (
        atomic_path(path) as tmp,
        o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error),
    ):
        ok = o3d.t.io.write_point_cloud(str(tmp), pcd, write_ascii=False)
        if not ok:
            raise InputError(f"{path}: Open3D could not write the {fmt} file")
    return path


def read_ply(path: str | Path) -> PointCloud:
    """Read a PLY file: float64 xyz (local, with origin) and every vertex property."""
    path = check_input_file(path, "PLY file")
    return _read_open3d(path, ply_header(path), "PLY")


def read_pcd(path: str | Path) -> PointCloud:
    """Read a PCD file: float64 xyz (local, with origin) and every field."""
    path = check_input_file(path, "PCD file")
    return _read_open3d(path, pcd_header(path), "PCD")


def write_ply(path: str | Path, cloud: PointCloud) -> Path:
    """Write a binary PLY file (absolute float64 coordinates plus every field), atomically."""
    return _write_open3d(Path(path), cloud, "PLY")


def write_pcd(path: str | Path, cloud: PointCloud) -> Path:
    """Write a binary PCD file (absolute float64 coordinates plus every field), atomically."""
    return _write_open3d(Path(path), cloud, "PCD")


def _describe(path: Path, cloud: PointCloud, fmt: str, header: CloudHeader) -> dict[str, Any]:
    lo, hi = cloud.bounds()
    return {
        "path": str(path),
        "format": f"{fmt} ({header.encoding})",
        "points": len(cloud),
        "attributes": [
            {
                "name": k,
                "dtype": str(v.dtype) if v.ndim == 1 else f"{v.dtype} x{v.shape[1]}",
                "extra": False,
            }
            for k, v in cloud.fields.items()
        ],
        "bounds": {"min": (lo + cloud.origin).tolist(), "max": (hi + cloud.origin).tolist()},
        "crs": None,
    }


class PlyReader:
    """Reader plugin for PLY files (``canopy_kit.readers`` entry point ``ply``)."""

    name = "ply"
    kind = "cloud"
    suffixes = (".ply",)

    def sniff(self, path: Path) -> bool:
        """True when the file starts with the PLY magic line."""
        path = Path(path)
        if not path.is_file():
            return False
        with path.open("rb") as fh:
            return fh.read(4) in (b"ply\n", b"ply\r")

    def describe(self, path: Path) -> dict[str, Any]:
        """Point count, attributes with dtypes, bounds (PLY has no CRS)."""
        path = check_input_file(path, "PLY file")
        return _describe(path, read_ply(path), "PLY", ply_header(path))

    def read(self, path: Path) -> PointCloud:
        """The whole file as a PointCloud."""
        return read_ply(path)

    def write(self, path: Path, cloud: PointCloud) -> Path:
        """Write as binary PLY."""
        return write_ply(path, cloud)


class PcdReader:
    """Reader plugin for PCD files (``canopy_kit.readers`` entry point ``pcd``)."""

    name = "pcd"
    kind = "cloud"
    suffixes = (".pcd",)

    def sniff(self, path: Path) -> bool:
        """True when the file starts like a PCD header."""
        path = Path(path)
        if not path.is_file():
            return False
        with path.open("rb") as fh:
            head = fh.read(64).lstrip()
        return head.startswith((b"# .PCD", b"VERSION", b"FIELDS"))

    def describe(self, path: Path) -> dict[str, Any]:
        """Point count, attributes with dtypes, bounds (PCD has no CRS)."""
        path = check_input_file(path, "PCD file")
        return _describe(path, read_pcd(path), "PCD", pcd_header(path))

    def read(self, path: Path) -> PointCloud:
        """The whole file as a PointCloud."""
        return read_pcd(path)

    def write(self, path: Path, cloud: PointCloud) -> Path:
        """Write as binary PCD."""
        return write_pcd(path, cloud)
