"""Conformance rules for reader plugins (``canopy_kit.readers``): the promises of
:mod:`canopy_kit.io.reader_contract`, each a named check.

The truths are independent of the reader: a file of other bytes is not its format and is
refused with an InputError naming it; a cloud written and read back keeps its points (to
the 1 mm a LAS file stores); a description is JSON. ``check_reader(MyReader, samples=[f])``
also reads sample files of the format (needed for readers that cannot write).
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.io.reader_contract import READER_KINDS, CloudReader, Reader, ScanReader
from canopy_kit.testing.estimators import Check, _run

ROUND_TRIP_TOL_M = 1e-3  # LAS keeps millimetres
OTHER_BYTES = b"this is not a point cloud, a bag or a capture\n" * 40 + bytes(range(256)) * 8


def _files(reader: Any) -> Iterator[Path]:
    """Files of other content, one per suffix the reader claims (and one without a suffix)."""
    with tempfile.TemporaryDirectory(prefix="reader-check-") as folder:
        for suffix in (*reader.suffixes, ""):
            path = Path(folder) / f"other{suffix}"
            path.write_bytes(OTHER_BYTES)
            yield path


def check_declares_identity(reader: Any) -> None:
    assert isinstance(reader.name, str) and reader.name, "name must be a non-empty string"
    assert reader.kind in READER_KINDS, f"kind {reader.kind!r} is not one of {READER_KINDS}"
    suffixes = reader.suffixes
    assert isinstance(suffixes, tuple) and suffixes, "suffixes must be a non-empty tuple"
    for s in suffixes:
        assert s.startswith(".") and s == s.lower(), f"suffix {s!r}: lower case with a dot"


def check_has_the_methods_of_its_kind(reader: Any) -> None:
    assert isinstance(reader, Reader), "needs sniff(path) and describe(path)"
    if reader.kind == "cloud":
        assert isinstance(reader, CloudReader), "a cloud reader needs read(path)"
    if reader.kind == "scans":
        assert isinstance(reader, ScanReader), "a scans reader needs scans(path)"


def check_sniff_refuses_other_content(reader: Any) -> None:
    for path in _files(reader):
        try:
            found = reader.sniff(path)
        except Exception as exc:  # any exception breaks the rule
            raise AssertionError(f"sniff raised {type(exc).__name__} on {path.name}") from None
        assert found is False or found == 0, f"sniff claims {path.name} of other bytes"


def _refuses(run: Any, path: Path, what: str) -> None:
    try:
        run(path)
    except InputError as exc:
        assert path.name in str(exc), f"{what}: the InputError does not name the file: {exc}"
        return
    except Exception as exc:  # any other exception breaks the rule
        raise AssertionError(
            f"{what} of other bytes raised {type(exc).__name__} ({exc}), not an InputError"
        ) from None
    raise AssertionError(f"{what} accepted a file of other bytes ({path.name})")


def check_other_content_is_an_input_error(reader: Any) -> None:
    path = next(_files(reader))  # the reader's own suffix, other bytes
    _refuses(reader.describe, path, "describe")
    if reader.kind == "cloud":
        _refuses(reader.read, path, "read")
    if reader.kind == "scans":
        _refuses(lambda p: list(reader.scans(p)), path, "scans")


def _json(facts: Any) -> None:
    from canopy_kit.core.atomic import to_json

    assert isinstance(facts, dict), f"describe returned {type(facts).__name__}, not a dict"
    json.loads(to_json(facts))


def check_write_read_round_trip(reader: Any) -> None:
    if reader.kind != "cloud" or not callable(getattr(reader, "write", None)):
        return  # readers that cannot write are checked on samples
    rng = np.random.default_rng(0)
    xyz = rng.uniform([-20, -20, 0], [20, 20, 6], (500, 3)).round(3)
    with tempfile.TemporaryDirectory(prefix="reader-check-") as folder:
        path = Path(folder) / f"cloud{reader.suffixes[0]}"
        reader.write(path, PointCloud(xyz))
        assert reader.sniff(path), f"sniff does not recognise its own {path.name}"
        back = reader.read(path)
        assert len(back) == len(xyz), f"wrote {len(xyz)} points, read {len(back)}"
        err = np.abs(back.xyz + back.origin - xyz).max()
        assert err <= ROUND_TRIP_TOL_M, f"points moved by {err:.4f} m on a round trip"
        _json(reader.describe(path))


def sample_check(path: Path) -> Any:
    """The rule for one sample file of the reader's format: sniffed, described, read."""

    def check(reader: Any) -> None:
        assert reader.sniff(path), f"sniff does not recognise the sample {path.name}"
        _json(reader.describe(path))
        if reader.kind == "cloud":
            cloud = reader.read(path)
            assert len(cloud) > 0 and np.isfinite(cloud.xyz).all(), f"{path.name}: no points"
        if reader.kind == "scans":
            first = next(iter(reader.scans(path)), None)
            assert first is not None and len(first) > 0, f"{path.name}: no scans"

    return check


READER_RULES = (
    ("declares_identity", check_declares_identity),
    ("has_the_methods_of_its_kind", check_has_the_methods_of_its_kind),
    ("sniff_refuses_other_content", check_sniff_refuses_other_content),
    ("other_content_is_an_input_error", check_other_content_is_an_input_error),
    ("write_read_round_trip", check_write_read_round_trip),
)


def reader_checks(samples: Iterable[str | Path] = ()) -> list[Check]:
    """Every rule of the reader contract, plus one per sample file of its format."""
    rules = [*READER_RULES, *((f"sample_{Path(p).name}", sample_check(Path(p))) for p in samples)]
    return [Check(name, func) for name, func in rules]


def check_reader(reader: Any, samples: Iterable[str | Path] = ()) -> None:
    """Run every reader rule on a class or instance; AssertionError naming each broken one."""
    _run(reader, reader_checks(samples))
