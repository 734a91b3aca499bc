"""Reading geotagged drone photos: what is read, and the message a user sees for bad input."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np
import piexif
import pytest
from PIL import Image

from canopy_kit.errors import InputError
from canopy_kit.sim.config import DroneSpec
from canopy_kit.sim.drone import encode_jpeg, exif_bytes, focal_px
from ground_truth.exif import read_flight, read_image

WHEN = datetime(2024, 6, 18, 11, 0, 0)


def _photo(
    path: Path,
    lat: float = 37.281,
    lon: float = -120.42,
    alt: float = 85.0,
    size: tuple[int, int] = (160, 120),
    seed: int = 0,
    exif: bytes | None = None,
) -> Path:
    spec = DroneSpec(image_width=size[0], image_height=size[1])
    pixels = np.random.default_rng(seed).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    data = exif if exif is not None else exif_bytes(spec, lat, lon, alt, WHEN)
    path.write_bytes(encode_jpeg(pixels, data, 90))
    return path


def _flight(folder: Path, n: int = 4) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        _photo(folder / f"IMG_{k:04d}.jpg", lat=37.281 + 1e-5 * k, seed=k)
    return folder


def test_reads_gps_and_focal_length(tmp_path):
    path = _photo(tmp_path / "a.jpg", lat=-33.5, lon=151.25, alt=123.456)
    im = read_image(path)
    assert (im.width, im.height) == (160, 120)
    assert im.lat == pytest.approx(-33.5, abs=1e-8) and im.lon == pytest.approx(151.25, abs=1e-8)
    assert im.altitude == pytest.approx(123.456, abs=1e-3)
    assert im.focal_px == pytest.approx(
        focal_px(DroneSpec(image_width=160, image_height=120)), rel=1e-4
    )
    assert im.focal_source == "FocalLength+FocalPlaneXResolution"


def test_focal_from_35mm_equivalent_and_none(tmp_path):
    exif = piexif.load(
        exif_bytes(DroneSpec(image_width=160, image_height=120), 37.0, -120.0, 50.0, WHEN)
    )
    for tag in (piexif.ExifIFD.FocalPlaneXResolution, piexif.ExifIFD.FocalPlaneYResolution):
        exif["Exif"].pop(tag)
    im = read_image(_photo(tmp_path / "b.jpg", exif=piexif.dump(exif)))
    assert im.focal_source == "FocalLengthIn35mmFilm"
    assert im.focal_px == pytest.approx(24 / 36 * 160)
    exif["Exif"].pop(piexif.ExifIFD.FocalLengthIn35mmFilm)
    im = read_image(_photo(tmp_path / "c.jpg", exif=piexif.dump(exif)))
    assert im.focal_px is None and im.focal_source == "none"


def test_resized_photo_rescales_focal_length(tmp_path):
    spec = DroneSpec(image_width=320, image_height=240)
    pixels = np.zeros((120, 160, 3), np.uint8)  # half the size the EXIF was written for
    (tmp_path / "half.jpg").write_bytes(
        encode_jpeg(pixels, exif_bytes(spec, 37.0, -120.0, 50.0, WHEN), 90)
    )
    assert read_image(tmp_path / "half.jpg").focal_px == pytest.approx(focal_px(spec) / 2, rel=1e-4)


def test_flight_sorted_with_local_positions(tmp_path):
    flight = read_flight(_flight(tmp_path / "f", 4))
    assert flight.names == [f"IMG_{k:04d}.jpg" for k in range(4)]
    xyz = flight.local_positions(flight.default_frame())
    # 1e-5 degree of latitude is about 1.11 m north.
    assert np.diff(xyz[:, 1]) == pytest.approx([1.11] * 3, abs=0.01)
    assert np.allclose(xyz[:, 2], 85.0)


def test_missing_folder(tmp_path):
    with pytest.raises(InputError, match="not a folder of drone photos"):
        read_flight(tmp_path / "nope")


def test_too_few_images(tmp_path):
    folder = _flight(tmp_path / "f", 2)
    with pytest.raises(InputError, match=r"2 JPEG image\(s\), at least 3 are needed"):
        read_flight(folder)


def test_image_without_exif(tmp_path):
    folder = _flight(tmp_path / "f", 3)
    Image.new("RGB", (160, 120), "green").save(folder / "IMG_9999.jpg", quality=90)
    with pytest.raises(InputError, match=r"IMG_9999.jpg: no EXIF metadata"):
        read_flight(folder)


def test_image_without_gps(tmp_path):
    folder = _flight(tmp_path / "f", 3)
    exif = piexif.load(
        exif_bytes(DroneSpec(image_width=160, image_height=120), 37.0, -120.0, 50.0, WHEN)
    )
    exif["GPS"] = {}
    _photo(folder / "IMG_9999.jpg", exif=piexif.dump(exif))
    with pytest.raises(
        InputError,
        match=r"IMG_9999.jpg: no GPS position in EXIF \(GPSLatitude, "
        r"GPSLongitude, GPSAltitude missing\)",
    ):
        read_flight(folder)


def test_corrupt_jpeg(tmp_path):
    folder = _flight(tmp_path / "f", 3)
    data = (folder / "IMG_0001.jpg").read_bytes()
    (folder / "IMG_0001.jpg").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"IMG_0001.jpg: not a readable JPEG"):
        read_flight(folder)


def test_not_a_jpeg(tmp_path):
    folder = _flight(tmp_path / "f", 3)
    (folder / "IMG_0005.jpg").write_text("hello")
    with pytest.raises(InputError, match=r"IMG_0005.jpg: not a readable JPEG"):
        read_flight(folder)


def test_duplicate_photo(tmp_path):
    folder = _flight(tmp_path / "f", 3)
    (folder / "IMG_0009.jpg").write_bytes((folder / "IMG_0001.jpg").read_bytes())
    with pytest.raises(InputError, match=r"IMG_0009.jpg: duplicate of IMG_0001.jpg"):
        read_flight(folder)


def test_photo_of_another_size(tmp_path):
    folder = _flight(tmp_path / "f", 3)
    _photo(folder / "IMG_0007.jpg", size=(200, 150), seed=9)
    with pytest.raises(
        InputError, match=r"IMG_0007.jpg: 200x150 px while IMG_0000.jpg is 160x120 px"
    ):
        read_flight(folder)


def test_real_drone_photo_focal_length(shared_data):
    photo = shared_data / "caliterra_drone" / "IMG_9376.jpg"
    if not photo.exists():
        pytest.skip("caliterra_drone photos not present")
    im = read_image(photo)
    # Canon SX260: 4.5 mm lens, 4000 px per 0.244 inch of sensor width.
    assert im.focal_px == pytest.approx(4.5 * (4000 / 0.244) / 25.4, rel=1e-6)
    assert 30.0 < im.lat < 30.3 and -98.2 < im.lon < -98.0


def test_photos_taken_at_one_place_are_refused_before_any_work(tmp_path):
    """No baseline, no structure from motion: said at once, not after minutes of matching,
    and nothing is written under the output folder."""
    from ground_truth.pipeline import process_flight

    folder = tmp_path / "hover"
    folder.mkdir()
    for k in range(6):  # one GPS point, a few decimetres of jitter, different pixels
        _photo(folder / f"IMG_{k:04d}.jpg", lat=37.281 + 2e-6 * (k % 2), seed=k)
    with pytest.raises(
        InputError, match=r"hover: the 6 photos were all taken within 0\.\d\d m of each other"
    ):
        read_flight(folder)
    with pytest.raises(
        InputError, match="structure from motion needs photos taken along a flight path"
    ):
        process_flight(folder, tmp_path / "out")
    assert not (tmp_path / "out").exists()
