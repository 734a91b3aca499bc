"""The LAS/LAZ header checked against the file before laspy sees it.

laspy trusts its header: it loops over the VLR count, reads each record length and sizes its
point buffer from the point count, so a few wrong bytes cost minutes and gigabytes. Here the
fixed header (LAS 1.0-1.4 layout, read with ``struct``), the VLR and EVLR chains, the LASzip
record and the LAZ chunk table are checked against the file's size first; a field that cannot
be true is an :class:`InputError` naming the file and the field.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from canopy_kit.errors import InputError

LAS_MAGIC = b"LASF"
# Smallest header of each minor version 0-4 (LAS 1.0-1.2: 227, 1.3: 235, 1.4: 375 bytes).
HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
# Bytes of each standard point record format 0-10.
FORMAT_SIZES = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)
VLR_HEADER = 54
EVLR_HEADER = 60
EXTRA_BYTES_RECORD = 192
# Extra-bytes data types 1-10 (u1 i1 u2 i2 u4 i4 u8 i8 f4 f8); 11-30 are 2- and 3-arrays.
EXTRA_TYPE_SIZES = (1, 1, 2, 2, 4, 4, 8, 8, 4, 8)
# Coordinates are integers times the scale: below a nanometre the scale is corrupt (one
# real scanner file uses 3.7e-9), above a kilometre the points are a few corners.
MIN_SCALE, MAX_SCALE = 1e-9, 1e3
# LAZ holds at most this many points per compressed byte: constant points, the best case,
# came to about 150 (lazrs, 50,000-point chunks); a count above it cannot be decompressed.
MAX_LAZ_POINTS_PER_BYTE = 1000
LASZIP_USER, LASZIP_RECORD = b"laszip encoded", 22204
VARIABLE_CHUNKS = 0xFFFFFFFF
KEPT_VLRS = ((b"LASF_Spec", 4), (LASZIP_USER, LASZIP_RECORD))  # extra bytes, LASzip

ReadAt = Callable[[int, int], bytes]  # (position, size) -> the bytes there


@dataclass(frozen=True)
class LasLayout:
    """What the header declares, checked: where the points are and how many the file holds."""

    path: Path
    file_size: int
    version: str
    point_format: int
    compressed: bool
    record_length: int
    offset_to_points: int
    point_count: int  # as declared
    points_in_file: int  # complete records present (uncompressed), else the declared count
    scales: tuple[float, float, float]
    offsets: tuple[float, float, float]
    header_min: tuple[float, float, float]
    header_max: tuple[float, float, float]
    laz_chunk_points: int | None = None  # LAZ with fixed-size chunks: points per chunk

    @property
    def cut_short(self) -> bool:
        """True when the file holds fewer complete point records than its header declares."""
        return self.points_in_file < self.point_count


@dataclass(frozen=True)
class _Fixed:
    minor: int
    header_size: int
    offset_to_points: int
    n_vlrs: int
    format_byte: int
    record_length: int
    point_count: int
    scales: tuple[float, float, float]
    offsets: tuple[float, float, float]
    header_min: tuple[float, float, float]
    header_max: tuple[float, float, float]
    evlr_start: int
    n_evlrs: int


def _fail(path: Path, field: str, text: str, cause: str = "corrupt or truncated") -> InputError:
    return InputError(f"{path}: LAS header field '{field}' {text}; the file is {cause}")


def _fixed_header(path: Path, head: bytes, file_size: int) -> _Fixed:
    if len(head) < 227:
        raise InputError(
            f"{path}: LAS header is cut short ({len(head)} bytes, at least 227 needed)"
        )
    major, minor = head[24], head[25]
    if major != 1 or minor not in HEADER_SIZES:
        raise _fail(
            path, "version", f"is {major}.{minor}; LAS 1.0-1.4 is read", "corrupt or not LAS"
        )
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    fmt_byte, record_length, legacy_count = struct.unpack_from("<BHI", head, 104)
    scales = struct.unpack_from("<3d", head, 131)
    offsets = struct.unpack_from("<3d", head, 155)
    bounds = struct.unpack_from("<6d", head, 179)  # max x, min x, max y, min y, max z, min z
    if header_size < HEADER_SIZES[minor]:
        raise _fail(
            path,
            "header size",
            f"is {header_size} bytes, LAS 1.{minor} needs {HEADER_SIZES[minor]}",
        )
    if header_size > min(offset, file_size):
        raise _fail(
            path,
            "header size",
            f"is {header_size} bytes, more than the offset to "
            f"point data ({offset}) or the file ({file_size})",
        )
    evlr_start, n_evlrs, count = 0, 0, legacy_count
    if minor >= 4:
        evlr_start, n_evlrs, count = struct.unpack_from("<QIQ", head, 235)
    return _Fixed(
        minor,
        header_size,
        offset,
        n_vlrs,
        fmt_byte,
        record_length,
        count,
        scales,
        offsets,
        bounds[1::2],
        bounds[0::2],
        evlr_start,
        n_evlrs,
    )


def _check_scales(path: Path, fixed: _Fixed) -> None:
    scales, offsets = fixed.scales, fixed.offsets
    if not all(math.isfinite(s) and MIN_SCALE <= s <= MAX_SCALE for s in scales):
        raise InputError(
            f"{path}: LAS header scale factors {list(scales)} are not positive finite "
            f"numbers from {MIN_SCALE:g} to {MAX_SCALE:g}; the header is corrupt"
        )
    if not all(math.isfinite(o) for o in offsets):
        raise InputError(
            f"{path}: LAS header offsets {list(offsets)} are not finite; the header is corrupt"
        )


def _vlrs(path: Path, fixed: _Fixed, read_at: ReadAt) -> dict[tuple[bytes, int], bytes]:
    """The extra-bytes and LASzip VLR payloads; every VLR checked to end before the points."""
    space = fixed.offset_to_points - fixed.header_size
    if fixed.n_vlrs * VLR_HEADER > space:
        raise _fail(
            path,
            "number of variable length records",
            f"is {fixed.n_vlrs}: {fixed.n_vlrs} x {VLR_HEADER} bytes do not fit the "
            f"{space} bytes before the point data",
        )
    out: dict[tuple[bytes, int], bytes] = {}
    pos = fixed.header_size
    for i in range(fixed.n_vlrs):
        raw = read_at(pos, VLR_HEADER)
        whole = len(raw) == VLR_HEADER
        end = pos + VLR_HEADER + struct.unpack_from("<H", raw, 20)[0] if whole else -1
        if not pos + VLR_HEADER <= end <= fixed.offset_to_points:
            raise _fail(
                path,
                f"record length after header (VLR {i})",
                f"makes VLR {i} (at byte {pos}) end after the point data start "
                f"({fixed.offset_to_points})",
            )
        key = (raw[2:18].split(b"\0")[0], struct.unpack_from("<H", raw, 18)[0])
        if key in KEPT_VLRS and key not in out:
            out[key] = read_at(pos + VLR_HEADER, end - pos - VLR_HEADER)
        pos = end
    return out


def _check_evlrs(path: Path, fixed: _Fixed, file_size: int, read_at: ReadAt) -> int:
    """Walk the EVLR chain; the byte where the point data must end at the latest."""
    if fixed.n_evlrs == 0:
        return file_size
    start = fixed.evlr_start
    if not fixed.offset_to_points <= start <= file_size - fixed.n_evlrs * EVLR_HEADER:
        raise _fail(
            path,
            "start of first extended variable length record",
            f"is {start} with {fixed.n_evlrs} records: they do not fit between the point "
            f"data ({fixed.offset_to_points}) and the end of the file ({file_size})",
        )
    pos = start
    for i in range(fixed.n_evlrs):
        raw = read_at(pos, EVLR_HEADER)
        whole = len(raw) == EVLR_HEADER
        end = pos + EVLR_HEADER + struct.unpack_from("<Q", raw, 20)[0] if whole else -1
        if not pos + EVLR_HEADER <= end <= file_size:
            raise _fail(
                path,
                f"record length after header (EVLR {i})",
                f"makes EVLR {i} (at byte {pos}) end after the file ({file_size} bytes)",
            )
        pos = end
    return start


def _extra_bytes(path: Path, payload: bytes | None) -> int:
    """Bytes per point the Extra Bytes VLR describes (0 without one)."""
    if payload is None:
        return 0
    total = 0
    for i in range(len(payload) // EXTRA_BYTES_RECORD):
        data_type, options = payload[i * EXTRA_BYTES_RECORD + 2 : i * EXTRA_BYTES_RECORD + 4]
        if data_type == 0:
            total += options  # undocumented bytes: the options field holds their number
        elif data_type <= 30:
            total += EXTRA_TYPE_SIZES[(data_type - 1) % 10] * ((data_type - 1) // 10 + 1)
        else:
            raise InputError(
                f"{path}: extra-bytes descriptor {i} has data type {data_type} "
                "(LAS defines 0-30); the file is corrupt"
            )
    return total


def _check_record(path: Path, fixed: _Fixed, extra: int) -> int:
    """The record length the point format and its described extra bytes make (as laspy reads
    it: an Extra Bytes VLR is ignored when the record has no room beyond the standard)."""
    fmt = fixed.format_byte & 0x3F
    if fmt >= len(FORMAT_SIZES):
        raise _fail(path, "point data record format", f"is {fmt}; LAS defines 0-10")
    if fixed.record_length == FORMAT_SIZES[fmt]:
        return FORMAT_SIZES[fmt]
    needed = FORMAT_SIZES[fmt] + extra
    if fixed.record_length < needed:
        raise _fail(
            path,
            "point data record length",
            f"is {fixed.record_length} bytes, less than point format {fmt}'s "
            f"{FORMAT_SIZES[fmt]} bytes plus {extra} extra bytes",
        )
    return needed


def _laz_point_bytes(
    path: Path, fixed: _Fixed, laszip: bytes | None, data_end: int, read_at: ReadAt
) -> int | None:
    """A LAZ point count must fit its LASzip record and chunk table (no decompression); the
    points per chunk when chunks have one size."""
    if laszip is None or len(laszip) < 34:
        raise InputError(
            f"{path}: LAZ file without a valid LASzip record (VLR 'laszip encoded' "
            f"{LASZIP_RECORD}); the file is corrupt"
        )
    compressor = struct.unpack_from("<H", laszip, 0)[0]
    (chunk_size,) = struct.unpack_from("<I", laszip, 12)
    (n_items,) = struct.unpack_from("<H", laszip, 32)
    if len(laszip) < 34 + 6 * n_items:
        raise InputError(
            f"{path}: LASzip record lists {n_items} items in {len(laszip)} bytes; "
            "the file is corrupt"
        )
    item_bytes = sum(struct.unpack_from("<H", laszip, 34 + 6 * i + 2)[0] for i in range(n_items))
    if item_bytes != fixed.record_length:
        raise _fail(
            path,
            "point data record length",
            f"is {fixed.record_length} bytes, the LASzip items make {item_bytes}",
        )
    data_bytes = data_end - fixed.offset_to_points
    if fixed.point_count > MAX_LAZ_POINTS_PER_BYTE * data_bytes:
        raise _fail(
            path,
            "number of point records",
            f"is {fixed.point_count}: {data_bytes} compressed bytes hold at most "
            f"{MAX_LAZ_POINTS_PER_BYTE * data_bytes}",
        )
    if compressor not in (2, 3):
        return None  # not chunked: no chunk table
    table = _chunk_table_offset(fixed, read_at, data_end)
    if not fixed.offset_to_points + 8 <= table <= data_end - 8:
        raise InputError(
            f"{path}: LAZ chunk table offset {table} lies outside the point data "
            f"(bytes {fixed.offset_to_points}-{data_end}); the file is corrupt or "
            "truncated"
        )
    version, n_chunks = struct.unpack("<II", read_at(table, 8))
    raw_points = table - fixed.offset_to_points - 8
    # Each chunk starts with one uncompressed point.
    if version != 0 or n_chunks * fixed.record_length > raw_points:
        raise InputError(
            f"{path}: LAZ chunk table (version {version}) lists {n_chunks} chunks "
            f"that do not fit {raw_points} compressed bytes; the file is corrupt or "
            "truncated"
        )
    if chunk_size != VARIABLE_CHUNKS and not (
        (n_chunks - 1) * chunk_size < fixed.point_count <= n_chunks * chunk_size
    ):
        raise _fail(
            path,
            "number of point records",
            f"is {fixed.point_count}; the LAZ chunk table lists {n_chunks} chunks of "
            f"{chunk_size} points",
        )
    return None if chunk_size == VARIABLE_CHUNKS else chunk_size


def _chunk_table_offset(fixed: _Fixed, read_at: ReadAt, data_end: int) -> int:
    """Where the chunk table starts: the first 8 bytes of the point data, or the last 8 of the
    file when the writer could not seek back (-1)."""
    (table,) = struct.unpack("<q", read_at(fixed.offset_to_points, 8).ljust(8, b"\0"))
    if table == -1:
        (table,) = struct.unpack("<q", read_at(data_end - 8, 8).ljust(8, b"\0"))
    return table


def read_las_layout(path: Path) -> LasLayout:
    """Check a LAS/LAZ header against the file; InputError naming the field that cannot be true.

    Reads the header, the VLRs and a few bytes of the LAZ chunk table; never the points.
    """
    file_size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(max(HEADER_SIZES.values()))
        if not head.startswith(LAS_MAGIC):
            raise InputError(f"{path}: not a LAS/LAZ file (no 'LASF' signature)")

        def read_at(pos: int, n: int) -> bytes:
            fh.seek(pos)
            return fh.read(n)

        fixed = _fixed_header(path, head, file_size)
        _check_scales(path, fixed)
        if fixed.offset_to_points > file_size:
            raise _fail(
                path,
                "offset to point data",
                f"is {fixed.offset_to_points}, beyond the end of the file ({file_size})",
            )
        vlrs = _vlrs(path, fixed, read_at)
        data_end = _check_evlrs(path, fixed, file_size, read_at)
        needed = _check_record(path, fixed, _extra_bytes(path, vlrs.get((b"LASF_Spec", 4))))
        compressed = fixed.format_byte & 0xC0 == 0x80  # bit 7 without bit 6, as laspy reads it
        if fixed.point_count == 0:
            raise InputError(f"{path}: LAS file has no points")
        chunk_points = None
        if compressed:
            chunk_points = _laz_point_bytes(
                path, fixed, vlrs.get((LASZIP_USER, LASZIP_RECORD)), data_end, read_at
            )
            in_file = fixed.point_count
        else:
            in_file = min(
                fixed.point_count, (data_end - fixed.offset_to_points) // fixed.record_length
            )
            _check_point_space(path, fixed, in_file, needed)
    return LasLayout(
        path,
        file_size,
        f"1.{fixed.minor}",
        fixed.format_byte & 0x3F,
        compressed,
        fixed.record_length,
        fixed.offset_to_points,
        fixed.point_count,
        in_file,
        fixed.scales,
        fixed.offsets,
        fixed.header_min,
        fixed.header_max,
        chunk_points,
    )


def _check_point_space(path: Path, fixed: _Fixed, in_file: int, needed: int) -> None:
    """Fewer records than declared is a cut file, unless the record length is the liar."""
    if in_file == fixed.point_count:
        return
    if fixed.record_length != needed:
        raise _fail(
            path,
            "point data record length",
            f"is {fixed.record_length} bytes (point format {fixed.format_byte & 0x3F} "
            f"with its extra bytes: {needed}) and the file holds only {in_file} of the "
            f"{fixed.point_count} records declared",
        )
    if in_file == 0:
        raise InputError(
            f"{path}: LAS file is truncated: no complete point record of "
            f"{fixed.record_length} bytes after byte {fixed.offset_to_points} "
            f"(header declares {fixed.point_count} points)"
        )
