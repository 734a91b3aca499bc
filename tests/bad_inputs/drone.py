"""Folders of geotagged drone JPEGs, whole or with the faults photographers meet."""

from __future__ import annotations

import shutil
from datetime import datetime
from pathlib import Path

import numpy as np

WHEN = datetime(2024, 6, 18, 11, 0, 0)


def photo(
    path: Path,
    lat: float = 38.54,
    lon: float = -121.75,
    alt: float = 60.0,
    size: tuple[int, int] = (160, 120),
    seed: int = 0,
    gps: bool = True,
) -> Path:
    """One small JPEG with camera and (optionally) GPS EXIF, as the simulator writes them."""
    import piexif

    from canopy_kit.sim.config import DroneSpec
    from canopy_kit.sim.drone import encode_jpeg, exif_bytes

    spec = DroneSpec(image_width=size[0], image_height=size[1])
    exif = exif_bytes(spec, lat, lon, alt, WHEN)
    if not gps:
        tags = piexif.load(exif)
        tags["GPS"] = {}
        exif = piexif.dump(tags)
    pixels = np.random.default_rng(seed).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    path.write_bytes(encode_jpeg(pixels, exif, 90))
    return path


def flight(folder: Path, n: int = 4) -> Path:
    """``n`` photos along a line, 1 m apart."""
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        photo(folder / f"DJI_{k:04d}.JPG", lat=38.54 + 9e-6 * k, seed=k)
    return folder


def without_gps(folder: Path) -> Path:
    """One photo's GPS block is empty (the drone had no fix yet)."""
    flight(folder)
    return photo(folder / "DJI_0002.JPG", lat=38.54 + 1.8e-5, seed=2, gps=False)


def duplicated(folder: Path) -> Path:
    """One photo copied twice under another name (a card copied twice)."""
    flight(folder)
    return Path(shutil.copy(folder / "DJI_0001.JPG", folder / "DJI_0001_copy.JPG"))


def truncated_jpeg(folder: Path) -> Path:
    """One photo cut short (the card was pulled during the copy)."""
    flight(folder)
    path = folder / "DJI_0003.JPG"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def not_a_jpeg(folder: Path) -> Path:
    """A file named .JPG holding random bytes."""
    flight(folder)
    path = folder / "DJI_0009.JPG"
    path.write_bytes(np.random.default_rng(9).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    return path


def other_size(folder: Path) -> Path:
    """One photo of a different size (a phone picture dropped into the folder)."""
    flight(folder)
    return photo(folder / "DJI_0004.JPG", lat=38.54 + 3.6e-5, size=(120, 90), seed=4)


def too_few(folder: Path) -> Path:
    """Two photos: structure from motion needs at least three."""
    return flight(folder, n=2)


def one_place(folder: Path) -> Path:
    """Six photos taken at one GPS point (a hover): no baseline for structure from motion."""
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(6):
        photo(folder / f"DJI_{k:04d}.JPG", lat=38.54 + 2e-6 * (k % 2), seed=k)
    return folder
