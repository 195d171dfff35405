"""The Recorder: taps the blackboard, the event buses, the HALs and ROS 2 topics into MCAP.

::

    with Recorder("run.mcap") as recorder:
        robot = Robot(load_config("emili.yaml"))
        recorder.attach_robot(robot)          # before start: the first events count too
        with robot:
            recorder.attach_ros_topics(robot)  # after start: the robot's node exists
            ...

Several robots go into one file, each under its own prefix (default: its namespace), so
``/emili1/beehave/blackboard`` and ``/kobuki1/beehave/blackboard`` are separate channels.

Recording never blocks what it records: every tap only appends to a bounded queue that a
writer thread drains (:mod:`beehave.recording.writer`); a full queue drops and counts.
"""

from __future__ import annotations

import asyncio
import functools
import inspect
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self

from pydantic_core import to_json as _dumps

import beehave
from beehave.behavior import running_engines
from beehave.blackboard import Blackboard, Change, to_json
from beehave.clock import WallClock
from beehave.errors import RecordingError
from beehave.events import Event, EventBus, EventKind
from beehave.hal import HAL, check_duration_s
from beehave.recording import schema
from beehave.recording.writer import Channel, OpenFile, RecorderStats, WriterThread

if TYPE_CHECKING:
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.lowlevel import LowLevelBehaviorManager
    from beehave.robot import Robot

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_TOPICS", "STANDARD_TOPICS", "Recorder", "command_methods", "message_type"]

DEFAULT_TOPICS: tuple[str, ...] = ("odom", "scan", "cmd_vel", "battery_state")
"""The robot topics recorded when the configuration's ``recording.topics`` is not given."""

STANDARD_TOPICS = {"odom": "nav_msgs/msg/Odometry", "scan": "sensor_msgs/msg/LaserScan",
                   "cmd_vel": "geometry_msgs/msg/Twist",
                   "battery_state": "sensor_msgs/msg/BatteryState"}
"""The robot interface every beehave robot shares (DESIGN.md): topic → ROS 2 type. Other
topics are given with their type in ``recording.topics``."""


def message_type(type_name: str, *, where: str) -> type:
    """``std_msgs/msg/Float64`` → its Python class; an error names ``where``."""
    import importlib

    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise RecordingError(f"{where}: a ROS 2 message type looks like "
                             f"'std_msgs/msg/Float64', got {type_name!r}")
    try:
        return getattr(importlib.import_module(f"{parts[0]}.msg"), parts[2])  # type: ignore[no-any-return]
    except (ImportError, AttributeError) as exc:
        raise RecordingError(f"{where}: unknown ROS 2 message type {type_name!r}: "
                             f"{exc}") from None


LIFECYCLE = frozenset({"on_load", "run", "safe_state", "on_unload"})


def command_methods(cls: type[HAL]) -> list[str]:
    """The public methods a HAL class adds to drive hardware (``set_color``, ``show`` …):
    those defined by classes outside the framework (``beehave.*``), lifecycle hooks
    excepted. The recorder records their calls; a replay captures them instead."""
    names: set[str] = set()
    for klass in cls.__mro__:
        if klass is object or klass.__module__.split(".")[0] == "beehave":
            continue
        for name, attr in vars(klass).items():
            if not name.startswith("_") and name not in LIFECYCLE and inspect.isfunction(attr):
                names.add(name)
    return sorted(names)


def _encode_change(item: Change | tuple[Change, float, int | None]) -> tuple[int, bytes]:
    """A queued change → (log time in ns, its beehave.BlackboardChange JSON), in the
    writer's thread: the general path (:func:`_encode_changes` is the fast one)."""
    if type(item) is Change:  # no batch (no loop), not stale
        change, at, batch = item, item.stamp, None
    else:
        change, at, batch = item  # type: ignore[misc]
    # A stale change keeps the stamp of its write: it is logged when it went stale.
    value = change.value
    if type(value) is not float or value - value != 0.0:  # finite floats pass as they are
        value = to_json(value)
    body = {"key": change.key, "value": value, "stamp": change.stamp,
            "writer": change.writer, "stale": change.stale}
    if batch is not None:
        body["batch"] = batch
    return int(at * 1e9), _dumps(body)


_HEADS: dict[str, tuple[str | None, bool, bytes, bytes]] = {}
"""Per key: its writer and stale flag, and the JSON of such a change before its value and
after its stamp. A key is mostly written by one writer, so each is encoded once (up to
:data:`_HEADS_MAX` keys)."""
CLOCK_SAMPLE_S = 0.01
"""How far (sim seconds) a sim clock moves between two of its samples in the recording:
one ``/clock`` period at 100 Hz (see :meth:`Recorder.attach_clock`)."""

_HEADS_MAX = 10_000

_PLAIN = frozenset({float, int, bool, type(None)})
"""Value types whose JSON is a bare number or word: never a comma in it."""


def _head(change: Change) -> tuple[str | None, bool, bytes, bytes]:
    entry = (change.writer, change.stale,
             b'{"key":' + _dumps(change.key) + b',"value":',
             b',"writer":' + _dumps(change.writer) + b',"stale":' + _dumps(change.stale))
    if len(_HEADS) < _HEADS_MAX or change.key in _HEADS:
        _HEADS[change.key] = entry
    return entry


def _encode_changes(items: list[Any]) -> tuple[list[int], list[bytes]]:
    """:func:`_encode_change` for many at once, byte for byte, at a fraction of the cost;
    returns the log times and the messages.

    Nearly every sensor value is a plain number (float, int, bool, None), and every stamp
    is, so all of them go through the JSON encoder in *one* call, as a flat list; a
    number's JSON never holds a comma, so splitting the list's text gives each one's.
    Each message is then its key's cached text around them. A value of any other type
    is sent as None, and comes out ``null`` as a non-finite float is made to: those take
    the general path (which tags non-finite floats)."""
    if not items:
        return [], []
    numbers: list[Any] = []
    add = numbers.extend
    for item in items:
        change = item if type(item) is Change else item[0]
        value = change.value
        add((value if type(value) in _PLAIN else None, change.stamp))
    texts = iter(_dumps(numbers, inf_nan_mode="null")[1:-1].split(b","))
    times: list[int] = []
    datas: list[bytes] = []
    add_time, add_data, join, heads = times.append, datas.append, b"".join, _HEADS
    for item, value, stamp in zip(items, texts, texts, strict=True):
        if type(item) is Change:
            change, at, batch = item, item.stamp, None
        else:
            change, at, batch = item
        if value == b"null" and change.value is not None:
            at_ns, data = _encode_change(item)  # not a plain number, or not finite
            add_time(at_ns)
            add_data(data)
            continue
        entry = heads.get(change.key)
        if entry is None or entry[0] != change.writer or entry[1] is not change.stale:
            entry = _head(change)
        add_time(int(at * 1e9))
        add_data(join((entry[2], value, b',"stamp":', stamp, entry[3], b"}"
                       if batch is None else b',"batch":%d}' % batch)))
    return times, datas


class _BatchingTap:
    """Records a blackboard's changes, each stamped with its *batch*: changes of one batch
    were stored between the same two looks of the loop's logics at the blackboard, so a
    replay that hands a logic one batch per step shows it what it saw live
    (:mod:`beehave.recording.replay`).

    Why not wall time: a logic runs between two loop callbacks. Under load, two writes a
    logic saw apart can be stamped microseconds apart, and two it saw together
    milliseconds apart.

    How: ``batch`` advances in a callback (:meth:`_bump`) queued with ``call_soon`` just
    before a watcher wakes a waiting task, or a task starts watching (:meth:`on_wake`).
    The loop runs callbacks in FIFO order, so the bump runs right before that task's step:
    what was stored until then (in the loop's thread or another: a logic reads the
    blackboard, not only the changes its watcher hands it) has the batch the step saw,
    what is stored after it the next. A blackboard bound to no loop (no logic runs between
    writes) records no batches.
    """

    def __init__(self, board: Blackboard, channel: Channel) -> None:
        self.batch = 0
        self._bump_queued = False
        queue, append = channel.queue, channel.queue.append
        capacity, drop = channel.capacity, channel.count_drop

        def tap(change: Change) -> None:
            # Runs inside every set (in the thread that writes), so it is kept to a few
            # steps: Channel.put fused in, ``_loop`` read rather than the ``loop`` property
            # (a call: 4 % of a set), and a fresh change of an unbound board (a bare board,
            # a bench) queued as it is -- no tuple.
            if len(queue) >= capacity:
                drop()
            elif board._loop is not None:
                append((change, time.time() if change.stale else change.stamp, self.batch))
            elif change.stale:
                append((change, time.time(), None))
            else:
                append(change)

        self.tap = tap

    def on_wake(self) -> None:  # in the loop's thread
        if self._bump_queued:
            return  # the bump queued is still ahead of the task woken now (FIFO)
        try:
            asyncio.get_running_loop().call_soon(self._bump)
        except RuntimeError:  # delivered outside the loop (it closed): nothing runs there
            self.batch += 1
            return
        self._bump_queued = True

    def _bump(self) -> None:
        self._bump_queued = False
        self.batch += 1


def _encode_event(event: Event) -> tuple[int, bytes]:
    body = event.as_dict()
    body["detail"] = to_json(body["detail"])
    return int(event.stamp * 1e9), _dumps(body)


def _encode_log(item: tuple[str, Event]) -> tuple[int, bytes]:
    name, event = item
    t_ns = int(event.stamp * 1e9)
    if event.status == "FAILED" or event.kind is EventKind.SAFE_STATE_FAILED:
        level = 4  # ERROR
    elif event.kind in _WARN_KINDS or event.error is not None:
        level = 3  # WARNING
    else:
        level = 2  # INFO
    words = [event.kind.value, event.subject, event.status or ""]
    message = " ".join(w for w in words if w)
    if event.error is not None:
        message += f": {event.error}"
    return t_ns, _dumps({"timestamp": {"sec": t_ns // 1_000_000_000,
                                       "nsec": t_ns % 1_000_000_000},
                         "level": level, "message": message, "name": name, "file": "",
                         "line": 0})


_WARN_KINDS = {EventKind.STUCK, EventKind.SAFE_STATE_OVERDUE, EventKind.HOOK_FAILED,
               EventKind.LOCK_PREEMPTED, EventKind.LOOP_BLOCKED, EventKind.FALLBACK,
               EventKind.SWITCH_REJECTED}


def _encode_command(item: tuple[float, str, str, tuple[Any, ...], dict[str, Any]]
                    ) -> tuple[int, bytes]:
    stamp, hal, method, args, kwargs = item
    return int(stamp * 1e9), _dumps({"hal": hal, "method": method, "args": to_json(args),
                                     "kwargs": to_json(kwargs), "stamp": stamp})


def _identity(item: tuple[int, bytes]) -> tuple[int, bytes]:
    return item


class _EngineSampler:
    """Looks at the decision engines of a high level's running behaviours (in the writer's
    thread, at each drain: about 50 times a second) and records what changed: a structure
    the first time its structure_id is seen, an engine's :meth:`describe` when it differs
    from the one recorded last (a tree's ``tick`` alone is no change), and ``engine:
    null`` when a behaviour no longer runs one. The engines only answer ``describe()`` --
    what the live snapshot asks them too --, so recording them adds nothing to their
    threads; a state held shorter than one look (20 ms) may be missed.

    An engine whose ``describe()`` or ``structure()`` raises is skipped (the others are
    still recorded) and its first error kept in :attr:`errors` (by behaviour path), which
    :attr:`Recorder.engine_errors` shows: a user engine never stops the writer."""

    def __init__(self, high: HighLevelBehaviorManager, structures: Channel,
                 states: Channel) -> None:
        self.high = high
        self.structures = structures
        self.states = states
        self.recorded: set[str] = set()  # structure_ids written
        self.last: dict[str, dict[str, Any]] = {}  # path → describe() as compared
        self.errors: dict[str, Exception] = {}  # path → its engine's first error
        self.detached = False  # the recorder closes: one last look (what ended is in)

    def _failed(self, path: str, exc: Exception) -> None:
        if path not in self.errors:
            self.errors[path] = exc
            log.warning("recorder: the decision engine of %s cannot be recorded: %r",
                        path or "the high level", exc)

    def sample(self) -> None:
        try:
            found = running_engines(self.high.top)
        except Exception as exc:  # a user behaviour's children: never stop the writer
            self._failed("", exc)
            return
        stamp = time.time()
        t_ns = int(stamp * 1e9)
        seen = set()
        for path, engine in found:
            seen.add(path)
            try:
                self._look(path, engine, t_ns, stamp)
            except Exception as exc:  # a user engine's describe(): the others go on
                self._failed(path, exc)
        for path in [p for p in self.last if p not in seen]:
            del self.last[path]
            self.states.put((t_ns, _dumps({"path": path, "engine": None, "stamp": stamp})))

    def _look(self, path: str, engine: Any, t_ns: int, stamp: float) -> None:
        described = engine.describe()
        if not isinstance(described, dict):
            return
        # Compared as given (cheaper than encoding it at every look): encoded only when
        # it changed.
        compared = {k: v for k, v in described.items() if k != "tick"} \
            if "tick" in described else described
        if self.last.get(path) == compared:
            return
        sid = described.get("structure_id")
        if isinstance(sid, str) and sid not in self.recorded:
            structure = engine.structure()
            if structure is not None:
                self.recorded.add(sid)
                self.structures.put((t_ns, _dumps({
                    "path": path, "structure_id": sid,
                    "structure": to_json(structure), "stamp": stamp})))
        self.states.put((t_ns, _dumps({"path": path, "engine": to_json(described),
                                       "stamp": stamp})))
        self.last[path] = compared


class Recorder:
    """Records into the MCAP file ``path`` (see the module docstring); a context manager.

    ``queue_size``: messages each channel may hold waiting for the disk before new ones are
    dropped (and counted in :attr:`stats`). ``max_file_mb``: roll over into
    ``<stem>_001.mcap`` … once a file reaches that size (None: one file). ``flush_period_s``:
    how often the chunk in progress is written out -- at most this much is lost when the
    process dies. ``close_timeout_s``: how long :meth:`close` waits for the disk.
    ``open_file(path)``: how a file is opened for writing (default ``open(path, "wb")``;
    for unusual storage, and for tests that make the disk slow).
    """

    def __init__(self, path: str | Path, *, queue_size: int = 100_000,
                 max_file_mb: float | None = None, flush_period_s: float = 1.0,
                 close_timeout_s: float = 5.0, open_file: OpenFile | None = None) -> None:
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise RecordingError(f"queue_size must be an int >= 1, got {queue_size!r}")
        if max_file_mb is not None and (isinstance(max_file_mb, bool) or not isinstance(
                max_file_mb, (int, float)) or not 0 < max_file_mb < 1e6):
            raise RecordingError(f"max_file_mb must be a number of megabytes > 0 (or None for "
                                 f"one file), got {max_file_mb!r}")
        self.path = Path(path)
        if self.path.suffix != ".mcap":
            raise RecordingError(f"a recording is an MCAP file: name it *.mcap, got "
                                 f"{str(path)!r}")
        self.queue_size = queue_size
        self.close_timeout_s = check_duration_s("close_timeout_s", close_timeout_s)
        self._clocks: list[tuple[Channel, WallClock]] = []
        self._engines: list[_EngineSampler] = []  # those the writer looks at
        self._samplers: list[_EngineSampler] = []  # every one attached (their errors)
        self._writer = WriterThread(
            self.path, flush_period_s=check_duration_s("flush_period_s", flush_period_s),
            max_file_bytes=None if max_file_mb is None else int(max_file_mb * 1e6),
            open_file=open_file, metadata={"beehave": beehave.__version__},
            on_drain=self._sample)
        self._detach: list[Callable[[], None]] = []
        self._topics: dict[str, Channel] = {}
        self._started = False
        self._closed = False

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Open the file and start the writer thread (``with`` does it)."""
        if self._started:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer.start()
        self._started = True

    def close(self) -> RecorderStats:
        """Stop recording: detach every tap, write what is queued, finish the file(s).
        Returns the :attr:`stats`; a loss is logged as a warning. Raises
        :class:`RecordingError` when the disk failed (what was flushed stays readable)."""
        if self._closed:
            return self.stats
        self._closed = True
        for detach in reversed(self._detach):
            try:
                detach()
            except Exception as exc:  # a node already destroyed by the robot's shutdown
                log.debug("recorder: detaching: %r", exc)
        self._detach.clear()
        stats = self._writer.close(timeout_s=self.close_timeout_s) if self._started \
            else self.stats
        if stats.dropped:
            log.warning("recorder: %d message(s) dropped because the disk was slower than "
                        "the robot (by channel: %s); %s", stats.dropped,
                        stats.dropped_by_channel, self.path)
        if stats.error is not None:
            raise RecordingError(f"recording {str(self.path)!r} failed: {stats.error!r}; "
                                 f"{stats.written} message(s) were written") from stats.error
        return stats

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc is None:
            self.close()
            return
        try:  # leaving on an error already: a failed disk must not hide it
            self.close()
        except RecordingError as failed:
            exc.add_note(f"and the recording failed: {failed}")

    @property
    def stats(self) -> RecorderStats:
        """Messages written and dropped so far, and the files."""
        self._writer._count_drops()
        return self._writer.stats

    def _channel(self, prefix: str, name: str, encode: Callable[[Any], tuple[int, bytes]],
                 **kwargs: Any) -> Channel:
        if self._closed:
            raise RecordingError(f"recorder of {str(self.path)!r} is closed")
        topic = schema.topic(prefix, name)
        if topic in self._topics:
            raise RecordingError(f"channel {topic!r} is recorded already; give each robot "
                                 "its own prefix")
        channel = Channel(topic, encode=encode, capacity=self.queue_size,
                          schema_name=kwargs.pop("schema_name",
                                                 schema.CHANNEL_SCHEMA.get(name, "")),
                          **kwargs)
        self._topics[topic] = channel
        return self._writer.add(channel)

    # -- what to record ------------------------------------------------------------------

    def attach_blackboard(self, board: Blackboard, *, prefix: str = "") -> None:
        """Record every stored change of ``board`` (key, value, stamp, writer, stale) and,
        once it is bound to a loop, its batch: which writes the logics saw together
        (:class:`_BatchingTap`)."""
        # _encode_changes is _encode_change in bulk, byte for byte.
        channel = self._channel(prefix, schema.BLACKBOARD, _encode_change,
                                encode_batch=_encode_changes)
        batching = _BatchingTap(board, channel)
        self._detach.append(board.tap(batching.tap, on_wake=batching.on_wake))

    def attach_events(self, events: EventBus, *, prefix: str = "",
                      level: str = "high") -> None:
        """Record every event of ``events`` (a manager's ``.events``) on the ``high`` or
        ``low`` events channel."""
        if level not in ("high", "low"):
            raise RecordingError(f"level must be 'high' or 'low', got {level!r}")
        channel = self._channel(prefix, schema.EVENTS_HIGH if level == "high"
                                else schema.EVENTS_LOW, _encode_event)
        self._detach.append(events.subscribe(channel.put))
        # The same events for Foxglove's Log panel: one log channel per robot.
        log = self._topics.get(schema.topic(prefix, schema.LOG))
        if log is None:
            log = self._channel(prefix, schema.LOG, _encode_log)
        name = f"{prefix.strip('/') or 'robot'}/{level}"
        self._detach.append(events.subscribe(lambda e: log.put((name, e))))

    def attach_hal_outputs(self, low: LowLevelBehaviorManager, *, prefix: str = "") -> None:
        """Record the commands given to the low level's HALs (:func:`command_methods`:
        ``set_color``, ``show`` …), each HAL as soon as it is loaded."""
        channel = self._channel(prefix, schema.OUTPUTS, _encode_command)
        wrapped: list[tuple[HAL, str, Callable[..., Any]]] = []

        def wrap(name: str, hal: HAL) -> None:
            for method in command_methods(type(hal)):
                original = getattr(hal, method)
                wrapper = _recording_call(original, name, method, channel.put)
                setattr(hal, method, wrapper)  # shadows the class's method on this instance
                wrapped.append((hal, method, wrapper))

        def on_event(event: Event) -> None:
            if event.kind is EventKind.STARTED and event.subject.startswith("hal:"):
                name = event.subject[len("hal:"):]
                hal = low.hals.loaded.get(name)
                if hal is not None:
                    wrap(name, hal)

        unsubscribe = low.events.subscribe(on_event)
        for name, hal in low.hals.loaded.items():
            wrap(name, hal)

        def detach() -> None:
            unsubscribe()
            for hal, method, wrapper in wrapped:
                if hal.__dict__.get(method) is wrapper:
                    delattr(hal, method)

        self._detach.append(detach)

    def attach_clock(self, clock: WallClock, *, prefix: str = "") -> None:
        """Record ``clock.now()`` beside wall time, so a replay can follow the
        simulation's time (a run at ``--fast`` replays at robot speed): a sim clock
        whenever it has moved :data:`CLOCK_SAMPLE_S` since its last sample (the replay
        interpolates between samples, and a simulation in lockstep under load does not
        move evenly), any clock before each write of the recording (about 50 times a
        second)."""
        channel = self._channel(prefix, schema.CLOCK, _identity)
        self._clocks.append((channel, clock))
        on_set = getattr(clock, "on_set", None)
        if on_set is None:
            return
        last = [-math.inf]

        def sample(now_s: float) -> None:  # in the thread that moved the clock
            if now_s - last[0] >= CLOCK_SAMPLE_S - 1e-6:  # (a stamp in whole ns)
                last[0] = now_s
                stamp = time.time()
                channel.put((int(stamp * 1e9), _dumps({"sim_time_s": now_s, "stamp": stamp})))
        self._detach.append(on_set(sample))

    def attach_engines(self, high: HighLevelBehaviorManager, *, prefix: str = "") -> None:
        """Record the decision engines of ``high``'s running behaviours (state machines,
        trees …): each structure once per ``structure_id`` on
        ``/<robot>/beehave/engines/structure``, and each engine's state
        (``DecisionEngine.describe()``) whenever it changes on
        ``/<robot>/beehave/engines/state``, looked at about 50 times a second by the
        writer thread (:class:`_EngineSampler`), so ``beehave view`` draws the same graphs
        as the live page."""
        sampler = _EngineSampler(high,
                                 self._channel(prefix, schema.ENGINE_STRUCTURE, _identity),
                                 self._channel(prefix, schema.ENGINE_STATE, _identity))
        self._engines = [*self._engines, sampler]
        self._samplers.append(sampler)

        def detach() -> None:  # the writer thread looks once more, then lets go
            sampler.detached = True

        self._detach.append(detach)

    @property
    def engine_errors(self) -> dict[str, Exception]:
        """The decision engines that could not be recorded: behaviour path → the first
        error its engine's ``describe()`` or ``structure()`` raised (``""``: walking the
        running behaviours failed). The others were recorded all the same."""
        return {path: exc for sampler in self._samplers for path, exc in
                sampler.errors.items()}

    def _sample(self) -> None:  # in the writer thread, before each drain
        self._sample_clocks()
        engines = self._engines
        done = [s for s in engines if s.detached]  # detached before this look: its last
        for sampler in engines:
            sampler.sample()
        if done:
            self._engines = [s for s in self._engines if s not in done]

    def _sample_clocks(self) -> None:  # in the writer thread
        for channel, clock in self._clocks:
            if not getattr(clock, "started", True):
                continue  # no /clock yet: its 0 is no time of the simulation
            stamp = time.time()
            channel.put((int(stamp * 1e9), _dumps({"sim_time_s": clock.now(),
                                                   "stamp": stamp})))

    def attach_topic(self, node: Any, topic: str, msg_type: type, *, prefix: str = "",
                     qos: Any = 10) -> None:
        """Record the ROS 2 topic ``topic`` (relative to ``node``'s namespace) as
        ``ros2msg``/CDR: the serialized bytes are stored as they came, unparsed."""
        msgdef = schema.ros_msgdef(msg_type)
        channel = self._channel(prefix, topic.strip("/"), _identity,
                                schema_name=schema.ros_type_name(msg_type),
                                schema_encoding="ros2msg", schema_data=msgdef.encode(),
                                encoding="cdr")
        put = channel.put

        def on_message(data: bytes) -> None:  # in the ROS executor thread
            put((time.time_ns(), data))

        subscription = node.create_subscription(msg_type, topic, on_message, qos, raw=True)
        self._detach.append(functools.partial(node.destroy_subscription, subscription))

    def attach_robot(self, robot: Robot, *, prefix: str | None = None) -> None:
        """Record a :class:`~beehave.robot.Robot`'s blackboard, events of both levels, HAL
        commands, decision engines and (on sim time) its clock, under ``prefix`` (default:
        its namespace). Call it before ``robot.start()`` so the first switches and HAL
        loads are in; then :meth:`attach_ros_topics` once it runs."""
        prefix = robot.config.namespace if prefix is None else prefix
        if robot.low is not None:
            self.attach_blackboard(robot.low.blackboard, prefix=prefix)
            self.attach_events(robot.low.events, prefix=prefix, level="low")
            self.attach_hal_outputs(robot.low, prefix=prefix)
        if robot.high is not None:
            self.attach_events(robot.high.events, prefix=prefix, level="high")
            self.attach_engines(robot.high, prefix=prefix)
            if robot.low is None:
                self.attach_blackboard(robot.high.blackboard, prefix=prefix)
            if type(robot.high.clock) is not WallClock:
                self.attach_clock(robot.high.clock, prefix=prefix)

    def attach_ros_topics(self, robot: Robot, *, prefix: str | None = None,
                          topics: list[Any] | None = None) -> None:
        """Record the robot topics of its configuration's ``recording.topics`` (default
        :data:`DEFAULT_TOPICS`), on the low level's node, and every topic its behaviours
        subscribe to from now on (what a replay of the high level feeds them:
        :func:`beehave.recording.inputs.attach_behavior_inputs`). Call it after
        ``robot.start()``. A topic is a name of :data:`STANDARD_TOPICS` or ``{name: …,
        type: pkg/msg/Type}``; anything else raises :class:`RecordingError` naming the
        entry and the choices."""
        from beehave.recording.inputs import attach_behavior_inputs

        prefix = robot.config.namespace if prefix is None else prefix
        options = getattr(robot.config, "recording", None)
        wanted = list(topics if topics is not None else
                      (options.topics if options is not None else DEFAULT_TOPICS))
        node = robot.low.hals.node if robot.low is not None else None
        if node is None:
            raise RecordingError(f"robot {robot.config.namespace!r} has no low-level ROS 2 "
                                 "node: call attach_ros_topics after robot.start(), on the "
                                 "process that runs the low level")
        for i, entry in enumerate(wanted):
            where = f"{robot.config.source}: recording.topics.{i}"
            name = entry if isinstance(entry, str) else getattr(entry, "name", None)
            type_name = STANDARD_TOPICS.get(entry) if isinstance(entry, str) else \
                getattr(entry, "type", None)
            if not isinstance(name, str) or type_name is None:
                raise RecordingError(
                    f"{where}: unknown topic {entry!r}; give one of "
                    f"{', '.join(sorted(STANDARD_TOPICS))} or {{name: TOPIC, type: "
                    "pkg/msg/Type}")
            self.attach_topic(node, name, message_type(type_name, where=where),
                              prefix=prefix)
            if name == "odom" and type_name == STANDARD_TOPICS["odom"]:
                self.attach_transforms(node, name, prefix=prefix)
        attach_behavior_inputs(self, robot, prefix=prefix)

    def attach_transforms(self, node: Any, odom_topic: str = "odom", *,
                          prefix: str = "") -> None:
        """Record the robot's pose from its odometry as ``foxglove.FrameTransform`` (JSON)
        on ``/<robot>/beehave/tf``: the odometry's frame (``map``) to its child frame
        (``<robot>/base_link``, the laser scans' frame), so Foxglove's 3D panel places the
        scans on the map. (There is no ``tf2_msgs`` on PyPI for a ``/tf`` topic.)"""
        from nav_msgs.msg import Odometry

        channel = self._channel(prefix, schema.TF, _identity)

        def on_odom(msg: Any) -> None:  # in the ROS executor thread
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            channel.put((time.time_ns(), _dumps({
                "timestamp": {"sec": int(msg.header.stamp.sec),
                              "nsec": int(msg.header.stamp.nanosec)},
                "parent_frame_id": msg.header.frame_id,
                "child_frame_id": msg.child_frame_id,
                "translation": {"x": p.x, "y": p.y, "z": p.z},
                "rotation": {"x": q.x, "y": q.y, "z": q.z, "w": q.w}})))

        subscription = node.create_subscription(Odometry, odom_topic, on_odom, 10)
        self._detach.append(functools.partial(node.destroy_subscription, subscription))


def _recording_call(original: Callable[..., Any], hal: str, method: str,
                    put: Callable[[Any], None]) -> Callable[..., Any]:
    """``original`` that also records each successful call (a refused command -- out of
    range -- raised in the logic and drove nothing)."""
    if inspect.iscoroutinefunction(original):
        @functools.wraps(original)
        async def async_call(*args: Any, **kwargs: Any) -> Any:
            result = await original(*args, **kwargs)
            put((time.time(), hal, method, args, kwargs))
            return result

        return async_call

    @functools.wraps(original)
    def call(*args: Any, **kwargs: Any) -> Any:
        result = original(*args, **kwargs)
        put((time.time(), hal, method, args, kwargs))
        return result

    return call
