"""The Recorder: every channel type round-trips; ROS channels read back with the ROS/Foxglove
decoder (mcap-ros2-support); a crash leaves a file readable up to its last chunk; a slow
disk drops and counts instead of stalling writers; files roll over by size."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import IO, Any

import pytest

from beehave.blackboard import Blackboard
from beehave.clock import SimClock
from beehave.events import Event, EventBus, EventKind
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.recording import Recorder, RecordingError, read_recording, recording_files
from beehave.testing import WALL_TIMEOUT_S, wait_until, wall_timeout
from behaviours.logics import LedLogic
from hal.debug import DebugHAL, DebugRobot

ROOT = Path(__file__).resolve().parents[1]


def test_a_sim_clock_is_sampled_every_clock_period_however_unevenly_it_moves(
        tmp_path: Path) -> None:
    """The replay maps recorded wall times to sim time by interpolating the clock's
    samples; a simulation in lockstep under load moves in bursts and stalls. Every 10 ms
    of sim time is sampled when the clock moves (not only when the writer wakes), so the
    sim time of an event read back is right to one /clock period."""
    import time

    from beehave.recording.recorder import CLOCK_SAMPLE_S

    path = tmp_path / "clock.mcap"
    clock = SimClock()
    with Recorder(path, flush_period_s=0.5) as recorder:
        recorder.attach_clock(clock, prefix="r1")
        for burst in range(5):  # a burst of 0.5 sim s in no wall time, then a stall
            for step in range(50):
                clock.set_time(burst + step * 0.01)
            time.sleep(0.05)
    rec = read_recording(path)
    samples = [m.data["sim_time_s"] for m in rec.of("/r1/beehave/clock")]
    moved = sorted({round(s, 3) for s in samples})
    gaps = [b - a for a, b in zip(moved, moved[1:], strict=False) if b - a < 0.5]  # a burst
    assert len(moved) >= 5 * 50 * 0.9 and max(gaps) <= CLOCK_SAMPLE_S + 1e-9, moved


def test_every_beehave_channel_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "all.mcap"
    board, high = Blackboard(), EventBus()
    clock = SimClock()
    clock.set_time(12.5)
    hardware = DebugRobot(battery_percentage=50.0)
    low = LowLevelBehaviorManager(default="leds", stop_timeout_s=0.5)
    low.register("leds", LedLogic)
    low.hals.register(DebugHAL, robot=hardware)
    values: list[Any] = [1, 2.5, math.inf, -math.inf, "text", None, True, (1, 2),
                         {"a": [1, {"b": math.inf}]}]
    with Recorder(path, flush_period_s=0.05) as recorder:
        recorder.attach_blackboard(board, prefix="r1")
        recorder.attach_events(high, prefix="r1", level="high")
        recorder.attach_clock(clock, prefix="r1")
        recorder.attach_blackboard(low.blackboard, prefix="r2")
        recorder.attach_events(low.events, prefix="r2", level="low")
        recorder.attach_hal_outputs(low, prefix="r2")
        for i, value in enumerate(values):
            board.set(f"v/{i}", value, writer="hal:test")
        board.set("nan", math.nan)
        board.mark_stale(pattern="v/0")
        high.emit(Event(EventKind.ENDED, "tour/drive", "FAILED", RuntimeError("wheel"),
                        {"took_s": 1.5, "why": object()}))
        with low:
            assert wait_until(lambda: hardware.led_color == "green")
            hardware.set_battery(10.0)
            assert wait_until(lambda: hardware.led_color == "red")
        # The writer samples the sim clock while it runs.
        assert wait_until(lambda: recorder.stats.written > 20)
    rec = read_recording(path)
    assert not rec.truncated and rec.dropped() == 0
    assert rec.prefixes == ["r1", "r2"]

    changes = [m.data for m in rec.of("/r1/beehave/blackboard")]
    from beehave.blackboard import from_json

    got = {c["key"]: from_json(c["value"]) for c in changes if not c["stale"]}
    assert [got[f"v/{i}"] for i in range(len(values))] == \
        [1, 2.5, math.inf, -math.inf, "text", None, True, [1, 2], {"a": [1, {"b": math.inf}]}]
    assert math.isnan(got["nan"])
    assert [c for c in changes if c["stale"]] == [
        {"key": "v/0", "value": 1, "stamp": changes[0]["stamp"], "writer": "hal:test",
         "stale": True}]
    assert changes[0]["writer"] == "hal:test"

    [event] = [m.data for m in rec.of("/r1/beehave/events/high")]
    assert event["kind"] == "ended" and event["subject"] == "tour/drive"
    assert event["status"] == "FAILED" and "wheel" in event["error"]
    assert event["detail"]["took_s"] == 1.5 and event["detail"]["why"].startswith("<object")

    assert {m.data["sim_time_s"] for m in rec.of("/r1/beehave/clock")} == {12.5}

    kinds = [m.data["kind"] for m in rec.of("/r2/beehave/events/low")]
    assert kinds[:2] == ["switch_requested", "started"] and "switch_completed" in kinds
    commands = [(m.data["hal"], m.data["method"], m.data["args"])
                for m in rec.of("/r2/beehave/outputs")]
    assert commands == [("debug", "set_leds", ["green"]), ("debug", "set_leds", ["red"])]
    writers = {m.data["writer"] for m in rec.of("/r2/beehave/blackboard")}
    assert "hal:debug" in writers
    # Every channel carries its JSON schema.
    assert rec.channels["/r2/beehave/outputs"].schema_name == "beehave.HalCommand"
    assert b'"required"' in rec.schemas["beehave.BlackboardChange"]


def test_ros_channels_read_back_with_the_ros2_decoder(tmp_path: Path) -> None:
    pytest.importorskip("rclpy")
    from mcap_ros2.reader import read_ros2_messages
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import LaserScan

    from beehave.ros.context import RosContext

    path = tmp_path / "ros.mcap"
    ros = RosContext()
    node = ros.create_node("rec_probe", namespace="rosbot")
    ros.start()
    try:
        odom_pub = node.create_publisher(Odometry, "odom", 10)
        scan_pub = node.create_publisher(LaserScan, "scan", 10)
        with Recorder(path, flush_period_s=0.05) as recorder:
            recorder.attach_topic(node, "odom", Odometry, prefix="rosbot")
            recorder.attach_topic(node, "scan", LaserScan, prefix="rosbot")
            assert wait_until(lambda: odom_pub.get_subscription_count() >= 1
                              and scan_pub.get_subscription_count() >= 1)
            for i in range(5):
                msg = Odometry()
                msg.header.frame_id = "map"
                msg.pose.pose.position.x = float(i)
                msg.twist.twist.linear.x = 0.5
                odom_pub.publish(msg)
            scan = LaserScan(angle_min=-1.0, ranges=[1.0, math.inf, 2.5])
            scan_pub.publish(scan)
            assert wait_until(lambda: recorder.stats.written >= 6
                              or _queued(recorder) >= 6)
            time.sleep(0.1)
    finally:
        ros.shutdown()
    odoms = list(read_ros2_messages(str(path), topics=["/rosbot/odom"]))
    assert [m.ros_msg.pose.pose.position.x for m in odoms] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert odoms[0].ros_msg.header.frame_id == "map"
    assert odoms[0].schema.name == "nav_msgs/msg/Odometry"
    assert odoms[0].channel.message_encoding == "cdr"
    [scan_back] = list(read_ros2_messages(str(path), topics=["/rosbot/scan"]))
    assert list(scan_back.ros_msg.ranges)[:1] == [1.0] and \
        math.isinf(scan_back.ros_msg.ranges[1])


def _queued(recorder: Recorder) -> int:
    return sum(len(c.queue) for c in recorder._writer.channels)


def test_a_crash_leaves_the_file_readable_up_to_the_last_chunk(tmp_path: Path) -> None:
    path = tmp_path / "crash.mcap"
    script = textwrap.dedent(f"""
        import os, sys, time
        from beehave.blackboard import Blackboard
        from beehave.recording import Recorder
        board = Blackboard()
        recorder = Recorder({str(path)!r}, flush_period_s=0.05)
        recorder.start()
        recorder.attach_blackboard(board, prefix="r")
        for i in range(500):
            board.set("count", i)
        # Wait until the chunk holding them is on disk, then more that never will be.
        while recorder.stats.written < 500:
            time.sleep(0.01)
        time.sleep(0.3)
        print("flushed", flush=True)
        for i in range(500, 100000):
            board.set("count", i)
        os._exit(3)  # dies without closing: no summary, no footer
    """)
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                          text=True, timeout=WALL_TIMEOUT_S)
    assert done.returncode == 3, done.stderr
    assert "flushed" in done.stdout
    rec = read_recording(path)
    assert rec.truncated
    counts = [m.data["value"] for m in rec.of("/r/beehave/blackboard")]
    assert counts[:500] == list(range(500))  # everything up to the last chunk, in order
    assert counts == list(range(len(counts)))
    # The standard reader, which trusts the summary, cannot read it: ours is needed.
    from mcap.reader import make_reader

    with open(path, "rb") as f, pytest.raises(Exception):  # noqa: B017
        list(make_reader(f).iter_messages())


class _Disk:
    """A file opened for the recorder (``open_file``); subclasses make its disk misbehave."""

    def __init__(self, path: Path) -> None:
        self._f: IO[bytes] = open(path, "wb")  # noqa: SIM115

    def write(self, data: bytes) -> int:
        return self._f.write(data)

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        self._f.close()


class _BlockedDisk(_Disk):
    """A file whose writes wait until ``release`` is set: a disk that stalls."""

    def __init__(self, path: Path, release: threading.Event) -> None:
        super().__init__(path)
        self._release = release
        self.blocked = threading.Event()

    def write(self, data: bytes) -> int:
        if not self._release.is_set():
            self.blocked.set()
            self._release.wait(WALL_TIMEOUT_S)  # bounded: a broken test must not hang the suite
        return super().write(data)


def test_a_slow_disk_drops_and_counts_instead_of_stalling(tmp_path: Path) -> None:
    path = tmp_path / "slow.mcap"
    release = threading.Event()
    disks: list[_BlockedDisk] = []

    def open_file(p: Path) -> Any:
        disk = _BlockedDisk(p, release)
        disks.append(disk)
        return disk

    board = Blackboard()
    low = LowLevelBehaviorManager(default="leds", stop_timeout_s=0.5)
    hardware = DebugRobot(battery_percentage=50.0)
    low.register("leds", LedLogic)
    low.hals.register(DebugHAL, robot=hardware)
    total = 5000
    release.set()  # the header goes through …
    with Recorder(path, queue_size=200, flush_period_s=0.05, open_file=open_file) as rec:
        rec.attach_blackboard(board, prefix="r")
        rec.attach_blackboard(low.blackboard, prefix="low")
        time.sleep(0.1)
        release.clear()  # … then the disk stalls
        board.set("first", 0)
        assert disks[0].blocked.wait(WALL_TIMEOUT_S)
        with low:
            # Every write returns while the writer is stuck on the disk, and the low
            # level goes on reacting: nothing waits for the recorder.
            for i in range(total):
                board.set("count", i)
            hardware.set_battery(10.0)
            assert wait_until(lambda: hardware.led_color == "red")
            assert not release.is_set()
            stats = rec.stats
            assert stats.dropped >= total - 200 - 1
            assert stats.dropped_by_channel["/r/beehave/blackboard"] >= total - 201
        release.set()
    final = rec.stats
    read = read_recording(path)
    written = len(read.of("/r/beehave/blackboard"))
    # Nothing vanished unaccounted: what is in the file plus what was dropped is all.
    assert written + final.dropped_by_channel["/r/beehave/blackboard"] == total + 1
    assert read.dropped() == final.dropped


def test_files_roll_over_by_size(tmp_path: Path) -> None:
    path = tmp_path / "roll.mcap"
    board = Blackboard()
    with Recorder(path, max_file_mb=0.02, flush_period_s=0.02) as rec:
        rec.attach_blackboard(board, prefix="r")
        for i in range(3000):
            board.set("payload", f"{i:06d}" + "x" * 40)
            if i % 300 == 0:
                time.sleep(0.03)  # let the writer keep up: no drops
    files = recording_files(path)
    assert len(files) >= 3 and files == rec.stats.files
    assert all(f.stat().st_size < 0.02e6 * 2 for f in files)
    from mcap.reader import make_reader

    for f in files:  # each part is a complete MCAP file on its own
        with open(f, "rb") as stream:
            summary = make_reader(stream).get_summary()
            assert summary is not None and summary.statistics is not None
            assert summary.statistics.message_count > 0
    values = [m.data["value"] for m in read_recording(path).of("/r/beehave/blackboard")]
    assert [int(v[:6]) for v in values] == list(range(3000))


def test_a_failing_disk_is_reported_and_never_breaks_the_writers(tmp_path: Path) -> None:
    class Full(_Disk):
        full = False

        def write(self, data: bytes) -> int:
            if Full.full:
                raise OSError(28, "No space left on device")
            return super().write(data)

    board = Blackboard()
    recorder = Recorder(tmp_path / "full.mcap", flush_period_s=0.02, queue_size=50,
                        open_file=Full)
    recorder.start()
    recorder.attach_blackboard(board, prefix="r")
    Full.full = True
    for i in range(1000):
        board.set("count", i)  # never raises
        if i % 100 == 0:
            time.sleep(0.01)
    with pytest.raises(RecordingError, match="No space left on device"):
        recorder.close()
    assert recorder.stats.dropped > 0


def test_bad_options_are_refused_with_the_reason(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"\*\.mcap"):
        Recorder(tmp_path / "run.bag")
    with pytest.raises(RecordingError, match="queue_size"):
        Recorder(tmp_path / "run.mcap", queue_size=0)
    with pytest.raises(RecordingError, match="max_file_mb"):
        Recorder(tmp_path / "run.mcap", max_file_mb=-1)
    with Recorder(tmp_path / "run.mcap") as rec:
        board = Blackboard()
        rec.attach_blackboard(board, prefix="a")
        with pytest.raises(RecordingError, match="own prefix"):
            rec.attach_blackboard(board, prefix="a")
    with pytest.raises(RecordingError, match="does not exist"):
        read_recording(tmp_path / "missing.mcap")
    (tmp_path / "not.mcap").write_text("hello")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_recording(tmp_path / "not.mcap")
    (tmp_path / "dir.mcap").mkdir()  # an OSError, said as a RecordingError (CLI: exit 2)
    with pytest.raises(RecordingError, match=r"'.*dir\.mcap' cannot be read: Is a directory"):
        read_recording(tmp_path / "dir.mcap")


def test_beehave_run_records_into_mcap(tmp_path: Path) -> None:
    """`beehave run ROBOT.yaml --record FILE` for real (ROS 2, both managers, bridge)."""
    pytest.importorskip("rclpy")
    import os

    path = tmp_path / "run.mcap"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(ROOT / "tests"), os.environ.get("PYTHONPATH")) if p)}
    done = subprocess.run([sys.executable, "-m", "beehave.cli", "run",
                           str(ROOT / "tests" / "data" / "rosbot.yaml"), "--duration-s", "1.5",
                           "--record", str(path)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=wall_timeout(1.5))
    assert done.returncode == 0, done.stderr
    assert f"into {path}" in done.stdout and "stopped cleanly" in done.stdout
    rec = read_recording(path)
    assert rec.prefixes == ["rosbot"]
    high = [m.data for m in rec.of("/rosbot/beehave/events/high")]
    assert ("switch_completed", "parked") in {(e["kind"], e["subject"]) for e in high}
    writers = {m.data["writer"] for m in rec.of("/rosbot/beehave/blackboard")}
    assert "hal:debug" in writers
    keys = {m.data["key"] for m in rec.of("/rosbot/beehave/blackboard")}
    assert "high_level/behavior" in keys  # the high level's state, over the bridge
    # The configured robot topics are channels of the file even when nothing was sent.
    for topic in ("odom", "scan", "cmd_vel", "battery_state"):
        assert rec.channels[f"/rosbot/{topic}"].encoding == "cdr"


def test_recording_options_in_the_configuration_are_checked() -> None:
    from beehave.config import parse_config
    from beehave.errors import ConfigError

    config = parse_config({"namespace": "r", "recording": {
        "topics": ["odom", {"name": "lift/state", "type": "std_msgs/msg/Float64"}],
        "max_file_mb": 50}})
    assert config.recording.max_file_mb == 50
    with pytest.raises(ConfigError, match=r"recording\.bogus: unknown key; valid keys: "
                                          r"topics, queue_size, max_file_mb"):
        parse_config({"namespace": "r", "recording": {"bogus": 1}})
    with pytest.raises(ConfigError, match=r"recording\.queue_size"):
        parse_config({"namespace": "r", "recording": {"queue_size": 0}})


def test_an_unknown_robot_topic_is_named_with_the_choices(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from beehave.config import parse_config

    config = parse_config({"namespace": "r", "recording": {"topics": ["odometry"]}},
                          source="r.yaml")
    robot: Any = SimpleNamespace(config=config,
                                 low=SimpleNamespace(hals=SimpleNamespace(node=object())))
    with Recorder(tmp_path / "r.mcap") as recorder:
        with pytest.raises(RecordingError, match=r"r\.yaml: recording\.topics\.0: unknown "
                                                 r"topic 'odometry'; give one of battery_state, "
                                                 r"cmd_vel, odom, scan or \{name: TOPIC"):
            recorder.attach_ros_topics(robot)
        with pytest.raises(RecordingError, match="unknown ROS 2 message type 'nope/msg/X'"):
            recorder.attach_ros_topics(robot, topics=[SimpleNamespace(name="x",
                                                                      type="nope/msg/X")])
        robot.low.hals.node = None
        with pytest.raises(RecordingError, match="after robot.start"):
            recorder.attach_ros_topics(robot)


def test_the_file_is_indexed_mcap_that_the_standard_readers_trust(tmp_path: Path) -> None:
    """The writer packs MCAP records itself (for speed): the summary, the statistics, the
    chunk and message indexes and the CRCs must be what MCAP tools rely on."""
    import struct
    import zlib

    import zstandard
    from mcap.reader import make_reader
    from mcap.records import Chunk, ChunkIndex, Footer, MessageIndex
    from mcap.stream_reader import StreamReader

    path = tmp_path / "indexed.mcap"
    board, events = Blackboard(), EventBus()
    total = 20_000  # several chunks of 512 kB
    with Recorder(path, flush_period_s=0.05) as recorder:
        recorder.attach_blackboard(board, prefix="r")
        recorder.attach_events(events, prefix="r", level="high")
        recorder.attach_blackboard(Blackboard(), prefix="silent")
        for i in range(total):
            board.set("laser/front_m", i * 0.25 + 0.1, writer="hal:laser")
            if i % 5000 == 0:
                events.emit(Event(EventKind.STARTED, f"step{i}"))
                time.sleep(0.02)  # let the writer keep up: no drops
    stats = recorder.stats
    assert stats.dropped == 0
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        by_topic = {c.topic: c.id for c in summary.channels.values()}
        assert set(by_topic) == {"/r/beehave/blackboard", "/r/beehave/events/high",
                                 "/r/beehave/log", "/silent/beehave/blackboard",
                                 "/beehave/recorder"}
        assert summary.statistics.message_count == stats.written
        counts = summary.statistics.channel_message_counts
        assert counts[by_topic["/r/beehave/blackboard"]] == total
        assert counts[by_topic["/r/beehave/events/high"]] == 4
        assert counts[by_topic["/r/beehave/log"]] == 4  # the same events, for Foxglove
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count >= 4
        values = [json.loads(m.data)["value"] for _, c, m in reader.iter_messages(
            topics=["/r/beehave/blackboard"], log_time_order=True)]
        assert values == [i * 0.25 + 0.1 for i in range(total)]
    # Every message index points at a message of its channel with its log time, and
    # every chunk index at its chunk and indexes; the footer's CRC covers the summary.
    data = path.read_bytes()
    records = list(StreamReader(str(path), emit_chunks=True, validate_crcs=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert len(chunks) == len(summary.chunk_indexes)
    indexed = 0
    for chunk, index in zip(chunks, summary.chunk_indexes, strict=True):
        assert isinstance(index, ChunkIndex) and index.compression == chunk.compression
        body = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size)
        assert zlib.crc32(body) == chunk.uncompressed_crc
        assert data[index.chunk_start_offset] == 0x06  # a Chunk record starts there
        for channel_id, offset in index.message_index_offsets.items():
            assert data[offset] == 0x07  # a MessageIndex record
            length = struct.unpack_from("<Q", data, offset + 1)[0]
            entry = MessageIndex.read(_stream(data[offset + 9:offset + 9 + length]))
            assert entry.channel_id == channel_id
            for log_time, at in entry.records:
                op, _, cid, _, log, publish = struct.unpack_from("<BQHIQQ", body, at)
                assert (op, cid, log, publish) == (0x05, channel_id, log_time, log_time)
                assert index.message_start_time <= log_time <= index.message_end_time
                indexed += 1
    assert indexed == stats.written
    [footer] = [r for r in records if isinstance(r, Footer)]
    summary_bytes = data[footer.summary_start:len(data) - 8 - 4]  # up to the footer's CRC
    assert zlib.crc32(summary_bytes) == footer.summary_crc


def _stream(data: bytes) -> Any:
    import io

    from mcap.data_stream import ReadDataStream

    return ReadDataStream(io.BytesIO(data))


def test_bulk_change_encoding_is_the_general_encoding_byte_for_byte() -> None:
    """The writer encodes blackboard changes in bulk through a fast path for plain
    numbers; every other value, a stale change, a batch, a key that changes writer, must
    come out exactly as the general (per change) encoder writes it."""
    import enum

    from beehave.blackboard import Change
    from beehave.recording.recorder import _encode_change, _encode_changes

    class Mode(enum.IntEnum):
        AUTO = 2

    class Meters(float):
        pass

    values: list[Any] = [1.5, 0.1 + 0.2, 1e16, -0.0, 5e-324, 3, -2**70, True, False, None,
                         math.inf, -math.inf, math.nan, Mode.AUTO, Meters(2.5), "a,b\"c",
                         "ünï", (1, 2.5), [math.nan], {"x": [math.inf]}, object(), 7.0]
    now = time.time()
    items: list[Any] = []
    for i, value in enumerate(values):
        key = ["k", "k,\"q\"", "ключ"][i % 3]  # few keys: their cached heads are reused
        writer = [None, "hal:x", "logic:y/z"][i % 4 % 3]
        change = Change(key, value, now + i * 1e-6, 0.0, writer, stale=i % 5 == 4)
        if i % 3 == 0 and not change.stale:
            items.append(change)  # how an unbound board queues a fresh change
        else:
            items.append((change, now + 1.0 + i, None if i % 3 == 1 else i))
    expected = [_encode_change(item) for item in items]
    times, datas = _encode_changes(items)
    assert list(zip(times, datas, strict=True)) == expected
    assert all(json.loads(d) for d in datas)  # strict JSON, also for NaN and infinities
    assert _encode_changes([]) == ([], [])


def test_a_raising_tap_is_removed_and_never_breaks_the_write(
        caplog: pytest.LogCaptureFixture) -> None:
    """Blackboard._store calls the taps inline (a recorder taps every set): a tap that
    raises is still logged and removed, the write and the other taps go on."""
    board = Blackboard()
    seen: list[Any] = []

    def broken(change: Any) -> None:
        raise RuntimeError("tap broke")

    board.tap(broken)
    board.tap(lambda change: seen.append(change.value))
    board.set("a", 1)
    board.set("a", 2)
    assert board.get("a") == 2 and seen == [1, 2]
    assert [r.message for r in caplog.records].count(
        f"blackboard tap {broken!r} raised on 'a'; it was removed") == 1
