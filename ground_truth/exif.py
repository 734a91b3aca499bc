"""Read and check a folder of geotagged drone JPEGs (GPS position, focal length, size).

Every photo must be a readable JPEG with EXIF GPS latitude, longitude and altitude, all
photos must have one size, and no photo may appear twice. The focal length in pixels
comes from ``FocalLength`` with ``FocalPlaneXResolution`` (the sensor's pixel pitch) or,
failing that, from ``FocalLengthIn35mmFilm`` (36 mm across the long side). A DJI photo's
gimbal attitude comes from its XMP packet (:mod:`ground_truth.xmp`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canopy_kit.core.extras import needs_extra
from canopy_kit.core.geo import LocalFrame
from canopy_kit.errors import InputError
from ground_truth.xmp import DroneAttitude, read_drone_attitude

JPEG_SUFFIXES = (".jpg", ".jpeg")
MIN_IMAGES = 3
# Structure from motion triangulates from the camera's motion between photos: photos whose GPS
# positions all lie within this many metres (a hover, one photo copied with new bytes) have
# no baseline, and pycolmap spends minutes matching them before it registers none.
MIN_BASELINE_M = 2.0
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF FocalPlaneResolutionUnit → mm


@dataclass(frozen=True)
class FlightImage:
    """One photo: file, size, GPS position (WGS84, altitude in m) and focal length in pixels."""

    path: Path
    width: int
    height: int
    lat: float
    lon: float
    altitude: float
    focal_px: float | None
    focal_source: str
    make: str = ""
    model: str = ""
    timestamp: str = ""
    attitude: DroneAttitude | None = None  # gimbal angles from a DJI XMP packet

    @property
    def name(self) -> str:
        return self.path.name


@dataclass(frozen=True)
class Flight:
    """The checked photos of one flight, sorted by file name."""

    folder: Path
    images: tuple[FlightImage, ...]

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) shared by all photos."""
        return self.images[0].width, self.images[0].height

    @property
    def names(self) -> list[str]:
        return [im.name for im in self.images]

    @property
    def focal_px(self) -> float | None:
        """Median EXIF focal length in pixels, or None when no photo states one."""
        values = [im.focal_px for im in self.images if im.focal_px]
        return float(np.median(values)) if values else None

    def local_positions(self, frame: LocalFrame) -> np.ndarray:
        """GPS positions of the photos as (N, 3) coordinates in ``frame``."""
        return frame.to_local(
            np.array([im.lat for im in self.images]),
            np.array([im.lon for im in self.images]),
            np.array([im.altitude for im in self.images]),
        )

    def default_frame(self) -> LocalFrame:
        """A UTM-based frame at the flight's mean position (heights kept as they are)."""
        return LocalFrame.at(
            float(np.mean([im.lat for im in self.images])),
            float(np.mean([im.lon for im in self.images])),
            0.0,
        )


def _ratio(value: object) -> float:
    if isinstance(value, tuple) and len(value) == 2:
        num, den = value
        if den == 0:
            raise ZeroDivisionError
        return num / den
    return float(value)  # type: ignore[arg-type]


def _degrees(dms: object, ref: bytes | str | None) -> float:
    d, m, s = (_ratio(v) for v in dms)  # type: ignore[union-attr]
    value = d + m / 60.0 + s / 3600.0
    ref_s = ref.decode(errors="ignore") if isinstance(ref, bytes) else (ref or "")
    return -value if ref_s.strip().upper() in ("S", "W") else value


def _text(value: object) -> str:
    if isinstance(value, bytes):
        return value.decode(errors="ignore").strip("\x00 ").strip()
    return str(value or "")


def focal_length_px(exif: dict, width: int) -> tuple[float | None, str]:
    """Focal length in pixels from EXIF tags, and which tags gave it."""
    with needs_extra("aerial"):
        import piexif

    e = exif.get("Exif", {})
    try:
        f_mm = _ratio(e[piexif.ExifIFD.FocalLength]) if piexif.ExifIFD.FocalLength in e else None
        res = e.get(piexif.ExifIFD.FocalPlaneXResolution)
        unit = e.get(piexif.ExifIFD.FocalPlaneResolutionUnit, 2)
        if f_mm and res is not None and unit in _UNIT_MM and _ratio(res) > 0:
            px_per_mm = _ratio(res) / _UNIT_MM[unit]
            # The resolution refers to the recorded pixel grid; rescale if the file was resized.
            recorded = e.get(piexif.ExifIFD.PixelXDimension) or width
            return f_mm * px_per_mm * width / float(recorded), "FocalLength+FocalPlaneXResolution"
        f35 = e.get(piexif.ExifIFD.FocalLengthIn35mmFilm)
        if f35:
            return float(f35) / 36.0 * width, "FocalLengthIn35mmFilm"
    except (ZeroDivisionError, TypeError, ValueError):
        pass
    return None, "none"


def read_image(path: str | Path) -> FlightImage:
    """Check one photo (decodable JPEG with GPS EXIF) and read its metadata."""
    with needs_extra("aerial"):
        import piexif
        from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        with Image.open(path) as im:
            if im.format != "JPEG":
                raise InputError(f"{path}: not a JPEG image (format {im.format})")
            width, height = im.size
            xmp = im.info.get("xmp")
            im.draft("RGB", (max(width // 8, 1), max(height // 8, 1)))
            im.load()  # decodes the whole stream (at 1/8 scale): finds truncated files
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise InputError(f"{path}: not a readable JPEG ({exc})") from None
    try:
        exif = piexif.load(str(path))
    except Exception as exc:  # piexif raises bare ValueError/struct.error on damaged blocks
        raise InputError(f"{path}: EXIF block cannot be read ({exc})") from None
    if not any(exif.get(k) for k in ("0th", "Exif", "GPS")):
        raise InputError(f"{path}: no EXIF metadata (a geotagged drone photo is needed)")
    gps = exif.get("GPS") or {}
    needed = {
        piexif.GPSIFD.GPSLatitude: "GPSLatitude",
        piexif.GPSIFD.GPSLongitude: "GPSLongitude",
        piexif.GPSIFD.GPSAltitude: "GPSAltitude",
    }
    missing = [name for tag, name in needed.items() if tag not in gps]
    if missing:
        raise InputError(f"{path}: no GPS position in EXIF ({', '.join(missing)} missing)")
    try:
        lat = _degrees(gps[piexif.GPSIFD.GPSLatitude], gps.get(piexif.GPSIFD.GPSLatitudeRef))
        lon = _degrees(gps[piexif.GPSIFD.GPSLongitude], gps.get(piexif.GPSIFD.GPSLongitudeRef))
        alt = _ratio(gps[piexif.GPSIFD.GPSAltitude])
    except (ZeroDivisionError, TypeError, ValueError):
        raise InputError(f"{path}: GPS position in EXIF is malformed") from None
    if gps.get(piexif.GPSIFD.GPSAltitudeRef) == 1:
        alt = -alt
    if not (-90 <= lat <= 90 and -180 <= lon <= 180) or (lat == 0 and lon == 0):
        raise InputError(f"{path}: GPS position ({lat}, {lon}) is not a valid fix")
    focal, source = focal_length_px(exif, width)
    zeroth, ex = exif.get("0th", {}), exif.get("Exif", {})
    return FlightImage(
        path,
        width,
        height,
        lat,
        lon,
        alt,
        focal,
        source,
        _text(zeroth.get(piexif.ImageIFD.Make)),
        _text(zeroth.get(piexif.ImageIFD.Model)),
        _text(ex.get(piexif.ExifIFD.DateTimeOriginal)),
        read_drone_attitude(xmp, path),
    )


def list_images(folder: str | Path) -> list[Path]:
    """JPEG files directly inside ``folder``, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder of drone photos")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in JPEG_SUFFIXES)


def read_flight(folder: str | Path, min_images: int = MIN_IMAGES) -> Flight:
    """Read and check every JPEG in ``folder`` (GPS, decodable, one size, no duplicates)."""
    folder = Path(folder)
    paths = list_images(folder)
    if len(paths) < min_images:
        raise InputError(
            f"{folder}: {len(paths)} JPEG image(s), at least {min_images} are needed "
            "for structure from motion"
        )
    images, seen = [], {}
    for path in paths:
        digest = hashlib.sha1(path.read_bytes()).hexdigest()
        if digest in seen:
            raise InputError(f"{path}: duplicate of {seen[digest].name} (identical file content)")
        seen[digest] = path
        images.append(read_image(path))
    first = images[0]
    for im in images[1:]:
        if (im.width, im.height) != (first.width, first.height):
            raise InputError(
                f"{im.path}: {im.width}x{im.height} px while {first.name} is "
                f"{first.width}x{first.height} px; all photos must have one size"
            )
    flight = Flight(folder, tuple(images))
    positions = flight.local_positions(flight.default_frame())
    span = float(np.max(np.linalg.norm(positions - positions.mean(axis=0), axis=1))) * 2.0
    if span < MIN_BASELINE_M:
        raise InputError(
            f"{folder}: the {len(images)} photos were all taken within {span:.2f} m of "
            f"each other (GPS): structure from motion needs photos taken along a flight "
            f"path, at least {MIN_BASELINE_M:g} m apart"
        )
    return flight
