"""Reading recordings back: every message in time order, also from a file cut short.

:func:`read_recording` scans the file(s) record by record rather than trusting the summary
at the end, so a recording whose process died mid-way is read up to its last complete
chunk (``Recording.truncated`` says so). JSON channels are decoded; ROS 2 channels keep
their CDR bytes (decode them with ``mcap_ros2``, as :func:`decode_ros` does).
"""

from __future__ import annotations

import bisect
import json
import os
import struct
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from beehave.errors import RecordingError
from beehave.recording import schema
from beehave.recording.writer import recording_files


@dataclass(frozen=True)
class Recorded:
    """One message: its MCAP ``topic``, ``log_time_ns``, and ``data`` (a dict for JSON
    channels, the raw bytes for CDR)."""

    topic: str
    log_time_ns: int
    data: Any
    encoding: str
    schema_name: str

    @property
    def t_s(self) -> float:
        return self.log_time_ns / 1e9


@dataclass
class ChannelInfo:
    topic: str
    encoding: str
    schema_name: str
    count: int = 0


@dataclass
class Recording:
    """A whole recording (all its rolled-over files), messages sorted by time."""

    files: list[Path]
    messages: list[Recorded]
    channels: dict[str, ChannelInfo]
    truncated: bool = False
    """A file ended before its footer (the recording process died); what it had up to its
    last complete chunk is here."""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    schemas: dict[str, bytes] = field(default_factory=dict)
    damaged: list[Damage] = field(default_factory=list)
    """Parts of the files that cannot be read (overwritten bytes, a failed CRC), in file
    order; what lies before and after them is here."""

    truncated_from_ns: int | None = None
    """For a truncated recording: the earliest message time of the chunk being written
    when the process died (None: its header did not reach the disk either)."""

    @property
    def intact_until_ns(self) -> int:
        """The recording time before which nothing is missing. A chunk holds what every
        channel queued since the last one, so a lost chunk (damaged, or cut off) may hold
        messages older than the last one read before it: the lost chunk's own first
        message time when its header says it, else :data:`LOST_MARGIN_S` before the last
        message read. The end when nothing is lost."""
        if self.damaged:
            first = self.damaged[0]
            known, read = first.lost_from_ns, first.after_ns
            upper = first.before_ns if first.before_ns is not None else self.end_ns
        elif self.truncated:
            known, read = self.truncated_from_ns, self.end_ns
            upper = self.end_ns + int(60e9)
        else:
            return self.end_ns
        if read is None:
            return self.start_ns
        if known is not None and self.start_ns <= known <= upper:  # a sane header
            return min(known, read)
        return max(self.start_ns, read - int(LOST_MARGIN_S * 1e9))

    def describe_damage(self) -> list[str]:
        return [d.describe(self.start_ns) for d in self.damaged]

    @property
    def start_ns(self) -> int:
        return self.messages[0].log_time_ns if self.messages else 0

    @property
    def end_ns(self) -> int:
        return self.messages[-1].log_time_ns if self.messages else 0

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def prefixes(self) -> list[str]:
        """The robots recorded (their channel prefixes; ``""`` for a bare recording)."""
        found = set()
        for topic in self.channels:
            if topic.endswith("/" + schema.BLACKBOARD) or topic.endswith(
                    "/" + schema.EVENTS_HIGH) or topic.endswith("/" + schema.EVENTS_LOW):
                head = topic.rsplit("/beehave/", 1)[0]
                found.add(head.strip("/"))
        return sorted(found)

    def of(self, topic: str) -> list[Recorded]:
        """The messages of one channel, in time order."""
        return [m for m in self.messages if m.topic == topic]

    def dropped(self) -> int:
        """Messages the recorder reported dropped (0 when it reported none)."""
        stats = [m.data for m in self.messages if m.topic == schema.RECORDER]
        if stats:
            return int(stats[-1].get("dropped", 0))
        done = self.metadata.get("beehave.recorder")
        return int(done["dropped"]) if done else 0

    def sim_time(self, prefix: str) -> Callable[[int], float] | None:
        """Wall time (ns) → the robot's sim time (s), interpolated from its clock channel;
        None when the robot did not run on sim time."""
        samples = [(m.log_time_ns, float(m.data["sim_time_s"]))
                   for m in self.of(schema.topic(prefix, schema.CLOCK))]
        # Keep the samples where sim time moved: a paused clock is flat, not a divisor 0.
        points: list[tuple[int, float]] = []
        for t, s in samples:
            if not points or (t > points[-1][0] and s >= points[-1][1]):
                points.append((t, s))
        if len(points) < 2:
            return None
        times = [t for t, _ in points]

        def sim_at(t_ns: int) -> float:
            i = bisect.bisect_right(times, t_ns)
            if i == 0:
                return points[0][1]
            if i >= len(points):
                return points[-1][1]
            (t0, s0), (t1, s1) = points[i - 1], points[i]
            return s0 + (s1 - s0) * (t_ns - t0) / (t1 - t0)

        return sim_at


@dataclass(frozen=True)
class Damage:
    """A part of a file that cannot be read although the file goes on after it (bytes
    overwritten, not a crash): its byte range, why, and the recording times of the last
    message read before it and the first one after it (None: none there)."""

    file: Path
    start_byte: int
    end_byte: int
    reason: str
    after_ns: int | None = None
    before_ns: int | None = None
    lost_from_ns: int | None = None
    """The earliest message time the lost part held (its chunk header says; None when the
    header itself is unreadable)."""

    def describe(self, start_ns: int) -> str:
        def at(t_ns: int | None, none: str) -> str:
            return none if t_ns is None else f"{(t_ns - start_ns) / 1e9:.3f} s"

        return (f"{self.file}: bytes {self.start_byte}-{self.end_byte} ({self.reason}); the "
                f"messages between {at(self.after_ns, 'the start')} and "
                f"{at(self.before_ns, 'the end')} (wall time since the start) are lost")


LOST_MARGIN_S = 2.0
"""How far before the last message read a lost chunk may reach when its header does not
say (the recorder writes a chunk at least every second)."""


@dataclass
class _Scan:
    truncated: bool = False
    truncated_from_ns: int | None = None
    damaged: list[Damage] = field(default_factory=list)


def _chunk_start_ns(f: Any, offset: int) -> int | None:
    """The first message time in the header of the chunk at ``offset`` (None: no chunk
    header there)."""
    f.seek(offset)
    head = f.read(17)
    if len(head) < 17 or head[0] != 0x06:  # opcode, record length, message_start_time
        return None
    return int(struct.unpack_from("<Q", head, 9)[0])


_MAGIC = b"\x89MCAP0\r\n"


def _records(path: Path) -> tuple[Iterable[Any], _Scan]:
    """The records of ``path``, each chunk checked (size and CRC) and skipped when damaged.
    A file that ends inside a record is *truncated* (the recording process died); one that
    cannot be read on although it ends in the MCAP magic (as only a finished file does) is
    *damaged* from there to its end."""
    scan = _Scan()

    def gen() -> Iterable[Any]:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            f.seek(max(size - len(_MAGIC), 0))
            finished = size >= 2 * len(_MAGIC) and f.read() == _MAGIC
            f.seek(0)
            it = iter(StreamReader(f, emit_chunks=True, record_size_limit=1 << 30).records)
            while True:
                start = f.tell()
                try:
                    record = next(it)
                except StopIteration:
                    return
                except Exception as exc:
                    if finished:
                        scan.damaged.append(Damage(path, start, size,
                                                   f"unreadable: {type(exc).__name__}"))
                    else:  # the file ends inside a record: the process died while writing
                        scan.truncated = True
                        scan.truncated_from_ns = _chunk_start_ns(f, start)
                    return
                if not isinstance(record, Chunk):
                    yield record
                    continue
                try:
                    records = breakup_chunk(record, validate_crc=True)  # decompressed
                except Exception as exc:
                    # Its place among the messages: the reader names what is around it.
                    yield Damage(path, start, f.tell(),
                                 f"damaged chunk: {type(exc).__name__} {exc}".strip(),
                                 lost_from_ns=record.message_start_time)
                    continue
                yield from records

    return gen(), scan


def read_recording(path: str | Path) -> Recording:
    """Read ``path`` (and the files it rolled over into). Raises :class:`RecordingError`
    when it does not exist or is not MCAP."""
    path = Path(path)
    files = recording_files(path)
    if not files:
        raise RecordingError(f"recording {str(path)!r} does not exist")
    messages: list[Recorded] = []
    channels: dict[str, ChannelInfo] = {}
    metadata: dict[str, dict[str, str]] = {}
    schemas_by_name: dict[str, bytes] = {}
    truncated = False
    truncated_from: int | None = None
    damaged: list[Damage] = []
    counts: Counter[str] = Counter()
    for file in files:
        try:
            with open(file, "rb") as f:
                magic = f.read(8)
        except OSError as exc:  # a directory, no permission …: said as the CLI says errors
            raise RecordingError(f"recording {str(file)!r} cannot be read: "
                                 f"{exc.strerror or exc}") from exc
        if magic != _MAGIC:
            raise RecordingError(f"{str(file)!r} is not an MCAP file (no MCAP magic)")
        schemas: dict[int, Schema] = {}
        by_id: dict[int, ChannelInfo] = {}
        records, scan = _records(file)
        last_ns: int | None = None
        waiting: list[Damage] = []  # damage seen, the next message's time not yet
        for record in records:
            if isinstance(record, Damage):
                waiting.append(record)
                continue
            if isinstance(record, Schema):
                schemas[record.id] = record
                schemas_by_name[record.name] = record.data
            elif isinstance(record, Channel):
                sch = schemas.get(record.schema_id)
                info = channels.setdefault(record.topic, ChannelInfo(
                    record.topic, record.message_encoding, sch.name if sch else ""))
                by_id[record.id] = info
            elif isinstance(record, Message):
                found = by_id.get(record.channel_id)
                if found is None:
                    continue
                info = found
                data: Any = record.data
                if info.encoding == "json":
                    try:
                        data = json.loads(data)
                    except ValueError:
                        truncated = True
                        continue
                counts[info.topic] += 1
                messages.append(Recorded(info.topic, record.log_time, data, info.encoding,
                                         info.schema_name))
                for d in waiting:
                    damaged.append(Damage(d.file, d.start_byte, d.end_byte, d.reason,
                                          last_ns, record.log_time, d.lost_from_ns))
                waiting.clear()
                last_ns = record.log_time if last_ns is None else max(last_ns,
                                                                      record.log_time)
            elif isinstance(record, Metadata):
                metadata[record.name] = dict(record.metadata)
        damaged += [Damage(d.file, d.start_byte, d.end_byte, d.reason, last_ns, None,
                           d.lost_from_ns) for d in [*waiting, *scan.damaged]]
        truncated = truncated or scan.truncated
        if scan.truncated_from_ns is not None:
            truncated_from = scan.truncated_from_ns
    for topic, info in channels.items():
        info.count = counts[topic]
    messages.sort(key=lambda m: m.log_time_ns)  # stable: one channel keeps its order
    return Recording(files, messages, channels, truncated, metadata, schemas_by_name,
                     damaged, truncated_from)


def decode_ros(recording: Recording, message: Recorded) -> Any:
    """A CDR message of ``recording`` decoded with ``mcap_ros2`` (an object with the
    message's fields, as ROS tools and Foxglove see it)."""
    return ros_decoder(recording, message.schema_name)(message.data)


def ros_decoder(recording: Recording, schema_name: str) -> Callable[[bytes], Any]:
    """The ``mcap_ros2`` decoder of the ros2msg schema ``schema_name`` (build it once per
    schema: building costs far more than decoding)."""
    from mcap.records import Schema as McapSchema
    from mcap_ros2.decoder import DecoderFactory

    cache: dict[str, Callable[[bytes], Any]] = recording.__dict__.setdefault("_decoders", {})
    decoder = cache.get(schema_name)
    if decoder is not None:
        return decoder
    data = recording.schemas.get(schema_name)
    if data is None:
        raise RecordingError(f"no ros2msg schema {schema_name!r} in the recording")
    made = DecoderFactory().decoder_for(
        "cdr", McapSchema(id=1, name=schema_name, encoding="ros2msg", data=data))
    if made is None:
        raise RecordingError(f"mcap_ros2 cannot decode {schema_name!r}")
    cache[schema_name] = made
    return made
