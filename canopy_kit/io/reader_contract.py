"""What a reader plugin (``canopy_kit.readers`` entry point) promises.

Every reader says what it reads (``name``, ``kind``, ``suffixes``), recognises its own files
(``sniff``) and describes one (``describe``: JSON-able facts). A ``cloud`` reader also
``read``s a file into a :class:`~canopy_kit.core.cloud.PointCloud` (and may ``write`` one); a
``scans`` reader yields a drive's scans; a ``bag`` reader is opened by the mapping stage.
A file it cannot read raises :class:`~canopy_kit.errors.InputError` naming the file.
``canopy_kit.testing.check_reader`` proves a reader keeps these promises.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from canopy_kit.core.cloud import PointCloud

READER_KINDS = ("cloud", "bag", "scans")


@runtime_checkable
class Reader(Protocol):
    """Every reader: its identity, a content test and a description."""

    name: str
    kind: str  # one of READER_KINDS
    suffixes: tuple[str, ...]  # lower case, with the dot: (".las", ".laz")

    def sniff(self, path: Path) -> bool:
        """True when ``path`` holds this reader's format (never raises for other content)."""
        ...

    def describe(self, path: Path) -> dict[str, Any]:
        """JSON-able facts about the file (counts, fields, bounds, CRS, times)."""
        ...


@runtime_checkable
class CloudReader(Reader, Protocol):
    """A reader of point-cloud files (``kind = "cloud"``)."""

    def read(self, path: Path) -> PointCloud:
        """The whole file as a PointCloud."""
        ...


@runtime_checkable
class ScanReader(Reader, Protocol):
    """A reader of a drive's raw scans (``kind = "scans"``)."""

    def scans(self, path: Path) -> Iterator[Any]:
        """The drive's scans (:class:`canopy_kit.io.bag.Scan`) in time order."""
        ...
