"""Every LAS/LAZ file canopy-kit writes is valid by the ASPRS LAS 1.2/1.4 specification.

Checked twice: with laspy, and with an independent reader of the public header block (and,
for uncompressed files, of the point records) written here from the specification's field
offsets with ``struct``. Field by field: signature, version, system identifier, generating
software, creation date, header size, offset to the points, point format and record length,
point counts (legacy and 64-bit), scales, offsets and bounds (equal to the points'), the
global encoding (GPS time type matching the times, WKT bit), return numbers in 1..number of
returns. Also the map.laz a pipeline run writes (the shared ``tiny_pistachio_run``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from datetime import UTC, date, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from canopy_kit import __version__
from canopy_kit.core.cloud import PointCloud
from canopy_kit.io.las import read_las, write_las

laspy = pytest.importorskip("laspy")

GPS_WEEK = 604_800.0
# The 2020s in Adjusted Standard GPS Time (GPS seconds - 1e9): 2020-01-01 is 2.62e8,
# 2030-01-01 5.77e8; in Unix seconds 1.578e9 and 1.893e9.
ADJUSTED_2020S = (2.6e8, 5.8e8)
UNIX_2020S = (1.578e9, 1.893e9)
# Bytes of the standard point records (LAS 1.4 table of point data record formats 0-10).
RECORD_SIZES = {0: 20, 1: 28, 2: 26, 3: 34, 6: 30, 7: 36, 8: 38}


# -- an independent reader of the public header block ----------------------------------------
@dataclass
class Header:
    signature: bytes
    file_source_id: int
    global_encoding: int
    version: tuple[int, int]
    system_identifier: bytes
    generating_software: bytes
    creation_day: int
    creation_year: int
    header_size: int
    offset_to_points: int
    n_vlrs: int
    point_format_byte: int
    record_length: int
    legacy_count: int
    legacy_by_return: tuple[int, ...]
    scales: tuple[float, float, float]
    offsets: tuple[float, float, float]
    maxs: tuple[float, float, float]
    mins: tuple[float, float, float]
    count: int  # the 64-bit count of LAS 1.4, else the legacy one
    by_return: tuple[int, ...]  # 15 counts in LAS 1.4, else the legacy 5

    @property
    def point_format(self) -> int:
        return self.point_format_byte & 0x3F  # LAZ sets bit 7 (and 6) of the format byte


def parse_header(path: Path) -> Header:
    """The public header block by the specification's offsets (LAS 1.2: 227 bytes, 1.4: 375)."""
    data = path.read_bytes()
    (sig, source, encoding) = struct.unpack_from("<4sHH", data, 0)
    major, minor = struct.unpack_from("<BB", data, 24)
    system_id, software = struct.unpack_from("<32s32s", data, 26)
    day, year, header_size, offset, n_vlrs = struct.unpack_from("<HHHII", data, 90)
    fmt_byte, record_length = struct.unpack_from("<BH", data, 104)
    legacy_count, *legacy_by_return = struct.unpack_from("<I5I", data, 107)
    scales = struct.unpack_from("<3d", data, 131)
    offsets = struct.unpack_from("<3d", data, 155)
    max_x, min_x, max_y, min_y, max_z, min_z = struct.unpack_from("<6d", data, 179)
    count, by_return = legacy_count, tuple(legacy_by_return)
    if minor >= 4:
        count, *by_return15 = struct.unpack_from("<Q15Q", data, 247)
        by_return = tuple(by_return15)
    return Header(
        sig,
        source,
        encoding,
        (major, minor),
        system_id,
        software,
        day,
        year,
        header_size,
        offset,
        n_vlrs,
        fmt_byte,
        record_length,
        legacy_count,
        tuple(legacy_by_return),
        scales,
        offsets,
        (max_x, max_y, max_z),
        (min_x, min_y, min_z),
        count,
        by_return,
    )


def parse_points(path: Path, head: Header) -> dict[str, np.ndarray]:
    """X, Y, Z, return number, number of returns and GPS time of an uncompressed file's
    records, by the specification's byte layout of formats 1, 3 (legacy) and 6, 7, 8."""
    fmt = head.point_format
    raw = np.frombuffer(
        path.read_bytes(), np.uint8, head.count * head.record_length, head.offset_to_points
    ).reshape(head.count, head.record_length)

    def field(start: int, dtype: str) -> np.ndarray:
        size = np.dtype(dtype).itemsize
        return raw[:, start : start + size].copy().view(dtype)[:, 0]

    out = {axis: field(4 * i, "<i4") for i, axis in enumerate("XYZ")}
    bits = raw[:, 14]
    if fmt < 6:
        out["return_number"], out["number_of_returns"] = bits & 0x07, (bits >> 3) & 0x07
        out["gps_time"] = field(20, "<f8")  # after scan angle, user data, point source id
    else:
        out["return_number"], out["number_of_returns"] = bits & 0x0F, bits >> 4
        out["gps_time"] = field(22, "<f8")
    return out


def expected_header_size(minor: int) -> int:
    return {2: 227, 4: 375}[minor]


def assert_valid(
    path: Path, cloud: PointCloud | None = None, adjusted_range: tuple = ADJUSTED_2020S
) -> Header:
    """Every check of the module docstring on ``path`` (``cloud``: what was written; times
    in Adjusted Standard GPS Time within ``adjusted_range``)."""
    head = parse_header(path)
    las = laspy.read(path)
    # identification
    assert head.signature == b"LASF"
    assert head.version in ((1, 2), (1, 4))
    assert head.header_size == expected_header_size(head.version[1])
    assert head.system_identifier == b"OTHER".ljust(32, b"\0")  # the rest null (spec)
    software = f"canopy-kit {__version__}".encode()
    assert head.generating_software == software.ljust(32, b"\0")
    created = date(head.creation_year, 1, 1) + timedelta(days=head.creation_day - 1)
    today = datetime.now(UTC).date()  # the spec's GMT day
    assert today - timedelta(days=1) <= created <= today
    # layout
    compressed = path.suffix.lower() == ".laz"
    assert bool(head.point_format_byte & 0x80) == compressed
    fmt = head.point_format
    assert fmt == las.header.point_format.id
    assert head.record_length == RECORD_SIZES[fmt] + las.header.point_format.num_extra_bytes
    assert head.offset_to_points >= head.header_size
    assert head.n_vlrs == len(las.header.vlrs) + compressed  # laspy hides LASzip's VLR
    assert (head.version == (1, 4)) == (fmt >= 6 or bool(head.global_encoding & 0x10))
    # counts
    n = len(las.points)
    assert head.count == n
    returns = np.asarray(las.return_number)
    per_return = [int(np.sum(returns == r)) for r in range(1, len(head.by_return) + 1)]
    assert list(head.by_return) == per_return
    if head.version == (1, 2):
        assert head.legacy_count == n
    else:  # 1.4 without legacy compatibility (formats 6+, or a WKT CRS): legacy fields zero
        assert head.legacy_count == 0 and head.legacy_by_return == (0,) * 5
    # coordinates
    assert head.scales == tuple(las.header.scales)
    assert head.offsets == tuple(las.header.offsets)
    ints = np.column_stack([np.asarray(las[c]) for c in "XYZ"]).astype(np.int64)
    if not compressed:
        own = parse_points(path, head)
        np.testing.assert_array_equal(np.column_stack([own[c] for c in "XYZ"]), ints)
    lo = ints.min(axis=0) * np.asarray(head.scales) + np.asarray(head.offsets)
    hi = ints.max(axis=0) * np.asarray(head.scales) + np.asarray(head.offsets)
    np.testing.assert_allclose(head.mins, lo, rtol=0, atol=1e-9)
    np.testing.assert_allclose(head.maxs, hi, rtol=0, atol=1e-9)
    if cloud is not None:
        np.testing.assert_allclose(head.mins, cloud.absolute_xyz.min(axis=0), rtol=0, atol=6e-4)
        np.testing.assert_allclose(head.maxs, cloud.absolute_xyz.max(axis=0), rtol=0, atol=6e-4)
    # returns: 1 <= return number <= number of returns
    number = np.asarray(las.return_number).astype(int)
    count = np.asarray(las.number_of_returns).astype(int)
    if not compressed:
        np.testing.assert_array_equal(own["return_number"], number)
        np.testing.assert_array_equal(own["number_of_returns"], count)
    assert count.min() >= 1 and number.min() >= 1 and np.all(number <= count)
    # global encoding: only defined bits; GPS time type as the times say
    reserved = 0xFFFE if head.version == (1, 2) else 0xFFE0
    assert head.global_encoding & reserved == 0
    if fmt >= 6:
        assert head.global_encoding & 0x10, "point formats 6-10 must use WKT"
    if "gps_time" in las.point_format.standard_dimension_names:
        times = np.asarray(las.gps_time)
        if not compressed:
            np.testing.assert_array_equal(own["gps_time"], times)
        if head.global_encoding & 1:
            assert adjusted_range[0] <= times.min() <= times.max() <= adjusted_range[1]
        else:
            assert 0 <= times.min() <= times.max() <= GPS_WEEK
    return head


# -- synthetic clouds --------------------------------------------------------------------------
UNIX_2024 = 1_717_000_000.0  # 2024-05-29
WKT_ONLY = (
    'LOCAL_CS["orchard frame",LOCAL_DATUM["tape",0],UNIT["metre",1],AXIS["X",EAST],AXIS["Y",NORTH]]'
)


def drive(n: int = 3000, times: np.ndarray | None = None, crs: str | None = "EPSG:32610", **extra):
    """A cloud as mapping gives it: intensity, absolute ``gps_time`` (Unix s), no returns."""
    rng = np.random.default_rng(5)
    fields = {
        "intensity": rng.integers(0, 255, n).astype(np.uint16),
        "gps_time": UNIX_2024 + np.sort(rng.uniform(0, 600, n)) if times is None else times,
        "ring": rng.integers(0, 32, n).astype(np.uint16),
        **extra,
    }
    xyz = rng.uniform([-40, -60, -1], [40, 60, 7], (n, 3))
    return PointCloud(xyz, fields, crs=crs, origin=np.array([700000.0, 4100000.0, 50.0]))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize(
    "point_format,crs,version",
    [(None, "EPSG:32610", (1, 2)), (6, "EPSG:32610", (1, 4)), (None, WKT_ONLY, (1, 4))],
    ids=["format1-epsg", "format6-epsg", "format1-wkt"],
)
def test_written_file_is_valid_field_by_field(tmp_path, suffix, point_format, crs, version):
    cloud = drive(crs=crs)
    path = write_las(tmp_path / f"map{suffix}", cloud, point_format=point_format)
    head = assert_valid(path, cloud)
    assert head.version == version
    assert head.point_format == (1 if point_format is None else point_format)
    assert head.global_encoding & 1, "Unix times are written as Adjusted Standard GPS Time"
    if version == (1, 4):
        assert head.global_encoding & 0x10  # WKT: formats 6+ and a CRS known only as WKT
    las = laspy.read(path)
    np.testing.assert_array_equal(las.return_number, 1)  # one return per pulse
    np.testing.assert_array_equal(las.number_of_returns, 1)
    back = read_las(path)
    np.testing.assert_array_equal(back.fields["gps_time"], cloud.fields["gps_time"])


def test_adjusted_gps_time_is_unix_minus_the_gps_epoch_leap_seconds_and_1e9(tmp_path) -> None:
    # 2017-01-01T00:00:00Z: Unix 1483228800 is GPS second 1167264018 (18 leap seconds).
    unix = 1_483_228_800.0 + np.array([0.0, 0.25, 3600.5])
    path = write_las(tmp_path / "t.las", drive(n=3, times=unix))
    assert parse_header(path).global_encoding & 1
    np.testing.assert_array_equal(laspy.read(path).gps_time, 1_167_264_018 - 1e9 + unix - unix[0])
    np.testing.assert_array_equal(read_las(path).fields["gps_time"], unix)


def test_unix_times_of_the_2020s_survive_a_round_trip_bit_for_bit(tmp_path) -> None:
    rng = np.random.default_rng(0)
    unix = np.sort(rng.uniform(*UNIX_2020S, 5000))
    path = write_las(tmp_path / "t.laz", drive(n=5000, times=unix))
    assert_valid(path)
    np.testing.assert_array_equal(read_las(path).fields["gps_time"], unix)


def test_gps_week_seconds_keep_the_bit_clear(tmp_path) -> None:
    week = np.linspace(345_600.0, 345_700.0, 500)
    path = write_las(tmp_path / "t.las", drive(n=500, times=week))
    head = assert_valid(path)
    assert head.global_encoding & 1 == 0
    np.testing.assert_array_equal(laspy.read(path).gps_time, week)
    np.testing.assert_array_equal(read_las(path).fields["gps_time"], week)


def test_another_programs_adjusted_times_are_kept_exactly(tmp_path) -> None:
    """Times finer than Unix seconds hold (a 2016 airborne file: 2.2e8 s, 3e-8 s steps) are
    read as stored and written back unchanged with the bit set."""
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    header.scales, header.offsets = np.full(3, 0.01), np.zeros(3)
    las = laspy.LasData(header)
    n = 200
    las.X, las.Y, las.Z = (np.arange(n, dtype=np.int32) for _ in range(3))
    adjusted = 220_367_380.8186882 + np.arange(n) * 2.98023223876953125e-08
    las.gps_time = adjusted
    las.return_number, las.number_of_returns = np.full(n, 2), np.full(n, 3)
    las.write(tmp_path / "foreign.las")
    cloud = read_las(tmp_path / "foreign.las")
    np.testing.assert_array_equal(cloud.fields["gps_time"], adjusted)
    path = write_las(tmp_path / "copy.las", cloud, scale=0.01)
    assert_valid(path, adjusted_range=(2.2e8, 2.3e8))
    assert parse_header(path).global_encoding & 1
    copy = laspy.read(path)
    np.testing.assert_array_equal(copy.gps_time, adjusted)
    np.testing.assert_array_equal(copy.return_number, 2)  # given returns are kept
    np.testing.assert_array_equal(copy.number_of_returns, 3)


def test_given_return_numbers_are_kept_and_zero_made_valid(tmp_path) -> None:
    number = np.array([0, 1, 2, 1, 3, 0], np.uint8)
    count = np.array([0, 2, 2, 0, 2, 3], np.uint8)
    cloud = drive(n=6, return_number=number, number_of_returns=count)
    las = laspy.read(write_las(tmp_path / "t.las", cloud))
    np.testing.assert_array_equal(las.return_number, [1, 1, 2, 1, 3, 1])  # 0 (unknown): 1
    np.testing.assert_array_equal(las.number_of_returns, [1, 2, 2, 1, 3, 3])  # >= return no.
    only_number = drive(n=3, return_number=np.array([2, 0, 1], np.uint8))
    path = write_las(tmp_path / "n.las", only_number)
    assert_valid(path)
    np.testing.assert_array_equal(laspy.read(path).number_of_returns, [2, 1, 1])


def test_a_cloud_without_times_or_crs_is_valid(tmp_path) -> None:
    cloud = PointCloud(np.random.default_rng(1).uniform(-5, 5, (100, 3)))
    for fmt in (0, 6):
        path = write_las(tmp_path / f"f{fmt}.laz", cloud, point_format=fmt)
        head = assert_valid(path, cloud)
        assert head.global_encoding & 1 == 0


# -- the map.laz of a pipeline run -------------------------------------------------------------
@pytest.mark.slow
def test_map_laz_of_a_pipeline_run_is_valid(tiny_pistachio_run) -> None:
    path = tiny_pistachio_run.out_dir / "map.laz"
    head = assert_valid(path)
    assert head.global_encoding & 1, "the bag's Unix times as Adjusted Standard GPS Time"
    times = read_las(path).fields["gps_time"]
    assert UNIX_2020S[0] <= times.min() <= times.max() <= UNIX_2020S[1]  # the bag's clock
