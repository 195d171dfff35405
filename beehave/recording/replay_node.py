"""The ROS 2 node a replayed high level runs on: nothing leaves it, recorded data comes in.

A replay (:mod:`beehave.recording.replay`) gives the high level a :class:`ReplayNode`
instead of an rclpy node, so behaviours and actions run unchanged — ``self.ros`` builds
its publishers, subscriptions and timers on it — while nothing reaches ROS:

- a publisher *captures* each message (:class:`Captured`: topic, message as a dict, time)
  instead of sending it — ``cmd_vel``, the lift's command, sounds, progress reports;
- a subscription receives the recorded messages of its topic, at their recorded times,
  from the replay's feed;
- a timer fires on the replay's clock;
- a service client or an action client cannot be replayed (their answers are not
  recorded): creating one raises :class:`~beehave.errors.RecordingError` naming it, so
  the action fails visibly and the determinism check reports where;
- parameters (a driving action's speed limit) hold their declared defaults.

The lockstep line (``/lockstep``) is no actuator: its announcements pace the replay's
clock as they pace a simulator (see :meth:`ReplayNode.holds`), and are not captured.
"""

from __future__ import annotations

import heapq
import json
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from beehave.clock import SimClock
from beehave.errors import RecordingError

__all__ = ["Captured", "ReplayClock", "ReplayNode", "message_dict"]

LOCKSTEP = "/lockstep"


@dataclass(frozen=True)
class Captured:
    """A message a replayed behaviour or action published: it was captured, not sent.
    ``topic`` is fully resolved, ``value`` the message as a dict, ``t_s`` the replay time
    (seconds since the recording's start)."""

    topic: str
    type_name: str
    value: Any
    t_s: float


def message_dict(msg: Any) -> Any:
    """A ROS 2 message as plain data (dicts, lists, numbers, strings)."""
    fields = getattr(msg, "get_fields_and_field_types", None)
    if fields is None:
        if isinstance(msg, (list, tuple)) or type(msg).__name__ == "array":
            return [message_dict(v) for v in msg]
        if isinstance(msg, float) and not math.isfinite(msg):
            return {"$float": str(msg)}
        if isinstance(msg, (bytes, bytearray)):
            return list(msg)
        return msg
    return {name: message_dict(getattr(msg, name)) for name in fields()}


class _Parameter:
    def __init__(self, name: str, value: Any) -> None:
        self.name, self.value = name, value


class _Publisher:
    def __init__(self, node: ReplayNode, msg_type: type, topic: str) -> None:
        self.node, self.msg_type, self.topic = node, msg_type, topic

    def publish(self, msg: Any) -> None:
        self.node._published(self, msg)

    def get_subscription_count(self) -> int:
        return 1  # nobody listens, but nobody must wait for a listener either

    def wait_for_all_acked(self, *_: Any) -> bool:
        return True


class _Subscription:
    def __init__(self, msg_type: type, topic: str, callback: Callable[[Any], None]) -> None:
        self.msg_type, self.topic, self.callback = msg_type, topic, callback


class _Timer:
    def __init__(self, period_s: float, callback: Callable[[], None], now_s: float) -> None:
        self.period_s, self.callback = period_s, callback
        self.next_s = now_s + period_s


class ReplayNode:
    """Stands in for the high level's rclpy node during a replay (module docstring).

    ``namespace``: the robot's (topics resolve under it as on the real node).
    ``now_s()``: the replay's time for captured messages and timers. ``on_subscribe(sub)``
    is told of each new subscription (the feed hands it what it missed a moment ago).
    """

    def __init__(self, namespace: str, *, now_s: Callable[[], float],
                 on_subscribe: Callable[[Any], None] | None = None) -> None:
        self._namespace = "/" + namespace.strip("/") if namespace.strip("/") else "/"
        self._now_s = now_s
        self._on_subscribe = on_subscribe
        self._lock = threading.Lock()
        self._subscriptions: dict[str, list[_Subscription]] = {}
        self._timers: list[_Timer] = []
        self._parameters: dict[str, _Parameter] = {}
        #: Every message published, in order (the lockstep line's excepted).
        self.captured: list[Captured] = []
        #: Lockstep: participant → the sim time it asked to be held at.
        self._holds: dict[str, float] = {}

    # -- what rclpy's Node offers and RosIO uses --------------------------------------------

    def get_name(self) -> str:
        return "beehave_high_level"

    def get_namespace(self) -> str:
        return self._namespace

    def get_fully_qualified_name(self) -> str:
        return f"{self._namespace.rstrip('/')}/{self.get_name()}"

    def resolve_topic_name(self, topic: str, *, only_expand: bool = False) -> str:
        if topic.startswith("/"):
            return topic
        return f"{self._namespace.rstrip('/')}/{topic.lstrip('~/')}"

    resolve_service_name = resolve_topic_name

    def create_publisher(self, msg_type: type, topic: str, qos: Any = 10,
                         **_: Any) -> _Publisher:
        return _Publisher(self, msg_type, self.resolve_topic_name(topic))

    def create_subscription(self, msg_type: type, topic: str, callback: Callable[[Any], None],
                            qos: Any = 10, **_: Any) -> _Subscription:
        sub = _Subscription(msg_type, self.resolve_topic_name(topic), callback)
        with self._lock:
            self._subscriptions.setdefault(sub.topic, []).append(sub)
        if self._on_subscribe is not None:
            self._on_subscribe(sub)
        return sub

    def create_timer(self, period_s: float, callback: Callable[[], None],
                     *_: Any, **__: Any) -> _Timer:
        timer = _Timer(float(period_s), callback, self._now_s())
        with self._lock:
            self._timers.append(timer)
        return timer

    def create_client(self, srv_type: type, name: str, **_: Any) -> Any:
        raise RecordingError(
            f"service {self.resolve_service_name(name)!r} ({srv_type.__name__}) cannot be "
            "called in a replay: its answers are not recorded")

    def create_action_client(self, action_type: type, name: str) -> Any:
        raise RecordingError(
            f"action server {self.resolve_topic_name(name)!r} ({action_type.__name__}) "
            "cannot be used in a replay: its answers are not recorded")

    def destroy_publisher(self, publisher: Any) -> None:
        return None

    def destroy_subscription(self, sub: _Subscription) -> None:
        with self._lock:
            subs = self._subscriptions.get(sub.topic, [])
            if sub in subs:
                subs.remove(sub)

    def destroy_timer(self, timer: _Timer) -> None:
        with self._lock:
            if timer in self._timers:
                self._timers.remove(timer)

    def destroy_client(self, client: Any) -> None:
        return None

    def has_parameter(self, name: str) -> bool:
        return name in self._parameters

    def declare_parameter(self, name: str, value: Any = None, *_: Any, **__: Any) -> Any:
        param = self._parameters.setdefault(name, _Parameter(name, value))
        return param

    def get_parameter(self, name: str) -> Any:
        return self._parameters[name]

    def add_on_set_parameters_callback(self, callback: Callable[..., Any]) -> None:
        return None  # nobody sets parameters in a replay

    # -- the feed's side ---------------------------------------------------------------------

    def subscriptions(self, topic: str) -> list[_Subscription]:
        with self._lock:
            return list(self._subscriptions.get(topic, ()))

    @property
    def topics(self) -> list[str]:
        """The topics subscribed to now."""
        with self._lock:
            return [t for t, subs in self._subscriptions.items() if subs]

    def fire_timers(self, now_s: float) -> None:
        """Run the timers due by ``now_s`` (the replay's clock), in the caller's thread."""
        with self._lock:
            due = [t for t in self._timers if t.next_s <= now_s]
            for timer in due:
                timer.next_s = max(timer.next_s + timer.period_s, now_s)
        for timer in due:
            timer.callback()

    def holds(self) -> dict[str, float]:
        """The lockstep holds announced and not let go: participant → sim time."""
        with self._lock:
            return dict(self._holds)

    def _published(self, publisher: _Publisher, msg: Any) -> None:
        if publisher.topic == LOCKSTEP:
            try:
                data = json.loads(msg.data)
                who, until = str(data["participant"]), data.get("until_s")
            except (ValueError, KeyError, TypeError, AttributeError):
                return
            with self._lock:
                if until is None:
                    self._holds.pop(who, None)
                else:
                    self._holds[who] = float(until)
            return
        item = Captured(publisher.topic, f"{publisher.msg_type.__module__.split('.')[0]}/"
                                         f"{publisher.msg_type.__name__}",
                        message_dict(msg), self._now_s())
        with self._lock:
            self.captured.append(item)


class ReplayClock(SimClock):
    """The replayed high level's clock: a :class:`~beehave.clock.SimClock` the feed moves,
    which also knows who waits on it. :meth:`ready` says whether a thread that waits here
    is due to run (its deadline passed, or what it waits for holds): the feed lets it run
    before it moves on, as a simulator in lockstep waits for its controllers."""

    def __init__(self) -> None:
        super().__init__()
        self._parked: dict[int, tuple[float, Callable[[], bool]]] = {}
        self._gate = math.inf  # deadlines after it are not reached yet (hold_wakes)

    def hold_wakes(self, from_s: float) -> None:
        """Until :meth:`release_wakes`, time moves but no timed wait due after ``from_s``
        ends: as a loaded host's late threads, which a switch or the shutdown cut
        off before their step."""
        with self._lock:
            self._gate = from_s

    def release_wakes(self) -> None:
        """End :meth:`hold_wakes`: the waits due by now end."""
        with self._lock:
            self._gate = math.inf
        self.set_time(self._now)

    def _due_until(self) -> float:
        return min(self._now, self._gate)

    def wait(self, cond: threading.Condition, predicate: Callable[[], bool],
             timeout_s: float | None) -> bool:
        me = threading.get_ident()
        deadline = math.inf if timeout_s is None else self._now + timeout_s
        entry = (deadline, next(self._ids), cond)
        if timeout_s is not None:
            with self._lock:
                heapq.heappush(self._waiters, entry)
        announce = getattr(self._local, "announce", None)
        try:
            if announce is not None and timeout_s is not None and not predicate():
                announce(deadline)
            while not predicate():
                if self._due_until() + self.SLACK_S >= deadline:
                    return predicate()
                self._parked[me] = (deadline, predicate)
                try:
                    cond.wait()
                finally:
                    self._parked.pop(me, None)
            return True
        finally:
            if timeout_s is not None:
                with self._lock:
                    if entry in self._waiters:
                        self._waiters.remove(entry)
                        heapq.heapify(self._waiters)

    def next_deadline(self) -> float | None:
        """The earliest deadline of a timed wait on this clock (None when nobody waits, or
        while :meth:`hold_wakes` holds it back)."""
        with self._lock:
            if not self._waiters or self._waiters[0][0] > self._gate + self.SLACK_S:
                return None
            return self._waiters[0][0]

    def parked(self) -> set[int]:
        """The threads waiting here for something that has not happened yet."""
        return set(self._parked)

    def ready(self) -> bool:
        """Whether a thread waiting here is due to run (woken, not yet running)."""
        now = self._due_until() + self.SLACK_S
        for deadline, predicate in list(self._parked.values()):
            if deadline <= now:
                return True
            try:
                if predicate():
                    return True
            except Exception:  # read without its lock: a torn read is no reason to stop
                return True
        return False
