"""Seeded fuzz of the PointCloud2 decoder, and a few hostile messages through the command line.

The decoder (``pointcloud2.decode_checked`` + ``xyz_from``) is compared with an independent
reading of the ROS message definition (:func:`oracle`: byte offsets gathered point by point):
on a well-formed message both give the same values; on a mutated one (a header field that
lies, a field outside the point, an unknown datatype, data cut or padded) the decoder gives
what the oracle gives or a ``MessageError``, never another exception, each message within a
time and memory bound. The command-line cases run ``canopy-kit map`` in a subprocess whose
address space is limited (``RLIMIT_AS``, :data:`ADDRESS_SPACE`) with a timeout.
"""

from __future__ import annotations

import os
import resource
import subprocess
import time
import tracemalloc
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from bad_inputs import drives, messages
from test_cli_foundation import cli_command

from canopy_kit.errors import MessageError
from canopy_kit.io import pointcloud2 as pc2

CASES = 3000
SEED = 20250427
TIME_BOUND_S = 0.5  # per message (most take well under a millisecond)
MEMORY_BOUND = 64 * 2**20  # bytes allocated at the peak of one message's decoding
# Measured: `canopy-kit map` of a 5 s drive ran under RLIMIT_AS 1 GiB and failed at 0.75 GiB
# (OpenBLAS could not allocate its buffers; the imports of KISS-ICP and gtsam reach ~1.1 GB of
# virtual memory without Open3D). 1.5 GiB leaves room and still stops a runaway allocation.
ADDRESS_SPACE = int(1.5 * 2**30)
SIZES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}
CODES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


@dataclass
class Field:
    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass
class Cloud:
    """The attributes of a sensor_msgs/PointCloud2 the decoder reads."""

    fields: list
    width: int
    height: int
    point_step: int
    row_step: int
    data: np.ndarray
    is_bigendian: bool = False


def oracle(msg: Cloud) -> tuple[dict[str, np.ndarray], int] | None:
    """Each field's values (rows flattened) and the data bytes beyond the points, read
    byte by byte from the message definition; None when the message cannot be decoded."""
    step, width, height, row_step = msg.point_step, msg.width, msg.height, msg.row_step
    names = [f.name for f in msg.fields]
    if len(set(names)) != len(names) or not {"x", "y", "z"} <= set(names):
        return None
    spans = {}
    for f in msg.fields:
        if f.datatype not in SIZES:
            return None
        size = SIZES[f.datatype] * max(f.count, 1)
        if f.offset + size > step:
            return None
        spans[f.name] = (f.offset, f.offset + size)
    for c in "xyz":
        f = next(f for f in msg.fields if f.name == c)
        if f.count > 1:
            return None
    for a, b in (("x", "y"), ("x", "z"), ("y", "z")):
        if spans[a][0] < spans[b][1] and spans[b][0] < spans[a][1]:
            return None
    n = width * height
    data = np.asarray(msg.data, np.uint8)
    if n == 0:
        return {f.name: np.zeros(0) for f in msg.fields}, len(data)
    if row_step < width * step or len(data) < row_step * (height - 1) + width * step:
        return None
    padding = row_step - width * step
    unused = max(0, len(data) - row_step * height) + (
        height * padding if padding >= max(step, 1) else 0
    )
    starts = (np.arange(height)[:, None] * row_step + np.arange(width)[None, :] * step).ravel()
    values = {}
    for f in msg.fields:
        count, size = max(f.count, 1), SIZES[f.datatype]
        at = starts[:, None] + f.offset + np.arange(count * size)[None, :]
        raw = data[at].reshape(n, count, size)
        if msg.is_bigendian:
            raw = raw[:, :, ::-1]
        v = np.ascontiguousarray(raw).view("<" + CODES[f.datatype]).reshape(n, count)
        values[f.name] = v[:, 0] if count == 1 else v
    return values, unused


def well_formed(rng: np.random.Generator) -> Cloud:
    """A random valid cloud: x, y, z and some of intensity, t, ring, in random order and types,
    with random gaps between fields, at the end of a point and of a row."""
    names = ["x", "y", "z"] + [
        n for n in ("intensity", "t", "ring", "reflectivity") if rng.random() < 0.5
    ]
    rng.shuffle(names)
    fields, offset = [], 0
    for name in names:
        datatype = int(rng.choice([7, 8])) if name in "xyz" else int(rng.integers(1, 9))
        count = 1 if name in "xyz" or rng.random() < 0.8 else int(rng.integers(2, 4))
        offset += int(rng.integers(0, 3))
        fields.append(Field(name, offset, datatype, count))
        offset += SIZES[datatype] * count
    step = offset + int(rng.integers(0, 9))
    width, height = int(rng.integers(0, 200)), int(rng.choice([1, 1, 2, 3, 16]))
    row_step = width * step + int(rng.choice([0, 0, int(rng.integers(1, step + 9))]))
    length = row_step * height - (
        int(rng.integers(0, row_step - width * step + 1)) if rng.random() < 0.2 else 0
    )
    data = rng.integers(0, 256, max(length, 0), dtype=np.uint8)
    return Cloud(fields, width, height, step, row_step, data, bool(rng.random() < 0.2))


def mutated(msg: Cloud, rng: np.random.Generator) -> tuple[Cloud, str]:
    """``msg`` with one header field, PointField or the data made to lie."""
    kind = str(
        rng.choice(
            [
                "width",
                "height",
                "point_step",
                "row_step",
                "data",
                "offset",
                "datatype",
                "count",
                "name",
                "huge",
            ]
        )
    )
    big = int(rng.choice([2**31 - 1, 2**32 - 1, 10**9]))
    f = int(rng.integers(len(msg.fields)))
    fields = list(msg.fields)
    if kind == "width":
        return replace(
            msg, width=int(rng.choice([msg.width * 2, msg.width // 2, msg.width + 1, 0]))
        ), kind
    if kind == "height":
        return replace(msg, height=int(rng.choice([msg.height + 1, 2 * msg.height, 0]))), kind
    if kind == "point_step":
        return replace(
            msg, point_step=max(0, msg.point_step + int(rng.choice([-8, -4, -1, 1, 4])))
        ), kind
    if kind == "row_step":
        return replace(
            msg,
            row_step=max(0, msg.row_step + int(rng.choice([-msg.point_step, -1, msg.point_step]))),
        ), kind
    if kind == "data":
        cut = int(rng.integers(0, len(msg.data) + 1))
        extra = rng.integers(0, 256, int(rng.integers(1, 4 * msg.point_step + 2)), dtype=np.uint8)
        return replace(
            msg, data=msg.data[:cut] if rng.random() < 0.5 else np.concatenate([msg.data, extra])
        ), kind
    if kind == "offset":
        fields[f] = replace(fields[f], offset=int(rng.integers(0, 2 * msg.point_step + 2)))
    elif kind == "datatype":
        fields[f] = replace(fields[f], datatype=int(rng.choice([0, 9, 11, 255])))
    elif kind == "count":
        fields[f] = replace(fields[f], count=int(rng.choice([0, 2, 1000, big])))
    elif kind == "name":
        fields[f] = replace(fields[f], name=str(rng.choice(["x", "y", "z", "t", "w"])))
    else:
        return replace(
            msg, **{str(rng.choice(["width", "height", "point_step", "row_step"])): big}
        ), kind
    return replace(msg, fields=fields), kind


def _decode(msg: Cloud) -> tuple[np.ndarray, np.ndarray, int] | None:
    try:
        points, unused = pc2.decode_checked(msg, "message 0")
        return points, pc2.xyz_from(points, "message 0"), unused
    except MessageError:
        return None


def test_pointcloud2_decoder_fuzz_against_the_message_definition() -> None:
    """``CASES`` messages (a third well-formed), seeded: decoder and oracle agree on each."""
    rng = np.random.default_rng(SEED)
    outcomes: dict[str, int] = {}
    tracemalloc.start()
    try:
        for k in range(CASES):
            msg = well_formed(rng)
            kind = "none"
            if k % 3:
                msg, kind = mutated(msg, rng)
            tracemalloc.reset_peak()
            t0 = time.perf_counter()
            got = _decode(msg)
            elapsed = time.perf_counter() - t0
            peak = tracemalloc.get_traced_memory()[1]
            assert elapsed < TIME_BOUND_S, (k, kind, elapsed)
            assert peak < MEMORY_BOUND, (k, kind, peak)
            want = oracle(msg)
            assert (got is None) == (want is None), (
                k,
                kind,
                msg.width,
                msg.height,
                msg.point_step,
                msg.row_step,
                len(msg.data),
                msg.fields,
            )
            outcomes[f"{kind}:{'error' if got is None else 'decoded'}"] = (
                outcomes.get(f"{kind}:{'error' if got is None else 'decoded'}", 0) + 1
            )
            if got is None:
                continue
            points, xyz, unused = got
            values, want_unused = want  # type: ignore[misc]
            assert unused == want_unused, (k, kind)
            assert len(points) == msg.width * msg.height
            if not len(points):
                continue
            for name, v in values.items():  # NaN where the oracle has NaN: equal
                np.testing.assert_array_equal(
                    np.asarray(points[name]).astype(v.dtype), v, err_msg=f"{k} {name}"
                )
            with np.errstate(invalid="ignore"):
                np.testing.assert_array_equal(
                    xyz, np.column_stack([values[c].astype(np.float64) for c in "xyz"])
                )
    finally:
        tracemalloc.stop()
    assert outcomes["none:decoded"] == CASES // 3  # every well-formed message decodes
    assert sum(v for k, v in outcomes.items() if k.endswith(":error")) > CASES // 4, outcomes


def test_a_header_that_lies_is_named_in_the_error() -> None:
    """The field that does not fit is the one the message names."""
    base = Cloud(
        [Field("x", 0, 7), Field("y", 4, 7), Field("z", 8, 7), Field("intensity", 12, 7)],
        10,
        1,
        16,
        160,
        np.zeros(160, np.uint8),
    )
    cases = [
        (replace(base, width=20, row_step=320), "data has 160 bytes, too few for 1x20 points"),
        (
            replace(base, point_step=12, row_step=120),
            "field 'intensity' (offset 12, 1 x 4 bytes) ends at byte 16, beyond point_step 12",
        ),
        (
            replace(base, fields=[*base.fields[:3], Field("intensity", 40, 7)]),
            "field 'intensity' (offset 40",
        ),
        (
            replace(base, fields=[Field("x", 0, 11), *base.fields[1:]]),
            "field 'x' has unknown datatype 11",
        ),
        (replace(base, fields=base.fields[1:]), "no x field"),
        (
            replace(base, fields=[Field("x", 0, 7), Field("y", 2, 7), *base.fields[2:]]),
            "fields 'x' and 'y' overlap",
        ),
        (replace(base, row_step=100), "row_step 100 is shorter than width x point_step = 10 x 16"),
        (
            replace(base, fields=[Field("x", 0, 7, 2**31), *base.fields[1:]]),
            "field 'x' (offset 0, 2147483648 x 4 bytes)",
        ),
    ]
    for msg, says in cases:
        with pytest.raises(MessageError) as err:
            points, _ = pc2.decode_checked(msg, "topic '/points', message 3")
            pc2.xyz_from(points, "topic '/points', message 3")
        assert str(err.value).startswith("topic '/points', message 3: ") and says in str(
            err.value
        ), str(err.value)
    points, unused = pc2.decode_checked(
        replace(base, width=5, row_step=80), "m"
    )  # half the data unclaimed
    assert len(points) == 5 and unused == 80


# -- the command line, under a memory limit ---------------------------------------------------------
def _limited(args: list[str], timeout: float = 180) -> subprocess.CompletedProcess[str]:
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))

    return subprocess.run(
        [*cli_command(), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        preexec_fn=limit,
        env={**os.environ, "COLUMNS": "400"},
    )


@pytest.fixture(scope="module")
def small_drive(tmp_path_factory) -> Path:
    return drives.write_drive(
        tmp_path_factory.mktemp("fuzz") / "clean", duration=5.0, points_per_scan=2000
    ).path


def test_clean_drive_maps_under_the_memory_limit(small_drive: Path, tmp_path: Path) -> None:
    result = _limited(["map", str(small_drive), "--out", str(tmp_path / "out"), "--no-plots"])
    assert result.returncode == 0, result.stderr[-2000:]


@pytest.mark.parametrize(
    ("case", "edit", "says"),
    [
        (
            "width-max",
            messages.cloud_header(width=2**32 - 1),
            "is shorter than width x point_step = 4294967295 x 20",
        ),
        ("height-huge", messages.cloud_header(height=2**31), "too few for 2147483648x"),
        (
            "point-step-huge",
            messages.cloud_header(width=1, point_step=2**31, row_step=2**32 - 1),
            "too few for 1x1 points of 2147483648 bytes",
        ),
        (
            "count-huge",
            messages.cloud_header(fields=messages.field_changed("x", count=2**31)),
            "field 'x' (offset 0, 2147483648 x 4 bytes)",
        ),
        ("data-gone", messages.data_cut(keep=0), "data has 0 bytes, too few for"),
    ],
)
def test_hostile_headers_stop_cleanly_under_the_memory_limit(
    small_drive: Path, tmp_path: Path, case: str, edit: messages.Edit, says: str
) -> None:
    """Each scan's header claims what no memory holds: exit 2 naming the topic and the field,
    within the time limit, not a MemoryError or a kill."""
    bag = messages.rewrite_bag(small_drive, tmp_path / case, edit)
    t0 = time.perf_counter()
    result = _limited(["map", str(bag), "--out", str(tmp_path / "out"), "--no-plots"])
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith(f"error: {bag}: topic '/points': ") and "message 0" in lines[0], (
        lines[0]
    )
    assert says in lines[0], lines[0]
    assert time.perf_counter() - t0 < 60
