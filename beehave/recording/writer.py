"""The writer thread: drains the recorder's bounded queues into MCAP files.

Whoever records (a blackboard ``set``, an event, a ROS callback) only appends to a queue
of its channel; this thread encodes and writes. When the disk is slower than the robot,
a full queue drops the new message and counts it -- the robot never waits for the disk.

Crash safety: the file is MCAP with chunks; every ``flush_period_s`` the chunk in progress
is closed and written out, so a process that dies leaves a file readable (by
:func:`beehave.recording.read_recording`, and by tools that scan it) up to the last chunk.
Files roll over by size: ``run.mcap``, ``run_001.mcap``, ``run_002.mcap`` …

Speed: a robot's blackboard can change a hundred thousand times a second in a burst, and
the writer shares the interpreter (the GIL) with the robot. The ``mcap`` library's
``Writer`` builds a record object per message (some 5 µs each), so :class:`McapFile`
writes the per-message records itself -- a ``struct`` header and the encoded bytes,
joined once per chunk -- and uses the library's record types for everything written
once per chunk or per file (schemas, channels, indexes, summary, footer). The file is
plain MCAP: chunked, compressed, indexed, read by every MCAP tool.
"""

from __future__ import annotations

import functools
import logging
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel as ChannelRecord,
)
from mcap.records import (
    ChunkIndex,
    DataEnd,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from beehave.errors import RecordingError
from beehave.recording import schema

log = logging.getLogger(__name__)

Encoder = Callable[[Any], tuple[int, bytes]]
"""An item of a queue → (log time in ns since the epoch, message bytes)."""

BatchEncoder = Callable[[list[Any]], tuple[list[int], list[bytes]]]
"""Items of a queue → their log times and their bytes (two lists, in order): for channels
whose items are cheaper to encode together
(:func:`beehave.recording.recorder._encode_changes`)."""

DRAIN_BATCH = 4096
"""Items taken out of a queue at a time: bounds the writer's memory per step."""

OpenFile = Callable[[Path], IO[bytes]]


def part_path(path: Path, index: int) -> Path:
    """The ``index``-th file of a rolled-over recording (0: ``path`` itself)."""
    return path if index == 0 else path.with_name(f"{path.stem}_{index:03d}{path.suffix}")


def recording_files(path: str | Path) -> list[Path]:
    """``path`` and the files it rolled over into, in order (those that exist)."""
    path = Path(path)
    files = []
    index = 0
    while part_path(path, index).exists():
        files.append(part_path(path, index))
        index += 1
    return files


@dataclass
class RecorderStats:
    """What the recorder did: ``written`` and ``dropped`` messages (``dropped_by_channel``
    by MCAP topic), the ``files`` written, and ``error`` when writing failed."""

    written: int = 0
    dropped: int = 0
    dropped_by_channel: dict[str, int] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    error: BaseException | None = None


class Channel:
    """One MCAP channel and its bounded queue. :meth:`put` is the hot path: it never
    blocks and never raises; when the queue is full the message is dropped and counted."""

    __slots__ = ("topic", "encoding", "schema_name", "schema_encoding", "schema_data",
                 "encode", "encode_batch", "queue", "capacity", "dropped", "_drop_lock",
                 "put")

    def __init__(self, topic: str, *, encode: Encoder, capacity: int, schema_name: str,
                 schema_encoding: str = "jsonschema", schema_data: bytes | None = None,
                 encoding: str = "json", encode_batch: BatchEncoder | None = None) -> None:
        self.topic = topic
        self.encoding = encoding
        self.schema_name = schema_name
        self.schema_encoding = schema_encoding
        self.schema_data = schema_data if schema_data is not None else \
            schema.schema_bytes(schema_name)
        self.encode = encode
        self.encode_batch: BatchEncoder = encode_batch or functools.partial(
            _encode_each, encode)
        self.queue: deque[Any] = deque()
        self.capacity = capacity
        self.dropped = 0
        self._drop_lock = threading.Lock()
        queue, append = self.queue, self.queue.append

        def put(item: Any) -> None:
            # len() then append() is not atomic, so the bound may be passed by a message or
            # two under contention: a bound on memory, not an exact count.
            if len(queue) < capacity:
                append(item)
            else:
                self.count_drop()

        self.put = put

    def count_drop(self, n: int = 1) -> None:
        """Count ``n`` messages lost (a tap that queues itself calls it when full)."""
        with self._drop_lock:
            self.dropped += n


MAGIC = b"\x89MCAP0\r\n"
"""The 8 bytes an MCAP file starts and ends with."""

# A Message record: opcode, record length, channel id, sequence, log time, publish time,
# then the data. 31 bytes before the data; the record length counts from the channel id.
_MESSAGE = struct.Struct("<BQHIQQ")
_MESSAGE_HEAD = _MESSAGE.size
_MESSAGE_FIELDS = _MESSAGE_HEAD - 9
_OP_MESSAGE = int(Opcode.MESSAGE)  # a plain int: no enum lookup in the hot loop
# A Chunk record up to its compression name: opcode, record length, message start and end
# time, uncompressed size, uncompressed CRC-32.
_CHUNK = struct.Struct("<BQQQQI")
_FOOTER = struct.Struct("<BQQQ")


class McapFile:
    """One MCAP file being written, chunked and indexed like the ``mcap`` library's
    ``Writer`` does it, at a fraction of its cost per message (see the module docstring).

    Schemas, channels and metadata go straight into the data section (a reader meets them
    before the chunks that use them); messages collect in the chunk in progress until
    ``chunk_bytes`` of it are full or :meth:`flush` is called; :meth:`finish` writes the
    summary (schemas, channels, statistics, chunk and metadata indexes) and the footer.
    """

    def __init__(self, stream: IO[bytes], *, chunk_bytes: int, profile: str,
                 library: str, compression_level: int = 1) -> None:
        self._stream = stream
        self.size = 0
        """Bytes written to the stream so far (it need not support ``tell()``)."""
        self.chunk_bytes = chunk_bytes
        self._compress = zstandard.ZstdCompressor(level=compression_level).compress
        self._schemas: list[Schema] = []
        self._channels: list[ChannelRecord] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = {}
        self._start_ns: int | None = None
        self._end_ns = 0
        # The chunk in progress: its records, and per channel the log times and offsets
        # (in the chunk) of its messages, for the chunk's message indexes.
        self._chunk = bytearray()
        self._index: dict[int, tuple[list[int], list[int]]] = {}
        self._write(MAGIC)
        self._write_record(Header(profile=profile, library=library))

    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self.size += len(data)

    def _write_record(self, record: McapRecord) -> int:
        builder = RecordBuilder()
        record.write(builder)
        data = builder.end()  # type: ignore[no-untyped-call]
        self._write(data)
        return len(data)

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._write_record(schema)
        return schema.id

    def add_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel = ChannelRecord(id=len(self._channels) + 1, topic=topic,
                                message_encoding=message_encoding, schema_id=schema_id,
                                metadata={})
        self._channels.append(channel)
        self._counts[channel.id] = 0
        self._write_record(channel)
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self.size
        length = self._write_record(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_messages(self, channel_id: int, times_ns: list[int], datas: list[bytes], *,
                     max_file_bytes: int | None = None) -> int:
        """Add messages of one channel (their log times in ns, their data) to the chunk in
        progress, writing each chunk that fills up; returns how many were added: all, or
        fewer when a chunk written made the file reach ``max_file_bytes`` (roll over)."""
        # The hot loop of the recorder: locals only, one struct call per message, the
        # chunk grows in place (no object per message kept).
        chunk, pack, chunk_bytes = self._chunk, _MESSAGE.pack, self.chunk_bytes
        times, offsets = self._index.setdefault(channel_id, ([], []))
        add_time, add_offset = times.append, offsets.append
        taken = 0
        for stamp_ns, data in zip(times_ns, datas, strict=True):
            add_time(stamp_ns)
            add_offset(len(chunk))
            chunk += pack(_OP_MESSAGE, _MESSAGE_FIELDS + len(data), channel_id, 0, stamp_ns,
                          stamp_ns)
            chunk += data
            taken += 1
            if len(chunk) >= chunk_bytes:
                self._write_chunk()
                if max_file_bytes is not None and self.size >= max_file_bytes:
                    break
                chunk = self._chunk
                times, offsets = self._index.setdefault(channel_id, ([], []))
                add_time, add_offset = times.append, offsets.append
        self._counts[channel_id] += taken
        return taken

    def _write_chunk(self) -> None:
        """Compress the chunk in progress and write it, then its message indexes."""
        records, index = self._chunk, self._index
        if not records:
            return
        self._chunk, self._index = bytearray(), {}
        start_ns = min(min(times) for times, _ in index.values() if times)
        end_ns = max(max(times) for times, _ in index.values() if times)
        compressed = self._compress(records)
        compression = b"zstd"
        chunk_start = self.size
        head = _CHUNK.pack(Opcode.CHUNK, 8 + 8 + 8 + 4 + 4 + len(compression) + 8
                           + len(compressed), start_ns, end_ns, len(records),
                           zlib.crc32(records))
        self._write(b"".join((head, struct.pack("<I", len(compression)), compression,
                              struct.pack("<Q", len(compressed)), compressed)))
        chunk_length = self.size - chunk_start
        offsets: dict[int, int] = {}
        index_start = self.size
        for channel_id, (times, starts) in index.items():
            if not times:
                continue
            pairs: list[int] = [0] * (2 * len(times))
            pairs[0::2], pairs[1::2] = times, starts
            offsets[channel_id] = self.size
            n = len(pairs)  # two u64 per message: log time, offset in the chunk
            self._write(struct.pack(f"<BQHI{n}Q", Opcode.MESSAGE_INDEX, 2 + 4 + 8 * n,
                                    channel_id, 8 * n, *pairs))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start_ns, message_end_time=end_ns,
            chunk_start_offset=chunk_start, chunk_length=chunk_length,
            message_index_offsets=offsets, message_index_length=self.size - index_start,
            compression=compression.decode(), compressed_size=len(compressed),
            uncompressed_size=len(records)))
        self._start_ns = start_ns if self._start_ns is None else min(self._start_ns,
                                                                        start_ns)
        self._end_ns = max(self._end_ns, end_ns)

    def flush(self) -> None:
        """Write the chunk in progress and flush the stream: a process that dies now
        leaves a file readable up to here."""
        self._write_chunk()
        self._stream.flush()

    def finish(self) -> None:
        """Write the last chunk, the summary and the footer (the stream stays open)."""
        self._write_chunk()
        self._write_record(DataEnd(data_section_crc=0))
        summary_start = self.size
        builder = RecordBuilder()
        statistics = Statistics(
            message_count=sum(self._counts.values()), schema_count=len(self._schemas),
            channel_count=len(self._channels), attachment_count=0,
            metadata_count=len(self._metadata_indexes), chunk_count=len(self._chunk_indexes),
            message_start_time=self._start_ns or 0, message_end_time=self._end_ns,
            channel_message_counts=dict(self._counts))
        groups: list[SummaryOffset] = []
        for opcode, group in ((Opcode.SCHEMA, self._schemas), (Opcode.CHANNEL, self._channels),
                              (Opcode.STATISTICS, [statistics]),
                              (Opcode.CHUNK_INDEX, self._chunk_indexes),
                              (Opcode.METADATA_INDEX, self._metadata_indexes)):
            if not group:
                continue
            begin = builder.count
            for record in group:
                record.write(builder)
            groups.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + begin,
                                        group_length=builder.count - begin))
        offsets_start = summary_start + builder.count
        for group_offset in groups:
            group_offset.write(builder)
        summary = builder.end()  # type: ignore[no-untyped-call]
        # The footer's CRC covers the summary and the footer's fields before it.
        footer = _FOOTER.pack(Opcode.FOOTER, 8 + 8 + 4, summary_start, offsets_start)
        crc = zlib.crc32(footer, zlib.crc32(summary))
        self._write(b"".join((summary, footer, struct.pack("<I", crc), MAGIC)))
        self._stream.flush()


class WriterThread:
    """Owns the MCAP file(s) and the thread that writes them (see the module docstring)."""

    def __init__(self, path: Path, *, max_file_bytes: int | None, flush_period_s: float,
                 drain_period_s: float = 0.02, chunk_bytes: int = 512 * 1024,
                 open_file: OpenFile | None = None,
                 metadata: dict[str, str] | None = None,
                 on_drain: Callable[[], None] | None = None) -> None:
        self.path = path
        self.max_file_bytes = max_file_bytes
        self.flush_period_s = flush_period_s
        self.drain_period_s = drain_period_s
        self.chunk_bytes = chunk_bytes if max_file_bytes is None else \
            max(4096, min(chunk_bytes, max_file_bytes // 4))
        self._open_file = open_file or (lambda p: open(p, "wb"))  # noqa: SIM115
        self._metadata = metadata or {}
        self._on_drain = on_drain
        self.channels: list[Channel] = []
        self._channels_lock = threading.Lock()
        self.stats = RecorderStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._file: McapFile | None = None
        self._stream: IO[bytes] | None = None
        self._ids: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._part = 0
        self._stats_channel = Channel(schema.RECORDER, encode=_identity, capacity=16,
                                      schema_name="beehave.RecorderStats")
        self._reported = (0, 0)

    def add(self, channel: Channel) -> Channel:
        with self._channels_lock:
            self.channels = [*self.channels, channel]
        return channel

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        self._open(0)  # in the caller's thread: a bad path fails the `with`, not later
        self._thread = threading.Thread(target=self._main, name="beehave-recorder",
                                        daemon=True)
        self._thread.start()

    def close(self, *, timeout_s: float) -> RecorderStats:
        """Write what is queued, finish the file (summary and index) and join the thread,
        within ``timeout_s``; what is still queued then is counted as dropped."""
        self._stop.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                log.warning("recorder: the disk did not take the rest within %.1f s; the "
                            "recording of %s may end early", timeout_s, self.path)
        for channel in self.channels:  # never written: lost, and counted as such
            left = len(channel.queue)
            if left:
                channel.queue.clear()
                channel.count_drop(left)
        self._count_drops()
        return self.stats

    # -- the thread ----------------------------------------------------------------------

    def _main(self) -> None:
        next_flush = time.monotonic() + self.flush_period_s
        try:
            while True:
                stopping = self._stop.wait(self.drain_period_s)
                if self._on_drain is not None:
                    self._on_drain()
                self._drain()
                now = time.monotonic()
                if stopping or now >= next_flush:
                    self._report_stats()
                    self._drain()
                    assert self._file is not None
                    self._file.flush()  # closes the chunk: readable up to here after a crash
                    next_flush = now + self.flush_period_s
                if stopping and not any(c.queue for c in self.channels):
                    break
        except BaseException as exc:
            # The queues stay full from now on, so every later message is dropped and
            # counted; close() counts what is left in them.
            self.stats.error = exc
            log.error("recorder: writing %s failed; recording stopped (messages from now on "
                      "are dropped and counted): %r", self.path, exc)
        finally:
            self._finish()

    def _drain(self) -> None:
        limit = self.max_file_bytes
        for channel in [*self.channels, self._stats_channel]:
            cid = self._ids.get(channel.topic)
            if cid is None:  # every attached channel is in the file, also one still silent
                cid = self._register(channel)
            queue, popleft = channel.queue, channel.queue.popleft
            while queue:
                # Only this thread takes from the queue: what len() counts stays there.
                items = [popleft() for _ in range(min(len(queue), DRAIN_BATCH))]
                times, datas = channel.encode_batch(items)
                while datas:
                    file = self._file
                    assert file is not None
                    taken = file.add_messages(cid, times, datas, max_file_bytes=limit)
                    self.stats.written += taken
                    times, datas = times[taken:], datas[taken:]
                    if limit is not None and file.size >= limit:
                        # Roll over now; the rest goes to the next file.
                        self._roll()
                        cid = self._register(channel)

    def _register(self, channel: Channel) -> int:
        file = self._file
        assert file is not None
        sid = self._schemas.get(channel.schema_name)
        if sid is None:
            sid = file.add_schema(channel.schema_name, channel.schema_encoding,
                                  channel.schema_data)
            self._schemas[channel.schema_name] = sid
        cid = file.add_channel(channel.topic, channel.encoding, sid)
        self._ids[channel.topic] = cid
        return cid

    def _open(self, part: int) -> None:
        path = part_path(self.path, part)
        try:
            stream = self._open_file(path)
        except OSError as exc:
            raise RecordingError(f"cannot write the recording {str(path)!r}: {exc}") from exc
        try:
            file = McapFile(stream, chunk_bytes=self.chunk_bytes, profile=schema.PROFILE,
                            library="beehave")
            file.add_metadata("beehave", {**self._metadata, "part": str(part)})
        except Exception:
            stream.close()
            raise
        self._stream, self._file, self._part = stream, file, part
        self._ids, self._schemas = {}, {}
        self.stats.files.append(path)

    def _roll(self) -> None:
        self._finish()
        self._open(self._part + 1)

    def _finish(self) -> None:
        file, stream = self._file, self._stream
        self._file = self._stream = None
        if file is None or stream is None:
            return
        try:
            self._count_drops()
            file.add_metadata("beehave.recorder", {
                "written": str(self.stats.written), "dropped": str(self.stats.dropped)})
            file.finish()
        except Exception as exc:  # a broken disk: what was flushed stays readable
            if self.stats.error is None:
                self.stats.error = exc
            log.error("recorder: cannot finish %s: %r", self.path, exc)
        finally:
            try:
                stream.close()
            except Exception as exc:
                log.error("recorder: cannot close %s: %r", self.path, exc)

    def _count_drops(self) -> None:
        by_channel = {c.topic: c.dropped for c in self.channels if c.dropped}
        self.stats.dropped_by_channel = by_channel
        self.stats.dropped = sum(by_channel.values())

    def _report_stats(self) -> None:
        """A stats message whenever the counts moved, so a crashed recording still says
        how much it lost."""
        self._count_drops()
        counts = (self.stats.written, self.stats.dropped)
        if counts == self._reported:
            return
        self._reported = counts
        stamp = time.time()
        body = {"written": counts[0], "dropped": counts[1],
                "dropped_by_channel": self.stats.dropped_by_channel, "stamp": stamp}
        self._stats_channel.put((int(stamp * 1e9), schema_json(body)))


def _identity(item: tuple[int, bytes]) -> tuple[int, bytes]:
    return item


def _encode_each(encode: Encoder, items: list[Any]) -> tuple[list[int], list[bytes]]:
    times: list[int] = []
    datas: list[bytes] = []
    for item in items:
        stamp_ns, data = encode(item)
        times.append(stamp_ns)
        datas.append(data)
    return times, datas


def schema_json(body: dict[str, Any]) -> bytes:
    import json

    return json.dumps(body, separators=(",", ":"), allow_nan=False).encode()
