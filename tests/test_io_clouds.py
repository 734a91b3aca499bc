"""LAS/LAZ/PLY/PCD: real public files checked against laspy and the data README, round
trips with extra attributes, format dispatch, and clear errors for bad input."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.io.clouds import find_reader, read_cloud, write_cloud
from canopy_kit.io.info import describe_path
from canopy_kit.io.las import read_las, write_las
from canopy_kit.io.open3d_clouds import read_pcd, read_ply, write_pcd, write_ply

laspy = pytest.importorskip("laspy")

REPO = Path(__file__).resolve().parents[1]
DBL_MAX = np.finfo(np.float64).max


def shared_data() -> Path:
    """The public test data folder (env CANOPY_KIT_SHARED_DATA, default ../shared/data)."""
    configured = os.environ.get("CANOPY_KIT_SHARED_DATA")
    path = Path(configured) if configured else REPO.parent / "shared" / "data"
    if not path.is_dir():
        if configured:
            pytest.fail(f"CANOPY_KIT_SHARED_DATA={configured} is not a folder")
        pytest.skip(f"public test data not found at {path} (set CANOPY_KIT_SHARED_DATA)")
    return path


# Facts from ../shared/data/README.md (read there with laspy by whoever fetched the files).
REAL_FILES = {
    "lidr/MixedConifer.laz": {
        "points": 37_657,
        "crs": "EPSG:26912",
        "format": 1,
        "extra": {"treeID": "float64"},
    },
    "lidr/Topography.laz": {"points": 73_403, "crs": "EPSG:2949", "format": 1, "extra": {}},
    "lidr/dbh.laz": {
        "points": 1_369,
        "crs": None,
        "format": 1,
        "extra": {"Range": "float64", "Ring": "float64", "hag": "float64", "cluster": "int32"},
    },
    "treels/pine.laz": {"points": 73_851, "crs": None, "format": 0, "extra": {}},
    "treels/spruce.laz": {"points": 83_392, "crs": None, "format": 0, "extra": {}},
    "treels/pine_plot.laz": {"points": 114_024, "crs": None, "format": 0, "extra": {}},
}


@pytest.fixture(params=sorted(REAL_FILES))
def real_laz(request: pytest.FixtureRequest) -> tuple[Path, dict]:
    path = shared_data() / request.param
    if not path.exists():
        pytest.skip(f"{path} missing from the shared data")
    return path, REAL_FILES[request.param]


def test_real_file_matches_laspy(real_laz: tuple[Path, dict]) -> None:
    path, facts = real_laz
    cloud = read_cloud(path)
    las = laspy.read(path)  # independent truth
    assert len(cloud) == len(las.points) == facts["points"]
    assert las.header.point_format.id == facts["format"]
    assert set(cloud.fields) == set(las.point_format.dimension_names) - {"X", "Y", "Z"}
    extra = {d.name: str(d.dtype) for d in las.point_format.extra_dimensions}
    assert extra == facts["extra"]
    for name, dtype in extra.items():
        assert str(cloud.fields[name].dtype) == dtype
    absolute = cloud.absolute_xyz
    truth = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    assert np.max(np.abs(absolute - truth)) < 1e-6
    np.testing.assert_allclose(absolute.min(axis=0), las.header.mins, atol=1e-6)
    np.testing.assert_allclose(absolute.max(axis=0), las.header.maxs, atol=1e-6)
    assert cloud.crs == facts["crs"]
    # local frame: coordinates stay small whatever the CRS
    assert np.abs(cloud.xyz).max() < 10_000
    for name in ("intensity", "classification", "return_number"):
        np.testing.assert_array_equal(cloud.fields[name], np.asarray(las[name]))


def test_describe_matches_laspy_header(real_laz: tuple[Path, dict]) -> None:
    path, facts = real_laz
    info = describe_path(path)
    header = laspy.read(path).header
    assert info["reader"] == "las" and info["kind"] == "cloud"
    assert info["points"] == facts["points"] == header.point_count
    assert info["crs"] == facts["crs"]
    np.testing.assert_allclose(info["bounds"]["min"], header.mins)
    np.testing.assert_allclose(info["bounds"]["max"], header.maxs)
    names = [a["name"] for a in info["attributes"]]
    assert names == [n for n in header.point_format.dimension_names if n not in ("X", "Y", "Z")]
    assert {a["name"] for a in info["attributes"] if a["extra"]} == set(facts["extra"])


def test_readme_extents() -> None:
    """Bounds as the data README states them (to its printed precision)."""
    cloud = read_las(shared_data() / "lidr" / "MixedConifer.laz")
    lo, hi = cloud.bounds()
    np.testing.assert_allclose(lo + cloud.origin, [481260.00, 3812921.09, 0.00], atol=0.005)
    np.testing.assert_allclose(hi + cloud.origin, [481349.99, 3813010.99, 32.07], atol=0.005)
    pine = read_las(shared_data() / "treels" / "pine.laz")
    np.testing.assert_allclose(pine.absolute_xyz.min(axis=0), [-1.249, -1.240, -0.224], atol=0.0006)
    np.testing.assert_allclose(pine.absolute_xyz.max(axis=0), [1.241, 1.240, 19.936], atol=0.0006)


def test_tree_id_no_data_becomes_nan() -> None:
    path = shared_data() / "lidr" / "MixedConifer.laz"
    raw = np.asarray(laspy.read(path)["treeID"])
    tree_id = read_las(path).fields["treeID"]
    missing = np.isnan(tree_id)
    # README: 8,296 points carry the declared no-data value DBL_MAX
    assert missing.sum() == (raw == DBL_MAX).sum() == 8_296
    np.testing.assert_array_equal(tree_id[~missing], raw[~missing])
    ids = np.unique(tree_id[~missing])
    assert len(ids) == 205 and ids.min() == 1 and ids.max() == 205
    assert np.array_equal(ids, np.round(ids))
    # per-tree sizes from the README: 1-350 points, median 145
    sizes = np.bincount(tree_id[~missing].astype(int))[1:]
    assert sizes.min() == 1 and sizes.max() == 350 and np.median(sizes) == 145


def test_dbh_extra_dimensions() -> None:
    cloud = read_las(shared_data() / "lidr" / "dbh.laz")
    assert np.all(cloud.fields["cluster"] == 37)
    assert cloud.fields["Ring"].min() == 0 and cloud.fields["Ring"].max() == 15
    assert 2.17 <= cloud.fields["Range"].min() < cloud.fields["Range"].max() <= 65.25
    assert 1.28 <= cloud.fields["hag"].min() < cloud.fields["hag"].max() <= 1.55
    np.testing.assert_array_equal(cloud.origin, [0.0, 0.0, 0.0])  # offsets 0, local data


def test_rewrite_at_file_scale_is_exact(real_laz: tuple[Path, dict], tmp_path: Path) -> None:
    """Read then write at the file's own scale: the same absolute grid coordinates."""
    path, facts = real_laz
    original = laspy.read(path)
    out = tmp_path / "copy.laz"
    write_las(out, read_las(path), scale=float(original.header.scales[0]))
    copy = laspy.read(out)
    assert copy.header.are_points_compressed
    assert len(copy.points) == facts["points"]
    for axis, name in enumerate("XYZ"):
        # compare integer grids: (X*s + o) equal means X_new - X_old == (o_old - o_new)/s exactly
        s = original.header.scales[axis]
        shift = (original.header.offsets[axis] - copy.header.offsets[axis]) / s
        assert shift == round(shift)
        np.testing.assert_array_equal(
            np.asarray(copy[name]).astype(np.int64) - np.asarray(original[name]).astype(np.int64),
            np.full(len(original.points), round(shift)),
        )
    for name in set(original.point_format.dimension_names) - {"X", "Y", "Z"}:
        before, after = np.asarray(original[name]), np.asarray(copy[name])
        if name == "treeID":  # declared no-data (DBL_MAX) is written back as NaN
            assert np.array_equal(np.isnan(after), before == DBL_MAX)
            before, after = before[before != DBL_MAX], after[before != DBL_MAX]
        np.testing.assert_array_equal(after, before)
    assert {d.name for d in copy.point_format.extra_dimensions} == {
        d.name for d in original.point_format.extra_dimensions
    }
    if facts["crs"]:
        assert copy.header.parse_crs().to_epsg() == int(facts["crs"].split(":")[1])


def test_rewrite_at_coarser_scale_is_within_half_scale(tmp_path: Path) -> None:
    path = shared_data() / "lidr" / "Topography.laz"  # scale 0.00025
    cloud = read_las(path)
    write_las(tmp_path / "coarse.las", cloud, scale=0.001)
    copy = laspy.read(tmp_path / "coarse.las")
    assert not copy.header.are_points_compressed
    np.testing.assert_array_equal(copy.header.scales, [0.001] * 3)
    diff = (
        np.column_stack([np.asarray(copy.x), np.asarray(copy.y), np.asarray(copy.z)])
        - cloud.absolute_xyz
    )
    assert np.abs(diff).max() <= 0.0005 + 1e-9
    assert np.abs(diff).max() > 0  # the coarser grid really rounds


# --- round trips of synthetic clouds -------------------------------------------------


def synthetic_cloud(n: int = 2_000, seed: int = 7) -> PointCloud:
    """A UTM-placed cloud with standard and extra attributes of many dtypes."""
    rng = np.random.default_rng(seed)
    xyz = np.round(rng.uniform([0, 0, -1], [80, 40, 9], size=(n, 3)), 3)  # on the 1 mm grid
    tree = rng.integers(1, 30, n).astype(np.float64)
    tree[rng.random(n) < 0.2] = np.nan
    fields = {
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "classification": rng.integers(0, 20, n).astype(np.uint8),
        "gps_time": 1.7e9 + np.sort(rng.uniform(0, 100, n)),
        "treeID": tree,
        "label": rng.integers(-1, 1000, n).astype(np.int32),
        "range_m": rng.uniform(0.5, 100, n).astype(np.float32),
        "ring": rng.integers(0, 128, n).astype(np.uint16),
        "deviation": rng.integers(-100, 100, n).astype(np.int8),
        "big_id": rng.integers(0, 2**40, n).astype(np.int64),
        "is_ground": rng.random(n) < 0.3,
    }
    return PointCloud(xyz, fields, crs="EPSG:32631", origin=np.array([288000.0, 4615000.0, 280.0]))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_round_trip_with_extra_attributes(tmp_path: Path, suffix: str) -> None:
    cloud = synthetic_cloud()
    path = write_cloud(tmp_path / f"cloud{suffix}", cloud)
    las = laspy.read(path)  # independent check of what is in the file
    assert las.header.are_points_compressed == (suffix == ".laz")
    assert las.header.point_format.id == 1  # gps_time + standard fields, no colour
    assert las.header.parse_crs().to_epsg() == 32631
    truth = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    assert np.abs(truth - cloud.absolute_xyz).max() < 1e-6  # xyz on the 1 mm grid: exact
    extra = {d.name: d.dtype for d in las.point_format.extra_dimensions}
    assert set(extra) == {"treeID", "label", "range_m", "ring", "deviation", "big_id", "is_ground"}
    back = read_cloud(path)
    assert back.crs == "EPSG:32631"
    assert np.abs(back.absolute_xyz - cloud.absolute_xyz).max() < 1e-6
    for name, values in cloud.fields.items():
        expected = values.astype(np.uint8) if values.dtype == bool else values
        np.testing.assert_array_equal(back.fields[name], expected, err_msg=name)
        if name != "is_ground":
            assert back.fields[name].dtype == values.dtype, name
    assert np.isnan(back.fields["treeID"]).sum() == np.isnan(cloud.fields["treeID"]).sum()


def test_las_float64_coordinates_within_scale(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    cloud = PointCloud(
        rng.uniform(-50, 50, (500, 3)), origin=np.array([500000.0, 4200000.0, 100.0])
    )
    for scale in (0.001, 0.0001):
        path = write_las(tmp_path / f"s{scale}.laz", cloud, scale=scale)
        back = read_las(path)
        err = np.abs(back.absolute_xyz - cloud.absolute_xyz).max()
        assert err <= scale / 2 + 1e-9
        assert err > scale / 20  # random coordinates are really quantised
        assert back.fields.keys() >= {"intensity", "classification"}


def test_las_wkt_only_crs_round_trip(tmp_path: Path) -> None:
    pyproj = pytest.importorskip("pyproj")
    wkt = pyproj.CRS.from_proj4(
        "+proj=tmerc +lat_0=41 +lon_0=0.45 +k=1 +x_0=0 +y_0=0 +ellps=GRS80 +units=m"
    ).to_wkt()
    cloud = PointCloud(np.zeros((3, 3)) + [[0, 0, 0], [1, 2, 3], [4, 5, 6]], crs=wkt)
    path = write_las(tmp_path / "custom.laz", cloud)
    las = laspy.read(path)
    assert str(las.header.version) == "1.4"  # WKT CRS needs LAS 1.4
    back = read_las(path)
    assert back.crs is not None and not back.crs.startswith("EPSG:")
    assert pyproj.CRS.from_wkt(back.crs).equals(pyproj.CRS.from_wkt(wkt))


def test_las_point_format_choice(tmp_path: Path) -> None:
    xyz = np.zeros((4, 3))
    rgb = {c: np.array([0, 1000, 40000, 65535], np.uint16) for c in ("red", "green", "blue")}
    assert laspy.read(write_las(tmp_path / "a.las", PointCloud(xyz))).header.point_format.id == 0
    assert (
        laspy.read(write_las(tmp_path / "b.las", PointCloud(xyz, dict(rgb)))).header.point_format.id
        == 2
    )
    classes = {"classification": np.array([1, 2, 40, 200], np.uint8)}  # > 31 needs format 6+
    las = laspy.read(write_las(tmp_path / "c.las", PointCloud(xyz, classes)))
    assert las.header.point_format.id == 6
    np.testing.assert_array_equal(np.asarray(las.classification), classes["classification"])
    with pytest.raises(InputError, match="field 'classification'.*does not fit LAS point format 1"):
        write_las(tmp_path / "d.las", PointCloud(xyz, classes), point_format=1)


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_open3d_round_trip_with_extra_attributes(tmp_path: Path, suffix: str) -> None:
    pytest.importorskip("open3d")
    rng = np.random.default_rng(11)
    cloud = synthetic_cloud()
    # unrounded coordinates: binary float64 must carry every bit
    cloud = PointCloud(
        cloud.xyz + rng.uniform(0, 1e-3, cloud.xyz.shape), cloud.fields, origin=cloud.origin
    ).with_field("normals", rng.normal(size=(len(cloud), 3)))
    path = write_cloud(tmp_path / f"cloud{suffix}", cloud)
    np.testing.assert_array_equal(_positions_in_file(path), cloud.absolute_xyz)
    back = read_cloud(path)
    np.testing.assert_array_equal(back.absolute_xyz, cloud.absolute_xyz)
    assert np.abs(back.xyz).max() < 10_000  # re-localised on reading
    assert set(back.fields) == set(cloud.fields)
    for name, values in cloud.fields.items():
        got = back.fields[name]
        assert got.shape == values.shape, name
        np.testing.assert_array_equal(
            got.astype(np.float64), values.astype(np.float64), err_msg=name
        )
    widened = {"deviation": "int32", "big_id": "float64"} if suffix == ".ply" else {}
    for name, values in cloud.fields.items():
        expected = widened.get(name, "uint8" if values.dtype == bool else str(values.dtype))
        assert str(back.fields[name].dtype) == expected, name


def _positions_in_file(path: Path) -> np.ndarray:
    """x, y, z as stored, by an independent route: Open3D's legacy PLY reader, or the
    binary PCD layout decoded here from its header (Open3D's legacy PCD reader returns
    zeros for double-precision x/y/z)."""
    if path.suffix == ".ply":
        import open3d as o3d

        return np.asarray(o3d.io.read_point_cloud(str(path)).points)
    data = path.read_bytes()
    head, body = data.split(b"DATA binary\n", 1)
    keys = {
        ln.split()[0]: ln.split()[1:] for ln in head.decode().splitlines() if ln and ln[0] != "#"
    }
    kinds = {"F": "f", "I": "i", "U": "u"}
    dtype = np.dtype(
        [
            (name, f"<{kinds[t]}{s}")
            for name, t, s in zip(keys["FIELDS"], keys["TYPE"], keys["SIZE"])
        ]
    )
    points = np.frombuffer(body, dtype=dtype, count=int(keys["POINTS"][0]))
    assert keys["TYPE"][:3] == ["F", "F", "F"] and keys["SIZE"][:3] == ["8", "8", "8"]
    return np.column_stack([points[c] for c in "xyz"])


def test_ply_splits_other_vector_fields(tmp_path: Path) -> None:
    cloud = PointCloud(np.eye(3), {"eigen": np.arange(9.0).reshape(3, 3)})
    back = read_ply(write_ply(tmp_path / "v.ply", cloud))
    np.testing.assert_array_equal(back.fields["eigen_1"], [1.0, 4.0, 7.0])
    back = read_pcd(write_pcd(tmp_path / "v.pcd", cloud))
    np.testing.assert_array_equal(back.fields["eigen_2"], [2.0, 5.0, 8.0])


def test_dispatch_by_content_when_suffix_is_unknown(tmp_path: Path) -> None:
    cloud = synthetic_cloud(50)
    for suffix, reader in ((".laz", "las"), (".ply", "ply"), (".pcd", "pcd")):
        written = write_cloud(tmp_path / f"c{suffix}", cloud)
        renamed = written.rename(tmp_path / f"c_{reader}.data")
        assert find_reader(renamed).name == reader
        assert len(read_cloud(renamed)) == 50


def test_writes_are_atomic(tmp_path: Path) -> None:
    cloud = synthetic_cloud(20)
    with pytest.raises(InputError):
        write_las(
            tmp_path / "bad.laz",
            cloud.with_field("name_is_far_too_long_for_a_las_extra_dim", np.zeros(20)),
        )
    assert list(tmp_path.iterdir()) == []  # neither the target nor a temporary file
    write_cloud(tmp_path / "ok.ply", cloud)
    assert [p.name for p in tmp_path.iterdir()] == ["ok.ply"]


# --- bad input -----------------------------------------------------------------------


def _message(path: Path) -> str:
    with pytest.raises(InputError) as err:
        read_cloud(path)
    assert str(path) in str(err.value)
    return str(err.value)


def test_missing_file(tmp_path: Path) -> None:
    assert "does not exist" in _message(tmp_path / "gone.laz")


@pytest.mark.parametrize("name", ["empty.laz", "empty.ply", "empty.pcd", "empty.bin"])
def test_empty_file(tmp_path: Path, name: str) -> None:
    (tmp_path / name).touch()
    assert "empty" in _message(tmp_path / name)


def test_las_with_zero_points(tmp_path: Path) -> None:
    path = tmp_path / "none.las"
    laspy.LasData(laspy.LasHeader(point_format=1, version="1.2")).write(path)
    assert laspy.read(path).header.point_count == 0
    assert "has no points" in _message(path)


def test_ply_with_zero_points(tmp_path: Path) -> None:
    path = tmp_path / "none.ply"
    path.write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n"
    )
    assert "has no points" in _message(path)


def test_writing_an_empty_cloud_is_refused(tmp_path: Path) -> None:
    for suffix in (".laz", ".ply", ".pcd"):
        with pytest.raises(InputError, match="no points"):
            write_cloud(tmp_path / f"e{suffix}", PointCloud(np.zeros((0, 3))))


@pytest.mark.parametrize("fraction", [0.02, 0.5, 0.98])
def test_truncated_laz(tmp_path: Path, fraction: float) -> None:
    data = write_cloud(tmp_path / "whole.laz", synthetic_cloud()).read_bytes()
    path = tmp_path / "cut.laz"
    path.write_bytes(data[: int(len(data) * fraction)])
    assert "corrupt or truncated" in _message(path)


def read_with_warnings(path: Path) -> tuple[PointCloud, list[str]]:
    """``read_cloud(path)`` and the messages of the InputWarnings it gave."""
    import warnings

    from canopy_kit.errors import InputWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cloud = read_cloud(path)
    return cloud, [str(w.message) for w in caught if issubclass(w.category, InputWarning)]


@pytest.mark.parametrize("suffix", [".las", ".ply", ".pcd"])
def test_truncated_uncompressed_gives_the_records_present(tmp_path: Path, suffix: str) -> None:
    # Fixed-size records: the complete ones before the cut are read, with a warning saying
    # how many (Open3D alone returned the declared number of points, zeros for the missing).
    cloud = synthetic_cloud()
    data = write_cloud(tmp_path / f"whole{suffix}", cloud).read_bytes()
    path = tmp_path / f"cut{suffix}"
    path.write_bytes(data[: len(data) * 2 // 3])
    back, notes = read_with_warnings(path)
    assert 0 < len(back) < len(cloud) and len(notes) == 1
    assert f"of {len(cloud)} points are in the file" in notes[0] and str(path) in notes[0]
    np.testing.assert_allclose(back.absolute_xyz, cloud.absolute_xyz[: len(back)], atol=1e-6)


def test_truncated_ascii_ply(tmp_path: Path) -> None:
    rows = "\n".join(f"{i} {i + 1} {i + 2}" for i in range(5))
    path = tmp_path / "cut_ascii.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 10\nproperty float x\nproperty float y\n"
        f"property float z\nend_header\n{rows}\n"
    )
    back, notes = read_with_warnings(path)
    assert len(back) == 5 and notes and "only 5 of 10 points" in notes[0]
    np.testing.assert_array_equal(back.absolute_xyz[:, 0], np.arange(5))


def test_garbage_with_las_suffix(tmp_path: Path) -> None:
    path = tmp_path / "fake.las"
    path.write_bytes(b"this is not lidar\n" * 20)
    assert "no 'LASF' signature" in _message(path)


def test_unknown_format(tmp_path: Path) -> None:
    path = tmp_path / "points.xyz"
    path.write_text("1 2 3\n4 5 6\n")
    message = _message(path)
    assert "unknown file format" in message and ".laz" in message and ".ply" in message


def test_bag_is_not_a_cloud(tmp_path: Path) -> None:
    from canopy_kit.io.bag_writer import BagWriter

    with BagWriter(tmp_path / "s.bag", "ros1") as w:
        w.write_imu("/imu", 1.0, (0, 0, 0), (0, 0, 9.8))
    assert "is a bag file" in _message(w.path)


def test_cannot_write_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot write suffix '.xyz'"):
        write_cloud(tmp_path / "out.xyz", synthetic_cloud(5))
