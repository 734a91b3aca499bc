"""Plugin registries: every registered reader honours the contract; entry points are
found; a broken entry point gives a clear PluginError. Nothing is installed."""

from __future__ import annotations

from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest

from canopy_kit import plugins
from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import PluginError

READER_KINDS = {"cloud", "bag", "scans"}


@pytest.mark.parametrize("name", plugins.names("readers"))
def test_every_reader_loads_and_honours_the_contract(name: str) -> None:
    target = plugins.load("readers", name)
    reader = target() if isinstance(target, type) else target
    assert reader.name == name
    assert reader.kind in READER_KINDS
    assert reader.suffixes and all(s.startswith(".") and s == s.lower() for s in reader.suffixes)
    assert callable(reader.sniff) and callable(reader.describe)
    if reader.kind == "cloud":
        assert callable(reader.read)
    if reader.kind == "scans":
        assert callable(reader.scans)


def test_built_in_plugins_are_registered() -> None:
    assert {"las", "ply", "pcd", "rosbag"} <= set(plugins.names("readers"))
    assert {"info", "plugins"} <= set(plugins.names("commands"))
    from canopy_kit.io.las import LasReader

    assert plugins.load("readers", "las") is LasReader
    # the full group name works as well as the short kind
    assert plugins.names("canopy_kit.readers") == plugins.names("readers")


def test_cloud_readers_sniff_only_their_own_format(tmp_path: Path) -> None:
    from canopy_kit.io.clouds import reader_objects, write_cloud

    cloud = PointCloud(np.arange(12.0).reshape(4, 3), {"intensity": np.arange(4, dtype=np.uint16)})
    files = {s: write_cloud(tmp_path / f"c{s}", cloud) for s in (".laz", ".ply", ".pcd")}
    for reader in reader_objects():
        for suffix, path in files.items():
            assert reader.sniff(path) == (suffix in reader.suffixes), (reader.name, suffix)


def _fake_entry_points(*extra: EntryPoint):
    real = plugins.entry_points

    def entry_points(group: str):
        return list(real(group=group)) + [ep for ep in extra if ep.group == group]

    return entry_points


def test_registered_entry_point_is_found(monkeypatch: pytest.MonkeyPatch) -> None:
    ep = EntryPoint(
        name="toy", value="canopy_kit.core.cloud:PointCloud", group="canopy_kit.segmenters"
    )
    monkeypatch.setattr(plugins, "entry_points", _fake_entry_points(ep))
    assert "toy" in plugins.names("segmenters")
    assert plugins.load("segmenters", "toy") is PointCloud
    (row,) = [r for r in plugins.describe("segmenters") if r.name == "toy"]
    assert row.error is None and row.value == "canopy_kit.core.cloud:PointCloud"


def test_entry_points_are_read_once_per_search_path(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A run asks for a kind's entry points many times: the installed distributions are
    scanned once; a new entry on sys.path (a package installed since) is scanned again."""
    calls = []
    real = plugins.entry_points

    def counting(group: str):
        calls.append(group)
        return real(group=group)

    monkeypatch.setattr(plugins, "entry_points", counting)
    first = plugins.names("volumes")
    for _ in range(5):
        assert plugins.names("volumes") == first
    assert calls == ["canopy_kit.volumes"]
    monkeypatch.syspath_prepend(str(tmp_path))
    assert plugins.names("volumes") == first
    assert calls == ["canopy_kit.volumes"] * 2


def test_broken_entry_point_gives_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    ep = EntryPoint(name="ghost", value="no_such_module:Thing", group="canopy_kit.segmenters")
    monkeypatch.setattr(plugins, "entry_points", _fake_entry_points(ep))
    with pytest.raises(PluginError) as err:
        plugins.load("segmenters", "ghost")
    message = str(err.value)
    assert "'ghost'" in message and "canopy_kit.segmenters" in message
    assert "no_such_module:Thing" in message and "ModuleNotFoundError" in message
    (row,) = [r for r in plugins.describe("segmenters") if r.name == "ghost"]
    assert row.error is not None and "no_such_module" in row.error


def test_entry_point_naming_a_missing_attribute(monkeypatch: pytest.MonkeyPatch) -> None:
    ep = EntryPoint(
        name="typo", value="canopy_kit.core.cloud:PointClod", group="canopy_kit.volumes"
    )
    monkeypatch.setattr(plugins, "entry_points", _fake_entry_points(ep))
    with pytest.raises(PluginError, match="AttributeError"):
        plugins.load("volumes", "typo")


def test_unknown_plugin_name_lists_the_registered_ones() -> None:
    with pytest.raises(PluginError) as err:
        plugins.load("readers", "e57")
    assert "no readers plugin named 'e57'" in str(err.value)
    assert "las" in str(err.value) and "rosbag" in str(err.value)


def test_unknown_plugin_kind() -> None:
    with pytest.raises(PluginError, match="unknown plugin kind 'exporters'"):
        plugins.names("exporters")


def test_broken_reader_plugin_does_not_stop_other_formats(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from canopy_kit.errors import InputError
    from canopy_kit.io.clouds import read_cloud, write_cloud

    ep = EntryPoint(name="broken", value="no_such_module:Reader", group="canopy_kit.readers")
    monkeypatch.setattr(plugins, "entry_points", _fake_entry_points(ep))
    assert "broken" in plugins.names("readers")
    cloud = PointCloud(np.eye(3))
    assert len(read_cloud(write_cloud(tmp_path / "ok.laz", cloud))) == 3
    unknown = tmp_path / "x.e57"
    unknown.write_bytes(b"ASTM-E57")
    with pytest.raises(InputError) as err:
        read_cloud(unknown)
    message = str(err.value)
    assert "unknown file format" in message
    assert (
        "failed to load" in message and "'broken'" in message and "ModuleNotFoundError" in message
    )
