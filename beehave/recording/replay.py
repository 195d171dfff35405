"""Replay: a robot's logics and behaviours run again on a recording, and the determinism check.

Low level. :func:`replay` builds the robot's low level from its configuration, replaces
every HAL by a *replay HAL* of the same name -- a subclass of the real one that opens no
device and captures each command (``set_color``, ``show`` …) instead of sending it -- and
feeds the recorded inputs into the blackboard at their recorded times: the values the HALs
and the ROS 2 bridge wrote (``hal:*``, ``ros:*`` writers, the high level's
``high_level/*`` state), the logic switches asked for from outside, and the HAL loads (the
feed waits for a HAL the recording loaded at that point, so values never overtake a load).

High level. When the configuration has behaviours (and the recording their events), its
HighLevelBehaviorManager runs too, on a :class:`~beehave.recording.replay_node.ReplayNode`
instead of a ROS node: what behaviours and actions publish (``cmd_vel``, the lift's
command, sounds) is captured, not sent, and their subscriptions get the recorded messages
of their topics (odometry, scan, the lift's state, another agent's orders: the recorder
records every topic a behaviour subscribes to, :mod:`beehave.recording.inputs`). The
switch requests that came from outside (events with ``source: external``) are asked again
at their recorded times; those the behaviours asked for they ask for again by themselves.
Service and action clients cannot be replayed (their answers are not recorded): making one
fails the action with a :class:`RecordingError` that names it. No ROS node is made.

What both produce -- HAL commands, logic writes and switches; top-level switches and each
behaviour's and action's start and end with its status -- is compared with what the
recording holds (:func:`compare`): the first divergence is reported with its time and key.

Keeping pace. The high level runs in threads, the feed in the low level's event loop. The
feed moves the high level's clock (a :class:`~beehave.recording.replay_node.ReplayClock`)
to each input's recorded time, and after every step waits until the high level has
*settled*: each of its threads waits again -- on the clock, on a condition or event, or
elsewhere using no CPU for two switch intervals -- and none is due to run. A driving
action's lockstep hold stops the clock at each control period, as it stops a simulator.
Before each input of the high
level, the feed also waits (bounded) until the replayed behaviours have done what the
recorded ones had done :data:`SYNC_MARGIN_S` earlier, so that a behaviour polling on wall
time (a queue's ``get(timeout=…)``) cannot fall behind. Once it has done all the recorded
ones did before the next switch requested from outside or before their shutdown, a timed
wait that live would have ended after that does not end until then: live steps come a
little late, replayed ones exactly on time, so a step that the switch or the shutdown cut
off live would otherwise start (see :meth:`_HighSide.advance`).

Batches. The recorded writes carry the batch in which the logics saw them (see the
recorder's ``_BatchingTap``): one batch is fed in one go, then the loop turns a few times
so that the logics run, as they ran live between two batches. Recordings without batch
ids are grouped by wall time (:data:`BATCH_NS`). The high level's inputs are fed between
two batches only.

Time. ``speed=1.0`` replays in real time, ``speed=N`` N times faster, ``speed=None`` as
fast as the logics and behaviours keep up. A recording of a robot on sim time is paced by
its sim time (``/<robot>/beehave/clock``): a demo run at ``--fast`` replays at robot
speed. Times reported are seconds since the start of the recording, sim time when there
is one.
"""

from __future__ import annotations

import asyncio
import bisect
import inspect
import logging
import math
import sys
import threading
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
from beehave.recording.inputs import input_channel
from beehave.recording.reader import Recording, read_recording
from beehave.recording.recorder import command_methods
from beehave.recording.replay_node import Captured, ReplayClock, ReplayNode
from beehave.threads import WorkerState

if TYPE_CHECKING:
    from beehave.config import RobotConfig
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.lowlevel import LowLevelBehaviorManager

log = logging.getLogger(__name__)

__all__ = ["Captured", "Divergence", "Output", "ReplayResult", "compare", "recorded_outputs",
           "replay", "replay_hal_class"]

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
    commands: list[Captured] = field(default_factory=list)
    """What the replayed behaviours and actions published: captured, not sent."""
    high: bool = False
    """Whether the high level ran too (the configuration has one and the recording its
    events)."""
    cut_s: float | None = None
    """Where the comparison stopped short of the replayed window because the recording
    does (it was cut off, or damaged from there): seconds since its start."""
    damaged: list[str] = field(default_factory=list)
    """The damaged parts of the recording (:meth:`Recording.describe_damage`): only what
    came before the first was compared, and the verdict is incomplete."""

    @property
    def speedup(self) -> float:
        """Recorded seconds replayed per wall-clock second."""
        return self.span_s / self.wall_s if self.wall_s > 0 else float("inf")


WINDOW_EDGE_S = 0.5
"""At the end of a window shorter than the run (``--to``, a cut-off or damaged
recording): an output that only one side has within this many seconds of the end is the
other side's just past it -- the two clocks differ by a step -- not a divergence."""


def _trim_window_end(expected: list[Output], got: list[Output],
                     hi: float) -> tuple[list[Output], list[Output]]:
    """Drop, per stream, the outputs that only one side has and that come within
    :data:`WINDOW_EDGE_S` of the window's end ``hi``."""
    count_a: dict[str, int] = defaultdict(int)
    count_b: dict[str, int] = defaultdict(int)
    for o in expected:
        count_a[o.key] += 1
    for o in got:
        count_b[o.key] += 1

    def keep(outputs: list[Output], other: dict[str, int]) -> list[Output]:
        seen: dict[str, int] = defaultdict(int)
        kept = []
        for o in outputs:
            seen[o.key] += 1
            if seen[o.key] > other[o.key] and o.t_s > hi - WINDOW_EDGE_S:
                continue
            kept.append(o)
        return kept

    return keep(expected, count_b), keep(got, count_a)


def _drop_shutdown_extras(expected: list[Output], got: list[Output],
                          shutdown_s: float) -> list[Output]:
    """From the recorded shutdown's start on, the live logics raced the shutdown: an output
    they had no time to give before their HALs' safe states, the replay (fed every input up
    to there) may give. Drop, per stream, the replayed outputs after ``shutdown_s`` that
    the recording's outputs after it do not contain, in order; the recorded ones are all
    still compared."""
    after: dict[str, list[Any]] = defaultdict(list)
    for o in expected:
        if o.t_s >= shutdown_s:
            after[o.key].append(o.value)
    kept: list[Output] = []
    matched: dict[str, int] = defaultdict(int)
    for o in got:
        if o.t_s < shutdown_s or o.key.startswith("high"):
            kept.append(o)
            continue
        want = after.get(o.key, [])
        i = matched[o.key]
        if i < len(want) and o.value == want[i]:
            matched[o.key] += 1
            kept.append(o)
        # else: an extra, dropped. A recorded output the replay lacks stays missing from
        # ``got``: a safe state that commands something else is still a divergence.
    return kept


def compare(expected: list[Output], got: list[Output]) -> Divergence | None:
    """The earliest place where ``got`` differs from ``expected``, stream by stream (a
    stream: one ``key``, in order), or None when every stream is the same."""
    want: dict[str, list[Output]] = defaultdict(list)
    have: dict[str, list[Output]] = defaultdict(list)
    for o in expected:
        want[o.key].append(o)
    for o in got:
        have[o.key].append(o)
    # At the same time, the one produced first: a switch requested too early comes before
    # the start of the behaviour it switched to.
    made = {id(o): n for n, o in enumerate(got)}
    made.update({id(o): len(got) + n for n, o in enumerate(expected)})
    first: Divergence | None = None
    rank: tuple[float, int] = (math.inf, 0)
    for key in sorted({*want, *have}):
        a, b = want.get(key, []), have.get(key, [])
        for i in range(max(len(a), len(b))):
            x = a[i] if i < len(a) else None
            y = b[i] if i < len(b) else None
            if x is not None and y is not None and x.value == y.value:
                continue
            # When the two differ: the earlier of the two (a replayed behaviour that
            # switches too early diverges when it switches, not when the recorded did).
            t = min(o.t_s for o in (x, y) if o is not None)
            here = (t, made[id(y if y is not None else x)])
            if here < rank:
                rank = here
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
    return [Output(key, value, timeline(m.log_time_ns))
            for m, key, value in _low_outputs(recording, prefix)]


def _low_outputs(recording: Recording, prefix: str) -> list[tuple[Any, str, Any]]:
    """The low level's outputs in the recording: (message, stream, value)."""
    found: list[tuple[Any, str, Any]] = []
    bb, low, cmds = (schema.topic(prefix, c) for c in REQUIRED)
    for m in recording.messages:
        if m.topic == cmds:
            found.append((m, f"{m.data['hal']}.{m.data['method']}",
                          [m.data["args"], m.data["kwargs"]]))
        elif m.topic == bb and _is_logic(m.data["writer"]):
            found.append((m, f"blackboard:{m.data['key']}", [m.data["value"], m.data["stale"]]))
        elif m.topic == low and m.data["kind"] == "switch_completed":
            found.append((m, "logic", m.data["subject"]))
    return found


HIGH_SWITCH = "high:switch"
"""The stream of the high level's top-level switches (requested, completed, superseded,
rejected, fallback)."""

_SWITCH_KINDS = {"switch_requested": "requested", "switch_completed": "completed",
                 "switch_superseded": "superseded", "switch_rejected": "rejected"}
_NOT_COMPARED = {"message_rejected", "agent_name_lost", "safe_state_overdue"}
"""Events of the high level that say how busy the host was or what other agents sent,
not what the behaviours decided."""


def _high_output(kind: str, subject: str, status: str | None,
                 error_type: str | None) -> tuple[str, Any] | None:
    """The stream and value a high-level event adds to the determinism check: switches
    go to :data:`HIGH_SWITCH`, the rest to ``high:<path>`` (one stream per behaviour or
    action: its thread orders them). An error counts by its type: its text may carry
    positions and times that differ in the last digit."""
    if kind in _SWITCH_KINDS:
        return HIGH_SWITCH, [_SWITCH_KINDS[kind], subject]
    if kind == "fallback":
        return HIGH_SWITCH, ["fallback", subject, status]
    if kind in _NOT_COMPARED or (kind == "safe_state_ran" and status == "STUCK"):
        # A STUCK action's safe state is forced from another thread: when it returns,
        # relative to the action's other events, is the host's timing.
        return None
    return f"high:{subject}", [kind, status, error_type]


def _is_safe_state_ran(output: Output) -> bool:
    return (output.key.startswith("high:") and isinstance(output.value, list)
            and bool(output.value) and output.value[0] == "safe_state_ran")


def _error_type(error: Any) -> str | None:
    if error is None:
        return None
    if isinstance(error, BaseException):
        return type(error).__name__
    return str(error).split("(", 1)[0]


def recorded_high_outputs(recording: Recording, prefix: str) -> list[Output]:
    """What the high level did in the recording (its switches, and each behaviour's and
    action's lifecycle), as :class:`Output` s."""
    timeline = _Timeline(recording, prefix)
    outputs: list[Output] = []
    for m in recording.of(schema.topic(prefix, schema.EVENTS_HIGH)):
        d = m.data
        made = _high_output(d["kind"], d["subject"], d["status"], _error_type(d["error"]))
        if made is not None:
            outputs.append(Output(made[0], made[1], timeline(m.log_time_ns)))
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
    outputs_before: int = 0  # the low level's outputs the recording logged before it


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
                        inputs.append(_Input(timeline(m.log_time_ns), "switch", subject,
                                             wall_ns=m.log_time_ns))
                    first_switch = False
            elif kind == "switch_completed":
                switching, top = False, subject
            elif kind == "started" and subject.startswith("hal:") and subject.count(":") == 1:
                inputs.append(_Input(timeline(m.log_time_ns), "hal", subject[len("hal:"):],
                                     wall_ns=m.log_time_ns))
            elif (kind == "ended" and subject == top and not switching
                  and m.data["status"] == "INTERRUPTED"):
                # The top-level logic was stopped without a switch: the recorded low level
                # shut down here. What follows (HALs unloaded, entries marked stale) is
                # the replay's own shutdown's to produce, not an input.
                break
    # What the logics had produced when each input came: the feed waits for as much
    # (see _feed), so that a logic still starting up (loading its HALs) sees the inputs
    # in the batches it saw them live.
    # Outputs logged less than BATCH_NS before an input may be its effect all the same
    # (a safe state's command and the stale marks of the shutdown that gave it): not those.
    done = sorted(m.log_time_ns for m, _, _ in _low_outputs(recording, prefix))
    return [replace(i, outputs_before=bisect.bisect_left(done, i.wall_ns - BATCH_NS))
            for i in _in_batch_order(inputs)]


_COMMANDS = ("request", "pause", "resume")
"""The kinds of :class:`_HighInput` that a caller outside the high level gave it."""


@dataclass(frozen=True)
class _HighInput:
    """What the high level got from outside at ``t_s``: a message (``kind="msg"``: the
    CDR ``value`` of ``channel``, for the subscriptions to ``key``, a resolved topic) or
    a switch request (``kind="request"``: behaviour ``key``, parameters ``value``), a
    pause (``kind="pause"``) or a resume (``kind="resume"``).
    ``before``: how many high-level events the recording had :data:`SYNC_MARGIN_S`
    before it; ``logged_before``: how many it had logged before it at all."""

    t_s: float
    wall_ns: int
    kind: str
    key: str
    value: Any = None
    channel: str = ""
    before: int = 0
    logged_before: int = 0


def _topic_of(channel: str, prefix: str, namespace: str) -> str:
    """The resolved ROS topic the recorded ``channel`` carried (inverse of
    :func:`~beehave.recording.inputs.input_channel`)."""
    head = schema.topic(prefix, "")
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    if prefix.strip("/") and channel.startswith(head):
        return f"{ns}/{channel[len(head):]}"
    return channel


def _high_inputs(recording: Recording, prefix: str, namespace: str) -> list[_HighInput]:
    """The high level's inputs in the recording, in log order: the switch requests, pauses
    and resumes that came from outside (the first switch -- the start of the default
    behaviour -- excepted; a recording older than the ``source`` field counts every
    request as from outside) and
    the messages of every ROS 2 channel of the robot (and the global ones): those nobody
    subscribes to in the replay are held a moment, then dropped."""
    timeline = _Timeline(recording, prefix)
    events = schema.topic(prefix, schema.EVENTS_HIGH)
    own = schema.topic(prefix, "")
    robots = [schema.topic(p, "") for p in recording.prefixes if p]

    def fed(topic: str, encoding: str) -> bool:
        if encoding != "cdr":
            return False
        return topic.startswith(own) or not any(topic.startswith(r) for r in robots)

    ros = {t for t, info in recording.channels.items() if fed(t, info.encoding)}
    inputs: list[_HighInput] = []
    # An input waits for the events the recording had SYNC_MARGIN_S before it: the replay's
    # clock moves in the recording's steps, so a behaviour's timed step may come that much
    # later than it did live.
    logged = recording.of(events)
    stamps = [timeline(m.log_time_ns) for m in logged]
    walls = [m.log_time_ns for m in logged]
    first = True

    def before(t_s: float) -> int:
        return bisect.bisect_right(stamps, t_s - SYNC_MARGIN_S)

    for m in recording.messages:
        if m.topic == events:
            d = m.data
            if d["kind"] == "switch_requested":
                source = d["detail"].get("source", "external")
                if source == "external" and not first:
                    params = d["detail"].get("params") or {}
                    t_s = timeline(m.log_time_ns)
                    inputs.append(_HighInput(
                        t_s, m.log_time_ns, "request", d["subject"], params,
                        before=before(t_s),
                        logged_before=bisect.bisect_left(walls, m.log_time_ns)))
                first = False
            elif (d["kind"] == "pause_requested"
                  or (d["kind"] == "resumed" and d["detail"].get("by") == "resume")) \
                    and d["detail"].get("source", "external") == "external":
                t_s = timeline(m.log_time_ns)
                inputs.append(_HighInput(
                    t_s, m.log_time_ns, "pause" if d["kind"] == "pause_requested" else "resume",
                    d["subject"], before=before(t_s),
                    logged_before=bisect.bisect_left(walls, m.log_time_ns)))
        elif m.topic in ros:
            t_s = timeline(m.log_time_ns)
            inputs.append(_HighInput(t_s, m.log_time_ns, "msg",
                                     _topic_of(m.topic, prefix, namespace), m.data,
                                     channel=m.topic, before=before(t_s)))
    return inputs


def _settled_count(recording: Recording, prefix: str) -> int:
    """How many high-level events the recording holds before its shutdown: the trailing
    run of ``ended … INTERRUPTED`` (and STUCK) events is the shutdown's, which the
    replay's own shutdown produces."""
    kinds = [(m.data["kind"], m.data["status"])
             for m in recording.of(schema.topic(prefix, schema.EVENTS_HIGH))]
    n = len(kinds)
    while n and (kinds[n - 1] in (("ended", "INTERRUPTED"), ("safe_state_ran", "INTERRUPTED"))
                 or kinds[n - 1][0] in ("stuck", "stuck_released", "safe_state_overdue")
                 or kinds[n - 1] == ("safe_state_ran", "STUCK")):
        n -= 1
    return n


def _running_at_end(recording: Recording, prefix: str) -> list[str]:
    """The top-level behaviours the recording shows started and never ended: it stops
    while the robot still ran (recorded for a while, not to the robot's shutdown)."""
    running: dict[str, None] = {}
    for m in recording.of(schema.topic(prefix, schema.EVENTS_HIGH)):
        kind, subject = m.data["kind"], m.data["subject"]
        if "/" in subject:
            continue
        if kind == "started":
            running[subject] = None
        elif kind in ("ended", "stuck_released"):
            running.pop(subject, None)
    return list(running)


def _shutdown_ns(recording: Recording, prefix: str) -> int:
    """When the recorded shutdown began: its first event (the recording's end when the
    high level shows none)."""
    logged = recording.of(schema.topic(prefix, schema.EVENTS_HIGH))
    n = _settled_count(recording, prefix)
    return logged[n].log_time_ns if n < len(logged) else recording.end_ns


def _batch_ends(inputs: list[Any]) -> list[bool]:
    """For each input: whether the logics get to run after it (the end of its batch)."""
    ends: list[bool] = []
    batch_ns = 0
    for n, item in enumerate(inputs):
        following = inputs[n + 1] if n + 1 < len(inputs) else None
        if not batch_ns:
            batch_ns = item.wall_ns
        if (following is None or not isinstance(item, _Input)
                or not isinstance(following, _Input)
                or not item.kind == following.kind == "set"):
            batched = False
        elif item.batch is not None and following.batch is not None:
            batched = following.batch == item.batch
        else:
            batched = following.wall_ns - batch_ns < BATCH_NS
        if not batched:
            batch_ns = 0
        ends.append(not batched)
    return ends


def _merge(low: list[_Input], high: list[_HighInput]) -> list[_Input | _HighInput]:
    """The low level's inputs with the high level's placed by log time -- but only between
    two batches, so that the logics see the same batches as without them."""
    if not high:
        return list(low)
    ends = _batch_ends(low)
    merged: list[_Input | _HighInput] = []
    j = 0
    reached = low[0].wall_ns if low else 0
    while j < len(high) and high[j].wall_ns < reached:
        merged.append(high[j])
        j += 1
    for i, item in enumerate(low):
        if i == 0 or ends[i - 1]:  # a batch starts here: what came before it goes first
            while j < len(high) and high[j].wall_ns < item.wall_ns:
                merged.append(high[j])
                j += 1
        merged.append(item)
        reached = max(reached, item.wall_ns)
        if ends[i]:
            while j < len(high) and high[j].wall_ns <= reached:
                merged.append(high[j])
                j += 1
    merged.extend(high[j:])
    return merged


_POLL_S = 0.0002
"""How often :meth:`_HighSide.settle` looks at the high level's threads (wall time)."""
SYNC_MARGIN_S = 0.1
"""See :func:`_high_inputs`: what the recorded high level had done by ``t - SYNC_MARGIN_S``
the replayed one must have done before the input at ``t`` is fed (seconds of the
recording's time)."""
SETTLE_S = 1.0
"""How long the feed waits, after each step, for the high level's threads to wait again
(see :meth:`_HighSide.settle`), counted in the CPU time those threads use meanwhile: a
thread that computes for longer is left to it, and the feed goes on. CPU time, not wall
time: on a loaded host a behaviour that starts late or computes slowly must not look like
one that never stops (CI: the default behaviour began its 0.15 s of computing late, and
the clock moved on during it)."""
SETTLE_WALL_S = 30.0
"""... and at most this long in wall time: threads that get no CPU at all. Once either
bound ran out in a replay, its later settles wait :data:`SETTLE_S` of wall time at most."""
_MAX_MISSES = 3
"""After this many catch-ups timed out the replay has diverged: the feed stops waiting."""
CATCH_UP_S = 10.0
"""How long (wall time) the feed waits, before an input of the high level, for the
replayed behaviours to have done what the recorded ones had done by then. Bounded: a
replay that diverged never catches up; the feed then goes on without waiting (and says
so in a warning). Generous: a loaded host (load 15 on 2 cores) took more than 2 s, and a
replay that catches up costs nothing here; one that diverged pays it once (then a tenth)."""
HOLD_S = 0.5
"""How long a message of a topic nobody subscribes to yet is kept for the next
subscription, in wall time and in the recording's time (both must hold): a behaviour that
has started but not yet subscribed must not miss the order that the recorded one
received. A message older than that, or one a subscription has had since, is not what a
subscription made now would receive live."""


def _quiet_s() -> float:
    """How long a high-level thread outside any known wait must use no CPU to count as
    waiting: one that waits for the GIL sleeps between its tries, which come every switch
    interval (5 ms by default); two of them."""
    return 2 * sys.getswitchinterval()


_QUIET_LOOKS = 5
"""... and over at least this many looks, each after the feed let the GIL go."""


def _runnable(native_id: int | None) -> bool:
    """Whether the OS thread ``native_id`` of this process runs or is ready to (Linux:
    state ``R`` in /proc): a thread preempted on a busy host uses no CPU for a while, yet
    it is not waiting for anything. False where /proc does not say."""
    if native_id is None:
        return False
    try:
        with open(f"/proc/self/task/{native_id}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return False
    return stat[stat.rfind(b")") + 2:][:1] == b"R"


def _thread_cpu_s(ident: int) -> float | None:
    """The CPU time thread ``ident`` (alive: an ended thread's clock must not be read) has
    used; None where there is no per-thread CPU clock."""
    try:
        return time.clock_gettime(time.pthread_getcpuclockid(ident))
    except (OSError, AttributeError):
        return None


class _CpuBudget:
    """The CPU time a pool's busy threads use from now on, against a budget (seconds).
    Idle (parked) threads are not looked at: they use none, and one may end meanwhile (an
    ended thread's CPU clock must not be read). A bound, not an account."""

    _EVERY_S = 0.01  # wall time between two sums: a look at each thread costs a syscall

    def __init__(self, pool: Any, budget_s: float) -> None:
        self._pool = pool
        self._budget_s = budget_s
        self._began = time.monotonic()
        self._next = self._began + self._EVERY_S
        self._start = self._used()

    def _used(self) -> dict[threading.Thread, float]:
        used = {}
        for thread, state in self._pool.threads():
            ident = thread.ident
            if ident is None or state is WorkerState.PARKED:
                continue
            cpu_s = _thread_cpu_s(ident)
            if cpu_s is not None:
                used[thread] = cpu_s
        return used

    def spent(self) -> bool:
        """Whether the threads have used the budget (looked at every 10 ms of wall time)."""
        now = time.monotonic()
        if now < self._next:
            return False
        self._next = now + self._EVERY_S
        if not hasattr(time, "pthread_getcpuclockid"):  # no per-thread CPU clock: wall time
            return now - self._began >= self._budget_s
        start = self._start
        return sum(max(0.0, t - start.get(thread, 0.0))
                   for thread, t in self._used().items()) >= self._budget_s


async def _wait(cond: threading.Condition, predicate: Callable[[], bool],
               timeout_s: float) -> bool:
    """Wait for ``predicate`` (whoever changes it notifies ``cond``) without blocking the
    event loop: in a worker thread, and only when it does not hold already."""
    with cond:
        if predicate():
            return True

    def blocking() -> bool:
        with cond:
            return cond.wait_for(predicate, timeout_s)

    return await asyncio.to_thread(blocking)


class _HighSide:
    """The replayed high level and what feeds it (see :func:`replay`)."""

    def __init__(self, high: HighLevelBehaviorManager, recording: Recording, prefix: str,
                 namespace: str, state: _ReplayState, warnings: list[str],
                 sim0: float) -> None:
        self.high = high
        self.recording = recording
        self.prefix, self.namespace = prefix, namespace
        self.state = state
        self.warnings = warnings
        self.sim0 = sim0
        self.clock = ReplayClock()
        self.node = ReplayNode(namespace, now_s=lambda: state.now_s,
                               on_subscribe=self._on_subscribe)
        self.abort = threading.Event()
        self.missing: dict[str, str] = {}
        self._cond = threading.Condition()
        self._events = 0
        self._misses = 0  # catch-ups that timed out
        self._given_up = 0  # the event count the last one waited for in vain
        self._pending: dict[str, tuple[Any, float, float]] = {}
        self._late: list[Any] = []  # subscriptions made while a message was held for them
        self._decoded: dict[tuple[int, type], Any] = {}
        self._settled_at = 0  # the event count when the high level last settled
        self._last_activity: dict[int, float] | None = None
        self._slow = False
        # How many events the recorded high level emitted before its shutdown, and before
        # each switch requested from outside, and when it came: once the replayed one has
        # emitted as many as the recorded one had before the next of them, no timed wait
        # ends that live would have ended after it (see advance).
        self.settled = _settled_count(recording, prefix)
        timeline = _Timeline(recording, prefix)
        self._shutdown_s = timeline(_shutdown_ns(recording, prefix))
        self._bounds: list[tuple[int, float]] = []
        # When the recorded high level emitted each event, and how far the replayed one is
        # ahead of it (its clock then, against the recording's time of the same event).
        self._recorded_s = [timeline(m.log_time_ns)
                            for m in recording.of(schema.topic(prefix, schema.EVENTS_HIGH))]
        self._lead_s = 0.0

    def expect(self, inputs: list[Any]) -> None:
        """Take note of the switch requests among ``inputs`` (the feed's, in order). Not
        of pauses: a pause fed early would end the behaviours' time early, and they would
        be behind the recording after the resume."""
        self._bounds = [(i.logged_before, i.t_s) for i in inputs
                        if isinstance(i, _HighInput) and i.kind == "request"]
        self._bounds.reverse()  # the next one last: fed ones are popped

    def _hold_if_done(self) -> None:
        """Once the replay has emitted as many events as the recording had before the next
        switch request (or its shutdown), hold back, until that request, every timed wait
        that -- the replay being :attr:`_lead_s` ahead of the recording, give or take
        :data:`SYNC_MARGIN_S` (a late step live) -- live would have ended after it (see
        advance). Not while paused: the behaviours' time stands then."""
        count, at_s = self._bounds[-1] if self._bounds else (self.settled, self._shutdown_s)
        if self._events >= count and not self.high.paused:
            self.clock.hold_wakes(self.sim0 + at_s - max(0.0, self._lead_s) - SYNC_MARGIN_S)

    def on_event(self, event: Any) -> None:  # in the high level's threads
        with self._cond:
            self._events += 1
            n = self._events - 1
            if n < len(self._recorded_s):
                self._lead_s = self._recorded_s[n] - (self.clock.now() - self.sim0)
            self._cond.notify_all()

    def _on_subscribe(self, sub: Any) -> None:  # in the subscribing behaviour's thread
        from beehave.runnable import current

        channel = input_channel(self.prefix, self.namespace, sub.topic)
        if channel not in self.recording.channels:
            who = current()
            self.missing[channel] = (f"{who.path if who is not None else '?'} subscribed to "
                                     f"{sub.topic} ({sub.msg_type.__name__})")
            self.abort.set()
            with self._cond:
                self._cond.notify_all()
            return
        with self._cond:
            held = self._pending.get(channel)
            if (held is not None and time.monotonic() - held[1] <= HOLD_S
                    and self.clock.now() - held[2] <= HOLD_S):
                self._late.append((sub, held[0]))

    async def advance(self, t_s: float, *, until: Callable[[], bool] | None = None) -> None:
        """Move the clock to ``t_s`` (seconds since the recording's start), stopping at every
        lockstep hold on the way until the high level has settled (as a simulator holds
        for its controllers): a control loop sees every one of its periods.

        Also stop at every timed wait's deadline on the way (the live clock passed each).
        With ``until``, stop for
        good (short of ``t_s``) as soon as ``until()`` holds once the high level settled: an
        input then comes exactly when the replay has done what the recording had done
        before it, not after a timed step the recording shows after it.

        Once the replay has done all the recorded high level did before the next switch
        requested from outside (or before its shutdown), a timed wait that live would have
        ended after that switch -- its deadline shifted by how far the replay is ahead of
        the recording at its last event, and by :data:`SYNC_MARGIN_S` -- does not end
        until the switch is fed
        (:meth:`ReplayClock.hold_wakes`): live, each step came a little late (the host's
        latency adds up over a loop of sleeps; a behaviour's computing takes time live, none
        in the replay), so the replay's exact steps run ahead, and a step that the switch or
        the shutdown cut off live would start in the replay. A control loop that emits no
        event goes on to there."""
        target = self.sim0 + t_s
        clock, node = self.clock, self.node
        gone: set[str] = set()
        while not self.abort.is_set():
            # First let whatever runs reach its next wait: a behaviour just started (the
            # default one, at the replay's start) has not yet asked for its first deadline,
            # and a clock moved past it would shift all its steps.
            await self.settle()
            if until is not None and until():
                return
            self._hold_if_done()
            holds = node.holds()
            early = [h for w, h in holds.items()
                     if w not in gone and h < target - ReplayClock.SLACK_S]
            # Every timed wait's deadline on the way, as the live clock passed each: a
            # loop of sleeps woken once by a jump over several of them would lose steps.
            timed = clock.next_deadline()
            if timed is not None and not timed < target - ReplayClock.SLACK_S:
                timed = None
            if not early and timed is None:
                break
            at = min([*early, *([timed] if timed is not None else [])])
            if at > clock.now() or at == timed:
                clock.set_time(max(at, clock.now()))
                node.fire_timers(at)
            await self.settle()
            if at != timed and node.holds() == holds:
                # Its holder waits for something else than time (a first message): the
                # clock goes on without it, as the simulator's lockstep timeout lets it.
                gone.update(w for w, h in holds.items() if h <= at)
        if until is not None and until():
            return
        if target > clock.now():
            clock.set_time(target)
            node.fire_timers(target)
            await self.settle()

    def _activity(self) -> dict[int, float] | None:
        """The CPU time each of the high level's threads has used so far, leaving out
        those that wait on the clock or on a condition or event; None when one of them
        is about to run (due on the clock, or not started yet)."""
        if self.clock.ready():
            return None
        parked = self.clock.parked()
        workers = self.high._pool.threads()
        if any(state is WorkerState.HANDED for _, state in workers):
            return None  # a job handed to a thread that has not taken it yet
        frames = sys._current_frames()
        used: dict[int, float] = {}
        for thread, state in workers:
            if state is WorkerState.PARKED:
                continue  # idle, waiting for a job
            ident = thread.ident
            if ident is None:
                return None  # being started
            frame = frames.get(ident)
            if frame is None:
                continue
            code = frame.f_code
            if code.co_filename == threading.__file__ and code.co_name == "wait":
                # Waits on a condition (an event, a child's end, the clock …) -- unless it
                # was notified already and only waits for its turn to run.
                waiter = frame.f_locals.get("waiter")
                if waiter is not None and not waiter.locked():
                    return None
                continue
            if ident in parked:
                continue
            if _runnable(thread.native_id):
                return None  # on a CPU, or waiting for one (a loaded host)
            cpu_s = _thread_cpu_s(ident)
            # (No per-thread CPU clock here: by its frame.)
            used[ident] = cpu_s if cpu_s is not None else float(hash((id(frame),
                                                                       frame.f_lasti)))
        return used

    async def settle(self) -> None:
        """Let the high level's threads run until each waits again: on the clock, on a
        condition or event, or anywhere else where it uses no CPU for :func:`_quiet_s`
        (a blocking call: a queue's ``get``, a socket). Bounded by :data:`SETTLE_S` of the
        threads' CPU time, and :data:`SETTLE_WALL_S`."""
        now = time.monotonic()
        # Once a settle ran out, the later ones wait SETTLE_S of wall time at most (as
        # before the CPU budget): a state that looks busy yet uses no CPU (a notified
        # waiter whose lock's holder blocks elsewhere) must not cost every step 30 s.
        deadline = now + (SETTLE_S if self._slow else SETTLE_WALL_S)
        budget = _CpuBudget(self.high._pool, SETTLE_S)
        last = self._last_activity
        since = now  # when the activity was last seen to change
        looks = 0  # how often since then
        seen = self._settled_at
        while True:
            # Something ended or started since the last look: whoever waits for it (a
            # parent, the switch) may have been woken and not run yet -- look again.
            events, seen = seen, self._events
            activity = self._activity() if events == seen else None
            now = time.monotonic()
            if activity is not None and activity == last:
                # Every thread waits on the clock, a condition or for a job: settled. One
                # elsewhere may only wait for the GIL, asleep and using no CPU on a loaded
                # host (CI: a behaviour computing before its first sleep looked settled and
                # the clock moved on); it tries again within the switch interval, and gets
                # it when this loop lets it go between two looks.
                looks += 1
                if not activity or (now - since >= _quiet_s() and looks >= _QUIET_LOOKS):
                    break
            else:
                since, looks = now, 0
            last = activity
            past_wall_cap = time.monotonic() > deadline
            if past_wall_cap or budget.spent():
                if not self._slow:
                    self._slow = True
                    self.warnings.append(
                        f"t={self.state.now_s:.3f} s: the high level was still busy after "
                        + (f"{SETTLE_WALL_S} s (wall time)" if past_wall_cap else
                           f"{SETTLE_S} s of CPU time") + "; the replay went on (and "
                        f"waits at most {SETTLE_S} s of wall time from now on)")
                break
            await asyncio.sleep(_POLL_S)
        self._settled_at = self._events
        self._last_activity = last

    async def catch_up(self, count: int) -> None:
        """Wait until the replayed high level has emitted ``count`` events (bounded)."""
        if self._misses >= _MAX_MISSES or count <= self._given_up:
            return
        done = await _wait(self._cond, lambda: self._events >= count or self.abort.is_set(),
                           CATCH_UP_S if not self._misses else CATCH_UP_S / 10)
        if not done:
            self._misses += 1
            self._given_up = count
            self.warnings.append(
                f"t={self.state.now_s:.3f} s: the replayed high level did not catch up with "
                f"the recording ({self._events} of {count} events)"
                + ("; the replay goes on without waiting for it any more"
                   if self._misses >= _MAX_MISSES else ""))

    async def feed(self, item: _HighInput) -> None:
        # A request comes as soon as the replay has done all the recording had done by
        # then: before the clock moves on when it has. A timed step due between the last
        # input and this one (a chime) then comes after the request, as it did live -- or
        # the recording shows it before the request, and the clock moves first.
        if item.kind in _COMMANDS and self._events < item.logged_before:
            # Behind the recording (a loaded host, or steps due before the request): move
            # only as far as needed to catch up, so a step the recording shows after the
            # request (a chime due at the same instant) still comes after it.
            await self.advance(item.t_s, until=lambda: self._events >= item.logged_before)
            await self.catch_up(item.logged_before)
        elif item.kind not in _COMMANDS:
            await self.advance(item.t_s)
            await self.catch_up(item.before)
        self._deliver_late()
        if item.kind in ("pause", "resume"):
            try:
                # As live: the pause has taken effect before anything else is fed (a
                # resume fed before it would find nothing to resume).
                await asyncio.to_thread(
                    self.high.pause if item.kind == "pause" else self.high.resume)
            except Exception as exc:  # the recording asked for it; say it did not work
                self.warnings.append(f"t={item.t_s:.3f} s: {item.kind} failed: {exc!r}")
            await self.settle()
            return
        if item.kind == "request":
            params = item.value if isinstance(item.value, dict) else {}
            try:
                self.high.request_switch(item.key, **params)
            except Exception as exc:  # the recording asked for it; say it did not work
                self.warnings.append(f"t={item.t_s:.3f} s: switch to behaviour {item.key!r} "
                                     f"failed: {exc!r}")
            await self.settle()
            # The switch has interrupted what a held-back wait would have woken (see
            # advance): the waits due by now end, and time goes on towards the next one.
            if self._bounds:
                self._bounds.pop()  # the next switch (or the shutdown) bounds it now
            self.clock.release_wakes()
            await self.settle()
            return
        subs = self.node.subscriptions(item.key)
        with self._cond:
            if not subs:
                self._pending[item.channel] = (item.value, time.monotonic(),
                                               self.clock.now())
                return
            # Delivered: a subscription made later hears the next message, not this one.
            self._pending.pop(item.channel, None)
        for sub in subs:
            self._call(sub, item.value)
        await self.settle()

    def _deliver_late(self) -> None:
        with self._cond:
            late, self._late = self._late, []
        for sub, data in late:
            self._call(sub, data)

    def _call(self, sub: Any, data: bytes) -> None:
        from rclpy.serialization import deserialize_message

        key = (id(data), sub.msg_type)
        msg = self._decoded.get(key)
        if msg is None:
            msg = deserialize_message(data, sub.msg_type)
            self._decoded = {key: msg}  # one message is shared by its subscriptions
        try:
            sub.callback(msg)
        except Exception as exc:  # the behaviour's callback, not the replay, failed
            self.warnings.append(f"t={self.state.now_s:.3f} s: a subscription to "
                                 f"{sub.topic} raised {exc!r}")

    async def finish(self) -> None:
        """After the last input: let the high level do what it did before the recorded
        shutdown (its shutdown follows: its safe states and ends are compared too) --
        moving the clock on towards the shutdown while it has not: a behaviour that only
        sleeps has no input to move it."""
        self._deliver_late()
        await self.advance(self._shutdown_s)
        await self.catch_up(self.settled)

    def missing_error(self) -> RecordingError:
        channels = ", ".join(sorted(self.missing))
        who = "; ".join(self.missing[c] for c in sorted(self.missing))
        return RecordingError(
            f"{self.recording.files[0]}: cannot replay robot {self.prefix!r}'s high level: "
            f"channel(s) {channels} missing ({who}); the recording has: "
            f"{', '.join(sorted(self.recording.channels)) or 'no channels'}. Record "
            "again with this version of beehave (it records what behaviours subscribe "
            "to), or add the topic to the configuration's recording.topics")


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
           hal_wait_s: float = 2.0, high: bool | None = None) -> ReplayResult:
    """Run ``config``'s low level -- and its high level, see ``high`` -- on ``recording``
    (see the module docstring) and compare.

    ``high``: replay the behaviours too (None: when the configuration has behaviours or
    the recording their events; False: the logics alone).
    ``prefix``: the robot in the recording (default: the configuration's namespace).
    ``speed``: 1.0 real time, N times faster, None as fast as possible. ``from_s`` /
    ``to_s``: the window to replay, in seconds since the recording's start; the state
    before ``from_s`` is set at once, and only outputs inside the window are compared.
    Raises :class:`RecordingError` when the robot or a channel a replay needs is not in
    the recording (naming them and what is there) -- for a topic a behaviour subscribes
    to, as soon as it subscribes (naming the behaviour).
    """
    from beehave.robot import Robot

    if speed is not None and not (isinstance(speed, (int, float)) and 0 < speed < 1e9):
        raise RecordingError(f"speed must be a number > 0 (or None: as fast as possible), "
                             f"got {speed!r}")
    rec = recording if isinstance(recording, Recording) else read_recording(recording)
    prefix = config.namespace if prefix is None else prefix
    _check_channels(rec, prefix)
    with_high = _check_high(rec, prefix, config, high)
    timeline = _Timeline(rec, prefix)
    inputs: list[_Input | _HighInput] = list(_inputs(rec, prefix))
    warnings: list[str] = []
    # Compare only what the recording has: a run cut off (its process died) or damaged
    # has no shutdown at the end of its data, and nothing after a damaged part can be
    # trusted -- the replay's own shutdown there would be an invented divergence.
    cut_s: float | None = None
    end_s = timeline(rec.end_ns)
    if rec.damaged:
        cut_s = timeline(rec.intact_until_ns)
        warnings.append(f"the recording is DAMAGED: compared only up to t={cut_s:.3f} s, "
                        "before its first damaged part: " + "; ".join(rec.describe_damage()))
    elif rec.truncated:
        cut_s = timeline(rec.intact_until_ns)
        warnings.append(f"the recording was cut off at t={cut_s:.3f} s (its process died "
                        "before closing it): compared up to there")
    running = _running_at_end(rec, prefix)
    if cut_s is None and running and (to_s is None or to_s >= end_s):
        # Recorded up to here while the robot ran on (no shutdown in it): the replay's own
        # shutdown would be an invented ending.
        cut_s = end_s
        warnings.append(f"the recording stops while {', '.join(running[:3])} still "
                        f"ran: compared up to its end (t={end_s:.3f} s)")
    if to_s is not None and cut_s is None and to_s >= end_s:
        warnings.append(f"--to {to_s:g} s is beyond the recording's end ({end_s:.3f} s): "
                        "replayed to its end")
        to_s = None
    if cut_s is not None and (to_s is None or to_s > cut_s):
        to_s = cut_s
    else:
        cut_s = None  # the window the caller asked for ends before it
    lo = from_s if from_s is not None else float("-inf")
    hi = to_s if to_s is not None else float("inf")
    recorded = recorded_outputs(rec, prefix)
    if with_high:
        recorded += recorded_high_outputs(rec, prefix)
    expected = [o for o in recorded if lo <= o.t_s <= hi]

    robot = Robot(config, only="low")
    low = robot.low
    if low is None:
        raise RecordingError(f"{config.source}: the configuration has no low level to replay")
    state = _ReplayState()
    side: _HighSide | None = None
    if with_high:
        side = _high_side(config, rec, prefix, low, state, warnings, timeline)
        inputs = _merge(inputs, _high_inputs(rec, prefix, config.namespace))  # type: ignore[arg-type]
        side.expect(inputs)

    def capture(hal: str, method: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        state.low_done += 1
        if state.comparing:
            state.outputs.append(Output(f"{hal}.{method}", [to_json(list(args)),
                                                            to_json(kwargs)], state.now_s))

    for name in hal_names(config):
        cls, params = low.hals.resolve(name)
        low.hals.register(replay_hal_class(cls, name, capture), name=name, **params)

    def on_event(event: Any) -> None:
        if event.kind.value == "switch_completed":
            state.low_done += 1
            if state.comparing:
                state.outputs.append(Output("logic", event.subject, state.now_s))

    def on_change(change: Any) -> None:
        if _is_logic(change.writer):
            state.low_done += 1
        if state.comparing and _is_logic(change.writer):
            state.outputs.append(Output(f"blackboard:{change.key}",
                                        [to_json(change.value), change.stale], state.now_s))

    def on_high_event(event: Any) -> None:  # in the high level's threads
        if not state.comparing:
            return
        made = _high_output(event.kind.value, event.subject, event.status,
                            _error_type(event.error))
        if made is not None:
            with state.lock:
                state.outputs.append(Output(made[0], made[1], state.now_s))

    unsubscribe = low.events.subscribe(on_event)
    remove_tap = low.blackboard.tap(on_change)
    state.comparing = from_s is None
    began = time.monotonic()
    fed = 0
    try:
        with low:
            try:
                if side is not None:
                    side.high.events.subscribe(side.on_event)
                    side.high.events.subscribe(on_high_event)
                    side.high.start()
                fed = low.call(_feed(low, inputs, state, speed=speed, lo=lo, hi=hi,
                                     hal_wait_s=hal_wait_s, warnings=warnings, high=side))
                if side is not None and not side.abort.is_set() and to_s is None:
                    low.call(side.finish())
                if to_s is not None:
                    state.comparing = False  # the shutdown's safe states lie outside it
            finally:
                if side is not None:
                    side.high.shutdown()
    finally:
        remove_tap()
        unsubscribe()
    if side is not None and side.missing:
        raise side.missing_error()
    wall = time.monotonic() - began
    span = (min(hi, inputs[-1].t_s) if inputs else 0.0) - (max(lo, 0.0) if inputs else 0.0)
    got = state.outputs
    if not any(_is_safe_state_ran(o) for o in recorded):
        # Recorded before beehave reported safe states: compare what it did report.
        got = [o for o in got if not _is_safe_state_ran(o)]
    if hi < float("inf"):
        expected, got = _trim_window_end(expected, got, hi)
    elif side is not None and not side.abort.is_set():
        got = _drop_shutdown_extras(expected, got, timeline(_shutdown_ns(rec, prefix)))
    return ReplayResult(got, expected, compare(expected, got), fed, max(span, 0.0), wall,
                        timeline.sim is not None, warnings,
                        commands=list(side.node.captured) if side is not None else [],
                        high=side is not None, cut_s=cut_s,
                        damaged=rec.describe_damage())


def _check_high(recording: Recording, prefix: str, config: RobotConfig,
                high: bool | None) -> bool:
    """Whether to replay the high level too: ``high`` when given, else when the
    configuration has behaviours of its own or the recording the high level's events. A
    configuration with behaviours needs their events (the recorded decisions)."""
    events = schema.topic(prefix, schema.EVENTS_HIGH)
    own = bool(config.behaviors) or config.default_behavior != "idle"
    if high is False:
        return False
    if events not in recording.channels:
        if high or own:
            raise RecordingError(
                f"{recording.files[0]}: cannot replay robot {prefix!r}'s high level: "
                f"channel(s) {events} missing (its behaviours' decisions); the recording "
                f"has: {', '.join(sorted(recording.channels)) or 'no channels'} (pass "
                "high=False to replay the low level alone)")
        return False
    return True


def _high_side(config: RobotConfig, recording: Recording, prefix: str,
               low: LowLevelBehaviorManager, state: _ReplayState, warnings: list[str],
               timeline: _Timeline) -> _HighSide:
    """The configuration's high level, built to run on the replay: the replay node (its
    publishers captured, its subscriptions fed from the recording), a clock the feed
    moves, and the replayed low level's blackboard."""
    from beehave.blackboard import BlackboardView
    from beehave.robot import Robot

    built = Robot(config, only="high").high
    assert built is not None
    side = _HighSide(built, recording, prefix, config.namespace, state, warnings,
                     timeline.sim0)
    built.clock = side.clock
    built.node = side.node
    built.blackboard = low.blackboard
    built.blackboard_view = BlackboardView(
        low.blackboard, why="behaviours and actions read the low level's blackboard; they "
                            "change the robot through actions")
    side.clock.set_time(timeline.sim0)
    return side


class _ReplayState:
    def __init__(self) -> None:
        self.now_s = 0.0
        self.comparing = True
        self.outputs: list[Output] = []
        self.lock = threading.Lock()  # the high level's threads append too
        self.low_done = 0  # the low level's outputs so far (compared or not)
        self.low_misses = 0  # waits for them that timed out


LOW_CATCH_UP_S = 0.5
"""How long (wall time) the feed waits, before a batch, for the logics to have produced
what the recorded ones had by then (a logic loading its HALs at the start). Three waits in
vain and it stops waiting: the replay has diverged."""


async def _low_catch_up(state: _ReplayState, item: _Input, warnings: list[str]) -> None:
    if state.low_done >= item.outputs_before or state.low_misses >= _MAX_MISSES:
        return
    loop = asyncio.get_running_loop()
    deadline = loop.time() + LOW_CATCH_UP_S
    turns = 0
    while state.low_done < item.outputs_before and loop.time() < deadline:
        turns += 1
        await asyncio.sleep(0 if turns < 50 else 0.001)  # turns first, then time
    if state.low_done < item.outputs_before:
        state.low_misses += 1
        warnings.append(f"t={item.t_s:.3f} s: the logics had not produced what the recorded "
                        f"ones had by then ({state.low_done} of {item.outputs_before} "
                        f"outputs) after {LOW_CATCH_UP_S} s")


async def _feed(low: LowLevelBehaviorManager, inputs: list[_Input | _HighInput],
                state: _ReplayState, *, speed: float | None, lo: float, hi: float,
                hal_wait_s: float, warnings: list[str], high: _HighSide | None = None) -> int:
    loop = asyncio.get_running_loop()
    board = low.blackboard
    fed = 0
    origin_wall: float | None = None
    origin_t = 0.0
    ends = _batch_ends(inputs)
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
        if isinstance(item, _HighInput):
            # The high level runs in threads of its own: it is fed (and waited for) here,
            # between two batches of the low level's inputs (see _merge).
            assert high is not None
            await high.feed(item)
            fed += 1
            if high.abort.is_set():
                break  # it needs what the recording lacks: replay() says which
            continue
        if not catching_up and (n == 0 or ends[n - 1]):
            await _low_catch_up(state, item, warnings)
        if high is not None and (n == 0 or ends[n - 1]):
            # Only between two batches: letting the high level run here lets the loop run
            # too, and a batch must reach the logics in one go.
            await high.advance(item.t_s)
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
        if not catching_up and ends[n]:
            for _ in range(_YIELDS):
                await asyncio.sleep(0)
    for _ in range(10 * _YIELDS):  # let the logics answer the last inputs
        await asyncio.sleep(0)
    return fed
