"""PLY and PCD files: read with numpy after checking the header, written with Open3D.

Reading is :mod:`canopy_kit.io.ply` and :mod:`canopy_kit.io.pcd`: Open3D's readers trust the
header (a short file or a face element before the vertices gave uninitialised memory as
points, a lone ``normal_x`` crashed the process), so the header is checked against the file
and the points present are read with numpy. The fields keep Open3D's names: ``normals`` and
``colors`` are (N, 3) fields, other fields (N,) arrays.

PLY cannot store int8/int16/uint32/int64/uint64 through Open3D; the writer widens them
to int32, or float64 when int32 cannot hold the values (exact up to 2**53). Files are
written binary: Open3D's ASCII PLY keeps 6 significant digits (metres lost on UTM
coordinates) and its ASCII PCD 8. Coordinates are written as absolute float64; note
that Open3D's legacy ``open3d.io`` PCD reader (and PCL's float point types) read
double-precision x/y/z PCD fields as zeros or not at all, while PLY doubles are widely read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.core.atomic import atomic_path
from canopy_kit.core.cloud import PointCloud
from canopy_kit.core.extras import needs_extra
from canopy_kit.errors import InputError, foreign_message
from canopy_kit.io import pcd, ply
from canopy_kit.io.clouds import check_input_file

PLY_WRITABLE = {"u1", "u2", "i4", "f4", "f8"}
VECTOR_FIELDS = ("normals", "colors")  # Open3D's (N, 3) attributes


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
    with needs_extra("open3d"):
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
        try:
            ok = o3d.t.io.write_point_cloud(str(tmp), pcd, write_ascii=False)
        except RuntimeError as exc:
            raise InputError(
                f"{path}: Open3D could not write the {fmt} file: {foreign_message(str(exc))}"
            ) from None
        if not ok:
            raise InputError(f"{path}: Open3D could not write the {fmt} file")
    return path


def read_ply(path: str | Path) -> PointCloud:
    """Read a PLY file: float64 xyz (local, with origin) and every vertex property."""
    return ply.read_ply(check_input_file(path, "PLY file"))


def read_pcd(path: str | Path) -> PointCloud:
    """Read a PCD file: float64 xyz (local, with origin) and every field."""
    return pcd.read_pcd(check_input_file(path, "PCD file"))


def write_ply(path: str | Path, cloud: PointCloud) -> Path:
    """Write a binary PLY file (absolute float64 coordinates plus every field), atomically."""
    return _write_open3d(Path(path), cloud, "PLY")


def write_pcd(path: str | Path, cloud: PointCloud) -> Path:
    """Write a binary PCD file (absolute float64 coordinates plus every field), atomically."""
    return _write_open3d(Path(path), cloud, "PCD")


def _describe(
    path: Path, cloud: PointCloud, fmt: str, encoding: str, declared: int
) -> dict[str, Any]:
    lo, hi = cloud.bounds()
    return {
        "path": str(path),
        "format": f"{fmt} ({encoding})",
        "points": len(cloud),
        "points_declared": declared,
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
        header = ply.read_ply_header(path)
        return _describe(path, read_ply(path), "PLY", header.encoding, header.vertices)

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
        header = pcd.read_pcd_header(path)
        return _describe(path, read_pcd(path), "PCD", header.encoding, header.points)

    def read(self, path: Path) -> PointCloud:
        """The whole file as a PointCloud."""
        return read_pcd(path)

    def write(self, path: Path, cloud: PointCloud) -> Path:
        """Write as binary PCD."""
        return write_pcd(path, cloud)
