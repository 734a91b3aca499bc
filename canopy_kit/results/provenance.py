"""Where a run's numbers come from: orchard, session date, bag and its hash, software, preset.

A flat dict of str/number values with snake_case keys, the same in ``metrics.json``
(``provenance``), the Parquet and GeoPackage metadata and every GeoJSON FeatureCollection
(foreign member ``provenance``): orchard, session_date, bag, bag_sha256, drone_images,
software_version, preset, run_started_utc, run_seconds.
"""

from __future__ import annotations

import hashlib
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import suppress
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from canopy_kit.errors import InputError

CHUNK = 1 << 20


def bag_sha256(bag: str | Path, stop: threading.Event | None = None) -> str:
    """SHA-256 of a bag file, or of every file of a ROS2 bag folder in sorted relative-path
    order (each file's path and bytes), streamed in 1 MiB chunks; an InputError when
    ``stop`` is set before the end."""
    from canopy_kit.io.bag import require_bag

    bag = require_bag(bag)
    digest = hashlib.sha256()
    files = sorted(p for p in bag.rglob("*") if p.is_file()) if bag.is_dir() else [bag]
    for path in files:
        if bag.is_dir():
            digest.update(path.relative_to(bag).as_posix().encode() + b"\0")
        with path.open("rb") as f:
            while chunk := f.read(CHUNK):
                if stop is not None and stop.is_set():
                    raise InputError(f"{bag}: hashing stopped")
                digest.update(chunk)
    return digest.hexdigest()


class BagHash:
    """:func:`bag_sha256` of ``bag`` on a thread of the lowest priority, started at once or by
    :meth:`start`: it uses the core a run leaves idle (segmentation is serial) instead of
    hashing a bag of gigabytes after every stage. :meth:`result` waits for the hash (or
    raises what hashing raised); :meth:`cancel` stops it, e.g. when the run fails."""

    def __init__(self, bag: str | Path, start: bool = True) -> None:
        self.bag = Path(bag)
        self._stop = threading.Event()
        self._future: Future[str] | None = None
        if start:
            self.start()

    def start(self) -> None:
        """Start hashing (once; later calls do nothing)."""
        if self._future is None:
            pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="bag-sha256")
            self._future = pool.submit(self._hash, self.bag)
            pool.shutdown(wait=False)

    def _hash(self, bag: Path) -> str:
        with suppress(AttributeError, OSError):  # Linux: a thread id's nice value is its own
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        return bag_sha256(bag, self._stop)

    def result(self) -> str:
        """The bag's SHA-256 (hex); hashed now if it was never started."""
        self.start()
        assert self._future is not None
        return self._future.result()

    def cancel(self) -> None:
        """Stop hashing (within one chunk) and wait for the thread to end."""
        self._stop.set()
        if self._future is not None:
            with suppress(Exception):
                self._future.result()


def utc_iso(seconds: float) -> str:
    """A POSIX time as ISO 8601 UTC, ``2026-12-02T07:01:02.500000Z``."""
    return datetime.fromtimestamp(seconds, UTC).isoformat().replace("+00:00", "Z")


def session_date(bag: str | Path) -> str:
    """The time of the bag's first message, ISO 8601 UTC ("" for a map file: not known)."""
    from canopy_kit.io.bag import open_bag
    from canopy_kit.mapping.map_source import is_map_file

    if is_map_file(bag):
        return ""
    with open_bag(bag) as session:
        return utc_iso(session.start_time)


def provenance(
    bag: str | Path,
    preset: str,
    started: float,
    seconds: float,
    orchard: str | None = None,
    drone_images: str | Path | None = None,
    bag_hash: BagHash | None = None,
) -> dict[str, Any]:
    """The provenance dict of a run of ``bag`` (``orchard`` defaults to the bag's stem;
    ``started`` POSIX time, ``seconds`` how long the run took; ``bag_hash`` the hash
    :class:`BagHash` started, else the bag is hashed now)."""
    from canopy_kit import __version__

    bag = Path(bag)
    return {
        "orchard": orchard or bag.stem,
        "session_date": session_date(bag),
        "bag": bag.name,
        "bag_sha256": bag_hash.result() if bag_hash is not None else bag_sha256(bag),
        "drone_images": str(drone_images) if drone_images is not None else "",
        "software_version": __version__,
        "preset": preset,
        "run_started_utc": utc_iso(started),
        "run_seconds": round(float(seconds), 3),
    }
