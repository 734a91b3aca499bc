"""The reader contract (canopy_kit.io.reader_contract) checked by the shipped suite:
every registered reader passes ``canopy_kit.testing.check_reader`` (on sample files of its
format where it cannot write one), a third-party reader proves itself in one call, and a
reader that breaks a rule is named with the rule."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SHARED_DATA

from canopy_kit import plugins
from canopy_kit.core.atomic import atomic_path
from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.io.bag_writer import BAG_FORMATS, BagWriter
from canopy_kit.testing import check_reader, checks_for, parametrize_with_checks, reader_checks

REAL_PCAP = SHARED_DATA / "mtls_vlp16_apple" / "velodyne_data_20frames_sample.pcap"


# -- a third-party reader: whitespace "x y z" text files ------------------------------------
class XyzReader:
    """Reads and writes ``.xyz`` text files, one ``x y z`` point per line."""

    name = "xyz"
    kind = "cloud"
    suffixes = (".xyz",)

    def sniff(self, path: Path) -> bool:
        try:
            first = Path(path).read_bytes()[:200].split(b"\n")[0].split()
            return len(first) == 3 and all(_is_number(v) for v in first)
        except OSError:
            return False

    def describe(self, path: Path) -> dict[str, Any]:
        cloud = self.read(path)
        return {"path": str(path), "points": len(cloud), "lower": cloud.xyz.min(axis=0)}

    def read(self, path: Path) -> PointCloud:
        if not self.sniff(path):
            raise InputError(f"{path}: not an x y z text file")
        return PointCloud(np.loadtxt(path, ndmin=2))

    def write(self, path: Path, cloud: PointCloud) -> Path:
        with atomic_path(Path(path)) as tmp:
            np.savetxt(tmp, cloud.xyz + cloud.origin, fmt="%.4f")
        return Path(path)


def _is_number(text: bytes) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


class CarelessReader(XyzReader):
    """Claims every file with its suffix and lets numpy's errors through."""

    name = "careless"
    suffixes = (".XYZ",)

    def sniff(self, path: Path) -> bool:
        return True

    def read(self, path: Path) -> PointCloud:
        return PointCloud(np.loadtxt(path, ndmin=2))


def test_third_party_reader_passes_in_one_call():
    check_reader(XyzReader)


@parametrize_with_checks([XyzReader()])
def test_third_party_reader_rule_by_rule(estimator, check):
    check(estimator)


def test_broken_reader_is_named_with_each_rule_it_breaks():
    with pytest.raises(AssertionError) as err:
        check_reader(CarelessReader)
    text = str(err.value)
    for rule in (
        "declares_identity",
        "sniff_refuses_other_content",
        "other_content_is_an_input_error",
    ):
        assert f"rule {rule!r} broken" in text
    assert "write_read_round_trip" not in text  # that rule it keeps
    assert [c.name for c in checks_for(CarelessReader)] == [c.name for c in reader_checks()]


def _bag_sample(folder: Path) -> Path:
    with BagWriter(folder / "tiny", "ros1") as writer:
        xyz = np.random.default_rng(0).uniform(-5, 5, (100, 3)).astype(np.float32)
        writer.write_points("/points", 1.0, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    return writer.path


def _samples(name: str, folder: Path) -> list[Path]:
    if name == "rosbag":
        return [_bag_sample(folder)]
    if name == "velodyne_pcap":
        if not REAL_PCAP.exists():
            pytest.skip(f"{REAL_PCAP} not here (../shared/data)")
        return [REAL_PCAP]
    return []  # cloud readers write their own


@pytest.mark.parametrize("name", plugins.names("readers"))
def test_every_registered_reader_keeps_the_contract(name, tmp_path):
    check_reader(plugins.create("readers", name), samples=_samples(name, tmp_path))


def test_rosbag_sniff_is_the_content_not_the_suffix(tmp_path):
    """A .bag of other bytes is not a bag (find_reader still routes it by suffix to the bag
    reader, whose recovery and errors name it)."""
    reader = plugins.create("readers", "rosbag")
    fake = tmp_path / "notes.bag"
    fake.write_text("field notes, not a bag\n")
    assert reader.sniff(fake) is False
    assert reader.sniff(_bag_sample(tmp_path)) is True
    assert "ros1" in BAG_FORMATS
