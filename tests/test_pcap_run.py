"""Issue 47: ``canopy-kit run DRIVE.pcap --gnss TRACK``: a simulated VLP-16 capture with its
GNSS track mapped end to end against the simulator's truth, the real MTLS sample through
run's reader path, and the track readers against hand-computed and pyproj values."""

from __future__ import annotations

import json
import struct
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_cli_mistakes import cli, one_error_line
from test_velodyne_pcap import sample_dir

from canopy_kit.errors import InputError
from canopy_kit.io.gnss_track import (
    hhmmss_seconds,
    leap_seconds,
    read_gnss_track,
    times_of_day_to_utc,
)

CAPTURE_DAY = datetime(2018, 8, 1, 8, 3, 10, tzinfo=UTC).timestamp()


# -- a simulated pcap drive -------------------------------------------------------------------
@pytest.fixture(scope="module")
def sim_drive(tmp_path_factory) -> dict[str, Path]:
    """One row of three pistachio trees, a VLP-16 (raw packets) and an RTK receiver at 5 Hz,
    no IMU; written as drive.pcap + track files (MTLS text, CSV, NMEA, GPX)."""
    from canopy_kit.sim import load_sim_config, simulate_session
    from canopy_kit.sim.pcap_drive import export_pcap_drive

    cfg = load_sim_config(
        "pistachio",
        {
            "seed": 23,
            "orchard": {"rows": 1, "trees_per_row": 3},
            "lidar": {"output": "velodyne_packets", "frame_id": "velodyne"},
            "imu": {"enabled": False},
            "gnss": {"mode": "rtk", "rate_hz": 5.0, "frame_id": "velodyne"},
            "drive": {"cruise_speed": 2.0},
        },
        sensor="vlp16",
    )
    root = tmp_path_factory.mktemp("pcap_sim")
    session = simulate_session(root / "session", cfg)
    files = export_pcap_drive(session.bag, root / "capture", ("mtls", "csv", "nmea", "gpx"))
    return {"truth": session.root, **files}


def _metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


def test_pcap_drive_with_mtls_track_maps_against_truth(sim_drive, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    code, stdout, err = cli(
        monkeypatch,
        capsys,
        "run",
        sim_drive["pcap"],
        "--gnss",
        sim_drive["mtls"],
        "--truth",
        sim_drive["truth"],
        "--out",
        out,
    )
    assert code in (0, None), err
    m = _metrics(out)
    ev = m["evaluation"]
    assert ev["mapping"]["ate_rmse_m"] <= 0.10  # measured 0.02 m
    seg = ev["segmentation"]
    assert seg["n_truth"] == 3 and seg["success_rate"] == 1.0 and seg["label_accuracy"] == 1.0
    assert m["flagged_segments"] == 0
    # the recommended estimator's stated interval holds its measurand for every tree
    held = ev["volumes"]["recommended_interval"]
    assert held["n"] == 3 and held["held"] == 3
    for method in ("convex_hull", "alpha_shape"):
        assert ev["volumes"][method]["mape_pct"] < 10.0  # as tests/test_pipeline.py
    # georeferenced by the track: tree positions in WGS84 agree with the truth's
    trees = pd.read_csv(out / "trees.csv")
    truth = pd.read_csv(Path(sim_drive["truth"]) / "truth" / "trees.csv")
    both = trees.dropna(subset=["truth_tree_id"]).merge(
        truth, left_on="truth_tree_id", right_on="tree_id", suffixes=("", "_true")
    )
    assert len(both) == 3
    assert np.allclose(both["lat"], both["lat_true"], atol=2e-5)
    assert np.allclose(both["lon"], both["lon_true"], atol=2e-5)
    prov = m["provenance"]
    assert prov["bag"] == "drive.pcap" and prov["orchard"] == "drive"
    assert prov["pcap_import"]["gnss_track"] == "track.txt"
    assert prov["pcap_import"]["clock"] == "gprmc"
    assert len(prov["pcap_import"]["gnss_track_sha256"]) == 64
    assert not any("not georeferenced" in w for w in m["warnings"])
    assert all(".cache" not in w for w in m["warnings"])  # warnings name the capture


@pytest.mark.slow
def test_pcap_drive_without_track_maps_in_a_local_frame(sim_drive, tmp_path, monkeypatch, capsys):
    """No track: a map in the local frame with the not-georeferenced warning. (--truth needs a
    CRS or a per-point truth field, which raw packets lack: judged here by frame-free numbers.)"""
    out = tmp_path / "run"
    code, _, err = cli(monkeypatch, capsys, "run", sim_drive["pcap"], "--out", out)
    assert code in (0, None), err
    m = _metrics(out)
    assert any("not georeferenced" in w for w in m["warnings"]), m["warnings"]
    assert m["provenance"]["pcap_import"]["gnss_track"] == ""
    trees = pd.read_csv(out / "trees.csv").sort_values("label")
    truth = pd.read_csv(Path(sim_drive["truth"]) / "truth" / "trees.csv").sort_values("label")
    assert list(trees["label"]) == list(truth["label"]) == ["L0", "L1", "L2"]
    # tree spacing along the row (independent of the frame) and volumes against the envelope
    spacing = np.linalg.norm(np.diff(trees[["x", "y"]].to_numpy(), axis=0), axis=1)
    true_spacing = np.linalg.norm(np.diff(truth[["x", "y"]].to_numpy(), axis=0), axis=1)
    np.testing.assert_allclose(spacing, true_spacing, atol=0.3)
    error = trees["volume_convex_hull_m3"].to_numpy() / truth["crown_volume_m3"].to_numpy() - 1
    assert np.abs(error).mean() < 0.10


def test_track_formats_of_one_drive_agree(sim_drive):
    """MTLS text (UTM by pyproj), CSV, NMEA and GPX of the same fixes read alike."""
    from canopy_kit.io.pcap_drive import read_pcap_drive

    ref = read_pcap_drive(sim_drive["pcap"]).packet_times[0]
    tracks = {k: read_gnss_track(sim_drive[k], None, ref) for k in ("csv", "gpx", "nmea")}
    from canopy_kit.core.geo import utm_epsg

    f = tracks["csv"].fixes
    tracks["mtls"] = read_gnss_track(
        sim_drive["mtls"], utm_epsg(f.latitude[0], f.longitude[0]), ref
    )
    for name, track in tracks.items():
        g = track.fixes
        assert len(g.t) == len(f.t), name
        assert np.abs(g.t - f.t).max() < 0.011, name  # NMEA keeps centiseconds
        tol = 2e-6 if name == "nmea" else 1e-8  # NMEA: 0.0001 minute
        assert np.abs(g.latitude - f.latitude).max() < tol, name
        assert np.abs(g.longitude - f.longitude).max() < tol, name
        assert np.abs(g.altitude - f.altitude).max() < 2e-3, name


def test_a_track_on_gps_time_reads_back_with_gnss_time_gps(sim_drive, tmp_path):
    """The simulator writes the MTLS text on GPS time (UTC + 18 s in 2023); read as gps it
    gives the UTC times of the CSV track, read as utc 18 s late."""
    from canopy_kit.io.bag import open_bag
    from canopy_kit.io.pcap_drive import import_pcap_drive, read_pcap_drive
    from canopy_kit.sim.pcap_drive import write_track

    ref = read_pcap_drive(sim_drive["pcap"]).packet_times[0]
    utc = read_gnss_track(sim_drive["csv"], None, ref).fixes
    gps_file = write_track(tmp_path / "gps.txt", utc, "mtls", time_scale="gps")
    got = read_gnss_track(gps_file, "EPSG:32610", ref, time_scale="gps").fixes
    np.testing.assert_allclose(got.t, utc.t, atol=1e-6)
    late = read_gnss_track(gps_file, "EPSG:32610", ref).fixes
    np.testing.assert_allclose(late.t - utc.t, 18.0, atol=1e-6)
    # the imported bag's fixes are the track's, on the capture's clock
    bag, info = import_pcap_drive(sim_drive["pcap"], tmp_path, gps_file, 32610, "gps")
    assert info["gnss_time_scale"] == "gps" and info["gnss_crs"] == "EPSG:32610"
    with open_bag(bag) as session:
        fixes = session.gnss()
    inside = (utc.t >= ref - 1.0) & (utc.t <= fixes.t[-1])
    np.testing.assert_allclose(fixes.t, utc.t[inside], atol=1e-6)
    np.testing.assert_allclose(fixes.latitude, utc.latitude[inside], atol=1e-8)


def test_bad_tracks_exit_2_naming_the_file(sim_drive, tmp_path, monkeypatch, capsys):
    lines = Path(sim_drive["mtls"]).read_text().splitlines()
    gap = tmp_path / "gap.txt"
    gap.write_text("\n".join(lines[:50] + lines[80:]) + "\n")  # 6 s missing at 5 Hz
    code, _, err = cli(
        monkeypatch, capsys, "run", sim_drive["pcap"], "--gnss", gap, "--out", tmp_path / "a"
    )
    line = one_error_line(err)
    assert code == 2 and f"{gap}, line 51" in line and "gap of 6.2 s" in line
    assert not (tmp_path / "a").exists()
    # the right numbers in the wrong UTM zone: 800 km off the capture's $GPRMC position
    code, _, err = cli(
        monkeypatch,
        capsys,
        "run",
        sim_drive["pcap"],
        "--gnss",
        sim_drive["mtls"],
        "--gnss-crs",
        "32617",
        "--out",
        tmp_path / "b",
    )
    line = one_error_line(err)
    assert code == 2 and str(sim_drive["mtls"]) in line and "CRS (EPSG:32617) right?" in line
    assert not (tmp_path / "b").exists()
    # a track of another day does not cover the capture
    shifted = tmp_path / "day.csv"
    csv = pd.read_csv(sim_drive["csv"])
    csv["time"] += 86400.0
    csv.to_csv(shifted, index=False)
    code, _, err = cli(
        monkeypatch, capsys, "run", sim_drive["pcap"], "--gnss", shifted, "--out", tmp_path / "c"
    )
    assert code == 2 and "does not cover the capture drive.pcap" in one_error_line(err)
    # a bag carries its own GNSS; a streamed run takes bags only
    bag = Path(sim_drive["truth"]) / "session"
    code, _, err = cli(
        monkeypatch, capsys, "run", bag, "--gnss", sim_drive["mtls"], "--out", tmp_path / "d"
    )
    assert code == 2 and "only a pcap capture takes a GNSS track file" in one_error_line(err)
    code, _, err = cli(
        monkeypatch, capsys, "run", sim_drive["pcap"], "--stream", "--out", tmp_path / "e"
    )
    assert code == 2 and "--stream takes a bag" in one_error_line(err)
    assert not any((tmp_path / name).exists() for name in "cde")


# -- the real MTLS sample ---------------------------------------------------------------------
def test_real_sample_is_refused_as_too_short(tmp_path, monkeypatch, capsys):
    data = sample_dir()
    pcap = data / "velodyne_data_20frames_sample.pcap"
    track = data / "GNSS_Track_data_sample.txt"
    out = tmp_path / "run"
    code, _, err = cli(
        monkeypatch, capsys, "run", pcap, "--gnss", track, "--gnss-crs", "25831", "--out", out
    )
    line = one_error_line(err)
    assert code == 2
    assert "the capture is 2.01 s long" in line and "at least 10 s" in line
    assert "the GNSS track spans 0.01 m" in line  # standing still (read as UTC)
    assert not out.exists()
    # read as GPS time the track is 18 s earlier, where the platform already drives
    code, _, err = cli(
        monkeypatch,
        capsys,
        "run",
        pcap,
        "--gnss",
        track,
        "--gnss-crs",
        "25831",
        "--gnss-time",
        "gps",
        "--out",
        out,
    )
    assert code == 2 and "the GNSS track spans 0.47 m" in one_error_line(err)
    code, _, err = cli(monkeypatch, capsys, "run", pcap, "--out", out)
    assert code == 2 and "2.01 s long (21 rotations); mapping needs" in one_error_line(err)


def test_real_sample_through_run_reader_matches_veloview_frame0(tmp_path):
    """The bag run imports a pcap into decodes frame 0 as VeloView does (REP 103 frame)."""
    from canopy_kit.io.bag import LIDAR_TYPES, open_bag
    from canopy_kit.io.pcap_drive import SCAN_TOPIC, read_pcap_drive, write_drive_bag
    from canopy_kit.io.velodyne import VLP16

    data = sample_dir()
    drive = read_pcap_drive(data / "velodyne_data_20frames_sample.pcap")
    assert drive.clock == "gprmc" and len(drive.rmc) == 291
    assert drive.rmc[0, 1] == pytest.approx(41 + 40.0133 / 60) and drive.rmc[0, 2] == pytest.approx(
        27.4508 / 60
    )
    bag = write_drive_bag(tmp_path / "drive.bag", drive, None)
    with open_bag(bag) as session:  # as the mapping reads it (mapping.sensors)
        topic = session.find_topic(LIDAR_TYPES)
        assert topic == SCAN_TOPIC
        scans = [
            session.decode_scan(topic, msg, i)
            for i, (_, msg) in enumerate(session._messages(topic))
        ]
    csv = np.genfromtxt(
        data / "velodyne_data_20frames_sample_frame_0000.csv", delimiter=",", skip_header=1
    )
    # The bag splits rotations between packets (as the ROS driver does), VeloView between
    # points: find each of VeloView's points by its time and laser in the bag's scans.
    xyz = np.concatenate([sc.xyz for sc in scans])
    times = np.concatenate([sc.times for sc in scans])
    ring = np.concatenate([sc.fields["ring"] for sc in scans]).astype(int)
    hour = datetime(2018, 8, 1, 8, tzinfo=UTC).timestamp()
    keys = np.round((times - hour) * 1e6).astype(np.int64) * 16 + ring
    csv_keys = csv[:, 11].astype(np.int64) * 16 + VLP16.ring_of_laser[csv[:, 7].astype(int)]
    order = np.argsort(keys)
    # epoch seconds in float64 keep about 0.2 µs: a time may round to the next microsecond
    found = np.full(len(csv), -1)
    for step in (0, -16, 16):
        at = np.clip(np.searchsorted(keys, csv_keys + step, sorter=order), 0, len(keys) - 1)
        hit = (keys[order[at]] == csv_keys + step) & (found < 0)
        found[hit] = order[at][hit]
    assert len(csv) == 20_197 and (found >= 0).all()  # every VeloView point is in the bag
    assert len(np.unique(found)) == len(found)
    veloview = csv[:, 3:6]
    rep103 = np.column_stack([veloview[:, 1], -veloview[:, 0], veloview[:, 2]])
    error = np.linalg.norm(xyz[found] - rep103, axis=1)
    assert np.median(error) < 0.001 and error.max() < 0.01
    # the scans' times are the sensor's counter on the UTC hour of the $GPRMC
    np.testing.assert_allclose(times[found] - hour, csv[:, 11] * 1e-6, atol=1e-6)


# -- track readers against hand-computed values ----------------------------------------------
def test_mtls_columns_round_trip_through_pyproj(tmp_path):
    from pyproj import Transformer

    lat, lon = np.array([41.667, 41.6671]), np.array([0.4575, 0.4576])
    east, north = Transformer.from_crs("EPSG:4326", "EPSG:25831", always_xy=True).transform(
        lon, lat
    )
    track = tmp_path / "t.txt"
    track.write_text(
        f"80150.95\t1\t{east[0]:.4f}\t{north[0]:.4f}\t283.9\t1\r\n"
        f"80151.15\t1\t{east[1]:.4f}\t{north[1]:.4f}\t284.0\t1\r\n"
    )
    got = read_gnss_track(track, 25831, CAPTURE_DAY)
    np.testing.assert_allclose(got.fixes.latitude, lat, atol=1e-8)
    np.testing.assert_allclose(got.fixes.longitude, lon, atol=1e-8)
    np.testing.assert_allclose(got.fixes.altitude, [283.9, 284.0])
    day = datetime(2018, 8, 1, tzinfo=UTC).timestamp()
    np.testing.assert_allclose(got.fixes.t, day + 8 * 3600 + 110.95 + np.array([0, 0.2]))
    gps = read_gnss_track(track, 25831, CAPTURE_DAY, time_scale="gps")
    np.testing.assert_allclose(gps.fixes.t, got.fixes.t - 18.0)  # GPS - UTC = 18 s in 2018
    assert list(got.lines) == [1, 2] and got.crs == "EPSG:25831"
    with pytest.raises(InputError, match="need their CRS"):
        read_gnss_track(track, None, CAPTURE_DAY)
    with pytest.raises(InputError, match="without a date"):
        read_gnss_track(track, 25831, None)


def test_easting_beyond_the_zone_is_refused_naming_the_line(tmp_path):
    track = tmp_path / "t.txt"
    track.write_text(
        "80150.95 1 288334.5 4615913.8 283.9 1\n80151.15 1 900000.0 4615913.8 283.9 1\n"
    )
    with pytest.raises(InputError, match=rf"{track}, line 2: easting 900000.0.*outside"):
        read_gnss_track(track, 25831, CAPTURE_DAY)


def test_leap_seconds_and_times_of_day():
    assert leap_seconds(datetime(2016, 12, 31, 23, 59, 59, tzinfo=UTC).timestamp()) == 17
    assert leap_seconds(datetime(2017, 1, 1, tzinfo=UTC).timestamp()) == 18
    assert leap_seconds(datetime(2013, 6, 1, tzinfo=UTC).timestamp()) == 16
    assert hhmmss_seconds(80150.95) == pytest.approx(8 * 3600 + 60 + 50.95)
    # across midnight, the date taken from a reference a little after midnight
    ref = datetime(2020, 5, 2, 0, 0, 30, tzinfo=UTC).timestamp()
    tod = np.array([hhmmss_seconds(v) for v in (235959.8, 0.2)])
    t = times_of_day_to_utc(tod, ref, gps=False, where="x")
    assert t[0] == pytest.approx(datetime(2020, 5, 1, 23, 59, 59, 800000, tzinfo=UTC).timestamp())
    assert t[1] - t[0] == pytest.approx(0.4)
    # GPS time of day 00:00:10 is 23:59:52 UTC the day before (18 s)
    t = times_of_day_to_utc(np.array([10.0]), ref, gps=True, where="x")
    assert t[0] == pytest.approx(datetime(2020, 5, 1, 23, 59, 52, tzinfo=UTC).timestamp())


def test_nmea_sentences(tmp_path):
    track = tmp_path / "t.nmea"
    track.write_text(
        "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A\n"
        "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\n"
        "$GPGGA,123520,4807.048,N,01131.010,W,1,08,0.9,545.6,M,46.9,M,,\n"
        "$GNGGA,123520,4807.048,N,01131.010,W,1,08,0.9,545.6,M,46.9,M,,\n"  # same epoch
        "$GPGGA,123521,,,,,0,00,,,M,,M,,\n"  # no fix: skipped
    )
    got = read_gnss_track(track)
    f = got.fixes
    assert got.format == "nmea" and list(got.lines) == [2, 3]
    np.testing.assert_allclose(f.latitude, [48 + 7.038 / 60, 48 + 7.048 / 60])
    np.testing.assert_allclose(f.longitude, [11 + 31.0 / 60, -(11 + 31.01 / 60)])
    np.testing.assert_allclose(f.altitude, [545.4 + 46.9, 545.6 + 46.9])  # ellipsoidal
    day = datetime(1994, 3, 23, tzinfo=UTC).timestamp()  # the date from $GPRMC
    np.testing.assert_allclose(f.t, day + 12 * 3600 + 35 * 60 + np.array([19.0, 20.0]))
    bad = tmp_path / "bad.nmea"
    bad.write_text("$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*48\n")
    with pytest.raises(InputError, match=rf"{bad}, line 1: NMEA checksum"):
        read_gnss_track(bad)


def test_gpx_and_csv(tmp_path):
    gpx = tmp_path / "t.gpx"
    gpx.write_text(
        '<?xml version="1.0"?><gpx xmlns="http://www.topografix.com/GPX/1/1"><trk><trkseg>'
        '<trkpt lat="41.5" lon="0.5"><ele>280.5</ele><time>2018-08-01T08:00:00Z</time></trkpt>'
        '<trkpt lat="41.50001" lon="0.5"><ele>280.6</ele><time>2018-08-01T08:00:00.2Z</time>'
        "</trkpt></trkseg></trk></gpx>"
    )
    got = read_gnss_track(gpx)
    t0 = datetime(2018, 8, 1, 8, tzinfo=UTC).timestamp()
    np.testing.assert_allclose(got.fixes.t, [t0, t0 + 0.2])
    np.testing.assert_allclose(got.fixes.latitude, [41.5, 41.50001])
    np.testing.assert_allclose(got.fixes.altitude, [280.5, 280.6])
    csv = tmp_path / "t.csv"
    csv.write_text(
        "Time,Easting,Northing,Height\n80000.0,288334.5,4615913.8,283.9\n80000.2,288334.6,4615913.9,284\n"
    )
    got = read_gnss_track(csv, "EPSG:25831", CAPTURE_DAY)
    assert got.format == "csv" and list(got.lines) == [2, 3]
    assert got.fixes.t[0] == pytest.approx(t0)
    with pytest.raises(InputError, match=rf"{csv}, line 3: time does not increase"):
        csv.write_text("t,lat,lon\n1533110400,41.5,0.5\n1533110400,41.5,0.5\n")
        read_gnss_track(csv)


def test_a_stationary_capture_without_track_is_refused(tmp_path, monkeypatch, capsys):
    """The real sample's 20 turns played six times over (12 s, one place): no track to tell,
    but its rotations coincide."""
    from canopy_kit.io.pcap_drive import read_pcap_drive
    from canopy_kit.sim.pcap_drive import write_pcap

    drive = read_pcap_drive(sample_dir() / "velodyne_data_20frames_sample.pcap")
    period = drive.duration + 0.0013
    packets = []
    for k in range(6):
        for t, p in zip(drive.packet_times, drive.payloads(), strict=True):
            counter = (
                struct.unpack("<I", p[1200:1204])[0] + round(k * period * 1e6)
            ) % 3_600_000_000
            packets.append((t + k * period, p[:1200] + struct.pack("<I", counter) + p[1204:]))
    pcap = write_pcap(tmp_path / "still.pcap", packets, None)
    out = tmp_path / "run"
    code, _, err = cli(monkeypatch, capsys, "run", pcap, "--out", out)
    line = one_error_line(err)
    assert code == 2 and "the capture is 12.07 s long" in line and "the sensor stood still" in line
    assert not out.exists()
