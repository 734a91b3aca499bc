"""End to end on a small simulated flight through the CLI, checked against the simulator's truth,
and a smoke test of structure from motion on real drone photos."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from canopy_kit.sim import load_sim_config
from canopy_kit.sim.drone import simulate_drone_session
from ground_truth.evaluate import crown_agreement
from ground_truth.raster import read_geotiff

pytestmark = pytest.mark.slow


def _cli() -> list[str]:
    script = Path(sys.executable).with_name("canopy-kit")
    return [str(script)] if script.exists() else [sys.executable, "-c",
                                                  "from canopy_kit.cli import main; main()"]


@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    """A 2 x 3 pistachio flight (12 photos), processed by ``canopy-kit ground-truth``."""
    root = tmp_path_factory.mktemp("gt_flight")
    cfg = load_sim_config("pistachio", {"seed": 4, "orchard": {"rows": 2, "trees_per_row": 3},
                                        "drone": {"enabled": True}})
    simulate_drone_session(root / "sim", cfg)
    out = root / "out"
    result = subprocess.run([*_cli(), "ground-truth", str(root / "sim" / "drone"), "--out", str(out),
                             "--seeds", str(root / "sim" / "truth" / "trees.csv"),
                             "--frame", str(root / "sim" / "truth" / "frame.json")],
                            capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    return root / "sim", out, result.stdout


def test_all_photos_registered_and_georeferenced(processed):
    sim, out, stdout = processed
    report = json.loads((out / "report.json").read_text())
    assert report["sfm"]["registered_images"] == report["sfm"]["total_images"] == 12
    assert report["sfm"]["mean_reprojection_error_px"] < 1.0
    assert "registered 12/12 photos" in stdout
    truth = pd.read_csv(sim / "truth" / "drone_cameras.csv").set_index("image")
    cams = pd.read_csv(out / "cameras.csv").set_index("image")
    err = np.linalg.norm(cams[["x", "y", "z"]].to_numpy() - truth.loc[cams.index, ["x", "y", "z"]].to_numpy(),
                         axis=1)
    assert err.max() <= 0.10, f"camera georeferencing errors {np.round(err, 3)}"


def test_crowns_against_truth(processed):
    sim, out, _ = processed
    truth = pd.read_csv(sim / "truth" / "trees.csv")
    crowns = pd.read_csv(out / "crowns.csv")
    table, m = crown_agreement(crowns, truth)
    assert m["detection_rate"] == 1.0 and m["unmatched_crowns"] == 0
    assert m["diameter_mae_m"] <= 0.12, table
    assert m["height_mae_m"] <= 0.3, table
    # The paper-style sphere uses the widest extent.
    assert crowns["sphere_volume_m3"].to_numpy() == pytest.approx(np.pi * crowns["diameter_max_m"] ** 3 / 6,
                                                                  rel=1e-3)


def test_one_row_per_seed_tree(processed):
    sim, out, _ = processed
    trees = pd.read_csv(out / "trees.csv")
    assert len(trees) == 6 and trees["matched"].all()
    assert (trees["aerial_distance_m"] < 0.5).all()
    assert (trees["aerial_diameter_max_m"] - trees["crown_diameter_m"]).abs().max() < 0.3


def test_geotiffs_carry_the_crs(processed):
    sim, out, _ = processed
    frame = json.loads((sim / "truth" / "frame.json").read_text())["frame"]
    for name in ("orthomosaic.tif", "dsm.tif", "chm.tif", "crown_labels.tif"):
        data, geo = read_geotiff(out / name)
        assert geo["epsg"] == frame["epsg"]
        assert geo["tiepoint"][3] > 100_000  # UTM eastings, not local coordinates
    ortho, _ = read_geotiff(out / "orthomosaic.tif")
    assert ortho.shape[2] == 4 and ortho[..., 3].mean() > 200
    chm, _ = read_geotiff(out / "chm.tif")
    assert 3.0 < np.nanmax(chm) < 7.0
    for name in ("orthomosaic.png", "chm.png", "crowns.png", "ground_truth_config.json"):
        assert (out / name).stat().st_size > 0


def test_cli_reports_bad_input(tmp_path):
    (tmp_path / "empty").mkdir()
    result = subprocess.run([*_cli(), "ground-truth", str(tmp_path / "empty"), "--out", str(tmp_path / "o")],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "0 JPEG image(s), at least 3 are needed" in result.stderr


def test_real_drone_photos_register_and_georeference(shared_data, tmp_path):
    """15 consumer-camera photos (4000 x 3000, metre-level GPS), features on 1200 px images."""
    from ground_truth.exif import read_flight
    from ground_truth.sfm import SfmOptions, run_sfm

    folder = shared_data / "caliterra_drone"
    if not folder.is_dir():
        pytest.skip("caliterra_drone photos not present")
    flight = read_flight(folder)
    model = run_sfm(flight, tmp_path / "sfm", options=SfmOptions(max_image_size=1200, max_num_features=4096))
    report = model.report()
    assert report["registered_images"] >= 0.8 * len(flight.images), report
    assert report["mean_reprojection_error_px"] < 2.0
    # Georeferenced: cameras sit on their GPS positions within consumer-GPS accuracy.
    assert report["gps_residual_rms_horizontal_m"] < 5.0, report
    spread = np.ptp(flight.local_positions(model.frame)[:, :2], axis=0).max()
    assert spread > 20 * report["gps_residual_rms_horizontal_m"]
