"""The two managers as ROS 2 nodes, and what flows between them.

Topics (relative to the robot's namespace; std_msgs/String carrying JSON):

``beehave/blackboard`` — from the low level; reliable, transient-local (depth 100)::

    {"schema": "beehave/blackboard/2", "kind": "changes" | "snapshot", "seq": 17,
     "stamp": 1795240691.67,            # time.time() of publication
     "entries": {"battery/percentage": {"value": 54.0, "stamp": 1795240691.6,
                                         "stale": false, "writer": "hal:debug"}, ...},
     "removed": []}                     # reserved; keys are never removed today

  ``changes`` carries the entries that changed since the previous message. A change is
  published at once, in the call that made it, when the previous message left at least
  ``1/blackboard_rate_hz`` ago; every change that comes within that interval (the rest of
  the logic's step, a burst) waits for its end and travels together with the others (only
  the newest value per key). So a quiet blackboard reaches the high level in about two
  bare-rclpy message times, and a busy one costs at most ``blackboard_rate_hz`` messages a
  second. ``snapshot`` carries every entry and comes every ``snapshot_period_s`` and
  ``settle_s`` after the last change. A late joiner receives the last messages at once
  (transient-local keeps 100) and applies them in order, then a full snapshot within
  ``snapshot_period_s``. The high level's mirror sets ``HighLevelBridge.mirror_complete``
  at its first snapshot and counts lost messages (by ``seq``) in ``missed_messages``.

  Values are strict JSON (:func:`beehave.blackboard.to_json`): tuples travel as lists,
  objects JSON cannot hold as their ``repr``, and the non-finite floats strict JSON lacks
  as tagged objects — ``{"$float": "inf"}``, ``{"$float": "-inf"}``, ``{"$float": "nan"}``,
  also inside lists and mappings — which the mirror turns back into floats (a laser's
  "nothing in range" stays ``inf``, so ``front_m < 0.5`` works). Schema ``/1`` (non-finite
  floats as strings) is still accepted.

``beehave/high_level/state`` — from the high level; reliable, transient-local (depth 1)::

    {"schema": "beehave/high_level/state/2", "stamp": ..., "behavior": "tour",
     "logic": "navigation_leds" | null,   # the top-level behaviour's `logic` attribute
     "running": [{"path": "tour/Navigation", "kind": "action", "class": "Navigation",
                  "action_type": "driving", "status": "RUNNING"}, ...],
     "engines": [{"path": "tour", "kind": "state_machine", "state": "to_shelf", ...},
                 {"path": "tour/pick", "kind": "behaviour_tree", "nodes": [...]}],
     "locks": {"driving": "tour/Navigation"}, "stuck": [], "paused": false}

  ``engines`` holds, for every running behaviour driven by a decision engine, its path and
  the engine's own snapshot (the ``"engine"`` entry of the behaviour's snapshot: a state
  machine's current state, a behaviour tree's node statuses …), strict JSON; empty when no
  engine runs. It is published with the rest — on every lifecycle change (at most
  ``state_rate_hz``) and every ``state_period_s`` — and, while an engine runs, whenever its
  snapshot changed (compared ``engine_rate_hz`` times a second while any behaviour runs,
  so an engine that appears after its behaviour started is published too). Schema ``/1``
  (without ``engines``) is still accepted.

  The low level writes it into its blackboard: ``high_level/behavior``,
  ``high_level/logic``, ``high_level/running`` (that list), ``high_level/engines`` (that
  list), ``high_level/locks`` (that dict), ``high_level/paused`` (true while the high
  level is paused: a logic can show it), and switches its top-level logic to ``logic``
  when it is set. (``paused`` is new in 2026-11; a state without it reads as false.)

Parameters: the high-level node's ``behavior`` (string) switches the top-level behaviour
(at once; the latest request wins, also when it names the running behaviour while another
switch is queued); the low-level node's ``logic`` switches the top-level logic and answers
once the switch is under way or failed — served in the executor thread, it does not wait
for the old logic's stop, which may need that thread — at most ``switch_timeout_s`` (a
blocked event loop gives a refusal that says so). Unknown names are refused
(``SetParametersResult.successful`` false; the reason lists the registered names). Both
always show what runs.
Service ``beehave/stop`` (std_srvs/Trigger) on the high-level node switches to ``idle``;
``beehave/pause`` and ``beehave/resume`` (std_srvs/Trigger) pause the robot in place and
resume it (:meth:`HighLevelBehaviorManager.pause`: the pause answers at once, the state's
``paused`` turns true once every action stands in its safe state).

The high-level side is an adapter of the control-plane core
(:class:`beehave.interfaces.ControlPlane`): the state message is its ``status()``, the
``behavior`` parameter and the stop service call its ``switch()`` and ``stop()``, so ROS 2,
HTTP and VDA 5050 accept and refuse the same requests.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from pydantic_core import to_json as to_json_bytes
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

from beehave.blackboard import Change, check_key, from_json, to_json
from beehave.clock import SimClock
from beehave.errors import BeehaveError, BlackboardError, ConfigError
from beehave.events import Event, EventBus, EventKind
from beehave.highlevel import HighLevelBehaviorManager
from beehave.interfaces.core import STATE_SCHEMA as STATE_SCHEMA  # the state topic's schema
from beehave.interfaces.core import ControlPlane
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.ros.context import RosContext, in_executor_thread
from beehave.ros.io import LATCHED

log = logging.getLogger(__name__)

BLACKBOARD_TOPIC = "beehave/blackboard"
STATE_TOPIC = "beehave/high_level/state"
STOP_SERVICE = "beehave/stop"
PAUSE_SERVICE = "beehave/pause"
RESUME_SERVICE = "beehave/resume"
BLACKBOARD_SCHEMA = "beehave/blackboard/2"
MIRROR_WRITER = "ros:low_level"


#: ``beehave/blackboard``: reliable + transient-local, but deep. ``changes`` messages are
#: deltas: with depth 1 a message the reader had not taken yet was replaced by the next
#: one and its changes were lost (~30 % at 1 kHz), leaving the mirror wrong until the next
#: snapshot. A late joiner gets the last BLACKBOARD_DEPTH messages and applies them in order.
BLACKBOARD_DEPTH = 100
BLACKBOARD_QOS = QoSProfile(depth=BLACKBOARD_DEPTH, history=HistoryPolicy.KEEP_LAST,
                            reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _check_positive(owner: str, **options: float) -> None:
    """Refuse rates and periods that are not finite numbers > 0 (0 Hz divided by zero,
    NaN made a timer that never or always fires), naming the option."""
    for label, value in options.items():
        if not (isinstance(value, (int, float)) and not isinstance(value, bool)
                and math.isfinite(value) and value > 0):
            unit = "Hz" if label.endswith("_hz") else "seconds"
            raise ConfigError(f"{owner}: {label} must be a finite number of {unit} > 0, "
                              f"got {value!r}")


def _running_in(loop: asyncio.AbstractEventLoop | None) -> bool:
    """Whether the calling code runs inside ``loop`` (in its thread, as a coroutine or
    callback)."""
    try:
        return asyncio.get_running_loop() is loop
    except RuntimeError:  # no loop runs in this thread: the usual case
        return False


def _string_param(node: Node, name: str, value: str, description: str) -> None:
    # dynamic_typing: our own callback refuses non-strings, with a reason naming the choices
    # (rclpy's type check would only say "expected '4' got '2'").
    node.declare_parameter(name, value, ParameterDescriptor(
        description=description, dynamic_typing=True))


def _remove_param(node: Node, name: str,
                  callback: Callable[[list[Parameter[Any]]], SetParametersResult]) -> None:
    """Undo :func:`_string_param` and the switch callback: after a bridge's destroy(),
    setting the parameter switches nothing, and a new bridge may declare it again."""
    try:
        node.remove_on_set_parameters_callback(callback)
    except ValueError:  # removed already
        pass
    if node.has_parameter(name):
        node.undeclare_parameter(name)


class _ParamGuard:
    """Lets a node set its own switch parameter (to show the current name) without the
    change being taken as a new switch request."""

    def __init__(self) -> None:
        self._local = threading.local()

    def __enter__(self) -> None:
        self._local.active = True

    def __exit__(self, *exc: object) -> None:
        self._local.active = False

    @property
    def active(self) -> bool:
        return bool(getattr(self._local, "active", False))


def _switch_param_callback(param_name: str, names: Callable[[], list[str]],
                           target: Callable[[], str | None],
                           request: Callable[[str], None], guard: _ParamGuard,
                           kind: str) -> Callable[[list[Parameter[Any]]], SetParametersResult]:
    def on_set(params: list[Parameter[Any]]) -> SetParametersResult:
        for param in params:
            if param.name != param_name or guard.active:
                continue
            value = param.value
            if not isinstance(value, str):
                return SetParametersResult(successful=False, reason=(
                    f"parameter {param_name!r} must be a string naming a {kind}, got "
                    f"{type(value).__name__}; registered: {', '.join(names())}"))
            if value not in names():
                return SetParametersResult(successful=False, reason=(
                    f"unknown {kind} {value!r}; registered: {', '.join(names())}"))
            if value == target():
                continue  # what runs (or will, once the queued switch is done): no-op
            try:
                request(value)
            except BeehaveError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    return on_set


class HighLevelBridge:
    """Puts a :class:`HighLevelBehaviorManager` on a ROS 2 node.

    Publishes ``beehave/high_level/state`` on every lifecycle change (at most
    ``state_rate_hz``) and every ``state_period_s``; mirrors ``beehave/blackboard`` into
    ``manager.blackboard`` (what behaviours read); serves the ``behavior`` parameter and the
    ``beehave/stop`` service; feeds a :class:`~beehave.clock.SimClock` from ``/clock`` when
    the manager has one. :meth:`destroy` removes all of it (the node stays).

    ``plane``: the robot's :class:`~beehave.interfaces.ControlPlane`, shared with its other
    interfaces; without one the bridge makes its own and closes it in :meth:`destroy`.
    """

    def __init__(self, manager: HighLevelBehaviorManager, node: Node, *,
                 state_rate_hz: float = 50.0, state_period_s: float = 1.0,
                 engine_rate_hz: float = 10.0, plane: ControlPlane | None = None) -> None:
        _check_positive("HighLevelBridge", state_rate_hz=state_rate_hz,
                        state_period_s=state_period_s, engine_rate_hz=engine_rate_hz)
        if plane is not None and plane.high is not manager:
            raise ConfigError(f"HighLevelBridge: the control plane {plane.name!r} belongs to "
                              f"another HighLevelBehaviorManager")
        self.manager = manager
        self.node = node
        self._own_plane = plane is None
        #: The control-plane core every request goes through (validation, state).
        self.plane = plane if plane is not None else ControlPlane(
            manager, name=node.get_namespace().strip("/") or node.get_name())
        self._previous_node = manager.node  # given back by destroy()
        manager.node = node
        self._guard = _ParamGuard()
        self._io = threading.Lock()  # publishing vs. destroy(), which runs in another thread
        self._closed = False
        self._dirty = threading.Event()
        self.mirror_complete = False
        #: ``beehave/blackboard`` messages that never arrived, by their ``seq`` (should stay
        #: 0; a gap leaves the mirror behind until the next snapshot).
        self.missed_messages = 0
        self._last_seq: int | None = None
        _string_param(node, "behavior", manager.current or manager.default,
                      "the top-level behaviour; set it to switch")
        # Kept to be removed by destroy() (rclpy identifies a callback by the function).
        self._on_set_param = _switch_param_callback(
            "behavior", lambda: manager.names, self._target, self._request, self._guard,
            "behavior")
        node.add_on_set_parameters_callback(self._on_set_param)
        self._state_pub = node.create_publisher(String, STATE_TOPIC, LATCHED)
        self._bb_sub = node.create_subscription(String, BLACKBOARD_TOPIC, self._on_blackboard,
                                                BLACKBOARD_QOS)
        self._stop_srv = node.create_service(Trigger, STOP_SERVICE, self._on_stop)
        self._pause_srv = node.create_service(Trigger, PAUSE_SERVICE, self._on_pause)
        self._resume_srv = node.create_service(Trigger, RESUME_SERVICE, self._on_resume)
        # A state machine's transition or a tree's tick is no lifecycle event: while an
        # engine runs, its state is compared every 1/engine_rate_hz and published on change.
        self._engines: list[dict[str, Any]] = []
        self._engine_period_s = 1.0 / engine_rate_hz
        self._engines_checked = 0.0
        self._fast = node.create_timer(1.0 / state_rate_hz, self._publish_if_dirty)
        self._slow = node.create_timer(state_period_s, self._dirty.set)
        self._clock_sub = None
        self._clock_off: Callable[[], None] | None = None
        if isinstance(manager.clock, SimClock):
            sim_clock = manager.clock
            ros = RosContext.of(node)
            if ros is not None:  # the process's one /clock subscription, shared
                self._clock_off = ros.on_clock(sim_clock.set_time, node=node)
            else:
                from rosgraph_msgs.msg import Clock as ClockMsg

                self._clock_sub = node.create_subscription(
                    ClockMsg, "/clock",
                    lambda m: sim_clock.set_time(m.clock.sec + m.clock.nanosec * 1e-9), 10)
        self._unsubscribe = manager.subscribe(self._on_event)
        self._dirty.set()

    def _target(self) -> str | None:
        """What will run once the queued switches are done. Setting the parameter to the
        running name is a no-op only when no other switch is queued: else it must win.

        Asked of the manager, which holds its queue, rather than rebuilt from events: a
        rejected or fallen-back switch says nothing about the requests still queued."""
        return self.manager.requested or self.manager.current

    def _request(self, name: str) -> None:
        self.plane.switch(name)

    def _on_stop(self, _req: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            self.plane.stop()
        except BeehaveError as exc:
            response.success, response.message = False, str(exc)
        else:
            response.success, response.message = True, "switching to idle"
        return response

    def _on_pause(self, _req: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        try:
            answer = self.plane.pause()
        except BeehaveError as exc:
            response.success, response.message = False, str(exc)
        else:
            response.success = True
            response.message = "pausing" if answer["pausing"] else "already paused"
        return response

    def _on_resume(self, _req: Trigger.Request, response: Trigger.Response
                   ) -> Trigger.Response:
        try:
            resumed = self.plane.resume()["resumed"]
        except BeehaveError as exc:
            response.success, response.message = False, str(exc)
        else:
            response.success = True
            response.message = "resumed" if resumed else "was not paused"
        return response

    def _on_event(self, event: Event) -> None:
        if event.kind in _STATE_EVENTS:
            self._dirty.set()
        if event.kind is EventKind.SWITCH_COMPLETED:
            with self._guard:
                try:
                    self.node.set_parameters([Parameter("behavior", value=event.subject)])
                except Exception:  # the node may be going away during shutdown
                    log.debug("could not update parameter 'behavior'", exc_info=True)

    def state(self) -> dict[str, Any]:
        """The message published on ``beehave/high_level/state``
        (:meth:`ControlPlane.status <beehave.interfaces.ControlPlane.status>`)."""
        return self.plane.status()

    def _publish_if_dirty(self) -> None:
        if self._dirty.is_set():
            self._dirty.clear()
            self._publish_state(self.state())
            return
        now = time.monotonic()
        # While any behaviour runs, not only while the last state had engines: one that
        # prepares before driving its engine was published with none.
        if (self.manager.top is not None
                and now - self._engines_checked >= self._engine_period_s):
            self._engines_checked = now
            state = self.state()
            if state["engines"] != self._engines:
                self._publish_state(state)

    def _publish_state(self, state: dict[str, Any]) -> None:
        self._engines = state["engines"]
        msg = String(data=json.dumps(state))
        with self._io:
            if not self._closed:
                self._state_pub.publish(msg)

    def _on_blackboard(self, msg: String) -> None:
        data = _parse(BlackboardMessage, msg, self.node, BLACKBOARD_TOPIC, self.manager.events)
        if data is None:
            return
        last = self._last_seq
        if last is not None and data.seq > last + 1:
            self.missed_messages += data.seq - last - 1
            log.warning("mirror: %d blackboard message(s) missed before seq %d",
                        data.seq - last - 1, data.seq)
        self._last_seq = data.seq  # a restarted low level starts again at 1
        board = self.manager.blackboard
        for key, entry in data.entries.items():
            # Value and stale flag in one store: an entry that stays stale (or NaN) is no
            # change at every snapshot, and never reads as fresh in between.
            board.set(key, from_json(entry.value), writer=entry.writer or MIRROR_WRITER,
                      stale=entry.stale)
        if data.kind == "snapshot":
            self.mirror_complete = True

    def destroy(self) -> None:
        with self._io:
            self._closed = True
        self._unsubscribe()
        for timer in (self._fast, self._slow):
            self.node.destroy_timer(timer)
        self.node.destroy_publisher(self._state_pub)
        self.node.destroy_subscription(self._bb_sub)
        if self._clock_sub is not None:
            self.node.destroy_subscription(self._clock_sub)
        if self._clock_off is not None:
            self._clock_off()
        self.node.destroy_service(self._stop_srv)
        self.node.destroy_service(self._pause_srv)
        self.node.destroy_service(self._resume_srv)
        _remove_param(self.node, "behavior", self._on_set_param)
        if self._own_plane:
            self.plane.close()
        if self.manager.node is self.node:
            self.manager.node = self._previous_node


_STATE_EVENTS = {EventKind.STARTED, EventKind.ENDED, EventKind.STUCK,
                 EventKind.STUCK_RELEASED, EventKind.SWITCH_COMPLETED, EventKind.FALLBACK,
                 EventKind.PAUSED, EventKind.RESUMED}


class LowLevelBridge:
    """Puts a running :class:`LowLevelBehaviorManager` on a ROS 2 node.

    Publishes its blackboard on ``beehave/blackboard`` (changes at once, batched above
    ``blackboard_rate_hz``; full snapshots every ``snapshot_period_s`` and when changes
    settle), writes ``beehave/high_level/state`` into the blackboard under ``high_level/``
    and follows its ``logic``, and serves the ``logic`` parameter.
    """

    def __init__(self, manager: LowLevelBehaviorManager, node: Node, *,
                 blackboard_rate_hz: float = 2000.0, snapshot_period_s: float = 1.0,
                 settle_s: float = 0.2, switch_timeout_s: float | None = None) -> None:
        _check_positive("LowLevelBridge", blackboard_rate_hz=blackboard_rate_hz,
                        snapshot_period_s=snapshot_period_s, settle_s=settle_s)
        if switch_timeout_s is None:
            # Stopping the old logic may take stop_timeout_s, unloading its HALs as long.
            switch_timeout_s = 2.0 * manager.stop_timeout_s + 1.0
        _check_positive("LowLevelBridge", switch_timeout_s=switch_timeout_s)
        self.manager = manager
        self.node = node
        #: How long setting the ``logic`` parameter waits for the switch (it answers the
        #: caller with the outcome, and must never hang on a blocked event loop).
        self.switch_timeout_s = float(switch_timeout_s)
        self._guard = _ParamGuard()
        self._lock = threading.Lock()  # also orders publishing before destroy()
        self._closed = False
        self._pending: dict[str, Change] = {}
        self._seq = 0
        self._last_kind = "snapshot"
        self._min_interval_s = 1.0 / blackboard_rate_hz
        self._settle_s = settle_s
        self._last_publish = 0.0
        self._flush_handle: asyncio.Handle | None = None
        self._settle_handle: asyncio.TimerHandle | None = None
        self._requested_logic: str | None = None  # what the high level's state asked for
        # The latest logic asked for whose switch has not completed (see HighLevelBridge).
        self._target_lock = threading.Lock()
        self._target: str | None = None
        _string_param(node, "logic", manager.current or manager.default or "",
                      "the top-level logic; set it to switch")
        self._on_set_param = _switch_param_callback(
            "logic", lambda: manager.registered, self._target_logic,
            self._switch_from_parameter, self._guard, "logic")
        node.add_on_set_parameters_callback(self._on_set_param)
        self._pub = node.create_publisher(String, BLACKBOARD_TOPIC, BLACKBOARD_QOS)
        self._state_sub = node.create_subscription(String, STATE_TOPIC, self._on_state, LATCHED)
        self._snap = node.create_timer(snapshot_period_s, self._publish_snapshot)
        self._bb_sub = manager.blackboard.subscribe("**", self._on_change)
        self._unsubscribe = manager.subscribe(self._on_event)
        self._publish_snapshot()

    # -- blackboard → ROS ------------------------------------------------------------------
    def _on_change(self, change: Change) -> None:
        # In the low level's loop thread (the blackboard is bound to it).
        with self._lock:
            self._pending[change.key] = change
            if self._flush_handle is not None:
                return  # a flush is already due: this change goes with it
            wait_s = self._last_publish + self._min_interval_s - time.monotonic()
        loop = self.manager.loop
        if loop is None or wait_s <= 0:
            # The rate cap allows a message now: send it at once rather than after the
            # loop's next turn (that hop cost a fifth of the latency across processes).
            try:
                self._publish_changes()
            except Exception:  # never let it close our blackboard subscription
                log.exception("publishing blackboard changes on %s failed",
                              self.node.resolve_topic_name(BLACKBOARD_TOPIC))
        else:
            # Whatever changes within the cap's interval (the rest of this step, a burst)
            # waits for its end and travels together.
            self._flush_handle = loop.call_later(wait_s, self._publish_changes)

    def _message(self, kind: str, entries: dict[str, dict[str, Any]]) -> String:
        self._seq += 1
        self._last_kind = kind
        self._last_publish = time.monotonic()
        # pydantic_core's serialiser: a quarter of json.dumps's time on this hot path.
        return String(data=to_json_bytes({"schema": BLACKBOARD_SCHEMA, "kind": kind,
                                          "seq": self._seq, "stamp": time.time(),
                                          "entries": entries, "removed": []}).decode())

    def _publish_changes(self) -> None:
        with self._lock:
            self._flush_handle = None
            pending, self._pending = self._pending, {}
            if not pending:
                return
            msg = self._message("changes", {k: _entry(c) for k, c in pending.items()})
            if self._closed:
                return
            self._pub.publish(msg)
        loop = self.manager.loop
        if loop is not None and self._settle_handle is None:
            # One timer, re-armed when it fires too early (cheaper than one per message).
            self._settle_handle = loop.call_later(self._settle_s, self._settled)

    def _settled(self) -> None:
        self._settle_handle = None
        if self._last_kind != "changes":
            return
        remaining_s = self._last_publish + self._settle_s - time.monotonic()
        loop = self.manager.loop
        if remaining_s > 0 and loop is not None:
            self._settle_handle = loop.call_later(remaining_s, self._settled)
            return
        self._publish_snapshot()  # leave a full picture for late joiners

    def _publish_snapshot(self) -> None:
        # Called from the executor thread (the period timer) while the loop thread writes.
        board = self.manager.blackboard
        entries = {}
        taken: dict[str, Change] = {}
        with self._lock:
            # The board is read under the lock that orders publishing: a change published
            # between this read and the snapshot would otherwise be followed by the older
            # snapshot value, and the mirror would keep it until the next snapshot. A
            # change made meanwhile waits in _on_change and goes out after the snapshot.
            for key in board.keys():
                change = board.entry(key)
                if change is not None:
                    entries[key] = _entry(change)
                    taken[key] = change
            # The snapshot carries these pending changes; those made after it read the
            # board must still go out as changes, or the mirror would miss them until the
            # next snapshot.
            for key, change in list(self._pending.items()):
                if taken.get(key) is change:
                    del self._pending[key]
            msg = self._message("snapshot", entries)
            if self._closed:
                return
            self._pub.publish(msg)

    # -- ROS → low level -------------------------------------------------------------------
    def _on_state(self, msg: String) -> None:
        state = _parse(StateMessage, msg, self.node, STATE_TOPIC, self.manager.events)
        if state is None:
            return
        board = self.manager.blackboard
        writer = "ros:high_level"
        board.set("high_level/behavior", state.behavior, writer=writer)
        board.set("high_level/logic", state.logic, writer=writer)
        board.set("high_level/running", [item.model_dump(by_alias=True)
                                          for item in state.running], writer=writer)
        board.set("high_level/engines", [from_json(item.model_dump())
                                          for item in state.engines], writer=writer)
        board.set("high_level/locks", state.locks, writer=writer)
        board.set("high_level/paused", state.paused, writer=writer)
        logic = state.logic
        if logic and logic != self._requested_logic:
            self._requested_logic = logic
            if logic not in self.manager.registered:
                log.error("high level asks for logic %r, which is not registered (%s)",
                          logic, ", ".join(self.manager.registered))
            elif logic != self.manager.current:
                self._request(logic)
        elif not logic:
            self._requested_logic = None

    def _target_logic(self) -> str | None:
        with self._target_lock:
            target = self._target
        return target if target is not None else self.manager.current

    def _submit(self, name: str) -> tuple[concurrent.futures.Future[None], _Ticket]:
        """Hand a switch to the low level's loop; its ticket tells whether it began."""
        loop = self.manager.loop
        if loop is None:
            raise BeehaveError(f"the low level is not running; cannot switch to {name!r}")
        ticket = _Ticket()
        manager = self.manager

        def on_event(event: Event) -> None:
            # switch_async creates the logic, then announces the request, before it awaits
            # anything: in this loop, the first request for `name` from now on is ours.
            if event.kind is EventKind.SWITCH_REQUESTED and event.subject == name:
                ticket.under_way.set()

        async def switch() -> None:
            with ticket.lock:
                if ticket.abandoned:
                    return  # its caller was told it failed: do not switch behind its back
                ticket.began = True
            unsubscribe = manager.subscribe(on_event)
            try:
                await manager.switch_async(name)
            finally:
                unsubscribe()

        with self._target_lock:
            self._target = name
        future = asyncio.run_coroutine_threadsafe(switch(), loop)
        future.add_done_callback(lambda _: ticket.under_way.set())  # failed, or done
        return future, ticket

    def _request(self, name: str) -> None:
        """Switch without waiting (the high level's state asked for ``name``)."""
        future, _ = self._submit(name)
        future.add_done_callback(_log_failure(f"switch to logic {name!r}"))

        def forget_if_failed(done: concurrent.futures.Future[None]) -> None:
            if done.cancelled() or done.exception() is not None:
                self._forget_target(name)  # a later set of the parameter may try again

        future.add_done_callback(forget_if_failed)

    def _switch_from_parameter(self, name: str) -> None:
        """Switch and wait for the outcome, at most ``switch_timeout_s``; raise a
        :class:`BeehaveError` whose message becomes the parameter's refusal reason.

        Runs in the executor thread, so it must never wait forever: a logic that blocks
        the event loop (``time.sleep`` in a coroutine) would otherwise hang every ROS
        callback of the process."""
        if _running_in(self.manager.loop):
            raise BeehaveError(f"the 'logic' parameter was set from inside the low level's "
                               f"loop, where waiting for the switch would block it; use "
                               f"`await ll.switch_async({name!r})`")
        future, ticket = self._submit(name)
        try:
            if in_executor_thread():
                # A ROS callback (a remote `ros2 param set`): stopping the old logic may
                # need this very thread (a HAL's service call in its `finally`), so do not
                # wait for the end — only until the new logic exists and the old one is
                # being stopped. The parameter shows the new logic once it runs.
                if not ticket.under_way.wait(self.switch_timeout_s):
                    raise concurrent.futures.TimeoutError
                if not future.done():
                    return
            future.result(self.switch_timeout_s)
        except concurrent.futures.TimeoutError:
            with ticket.lock:
                began = ticket.began
                ticket.abandoned = not began
            self._forget_target(name)
            if not began:
                raise BeehaveError(
                    f"switch to logic {name!r} refused: the low level's event loop did not "
                    f"take it within {self.switch_timeout_s:g} s; a logic or HAL is blocking "
                    f"the loop (time.sleep or blocking I/O inside a coroutine?). Nothing was "
                    f"switched; running: {self.manager.current!r}") from None
            raise BeehaveError(
                f"switch to logic {name!r} did not complete within "
                f"{self.switch_timeout_s:g} s (the old logic or its HALs are slow to stop); "
                f"it goes on, and this parameter will show the logic that runs") from None
        except BeehaveError:
            self._forget_target(name)
            raise
        except Exception as exc:  # a logic's constructor, say: report, never crash
            self._forget_target(name)
            raise BeehaveError(f"switch to logic {name!r} failed: {exc!r}") from exc

    def _forget_target(self, name: str) -> None:
        with self._target_lock:
            if self._target == name:
                self._target = None

    def _on_event(self, event: Event) -> None:
        if event.kind is EventKind.SWITCH_COMPLETED:
            self._forget_target(event.subject)
        elif event.kind is EventKind.FALLBACK:
            with self._target_lock:
                self._target = None
        else:
            return
        # A fallback is reported before the default logic starts: show the running logic
        # once the loop has finished this step (events come from the loop's thread).
        loop = self.manager.loop
        try:
            if loop is None:
                raise RuntimeError("not running")
            loop.call_soon_threadsafe(self._show_running_logic)
        except RuntimeError:  # the loop is gone: nothing more will change
            self._show_running_logic()

    def _show_running_logic(self) -> None:
        """Make the ``logic`` parameter show what runs ("" when no logic runs)."""
        current = self.manager.current or ""
        with self._lock:
            if self._closed:
                return
        try:
            if self.node.get_parameter("logic").value == current:
                return
            with self._guard:
                self.node.set_parameters([Parameter("logic", value=current)])
        except Exception:  # the node may be going away during shutdown
            log.debug("could not update parameter 'logic'", exc_info=True)

    def _cancel_handles(self) -> None:
        # Should one fire first, it finds the bridge closed and publishes nothing.
        for handle in (self._flush_handle, self._settle_handle):
            if handle is not None:
                handle.cancel()

    def _in_loop(self, fn: Callable[[], None]) -> None:
        loop = self.manager.loop
        if loop is None or _running_in(loop):
            fn()
            return
        try:
            loop.call_soon_threadsafe(fn)
        except RuntimeError:  # the loop is closed: nothing can fire any more
            fn()

    def destroy(self) -> None:
        with self._lock:
            self._closed = True
        self._unsubscribe()
        self._bb_sub.close()
        self._in_loop(self._cancel_handles)  # asyncio handles belong to the loop's thread
        self.node.destroy_timer(self._snap)
        self.node.destroy_publisher(self._pub)
        self.node.destroy_subscription(self._state_sub)
        _remove_param(self.node, "logic", self._on_set_param)


class _Ticket:
    """Whether a switch handed to the loop began, or was abandoned by its waiter first."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.began = False
        self.abandoned = False
        #: Set once the new logic exists and the switch proceeds (or it ended either way).
        self.under_way = threading.Event()


class _Message(BaseModel):
    model_config = ConfigDict(extra="ignore", populate_by_name=True)


class EntryMessage(_Message):
    value: Any = None
    stamp: float | None = None
    stale: bool = False
    writer: str | None = None


class BlackboardMessage(_Message):
    """``beehave/blackboard`` (see the module docstring)."""

    # /1 differs only in sending non-finite floats as strings; still read.
    schema_: Literal["beehave/blackboard/2", "beehave/blackboard/1"] = Field(alias="schema")
    kind: Literal["changes", "snapshot"]
    seq: int
    stamp: float
    entries: dict[str, EntryMessage]
    removed: list[str] = []

    @field_validator("entries")
    @classmethod
    def _keys(cls, entries: dict[str, EntryMessage]) -> dict[str, EntryMessage]:
        for key in entries:
            check_key(key)
        return entries


class RunningItem(_Message):
    path: str
    kind: Literal["behavior", "action"]
    status: str
    action_type: str | None = None
    class_: str = Field(alias="class")


class EngineItem(_Message):
    """One running behaviour's decision engine: its path, its kind, and whatever the engine
    reports (kept as it came)."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    path: str
    kind: str | None = None


class StateMessage(_Message):
    """``beehave/high_level/state`` (see the module docstring)."""

    schema_: Literal["beehave/high_level/state/2", "beehave/high_level/state/1"] = Field(
        alias="schema")
    stamp: float
    behavior: str | None
    logic: str | None = None
    running: list[RunningItem] = []
    engines: list[EngineItem] = []  # /2
    locks: dict[str, str] = {}
    stuck: list[str] = []
    paused: bool = False


M = TypeVar("M", bound=_Message)


def _parse(model: type[M], msg: String, node: Node, topic: str, events: EventBus) -> M | None:
    """The validated message, or None after reporting (log + event) what is wrong with it:
    a malformed message is refused whole, never half-applied."""
    try:
        return model.model_validate_json(msg.data)
    except (ValidationError, BlackboardError) as exc:
        log.error("malformed message on %s refused: %s (%.200s)",
                  node.resolve_topic_name(topic), exc, msg.data)
        events.emit(Event(EventKind.ENDED, f"ros:{topic}", "FAILED", exc,
                          {"message": msg.data[:200]}))
        return None


def _entry(change: Change) -> dict[str, Any]:
    return {"value": to_json(change.value), "stamp": change.stamp, "stale": change.stale,
            "writer": change.writer}


def _log_failure(what: str) -> Callable[[Any], None]:
    def done(future: Any) -> None:
        exc = future.exception()
        if exc is not None:
            log.error("%s failed: %r", what, exc)

    return done
