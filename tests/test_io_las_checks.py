"""The LAS/LAZ reader against hand-built files: the header checked against the file before
laspy sees it, each lying field named, cut files read in part with a warning, bounds from
the points. The truth is what tests/bad_inputs/clouds.py wrote into each file."""

from __future__ import annotations

import io
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from bad_inputs.clouds import grid_points, las_bytes, vlr_bytes
from test_io_clouds import read_with_warnings

from canopy_kit.errors import InputError
from canopy_kit.io.info import describe_path
from canopy_kit.io.las import describe_las, read_las
from canopy_kit.io.las_header import read_las_layout

laspy = pytest.importorskip("laspy")

N = 1000
OFFSET = (300000.0, 4100000.0, 50.0)


def write(tmp_path: Path, data: bytes, name: str = "t.las") -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def refused(path: Path, *fragments: str) -> str:
    """The InputError message for ``path``; it names the file and every fragment."""
    start = time.perf_counter()
    with pytest.raises(InputError) as err:
        read_las(path)
    assert time.perf_counter() - start < 2.0  # checked before anything loops or allocates
    message = str(err.value)
    assert str(path) in message and "\n" not in message
    for fragment in fragments:
        assert fragment in message, message
    return message


@pytest.mark.parametrize("point_format,minor", [(0, 2), (1, 2), (6, 4)])
def test_hand_built_las_reads_exactly(tmp_path: Path, point_format: int, minor: int) -> None:
    ints = grid_points(N)
    path = write(tmp_path, las_bytes(ints, offset=OFFSET, point_format=point_format, minor=minor))
    cloud, notes = read_with_warnings(path)
    assert notes == []
    np.testing.assert_allclose(
        cloud.absolute_xyz, ints * 0.01 + np.asarray(OFFSET), rtol=0, atol=1e-9
    )
    np.testing.assert_array_equal(cloud.fields["intensity"], np.arange(N))
    facts = describe_las(path)
    assert facts["points"] == N and facts["point_format"] == point_format
    np.testing.assert_allclose(facts["bounds"]["min"], ints.min(axis=0) * 0.01 + OFFSET, atol=1e-9)
    np.testing.assert_allclose(facts["bounds"]["max"], ints.max(axis=0) * 0.01 + OFFSET, atol=1e-9)


def test_vlr_count_bomb_is_refused_at_once(tmp_path: Path) -> None:
    # laspy looped over 4e9 VLRs (131 s, 5.6 GB) before this check.
    path = write(tmp_path, las_bytes(grid_points(10), n_vlrs=4_000_000_000))
    refused(path, "'number of variable length records'", "4000000000")


def test_vlr_longer_than_the_space_before_the_points(tmp_path: Path) -> None:
    data = bytearray(las_bytes(grid_points(10), vlrs=(vlr_bytes(b"me", 1, b"x" * 10),)))
    struct.pack_into("<H", data, 227 + 20, 60000)  # the VLR's record length after header
    refused(write(tmp_path, bytes(data)), "'record length after header (VLR 0)'")


@pytest.mark.parametrize(
    "field,value,named",
    [
        ("header_size", 100, "'header size'"),
        ("header_size", 5000, "'header size'"),
        ("offset_to_points", 10**9, "'offset to point data'"),
        ("record_length", 65535, "'point data record length'"),
        ("record_length", 12, "'point data record length'"),
    ],
)
def test_lying_layout_fields_are_named(tmp_path: Path, field: str, value: int, named: str) -> None:
    refused(write(tmp_path, las_bytes(grid_points(N), **{field: value})), named)


def test_unknown_point_format_and_version(tmp_path: Path) -> None:
    data = bytearray(las_bytes(grid_points(10)))
    data[104] = 11
    refused(write(tmp_path, bytes(data), "f.las"), "'point data record format'", "is 11")
    data = bytearray(las_bytes(grid_points(10)))
    data[24] = 2
    refused(write(tmp_path, bytes(data), "v.las"), "'version'", "2.2")


@pytest.mark.parametrize("scale", [1e-300, 1e-10, 0.0, -0.01, float("nan"), float("inf"), 1e6])
def test_unusable_scales_are_refused(tmp_path: Path, scale: float) -> None:
    refused(write(tmp_path, las_bytes(grid_points(N), scale=scale)), "scale factors", "corrupt")


def test_smallest_real_scale_is_read(tmp_path: Path) -> None:
    # A real Riegl file (pointcloudset_test_tree.las) uses 3.7e-9 to 7.8e-9.
    ints = grid_points(N) * 1000
    cloud = read_las(write(tmp_path, las_bytes(ints, scale=4e-9, offset=OFFSET)))
    np.testing.assert_allclose(cloud.absolute_xyz, ints * 4e-9 + np.asarray(OFFSET), atol=1e-9)


@pytest.mark.parametrize("offset", [float("inf"), float("nan")])
def test_non_finite_offsets_are_refused(tmp_path: Path, offset: float) -> None:
    refused(write(tmp_path, las_bytes(grid_points(N), offset=(0, offset, 0))), "offsets")


def test_claimed_points_beyond_the_file_give_the_points_present(tmp_path: Path) -> None:
    # Before: 3.5 GB allocated for 1e8 points, exit 0 and no warning.
    ints = grid_points(N)
    cloud, notes = read_with_warnings(write(tmp_path, las_bytes(ints, point_count=100_000_000)))
    assert len(cloud) == N
    assert notes == [
        (
            f"{tmp_path / 't.las'}: only {N} of 100000000 points are in the file (cut "
            "short, or the header's point count is wrong); read those"
        )
    ]


@pytest.mark.parametrize("keep_bytes", [0, 1, 19])  # at a record boundary, 1 and 19 bytes in
def test_cut_file_gives_the_complete_records_and_a_warning(tmp_path: Path, keep_bytes: int) -> None:
    ints = grid_points(N)
    data = las_bytes(ints, offset=OFFSET)
    path = write(tmp_path, data[: 227 + 600 * 20 + keep_bytes])
    cloud, notes = read_with_warnings(path)
    assert len(cloud) == 600 and len(notes) == 1 and f"only 600 of {N} points" in notes[0]
    np.testing.assert_allclose(
        cloud.absolute_xyz, ints[:600] * 0.01 + np.asarray(OFFSET), atol=1e-9
    )
    facts, _ = describe_warned(path)
    assert facts["points"] == 600 and facts["points_declared"] == N
    assert any(f"only 600 of {N} points" in w for w in facts["warnings"])


def describe_warned(path: Path) -> tuple[dict, list[str]]:
    """info's facts and the warnings among them."""

    facts = describe_path(path)
    return facts, facts["warnings"]


@pytest.mark.parametrize(
    "cut,named",
    [
        (100, "cut short"),  # inside the fixed header
        (
            227 + 30,
            "'offset to point data'",
        ),  # inside the VLR: the points would start beyond the end
        (227 + 64 + 10, "no complete point record"),  # inside the first point record
    ],
)
def test_file_cut_before_any_point_is_refused(tmp_path: Path, cut: int, named: str) -> None:
    data = las_bytes(grid_points(N), vlrs=(vlr_bytes(b"me", 1, b"x" * 10),))
    refused(write(tmp_path, data[:cut]), named)


def test_evlrs_that_do_not_fit_are_refused(tmp_path: Path) -> None:
    ints = grid_points(N)
    body = las_bytes(ints, minor=4, point_format=6)
    path = write(
        tmp_path, las_bytes(ints, minor=4, point_format=6, evlr_start=len(body), n_evlrs=3)
    )
    refused(path, "'start of first extended variable length record'")
    evlr = struct.pack("<H16sHQ32s", 0, b"me", 1, 10**12, b"")
    path = write(
        tmp_path,
        las_bytes(ints, minor=4, point_format=6, evlr_start=len(body), n_evlrs=1) + evlr,
        "e.las",
    )
    refused(path, "'record length after header (EVLR 0)'")


def test_zero_header_bounds_give_true_bounds_and_a_warning(tmp_path: Path) -> None:
    # Like the real pointcloudset_test_tree.las, whose header min/max are all 0.
    ints = grid_points(N)
    path = write(tmp_path, las_bytes(ints, offset=OFFSET, header_bounds=((0, 0, 0), (0, 0, 0))))
    facts, notes = describe_warned(path)
    np.testing.assert_allclose(facts["bounds"]["min"], ints.min(axis=0) * 0.01 + OFFSET, atol=1e-9)
    assert facts["header_bounds"] == {"min": [0.0] * 3, "max": [0.0] * 3}
    assert len(notes) == 1 and "the header's bounds (x 0..0, y 0..0, z 0..0) disagree" in notes[0]
    cloud = read_las(path)  # the local origin comes from the points too
    assert np.abs(cloud.xyz).max() < 10_000


def laz_of(tmp_path: Path, ints: np.ndarray, name: str = "t.laz") -> bytes:
    las = laspy.read(io.BytesIO(las_bytes(ints, offset=OFFSET)))
    las.write(tmp_path / name, do_compress=True)
    return (tmp_path / name).read_bytes()


def test_laz_point_count_checked_against_the_chunk_table(tmp_path: Path) -> None:
    ints = grid_points(N)
    data = bytearray(laz_of(tmp_path, ints))
    cloud = read_las(tmp_path / "t.laz")
    np.testing.assert_allclose(cloud.absolute_xyz, ints * 0.01 + np.asarray(OFFSET), atol=1e-9)
    struct.pack_into("<I", data, 107, N + 60_000)  # one chunk of 50,000 points cannot hold it
    refused(write(tmp_path, bytes(data), "more.laz"), "'number of point records'", "chunk table")
    struct.pack_into("<I", data, 107, 4_000_000_000)  # reported as fact by info before
    refused(
        write(tmp_path, bytes(data), "bomb.laz"),
        "'number of point records'",
        "compressed bytes hold at most",
    )


def test_laz_record_length_must_match_the_laszip_items(tmp_path: Path) -> None:
    data = bytearray(laz_of(tmp_path, grid_points(N)))
    struct.pack_into("<H", data, 105, 40)
    refused(
        write(tmp_path, bytes(data), "r.laz"), "'point data record length'", "LASzip items make 20"
    )


@pytest.mark.parametrize("fraction", [0.3, 0.9, 0.999])
def test_cut_laz_is_refused(tmp_path: Path, fraction: float) -> None:
    data = laz_of(tmp_path, grid_points(20_000))
    refused(write(tmp_path, data[: int(len(data) * fraction)], "cut.laz"), "corrupt or truncated")


def test_layout_of_a_real_file_matches_laspy(tmp_path: Path) -> None:
    from test_io_clouds import shared_data

    path = shared_data() / "real_trees" / "pointcloudset_test_tree.las"
    if not path.exists():
        pytest.skip(f"{path} not present")
    layout = read_las_layout(path)
    las = laspy.read(path)
    assert (layout.point_count, layout.points_in_file, layout.point_format) == (11631, 11631, 7)
    assert layout.record_length == las.header.point_format.size
    facts, notes = describe_warned(path)
    assert facts["bounds"]["min"] == pytest.approx(
        [float(las.x.min()), float(las.y.min()), float(las.z.min())], abs=1e-6
    )
    assert facts["bounds"]["max"][2] == pytest.approx(float(las.z.max()), abs=1e-6)
    assert any("disagree with the points'" in n for n in notes)
