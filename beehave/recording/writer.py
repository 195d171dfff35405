"""The writer thread: drains the recorder's bounded queues into MCAP files.

Whoever records (a blackboard ``set``, an event, a ROS callback) only appends to a queue
of its channel; this thread encodes and writes. When the disk is slower than the robot,
a full queue drops the new message and counts it -- the robot never waits for the disk.

Crash safety: the file is MCAP with chunks; every ``flush_period_s`` the chunk in progress
is closed and written out, so a process that dies leaves a file readable (by
:func:`beehave.recording.read_recording`, and by tools that scan it) up to the last chunk.
Files roll over by size: ``run.mcap``, ``run_001.mcap``, ``run_002.mcap`` …
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer

from beehave.errors import RecordingError
from beehave.recording import schema

log = logging.getLogger(__name__)

Encoder = Callable[[Any], tuple[int, bytes]]
"""An item of a queue → (log time in ns since the epoch, message bytes)."""

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
                 "encode", "queue", "capacity", "dropped", "_drop_lock", "put")

    def __init__(self, topic: str, *, encode: Encoder, capacity: int, schema_name: str,
                 schema_encoding: str = "jsonschema", schema_data: bytes | None = None,
                 encoding: str = "json") -> None:
        self.topic = topic
        self.encoding = encoding
        self.schema_name = schema_name
        self.schema_encoding = schema_encoding
        self.schema_data = schema_data if schema_data is not None else \
            schema.schema_bytes(schema_name)
        self.encode = encode
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
                self._drop()

        self.put = put

    def _drop(self, n: int = 1) -> None:
        with self._drop_lock:
            self.dropped += n


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
        self._writer: Writer | None = None
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
                channel._drop(left)
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
                    assert self._writer is not None
                    self._writer.flush()  # type: ignore[no-untyped-call]  # closes the chunk: readable up to here after a crash
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
        for channel in [*self.channels, self._stats_channel]:
            cid = self._ids.get(channel.topic)
            if cid is None:  # every attached channel is in the file, also one still silent
                cid = self._register(channel)
            queue = channel.queue
            if not queue:
                continue
            writer = self._writer
            assert writer is not None
            add, encode, popleft = writer.add_message, channel.encode, queue.popleft
            written = 0
            limit = self.max_file_bytes
            while queue:
                stamp_ns, data = encode(popleft())
                add(cid, stamp_ns, data, stamp_ns)
                written += 1
                if limit is not None and written % 64 == 0 and self._full(limit):
                    break  # roll over now; the rest of the queue goes to the next file
            self.stats.written += written
            if limit is not None and self._full(limit):
                self._roll()

    def _full(self, limit: int) -> bool:
        return self._stream is not None and self._stream.tell() >= limit

    def _register(self, channel: Channel) -> int:
        writer = self._writer
        assert writer is not None
        sid = self._schemas.get(channel.schema_name)
        if sid is None:
            sid = writer.register_schema(channel.schema_name, channel.schema_encoding,
                                         channel.schema_data)
            self._schemas[channel.schema_name] = sid
        cid = writer.register_channel(channel.topic, channel.encoding, sid)
        self._ids[channel.topic] = cid
        return cid

    def _open(self, part: int) -> None:
        path = part_path(self.path, part)
        try:
            stream = self._open_file(path)
        except OSError as exc:
            raise RecordingError(f"cannot write the recording {str(path)!r}: {exc}") from exc
        writer = Writer(stream, chunk_size=self.chunk_bytes, compression=CompressionType.LZ4)
        writer.start(profile=schema.PROFILE, library="beehave")
        writer.add_metadata("beehave", {**self._metadata, "part": str(part)})
        self._stream, self._writer, self._part = stream, writer, part
        self._ids, self._schemas = {}, {}
        self.stats.files.append(path)

    def _roll(self) -> None:
        self._finish()
        self._open(self._part + 1)

    def _finish(self) -> None:
        writer, stream = self._writer, self._stream
        self._writer = self._stream = None
        if writer is None or stream is None:
            return
        try:
            self._count_drops()
            writer.add_metadata("beehave.recorder", {
                "written": str(self.stats.written), "dropped": str(self.stats.dropped)})
            writer.finish()  # type: ignore[no-untyped-call]
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


def schema_json(body: dict[str, Any]) -> bytes:
    import json

    return json.dumps(body, separators=(",", ":"), allow_nan=False).encode()
