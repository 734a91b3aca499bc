"""LAS files with a broken header or no points, written with laspy directly (canopy-kit's own
writer refuses to make them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_raw_las(
    path: Path, n_points: int = 200, scale: float = 0.001, offset: float = 0.0, seed: int = 0
) -> Path:
    """A LAS 1.2 file whose header holds ``scale`` and ``offset`` as given, however wrong."""
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.full(3, scale, dtype=np.float64)
    header.offsets = np.full(3, offset, dtype=np.float64)
    las = laspy.LasData(header)
    rng = np.random.default_rng(seed)
    ints = rng.integers(0, 5000, (n_points, 3)).astype(np.int32)
    las.X, las.Y, las.Z = ints[:, 0], ints[:, 1], ints[:, 2]
    import warnings

    with warnings.catch_warnings():  # laspy computes bounds with the (bad) scale: NaN warnings
        warnings.simplefilter("ignore", RuntimeWarning)
        las.write(path)
    return path


def write_truncated_laz(path: Path, fraction: float = 0.6) -> Path:
    """A valid LAZ cut to ``fraction`` of its length."""
    from canopy_kit.core.cloud import PointCloud
    from canopy_kit.io.las import write_las

    rng = np.random.default_rng(1)
    write_las(path, PointCloud(rng.uniform(0, 10, (5000, 3))))
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


# --- hand-built files: every byte written here, so the numbers in them are the truth ---------

import struct  # noqa: E402 (the hand-built files start here)

LAS_RECORD = {0: 20, 1: 28, 6: 30}  # point formats the builder writes


def las_record_bytes(
    ints: np.ndarray, point_format: int, intensity: np.ndarray, extra: int = 0
) -> bytes:
    """Point records of format 0, 1 or 6: X, Y, Z, intensity; every other attribute 0; then
    ``extra`` bytes per point holding the point's index (little-endian)."""
    n = len(ints)
    if point_format == 6:
        fields = [("xyz", "<i4", 3), ("intensity", "<u2"), ("rest", "V8"), ("gps", "<f8")]
    else:
        fields = [("xyz", "<i4", 3), ("intensity", "<u2"), ("rest", "V6")]
        fields += [("gps", "<f8")] if point_format == 1 else []
    dtype = np.dtype(fields + ([("extra", f"V{extra}")] if extra else []))
    rec = np.zeros(n, dtype)
    rec["xyz"] = ints
    rec["intensity"] = intensity
    if extra:
        index = np.arange(n, dtype="<u8").view(np.uint8).reshape(n, 8)
        rec["extra"] = np.ascontiguousarray(
            np.pad(index, ((0, 0), (0, max(0, extra - 8))))[:, :extra]
        ).view(f"V{extra}")[:, 0]
    assert dtype.itemsize == LAS_RECORD[point_format] + extra
    return rec.tobytes()


def extra_bytes_vlr(name: bytes, data_type: int) -> bytes:
    """An Extra Bytes VLR (LASF_Spec 4) describing one extra dimension."""
    descriptor = bytearray(192)
    descriptor[2], descriptor[3] = data_type, 0
    descriptor[4 : 4 + len(name)] = name
    return vlr_bytes(b"LASF_Spec", 4, bytes(descriptor))


def vlr_bytes(user: bytes, record: int, payload: bytes) -> bytes:
    """One VLR: 54-byte header (reserved, user id, record id, length, description) + payload."""
    return struct.pack("<H16sHH32s", 0, user, record, len(payload), b"") + payload


def las_bytes(
    ints: np.ndarray,
    *,
    scale: float = 0.01,
    offset: tuple[float, float, float] = (0, 0, 0),
    point_format: int = 0,
    minor: int = 2,
    vlrs: tuple[bytes, ...] = (),
    header_bounds: tuple[tuple, tuple] | None = None,
    extra: int = 0,
    evlrs: tuple[bytes, ...] = (),
    **fields: int,
) -> bytes:
    """A LAS 1.2 (or 1.4) file of the integer coordinates ``ints``; ``fields`` overwrite what
    the header declares (``point_count``, ``record_length``, ``n_vlrs``, ``offset_to_points``,
    ``header_size``, ``evlr_start``, ``n_evlrs``) however wrong. ``extra`` bytes follow each
    standard record; ``evlrs`` (LAS 1.4) follow the points."""
    ints = np.asarray(ints, dtype=np.int32)
    n = len(ints)
    header_size = 375 if minor == 4 else 227
    vlr_data = b"".join(vlrs)
    offset_to_points = header_size + len(vlr_data)
    scales = np.full(3, scale)
    with np.errstate(invalid="ignore", over="ignore"):  # the scale may be as wrong as asked
        absolute = ints * scales + np.asarray(offset)
    lo, hi = header_bounds or (absolute.min(axis=0), absolute.max(axis=0))
    record_length = LAS_RECORD[point_format] + extra
    evlr_start = offset_to_points + n * record_length if evlrs else 0
    decl = {
        "point_count": n,
        "record_length": record_length,
        "n_vlrs": len(vlrs),
        "offset_to_points": offset_to_points,
        "header_size": header_size,
        "evlr_start": evlr_start,
        "n_evlrs": len(evlrs),
        **fields,
    }
    head = bytearray(header_size)
    head[0:4] = b"LASF"
    head[24], head[25] = 1, minor
    head[26:58] = b"canopy-kit test".ljust(32, b"\0")
    legacy = decl["point_count"] if point_format < 6 and decl["point_count"] < 2**32 else 0
    struct.pack_into(
        "<HIIBHI",
        head,
        94,
        decl["header_size"],
        decl["offset_to_points"],
        decl["n_vlrs"],
        point_format,
        decl["record_length"],
        legacy,
    )
    struct.pack_into("<3d3d", head, 131, *scales, *offset)
    struct.pack_into("<6d", head, 179, hi[0], lo[0], hi[1], lo[1], hi[2], lo[2])
    if minor == 4:
        struct.pack_into(
            "<QIQ", head, 235, decl["evlr_start"], decl["n_evlrs"], decl["point_count"]
        )
    intensity = np.arange(n) % 65536
    return (
        bytes(head)
        + vlr_data
        + las_record_bytes(ints, point_format, intensity, extra)
        + b"".join(evlrs)
    )


def evlr_bytes(user: bytes, record: int, payload: bytes) -> bytes:
    """One EVLR: 60-byte header (reserved, user id, record id, u64 length, description)."""
    return struct.pack("<H16sHQ32s", 0, user, record, len(payload), b"") + payload


def grid_points(n: int = 1000, seed: int = 0) -> np.ndarray:
    """Seeded integer coordinates in a 10 x 10 x 8 m box at 1 cm (with scale 0.01)."""
    rng = np.random.default_rng(seed)
    return rng.integers([0, 0, 0], [1000, 1000, 800], (n, 3)).astype(np.int32)


def ply_bytes(
    xyz: np.ndarray,
    encoding: str = "binary_little_endian",
    *,
    before: tuple[tuple[str, int, str, bytes], ...] = (),
    after: tuple[tuple[str, int, str, bytes], ...] = (),
    vertices: int | None = None,
    extra: dict[str, np.ndarray] | None = None,
) -> bytes:
    """A PLY file: float64 x, y, z (+ ``extra`` float32 properties) per vertex; elements
    ``before``/``after`` the vertices as (name, count, property lines, data bytes)."""
    extra = extra or {}
    n = len(xyz) if vertices is None else vertices
    lines = [b"ply", f"format {encoding} 1.0".encode(), b"comment hand-built"]
    for name, count, props, _ in before:
        lines += [f"element {name} {count}".encode(), props.encode()]
    lines += [
        f"element vertex {n}".encode(),
        b"property double x",
        b"property double y",
        b"property double z",
    ] + [f"property float {k}".encode() for k in extra]
    for name, count, props, _ in after:
        lines += [f"element {name} {count}".encode(), props.encode()]
    lines.append(b"end_header")
    if encoding == "ascii":
        cols = [np.asarray(xyz, float)] + [np.asarray(v, float)[:, None] for v in extra.values()]
        table = np.hstack(cols)
        body = b"".join((" ".join(repr(float(v)) for v in row) + "\n").encode() for row in table)
    else:
        order = "<" if encoding == "binary_little_endian" else ">"
        dtype = np.dtype([(c, order + "f8") for c in "xyz"] + [(k, order + "f4") for k in extra])
        rec = np.zeros(len(xyz), dtype)
        for i, c in enumerate("xyz"):
            rec[c] = xyz[:, i]
        for k, v in extra.items():
            rec[k] = v
        body = rec.tobytes()
    data_before = b"".join(d for *_, d in before)
    data_after = b"".join(d for *_, d in after)
    return b"\n".join(lines) + b"\n" + data_before + body + data_after


def lzf_literals(data: bytes) -> bytes:
    """``data`` as a valid LZF stream of literal runs only (an independent encoder)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i : i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def pcd_bytes(
    xyz: np.ndarray,
    encoding: str = "binary",
    *,
    intensity: np.ndarray | None = None,
    points: int | None = None,
    width: int | None = None,
    sizes: tuple[int, int] | None = None,
) -> bytes:
    """A PCD v0.7 file of float32 x, y, z and intensity; ``points``/``width`` overwrite what
    the header declares, ``sizes`` the binary_compressed (compressed, uncompressed) sizes."""
    n = len(xyz)
    intensity = np.arange(n, dtype=np.float32) if intensity is None else intensity
    declared = n if points is None else points
    head = (
        f"# .PCD v0.7 - hand-built\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\n"
        f"TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {declared if width is None else width}\n"
        f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {declared}\nDATA {encoding}\n"
    ).encode()
    table = np.column_stack([np.asarray(xyz, np.float32), intensity]).astype("<f4")
    if encoding == "ascii":
        return head + b"".join(
            (" ".join(repr(float(v)) for v in row) + "\n").encode() for row in table
        )
    if encoding == "binary":
        return head + table.tobytes()
    columns = np.ascontiguousarray(table.T).tobytes()  # field by field
    packed = lzf_literals(columns)
    compressed, uncompressed = sizes or (len(packed), len(columns))
    return head + struct.pack("<II", compressed, uncompressed) + packed


# --- files of the bad-input catalogue (tests/bad_inputs/catalogue.py) ---------------------------

CATALOGUE_OFFSET = (300000.0, 4100000.0, 50.0)


def catalogue_points(n: int) -> np.ndarray:
    """Seeded integer coordinates whose extremes are the corners (0, 0, 0) and (999, 999, 799):
    at scale 0.01 the bounds are the offset plus (0..9.99, 0..9.99, 0..7.99) m."""
    ints = grid_points(n, seed=9)
    ints[0], ints[1] = (0, 0, 0), (999, 999, 799)
    return ints


def write_las_vlr_bomb(path: Path) -> Path:
    """3 KB: a LAS 1.2 header claiming 4,000,000,000 VLRs, then random bytes."""
    head = las_bytes(catalogue_points(10), n_vlrs=4_000_000_000)[:227]
    tail = np.random.default_rng(5).integers(0, 256, 3000 - 227, dtype=np.uint8).tobytes()
    path.write_bytes(head + tail)
    return path


def write_las_claiming(path: Path, n: int, **fields: int) -> Path:
    """A LAS of ``n`` points whose header fields are overwritten with ``fields``."""
    path.write_bytes(las_bytes(catalogue_points(n), offset=CATALOGUE_OFFSET, **fields))
    return path


def write_las_cut(path: Path, n: int, kept: int) -> Path:
    """A LAS of ``n`` points cut exactly after point record ``kept``."""
    data = las_bytes(catalogue_points(n), offset=CATALOGUE_OFFSET)
    path.write_bytes(data[: 227 + kept * LAS_RECORD[0]])
    return path


def write_las_zero_bounds(path: Path) -> Path:
    """A LAS whose header min/max are all 0 (like the real pointcloudset_test_tree.las)."""
    path.write_bytes(
        las_bytes(
            catalogue_points(2000), offset=CATALOGUE_OFFSET, header_bounds=((0, 0, 0), (0, 0, 0))
        )
    )
    return path


def write_pcd_compressed_empty(path: Path) -> Path:
    """A binary_compressed PCD of 2000 points whose compressed size is 0, no data after it."""
    head = pcd_bytes(catalogue_points(2000) * 0.01, "binary_compressed").split(b"DATA ")[0]
    path.write_bytes(head + b"DATA binary_compressed\n" + struct.pack("<II", 0, 2000 * 16))
    return path


def write_ply_face_before_vertex(path: Path, faces: int = 2) -> Path:
    """A binary PLY of 2000 vertices after ``faces`` declared triangles (2 present)."""
    triangles = struct.pack("<B3i", 3, 0, 1, 2) * 2
    face = ("face", faces, "property list uchar int vertex_indices", triangles)
    path.write_bytes(ply_bytes(catalogue_points(2000) * 0.25, before=(face,)))
    return path
