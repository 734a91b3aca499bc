"""PLY files read with numpy after the header is checked against the file.

Open3D's PLY reader trusts the header: a face element declared before the vertices but
shorter than declared gave uninitialised memory as coordinates, a lone ``nx`` gave garbage
normals, ``ushort`` properties were dropped. Here the header (text) is parsed, every element
before the vertices is located (lists included), the vertex rows that are present are read
(fewer than declared: an :class:`InputWarning`), and the properties become fields the way
Open3D names them: ``nx/ny/nz`` -> ``normals`` and ``red/green/blue`` -> ``colors`` (N, 3).
A list property of one length on every vertex becomes an (N, k) field.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import InputError
from canopy_kit.io.cloud_records import (
    ascii_rows,
    build_cloud,
    cast_column,
    group_columns,
    header_lines,
)

PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
ENCODINGS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
GROUPS = {"normals": ("nx", "ny", "nz"), "colors": ("red", "green", "blue")}


@dataclass(frozen=True)
class PlyProperty:
    """One property: its name and type; ``count`` is the length type of a list property."""

    name: str
    dtype: str
    count: str | None = None


@dataclass(frozen=True)
class PlyElement:
    """An element of the header: name, declared row count, properties in file order."""

    name: str
    rows: int
    properties: tuple[PlyProperty, ...]


@dataclass(frozen=True)
class PlyHeader:
    """A checked PLY header: encoding, elements in order, where the data start."""

    encoding: str
    elements: tuple[PlyElement, ...]
    data_start: int

    @property
    def vertex_index(self) -> int:
        """Position of the vertex element among the elements."""
        return next(i for i, e in enumerate(self.elements) if e.name == "vertex")

    @property
    def vertices(self) -> int:
        """Vertex rows the header declares."""
        return self.elements[self.vertex_index].rows


def _property(path: Path, words: list[str], number: int) -> PlyProperty:
    def dtype(word: str) -> str:
        if word not in PLY_TYPES:
            raise InputError(
                f"{path}: PLY header line {number}: unknown property type {word!r} "
                f"(types: {', '.join(PLY_TYPES)})"
            )
        return PLY_TYPES[word]

    if len(words) == 5 and words[1] == "list":
        count = dtype(words[2])
        if count[0] == "f":
            raise InputError(
                f"{path}: PLY header line {number}: list length type {words[2]!r} "
                "is not an integer type"
            )
        return PlyProperty(words[4], dtype(words[3]), count)
    if len(words) != 3 or words[1] == "list":
        raise InputError(f"{path}: PLY header line {number}: bad property line {' '.join(words)!r}")
    return PlyProperty(words[2], dtype(words[1]))


def read_ply_header(path: Path) -> PlyHeader:
    """Parse and check a PLY header; InputError naming the line or element that is wrong."""
    lines, data_start = header_lines(path, b"end_header", "PLY")
    if lines[0] != "ply":
        raise InputError(f"{path}: not a PLY file (first line is not 'ply')")
    encoding, elements = None, []
    for number, line in enumerate(lines[1:-1], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3 and words[1] in ENCODINGS:
            encoding = words[1]
        elif words[0] == "element" and len(words) == 3:
            if not words[2].isdigit():
                raise InputError(
                    f"{path}: PLY header line {number}: element {words[1]!r} count "
                    f"{words[2]!r} is not a non-negative integer"
                )
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property" and elements:
            elements[-1][2].append(_property(path, words, number))
        else:
            raise InputError(f"{path}: PLY header line {number}: unexpected {line[:60]!r}")
    if encoding is None:
        raise InputError(
            f"{path}: PLY header has no 'format ascii|binary_little_endian|"
            "binary_big_endian 1.0' line"
        )
    empty = [n for n, _, p in elements if not p]
    if empty:
        raise InputError(f"{path}: PLY element {empty[0]!r} has no properties")
    header = PlyHeader(
        encoding, tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements), data_start
    )
    _check_vertex(path, header)
    return header


def _check_vertex(path: Path, header: PlyHeader) -> None:
    vertex = [e for e in header.elements if e.name == "vertex"]
    if len(vertex) != 1:
        raise InputError(f"{path}: PLY file has {len(vertex)} 'vertex' elements, expected one")
    names = [p.name for p in vertex[0].properties]
    if len(set(names)) != len(names):
        raise InputError(f"{path}: PLY vertex element repeats a property name ({', '.join(names)})")
    scalars = {p.name for p in vertex[0].properties if p.count is None}
    missing = [c for c in "xyz" if c not in scalars]
    if missing:
        raise InputError(f"{path}: PLY vertex element has no {'/'.join(missing)} property")


def _uniform_rows(
    buf: np.ndarray, pos: int, element: PlyElement, order: str
) -> tuple[np.ndarray | None, bool]:
    """The rows present from ``pos`` as a structured array whose lists have the first row's
    lengths, and whether every row present really has those lengths; None when not even
    the first row is there."""
    fields: list[tuple] = []
    cursor = pos
    for prop in element.properties:
        if prop.count is None:
            fields.append((prop.name, order + prop.dtype))
            cursor += np.dtype(prop.dtype).itemsize
            continue
        size = np.dtype(prop.count).itemsize
        head = buf[cursor : cursor + size]
        if len(head) < size:
            return None, True
        length = int(head.view(order + prop.count)[0])
        if length < 0:
            return None, False
        fields += [
            (f"{prop.name}__length", order + prop.count),
            (prop.name, order + prop.dtype, (length,)),
        ]
        cursor += size + length * np.dtype(prop.dtype).itemsize
    if element.rows == 0 or cursor > len(buf):
        return None, True
    dtype = np.dtype(fields)
    present = min(element.rows, (len(buf) - pos) // dtype.itemsize)
    rows = buf[pos : pos + present * dtype.itemsize].view(dtype)
    uniform = all(
        np.all(rows[f"{p.name}__length"] == rows[f"{p.name}__length"][:1])
        for p in element.properties
        if p.count is not None
    )
    return rows, uniform


def _walk_rows(
    path: Path, buf: np.ndarray, pos: int, element: PlyElement, order: str
) -> tuple[int, int]:
    """Row by row through an element whose lists vary in length: (end byte, rows present)."""
    for row in range(element.rows):
        start = pos
        for prop in element.properties:
            if prop.count is None:
                pos += np.dtype(prop.dtype).itemsize
                continue
            size = np.dtype(prop.count).itemsize
            if pos + size > len(buf):
                return start, row
            length = int(buf[pos : pos + size].view(order + prop.count)[0])
            if length < 0:
                raise InputError(
                    f"{path}: PLY {element.name} {row}: list {prop.name!r} has length {length}"
                )
            pos += size + length * np.dtype(prop.dtype).itemsize
        if pos > len(buf):
            return start, row
    return pos, element.rows


def _shortest_row(element: PlyElement) -> int:
    """Bytes of a binary row whose lists are all empty."""
    return sum(np.dtype(p.count or p.dtype).itemsize for p in element.properties)


def _binary_vertices(path: Path, header: PlyHeader) -> tuple[np.ndarray | None, list[str]]:
    """The vertex rows present (structured array; None: not one) and a note when an element
    after them is cut short. InputError when the data before the vertices are."""
    order = ENCODINGS[header.encoding]
    with path.open("rb") as fh:
        fh.seek(header.data_start)
        buf = np.frombuffer(fh.read(), np.uint8)
    pos, vertices, notes = 0, None, []
    for index, element in enumerate(header.elements):
        rows, uniform = _uniform_rows(buf, pos, element, order)
        if index == header.vertex_index:
            if not uniform:
                raise InputError(
                    f"{path}: PLY vertex list property changes length from row to "
                    "row; only lists of one length are read"
                )
            if rows is None or len(rows) < element.rows:
                vertices = rows
                break
            vertices, pos = rows, pos + rows.nbytes
            continue
        if uniform:
            present = 0 if rows is None else len(rows)
            end = pos + (0 if rows is None else rows.nbytes)
        elif index < header.vertex_index:
            end, present = _walk_rows(path, buf, pos, element, order)
        else:  # after the vertices, only whether the shortest rows could fit (no Python walk)
            end, present = pos, min(element.rows, (len(buf) - pos) // _shortest_row(element))
        if present < element.rows:
            if index < header.vertex_index:
                raise InputError(
                    f"{path}: PLY file is truncated or corrupt: the {element.name!r} "
                    f"element before the vertices holds {present} of its "
                    f"{element.rows} rows"
                )
            notes.append(
                f"{path}: the {element.name!r} element after the vertices is cut short "
                f"({present} of {element.rows} rows); the vertices are complete"
            )
            break
        pos = end
    return vertices, notes


def _ascii_vertices(path: Path, header: PlyHeader) -> tuple[dict[str, np.ndarray], list[str]]:
    """Vertex columns of an ASCII body (one row per line; lists of one length), and a note
    when the lines end before the elements after the vertices do."""
    index = header.vertex_index
    vertex = header.elements[index]
    skip = sum(e.rows for e in header.elements[:index])
    lists = any(p.count for p in vertex.properties)
    width = _ascii_width(path, header, skip) if lists else len(vertex.properties)
    values, line_note = ascii_rows(path, header.data_start, skip, vertex.rows, width, "PLY vertex")
    columns, col = {}, 0
    for prop in vertex.properties:
        if prop.count is None:
            columns[prop.name] = cast_column(path, prop.name, values[:, col], prop.dtype)
            col += 1
            continue
        length = int(values[0, col]) if len(values) else 0
        if np.any(values[:, col] != length):
            raise InputError(
                f"{path}: PLY vertex list {prop.name!r} changes length from row to "
                "row; only lists of one length are read"
            )
        columns[prop.name] = cast_column(
            path, prop.name, values[:, col + 1 : col + 1 + length], prop.dtype
        )
        col += 1 + length
    notes = [line_note] if line_note else []
    declared = sum(e.rows for e in header.elements)
    if len(values) == vertex.rows and index < len(header.elements) - 1:
        found = _line_count(path, header.data_start)
        if found < declared:
            notes.append(
                f"{path}: the elements after the vertices are cut short ({found} of "
                f"{declared} data lines); the vertices are complete"
            )
    return columns, notes


def _ascii_width(path: Path, header: PlyHeader, skip: int) -> int:
    """Values on the first vertex line (lists make it differ from the property count)."""
    with path.open("rb") as fh:
        fh.seek(header.data_start)
        for number, line in enumerate(fh):
            if number == skip:
                return len(line.split())
    return len(header.elements[header.vertex_index].properties)


def _line_count(path: Path, start: int) -> int:
    with path.open("rb") as fh:
        fh.seek(start)
        body = fh.read()
    return body.count(b"\n")  # a last line without its line end may be cut: not counted


def _columns(vertices: np.ndarray, vertex: PlyElement) -> dict[str, np.ndarray]:
    out = {}
    for prop in vertex.properties:
        values = vertices[prop.name]
        out[prop.name] = values.astype(values.dtype.newbyteorder("="))
    return out


def read_ply(path: Path) -> PointCloud:
    """Read a checked PLY file's vertices: float64 xyz (local, with origin) and every
    property; fewer vertices than declared or non-finite ones give an InputWarning."""
    header = read_ply_header(path)
    vertex = header.elements[header.vertex_index]
    notes: list[str] = []
    if header.encoding == "ascii":
        columns, notes = _ascii_vertices(path, header)
    else:
        vertices, notes = _binary_vertices(path, header)
        if vertices is None:
            raise InputError(
                f"{path}: PLY file has no points"
                if vertex.rows == 0
                else f"{path}: PLY file is truncated: no complete vertex (header "
                f"declares {vertex.rows})"
            )
        columns = _columns(vertices, vertex)
    xyz = np.column_stack([columns.pop(c) for c in "xyz"]).astype(np.float64)
    return build_cloud(path, "PLY", xyz, group_columns(columns, GROUPS), header.vertices, notes)
