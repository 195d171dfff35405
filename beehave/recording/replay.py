"""Replay: a robot's low level run again on a recording, and the determinism check.

:func:`replay` builds the robot's low level from its configuration, replaces every HAL by
a *replay HAL* of the same name -- a subclass of the real one that opens no device and
captures each command (``set_color``, ``show`` …) instead of sending it -- and feeds the
recorded inputs into the blackboard at their recorded times: the values the HALs and the
ROS 2 bridge wrote (``hal:*``, ``ros:*`` writers, the high level's ``high_level/*``
state), the logic switches asked for from outside, and the HAL loads (the feed waits for
a HAL the recording loaded at that point, so values never overtake a load). The logics
run on them as they did live. What they produce -- HAL commands, their own blackboard
writes, the logic switches -- is compared with what the recording holds
(:func:`compare`): the first divergence is reported with its time and key.

Batches. The recorded writes carry the batch in which the logics saw them (see the
recorder's ``_BatchingTap``): one batch is fed in one go, then the loop turns a few times
so that the logics run, as they ran live between two batches. Recordings without batch
ids are grouped by wall time (:data:`BATCH_NS`).

Time. ``speed=1.0`` replays in real time, ``speed=N`` N times faster, ``speed=None`` as
fast as the logics keep up (each batch is followed by a few turns of the event loop, so
every logic sees every batch). A recording of a robot on sim time is paced by its sim
time (``/<robot>/beehave/clock``): a demo run at ``--fast`` replays at robot speed.
Times reported are seconds since the start of the recording, sim time when there is one.

The high level is not run again: its behaviours drive the robot in closed loop over ROS 2
(odometry in, ``cmd_vel`` out) and their switches come from outside; what the low level
learnt of them (``high_level/*``) is part of the replayed input.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from beehave.blackboard import from_json, to_json
from beehave.config import hal_names
from beehave.errors import RecordingError
from beehave.hal import HAL
from beehave.recording import schema
from beehave.recording.reader import Recording, read_recording
from beehave.recording.recorder import command_methods

if TYPE_CHECKING:
    from beehave.config import RobotConfig
    from beehave.lowlevel import LowLevelBehaviorManager

log = logging.getLogger(__name__)

__all__ = ["Divergence", "Output", "ReplayResult", "compare", "recorded_outputs", "replay",
           "replay_hal_class"]

REQUIRED = (schema.BLACKBOARD, schema.EVENTS_LOW, schema.OUTPUTS)
"""The channels of a robot a replay cannot do without."""

_YIELDS = 3
"""Loop turns after each fed input: a watcher wakes its logic in one, a logic that hands
on to a sub-logic needs another."""


@dataclass(frozen=True)
class Output:
    """One thing the low level produced: ``key`` names the stream (``emili_leds.set_color``
    for a HAL command, ``blackboard:leds/pattern`` for a logic's write, ``logic`` for a
    switch of the top-level logic), ``value`` what it was, ``t_s`` when (seconds since the
    recording's start)."""

    key: str
    value: Any
    t_s: float


@dataclass(frozen=True)
class Divergence:
    """Where a replay first did something else than the recording: the ``index``-th output
    of stream ``key`` at ``t_s``; ``expected`` / ``got`` are the two values (None: that
    side has no such output)."""

    key: str
    t_s: float
    index: int
    expected: Any
    got: Any

    def __str__(self) -> str:
        return (f"first divergence at t={self.t_s:.3f} s in {self.key!r} (output "
                f"#{self.index}): recorded {self.expected!r}, replayed {self.got!r}")


@dataclass
class ReplayResult:
    """What a replay did: the ``outputs`` the logics produced, the ``expected`` ones from
    the recording, the first ``divergence`` (None: the same), how many inputs were
    ``fed``, the recording ``span_s`` replayed and the ``wall_s`` it took."""

    outputs: list[Output]
    expected: list[Output]
    divergence: Divergence | None
    fed: int
    span_s: float
    wall_s: float
    sim_time: bool
    warnings: list[str] = field(default_factory=list)

    @property
    def speedup(self) -> float:
        """Recorded seconds replayed per wall-clock second."""
        return self.span_s / self.wall_s if self.wall_s > 0 else float("inf")


def compare(expected: list[Output], got: list[Output]) -> Divergence | None:
    """The earliest place where ``got`` differs from ``expected``, stream by stream (a
    stream: one ``key``, in order), or None when every stream is the same."""
    want: dict[str, list[Output]] = defaultdict(list)
    have: dict[str, list[Output]] = defaultdict(list)
    for o in expected:
        want[o.key].append(o)
    for o in got:
        have[o.key].append(o)
    first: Divergence | None = None
    for key in sorted({*want, *have}):
        a, b = want.get(key, []), have.get(key, [])
        for i in range(max(len(a), len(b))):
            x = a[i] if i < len(a) else None
            y = b[i] if i < len(b) else None
            if x is not None and y is not None and x.value == y.value:
                continue
            t = x.t_s if x is not None else y.t_s  # type: ignore[union-attr]
            if first is None or t < first.t_s:
                first = Divergence(key, t, i, None if x is None else x.value,
                                   None if y is None else y.value)
            break
    return first


# ---- the recording's side ------------------------------------------------------------------

class _Timeline:
    """Recording time (ns since the epoch) → seconds since its start; sim time when the
    robot ran on it."""

    def __init__(self, recording: Recording, prefix: str) -> None:
        self.start_ns = recording.start_ns
        self.sim = recording.sim_time(prefix)
        self.sim0 = self.sim(self.start_ns) if self.sim is not None else 0.0

    def __call__(self, t_ns: int) -> float:
        if self.sim is not None:
            return self.sim(t_ns) - self.sim0
        return (t_ns - self.start_ns) / 1e9


def _check_channels(recording: Recording, prefix: str) -> None:
    prefixes = recording.prefixes
    if prefix not in prefixes:
        shown = ", ".join(repr(p) for p in prefixes) or "none"
        raise RecordingError(f"{recording.files[0]}: no robot {prefix!r} in the recording; "
                             f"robots recorded: {shown} (the prefix is the robot's "
                             "namespace)")
    missing = [schema.topic(prefix, c) for c in REQUIRED
               if schema.topic(prefix, c) not in recording.channels]
    if missing:
        raise RecordingError(
            f"{recording.files[0]}: cannot replay robot {prefix!r}: channel(s) "
            f"{', '.join(missing)} missing; the recording has: "
            f"{', '.join(sorted(recording.channels)) or 'no channels'}")


def _is_logic(writer: object) -> bool:
    return isinstance(writer, str) and writer.startswith("logic:")


def recorded_outputs(recording: Recording, prefix: str) -> list[Output]:
    """What the low level produced in the recording, as :class:`Output` s."""
    timeline = _Timeline(recording, prefix)
    outputs: list[Output] = []
    bb, low, cmds = (schema.topic(prefix, c) for c in REQUIRED)
    for m in recording.messages:
        if m.topic == cmds:
            outputs.append(Output(f"{m.data['hal']}.{m.data['method']}",
                                  [m.data["args"], m.data["kwargs"]], timeline(m.log_time_ns)))
        elif m.topic == bb and _is_logic(m.data["writer"]):
            outputs.append(Output(f"blackboard:{m.data['key']}",
                                  [m.data["value"], m.data["stale"]], timeline(m.log_time_ns)))
        elif m.topic == low and m.data["kind"] == "switch_completed":
            outputs.append(Output("logic", m.data["subject"], timeline(m.log_time_ns)))
    return outputs


@dataclass(frozen=True)
class _Input:
    t_s: float
    kind: str  # "set", "switch", "hal"
    key: str
    value: Any = None
    writer: str | None = None
    stale: bool = False
    wall_ns: int = 0
    batch: int | None = None


BATCH_NS = 500_000
"""For recordings without batch ids (older than them, or of a blackboard bound to no
loop): writes within this much (wall time) of a batch's first are fed as one batch,
without letting the logics run in between. A guess -- what the HALs and the bridge write
from the ROS thread usually reaches the loop together -- that load can prove wrong;
recordings with batch ids say which writes the logics saw together."""


def _in_batch_order(inputs: list[_Input]) -> list[_Input]:
    """``inputs`` (in log order) with the writes in batch order.

    Log time and batch are taken a moment apart in the writer's thread, so where writes
    of two threads interleave their orders may disagree: between two other inputs
    (switches, HAL loads) the writes are sorted by batch, stably. A write whose key is
    written again with an earlier batch counts in that batch: it was never seen on its
    own, and it must still come before the write that replaced it.
    """
    if any(i.kind == "set" and i.batch is None for i in inputs):
        return inputs  # no batches (or not throughout): log order and the wall-time rule
    later: dict[str, int] = {}
    effective: list[_Input] = []
    for item in reversed(inputs):
        if item.kind == "set":
            assert item.batch is not None
            batch = min(item.batch, later.get(item.key, item.batch))
            later[item.key] = batch
            item = replace(item, batch=batch)
        effective.append(item)
    effective.reverse()
    ordered: list[_Input] = []
    run: list[_Input] = []
    for item in effective:
        if item.kind == "set":
            run.append(item)
            continue
        ordered.extend(sorted(run, key=lambda i: i.batch or 0))
        run = []
        ordered.append(item)
    ordered.extend(sorted(run, key=lambda i: i.batch or 0))
    return ordered


def _inputs(recording: Recording, prefix: str) -> list[_Input]:
    timeline = _Timeline(recording, prefix)
    bb, low, _ = (schema.topic(prefix, c) for c in REQUIRED)
    inputs: list[_Input] = []
    first_switch = True
    switching = False
    top: str | None = None
    for m in recording.messages:
        if m.topic == bb and not _is_logic(m.data["writer"]):
            inputs.append(_Input(timeline(m.log_time_ns), "set", m.data["key"],
                                 from_json(m.data["value"]), m.data["writer"],
                                 bool(m.data["stale"]), m.log_time_ns, m.data.get("batch")))
        elif m.topic == low:
            kind, subject, detail = m.data["kind"], m.data["subject"], m.data["detail"]
            if kind == "switch_requested":
                switching = True
                if not detail.get("fallback"):
                    if not first_switch:  # the first is the start of the default logic
                        inputs.append(_Input(timeline(m.log_time_ns), "switch", subject))
                    first_switch = False
            elif kind == "switch_completed":
                switching, top = False, subject
            elif kind == "started" and subject.startswith("hal:") and subject.count(":") == 1:
                inputs.append(_Input(timeline(m.log_time_ns), "hal", subject[len("hal:"):]))
            elif (kind == "ended" and subject == top and not switching
                  and m.data["status"] == "INTERRUPTED"):
                # The top-level logic was stopped without a switch: the recorded low level
                # shut down here. What follows (HALs unloaded, entries marked stale) is
                # the replay's own shutdown's to produce, not an input.
                break
    return _in_batch_order(inputs)


# ---- the replay's side ---------------------------------------------------------------------

Capture = Callable[[str, str, tuple[Any, ...], dict[str, Any]], None]


def replay_hal_class(cls: type[HAL], name: str, capture: Capture) -> type[HAL]:
    """A subclass of HAL ``cls`` for replays: it opens nothing (``on_load``, ``run`` and
    ``on_unload`` do nothing), and each of its :func:`command_methods` calls
    ``capture(hal, method, args, kwargs)`` instead of driving hardware. Its ``safe_state``
    is the real one, so the commands a safe state gives are captured too."""

    async def on_load(self: HAL) -> None:
        return None

    async def run(self: HAL) -> None:
        return None

    def on_unload(self: HAL) -> None:
        return None

    attrs: dict[str, Any] = {"name": name, "on_load": on_load, "run": run,
                             "on_unload": on_unload, "__module__": __name__,
                             "__doc__": f"Replay stand-in for HAL {name!r} ({cls.__qualname__})."}
    for method in command_methods(cls):
        attrs[method] = _capturing(getattr(cls, method), name, method, capture)
    return type(f"Replay{cls.__name__}", (cls,), attrs)


def _capturing(original: Callable[..., Any], hal: str, method: str,
               capture: Capture) -> Callable[..., Any]:
    if inspect.iscoroutinefunction(original):
        async def async_captured(self: HAL, *args: Any, **kwargs: Any) -> None:
            capture(hal, method, args, kwargs)

        return async_captured

    def captured(self: HAL, *args: Any, **kwargs: Any) -> None:
        capture(hal, method, args, kwargs)

    return captured


def replay(recording: Recording | str | Path, config: RobotConfig, *,
           prefix: str | None = None, speed: float | None = 1.0,
           from_s: float | None = None, to_s: float | None = None,
           hal_wait_s: float = 2.0) -> ReplayResult:
    """Run ``config``'s low level on ``recording`` (see the module docstring) and compare.

    ``prefix``: the robot in the recording (default: the configuration's namespace).
    ``speed``: 1.0 real time, N times faster, None as fast as possible. ``from_s`` /
    ``to_s``: the window to replay, in seconds since the recording's start; the state
    before ``from_s`` is set at once, and only outputs inside the window are compared.
    Raises :class:`RecordingError` when the robot or a channel a replay needs is not in
    the recording (naming them and what is there).
    """
    from beehave.robot import Robot

    if speed is not None and not (isinstance(speed, (int, float)) and 0 < speed < 1e9):
        raise RecordingError(f"speed must be a number > 0 (or None: as fast as possible), "
                             f"got {speed!r}")
    rec = recording if isinstance(recording, Recording) else read_recording(recording)
    prefix = config.namespace if prefix is None else prefix
    _check_channels(rec, prefix)
    timeline = _Timeline(rec, prefix)
    inputs = _inputs(rec, prefix)
    lo = from_s if from_s is not None else float("-inf")
    hi = to_s if to_s is not None else float("inf")
    expected = [o for o in recorded_outputs(rec, prefix) if lo <= o.t_s <= hi]

    robot = Robot(config, only="low")
    low = robot.low
    if low is None:
        raise RecordingError(f"{config.source}: the configuration has no low level to replay")
    state = _ReplayState()
    warnings: list[str] = []

    def capture(hal: str, method: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        if state.comparing:
            state.outputs.append(Output(f"{hal}.{method}", [to_json(list(args)),
                                                            to_json(kwargs)], state.now_s))

    for name in hal_names(config):
        cls, params = low.hals.resolve(name)
        low.hals.register(replay_hal_class(cls, name, capture), name=name, **params)

    def on_event(event: Any) -> None:
        if not state.comparing:
            return
        if event.kind.value == "switch_completed":
            state.outputs.append(Output("logic", event.subject, state.now_s))

    def on_change(change: Any) -> None:
        if state.comparing and _is_logic(change.writer):
            state.outputs.append(Output(f"blackboard:{change.key}",
                                        [to_json(change.value), change.stale], state.now_s))

    unsubscribe = low.events.subscribe(on_event)
    remove_tap = low.blackboard.tap(on_change)
    state.comparing = from_s is None
    began = time.monotonic()
    fed = 0
    try:
        with low:
            fed = low.call(_feed(low, inputs, state, speed=speed, lo=lo, hi=hi,
                                 hal_wait_s=hal_wait_s, warnings=warnings))
            if to_s is not None:
                state.comparing = False  # the shutdown's safe states lie outside the window
    finally:
        remove_tap()
        unsubscribe()
    wall = time.monotonic() - began
    span = (min(hi, inputs[-1].t_s) if inputs else 0.0) - (max(lo, 0.0) if inputs else 0.0)
    got = state.outputs
    return ReplayResult(got, expected, compare(expected, got), fed, max(span, 0.0), wall,
                        timeline.sim is not None, warnings)


class _ReplayState:
    def __init__(self) -> None:
        self.now_s = 0.0
        self.comparing = True
        self.outputs: list[Output] = []


async def _feed(low: LowLevelBehaviorManager, inputs: list[_Input], state: _ReplayState, *,
                speed: float | None, lo: float, hi: float, hal_wait_s: float,
                warnings: list[str]) -> int:
    loop = asyncio.get_running_loop()
    board = low.blackboard
    fed = 0
    origin_wall: float | None = None
    origin_t = 0.0
    batch_ns = 0  # wall time of the first write of the batch being fed
    for n, item in enumerate(inputs):
        if item.t_s > hi:
            break
        catching_up = item.t_s < lo
        if not catching_up:
            if not state.comparing:
                # The state at from_s is in: let the logics settle on it (what they answer
                # to it was answered before the window) before their outputs count.
                for _ in range(10 * _YIELDS):
                    await asyncio.sleep(0)
                state.comparing = True
            if speed is not None:
                if origin_wall is None:
                    origin_wall, origin_t = loop.time(), item.t_s
                delay = (item.t_s - origin_t) / speed - (loop.time() - origin_wall)
                if delay > 0:
                    await asyncio.sleep(delay)
        state.now_s = item.t_s
        if item.kind == "set":
            board.set(item.key, item.value, writer=item.writer, stale=item.stale)
        elif item.kind == "switch":
            try:
                await low.switch_async(item.key)
            except Exception as exc:  # the recording asked for it; say it did not work
                warnings.append(f"t={item.t_s:.3f} s: switch to logic {item.key!r} "
                                f"failed: {exc!r}")
        elif item.kind == "hal":
            deadline = loop.time() + hal_wait_s
            while item.key not in low.hals.loaded and loop.time() < deadline:
                await asyncio.sleep(0.001)
            if item.key not in low.hals.loaded:
                warnings.append(f"t={item.t_s:.3f} s: HAL {item.key!r} was loaded in the "
                                f"recording but not in the replay within {hal_wait_s} s")
        fed += 1
        # One recorded batch is fed in one go (one loop callback: this step), then the
        # logics run, as they ran live between two batches.
        following = inputs[n + 1] if n + 1 < len(inputs) else None
        if not batch_ns:
            batch_ns = item.wall_ns
        if following is None or not item.kind == following.kind == "set":
            batched = False
        elif item.batch is not None and following.batch is not None:
            batched = following.batch == item.batch
        else:
            batched = following.wall_ns - batch_ns < BATCH_NS
        if not batched:
            batch_ns = 0
        if not catching_up and not batched:
            for _ in range(_YIELDS):
                await asyncio.sleep(0)
    for _ in range(10 * _YIELDS):  # let the logics answer the last inputs
        await asyncio.sleep(0)
    return fed
