"""The ``mcap`` library's reader behind an MCAP bag gives exactly rosbags' messages: the same
connections, log times and bytes in the same order, whole or from a time window; other bags
keep rosbags' reader."""

from __future__ import annotations

import zlib
from pathlib import Path

import pytest
from test_io_bags import write_full_bag

from canopy_kit.io.bag import open_bag
from canopy_kit.io.mcap_messages import FastMcapReader


def _stream(messages) -> list[tuple[str, str, int, int, int]]:
    return [(c.topic, c.msgtype, t, len(raw), zlib.crc32(raw)) for c, t, raw in messages]


def _rosbags_stream(path: Path, topics: set[str] | None, **window) -> list:
    from rosbags.highlevel import AnyReader

    target = path.parent if path.is_file() else path
    with AnyReader([target]) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        return _stream(reader.messages(connections=conns, **window))


def _check_against_rosbags(path: Path) -> int:
    """Compare whole, windowed and topic-filtered streams; the number of messages."""
    with open_bag(path) as bag:
        reader = bag.reader
        assert isinstance(reader, FastMcapReader)
        every = _stream(reader.messages(connections=reader.connections))
        assert every == _rosbags_stream(path, None)
        times = sorted({t for _, _, t, _, _ in every})
        window = {"start": times[len(times) // 3], "stop": times[2 * len(times) // 3]}
        lidar = {c.topic for c in reader.connections if c.msgtype.endswith("PointCloud2")}
        imu = {c.topic for c in reader.connections if c.msgtype.endswith("Imu")}
        wanted = lidar | imu
        conns = [c for c in reader.connections if c.topic in wanted]
        part = _stream(reader.messages(connections=conns, **window))
        assert part == _rosbags_stream(path, wanted, **window)
        assert 0 < len(part) < len(every)
        assert all(window["start"] <= t < window["stop"] for _, _, t, _, _ in part)
    return len(every)


def test_hand_written_bag_reads_as_rosbags_reads_it(tmp_path: Path) -> None:
    """Three LiDAR topics, IMU, GNSS and odometry, some sharing a time stamp."""
    assert _check_against_rosbags(write_full_bag(tmp_path / "session", "ros2-mcap")) > 10


def test_simulated_drive_reads_as_rosbags_reads_it(tiny_pistachio) -> None:
    """A simulated drive of many chunks, read across their borders."""
    assert _check_against_rosbags(Path(tiny_pistachio.bag)) > 1000


@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite3"])
def test_other_bags_keep_rosbags_reader(tmp_path: Path, fmt: str) -> None:
    with open_bag(write_full_bag(tmp_path / "session", fmt)) as bag:
        assert not isinstance(bag.reader, FastMcapReader)
        assert len(list(bag.scans())) == 3


def test_a_bag_of_two_mcap_files_keeps_rosbags_reader(tmp_path: Path) -> None:
    """A split recording (two storage files): rosbags merges them; not wrapped."""
    path = write_full_bag(tmp_path / "session", "ros2-mcap")
    storage = next(path.glob("*.mcap"))
    (path / "extra.mcap").write_bytes(storage.read_bytes())
    with open_bag(path) as bag:
        assert not isinstance(bag.reader, FastMcapReader)
