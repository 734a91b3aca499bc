"""The PLY and PCD readers against hand-built files: headers checked against the file, the
points present read (cut files with a warning), non-finite points dropped, Open3D's field
names kept. The truth is what tests/bad_inputs/clouds.py wrote into each file."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from bad_inputs.clouds import grid_points, lzf_literals, pcd_bytes, ply_bytes
from test_io_clouds import read_with_warnings

from canopy_kit.errors import InputError, foreign_message
from canopy_kit.io.clouds import read_cloud
from canopy_kit.io.info import describe_path
from canopy_kit.io.lzf import lzf_decompress

XYZ = grid_points(300) * 0.01 + np.array([500.0, 200.0, 10.0])
TRIANGLES = struct.pack("<B3i", 3, 0, 1, 2) * 2


def write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def refused(path: Path, *fragments: str) -> str:
    with pytest.raises(InputError) as err:
        read_cloud(path)
    message = str(err.value)
    assert str(path) in message and "\n" not in message
    for fragment in fragments:
        assert fragment in message, message
    return message


# --- PLY --------------------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_reads_exactly(tmp_path: Path, encoding: str) -> None:
    q = np.arange(len(XYZ), dtype=np.float32) / 4
    cloud, notes = read_with_warnings(
        write(tmp_path, "a.ply", ply_bytes(XYZ, encoding, extra={"q": q}))
    )
    assert notes == []
    np.testing.assert_array_equal(cloud.absolute_xyz, XYZ)
    np.testing.assert_array_equal(cloud.fields["q"], q)
    assert cloud.fields["q"].dtype == np.float32


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
def test_ply_face_before_vertex(tmp_path: Path, encoding: str) -> None:
    # Before: NaN bounds from info, MemoryError 3.52 PiB from volume.
    if encoding == "ascii":
        faces = ("face", 2, "property list uchar int vertex_indices", b"3 0 1 2\n4 0 1 2 3\n")
    else:  # a triangle and a quad: rows of two lengths, walked one by one
        faces = (
            "face",
            2,
            "property list uchar int vertex_indices",
            struct.pack("<B3i", 3, 0, 1, 2) + struct.pack("<B4i", 4, 0, 1, 2, 3),
        )
    path = write(tmp_path, "f.ply", ply_bytes(XYZ, encoding, before=(faces,)))
    cloud, notes = read_with_warnings(path)
    assert notes == []
    np.testing.assert_array_equal(cloud.absolute_xyz, XYZ)
    facts = describe_path(path)
    np.testing.assert_array_equal(facts["bounds"]["min"], XYZ.min(axis=0))


def test_ply_face_before_vertex_declared_longer_than_it_is(tmp_path: Path) -> None:
    faces = ("face", 1000, "property list uchar int vertex_indices", TRIANGLES)
    refused(
        write(tmp_path, "f.ply", ply_bytes(XYZ, before=(faces,))),
        "'face' element before the vertices holds",
        "of its 1000 rows",
    )


def test_ply_faces_after_vertices_cut_short(tmp_path: Path) -> None:
    faces = ("face", 50, "property list uchar int vertex_indices", TRIANGLES)
    cloud, notes = read_with_warnings(write(tmp_path, "f.ply", ply_bytes(XYZ, after=(faces,))))
    np.testing.assert_array_equal(cloud.absolute_xyz, XYZ)
    assert len(notes) == 1 and "'face' element after the vertices is cut short" in notes[0]


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
def test_ply_more_vertices_declared_than_present(tmp_path: Path, encoding: str) -> None:
    data = ply_bytes(XYZ, encoding, vertices=10**9)
    cloud, notes = read_with_warnings(write(tmp_path, "v.ply", data))
    np.testing.assert_array_equal(cloud.absolute_xyz, XYZ)
    assert notes == [
        (
            f"{tmp_path / 'v.ply'}: only {len(XYZ)} of 1000000000 points are in the "
            "file (cut short, or the header's point count is wrong); read those"
        )
    ]


@pytest.mark.parametrize(
    "text,named",
    [
        (
            b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty uchar a\nend_header\n",
            "0 'vertex' elements",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n",
            "no z property",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n",
            "line 4: unknown property type 'float128'",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex -3\nproperty float x\nend_header\n",
            "count '-3' is not a non-negative integer",
        ),
        (b"ply\nformat compressed 1.0\nelement vertex 1\nend_header\n", "line 2: unexpected"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "no 'end_header' line"),
    ],
)
def test_ply_bad_headers_are_named(tmp_path: Path, text: bytes, named: str) -> None:
    refused(write(tmp_path, "h.ply", text + b"\0" * 64), named)


def test_ply_lists_and_unusual_types(tmp_path: Path) -> None:
    head = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
        b"property float y\nproperty float z\nproperty ushort intensity\nproperty float nx\n"
        b"property list uchar float h\nend_header\n"
    )
    rows = b"".join(
        struct.pack("<3fHfB2f", i, 2 * i, 3 * i, 1000 + i, 0.5, 2, i, -i) for i in range(3)
    )
    cloud, _ = read_with_warnings(write(tmp_path, "l.ply", head + rows))
    np.testing.assert_array_equal(cloud.absolute_xyz[:, 1], [0, 2, 4])
    np.testing.assert_array_equal(cloud.fields["intensity"], [1000, 1001, 1002])  # Open3D dropped
    np.testing.assert_array_equal(cloud.fields["nx"], [0.5] * 3)  # alone: not a normals field
    np.testing.assert_array_equal(cloud.fields["h"], [[0, 0], [1, -1], [2, -2]])
    longer = struct.pack("<3fHfB3f", 1, 1, 1, 1, 1, 3, 1, 1, 1)  # a list of 3 after one of 2
    varying = head.replace(b"vertex 3", b"vertex 2") + rows[:27] + longer
    refused(write(tmp_path, "q.ply", varying), "changes length from row to row")


def test_ply_ascii_vertex_list(tmp_path: Path) -> None:
    head = (
        b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        b"property list uchar int ids\nproperty float z\nend_header\n"
    )
    cloud, _ = read_with_warnings(write(tmp_path, "l.ply", head + b"1 2 2 7 8 3\n4 5 2 9 10 6\n"))
    np.testing.assert_array_equal(cloud.absolute_xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(cloud.fields["ids"], [[7, 8], [9, 10]])
    refused(write(tmp_path, "v.ply", head + b"1 2 2 7 8 3\n4 5 1 9 6 0\n"), "changes length")


def test_ply_normals_and_colours_like_open3d(tmp_path: Path) -> None:
    head = (
        b"ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
        b"property double z\nproperty float nx\nproperty float ny\nproperty float nz\n"
        b"property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    cloud, _ = read_with_warnings(
        write(tmp_path, "c.ply", head + b"1 2 3 0 0 1 10 20 30\n4 5 6 1 0 0 1 2 3\n")
    )
    np.testing.assert_array_equal(cloud.fields["normals"], [[0, 0, 1], [1, 0, 0]])
    np.testing.assert_array_equal(cloud.fields["colors"], [[10, 20, 30], [1, 2, 3]])
    assert cloud.fields["colors"].dtype == np.uint8
    bad = head + b"1 2 3 0 0 1 300 20 30\n4 5 6 1 0 0 1 2 3\n"
    refused(write(tmp_path, "b.ply", bad), "field 'red' (uint8) holds 300.0 at point 0")


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_non_finite_points_are_dropped_with_a_warning(tmp_path: Path, suffix: str) -> None:
    xyz = XYZ.copy()
    xyz[[3, 7], 1] = np.nan
    xyz[11, 2] = np.inf
    data = ply_bytes(xyz) if suffix == ".ply" else pcd_bytes(xyz, "binary")
    cloud, notes = read_with_warnings(write(tmp_path, f"n{suffix}", data))
    assert len(cloud) == len(XYZ) - 3 and np.isfinite(cloud.xyz).all()
    assert notes == [
        (
            f"{tmp_path / f'n{suffix}'}: dropped 3 of {len(XYZ)} points with non-finite "
            "coordinates (NaN or infinite x/y/z)"
        )
    ]
    data = ply_bytes(xyz * np.nan) if suffix == ".ply" else pcd_bytes(xyz * np.nan, "binary")
    refused(write(tmp_path, f"all{suffix}", data), f"all {len(XYZ)} points have non-finite")


# --- PCD --------------------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_reads_exactly(tmp_path: Path, encoding: str) -> None:
    xyz = XYZ.astype(np.float32)
    cloud, notes = read_with_warnings(write(tmp_path, "a.pcd", pcd_bytes(xyz, encoding)))
    assert notes == []
    np.testing.assert_array_equal(cloud.absolute_xyz, xyz.astype(np.float64))
    np.testing.assert_array_equal(cloud.fields["intensity"], np.arange(len(xyz)))


def test_pcd_compressed_zero_bytes_is_refused(tmp_path: Path) -> None:
    # Before: info printed bounds from uninitialised memory (-3.9e19 ... 7.3e19, NaN).
    head = pcd_bytes(XYZ, "binary_compressed").split(b"DATA binary_compressed\n")[0]
    data = head + b"DATA binary_compressed\n" + struct.pack("<II", 0, len(XYZ) * 16)
    refused(write(tmp_path, "z.pcd", data), "compressed size is 0 bytes")


@pytest.mark.parametrize(
    "sizes,named",
    [
        ((10**9, 300 * 16), "compressed size is 1000000000 bytes"),
        ((100, 300 * 16 + 4), "uncompressed size is 4804 bytes; 300 points of 16 bytes make 4800"),
    ],
)
def test_pcd_compressed_sizes_checked(tmp_path: Path, sizes: tuple[int, int], named: str) -> None:
    refused(write(tmp_path, "s.pcd", pcd_bytes(XYZ, "binary_compressed", sizes=sizes)), named)


def test_pcd_damaged_lzf_stream_is_refused(tmp_path: Path) -> None:
    data = bytearray(pcd_bytes(XYZ, "binary_compressed"))
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n") + 8
    data[start] = 0xE0  # a back reference before the first byte written
    refused(write(tmp_path, "d.pcd", bytes(data)), "do not decompress to 4800 bytes")


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_pcd_cut_short_gives_the_points_present(tmp_path: Path, encoding: str) -> None:
    data = pcd_bytes(XYZ, encoding)
    cloud, notes = read_with_warnings(write(tmp_path, "c.pcd", data[: len(data) - len(data) // 3]))
    assert 0 < len(cloud) < len(XYZ) and len(notes) == 1
    assert f"of {len(XYZ)} points are in the file" in notes[0]
    np.testing.assert_allclose(cloud.absolute_xyz, XYZ[: len(cloud)], atol=1e-4)


@pytest.mark.parametrize(
    "change,named",
    [
        ((b"WIDTH 300", b"WIDTH 299"), "WIDTH x HEIGHT (299 x 1) differs from POINTS (300)"),
        ((b"SIZE 4 4 4 4", b"SIZE 4 4 4"), "do not list one value per field"),
        ((b"TYPE F F F F", b"TYPE F F F Q"), "field 'intensity' has TYPE 'Q' SIZE 4"),
        ((b"SIZE 4 4 4 4", b"SIZE 4 4 4 3"), "TYPE 'F' SIZE 3"),
        ((b"DATA binary", b"DATA zip"), "DATA 'zip' is not one of"),
        ((b"FIELDS x y z", b"FIELDS x y q"), "no z field"),
        ((b"POINTS 300", b"POINTS -300"), "POINTS '-300' is not a list of integers"),
        ((b"COUNT 1 1 1 1", b"COUNT 1 1 0 1"), "COUNT '1 1 0 1'"),
    ],
)
def test_pcd_bad_headers_are_named(tmp_path: Path, change: tuple[bytes, bytes], named: str) -> None:
    data = pcd_bytes(XYZ, "binary").replace(*change, 1)
    refused(write(tmp_path, "h.pcd", data), named)


def test_pcd_fields_like_open3d(tmp_path: Path) -> None:
    rgb = np.array([0x0A141E, 0x010203], np.uint32).view(np.float32)
    head = (
        b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z normal_x rgb h _\nSIZE 4 4 4 4 4 4 1\n"
        b"TYPE F F F F F F U\nCOUNT 1 1 1 1 1 2 3\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary\n"
    )
    rows = b"".join(struct.pack("<5f2f3B", i, i, i, 0.5, rgb[i], i, -i, 0, 0, 0) for i in range(2))
    cloud, _ = read_with_warnings(
        write(tmp_path, "f.pcd", head + rows)
    )  # Open3D crashed on a lone normal_x
    np.testing.assert_array_equal(cloud.fields["colors"], [[10, 20, 30], [1, 2, 3]])
    np.testing.assert_array_equal(cloud.fields["normal_x"], [0.5, 0.5])
    np.testing.assert_array_equal(cloud.fields["h"], [[0, 0], [1, -1]])
    assert set(cloud.fields) == {"colors", "normal_x", "h"}  # padding "_" skipped


def test_lzf_decodes_back_references_and_refuses_overruns() -> None:
    # "abcabcabc": 3 literals, then a back reference of length 6 at distance 3.
    stream = bytes([2]) + b"abc" + bytes([(4 << 5) | 0, 2])
    assert lzf_decompress(stream, 9).tobytes() == b"abcabcabc"
    assert lzf_decompress(stream, 8) is None  # longer than expected
    assert lzf_decompress(stream[:3], 9) is None  # literal run cut short
    payload = bytes(range(200)) * 3
    assert lzf_decompress(lzf_literals(payload), len(payload)).tobytes() == payload


def test_open3d_messages_become_one_plain_line() -> None:
    raw = (
        "\x1b[1;31m[Open3D Error] (std::shared_ptr<T> open3d::io::Read(const std::string&)) "
        "/root/Open3D/cpp/open3d/io/PointCloudIO.cpp:112: Read PCD failed: unable to read "
        "data.\x1b[0;m\nRPly: Error reading value\n"
    )
    assert (
        foreign_message(raw) == "Read PCD failed: unable to read data.; RPly: Error reading value"
    )
