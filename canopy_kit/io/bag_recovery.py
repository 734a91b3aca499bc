"""Read what is left of a damaged bag, in file order, up to the first incomplete record.

rosbags opens a bag through its index or summary, which a recorder writes last: a ROS1
bag cut short (power lost, disk full) has none (``index_pos`` 0 or past the end), an MCAP
file has no footer, and a sqlite3 file cut short has a header promising pages that are
gone. :func:`recover_bag` reads such files record by record instead and keeps every
complete message before the damage: ROS1 chunks (uncompressed, bz2, lz4), MCAP records
(chunked or not) and sqlite3 rows (through a read-only view whose header matches the
pages actually present). :class:`RecoveredBag` offers the part of rosbags' ``AnyReader``
that :mod:`canopy_kit.io.bag` uses, with messages in file order (recording order).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from canopy_kit.errors import InputError

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
_OP_MSGDATA, _OP_CHUNK, _OP_CONNECTION = 2, 5, 7


@dataclass
class _Message:
    conn: int
    time: int  # ns
    block: int  # index of the chunk holding it, or -1: ``start`` is a file offset
    start: int
    size: int


@dataclass
class _Block:
    """A (ROS1 or MCAP) chunk: where its possibly compressed bytes lie and how many are present."""

    pos: int
    size: int
    compression: str
    complete: bool


def _inflate(compression: str, raw: bytes, complete: bool) -> bytes:
    """Decompressed chunk bytes; of a chunk cut short, as much as its beginning gives."""
    if compression in ("", "none"):
        return raw
    if compression == "bz2":
        import bz2

        return bz2.decompress(raw) if complete else bz2.BZ2Decompressor().decompress(raw)
    if compression == "lz4":
        import lz4.frame

        return (
            lz4.frame.decompress(raw)
            if complete
            else lz4.frame.LZ4FrameDecompressor().decompress(raw)
        )
    if compression == "zstd":
        try:
            from compression import zstd  # type: ignore[import-not-found]  # Python 3.14
        except ImportError:
            from backports import zstd  # type: ignore[no-redef]

        return zstd.ZstdDecompressor().decompress(raw)
    raise ValueError(f"unknown chunk compression {compression!r}")


def _block_messages(
    path: Path, blocks: list[_Block], messages: list[_Message], wanted: dict[int, Any]
) -> Iterator[tuple[Any, int, bytes]]:
    current, body = -2, b""
    with path.open("rb") as fh:
        for m in messages:
            if m.conn not in wanted:
                continue
            if m.block < 0:
                fh.seek(m.start)
                yield wanted[m.conn], m.time, fh.read(m.size)
                continue
            if m.block != current:
                block = blocks[m.block]
                fh.seek(block.pos)
                body = _inflate(block.compression, fh.read(block.size), block.complete)
                current = m.block
            yield wanted[m.conn], m.time, body[m.start : m.start + m.size]


class RecoveredBag:
    """Complete messages of a damaged bag (the reader subset of rosbags' ``AnyReader``)."""

    def __init__(
        self,
        path: Path,
        kind: str,
        connections: list[Any],
        times: tuple[int, int, int],
        stopped: str,
        source: Any,
        messages: list[_Message] | None = None,
    ) -> None:
        self.path = path
        self.kind = kind
        self.connections = connections
        self._messages = messages
        self._source = source  # per-format reader state
        self.ros1 = kind == "ros1"
        self.typestore = _typestore(connections, self.ros1)
        self.stopped = stopped  # where and why reading stopped
        self.message_count, self.start_time, self.end_time = times

    def messages(self, connections: Iterable[Any] = ()) -> Iterator[tuple[Any, int, bytes]]:
        """``(connection, timestamp_ns, raw)`` of the wanted connections, in file order."""
        wanted = {c.id: c for c in (connections or self.connections)}
        if self.kind == "sqlite3":
            yield from self._source.messages(wanted)
        else:
            yield from _block_messages(self.path, self._source, self._messages, wanted)

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        if self.ros1:
            return self.typestore.deserialize_ros1(raw, msgtype)
        return self.typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        if self._source is not None and hasattr(self._source, "close"):
            self._source.close()


def storage_file(path: Path) -> Path | None:
    """The file holding a bag's messages: the ``.bag`` itself or a ROS2 folder's storage file."""
    if path.is_file():
        return path
    files = sorted(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    return files[0] if files else None


def recover_bag(path: str | Path) -> RecoveredBag:
    """Open a damaged bag by reading its records in order; InputError when none is usable."""
    path = Path(path)
    storage = storage_file(path)
    if storage is None:
        raise InputError(f"{path}: no .db3 or .mcap storage file in the bag folder")
    with storage.open("rb") as fh:
        head = fh.read(16)
    if head.startswith(ROS1_MAGIC[:12]):
        bag = _recover_ros1(storage)
    elif head.startswith(MCAP_MAGIC):
        bag = _recover_mcap(storage)
    elif head.startswith(SQLITE_MAGIC):
        bag = _recover_sqlite(storage)
    else:
        raise InputError(f"{storage}: unknown bag storage (starts with {head[:8]!r})")
    if bag.message_count == 0:
        bag.close()
        raise InputError(f"{storage}: no complete message could be read ({bag.stopped})")
    return bag


def _typestore(connections: list[Any], ros1: bool) -> Any:
    """Types from the bag's own message definitions, else the default ROS1/ROS2 store."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    default = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types: dict = {}
    try:
        for c in connections:
            if c.msgdef.format == MessageDefinitionFormat.MSG and c.msgdef.data:
                types.update(get_types_from_msg(c.msgdef.data, c.msgtype))
            elif c.msgdef.format == MessageDefinitionFormat.IDL and c.msgdef.data:
                types.update(get_types_from_idl(c.msgdef.data))
    except Exception:  # a damaged or odd definition: the standard types will do
        return default
    if not types:
        return default
    store = get_typestore(Stores.EMPTY)
    store.register({**default.fielddefs, **types})
    return store


# -- ROS1 ------------------------------------------------------------------------------------
def _ros1_header(blob: bytes) -> dict[str, bytes]:
    fields, pos = {}, 0
    while pos + 4 <= len(blob):
        (size,) = struct.unpack_from("<I", blob, pos)
        pos += 4
        if pos + size > len(blob):
            raise ValueError("header field runs past the header")
        name, sep, value = blob[pos : pos + size].partition(b"=")
        if not sep:
            raise ValueError("header field without '='")
        fields[name.decode(errors="replace")] = value
        pos += size
    return fields


def _ros1_records(data: bytes, start: int = 0) -> Iterator[tuple[dict[str, bytes], int, int]]:
    """``(header, data_start, data_size)`` of each complete record of ``data``."""
    pos = start
    while pos + 4 <= len(data):
        (hlen,) = struct.unpack_from("<I", data, pos)
        if pos + 4 + hlen + 4 > len(data):
            return
        header = _ros1_header(data[pos + 4 : pos + 4 + hlen])
        (dlen,) = struct.unpack_from("<I", data, pos + 4 + hlen)
        begin = pos + 8 + hlen
        if begin + dlen > len(data):
            return
        yield header, begin, dlen
        pos = begin + dlen


def _recover_ros1(path: Path) -> RecoveredBag:
    conns: dict[int, Any] = {}
    chunks: list[_Block] = []
    messages: list[_Message] = []
    size = path.stat().st_size
    stopped = f"read to the end of the file ({size} bytes)"
    with path.open("rb") as fh:
        pos = len(ROS1_MAGIC)
        fh.seek(pos)
        while True:
            head = fh.read(4)
            if len(head) < 4:
                break
            (hlen,) = struct.unpack("<I", head)
            blob = fh.read(hlen)
            dlen_raw = fh.read(4)
            if len(blob) < hlen or len(dlen_raw) < 4:
                stopped = f"the file ends inside a record header at byte {pos} of {size}"
                break
            (dlen,) = struct.unpack("<I", dlen_raw)
            data_pos = fh.tell()
            present = min(dlen, size - data_pos)
            try:
                _read_ros1_record(fh, blob, data_pos, present, dlen, conns, chunks, messages)
            except (
                ValueError,
                KeyError,
                IndexError,
                struct.error,
                OSError,
                EOFError,
                RuntimeError,
            ) as exc:
                stopped = f"damaged record at byte {pos} of {size} ({type(exc).__name__}: {exc})"
                break
            if present < dlen:
                stopped = f"the file ends inside a record at byte {pos} of {size}"
                break
            pos = data_pos + dlen
            fh.seek(pos)
    messages = [m for m in messages if m.conn in conns]
    counts: dict[int, int] = {}
    for m in messages:
        counts[m.conn] = counts.get(m.conn, 0) + 1
    connections = [c._replace(msgcount=counts.get(c.id, 0)) for c in conns.values()]
    stamps = [m.time for m in messages]
    times = (len(stamps), min(stamps, default=0), max(stamps, default=-1) + 1)
    return RecoveredBag(path, "ros1", connections, times, stopped, chunks, messages)


def _read_ros1_record(
    fh: BinaryIO,
    blob: bytes,
    data_pos: int,
    present: int,
    dlen: int,
    conns: dict[int, Any],
    chunks: list[_Block],
    messages: list[_Message],
) -> None:
    """One top-level record (header ``blob``, ``present`` of its ``dlen`` data bytes at
    ``data_pos``): a chunk's connections and messages, or a connection, added to ``conns``,
    ``chunks`` and ``messages``; other records are skipped."""
    header = _ros1_header(blob)
    op = header["op"][0]
    if op == _OP_CHUNK:
        compression = header.get("compression", b"none").decode()
        body = _inflate(compression, fh.read(present), present == dlen)
        chunks.append(_Block(data_pos, present, compression, present == dlen))
        for inner, begin, length in _ros1_records(body):
            inner_op = inner["op"][0]
            if inner_op == _OP_CONNECTION:
                _add_ros1_connection(conns, inner, body[begin : begin + length])
            elif inner_op == _OP_MSGDATA:
                sec, nsec = struct.unpack("<II", inner["time"])
                cid = struct.unpack("<I", inner["conn"])[0]
                messages.append(_Message(cid, sec * 10**9 + nsec, len(chunks) - 1, begin, length))
    elif op == _OP_CONNECTION and present == dlen:
        _add_ros1_connection(conns, header, fh.read(dlen))


def _add_ros1_connection(conns: dict[int, Any], header: dict[str, bytes], body: bytes) -> None:
    """The connection a connection record describes, unless its id is known already."""
    from rosbags.interfaces import (
        Connection,
        ConnectionExtRosbag1,
        MessageDefinition,
        MessageDefinitionFormat,
    )
    from rosbags.typesys.msg import normalize_msgtype

    cid = struct.unpack("<I", header["conn"])[0]
    if cid in conns:
        return
    info = _ros1_header(body)
    msgtype = normalize_msgtype(info["type"].decode())
    msgdef = MessageDefinition(
        MessageDefinitionFormat.MSG, info.get("message_definition", b"").decode()
    )
    conns[cid] = Connection(
        cid,
        header["topic"].decode(),
        msgtype,
        msgdef,
        info.get("md5sum", b"").decode(),
        0,
        ConnectionExtRosbag1(None, None),
        None,
    )


# -- MCAP ------------------------------------------------------------------------------------
def _mcap_records(data: bytes, pos: int = 0) -> Iterator[tuple[int, int, int]]:
    """``(op, content_start, content_size)`` of each complete MCAP record in ``data``."""
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if pos + 9 + length > len(data):
            return
        yield op, pos + 9, length
        pos += 9 + length


def _mcap_string(data: bytes, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", data, pos)
    if pos + 4 + n > len(data):
        raise ValueError("string runs past its record")
    return data[pos + 4 : pos + 4 + n].decode(), pos + 4 + n


class _McapScan:
    """Schemas, channels and message locations met while walking MCAP records."""

    def __init__(self) -> None:
        self.schemas: dict[int, Any] = {}
        self.channels: dict[int, tuple[str, int, str]] = {}  # id -> topic, schema id, encoding
        self.messages: list[_Message] = []

    def record(self, op: int, data: bytes, start: int, size: int, block: int, base: int) -> None:
        from rosbags.rosbag2.storage_mcap import Schema

        if op == 0x03:
            (sid,) = struct.unpack_from("<H", data, start)
            name, pos = _mcap_string(data, start + 2)
            encoding, pos = _mcap_string(data, pos)
            (n,) = struct.unpack_from("<I", data, pos)
            self.schemas[sid] = Schema(sid, name, encoding, data[pos + 4 : pos + 4 + n].decode())
        elif op == 0x04:
            cid, sid = struct.unpack_from("<HH", data, start)
            topic, pos = _mcap_string(data, start + 4)
            encoding, _ = _mcap_string(data, pos)
            self.channels[cid] = (topic, sid, encoding)
        elif op == 0x05:
            cid, _, log_time = struct.unpack_from("<HIQ", data, start)
            self.messages.append(_Message(cid, log_time, block, base + start + 22, size - 22))


def _recover_mcap(path: Path) -> RecoveredBag:
    from rosbags.interfaces import Connection, ConnectionExtRosbag2
    from rosbags.rosbag2.storage_mcap import get_msgdef

    size = path.stat().st_size
    scan, blocks = _McapScan(), []
    stopped = f"read to the end of the data ({size} bytes)"
    with path.open("rb") as fh:
        fh.seek(len(MCAP_MAGIC))
        pos = len(MCAP_MAGIC)
        while True:
            head = fh.read(9)
            if len(head) < 9:
                break
            op = head[0]
            (length,) = struct.unpack_from("<Q", head, 1)
            if op in (0x02, 0x0F):  # footer or data end: the summary is no use without the rest
                stopped = "read the whole data section"
                break
            if op == 0 or op > 0x0F:
                stopped = f"unreadable record at byte {pos} of {size}"
                break
            present = min(length, size - pos - 9)
            try:
                if op == 0x06:
                    header = fh.read(min(present, 4096))
                    compression, after = _mcap_string(header, 28)
                    (records,) = struct.unpack_from("<Q", header, after)
                    begin = pos + 9 + after + 8
                    available = min(records, size - begin)
                    fh.seek(begin)
                    raw = fh.read(available)
                    body = _inflate(compression, raw, available == records)
                    blocks.append(_Block(begin, available, compression, available == records))
                    for inner, start, n in _mcap_records(body):
                        scan.record(inner, body, start, n, len(blocks) - 1, 0)
                elif present == length:
                    body = fh.read(length)
                    scan.record(op, body, 0, length, -1, pos + 9)
            except (ValueError, struct.error, OSError, EOFError, RuntimeError) as exc:
                stopped = f"damaged record at byte {pos} of {size} ({type(exc).__name__}: {exc})"
                break
            if present < length:
                stopped = f"the file ends inside a record at byte {pos} of {size}"
                break
            pos += 9 + length
            fh.seek(pos)
    messages = [m for m in scan.messages if m.conn in scan.channels]
    counts: dict[int, int] = {}
    for m in messages:
        counts[m.conn] = counts.get(m.conn, 0) + 1
    connections = []
    for cid, (topic, sid, encoding) in scan.channels.items():
        schema = scan.schemas.get(sid)
        connections.append(
            Connection(
                cid,
                topic,
                schema.name if schema else "",
                get_msgdef(schema),
                "",
                counts.get(cid, 0),
                ConnectionExtRosbag2(encoding, []),
                None,
            )
        )
    stamps = [m.time for m in messages]
    times = (len(stamps), min(stamps, default=0), max(stamps, default=-1) + 1)
    return RecoveredBag(path, "mcap", connections, times, stopped, blocks, messages)


# -- sqlite3 ---------------------------------------------------------------------------------
def sqlite_cut_short(path: Path) -> bool:
    """Whether a sqlite3 bag file holds fewer pages than its header counts (cut short).

    rosbags can open such a file when the tables' first pages survive, then fails halfway
    through the messages; it is read record by record from the start instead.
    """
    storage = storage_file(path)
    if storage is None or storage.suffix != ".db3":
        return False
    with storage.open("rb") as fh:
        header = fh.read(100)
    if len(header) < 100 or not header.startswith(SQLITE_MAGIC) or header[24:28] != header[92:96]:
        return False  # no trustworthy page count in the header
    page = struct.unpack(">H", header[16:18])[0]
    page = 65536 if page == 1 else page
    return storage.stat().st_size < struct.unpack(">I", header[28:32])[0] * page


def _sqlite_vfs(path: Path, name: str) -> Any:
    """A read-only apsw VFS showing ``path`` cut to whole pages, its header page count fixed.

    SQLite treats a file shorter than the page count in its header as malformed before
    reading anything; with the count matching the file, every intact page stays readable.
    """
    import apsw

    size = path.stat().st_size
    with path.open("rb") as fh:
        header = bytearray(fh.read(100))
    page = struct.unpack(">H", header[16:18])[0]
    page = 65536 if page == 1 else page
    pages = size // page if page else 0
    header[28:32] = struct.pack(">I", pages)
    length = pages * page

    class File(apsw.VFSFile):  # type: ignore[misc]
        def __init__(self, *_: object) -> None:
            self._fh = path.open("rb")

        def xRead(self, amount: int, offset: int) -> bytes:
            if offset >= length:
                return b""
            self._fh.seek(offset)
            data = bytearray(self._fh.read(min(amount, length - offset)))
            if offset < 100:
                end = min(100, offset + len(data))
                data[: end - offset] = header[offset:end]
            return bytes(data)

        def xFileSize(self) -> int:
            return length

        def xClose(self) -> None:
            self._fh.close()

        def xDeviceCharacteristics(self) -> int:
            return 0

        def xSectorSize(self) -> int:
            return 0

        def xFileControl(self, op: int, ptr: int) -> bool:
            return False

        def xLock(self, level: int) -> None:
            return None

        def xUnlock(self, level: int) -> None:
            return None

        def xCheckReservedLock(self) -> bool:
            return False

    class Vfs(apsw.VFS):  # type: ignore[misc]
        def __init__(self) -> None:
            super().__init__(name, "")

        def xOpen(self, fname: Any, flags: Any) -> Any:
            return File()

    return Vfs()


class _SqliteSource:
    def __init__(self, path: Path) -> None:
        import apsw

        self.name = f"canopy_kit_recover_{os.getpid()}_{id(self)}"
        self.vfs = _sqlite_vfs(path, self.name)
        self.db = apsw.Connection(
            f"file:{path}?immutable=1",
            vfs=self.name,
            flags=apsw.SQLITE_OPEN_READONLY | apsw.SQLITE_OPEN_URI,
        )
        self.last_row = 0
        self.conns: dict[int, Any] = {}

    def messages(self, wanted: dict[int, Any]) -> Iterator[tuple[Any, int, bytes]]:
        import apsw

        cursor = self.db.cursor()
        try:
            for _rowid, topic_id, timestamp, data in cursor.execute(
                "SELECT id, topic_id, timestamp, data FROM messages WHERE id <= ? ORDER BY id",
                (self.last_row,),
            ):
                if topic_id in wanted:
                    yield wanted[topic_id], int(timestamp), bytes(data)
        except apsw.Error:
            return  # the damage found when the bag was opened: the rows before it are done

    def close(self) -> None:
        self.db.close()
        self.vfs.unregister()


def _recover_sqlite(path: Path) -> RecoveredBag:
    import apsw
    from rosbags.interfaces import (
        Connection,
        ConnectionExtRosbag2,
        MessageDefinition,
        MessageDefinitionFormat,
    )

    try:
        source = _SqliteSource(path)
    except (apsw.Error, OSError, struct.error) as exc:
        raise InputError(f"{path}: damaged sqlite3 bag cannot be opened ({exc})") from None
    try:
        topics = source.db.execute(
            "SELECT id, name, type, serialization_format FROM topics"
        ).fetchall()
    except apsw.Error as exc:
        source.close()
        raise InputError(
            f"{path}: the topics table of the damaged sqlite3 bag is unreadable ({exc})"
        ) from None
    stopped = "read every row of the messages table"
    counts: dict[int, int] = {}
    first, last = None, -1
    try:  # the data too: a row is usable only when its overflow pages are present
        for rowid, topic_id, timestamp, _ in source.db.execute(
            "SELECT id, topic_id, timestamp, data FROM messages ORDER BY id"
        ):
            counts[topic_id] = counts.get(topic_id, 0) + 1
            first = timestamp if first is None else min(first, timestamp)
            last = max(last, timestamp)
            source.last_row = rowid
    except apsw.Error as exc:
        stopped = f"rows after message {source.last_row} are unreadable ({exc})"
    connections = [
        Connection(
            tid,
            name,
            typ,
            MessageDefinition(MessageDefinitionFormat.NONE, ""),
            "",
            counts.get(tid, 0),
            ConnectionExtRosbag2(fmt, []),
            None,
        )
        for tid, name, typ, fmt in topics
    ]
    times = (sum(counts.values()), int(first or 0), int(last) + 1)
    return RecoveredBag(path, "sqlite3", connections, times, stopped, source)
