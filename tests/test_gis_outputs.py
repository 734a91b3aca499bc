"""GIS-ready outputs of ``canopy-kit run`` and ``segment``: RFC 7946 GeoJSON, the GeoPackage in
the projected CRS, one tree id in every output, LAS classes, per-tree LAZ and provenance.

Checked against what the code does not compute itself: pyproj directly, the simulator's
truth (tree positions, which points are trees), the bag read by rosbags, hashlib.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fixtures_sim import synthetic_orchard

from canopy_kit.core.cloud import PointCloud
from canopy_kit.io.clouds import read_cloud

PROVENANCE_KEYS = {
    "orchard",
    "session_date",
    "bag",
    "bag_sha256",
    "drone_images",
    "software_version",
    "preset",
    "run_started_utc",
    "run_seconds",
}


# -- an RFC 7946 validator, independent of canopy_kit.io.geojson ------------------------------
def _positions(geometry: dict) -> list[list[float]]:
    kind, coords = geometry["type"], geometry["coordinates"]
    if kind == "Point":
        return [coords]
    if kind in ("LineString", "MultiPoint"):
        return list(coords)
    if kind == "Polygon":
        return [p for ring in coords for p in ring]
    raise AssertionError(f"unexpected geometry type {kind}")


def _signed_area(ring: list[list[float]]) -> float:
    x = np.array([p[0] for p in ring])
    y = np.array([p[1] for p in ring])
    return 0.5 * float(np.sum(x[:-1] * y[1:] - x[1:] * y[:-1]))


def validate_rfc7946(path: Path, min_features: int = 1) -> dict:
    """Assert ``path`` is an RFC 7946 FeatureCollection; returns it parsed."""
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text, f"{path}: JSON has no NaN"
    data = json.loads(text)
    assert data["type"] == "FeatureCollection", path
    assert "crs" not in data, f"{path}: RFC 7946 §4 removed the crs member"
    assert isinstance(data["features"], list) and len(data["features"]) >= min_features, path
    for f in data["features"]:
        assert f["type"] == "Feature" and isinstance(f["properties"], dict), path
        assert "crs" not in f and "crs" not in f["geometry"]
        for p in _positions(f["geometry"]):
            assert len(p) in (2, 3) and all(isinstance(v, float) for v in p), (path, p)
            assert -180 <= p[0] <= 180 and -90 <= p[1] <= 90, f"{path}: {p} is not lon/lat"
        if f["geometry"]["type"] == "Polygon":
            for k, ring in enumerate(f["geometry"]["coordinates"]):
                assert len(ring) >= 4 and ring[0] == ring[-1], f"{path}: ring not closed"
                area = _signed_area(ring)
                assert (area > 0) if k == 0 else (area < 0), f"{path}: §3.1.6 ring orientation"
    return data


def _utm_to_lonlat(crs: str, e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from pyproj import Transformer

    return Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(e, n)


def _metres(lon_a, lat_a, lon_b, lat_b) -> np.ndarray:
    """Distance in metres between lon/lat points a few metres apart (equirectangular)."""
    dy = (np.asarray(lat_a) - np.asarray(lat_b)) * 111_132.0
    dx = (np.asarray(lon_a) - np.asarray(lon_b)) * 111_320.0 * np.cos(np.radians(np.asarray(lat_b)))
    return np.hypot(dx, dy)


# -- a run with every output ----------------------------------------------------------------
@pytest.fixture(scope="module")
def gis_run(tiny_pistachio, tiny_pistachio_run, tmp_path_factory):
    """The adaptive run of ``tiny_pistachio`` with every output (an orchard name, the trees'
    points), its stages from a copy of the shared run's cache (the same bag and preset: the
    same keys; neither option is part of one), every output written anew."""
    import shutil

    from canopy_kit.config import load_preset
    from canopy_kit.pipeline import run

    out = tmp_path_factory.mktemp("gis_run")
    shutil.copytree(tiny_pistachio_run.out_dir / ".cache", out / ".cache")
    results = run(
        load_preset("adaptive"),
        tiny_pistachio.bag,
        out,
        truth=tiny_pistachio.root,
        orchard="block 7",
        export_trees=True,
    )
    assert set(results.cache_hits) == {"map", "segment", "volumes"}
    return tiny_pistachio, out, results


def test_every_geojson_of_a_run_is_rfc7946_wgs84(gis_run) -> None:
    _, out, _ = gis_run
    names = sorted(p.name for p in out.glob("*.geojson"))
    assert names == ["crowns.geojson", "rows.geojson", "rows_sections.geojson", "trees.geojson"]
    for name in names:
        validate_rfc7946(out / name)


def test_geojson_coordinates_agree_with_pyproj_and_the_simulator(gis_run) -> None:
    """Tree points are trees.csv x, y + the map origin projected by pyproj, and lie on the
    simulator's crowns; crown polygons enclose their segment's map.laz points."""
    from shapely.geometry import Point, Polygon

    sim, out, _ = gis_run
    summary = json.loads((out / "segmentation.json").read_text())
    crs, origin = summary["crs"], np.asarray(summary["origin"])
    trees = pd.read_csv(out / "trees.csv", dtype={"tree_id": str})
    lon, lat = _utm_to_lonlat(crs, trees["x"] + origin[0], trees["y"] + origin[1])
    feats = {
        f["properties"]["tree_id"]: f["geometry"]["coordinates"]
        for f in json.loads((out / "trees.geojson").read_text())["features"]
    }
    got = np.array([feats[t] for t in trees["tree_id"]])
    # trees.csv holds x/y to the mm and lat/lon to 1e-8 degree: they agree to that (~1 mm)
    assert np.allclose(got[:, 0], lon, atol=2e-8) and np.allclose(got[:, 1], lat, atol=2e-8)
    assert np.allclose(trees["lon"], lon, atol=2e-8) and np.allclose(trees["lat"], lat, atol=2e-8)
    truth = pd.read_csv(sim.root / "truth" / "trees.csv").set_index("tree_id")
    frame = json.loads((sim.root / "truth" / "frame.json").read_text())["frame"]
    matched = trees.dropna(subset=["truth_tree_id"])
    assert len(matched) == len(truth)
    t = truth.loc[matched["truth_tree_id"].astype(int)]
    t_lon, t_lat = _utm_to_lonlat(
        frame["crs"],
        t["crown_x"] + frame["origin_easting"],
        t["crown_y"] + frame["origin_northing"],
    )
    # The table's position is the median of the scanned points (0.3-0.6 m from the crown
    # centre here); mixing up the map's and the GNSS frame's origins would move it 5.5 m.
    assert _metres(matched["lon"], matched["lat"], t_lon, t_lat).max() < 1.0

    cloud = read_cloud(out / "map.laz")
    absolute = cloud.absolute_xyz
    from pyproj import Transformer

    to_utm = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    for f in json.loads((out / "crowns.geojson").read_text())["features"]:
        ring = np.array(f["geometry"]["coordinates"][0])
        e, n = to_utm.transform(ring[:, 0], ring[:, 1])
        poly = Polygon(np.column_stack([e, n])).buffer(0.005)  # LAZ keeps 1 mm
        pts = absolute[cloud.fields["segment_id"] == f["properties"]["segment_id"]]
        step = max(1, len(pts) // 500)
        assert all(poly.contains(Point(p)) for p in pts[::step, :2])
        assert poly.area < 1.2 * Polygon(np.column_stack([e, n])).convex_hull.area + 1


def test_the_same_tree_has_the_same_id_in_every_output(gis_run) -> None:
    """Join trees.csv, trees.parquet, every GeoJSON, the GeoPackage layers, map.laz's
    segment_id and the per-tree LAZ files on tree_id / segment: they agree."""
    import pyogrio

    _, out, _ = gis_run
    csv = pd.read_csv(out / "trees.csv", dtype={"tree_id": str})
    ids = csv.set_index("tree_id")["segment"]
    assert ids.index.is_unique and ids.is_unique and len(ids) == 6
    assert all(re.fullmatch(r"r\d+-[LR]\d+", t) for t in ids.index)
    parquet = pd.read_parquet(out / "trees.parquet")
    assert parquet.set_index("tree_id")["segment"].to_dict() == ids.to_dict()
    for name in ("trees.geojson", "crowns.geojson"):
        props = [f["properties"] for f in json.loads((out / name).read_text())["features"]]
        key = "segment" if name == "trees.geojson" else "segment_id"
        assert {p["tree_id"]: p[key] for p in props} == ids.to_dict(), name
    rows = json.loads((out / "rows.geojson").read_text())["features"]
    assert {f["properties"]["row"] for f in rows} == set(csv["row"])
    assert sum(f["properties"]["n_trees"] for f in rows) == len(csv)
    for layer, key in (("trees", "segment"), ("crowns", "segment_id")):
        gdf = pyogrio.read_dataframe(out / "trees.gpkg", layer=layer)
        assert dict(zip(gdf["tree_id"], gdf[key])) == ids.to_dict(), layer
    cloud = read_cloud(out / "map.laz")
    assert "tree_id" not in cloud.fields and "truth_tree_id" in cloud.fields
    seg_ids = cloud.fields["segment_id"]
    counts = pd.Series(seg_ids[seg_ids >= 0]).value_counts()
    assert counts.to_dict() == csv.set_index("segment")["n_points"].to_dict()
    for tree_id, segment in ids.items():
        part = read_cloud(out / "trees" / f"{tree_id}.laz")
        mine = cloud.absolute_xyz[seg_ids == segment]
        assert np.array_equal(part.absolute_xyz, mine)
        assert set(np.unique(part.fields["segment_id"])) == {segment}
        # trees.csv x, y: the median of the tree's points (the table's position)
        row = csv.set_index("tree_id").loc[tree_id]
        centre = np.median(part.xyz[:, :2] + part.origin[:2] - cloud.origin[:2], axis=0)
        assert np.allclose(centre, row[["x", "y"]].to_numpy(float), atol=1e-9)


def test_map_laz_las_classes_follow_the_segmentation_and_the_truth(gis_run) -> None:
    """5 exactly on the trees' points; against the simulator: its ground points are 2 or 4,
    its tree points 5 or 4 (trunks, low branches) and never ground."""
    _, out, _ = gis_run
    cloud = read_cloud(out / "map.laz")
    cls = np.asarray(cloud.fields["classification"])
    seg_ids = cloud.fields["segment_id"]
    truth = np.asarray(cloud.fields["truth_tree_id"])
    assert np.array_equal(cls == 5, seg_ids >= 0)
    assert set(np.unique(cls)) <= {1, 2, 4, 5}
    ground = truth < 0
    assert np.mean(cls[ground] == 2) > 0.95
    assert np.mean(np.isin(cls[~ground], [4, 5])) > 0.95
    assert np.mean(cls[~ground] == 2) < 0.02
    assert np.mean(truth[cls == 5] >= 0) > 0.99


def test_exported_tree_volume_matches_trees_csv(gis_run) -> None:
    """``canopy-kit volume trees/<id>.laz --voxel-size 0.1`` gives the table's volume: the run
    measures the tree thinned to volume.voxel_size, on the map's points as map.laz stores
    them (1 mm). Measured on the unrounded points the alpha shape differed by up to 1.4e-3."""
    from typer.testing import CliRunner

    from canopy_kit.cli import app

    _, out, _ = gis_run
    csv = pd.read_csv(out / "trees.csv", dtype={"tree_id": str}).set_index("tree_id")
    runner = CliRunner()
    for tree_id in csv.index:
        for method, column, extra in (
            ("convex_hull", "volume_convex_hull_m3", []),
            ("alpha_shape", "volume_alpha_m3", ["--alpha", "0.9"]),
        ):
            res = runner.invoke(
                app,
                [
                    "volume",
                    str(out / "trees" / f"{tree_id}.laz"),
                    "-m",
                    method,
                    "--voxel-size",
                    "0.1",
                    "--json",
                    *extra,
                ],
            )
            assert res.exit_code == 0, res.output
            got = json.loads(res.output)["volume_m3"]
            # trees.csv holds volumes to the litre
            assert got == pytest.approx(csv.loc[tree_id, column], abs=5e-4), (tree_id, method)
        plain = runner.invoke(
            app, ["volume", str(out / "trees" / f"{tree_id}.laz"), "-m", "convex_hull", "--json"]
        )
        n_all = json.loads(plain.output)["n_points"]
        assert n_all == csv.loc[tree_id, "n_points"]
        # With the run's config: its recommended estimator, parameters and voxel size.
        as_run = runner.invoke(
            app,
            [
                "volume",
                str(out / "trees" / f"{tree_id}.laz"),
                "--config",
                str(out / "config.toml"),
                "--json",
            ],
        )
        assert as_run.exit_code == 0, as_run.output
        measured = json.loads(as_run.output)
        assert measured["method"] == csv.loc[tree_id, "volume_method"]
        from canopy_kit.volume.verb import volume_column

        column = volume_column(measured["method"])
        assert measured["volume_m3"] == pytest.approx(csv.loc[tree_id, column], abs=5e-4)


def test_provenance_in_metrics_tables_gpkg_and_geojson(gis_run) -> None:
    from rosbags.highlevel import AnyReader

    from canopy_kit import __version__
    from canopy_kit.io.gpkg import gpkg_metadata

    sim, out, _ = gis_run
    prov = json.loads((out / "metrics.json").read_text())["provenance"]
    assert set(prov) == PROVENANCE_KEYS
    assert all(isinstance(v, str | int | float) for v in prov.values())
    bag = Path(sim.bag)
    digest = hashlib.sha256()
    for p in sorted(q for q in bag.rglob("*") if q.is_file()):
        digest.update(p.relative_to(bag).as_posix().encode() + b"\0" + p.read_bytes())
    with AnyReader([bag]) as reader:
        first = reader.start_time  # ns of the bag's first message
    assert prov == {
        **prov,
        "orchard": "block 7",
        "bag": bag.name,
        "bag_sha256": digest.hexdigest(),
        "software_version": __version__,
        "preset": "adaptive",
        "drone_images": "",
    }
    assert pd.Timestamp(prov["session_date"]).value == first
    assert prov["session_date"].endswith("Z") and prov["run_started_utc"].endswith("Z")
    assert 0 < prov["run_seconds"] < 3600
    import pyarrow.parquet as pq

    meta = pq.read_schema(out / "trees.parquet").metadata
    assert json.loads(meta[b"provenance"]) == prov
    # GDAL keeps no empty metadata item: drone_images "" (no photos) is absent there
    assert gpkg_metadata(out / "trees.gpkg") == {k: str(v) for k, v in prov.items() if str(v)}
    for name in ("trees.geojson", "crowns.geojson", "rows.geojson"):
        assert json.loads((out / name).read_text())["provenance"] == prov, name


def test_trees_csv_is_rounded_to_its_meaning_and_carries_its_provenance(gis_run) -> None:
    """Metres to the millimetre, lat/lon to 1e-8 degree (about 1 mm: no float noise, no
    precision lost beyond the map's own LAS grid); the full-precision numbers are in
    trees.parquet; the provenance is in the CSVW sidecar."""
    _, out, _ = gis_run
    lines = (out / "trees.csv").read_text().splitlines()
    header = lines[0].split(",")
    for line in lines[1:]:
        cells = line.split(",")
        for col, most in (("lat", 8), ("lon", 8), ("x", 3), ("y", 3), ("height_m", 3)):
            cell = cells[header.index(col)]
            decimals = cell.split(".")[1] if "." in cell else ""
            assert "e" not in cell and len(decimals) <= most, (col, cell)
    csv = pd.read_csv(out / "trees.csv", dtype={"tree_id": str})
    parquet = pd.read_parquet(out / "trees.parquet")
    assert np.allclose(csv["lat"], parquet["lat"], rtol=0, atol=5e-9)
    assert np.allclose(csv["x"], parquet["x"], rtol=0, atol=5e-4)
    assert (np.abs(parquet["lat"] - parquet["lat"].round(8)) > 0).any()  # parquet: not rounded
    meta = json.loads((out / "trees.csv-metadata.json").read_text())
    provenance = json.loads((out / "metrics.json").read_text())["provenance"]
    assert meta["url"] == "trees.csv" and meta["prov:wasGeneratedBy"] == provenance
    assert [c["name"] for c in meta["tableSchema"]["columns"]] == header


def test_evaluate_reads_the_renamed_truth_field(gis_run) -> None:
    from canopy_kit.evaluate.segmentation_score import evaluate_run

    sim, out, _ = gis_run
    points = evaluate_run(out, sim.root, mode="points")
    footprints = evaluate_run(out, sim.root, mode="footprints")
    assert points.n_truth == footprints.n_truth == 6
    assert points.success_rate == footprints.success_rate == 1.0


def test_plot_top_view_labels_trees_by_tree_id(gis_run) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from canopy_kit.config import load_preset
    from canopy_kit.pipeline import compute
    from canopy_kit.segment.plots import plot_top_view

    sim, out, results = gis_run
    ctx, _ = compute(load_preset("adaptive"), sim.bag, out)  # every stage from the cache
    fig = plot_top_view(ctx.mapping.map, ctx.segmentation)
    labels = {t.get_text() for t in fig.axes[0].texts} - {""}
    assert labels == set(results.trees["tree_id"])


# -- segment: with and without a CRS --------------------------------------------------------
def test_segment_folder_geojson_and_gpkg_round_trip(tmp_path) -> None:
    from canopy_kit.segment.export import read_segmentation, write_segmentation
    from canopy_kit.segment.verb import segment

    orch = synthetic_orchard(rows=2, trees_per_row=2, density=100)
    seg = segment(orch.cloud, "adaptive")
    paths = write_segmentation(tmp_path / "run", seg, orch.cloud, provenance={"orchard": "x"})
    assert not seg.rows.lines  # two trees a row: too few for a row line
    for key in ("positions", "crowns", "rows"):
        data = validate_rfc7946(paths[key], min_features=0 if key == "rows" else 1)
        assert data["provenance"] == {"orchard": "x"}
    pos = json.loads(paths["positions"].read_text())["features"]
    lon, lat = _utm_to_lonlat(
        "EPSG:32610", seg.trees[0].x + seg.origin[0], seg.trees[0].y + seg.origin[1]
    )
    assert pos[0]["geometry"]["coordinates"][:2] == pytest.approx([lon, lat], abs=1e-10)
    assert pos[0]["geometry"]["coordinates"][2] == pytest.approx(seg.trees[0].z + seg.origin[2])
    run = read_segmentation(tmp_path / "run")
    assert set(run.footprints) == set(seg.footprints)
    for sid, ring in seg.footprints.items():
        assert np.allclose(run.footprints[sid], ring, atol=1e-6)
    (tmp_path / "run" / "trees.gpkg").unlink()  # older folders: WGS84 crowns.geojson only
    legacy = read_segmentation(tmp_path / "run", with_cloud=False)
    for sid, ring in seg.footprints.items():
        assert np.allclose(legacy.footprints[sid], ring, atol=1e-4)


def test_a_map_without_crs_gets_no_geojson_and_says_why(tmp_path) -> None:
    from canopy_kit.segment.export import read_segmentation, write_segmentation
    from canopy_kit.segment.verb import segment

    orch = synthetic_orchard(rows=2, trees_per_row=2, density=100)
    local = PointCloud(orch.cloud.xyz, dict(orch.cloud.fields))
    seg = segment(local, "adaptive")
    out = tmp_path / "run"
    out.mkdir()
    (out / "crowns.geojson").write_text("{}")  # a stale file of an earlier, georeferenced run
    write_segmentation(out, seg, local)
    assert not list(out.glob("*.geojson"))
    assert "no CRS" in json.loads((out / "segmentation.json").read_text())["geojson"]
    run = read_segmentation(out)
    for sid, ring in seg.footprints.items():
        assert np.allclose(run.footprints[sid], ring, atol=1e-9)


def test_polygon_is_closed_and_counter_clockwise() -> None:
    from canopy_kit.io.geojson import polygon

    clockwise = np.array([[0, 0], [0, 1], [1, 1], [1, 0]], float)
    ring = polygon(clockwise[:, 0], clockwise[:, 1])["coordinates"][0]
    ccw = [[1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.0], [1.0, 0.0]]
    assert ring == ccw  # reversed, closed
    closed = np.array(ccw)
    assert polygon(closed[:, 0], closed[:, 1])["coordinates"][0] == ccw  # kept as it is


def test_bag_hash_streams_files_and_folders(tmp_path) -> None:
    from canopy_kit.results.provenance import CHUNK, bag_sha256

    data = np.random.default_rng(0).bytes(CHUNK * 2 + 17)  # more than one chunk
    (tmp_path / "a.bag").write_bytes(data)
    assert bag_sha256(tmp_path / "a.bag") == hashlib.sha256(data).hexdigest()
    folder = tmp_path / "ros2"
    folder.mkdir()
    (folder / "metadata.yaml").write_bytes(b"m")
    (folder / "b.mcap").write_bytes(b"bb")
    expected = hashlib.sha256(b"b.mcap\0bb" + b"metadata.yaml\0m").hexdigest()
    assert bag_sha256(folder) == expected


def test_bag_hash_on_a_background_thread_is_the_hash_and_can_be_stopped(tmp_path) -> None:
    import threading

    from canopy_kit.errors import InputError
    from canopy_kit.results.provenance import CHUNK, BagHash, bag_sha256

    data = np.random.default_rng(1).bytes(CHUNK * 3 + 5)
    (tmp_path / "a.bag").write_bytes(data)
    assert BagHash(tmp_path / "a.bag").result() == hashlib.sha256(data).hexdigest()
    later = BagHash(tmp_path / "a.bag", start=False)
    assert later.result() == hashlib.sha256(data).hexdigest()  # started by result()
    stop = threading.Event()
    stop.set()
    with pytest.raises(InputError, match="a.bag: hashing stopped"):
        bag_sha256(tmp_path / "a.bag", stop)
    stopped = BagHash(tmp_path / "a.bag")
    stopped.cancel()  # returns once the thread has ended, whether or not it had finished
    assert stopped._future.done()


def test_crowns_are_labelled_by_the_matched_lidar_tree() -> None:
    from ground_truth.match import crown_tree_ids
    from ground_truth.plots import crown_labels

    crowns = pd.DataFrame({"crown_id": [1, 2, 3], "x": [0.0, 5, 10], "y": [0.0, 0, 0]})
    matched = pd.DataFrame(
        {"tree_id": ["r0-L0", "r0-L1"], "matched": [True, False], "aerial_crown_id": [3.0, np.nan]}
    )
    crowns["tree_id"] = crown_tree_ids(crowns, matched)
    assert crowns["tree_id"].tolist() == ["", "", "r0-L0"]
    assert crown_labels(crowns) == ["aerial 1", "aerial 2", "r0-L0"]
    assert crown_labels(crowns.drop(columns="tree_id")) == ["aerial 1", "aerial 2", "aerial 3"]


def test_ground_truth_tables_keep_lat_lon_to_1e_9_degrees() -> None:
    """crowns.csv and the aerial trees.csv: 9 decimals (1e-4 deg put crowns 5 m apart on
    one position, issue 26)."""
    from ground_truth.pipeline import table_csv

    text = table_csv(
        pd.DataFrame(
            {
                "crown_id": [1, 2],
                "lat": [37.28100123456, 37.28104567891],
                "lon": [-120.41999987654, -120.4199],
            }
        )
    )
    rows = [line.split(",") for line in text.splitlines()[1:]]
    assert [r[1] for r in rows] == ["37.281001235", "37.281045679"]
    assert [r[2] for r in rows] == ["-120.419999877", "-120.419900000"]


def test_cli_run_and_segment_export_trees(gis_run, tmp_path) -> None:
    """``run --export-trees --orchard`` (stages from a copied cache) and ``segment
    --export-trees`` write one LAZ per trees.csv tree_id."""
    import shutil

    from typer.testing import CliRunner

    from canopy_kit.cli import app

    sim, out, _ = gis_run
    again = tmp_path / "again"
    shutil.copytree(out / ".cache", again / ".cache")
    (again / "trees").mkdir()
    (again / "trees" / "r9-L9.laz").write_bytes(b"")  # a tree of an earlier run: removed
    runner = CliRunner()
    res = runner.invoke(
        app,
        ["run", str(sim.bag), "--out", str(again), "--export-trees", "--orchard", "north block"],
    )
    assert res.exit_code == 0, res.output
    metrics = json.loads((again / "metrics.json").read_text())
    assert metrics["provenance"]["orchard"] == "north block"
    assert set(metrics["cached_stages"]) >= {"map", "segment", "volumes"}
    ids = pd.read_csv(again / "trees.csv", dtype={"tree_id": str})["tree_id"]
    assert sorted(p.stem for p in (again / "trees").glob("*.laz")) == sorted(ids)
    res = runner.invoke(
        app,
        [
            "segment",
            str(out / "map.laz"),
            "--out",
            str(tmp_path / "seg"),
            "--export-trees",
            "--no-cloud",
        ],
    )
    assert res.exit_code == 0, res.output
    seg_trees = pd.read_csv(tmp_path / "seg" / "trees.csv", dtype={"tree_id": str})
    seg_ids = seg_trees["tree_id"]
    assert sorted(p.stem for p in (tmp_path / "seg" / "trees").glob("*.laz")) == sorted(seg_ids)
    # `segment` writes the run's columns for a tree (before its volumes), in the run's order,
    # measured the same way: the same trees have the same numbers (to the CSV's rounding).
    run_trees = pd.read_csv(again / "trees.csv", dtype={"tree_id": str})
    assert [c for c in run_trees.columns if c in seg_trees.columns] == list(seg_trees.columns)
    assert seg_trees["lat"].notna().all() and seg_trees["lon"].notna().all()
    same = run_trees.merge(seg_trees, on=["tree_id", "n_points"], suffixes=("_run", "_seg"))
    assert len(same) >= len(run_trees) - 1, (len(same), len(run_trees))
    for col, tol in (("x", 2e-3), ("y", 2e-3), ("lat", 5e-8), ("height_m", 2e-3)):
        assert np.allclose(same[f"{col}_run"], same[f"{col}_seg"], rtol=0, atol=tol), col
    for col in ("crown_diameter_m", "projected_area_m2", "crown_base_height_m"):
        assert np.allclose(same[f"{col}_run"], same[f"{col}_seg"], rtol=0, atol=2e-3), col
    for name in ("trees.geojson", "crowns.geojson", "rows.geojson", "rows_sections.geojson"):
        validate_rfc7946(tmp_path / "seg" / name)
    # ... and the run's row metrics: the same rows cut into the same sections.
    seg_rows = pd.read_csv(tmp_path / "seg" / "rows.csv")
    run_rows = pd.read_csv(again / "rows.csv")
    assert list(seg_rows.columns) == list(run_rows.columns)
    assert seg_rows.groupby("row").size().to_dict() == run_rows.groupby("row").size().to_dict()
    res = runner.invoke(
        app, ["run", str(sim.bag), "--out", str(tmp_path / "s"), "--stream", "--export-trees"]
    )
    assert "--export-trees" in str(res.exception)  # an InputError: `canopy-kit` exits 2


def test_a_table_without_positions_gets_no_trees_geojson(tmp_path) -> None:
    """A run whose map has no CRS: trees.csv/parquet are written, no trees.geojson (and an
    earlier run's is removed), full-precision positions where there are some."""
    from canopy_kit.results.outputs import trees_geojson, write_trees

    local = pd.DataFrame(
        {
            "tree_id": ["r0-L0"],
            "segment": [0],
            "x": [1.0],
            "y": [2.0],
            "lat": [np.nan],
            "lon": [np.nan],
        }
    )
    (tmp_path / "trees.geojson").write_text("{}")
    files = write_trees(local, tmp_path, {"orchard": "o"})
    assert (
        set(files) == {"trees.csv", "trees.csv-metadata.json", "trees.parquet"}
        and not (tmp_path / "trees.geojson").exists()
    )
    placed = local.assign(lat=[37.123456789012], lon=[-120.98765432101], volume=[np.nan])
    data = json.loads(trees_geojson(placed, {"orchard": "o"}))
    assert data["features"][0]["geometry"]["coordinates"] == [-120.98765432101, 37.123456789012]
    assert data["features"][0]["properties"]["volume"] is None and data["provenance"] == {
        "orchard": "o"
    }


def test_tree_file_names_are_safe() -> None:
    from canopy_kit.segment.tree_export import tree_file_name

    assert tree_file_name("r0-L3") == "r0-L3.laz"
    assert tree_file_name("t2") == "t2.laz"
    assert tree_file_name("a/b c") == "a_b_c.laz"


@pytest.mark.slow
def test_drone_crowns_carry_the_lidar_tree_id(tiny_drone_session, tmp_path) -> None:
    """With drone photos: each aerial crown matched to a LiDAR tree carries its tree_id in
    crowns.csv (lat/lon to >= 7 decimals) and on the orthomosaic figure, and trees.csv's
    aerial columns are that crown's."""
    import matplotlib

    matplotlib.use("Agg")
    from canopy_kit.config import load_preset
    from canopy_kit.pipeline import compute
    from ground_truth.plots import plot_crowns

    # the 2 x 3 pistachio session with drone photos (seed 4), shared with other files
    sim = tiny_drone_session
    drone = sim.drone_dir
    out = tmp_path / "run"
    results = sim.run_into(out)
    assert results.metrics["provenance"]["drone_images"] == str(drone)
    trees = pd.read_csv(out / "trees.csv", dtype={"tree_id": str}).set_index("tree_id")
    text = (out / "aerial" / "crowns.csv").read_text().splitlines()
    crowns = pd.read_csv(out / "aerial" / "crowns.csv", dtype={"tree_id": str}).fillna(
        {"tree_id": ""}
    )
    header = text[0].split(",")
    for line in text[1:]:
        for col in ("lat", "lon"):
            assert len(line.split(",")[header.index(col)].split(".")[1]) >= 7
    named = crowns[crowns["tree_id"] != ""].set_index("tree_id")
    matched = trees[trees["aerial_diameter_m"].notna()]
    assert len(matched) == len(trees) == 6 and set(named.index) == set(matched.index)
    assert np.allclose(  # trees.csv: metres to the mm
        named.loc[matched.index, "diameter_max_m"], matched["aerial_diameter_m"], rtol=0, atol=5e-4
    )
    ctx, _ = compute(load_preset("adaptive"), sim.bag, out, drone_images=drone, sfm_threads=1)
    ax = plot_crowns(ctx.aerial.ortho, ctx.aerial.segmentation, ctx.aerial.crowns)
    labels = [t.get_text() for t in ax.texts]
    expected = [tid or f"aerial {cid}" for tid, cid in zip(crowns["tree_id"], crowns["crown_id"])]
    assert labels == expected and set(trees.index) <= set(labels)
