"""A recording as a timeline: what each robot ran, held and knew at any moment.

:class:`RecordingTimeline` indexes a :class:`~beehave.recording.Recording` once (each
blackboard key's changes, each robot's lifecycle events and the state they lead to) so
that :meth:`~RecordingTimeline.state_at` answers for any time ``t`` with bisections only:
scrubbing a long recording costs the keys and the running items, not its length. The web
view of ``beehave view FILE.mcap`` and ``beehave inspect --at T`` both read it, so the page
at ``t`` says what ``inspect`` says.

Times are wall seconds since the start of the recording (what ``beehave inspect`` prints).
What a recording does not hold is not invented: the decision engines (a state machine's
state, a tree's node statuses, and their structures for the graphs) come from the
``engines`` channels (:meth:`~beehave.recording.Recorder.attach_engines`); a recording
without them (older ones) has ``engines`` empty. The type locks come from the actions'
``started`` events (``action_type``).
"""

from __future__ import annotations

import bisect
import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from beehave.errors import RecordingError
from beehave.recording import schema
from beehave.recording.reader import Recording

#: The events a state at ``t`` carries (the newest ones up to ``t``), as the live page.
EVENTS_SHOWN = 200
#: The trail a state at ``t`` carries: the last poses up to ``t``, 2 cm apart at least.
TRAIL_POINTS = 300
TRAIL_STEP_M = 0.02
#: Where a robot's pose is on its blackboard (the beehave HALs' keys).
POSE_KEYS = ("odom/x_m", "odom/y_m")


T_RESOLUTION_S = 1e-6
"""The resolution of a moment asked for (seconds): the HTTP API's ``t`` has six decimals."""


@dataclass(frozen=True)
class _Item:
    """A running behaviour, action or logic."""

    kind: str
    status: str
    since_ns: int
    action_type: str | None = None


@dataclass(frozen=True)
class _State:
    """What a robot runs after one of its events (immutable: one per event)."""

    behavior: str | None = None
    logic: str | None = None
    paused: bool = False
    high: dict[str, _Item] = field(default_factory=dict)
    low: dict[str, _Item] = field(default_factory=dict)
    hals: tuple[str, ...] = ()


def _without(items: dict[str, _Item], path: str) -> dict[str, _Item]:
    """``items`` without ``path`` and what runs under it, but for STUCK actions: their
    thread (and type lock) outlives their parent until ``stuck_released``."""
    return {p: i for p, i in items.items()
            if p != path and (not p.startswith(path + "/") or i.status == "STUCK")}


def _step(state: _State, level: str, t_ns: int, event: dict[str, Any]) -> _State:
    """The state after ``event`` (one place for every lifecycle rule of the timeline)."""
    kind, subject, status = event["kind"], event["subject"], event["status"]
    detail = event.get("detail") or {}
    if level == "high":
        high = state.high
        if kind == "started":
            action_type = detail.get("action_type")
            previous = high.get(subject)
            since = previous.since_ns if previous is not None and detail.get("resumed") \
                else t_ns
            high = {**high, subject: _Item("action" if action_type else "behaviour",
                                           "RUNNING", since, action_type)}
            behavior = subject if "/" not in subject else state.behavior
            return _State(behavior, state.logic, state.paused, high, state.low, state.hals)
        if kind == "stuck_released":
            return _State(state.behavior, state.logic, state.paused,
                          {p: i for p, i in high.items() if p != subject}, state.low,
                          state.hals)
        if kind == "ended":
            return _State(state.behavior, state.logic, state.paused, _without(high, subject),
                          state.low, state.hals)
        if kind == "stuck":
            item = high.get(subject)
            if item is None:
                return state
            high = {**high, subject: _Item(item.kind, "STUCK", item.since_ns,
                                           item.action_type)}
            return _State(state.behavior, state.logic, state.paused, high, state.low,
                          state.hals)
        if kind == "switch_completed":
            return _State(subject, state.logic, False, high, state.low, state.hals)
        if kind in ("paused", "resumed"):
            return _State(state.behavior, state.logic, kind == "paused", high, state.low,
                          state.hals)
        return state
    low, hals = state.low, state.hals
    if kind == "started":
        if subject.startswith("hal:"):
            hals = tuple(sorted({*hals, subject[4:]}))
        else:
            low = {**low, subject: _Item("logic", status or "RUNNING", t_ns)}
    elif kind == "ended":
        if subject.startswith("hal:"):
            hals = tuple(h for h in hals if h != subject[4:])
        else:
            low = _without(low, subject)
    elif kind == "switch_completed":
        return _State(state.behavior, subject, state.paused, state.high, low, hals)
    else:
        return state
    return _State(state.behavior, state.logic, state.paused, state.high, low, hals)


def _tree(items: dict[str, _Item], root: str | None, t_ns: int) -> dict[str, Any] | None:
    """The running tree under ``root`` as the live snapshot draws it."""
    if root is None or root not in items:
        return None

    def node(path: str) -> dict[str, Any]:
        item = items[path]
        children = [node(p) for p in sorted(items)
                    if p.startswith(path + "/") and "/" not in p[len(path) + 1:]]
        out: dict[str, Any] = {"path": path, "name": path.rsplit("/", 1)[-1],
                               "kind": item.kind, "status": item.status,
                               "elapsed_s": round(max(0, t_ns - item.since_ns) / 1e9, 3),
                               "children": children}
        if item.action_type:
            out["action_type"] = item.action_type
        return out

    return node(root)


def _number(value: Any) -> float | None:
    """A recorded value as a number to plot (None: not a number)."""
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)):
        return float(value) if math.isfinite(value) else None
    return None


@dataclass
class _Robot:
    prefix: str
    #: key → the log times (ns) of its changes, and the changes (as recorded)
    times: dict[str, list[int]] = field(default_factory=dict)
    changes: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    event_times: list[int] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    #: the state after each lifecycle event (parallel to event_times)
    states: list[_State] = field(default_factory=list)
    trail_times: list[int] = field(default_factory=list)
    trail: list[tuple[float, float]] = field(default_factory=list)
    low_recorded: bool = False
    high_recorded: bool = False
    #: the engines (path → its recorded describe(), with "path") after each change
    engine_times: list[int] = field(default_factory=list)
    engine_sets: list[dict[str, dict[str, Any]]] = field(default_factory=list)
    #: structure_id → {"path", "structure_id", **structure} (what /structure serves)
    structures: dict[str, dict[str, Any]] = field(default_factory=dict)


class RecordingTimeline:
    """Every robot of ``recording`` at any time (see the module docstring)."""

    def __init__(self, recording: Recording) -> None:
        if not recording.messages:
            raise RecordingError(f"{recording.files[0]}: the recording holds no message")
        self.recording = recording
        self.start_ns = recording.start_ns
        self.duration_s = recording.duration_s
        self.robots: dict[str, _Robot] = {p: _Robot(p) for p in recording.prefixes}
        topics: dict[str, tuple[_Robot, str]] = {}
        # What each channel's messages must hold (their schemas' required fields), checked
        # on each channel's first message: a file another tool wrote is refused here, not
        # at some later query (checking every message doubled the indexing time).
        unchecked: dict[str, frozenset[str]] = {}
        for robot in self.robots.values():
            robot.low_recorded = schema.topic(robot.prefix, schema.EVENTS_LOW) in \
                recording.channels
            robot.high_recorded = schema.topic(robot.prefix, schema.EVENTS_HIGH) in \
                recording.channels
            for channel, what in ((schema.BLACKBOARD, "board"), (schema.EVENTS_HIGH, "high"),
                                  (schema.EVENTS_LOW, "low"),
                                  (schema.ENGINE_STRUCTURE, "structure"),
                                  (schema.ENGINE_STATE, "engine")):
                topic = schema.topic(robot.prefix, channel)
                topics[topic] = (robot, what)
                unchecked[topic] = frozenset(
                    schema.SCHEMAS[schema.CHANNEL_SCHEMA[channel]]["required"])
        pose: dict[str, dict[str, float]] = {p: {} for p in self.robots}
        seq = 0
        for message in recording.messages:
            found = topics.get(message.topic)
            if found is None:
                continue
            robot, what = found
            try:
                required = unchecked.pop(message.topic, None)
                if required is not None and not message.data.keys() >= required:
                    raise KeyError(", ".join(sorted(required - message.data.keys())))
                data, t_ns = message.data, message.log_time_ns
                if what == "board":
                    key = data["key"]
                    robot.times.setdefault(key, []).append(t_ns)
                    robot.changes.setdefault(key, []).append(data)
                    if key in POSE_KEYS and not data["stale"]:
                        value = _number(data["value"])
                        if value is not None:
                            pose[robot.prefix][key] = value
                            self._extend_trail(robot, t_ns, pose[robot.prefix])
                    continue
                if what == "structure":
                    structure = data.get("structure")
                    if isinstance(structure, dict):
                        robot.structures.setdefault(data["structure_id"], {
                            "path": data["path"], "structure_id": data["structure_id"],
                            **structure})
                    continue
                if what == "engine":
                    engines = dict(robot.engine_sets[-1]) if robot.engine_sets else {}
                    if isinstance(data.get("engine"), dict):
                        engines[data["path"]] = {"path": data["path"], **data["engine"]}
                    else:
                        engines.pop(data["path"], None)
                    robot.engine_times.append(t_ns)
                    robot.engine_sets.append(engines)
                    continue
                state = robot.states[-1] if robot.states else _State()
                robot.event_times.append(t_ns)
                robot.states.append(_step(state, what, t_ns, data))
                # One numbering over every robot: a page tells two robots' lists apart by it.
                seq += 1
                robot.events.append({**data, "seq": seq, "source": what,
                                     "t_s": round((t_ns - self.start_ns) / 1e9, 6)})
            except (KeyError, TypeError, AttributeError) as exc:
                # Written by another tool or version: said, not a traceback.
                raise RecordingError(
                    f"{message.topic} at t={(message.log_time_ns - self.start_ns) / 1e9:.3f} s: "
                    f"not a {message.schema_name} message as beehave records it "
                    f"({'missing ' if isinstance(exc, KeyError) else ''}{exc}): "
                    f"{str(message.data)[:200]}") from exc

    @staticmethod
    def _extend_trail(robot: _Robot, t_ns: int, pose: dict[str, float]) -> None:
        if len(pose) < len(POSE_KEYS):
            return
        x, y = pose[POSE_KEYS[0]], pose[POSE_KEYS[1]]
        if robot.trail and math.hypot(x - robot.trail[-1][0],
                                      y - robot.trail[-1][1]) <= TRAIL_STEP_M:
            return
        robot.trail_times.append(t_ns)
        robot.trail.append((x, y))

    # -- queries --------------------------------------------------------------------------

    def robot(self, name: str) -> _Robot:
        found = self.robots.get(name)
        if found is None:
            raise RecordingError(f"no robot {name!r} in the recording; robots recorded: "
                                 f"{', '.join(map(repr, self.robots)) or 'none'}")
        return found

    def _t_ns(self, t_s: float) -> int:
        if not isinstance(t_s, (int, float)) or isinstance(t_s, bool) or not math.isfinite(t_s):
            raise RecordingError(f"a time must be a finite number of seconds, got {t_s!r}")
        # To the microsecond, as the page asks (``t.toFixed(6)`` of the duration may round
        # up past the end): a time within that of the end is the end.
        if not 0 <= t_s <= self.duration_s + T_RESOLUTION_S:
            raise RecordingError(f"t={t_s:g} s is outside the recording: 0 to "
                                 f"{self.duration_s:.3f} s")
        return self.start_ns + round(min(t_s, self.duration_s) * 1e9)

    def blackboard_at(self, name: str, t_s: float) -> dict[str, dict[str, Any]]:
        """Every key's entry as it was at ``t_s``: ``{value, stamp, stale, writer,
        age_s}`` (age: since it was recorded), as the live blackboard endpoint gives it."""
        robot, t_ns = self.robot(name), self._t_ns(t_s)
        out = {}
        for key in sorted(robot.times):
            i = bisect.bisect_right(robot.times[key], t_ns) - 1
            if i < 0:
                continue
            change = robot.changes[key][i]
            out[key] = {"value": change["value"], "stamp": change["stamp"],
                        "stale": change["stale"], "writer": change["writer"],
                        "age_s": round((t_ns - robot.times[key][i]) / 1e9, 6)}
        return out

    def _engines(self, robot: _Robot, t_ns: int, state: _State) -> list[dict[str, Any]]:
        """The engines at ``t_ns`` as the live snapshot lists them, those of the running
        behaviours only (the events say which run; the engines were looked at apart)."""
        i = bisect.bisect_right(robot.engine_times, t_ns) - 1
        if i < 0:
            return []
        return [engine for path, engine in sorted(robot.engine_sets[i].items())
                if not robot.high_recorded or path in state.high]

    def engines_at(self, name: str, t_s: float) -> list[dict[str, Any]]:
        """The decision engines of the behaviours running at ``t_s``: ``[{"path", "kind",
        "structure_id", …}]`` as the live snapshot's ``engines`` (a state machine's
        ``state`` and ``last_transition``, a tree's ``nodes`` with their statuses);
        empty for a recording without engine channels."""
        robot, t_ns = self.robot(name), self._t_ns(t_s)
        i = bisect.bisect_right(robot.event_times, t_ns) - 1
        return self._engines(robot, t_ns, robot.states[i] if i >= 0 else _State())

    def structures(self, name: str, t_s: float | None = None) -> list[dict[str, Any]]:
        """The recorded structures of the robot's engines, as ``GET
        /api/robots/{robot}/structure`` lists them (``[{"path", "structure_id",
        **structure}]``): every one recorded, or (``t_s``) those of the engines at that
        time."""
        robot = self.robot(name)
        if t_s is None:
            return list(robot.structures.values())
        ids = {e.get("structure_id") for e in self.engines_at(name, t_s)}
        return [s for sid, s in robot.structures.items() if sid in ids]

    def snapshot_at(self, name: str, t_s: float) -> dict[str, Any]:
        """What runs at ``t_s``, in the shape of the live snapshot (``behavior``, ``logic``,
        ``paused``, ``running``, ``engines``, ``locks``, ``lock_details``, ``stuck``,
        ``tree``, ``low``) and ``recorded``: True."""
        robot, t_ns = self.robot(name), self._t_ns(t_s)
        i = bisect.bisect_right(robot.event_times, t_ns) - 1
        state = robot.states[i] if i >= 0 else _State()
        running = [{"path": p, "kind": item.kind, "status": item.status,
                    "action_type": item.action_type} for p, item in sorted(state.high.items())]
        holders = {item.action_type: (p, item) for p, item in sorted(state.high.items())
                   if item.action_type}
        stuck = sorted(p for p, item in state.high.items() if item.status == "STUCK")
        low_root = next((p for p in sorted(state.low) if "/" not in p), None)
        return {
            "robot": name, "recorded": True, "t_s": round(t_s, 6),
            "stamp": (t_ns) / 1e9, "behavior": state.behavior, "logic": state.logic,
            "paused": state.paused, "running": running,
            "engines": self._engines(robot, t_ns, state),
            "locks": {kind: p for kind, (p, _) in holders.items()},
            "lock_details": {kind: {"holder": p, "status": item.status,
                                    "held_s": round(max(0, t_ns - item.since_ns) / 1e9, 3)}
                             for kind, (p, item) in holders.items()},
            "stuck": stuck, "tree": _tree(state.high, state.behavior, t_ns), "history": [],
            # None when the low level was not recorded (as a process without one)
            "low": {"current": state.logic, "registered": [],
                    "logic": _tree(state.low, low_root, t_ns),
                    "hals": {"loaded": {h: {} for h in state.hals}}}
            if robot.low_recorded else None,
        }

    def events_at(self, name: str, t_s: float, *, limit: int = EVENTS_SHOWN
                  ) -> list[dict[str, Any]]:
        """The robot's events up to ``t_s``, oldest first, the newest ``limit``."""
        robot, t_ns = self.robot(name), self._t_ns(t_s)
        i = bisect.bisect_right(robot.event_times, t_ns)
        return robot.events[max(0, i - limit):i]

    def trail_at(self, name: str, t_s: float) -> list[tuple[float, float]]:
        robot, t_ns = self.robot(name), self._t_ns(t_s)
        i = bisect.bisect_right(robot.trail_times, t_ns)
        return robot.trail[max(0, i - TRAIL_POINTS):i]

    def state_at(self, name: str, t_s: float) -> dict[str, Any]:
        """One robot at ``t_s``: ``{snapshot, blackboard, events, trail}``."""
        return {"snapshot": self.snapshot_at(name, t_s),
                "blackboard": self.blackboard_at(name, t_s),
                "events": self.events_at(name, t_s), "trail": self.trail_at(name, t_s)}

    def keys(self, name: str) -> list[str]:
        """The robot's blackboard keys that held a number (what can be plotted)."""
        robot = self.robot(name)
        return sorted(k for k, changes in robot.changes.items()
                      if any(_number(c["value"]) is not None for c in changes[:50]))

    def series(self, name: str, keys: Iterable[str], *, max_points: int = 2000
               ) -> dict[str, dict[str, list[float]]]:
        """Each key's numeric values over the whole recording: ``{key: {"t": [s…],
        "v": [...]}}``, thinned to ``max_points`` evenly spaced changes (the last kept)."""
        robot = self.robot(name)
        out = {}
        for key in keys:
            if key not in robot.changes:
                raise RecordingError(f"{name}: no blackboard key {key!r} in the recording; "
                                     f"numeric keys: {', '.join(self.keys(name)) or 'none'}")
            points = [((t - self.start_ns) / 1e9, v) for t, c in
                      zip(robot.times[key], robot.changes[key], strict=True)
                      if (v := _number(c["value"])) is not None]
            if len(points) > max_points:
                stride = len(points) / max_points
                points = [points[int(i * stride)] for i in range(max_points - 1)] + [points[-1]]
            out[key] = {"t": [round(p[0], 6) for p in points], "v": [p[1] for p in points]}
        return out

    def describe_at(self, t_s: float, robots: Iterable[str] | None = None) -> list[str]:
        """``beehave inspect --at T``: each robot's behaviour, logic, running items, decision
        engines (a state machine's state, a tree's node statuses), type locks and
        blackboard at ``t_s``, one fact per line."""
        lines = [f"at {t_s:.3f} s (wall seconds since the start of the recording)"]
        for name in robots or self.robots:
            snap, board = self.snapshot_at(name, t_s), self.blackboard_at(name, t_s)
            lines.append(f"{name} behaviour: {snap['behavior'] or '-'}")
            lines.append(f"{name} logic: {snap['logic'] or '-'}")
            lines.append(f"{name} paused: {'yes' if snap['paused'] else 'no'}")
            for item in snap["running"]:
                kind = f"action {item['action_type']}" if item["action_type"] else item["kind"]
                lines.append(f"{name} running: {item['path']} ({kind}) {item['status']}")
            for engine in snap["engines"]:
                lines.extend(_engine_lines(name, engine))
            for kind, lock in sorted(snap["lock_details"].items()):
                lines.append(f"{name} lock: {kind} held by {lock['holder']}")
            for key, entry in board.items():
                stale = " stale" if entry["stale"] else ""
                lines.append(f"{name} blackboard: {key} = "
                             f"{json.dumps(entry['value'], separators=(',', ':'))}"
                             f" (writer {entry['writer'] or '-'}){stale}")
        return lines


def _engine_lines(name: str, engine: dict[str, Any]) -> list[str]:
    """``beehave inspect --at``'s lines of one engine: ``<robot> engine: <path>
    (<kind>) …``, and for a tree one ``<robot> node: <path> <node path> <status>`` per
    node."""
    head = f"{name} engine: {engine['path']} ({engine.get('kind', 'engine')})"
    if engine.get("kind") == "state_machine":
        last = engine.get("last_transition")
        came = f" (from {last['source']} on {last['trigger']})" \
            if isinstance(last, dict) else ""
        return [f"{head} state {engine.get('state') or '-'}{came}"]
    if engine.get("kind") == "behaviour_tree":
        return [f"{head} tick {engine.get('tick')}"] + [
            f"{name} node: {engine['path']} {node['path']} {node['status']}"
            for node in engine.get("nodes") or ()]
    return [head]


__all__ = ["RecordingTimeline"]
