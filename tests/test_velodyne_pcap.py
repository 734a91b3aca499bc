"""VLP-16 pcap decoding checked against VeloView's export of the same capture's frame 0."""

from __future__ import annotations

import os
import struct
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from canopy_kit.errors import InputError
from canopy_kit.io.clouds import find_reader, read_cloud
from canopy_kit.io.info import describe_path
from canopy_kit.io.velodyne_pcap import scans

REPO = Path(__file__).resolve().parents[1]


def sample_dir() -> Path:
    configured = os.environ.get("CANOPY_KIT_SHARED_DATA")
    base = Path(configured) if configured else REPO.parent / "shared" / "data"
    path = base / "mtls_vlp16_apple"
    if not path.is_dir():
        if configured:
            pytest.fail(f"{path} missing under CANOPY_KIT_SHARED_DATA={configured}")
        pytest.skip(f"public test data not found at {path} (set CANOPY_KIT_SHARED_DATA)")
    return path


@pytest.fixture(scope="module")
def pcap() -> Path:
    return sample_dir() / "velodyne_data_20frames_sample.pcap"


@pytest.fixture(scope="module")
def veloview_frame0() -> np.ndarray:
    """Columns: 3-5 X/Y/Z m, 6 intensity, 7 laser_id, 8 azimuth 0.01°, 9 distance m, 11 µs past hour."""
    return np.genfromtxt(
        sample_dir() / "velodyne_data_20frames_sample_frame_0000.csv", delimiter=",", skip_header=1
    )


@pytest.fixture(scope="module")
def all_scans(pcap: Path) -> list:
    return list(scans(pcap))


def test_first_full_rotation_matches_veloview_frame0(
    all_scans: list, veloview_frame0: np.ndarray
) -> None:
    csv = veloview_frame0
    assert len(csv) == 20_197
    # The capture starts at 315°: scan 0 is the partial turn VeloView leaves out.
    assert all_scans[0].fields["azimuth_deg"].min() > 300
    scan = all_scans[1]
    assert len(scan) == len(csv)
    # same points, in the same order: (µs timestamp, laser id) of every return
    np.testing.assert_array_equal(np.round(scan.fields["timestamp_us"]), csv[:, 11])
    np.testing.assert_array_equal(scan.fields["ring"], csv[:, 7])
    np.testing.assert_array_equal(scan.fields["intensity"], csv[:, 6])
    np.testing.assert_allclose(scan.fields["distance_m"], csv[:, 9], atol=1e-9)
    error = np.linalg.norm(scan.xyz - csv[:, 3:6], axis=1)
    assert np.median(error) < 0.001  # measured 0.09 mm
    assert np.percentile(error, 99) < 0.002  # measured 0.70 mm
    assert error.max() < 0.01  # measured 5.3 mm (VeloView's azimuth rounding at long range)
    assert np.abs(scan.fields["azimuth_deg"] * 100 - csv[:, 8]).max() < 3.0  # 0.03°


def test_point_times_are_absolute_utc(all_scans: list) -> None:
    scan = all_scans[1]
    first = datetime.fromtimestamp(scan.times[0], UTC)
    # 190,271,170 µs past 08:00 on the capture day (2018-08-01)
    assert first.strftime("%Y-%m-%d %H:%M") == "2018-08-01 08:03"
    assert scan.times[0] == pytest.approx(
        datetime(2018, 8, 1, 8, tzinfo=UTC).timestamp() + 190.271170, abs=1e-6
    )
    assert scan.stamp == scan.times[0]
    assert np.all(np.diff(scan.times) >= 0)
    assert 0.095 < scan.times[-1] - scan.times[0] < 0.1  # one turn at 600 rpm


def test_rotations(all_scans: list) -> None:
    # 1,516 packets at about 75.4 per turn: a partial turn, 19 full turns, the capture's
    # last turn cut at 326°, and one point past the final wrap.
    assert len(all_scans) == 22
    full = all_scans[1:20]
    for scan in full:
        az = scan.fields["azimuth_deg"]
        # the whole circle, but for the sector around 355°-0° where nothing returns
        assert az.min() < 15 and az.max() > 350
        assert 0.09 < scan.times[-1] - scan.times[0] < 0.1  # one turn at 600 rpm
        assert 20_000 < len(scan) < 20_400
        assert scan.xyz.dtype == np.float64 and scan.frame_id == "velodyne"
    assert all_scans[20].fields["azimuth_deg"].max() < 330 and len(all_scans[21]) == 1
    assert [s.index for s in all_scans] == list(range(len(all_scans)))
    ranges = np.linalg.norm(all_scans[1].xyz, axis=1)
    np.testing.assert_allclose(ranges, all_scans[1].fields["distance_m"], rtol=1e-12)


def test_plugin_and_describe(pcap: Path) -> None:
    reader = find_reader(pcap)
    assert (reader.name, reader.kind) == ("velodyne_pcap", "scans")
    facts = describe_path(pcap)
    # README: 1,516 data packets and 291 position packets over 2.01 s
    assert facts["data_packets"] == 1_516 and facts["position_packets"] == 291
    assert facts["duration_s"] == pytest.approx(2.01, abs=0.01)
    assert facts["return_mode"] == "strongest"
    with pytest.raises(InputError, match="is a scans file"):
        read_cloud(pcap)


def test_truncated_pcap(pcap: Path, tmp_path: Path) -> None:
    data = pcap.read_bytes()
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(data[: len(data) // 3 + 7])
    with pytest.raises(InputError) as err:
        list(scans(cut))
    assert str(cut) in str(err.value) and "truncated" in str(err.value)


def test_pcap_without_lidar_packets(tmp_path: Path) -> None:
    path = tmp_path / "empty_capture.pcap"
    path.write_bytes(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1))
    with pytest.raises(InputError, match="no VLP-16 data packets"):
        list(scans(path))


def test_not_a_pcap(tmp_path: Path) -> None:
    path = tmp_path / "fake.pcap"
    path.write_bytes(b"\x00" * 100)
    with pytest.raises(InputError, match="not a classic pcap file"):
        list(scans(path))
