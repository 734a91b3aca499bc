"""trees.gpkg and the GeoJSON files as GDAL reads them: ``ogrinfo`` (Debian's gdal-bin, which
``make setup`` installs through scripts/system-deps.sh) opens each without a warning or
error, with one feature per tree, the geometry type and CRS each file promises, and the
GeoJSON positions in RFC 7946 order (longitude, latitude).

GDAL here is a separate build from the one inside pyogrio that writes the GeoPackage, so
what it says is what another program on the user's machine would say.
"""

from __future__ import annotations

import re
import shutil
import sqlite3
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fixtures_sim import synthetic_orchard

from canopy_kit.core.cloud import PointCloud
from canopy_kit.results.outputs import write_trees

OGRINFO = shutil.which("ogrinfo")
pytestmark = pytest.mark.skipif(
    OGRINFO is None, reason="ogrinfo (Debian gdal-bin) is absent: run `make setup`"
)


def ogrinfo(*args: str | Path) -> str:
    """``ogrinfo`` output; asserts exit 0 and neither a warning nor an error."""
    done = subprocess.run(
        [OGRINFO, *map(str, args)], capture_output=True, text=True, timeout=120, check=False
    )
    said = done.stdout + done.stderr
    assert done.returncode == 0, said
    assert "Warning" not in said and "ERROR" not in said, said
    return done.stdout


def layers(summary: str) -> dict[str, dict[str, str]]:
    """``ogrinfo -al -so`` as {layer: {"geometry", "count", "srs"}}."""
    out: dict[str, dict[str, str]] = {}
    for block in summary.split("Layer name: ")[1:]:
        name = block.splitlines()[0].strip()
        out[name] = {
            "geometry": re.search(r"^Geometry: (.+)$", block, re.M).group(1),
            "count": re.search(r"^Feature Count: (\d+)$", block, re.M).group(1),
            "srs": block.split("Layer SRS WKT:")[1].split("Data axis")[0]
            if "Layer SRS WKT:" in block
            else "",
        }
    return out


def epsg(srs_wkt: str) -> int | None:
    """The EPSG code of a layer's CRS (its last ID, the CRS's own)."""
    codes = re.findall(r'ID\["EPSG",(\d+)\]', srs_wkt)
    return int(codes[-1]) if codes else None


def points(full: str) -> np.ndarray:
    """The POINT coordinates ``ogrinfo -al`` prints, in its (x, y) order."""
    found = re.findall(r"^\s*POINT(?: Z)? \(([-0-9.e ]+)\)$", full, re.M)
    return np.array([[float(v) for v in p.split()[:2]] for p in found])


def gpkg_version(path: Path) -> tuple[bytes, int]:
    """A GeoPackage's application id and user version (SQLite header), read without GDAL."""
    with sqlite3.connect(path) as db:
        app = db.execute("PRAGMA application_id").fetchone()[0]
        user = db.execute("PRAGMA user_version").fetchone()[0]
    return app.to_bytes(4, "big"), user


# -- a segmentation of a synthetic orchard (fast) ----------------------------------------------
@pytest.fixture(scope="module")
def segmented(tmp_path_factory):
    from canopy_kit.segment.export import write_segmentation
    from canopy_kit.segment.verb import segment

    orch = synthetic_orchard(rows=2, trees_per_row=4, density=100)
    seg = segment(orch.cloud, "adaptive")
    out = tmp_path_factory.mktemp("ogr") / "run"
    paths = write_segmentation(out, seg, orch.cloud, with_cloud=False, provenance={"orchard": "x"})
    return seg, paths


def test_segmentation_gpkg_opens_cleanly_with_one_feature_per_tree(segmented) -> None:
    seg, paths = segmented
    assert gpkg_version(paths["gis"]) == (b"GPKG", 10200)  # GeoPackage 1.2: every GDAL reads it
    found = layers(ogrinfo("-al", "-so", paths["gis"]))
    assert set(found) == {"trees", "crowns", "rows"}
    assert found["trees"]["geometry"] == "Point"
    assert int(found["trees"]["count"]) == len(seg.table()) == len(seg.trees)
    assert found["crowns"]["geometry"] == "Polygon"
    assert int(found["crowns"]["count"]) == len(seg.footprints)
    assert found["rows"]["geometry"] == "Line String"
    assert int(found["rows"]["count"]) == len(seg.rows.lines)
    for layer in found.values():
        assert epsg(layer["srs"]) == 32610  # the map's projected CRS (UTM 10N)


@pytest.mark.parametrize("name", ["trees.geojson", "crowns.geojson", "rows.geojson"])
def test_segmentation_geojson_opens_cleanly_in_wgs84(segmented, name) -> None:
    seg, paths = segmented
    path = paths["positions"].parent / name
    (layer,) = layers(ogrinfo("-al", "-so", path)).values()
    assert epsg(layer["srs"]) in (4326, 4979)  # WGS84 (4979: with ellipsoidal heights)
    expected = {
        "trees.geojson": ("3D Point", len(seg.trees)),
        "crowns.geojson": ("Polygon", len(seg.footprints)),
        "rows.geojson": ("Line String", len(seg.rows.lines)),
    }[name]
    assert (layer["geometry"], int(layer["count"])) == expected


def test_positions_are_longitude_then_latitude(segmented) -> None:
    from pyproj import Transformer

    seg, paths = segmented
    shown = points(ogrinfo("-al", paths["positions"]))
    table = seg.table()
    e, n = table["x"].to_numpy() + seg.origin[0], table["y"].to_numpy() + seg.origin[1]
    lon, lat = Transformer.from_crs("EPSG:32610", "EPSG:4326", always_xy=True).transform(e, n)
    np.testing.assert_allclose(shown, np.column_stack([lon, lat]), rtol=0, atol=1e-9)


def test_a_gpkg_without_crs_opens_cleanly(tmp_path) -> None:
    from canopy_kit.segment.export import write_segmentation
    from canopy_kit.segment.verb import segment

    orch = synthetic_orchard(rows=2, trees_per_row=3, density=100)
    local = PointCloud(orch.cloud.xyz, dict(orch.cloud.fields))  # no GNSS: no CRS
    seg = segment(local, "adaptive")
    paths = write_segmentation(tmp_path / "run", seg, local, with_cloud=False)
    found = layers(ogrinfo("-al", "-so", paths["gis"]))
    assert int(found["trees"]["count"]) == len(seg.trees)
    assert epsg(found["trees"]["srs"]) is None  # GeoPackage's undefined Cartesian SRS
    assert not list((tmp_path / "run").glob("*.geojson"))


# -- the per-tree table's GeoJSON, from a table built by hand ----------------------------------
def test_trees_geojson_of_a_tree_table_opens_cleanly(tmp_path) -> None:
    n = 7
    rng = np.random.default_rng(3)
    trees = pd.DataFrame(
        {
            "tree_id": [f"r{i // 4}-L{i % 4}" for i in range(n)],
            "row": np.arange(n) // 4,
            "x": rng.uniform(0, 30, n),
            "y": rng.uniform(0, 12, n),
            "lat": 37.28 + rng.uniform(0, 1e-3, n),
            "lon": -120.42 + rng.uniform(0, 1e-3, n),
            "n_points": rng.integers(1000, 40000, n),
            "volume_foliage_envelope_m3": np.where(np.arange(n) == 2, np.nan, 20.0),
            "volume_flags": ["", "sparse", "", "", "cut", "", ""],
            "aerial_flag": [None] * n,
            "scan_coverage": rng.uniform(0, 1, n),
        }
    )
    written = write_trees(trees, tmp_path, provenance={"orchard": "block 7"})
    full = ogrinfo("-al", written["trees.geojson"])
    (layer,) = layers(ogrinfo("-al", "-so", written["trees.geojson"])).values()
    assert layer["geometry"] == "Point" and int(layer["count"]) == n
    assert epsg(layer["srs"]) == 4326
    np.testing.assert_allclose(points(full), trees[["lon", "lat"]].to_numpy(), rtol=0, atol=1e-9)


# -- the files a pipeline run writes -----------------------------------------------------------
@pytest.mark.slow
def test_the_gis_files_of_a_pipeline_run_open_cleanly(tiny_pistachio_run) -> None:
    out, trees = tiny_pistachio_run.out_dir, tiny_pistachio_run.trees
    assert gpkg_version(out / "trees.gpkg") == (b"GPKG", 10200)
    found = layers(ogrinfo("-al", "-so", out / "trees.gpkg"))
    assert found["trees"]["geometry"] == "Point"
    assert int(found["trees"]["count"]) == len(trees) > 0
    assert {epsg(layer["srs"]) for layer in found.values()} == {epsg(found["trees"]["srs"])}
    assert 32601 <= epsg(found["trees"]["srs"]) <= 32760  # the drive's UTM zone
    full = ogrinfo("-al", out / "trees.geojson")
    (layer,) = layers(ogrinfo("-al", "-so", out / "trees.geojson")).values()
    assert layer["geometry"] == "Point" and int(layer["count"]) == len(trees)
    np.testing.assert_allclose(points(full), trees[["lon", "lat"]].to_numpy(), rtol=0, atol=1e-9)
    for name in ("crowns.geojson", "rows.geojson"):
        ogrinfo("-al", "-so", out / name)
