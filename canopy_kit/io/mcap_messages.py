"""Raw messages of a ROS2 MCAP bag through the ``mcap`` library, for speed.

rosbags' MCAP storage parses every record of a chunk in Python and copies each message
three times: 6.5 s per pass over the scans and IMU of a 5.5 GB 128-ring bag, against 1.4 s
through ``mcap``'s reader (docs/history/BENCHMARKS_LOG.md). :func:`fast_mcap_reader` wraps an open
rosbags ``AnyReader`` so that its ``messages`` come from ``mcap`` while everything else
(connections, types, deserialisation) stays rosbags'. It does so only where both read the
same bytes in the same order: one uncompressed-message ROS2 bag of a single indexed
``.mcap`` file; anything else keeps rosbags' reader.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any


class FastMcapReader:
    """An open rosbags ``AnyReader`` whose ``messages`` are read by ``mcap``'s indexed reader.

    Messages come in log-time order, ties in file order, as rosbags gives them; chunk CRCs
    are checked where the file has them, as rosbags does.
    """

    def __init__(self, reader: Any, mcap_path: Path, stream: Any, mcap_reader: Any) -> None:
        self._reader = reader
        self.mcap_path = mcap_path
        self._stream = stream
        self._mcap = mcap_reader
        self._summary = mcap_reader.get_summary()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._reader, name)

    def messages(
        self,
        connections: Collection[Any] = (),
        start: int | None = None,
        stop: int | None = None,
    ) -> Iterator[tuple[Any, int, bytes]]:
        """(connection, log time in ns, raw CDR bytes) of ``connections`` (all when empty) with
        ``start <= log time < stop``, like rosbags' ``AnyReader.messages``."""
        wanted = list(connections) or list(self._reader.connections)
        by_channel: dict[int, Any] = {}
        for channel_id, channel in self._summary.channels.items():
            schema = self._summary.schemas.get(channel.schema_id)
            for conn in wanted:
                if conn.topic == channel.topic and (schema is None or schema.name == conn.msgtype):
                    by_channel[channel_id] = conn
                    break
        if not by_channel:
            return
        topics = sorted({c.topic for c in by_channel.values()})
        for _, channel, message in self._mcap.iter_messages(
            topics=topics, starting_at=start, ending_before=stop, log_time_order=True
        ):
            conn = by_channel.get(channel.id)
            if conn is not None:
                yield conn, message.log_time, message.data

    def close(self) -> None:
        """Close the ``mcap`` stream and the wrapped reader."""
        self._stream.close()
        self._reader.close()


def fast_mcap_reader(reader: Any, target: Path) -> Any:
    """``reader`` (an open rosbags ``AnyReader`` of ``target``) wrapped in a
    :class:`FastMcapReader` when ``target`` is a ROS2 bag folder of one indexed ``.mcap``
    file without per-message compression; else ``reader`` itself."""
    try:
        from mcap.reader import make_reader
    except ImportError:  # an install without it reads through rosbags
        return reader
    if not target.is_dir() or len(reader.readers) != 1 or not getattr(reader, "is2", False):
        return reader
    files = sorted(target.glob("*.mcap"))
    if len(files) != 1 or any(target.glob("*.db3")):
        return reader
    if getattr(reader.readers[0], "compression_mode", "") not in ("", "none", None):
        return reader  # rosbags decompresses whole files or messages; mcap would not
    stream = files[0].open("rb")
    try:
        indexed = make_reader(stream, validate_crcs=True)
        summary = indexed.get_summary()
    except Exception:  # a damaged summary: rosbags reads it (or reports why not)
        summary = None
    if summary is None or not summary.chunk_indexes:
        stream.close()  # unindexed or damaged: rosbags reads it (and checks the order)
        return reader
    return FastMcapReader(reader, files[0], stream, indexed)
