"""``canopy-kit run MAP`` on a map made elsewhere (issue 47): a simulated session's map built
from its true poses (an independent map: no odometry of ours) written as LAS with a CRS and
as PCD without, a real forest plot, and the mistakes a user makes with map files."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from canopy_kit.core.cloud import PointCloud
from canopy_kit.io.clouds import write_cloud


def cli(monkeypatch, capsys, *args: object) -> tuple[int, str, str]:
    """``canopy-kit ARGS`` in this process: (exit code, stdout, stderr)."""
    from canopy_kit.cli import main

    monkeypatch.setattr(sys, "argv", ["canopy-kit", *map(str, args)])
    monkeypatch.setenv("COLUMNS", "200")
    monkeypatch.delenv("CANOPY_KIT_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_info:
        main()
    out = capsys.readouterr()
    return exit_info.value.code, out.out, out.err


# -- a simulated orchard's map, as FAST-LIO / a scanner would hand it over ---------------------
@pytest.fixture(scope="module")
def finished(tiny_pistachio, tmp_path_factory):
    """The tiny session's true-pose map as ``map.las`` (UTM, CRS in the file) and ``map.pcd``
    (local x/y, no CRS), its true trajectory as TUM, and the truth."""
    from canopy_kit.evaluate.truth import load_truth
    from canopy_kit.evaluate.truth_map import truth_map

    truth = load_truth(tiny_pistachio.root)
    cloud = truth_map(tiny_pistachio.root, voxel_size=0.05)
    # Only what a foreign map file surely has: coordinates (no per-point truth labels).
    plain = PointCloud(cloud.xyz, {}, cloud.crs, cloud.origin)
    folder = tmp_path_factory.mktemp("finished_maps")
    las = write_cloud(folder / "map.las", plain)
    pcd = write_cloud(folder / "map.pcd", PointCloud(plain.xyz, dict(plain.fields)))
    tum = folder / "poses_tum.txt"
    traj = truth.trajectory[["time", "x", "y", "z", "qx", "qy", "qz", "qw"]]
    tum.write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        + "\n".join(" ".join(f"{v:.6f}" for v in row) for row in traj.to_numpy())
    )
    return {"las": las, "pcd": pcd, "tum": tum, "truth": truth, "root": tiny_pistachio.root}


def _matched(trees: pd.DataFrame, truth: pd.DataFrame, shift: np.ndarray) -> pd.DataFrame:
    """Each run tree with the nearest true tree (run x, y + ``shift`` = truth-local x, y)."""
    xy = trees[["x", "y"]].to_numpy(float) + shift
    txy = truth[["x", "y"]].to_numpy(float)
    d = np.linalg.norm(xy[:, None, :] - txy[None, :, :], axis=2)
    nearest = d.argmin(axis=1)
    return trees.assign(truth_index=nearest, truth_distance_m=d[np.arange(len(xy)), nearest]).join(
        truth.reset_index(drop=True).add_suffix("_true"), on="truth_index"
    )


def test_las_map_with_crs_runs_the_whole_chain_and_georeferences_the_trees(
    finished, tmp_path, monkeypatch, capsys
):
    from pyproj import Transformer

    out = tmp_path / "las_run"
    code, stdout, err = cli(
        monkeypatch, capsys, "run", finished["las"], "--out", out, "--truth", finished["root"]
    )
    assert code == 0, err
    truth = finished["truth"]
    trees = pd.read_csv(out / "trees.csv")
    metrics = json.loads((out / "metrics.json").read_text())
    # Same per-tree columns as a bag run (tests/test_pipeline.py).
    assert list(trees.columns[:7]) == ["tree_id", "label", "row", "x", "y", "lat", "lon"]
    ev = metrics["evaluation"]
    assert ev["segmentation"]["n_truth"] == len(truth.trees)
    assert ev["segmentation"]["success_rate"] == 1.0
    assert ev["segmentation"]["label_accuracy"] == 1.0
    # The bag run's volume accuracy (tests/test_pipeline.py) on a map from the true poses.
    assert ev["volumes"]["convex_hull"]["mape_pct"] < 10.0
    assert ev["volumes"]["alpha_shape"]["mape_pct"] < 10.0
    # lat/lon against the true trunks projected by pyproj itself (crown centre ~ trunk).
    to_utm = Transformer.from_crs("EPSG:4326", truth.frame.crs, always_xy=True)
    e, n = to_utm.transform(trees["lon"].to_numpy(), trees["lat"].to_numpy())
    m = _matched(trees.assign(x=e, y=n), truth.trees, -truth.frame.origin[:2])
    assert m["truth_index"].is_unique and len(m) == len(truth.trees)
    assert m["truth_distance_m"].max() < 0.5
    # No trajectory given: the drive-based checks say so instead of failing.
    notes = {c["name"]: c for c in metrics["checks"]}
    assert notes["trajectory ATE RMSE (vs true odometry)"]["note"] == "not judged: no trajectory"
    assert (
        "not judged: no trajectory"
        in notes["map made elsewhere (registration, GNSS, drive)"]["note"]
    )
    assert not any("not georeferenced" in w for w in metrics["warnings"])
    page = (out / "report.html").read_text()
    assert "map made elsewhere" in page and "map.las" in page


def test_pcd_map_without_crs_keeps_local_xy_warns_and_judges_a_tum_trajectory(
    finished, tmp_path, monkeypatch, capsys
):
    out = tmp_path / "pcd_run"
    code, stdout, err = cli(
        monkeypatch,
        capsys,
        "run",
        finished["pcd"],
        "--trajectory",
        finished["tum"],
        "--out",
        out,
    )
    assert code == 0, err
    assert "not georeferenced" in stdout
    truth = finished["truth"]
    trees = pd.read_csv(out / "trees.csv")
    assert trees["lat"].isna().all() and trees["lon"].isna().all()
    assert not (out / "trees.geojson").exists()
    # One-to-one by position in the map's own (here: the truth's local) frame.
    m = _matched(trees, truth.trees, np.zeros(2))
    assert m["truth_index"].is_unique and len(m) == len(truth.trees)
    assert m["truth_distance_m"].max() < 0.5
    assert (m["label"] == m["label_true"]).all()  # the drive's first pass orders the labels
    err_pct = 100 * (m["volume_convex_hull_m3"] / m["crown_volume_m3_true"] - 1)
    assert np.mean(np.abs(err_pct)) < 10.0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mapping"]["trajectory_file"] == "poses_tum.txt"
    assert metrics["mapping"]["path_length_m"] > 10
    # The cache keys on the map file: unchanged, every stage is reused; touched, it is read anew.
    from canopy_kit.config import load_preset
    from canopy_kit.mapping.map_source import MapFile
    from canopy_kit.pipeline import compute

    source = MapFile(finished["pcd"], finished["tum"])
    _, cache = compute(load_preset("adaptive"), source, out)
    assert {"map", "segment", "volumes"} <= set(cache.hits)
    stat = finished["pcd"].stat()
    os.utime(finished["pcd"], ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    _, cache = compute(load_preset("adaptive"), source, out)
    assert "map" in cache.misses
    assert any("not georeferenced" in w for w in metrics["warnings"])


# -- a real cloud ---------------------------------------------------------------------------
@pytest.mark.slow  # about 1.5 CPU-minutes, most of it the volume estimators on sparse crowns
def test_a_real_forest_plot_runs_and_writes_sane_outputs(shared_data, tmp_path):
    """TreeLS's 10 m x 10 m pine plot (terrestrial scan, no CRS): not an orchard, so only
    that the run completes with a report and every tree's numbers are physical."""
    from canopy_kit.config import load_preset
    from canopy_kit.mapping.map_source import MapFile
    from canopy_kit.pipeline import run

    plot = shared_data / "treels" / "pine_plot.laz"
    results = run(load_preset("adaptive"), MapFile(plot), tmp_path / "plot")
    trees = results.trees
    assert (tmp_path / "plot" / "report.html").stat().st_size > 10_000
    assert len(trees) >= 1
    assert (trees["height_m"] > 0).all() and (trees["height_m"] < 40).all()
    assert (trees["n_points"] > 0).all()
    ok = trees["volume_convex_hull_m3"].dropna()
    assert len(ok) and (ok > 0).all() and (ok < 10 * 10 * 25).all()  # inside the plot's box
    assert trees["lat"].isna().all()


# -- mistakes ---------------------------------------------------------------------------------
@pytest.fixture
def small_map(tmp_path: Path) -> Path:
    """Two rows of synthetic crowns in UTM zone 10N (fast: no simulator)."""
    from fixtures_sim import synthetic_orchard

    return write_cloud(tmp_path / "small.laz", synthetic_orchard(density=150).cloud)


def _refused(monkeypatch, capsys, out: Path, *args: object) -> str:
    code, _, err = cli(monkeypatch, capsys, "run", *args, "--out", out)
    assert code == 2, err
    assert not out.exists()  # nothing half-written
    return err


def test_unusable_map_files_are_refused_naming_the_file(tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    empty = tmp_path / "empty.las"
    empty.write_bytes(b"")
    assert "empty.las" in _refused(monkeypatch, capsys, out, empty)
    junk = tmp_path / "junk.laz"
    junk.write_bytes(b"LASF" + bytes(range(256)) * 3)
    assert "junk.laz" in _refused(monkeypatch, capsys, out, junk)
    no_points = tmp_path / "no_points.pcd"
    no_points.write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\n"
        "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 0\nDATA ascii\n"
    )
    assert "no_points.pcd" in _refused(monkeypatch, capsys, out, no_points)
    rng = np.random.default_rng(0)
    flat = np.column_stack([rng.uniform(0, 30, (4000, 2)), rng.normal(0, 0.02, 4000)])
    ground = write_cloud(tmp_path / "ground.las", PointCloud(flat))
    err = _refused(monkeypatch, capsys, out, ground)
    assert "ground.las" in err and "above the ground" in err


def test_bad_crs_is_refused(small_map, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    local = write_cloud(tmp_path / "local.pcd", PointCloud(_read(small_map).xyz))
    assert "not a CRS" in _refused(monkeypatch, capsys, out, local, "--crs", "EPSG:999999")
    assert "not a projected CRS" in _refused(monkeypatch, capsys, out, local, "--crs", "4326")
    # The file says UTM 10N: --crs naming another zone contradicts it.
    err = _refused(monkeypatch, capsys, out, small_map, "--crs", "32611")
    assert "small.laz" in err and "differs" in err


def test_a_wkt_crs_pyproj_cannot_parse_is_refused(tmp_path, monkeypatch, capsys):
    import laspy

    header = laspy.LasHeader(point_format=3, version="1.4")
    header.add_extra_dims([])
    header.global_encoding.wkt = True
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr("PROJCS[nonsense"))
    las = laspy.LasData(header)
    xyz = np.random.default_rng(1).uniform(0, 10, (500, 3))
    las.x, las.y, las.z = xyz.T
    path = tmp_path / "bad_crs.las"
    las.write(path)
    err = _refused(monkeypatch, capsys, tmp_path / "out", path)
    assert "bad_crs.las" in err and "CRS" in err


def test_bad_trajectory_files_are_refused_naming_them(small_map, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    columns = tmp_path / "columns.csv"
    columns.write_text("a,b\n1,2\n3,4\n")
    err = _refused(monkeypatch, capsys, out, small_map, "--trajectory", columns)
    assert "columns.csv" in err and "x and y" in err
    words = tmp_path / "words.csv"
    words.write_text("t,x,y\n0,1,2\n1,north,3\n")
    err = _refused(monkeypatch, capsys, out, small_map, "--trajectory", words)
    assert "words.csv" in err and "'x'" in err
    short = tmp_path / "short_tum.txt"
    short.write_text("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 0\n")
    err = _refused(monkeypatch, capsys, out, small_map, "--trajectory", short)
    assert "short_tum.txt" in err and "line 2" in err
    far = tmp_path / "far.csv"  # local coordinates given with a map in UTM
    far.write_text("x,y\n-500000,-4000000\n-499990,-4000000\n")
    err = _refused(monkeypatch, capsys, out, small_map, "--trajectory", far)
    assert "far.csv" in err and "outside the map" in err


def test_map_options_with_a_bag_are_refused(tmp_path, monkeypatch, capsys):
    bag = tmp_path / "drive.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    err = _refused(monkeypatch, capsys, tmp_path / "out", bag, "--crs", "32633")
    assert "--crs" in err and "map file" in err


def test_a_trajectory_csv_in_the_map_files_coordinates_is_moved_with_the_map(tmp_path):
    """A UTM trajectory beside a UTM map ends up in the map's local frame (origin removed)."""
    from canopy_kit.mapping.map_source import read_trajectory

    path = tmp_path / "utm.csv"
    path.write_text("t,x,y\n0,700010.5,4100020.25\n1,700011.5,4100021.25\n")
    traj = read_trajectory(path, np.array([700000.0, 4100000.0, 50.0]))
    assert traj[["x", "y"]].to_numpy().tolist() == [[10.5, 20.25], [11.5, 21.25]]
    assert traj["z"].isna().all() and traj["time"].tolist() == [0.0, 1.0]
    headless = tmp_path / "headless.csv"  # t, x, y, z without a header
    headless.write_text("0,700010.5,4100020.25,51\n1,700011.5,4100021.25,52\n")
    traj = read_trajectory(headless, np.array([700000.0, 4100000.0, 50.0]))
    assert traj[["time", "x", "y", "z"]].to_numpy().tolist() == [
        [0.0, 10.5, 20.25, 1.0],
        [1.0, 11.5, 21.25, 2.0],
    ]


def _read(path: Path) -> PointCloud:
    from canopy_kit.io.clouds import read_cloud

    return read_cloud(path)


def test_a_tum_trajectory_is_judged_against_the_truth_and_none_is_not_judged(finished):
    """The true poses handed over as TUM score zero ATE; without a trajectory: not judged."""
    from canopy_kit.evaluate.trajectory_error import finished_map_errors
    from canopy_kit.mapping.map_source import MapFile, load_finished_map

    with_poses = load_finished_map(MapFile(finished["pcd"], finished["tum"]))
    assert with_poses.frame is None and with_poses.map.crs is None
    scored = finished_map_errors(with_poses, finished["root"])
    assert scored["ate_rmse_m"] < 0.01 and scored["poses"] >= 10
    bare = load_finished_map(MapFile(finished["las"]))
    assert bare.frame.crs == finished["truth"].frame.crs
    assert finished_map_errors(bare, finished["root"]) == {
        "not_judged": "not judged: no trajectory"
    }


def test_a_pcd_in_utm_with_crs_flag_keeps_a_local_origin_and_gives_lat_lon(tmp_path):
    """FAST-LIO-style map saved in absolute UTM coordinates (PCD has no CRS field) and a
    trajectory CSV in the same coordinates: ``--crs`` georeferences it, float64 coordinates
    stay local (round origin), and the trees' lat/lon are the known crown centres' (pyproj)."""
    from fixtures_sim import synthetic_orchard
    from pyproj import Transformer

    from canopy_kit.config import load_preset
    from canopy_kit.mapping.map_source import MapFile
    from canopy_kit.pipeline import compute

    orchard = synthetic_orchard(density=150)
    utm = orchard.cloud.absolute_xyz
    pcd = write_cloud(tmp_path / "fastlio_map.pcd", PointCloud(utm))  # no origin, no CRS
    drive = orchard.centres[:4] + orchard.cloud.origin[:2] + np.array([3.0, 0.0])  # beside row 0
    traj = tmp_path / "drive.csv"
    pd.DataFrame({"t": np.arange(4.0), "x": drive[:, 0], "y": drive[:, 1]}).to_csv(
        traj, index=False, float_format="%.3f"
    )
    ctx, _ = compute(
        load_preset("adaptive"), MapFile(pcd, traj, "32610"), tmp_path / "out", use_cache=False
    )
    assert ctx.mapping.map.crs == "EPSG:32610"
    assert np.all(np.abs(ctx.mapping.map.xyz[:, :2]) < 10_000)  # local, not raw UTM
    assert np.abs(ctx.mapping.trajectory["x"]).max() < 10_000
    trees = ctx.table
    assert len(trees) == len(orchard.centres)
    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32610", always_xy=True)
    e, n = to_utm.transform(trees["lon"].to_numpy(), trees["lat"].to_numpy())
    true_xy = orchard.centres + orchard.cloud.origin[:2]
    d = np.linalg.norm(np.column_stack([e, n])[:, None] - true_xy[None], axis=2)
    assert len(set(d.argmin(axis=1))) == len(true_xy) and d.min(axis=1).max() < 0.3
    # Without --crs the same file still runs, and the warning says what to give.
    from canopy_kit.mapping.map_source import load_finished_map

    bare = load_finished_map(MapFile(pcd))
    assert bare.frame is None and any("give --crs EPSG" in w for w in bare.warnings)
