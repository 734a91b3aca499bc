"""Seeded damage to small valid point-cloud files, and the worker that reads each damaged
file under an address-space limit (tests/test_fuzz_readers.py).

A case is (id, bytes, suffix, cut): the valid seed file with header fields overwritten (0,
the type's largest value, a random value), cut at a byte position (inside the header, inside
a VLR, at a record boundary, inside a record, ...) or with random bytes changed. ``cut`` says
the file lost bytes: such a file must never read without a warning.

    python -m bad_inputs.fuzz CASES_DIR   # reads CASES_DIR/cases.json, prints one JSON line a case
"""

from __future__ import annotations

import io
import json
import math
import resource
import signal
import struct
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bad_inputs.clouds import (
    evlr_bytes,
    extra_bytes_vlr,
    grid_points,
    las_bytes,
    pcd_bytes,
    ply_bytes,
    vlr_bytes,
)

MEMORY_LIMIT = 1 << 30
CASE_SECONDS = 10


@dataclass(frozen=True)
class Case:
    """One damaged file."""

    id: str
    data: bytes
    suffix: str
    cut: bool = False


# -- seed files ---------------------------------------------------------------------------------


def las12() -> bytes:
    """LAS 1.2, point format 1, an extra-bytes dimension and a second VLR: 400 points."""
    vlrs = (vlr_bytes(b"canopy", 1, b"z" * 20), extra_bytes_vlr(b"h", 3))
    return las_bytes(
        grid_points(400, 1), offset=(300000.0, 4100000.0, 50.0), point_format=1, extra=2, vlrs=vlrs
    )


def las14() -> bytes:
    """LAS 1.4, point format 6, one VLR and one EVLR after the points: 400 points."""
    return las_bytes(
        grid_points(400, 2),
        minor=4,
        point_format=6,
        vlrs=(vlr_bytes(b"canopy", 1, b"z" * 20),),
        evlrs=(evlr_bytes(b"canopy", 2, b"e" * 30),),
    )


def laz12() -> bytes:
    """The LAS 1.2 seed compressed by laspy/lazrs (chunks of 50,000 points: one chunk)."""
    import laspy

    las = laspy.read(io.BytesIO(las12()))
    out = io.BytesIO()
    las.write(out, do_compress=True)
    return out.getvalue()


def ply_binary() -> bytes:
    """Binary PLY: triangles before the 300 vertices (float64 x, y, z, float32 q), more after."""
    xyz = grid_points(300, 3) * 0.01
    tris = (
        "face",
        4,
        "property list uchar int vertex_indices",
        struct.pack("<B3i", 3, 0, 1, 2) * 4,
    )
    edges = ("edge", 3, "property int vertex1\nproperty int vertex2", struct.pack("<2i", 0, 1) * 3)
    return ply_bytes(
        xyz, before=(tris,), after=(edges,), extra={"q": np.arange(300, dtype=np.float32)}
    )


def ply_ascii() -> bytes:
    """ASCII PLY of 200 vertices, then 3 faces."""
    faces = ("face", 3, "property list uchar int vertex_indices", b"3 0 1 2\n" * 3)
    return ply_bytes(grid_points(200, 4) * 0.01, "ascii", after=(faces,))


def pcd(encoding: str) -> bytes:
    """PCD v0.7 of 300 float32 points with intensity."""
    return pcd_bytes(grid_points(300, 5) * 0.01, encoding)


def pcd_open3d_compressed() -> bytes:
    """A binary_compressed PCD written by Open3D (real LZF back references)."""
    import tempfile

    import open3d as o3d

    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor((grid_points(300, 6) * 0.01).astype(np.float32))
    pc.point.intensity = o3d.core.Tensor(np.zeros((300, 1), np.float32))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.pcd"
        o3d.t.io.write_point_cloud(str(path), pc, compressed=True)
        return path.read_bytes()


# -- damage -------------------------------------------------------------------------------------

FORMAT_MAX = {
    "B": 0xFF,
    "H": 0xFFFF,
    "I": 0xFFFFFFFF,
    "Q": 2**64 - 1,
    "q": 2**63 - 1,
    "d": float("inf"),
}


def _values(fmt: str, rng: np.random.Generator) -> list:
    if fmt == "d":
        return [0.0, 1e308, float("nan"), float(rng.normal() * 10.0 ** rng.integers(-320, 300))]
    random = (
        int(rng.integers(0, FORMAT_MAX[fmt], dtype=np.uint64))
        if fmt != "q"
        else int(rng.integers(-(2**62), 2**62))
    )
    return [0, FORMAT_MAX[fmt], random]


def field_cases(
    name: str,
    data: bytes,
    fields: dict[str, tuple[int, str]],
    suffix: str,
    rng: np.random.Generator,
) -> list[Case]:
    """Each binary header field set to 0, its type's maximum and a random value."""
    out = []
    for field, (offset, fmt) in fields.items():
        for i, value in enumerate(_values(fmt, rng)):
            raw = bytearray(data)
            struct.pack_into("<" + fmt, raw, offset, value)
            out.append(Case(f"{name}-field-{field}-{i}", bytes(raw), suffix))
    return out


def cut_cases(name: str, data: bytes, positions: list[int], suffix: str) -> list[Case]:
    """The file cut at each position (bytes kept)."""
    keep = sorted({p for p in positions if 0 < p < len(data)})
    return [Case(f"{name}-cut-{p}", data[:p], suffix, cut=True) for p in keep]


def flip_cases(
    name: str, data: bytes, suffix: str, rng: np.random.Generator, n: int = 40, head: int = 400
) -> list[Case]:
    """Up to 8 random bytes overwritten; half the cases only in the first ``head`` bytes."""
    out = []
    for i in range(n):
        raw = bytearray(data)
        span = min(head, len(data)) if i % 2 else len(data)
        for offset in rng.integers(0, span, int(rng.integers(1, 9))):
            raw[int(offset)] = int(rng.integers(0, 256))
        out.append(Case(f"{name}-flip-{i}", bytes(raw), suffix))
    return out


def token_cases(
    name: str, data: bytes, end: bytes, suffix: str, rng: np.random.Generator, most: int = 24
) -> list[Case]:
    """Up to ``most`` words of a text header (before the ``end`` line; numbers always) each
    replaced by 0, a huge number and, for a number, a random one, else a type name."""
    head_end = data.index(end)
    head, body = data[:head_end], data[head_end:]
    words = [(i, pos, w) for i, (pos, w) in enumerate(_words(head)) if i > 0]  # not the magic
    numbers = [w for w in words if w[2].lstrip(b"-").isdigit()]
    others = [w for w in words if w not in numbers]
    picked = numbers + [
        others[i] for i in rng.permutation(len(others))[: max(0, most - len(numbers))]
    ]
    out = []
    for index, pos, word in sorted(picked):
        last = (
            str(int(rng.integers(0, 10**6))).encode()
            if word in (w for *_, w in numbers)
            else b"uchar"
        )
        for j, new in enumerate([b"0", b"18446744073709551616", last]):
            raw = head[:pos] + new + head[pos + len(word) :] + body
            out.append(Case(f"{name}-token-{index}-{j}", raw, suffix))
    return out


def _words(head: bytes) -> list[tuple[int, bytes]]:
    out, pos = [], 0
    for word in head.split():
        pos = head.index(word, pos)
        out.append((pos, word))
        pos += len(word)
    return out


def las_cases(rng: np.random.Generator) -> list[Case]:
    """LAS 1.2 and 1.4 seeds: every header field, the VLRs, cuts and flips."""
    out = []
    header = {
        "file_source": (4, "H"),
        "global_encoding": (6, "H"),
        "guid": (8, "I"),
        "version_major": (24, "B"),
        "version_minor": (25, "B"),
        "system": (26, "Q"),
        "creation_day": (90, "H"),
        "creation_year": (92, "H"),
        "header_size": (94, "H"),
        "offset_to_points": (96, "I"),
        "n_vlrs": (100, "I"),
        "point_format": (104, "B"),
        "record_length": (105, "H"),
        "legacy_count": (107, "I"),
        "by_return": (111, "I"),
        **{f"scale_{a}": (131 + 8 * i, "d") for i, a in enumerate("xyz")},
        **{f"offset_{a}": (155 + 8 * i, "d") for i, a in enumerate("xyz")},
        **{f"bound_{i}": (179 + 8 * i, "d") for i in range(6)},
    }
    data = las12()
    vlr0, vlr1 = 227, 227 + 54 + 20
    fields = {
        **header,
        "vlr0_record": (vlr0 + 18, "H"),
        "vlr0_length": (vlr0 + 20, "H"),
        "vlr1_length": (vlr1 + 20, "H"),
        "extra_type": (vlr1 + 54 + 2, "B"),
        "extra_options": (vlr1 + 54 + 3, "B"),
    }
    out += field_cases("las12", data, fields, ".las", rng)
    offset, record = struct.unpack_from("<I", data, 96)[0], 30
    cuts = [
        1,
        4,
        100,
        226,
        227,
        vlr0 + 10,
        vlr0 + 54,
        vlr1 + 100,
        offset,
        offset + 1,
        offset + record,
        offset + record // 2,
        offset + 200 * record,
        offset + 200 * record + 7,
        offset + 399 * record,
        len(data) - 1,
        *rng.integers(offset, len(data), 8).tolist(),
    ]
    out += cut_cases("las12", data, cuts, ".las")
    out += flip_cases("las12", data, ".las", rng)
    data = las14()
    fields = {
        **header,
        "evlr_start": (235, "Q"),
        "n_evlrs": (243, "I"),
        "count": (247, "Q"),
        "vlr0_length": (375 + 20, "H"),
    }
    out += field_cases("las14", data, fields, ".las", rng)
    evlr = len(data) - 90
    cuts = [
        300,
        374,
        375 + 30,
        449,
        449 + 30 * 100,
        449 + 30 * 100 + 3,
        evlr,
        evlr + 20,
        len(data) - 1,
        *rng.integers(449, len(data), 6).tolist(),
    ]
    out += cut_cases("las14", data, cuts, ".las")
    out += flip_cases("las14", data, ".las", rng)
    return out


def laz_cases(rng: np.random.Generator) -> list[Case]:
    """The LAZ seed: header fields, the LASzip record, the chunk table, cuts and flips."""
    data = laz12()
    offset = struct.unpack_from("<I", data, 96)[0]
    n_vlrs = struct.unpack_from("<I", data, 100)[0]
    pos, laszip = 227, None
    for _ in range(n_vlrs):
        if data[pos + 2 : pos + 16].startswith(b"laszip encoded"):
            laszip = pos + 54
        pos += 54 + struct.unpack_from("<H", data, pos + 20)[0]
    table = struct.unpack_from("<q", data, offset)[0]
    fields = {
        "offset_to_points": (96, "I"),
        "n_vlrs": (100, "I"),
        "point_format": (104, "B"),
        "record_length": (105, "H"),
        "count": (107, "I"),
        "scale_y": (139, "d"),
        "laszip_compressor": (laszip, "H"),
        "laszip_chunk_size": (laszip + 12, "I"),
        "laszip_items": (laszip + 32, "H"),
        "laszip_item0_size": (laszip + 36, "H"),
        "chunk_table_offset": (offset, "q"),
        "chunk_table_version": (table, "I"),
        "chunk_count": (table + 4, "I"),
    }
    out = field_cases("laz", data, fields, ".laz", rng)
    cuts = [
        200,
        offset,
        offset + 4,
        offset + 8,
        offset + 100,
        (offset + table) // 2,
        table,
        table + 4,
        table + 8,
        len(data) - 1,
        *rng.integers(offset, len(data), 6).tolist(),
    ]
    out += cut_cases("laz", data, cuts, ".laz")
    out += flip_cases("laz", data, ".laz", rng)
    return out


def text_cases(
    name: str, data: bytes, end: bytes, suffix: str, rng: np.random.Generator, record: int | None
) -> list[Case]:
    """Header words, cuts (header, data start, record boundaries and inside) and flips."""
    start = data.index(end) + data[data.index(end) :].index(b"\n") + 1
    cuts = [
        10,
        start - 5,
        start - 1,
        start,
        start + 1,
        len(data) - 1,
        len(data) - 2,
        *rng.integers(start, len(data), 8).tolist(),
    ]
    if record:
        cuts += [start + record * k for k in (1, 50, 100)] + [start + record * 50 + 3]
    return (
        token_cases(name, data, end, suffix, rng)
        + cut_cases(name, data, cuts, suffix)
        + flip_cases(name, data, suffix, rng, head=start)
    )


def ply_pcd_cases(rng: np.random.Generator, with_open3d: bool = True) -> list[Case]:
    """PLY (binary, ascii) and PCD (ascii, binary, binary_compressed) seeds."""
    out = text_cases("ply-binary", ply_binary(), b"end_header", ".ply", rng, None)
    out += text_cases("ply-ascii", ply_ascii(), b"end_header", ".ply", rng, None)
    for encoding in ("ascii", "binary", "binary_compressed"):
        out += text_cases(
            f"pcd-{encoding}",
            pcd(encoding),
            b"DATA",
            ".pcd",
            rng,
            16 if encoding == "binary" else None,
        )
    if with_open3d:
        data = pcd_open3d_compressed()
        out += cut_cases("pcd-open3d", data, rng.integers(0, len(data), 6).tolist(), ".pcd")
        out += flip_cases("pcd-open3d", data, ".pcd", rng, n=10, head=len(data))
    return out


# -- the worker ---------------------------------------------------------------------------------


def _outcome(call, path: Path) -> dict:
    """What one read gives: 'ok' with finite bounds and warnings, 'input_error' with its
    message, or 'other' with the exception (a bug)."""
    from canopy_kit.errors import InputError, InputWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            lo, hi, notes = call(path)
        except InputError as exc:
            return {"outcome": "input_error", "message": str(exc)}
        except Exception as exc:
            return {"outcome": "other", "message": f"{type(exc).__name__}: {exc}"[:500]}
    notes = list(notes) + [str(w.message) for w in caught if issubclass(w.category, InputWarning)]
    finite = bool(all(math.isfinite(v) for v in [*lo, *hi]))
    return {"outcome": "ok", "finite": finite, "warnings": notes}


def _describe(path: Path) -> tuple[list, list, list]:
    from canopy_kit.io.info import describe_path

    facts = describe_path(path)
    return facts["bounds"]["min"], facts["bounds"]["max"], facts.get("warnings", [])


def _read(path: Path) -> tuple[list, list, list]:
    from canopy_kit.io.clouds import read_cloud

    cloud = read_cloud(path)
    lo, hi = cloud.absolute_xyz.min(axis=0), cloud.absolute_xyz.max(axis=0)
    return lo.tolist(), hi.tolist(), []


def _peak_rss_kib() -> int:
    """This process's own peak resident set (VmHWM). Not ``ru_maxrss``: Linux carries the
    parent's high-water mark across fork and exec, so a worker spawned by a large pytest
    process would report the parent's size."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def _alarm(signum, frame):
    raise TimeoutError(f"over {CASE_SECONDS} s")


def main(folder: Path) -> None:
    """Read every case file of ``folder`` twice (info's describe_path, read_cloud) within
    1 GiB of address space and 10 s a case; one JSON line a case."""
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    signal.signal(signal.SIGALRM, _alarm)
    import functools

    from canopy_kit import plugins
    from canopy_kit.io.lzf import lzf_decompress

    # Finding the reader plugins scans the installed packages' metadata (about 60 ms a file);
    # that is not under test and the packages do not change while the worker runs.
    plugins.entry_points = functools.cache(plugins.entry_points)
    lzf_decompress(b"\x00a", 1)  # compile (or load) the LZF kernel before the clock runs
    for entry in json.loads((folder / "cases.json").read_text()):
        path = folder / entry["file"]
        start = time.perf_counter()
        signal.alarm(CASE_SECONDS)
        try:
            result = {"describe": _outcome(_describe, path), "read": _outcome(_read, path)}
        except TimeoutError as exc:
            result = {"describe": {"outcome": "other", "message": str(exc)}, "read": {}}
        finally:
            signal.alarm(0)
        result.update(id=entry["id"], seconds=time.perf_counter() - start, peak_kib=_peak_rss_kib())
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
