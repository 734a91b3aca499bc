"""``sensor_msgs/PointCloud2`` to and from numpy, with per-point time normalisation.

Per-point time conventions differ between drivers; :func:`point_times` turns each into
absolute seconds:

- Ouster ``t``: uint32 nanoseconds since the scan's header stamp;
- Velodyne ``time``: float32 seconds relative to the header stamp (may be negative when
  the stamp marks the end of the sweep);
- Hesai ``timestamp``: float64 absolute seconds; livox_ros_driver2 ``timestamp``: float64
  absolute nanoseconds; integer absolute nanoseconds.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from canopy_kit.errors import InputError, MessageError

# sensor_msgs/PointField datatype constants
POINTFIELD_DTYPES: dict[int, str] = {
    1: "i1",
    2: "u1",
    3: "i2",
    4: "u2",
    5: "i4",
    6: "u4",
    7: "f4",
    8: "f8",
}
DTYPE_TO_POINTFIELD: dict[str, int] = {v: k for k, v in POINTFIELD_DTYPES.items()}

TIME_FIELD_NAMES: tuple[str, ...] = ("t", "time", "timestamp", "time_stamp", "offset_time")


def structured_dtype(msg: Any, where: str = "PointCloud2") -> np.dtype:
    """The numpy structured dtype that the message's ``fields`` describe (checked against
    ``point_step``: see :func:`check_fields`)."""
    check_fields(msg, where)
    endian = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        code = POINTFIELD_DTYPES[int(f.datatype)]
        count = max(int(f.count), 1)
        names.append(f.name)
        formats.append((endian + code, (count,)) if count > 1 else endian + code)
        offsets.append(int(f.offset))
    try:
        return np.dtype(
            {
                "names": names,
                "formats": formats,
                "offsets": offsets,
                "itemsize": int(msg.point_step),
            }
        )
    except (ValueError, TypeError) as exc:
        raise MessageError(
            f"{where}: field layout does not fit point_step {msg.point_step}: {exc}"
        ) from None


def check_fields(msg: Any, where: str = "PointCloud2") -> None:
    """Raise a :class:`MessageError` naming the field when the ``fields`` cannot describe the
    points: an unknown datatype, a repeated name or a field reaching past ``point_step``."""
    step = int(msg.point_step)
    spans: dict[str, tuple[int, int]] = {}
    for f in msg.fields:
        code = POINTFIELD_DTYPES.get(int(f.datatype))
        if code is None:
            raise MessageError(
                f"{where}: field {f.name!r} has unknown datatype {f.datatype} "
                f"(PointField knows 1-8: INT8 ... FLOAT64)"
            )
        if f.name in spans:
            raise MessageError(f"{where}: field {f.name!r} appears twice")
        count = max(int(f.count), 1)
        offset, size = int(f.offset), np.dtype(code).itemsize * count
        if offset + size > step:
            raise MessageError(
                f"{where}: field {f.name!r} (offset {offset}, {count} x {size // count} "
                f"bytes) ends at byte {offset + size}, beyond point_step {step}"
            )
        spans[f.name] = (offset, offset + size)


def unused_bytes(msg: Any, n_data: int, where: str = "PointCloud2") -> int:
    """Bytes of ``data`` beyond the points the header describes: past ``height`` rows of
    ``row_step``, and the padding of rows with room for another point (alignment padding,
    shorter than a point, is part of the format). A :class:`MessageError` naming the header
    field when ``row_step`` or ``data`` is too short for the points claimed."""
    width, height = int(msg.width), int(msg.height)
    step, row_step = int(msg.point_step), int(msg.row_step)
    if width * height == 0:
        return n_data
    if row_step < width * step:
        raise MessageError(
            f"{where}: row_step {row_step} is shorter than width x point_step = "
            f"{width} x {step} = {width * step} bytes"
        )
    needed = row_step * (height - 1) + width * step
    if n_data < needed:
        raise MessageError(
            f"{where}: data has {n_data} bytes, too few for {height}x{width} points of {step} bytes "
            f"(row_step {row_step}: {needed} bytes needed); width, height or point_step is wrong "
            "or the data is cut"
        )
    padding = row_step - width * step
    return max(0, n_data - row_step * height) + (height * padding if padding >= max(step, 1) else 0)


def decode_checked(msg: Any, where: str = "PointCloud2") -> tuple[np.ndarray, int]:
    """The points of a PointCloud2 (1-D structured array, rows flattened) and the number of
    data bytes no point covers. A malformed message raises a :class:`MessageError` naming
    the field that does not fit (see :func:`check_fields`, :func:`unused_bytes`)."""
    data = (
        msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(bytes(msg.data), np.uint8)
    )
    data = data.reshape(-1).view(np.uint8)
    unused = unused_bytes(msg, len(data), where)  # the sizes first: they need no allocation
    dtype = structured_dtype(msg, where)
    width, height = int(msg.width), int(msg.height)
    step, row_step = int(msg.point_step), int(msg.row_step)
    n = width * height
    if n == 0:
        return np.zeros(0, dtype=dtype), unused
    if row_step == width * step or height == 1:
        flat = np.ascontiguousarray(data[: n * step])
    else:  # rows with padding: one strided view, no Python loop over rows
        data = np.ascontiguousarray(data)
        rows = np.lib.stride_tricks.as_strided(
            data, shape=(height, width * step), strides=(row_step, 1), writeable=False
        )
        flat = np.ascontiguousarray(rows).reshape(-1)
    return np.frombuffer(flat, dtype=dtype, count=n), unused


def decode(msg: Any, where: str = "PointCloud2") -> np.ndarray:
    """Decode a PointCloud2 message into a 1-D structured array (rows flattened)."""
    return decode_checked(msg, where)[0]


def xyz_from(points: np.ndarray, where: str = "PointCloud2") -> np.ndarray:
    """The (N, 3) float64 coordinates of decoded points; a :class:`MessageError` naming the
    field when x, y or z is missing, holds several values or shares bytes with another."""
    fields = points.dtype.fields or {}
    missing = [c for c in ("x", "y", "z") if c not in fields]
    if missing:
        raise MessageError(
            f"{where}: no {'/'.join(missing)} field (fields: {', '.join(fields) or 'none'})"
        )
    spans = {}
    for c in ("x", "y", "z"):
        dtype, offset = fields[c][0], fields[c][1]
        if dtype.shape:
            raise MessageError(f"{where}: field {c!r} has count {dtype.shape[0]}, expected 1")
        spans[c] = (offset, offset + dtype.itemsize)
    for a, b in (("x", "y"), ("x", "z"), ("y", "z")):
        (a0, a1), (b0, b1) = spans[a], spans[b]
        if a0 < b1 and b0 < a1:
            raise MessageError(
                f"{where}: fields {a!r} and {b!r} overlap (bytes {a0}-{a1} and {b0}-{b1})"
            )
    xyz = np.empty((len(points), 3))
    with np.errstate(invalid="ignore"):  # a signalling NaN among corrupt bytes raises the flag
        for i, c in enumerate(("x", "y", "z")):  # straight into place: no temporary columns
            xyz[:, i] = points[c]
    return xyz


def time_field_name(names: tuple[str, ...] | list[str]) -> str | None:
    """The per-point time field among ``names``, by the common driver conventions."""
    for candidate in TIME_FIELD_NAMES:
        if candidate in names:
            return candidate
    return None


def point_times(values: np.ndarray, stamp: float) -> np.ndarray:
    """Per-point times in absolute seconds from a driver's time field (see module doc)."""
    if values.size == 0:
        return np.zeros(0)
    if np.issubdtype(values.dtype, np.integer):
        v = values.astype(np.float64)
        if np.nanmax(np.abs(v)) > 1e15:  # absolute nanoseconds
            return v * 1e-9
        return stamp + v * 1e-9  # relative nanoseconds (Ouster t, Livox offset_time)
    v = values.astype(np.float64)
    finite = v[np.isfinite(v)]
    peak = np.max(np.abs(finite)) if finite.size else 0.0
    if peak > 1e6:  # absolute: seconds (Hesai) or nanoseconds as float64 (livox_ros_driver2)
        # the unit whose times lie nearer the header stamp (a bag on a clock started near 0,
        # 100 s in, holds 1e11 ns: larger than any plausible time in seconds near its stamp)
        middle = float(np.median(finite))
        nearer_ns = stamp > 0 and abs(middle * 1e-9 - stamp) < abs(middle - stamp)
        return v * 1e-9 if peak > 1e15 or nearer_ns else v
    return stamp + v  # relative seconds (Velodyne)


def build_message(
    typestore: Any,
    columns: Mapping[str, np.ndarray],
    stamp: float,
    frame_id: str = "lidar",
    ros1: bool = False,
    seq: int = 0,
    height: int = 1,
) -> Any:
    """Build a PointCloud2 message object from named 1-D columns (packed, little endian)."""
    names = list(columns)
    n = len(next(iter(columns.values()))) if columns else 0
    formats = [np.asarray(columns[k]).dtype.newbyteorder("<") for k in names]
    for k, fmt in zip(names, formats):
        if fmt.str[1:] not in DTYPE_TO_POINTFIELD:
            raise InputError(f"column {k!r} has dtype {fmt} that PointCloud2 cannot carry")
        if len(columns[k]) != n:
            raise InputError(f"column {k!r} has {len(columns[k])} values, expected {n}")
    packed = np.zeros(n, dtype=np.dtype({"names": names, "formats": formats}))
    for k in names:
        packed[k] = columns[k]
    dt = packed.dtype
    if n % height:
        raise InputError(f"{n} points do not fill {height} rows")
    width = n // height
    pf = typestore.types["sensor_msgs/msg/PointField"]
    fields = [
        pf(
            name=k,
            offset=int(dt.fields[k][1]),
            datatype=DTYPE_TO_POINTFIELD[dt.fields[k][0].str[1:]],
            count=1,
        )
        for k in names
    ]
    return typestore.types["sensor_msgs/msg/PointCloud2"](
        header=make_header(typestore, stamp, frame_id, ros1, seq),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=False,
        point_step=dt.itemsize,
        row_step=dt.itemsize * width,
        data=np.frombuffer(packed.tobytes(), dtype=np.uint8),
        is_dense=True,
    )


def make_header(typestore: Any, stamp: float, frame_id: str, ros1: bool, seq: int = 0) -> Any:
    """A std_msgs/Header for ROS1 (with ``seq``) or ROS2."""
    time_cls = typestore.types["builtin_interfaces/msg/Time"]
    sec = int(np.floor(stamp))
    nanosec = int(round((stamp - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    header_cls = typestore.types["std_msgs/msg/Header"]
    if ros1:
        return header_cls(seq=seq, stamp=time_cls(sec=sec, nanosec=nanosec), frame_id=frame_id)
    return header_cls(stamp=time_cls(sec=sec, nanosec=nanosec), frame_id=frame_id)


def stamp_seconds(header: Any) -> float:
    """Header stamp as float seconds."""
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9
