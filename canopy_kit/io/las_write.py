"""Writing LAS/LAZ through laspy (LAZ via lazrs): absolute = xyz + origin, every field kept.

Fields that are not standard dimensions of the chosen point format become extra-bytes
dimensions; the smallest format that holds the standard fields exactly is chosen.

What the ASPRS LAS 1.2/1.4 specification asks of every file written here:

* return numbers: ``return_number`` in 1..``number_of_returns``; a cloud without them gets
  1 of 1 (one return per pulse, the specification's values for a system that does not
  record several); given ones are kept, a 0 (unknown) becoming 1 (:func:`las_returns`);
* GPS time: ``gps_time`` of a cloud holds Unix seconds (the bag clock; all values from
  1e9, i.e. 2001, on), seconds of a GPS week (all in 0..604800) or, from another program's
  LAS file, Adjusted Standard GPS Time (anything else). Unix seconds are written as
  Adjusted Standard GPS Time, the others as they are, with the global encoding's bit 0
  saying which (:func:`las_gps_time`; the reader's :func:`cloud_gps_time` undoes it);
* header: generating software ``canopy-kit <version>``, system identifier ``OTHER``,
  creation day and year (UTC) of the writing; LAS 1.4 (point formats 6-8, or a CRS known
  only as WKT) sets the WKT bit (formats 6-10 must use WKT) and, as the specification asks
  of a file that is not legacy-compatible, zero legacy point counts.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from canopy_kit.core.atomic import atomic_path
from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError, foreign_message

# Point formats without waveform packets, smallest first.
WRITABLE_FORMATS: tuple[int, ...] = (0, 1, 2, 3, 6, 7, 8)
EXTRA_BYTES_DTYPES = {"u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8", "f4", "f8"}
INT32_MAX = 2**31 - 1

SYSTEM_IDENTIFIER = "OTHER"  # LAS: not a sensor, a merge or a reprojection of one file
GPS_EPOCH_UNIX = 315_964_800  # 1980-01-06T00:00:00Z, the GPS epoch, in Unix seconds
GPS_LEAP_SECONDS = 18  # GPS time ahead of UTC (and Unix time) since 2017-01-01
GPS_WEEK_SECONDS = 604_800
UNIX_TIME_MIN = 1e9  # 2001-09-09 in Unix seconds: bag clocks are later
# Adjusted Standard GPS Time = GPS seconds since the epoch - 1e9 = Unix seconds - this.
UNIX_TO_ADJUSTED_GPS = GPS_EPOCH_UNIX - GPS_LEAP_SECONDS + 1_000_000_000  # 1_315_964_782


def _fits_standard(values: np.ndarray, dim: Any) -> bool:
    """Whether ``values`` can be stored exactly in a standard LAS dimension."""
    if values.ndim != 1:
        return False
    if dim.kind.name == "FloatingPoint":
        return values.dtype.kind in "fiub"
    if values.dtype.kind == "f" and not np.all(np.isfinite(values)):
        return False
    if values.size == 0:
        return True
    if values.dtype.kind == "f" and not np.array_equal(values, np.round(values)):
        return False
    return bool(values.min() >= dim.min and values.max() <= dim.max)


def choose_point_format(fields: dict[str, np.ndarray]) -> int:
    """The smallest point format whose standard dimensions hold the most fields exactly."""
    import laspy

    best: tuple[int, int] | None = None
    for fmt_id in WRITABLE_FORMATS:
        fmt = laspy.PointFormat(fmt_id)
        standard = set(fmt.dimension_names)
        if any(
            k in standard and not _fits_standard(np.asarray(v), fmt.dimension_by_name(k))
            for k, v in fields.items()
        ):
            continue
        extras = sum(1 for k in fields if k not in standard)
        if best is None or extras < best[0]:
            best = (extras, fmt_id)
    return best[1] if best is not None else 6


def _extra_bytes_type(name: str, values: np.ndarray, path: Path) -> str:
    if values.ndim not in (1, 2) or (values.ndim == 2 and values.shape[1] > 3):
        raise InputError(
            f"{path}: field {name!r} has shape {values.shape}; LAS extra bytes "
            f"hold 1-3 values per point"
        )
    if len(name) > 32:
        raise InputError(f"{path}: field name {name!r} is longer than the 32 characters LAS allows")
    code = "u1" if values.dtype.kind == "b" else values.dtype.newbyteorder("<").str[1:]
    if code not in EXTRA_BYTES_DTYPES:
        raise InputError(f"{path}: field {name!r} has dtype {values.dtype} that LAS cannot store")
    return code if values.ndim == 1 else f"{values.shape[1]}{code}"


def generating_software() -> str:
    """The header's generating software: ``canopy-kit <version>`` (32 bytes at most)."""
    from canopy_kit import __version__

    return f"canopy-kit {__version__}"[:32]


def gps_time_kind(values: np.ndarray) -> str:
    """What ``gps_time`` values are, by their finite values: ``"week"`` (none, or all in
    0..604800: GPS week seconds), ``"unix"`` (all from 1e9 on: Unix seconds after 2001-09-09,
    when Adjusted Standard GPS Time is below 1e9 until 2043) or ``"adjusted"`` (Adjusted
    Standard GPS Time, as read from another program's file; also any other clock)."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0 or (finite.min() >= 0 and finite.max() <= GPS_WEEK_SECONDS):
        return "week"
    return "unix" if finite.min() >= UNIX_TIME_MIN else "adjusted"


def adjusted_gps_time(unix: np.ndarray) -> np.ndarray:
    """Unix seconds as LAS Adjusted Standard GPS Time (global encoding bit 0 set).

    Standard GPS time counts seconds from the GPS epoch, 1980-01-06 00:00:00 UTC (Unix
    315964800), without leap seconds; Unix time ignores leap seconds, so GPS = Unix -
    315964800 + 18 (the leap seconds since 2017-01-01; a time before 2017 comes out up to
    18 s late, the leap seconds inserted between it and 2017). Adjusted Standard GPS Time is
    GPS - 1e9: adjusted = Unix - 1315964782 (a 2024 drive: about 3.9e8 s). One subtraction
    of an integer, exact for times of 1990-2053, so :func:`unix_time` gives them back
    bit for bit.
    """
    return np.asarray(unix, dtype=np.float64) - UNIX_TO_ADJUSTED_GPS


def unix_time(adjusted: np.ndarray) -> np.ndarray:
    """Adjusted Standard GPS Time as Unix seconds: the inverse of :func:`adjusted_gps_time`."""
    return np.asarray(adjusted, dtype=np.float64) + UNIX_TO_ADJUSTED_GPS


def las_gps_time(values: np.ndarray) -> tuple[np.ndarray, bool]:
    """``gps_time`` as stored, and whether it is Adjusted Standard GPS Time (global encoding
    bit 0) (see :func:`gps_time_kind`): Unix seconds are converted, GPS week seconds and
    Adjusted Standard GPS Time are stored as they are."""
    kind = gps_time_kind(values)
    if kind == "unix":
        return adjusted_gps_time(values), True
    return np.asarray(values), kind == "adjusted"


def cloud_gps_time(stored: np.ndarray) -> np.ndarray:
    """A LAS file's Adjusted Standard GPS Time as a cloud's ``gps_time``: Unix seconds when
    they give the stored values back exactly (the times were Unix seconds, as in every file
    written here), else as stored: another program's finer times would be rounded by up to
    0.12 us in Unix seconds, and :func:`las_gps_time` writes them back unchanged."""
    stored = np.asarray(stored, dtype=np.float64)
    unix = unix_time(stored)
    exact = np.array_equal(adjusted_gps_time(unix), stored, equal_nan=True)
    return unix if exact and gps_time_kind(unix) == "unix" else stored


def las_returns(fields: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    """``fields`` of ``n`` points with valid ``return_number`` and ``number_of_returns`` (LAS:
    return number 1..number of returns): both 1 when the cloud has neither (one return per
    pulse); given values are kept, except that a return number below 1 (0: unknown) becomes
    1 and the number of returns is raised to at least the return number (a missing one: to
    it). Values no point format holds (above 15, NaN) are refused by :func:`write_las`."""
    out = dict(fields)
    number, count = out.get("return_number"), out.get("number_of_returns")
    if number is None and count is None:
        out["return_number"] = np.ones(n, np.uint8)
        out["number_of_returns"] = np.ones(n, np.uint8)
        return out
    numeric = "iuf"
    if number is None:
        number = np.ones(n, np.uint8)
    elif number.ndim == 1 and number.dtype.kind in numeric:
        number = np.maximum(number, 1).astype(number.dtype)
    if count is None:
        count = number.copy()
    elif count.ndim == 1 and count.dtype.kind in numeric and number.dtype.kind in numeric:
        count = np.maximum(count, np.maximum(number, 1)).astype(count.dtype)
    out["return_number"], out["number_of_returns"] = number, count
    return out


def _write_offsets(cloud: PointCloud, scale: float, path: Path) -> np.ndarray:
    """Header offsets: the origin, moved to the data when integers would overflow int32."""
    offsets = cloud.origin.copy()
    if len(cloud):
        lo, hi = cloud.bounds()
        for axis in range(3):
            if max(abs(lo[axis]), abs(hi[axis])) / scale > INT32_MAX:
                centre = np.round((lo[axis] + hi[axis]) / 2 / scale) * scale
                if (hi[axis] - lo[axis]) / 2 / scale > INT32_MAX:
                    raise InputError(f"{path}: extent too large for LAS integers at scale {scale}")
                offsets[axis] += centre
    return offsets


def las_ready(cloud: PointCloud) -> PointCloud:
    """LAS stores intensity as uint16: round a float intensity (drivers publish float32 0-255)."""
    value = cloud.fields.get("intensity")
    if value is not None and np.issubdtype(np.asarray(value).dtype, np.floating):
        value = np.nan_to_num(np.asarray(value, dtype=np.float64), nan=0.0)
        return cloud.with_field("intensity", np.clip(np.round(value), 0, 65535).astype(np.uint16))
    return cloud


LAS_SCALE = 0.001  # metres per stored integer: 1 mm


def on_las_grid(cloud: PointCloud, scale: float = LAS_SCALE) -> PointCloud:
    """``cloud`` with its local coordinates rounded as :func:`write_las` stores them (the
    origin as offset), so what is measured on it is what a reader of the file measures."""
    xyz = np.round(cloud.xyz / scale) * scale
    return PointCloud(xyz, cloud.fields, cloud.crs, cloud.origin.copy())


def write_las(
    path: str | Path, cloud: PointCloud, point_format: int | None = None, scale: float = LAS_SCALE
) -> Path:
    """Write a PointCloud as LAS or LAZ (by suffix), absolute = xyz + origin, atomically.

    ``point_format`` None picks the smallest format that holds the standard fields; fields
    that are not standard dimensions become extra-bytes dimensions. Return numbers, GPS time
    and the header follow the specification as the module docstring says.
    """
    import laspy
    from laspy.header import GpsTimeType

    path = Path(path)
    if path.suffix.lower() not in (".las", ".laz"):
        raise InputError(f"{path}: LAS output needs a .las or .laz suffix")
    if len(cloud) == 0:
        raise InputError(f"{path}: refusing to write a point cloud with no points")
    if not scale > 0:
        raise InputError(f"{path}: scale must be positive, got {scale}")
    fields = las_returns({k: np.asarray(v) for k, v in cloud.fields.items()}, len(cloud))
    fmt_id = choose_point_format(fields) if point_format is None else int(point_format)
    if fmt_id not in WRITABLE_FORMATS:
        raise InputError(f"{path}: point format {fmt_id} is not one of {WRITABLE_FORMATS}")
    fmt = laspy.PointFormat(fmt_id)
    standard = set(fmt.dimension_names)
    crs = _pyproj_crs(cloud.crs, path)
    wkt_only = crs is not None and crs.to_epsg() is None
    version = "1.4" if fmt_id >= 6 or wkt_only else "1.2"
    header = laspy.LasHeader(point_format=fmt_id, version=version)
    header.system_identifier = SYSTEM_IDENTIFIER
    header.generating_software = generating_software()
    header.creation_date = datetime.now(UTC).date()
    header.scales = np.full(3, float(scale))
    header.offsets = _write_offsets(cloud, float(scale), path)
    extra = [k for k in fields if k not in standard]
    header.add_extra_dims(
        [laspy.ExtraBytesParams(name=k, type=_extra_bytes_type(k, fields[k], path)) for k in extra]
    )
    if crs is not None:
        header.add_crs(crs, keep_compatibility=not wkt_only)
    if fmt_id >= 6:
        header.global_encoding.wkt = True  # formats 6-10 must use WKT, CRS or not
    if "gps_time" in standard and "gps_time" in fields:
        fields["gps_time"], adjusted = las_gps_time(fields["gps_time"])
        header.global_encoding.gps_time_type = (
            GpsTimeType.STANDARD if adjusted else GpsTimeType.WEEK_TIME
        )
    # Sized up front: filling an empty LasData grows its record once per dimension.
    las = laspy.LasData(header, points=laspy.ScaleAwarePointRecord.zeros(len(cloud), header=header))
    local_shift = cloud.origin - header.offsets
    integers = np.round((cloud.xyz + local_shift) / scale)
    if np.abs(integers).max() > INT32_MAX:
        raise InputError(f"{path}: coordinates do not fit LAS integers at scale {scale}")
    las.X, las.Y, las.Z = (integers[:, i].astype(np.int32) for i in range(3))
    for name, values in fields.items():
        if name in standard and not _fits_standard(values, fmt.dimension_by_name(name)):
            dim = fmt.dimension_by_name(name)
            raise InputError(
                f"{path}: field {name!r} ({values.dtype}) does not fit LAS point "
                f"format {fmt_id} dimension {name} (range {dim.min}..{dim.max})"
            )
        if name in standard and fmt.dimension_by_name(name).kind.name != "FloatingPoint":
            values = values.astype(fmt.dimension_by_name(name).dtype or np.uint8)
        las[name] = values.astype(np.uint8) if values.dtype.kind == "b" else values
    # LAZ is compressed with lazrs on every core when it is there (a 3.8 M-point map:
    # 4.7 -> 3.2 s).
    compressed = path.suffix.lower() == ".laz"
    backend = _laz_backend() if compressed else None
    with atomic_path(path) as tmp:
        try:
            if backend is None:
                las.write(tmp, do_compress=compressed)
            else:
                las.write(tmp, do_compress=True, laz_backend=backend)
        except Exception as exc:
            raise InputError(
                f"{path}: writing failed ({type(exc).__name__}: {foreign_message(str(exc))})"
            ) from None
    return path


def _pyproj_crs(crs: str | None, path: Path) -> Any:
    if crs is None:
        return None
    import pyproj

    try:
        return pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError as exc:
        raise InputError(f"{path}: CRS {crs[:60]!r} is not understood by pyproj: {exc}") from None


def _laz_backend() -> Any:
    """lazrs with parallel compression when installed, else laspy's own choice."""
    import laspy

    if laspy.LazBackend.LazrsParallel.is_available():
        return laspy.LazBackend.LazrsParallel
    return None
