"""Where a run's numbers come from: orchard, session date, bag and its hash, software, preset.

A flat dict of str/number values with snake_case keys, the same in ``metrics.json``
(``provenance``), the Parquet and GeoPackage metadata and every GeoJSON FeatureCollection
(foreign member ``provenance``): orchard, session_date, bag, bag_sha256, drone_images,
software_version, preset, run_started_utc, run_seconds.
"""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from canopy_kit.errors import InputError

CHUNK = 1 << 20


def bag_sha256(bag: str | Path) -> str:
    """SHA-256 of a bag file, or of every file of a ROS2 bag folder in sorted relative-path
    order (each file's path and bytes), streamed in 1 MiB chunks."""
    bag = Path(bag)
    if not bag.exists():
        raise InputError(f"{bag}: bag does not exist")
    digest = hashlib.sha256()
    files = sorted(p for p in bag.rglob("*") if p.is_file()) if bag.is_dir() else [bag]
    for path in files:
        if bag.is_dir():
            digest.update(path.relative_to(bag).as_posix().encode() + b"\0")
        with path.open("rb") as f:
            while chunk := f.read(CHUNK):
                digest.update(chunk)
    return digest.hexdigest()


def utc_iso(seconds: float) -> str:
    """A POSIX time as ISO 8601 UTC, ``2026-12-02T07:01:02.500000Z``."""
    return datetime.fromtimestamp(seconds, UTC).isoformat().replace("+00:00", "Z")


def session_date(bag: str | Path) -> str:
    """The time of the bag's first message, ISO 8601 UTC."""
    from canopy_kit.io.bag import open_bag

    with open_bag(bag) as session:
        return utc_iso(session.start_time)


def provenance(
    bag: str | Path,
    preset: str,
    started: float,
    seconds: float,
    orchard: str | None = None,
    drone_images: str | Path | None = None,
) -> dict[str, Any]:
    """The provenance dict of a run of ``bag`` (``orchard`` defaults to the bag's stem;
    ``started`` POSIX time, ``seconds`` how long the run took)."""
    from canopy_kit import __version__

    bag = Path(bag)
    return {
        "orchard": orchard or bag.stem,
        "session_date": session_date(bag),
        "bag": bag.name,
        "bag_sha256": bag_sha256(bag),
        "drone_images": str(drone_images) if drone_images is not None else "",
        "software_version": __version__,
        "preset": preset,
        "run_started_utc": utc_iso(started),
        "run_seconds": round(float(seconds), 3),
    }
