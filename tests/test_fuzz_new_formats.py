"""Fuzzed inputs of the data-set formats of issue 47: damaged GNSS track files and Livox
CustomMsgs give the project's own errors (never a crash), quickly and in bounded memory."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from canopy_kit.errors import CanopyKitError
from canopy_kit.io.gnss_track import read_gnss_track
from canopy_kit.io.livox import POINT_RECORD, parse_custom_msg, serialize_custom_msg
from canopy_kit.sim.pcap_drive import gpgga, gprmc


def _damaged(data: bytes, rng: np.random.Generator) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 30))):
        b[int(rng.integers(len(b)))] = int(rng.integers(256))
    return bytes(b[: int(rng.integers(1, len(b) + 1))] if rng.random() < 0.3 else b)


@pytest.mark.parametrize("suffix", [".txt", ".csv", ".nmea", ".gpx"])
def test_damaged_gnss_tracks_give_input_errors(tmp_path, suffix):
    rng = np.random.default_rng(len(suffix))
    t0 = 1533110593.0
    mtls = "".join(
        f"80{3 + k // 300:02d}{(k // 5) % 60:02d}.{(k % 5) * 20:02d}\t0\t{288334 + k * 0.1:.3f}\t"
        f"{4615913 + k * 0.05:.3f}\t283.9\t0\n"
        for k in range(200)
    )
    nmea = "\n".join(
        s
        for k in range(100)
        for s in (gprmc(t0 + k, 41.667, 0.458), gpgga(t0 + k, 41.667, 0.458, 283.9))
    )
    for _ in range(60):
        f = tmp_path / f"track{suffix}"
        f.write_bytes(_damaged((nmea if suffix == ".nmea" else mtls).encode(), rng))
        try:
            read_gnss_track(f, crs="EPSG:25831", reference_time=t0)
        except CanopyKitError:
            pass


def test_damaged_custom_msgs_give_message_errors_in_bounded_memory():
    raw = serialize_custom_msg(10**18, np.zeros(100, POINT_RECORD), "livox_frame", ros2=True)
    rng = np.random.default_rng(3)
    tracemalloc.start()
    try:
        for _ in range(1000):
            try:
                parse_custom_msg(_damaged(raw, rng), ros2=True)
            except (CanopyKitError, ValueError):  # ValueError: a byte order rosbags then reads
                pass
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10e6  # a point_num of 4e9 must not allocate 80 GB
