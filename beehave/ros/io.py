"""Robot I/O for behaviours and actions: publishers, subscriptions, clients and timers that
are destroyed when their owner ends, and :class:`Latest` — the newest message of a topic,
with a thread-safe wait for a condition on it.

Inside ``run()`` use ``self.ros``::

    class Drive(Action):
        action_type = "driving"

        def run(self) -> None:
            cmd = self.ros.publisher(Twist, "cmd_vel")
            odom = self.ros.latest(Odometry, "odom")
            cmd.publish(forward(0.3))
            odom.wait_for(lambda m: m.pose.pose.position.x > 2.0, timeout_s=20.0)

Topic names are relative to the robot's namespace (the manager's node).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from rclpy.node import Node
from rclpy.qos import QoSProfile

from beehave.clock import WallClock
from beehave.errors import BeehaveError, Interrupted

M = TypeVar("M")


class WaitTimeout(BeehaveError, TimeoutError):
    """A wait for a message or condition did not succeed in time."""


class Latest(Generic[M]):
    """The newest message on a topic. ``get()`` never blocks; :meth:`wait_for` waits.

    Messages arrive in the executor thread; readers are any threads. When created by a
    behaviour or action (``self.ros.latest``), waits also end when it is interrupted.
    """

    def __init__(self, topic: str, *, cond: threading.Condition | None = None,
                 interrupted: Callable[[], bool] | None = None,
                 clock: WallClock | None = None) -> None:
        self.topic = topic
        self._cond = cond if cond is not None else threading.Condition()
        self._interrupted = interrupted or (lambda: False)
        self._clock = clock or WallClock()
        self._msg: M | None = None
        self._count = 0
        self.received_at: float | None = None  # time.monotonic() of the newest message

    def _on_message(self, msg: M) -> None:
        with self._cond:
            self._msg = msg
            self._count += 1
            self.received_at = time.monotonic()
            self._cond.notify_all()

    @property
    def count(self) -> int:
        """How many messages arrived so far."""
        return self._count

    def get(self) -> M | None:
        """The newest message, or None before the first."""
        return self._msg

    def wait_for(self, predicate: Callable[[M], bool] | None = None, *,
                 timeout_s: float | None = None, newer: bool = False) -> M:
        """Wait until a message satisfies ``predicate`` (any message when None) and return
        it. ``newer=True`` ignores the message held at the time of the call. Raises
        :class:`WaitTimeout` after ``timeout_s`` (the clock's time) and
        :class:`~beehave.errors.Interrupted` when the owner is interrupted."""
        with self._cond:
            start_count = self._count

            def ready() -> bool:
                msg = self._msg
                if self._interrupted():
                    return True
                if msg is None or (newer and self._count == start_count):
                    return False
                return predicate is None or bool(predicate(msg))

            ok = self._clock.wait(self._cond, ready, timeout_s)
            if self._interrupted():
                raise Interrupted(f"interrupted while waiting on {self.topic!r}")
            if not ok:
                last = "no message yet" if self._msg is None else f"last: {self._msg!r:.200}"
                raise WaitTimeout(f"no message on {self.topic!r} satisfied the condition "
                                  f"within {timeout_s} s ({last})")
            assert self._msg is not None
            return self._msg


class RosIO:
    """ROS entities owned by one behaviour, action or HAL; :meth:`destroy_all` ends them.

    The framework calls ``destroy_all`` when the owner ends, whatever its status (after
    ``safe_state()``, so a safe state may still publish). Every method is thread-safe.
    """

    def __init__(self, node: Node, *, owner: str = "", cond: threading.Condition | None = None,
                 interrupted: Callable[[], bool] | None = None,
                 clock: WallClock | None = None) -> None:
        self.node = node
        self.owner = owner
        self._cond = cond
        self._interrupted = interrupted
        self._clock = clock
        self._lock = threading.Lock()
        self._entities: list[tuple[str, Any]] = []
        self._closed = False
        # The clients call() uses, one per (type, resolved name): a behaviour that polls a
        # service in a loop must not leave a client (and its DDS readers) per call.
        self._call_clients: dict[tuple[type, str], Any] = {}

    def _track(self, kind: str, entity: Any) -> Any:
        with self._lock:
            if self._closed:
                self._destroy(kind, entity)
                raise BeehaveError(f"{self.owner}: has ended; cannot create a {kind}")
            self._entities.append((kind, entity))
        return entity

    def publisher(self, msg_type: type, topic: str, *, qos: QoSProfile | int = 10) -> Any:
        return self._track("publisher", self.node.create_publisher(msg_type, topic, qos))

    def subscription(self, msg_type: type, topic: str, callback: Callable[[Any], None], *,
                     qos: QoSProfile | int = 10) -> Any:
        """``callback(msg)`` runs in the executor thread: keep it short."""
        return self._track("subscription",
                           self.node.create_subscription(msg_type, topic, callback, qos))

    def client(self, srv_type: type, name: str) -> Any:
        return self._track("client", self.node.create_client(srv_type, name))

    def timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        return self._track("timer", self.node.create_timer(period_s, callback))

    def latest(self, msg_type: type, topic: str, *, qos: QoSProfile | int = 10) -> Latest[Any]:
        """Subscribe to ``topic`` and keep its newest message (see :class:`Latest`)."""
        latest: Latest[Any] = Latest(self.node.resolve_topic_name(topic), cond=self._cond,
                                     interrupted=self._interrupted, clock=self._clock)
        self.subscription(msg_type, topic, latest._on_message, qos=qos)
        return latest

    def call(self, srv_type: type, name: str, request: Any, *, timeout_s: float = 5.0) -> Any:
        """Call a service and wait for the response, ``timeout_s`` in all (the clock's
        time). Raises :class:`WaitTimeout`, or :class:`~beehave.errors.Interrupted` as
        soon as the owner is interrupted. Calls to one service (name and type) share one
        client, created at the first call and destroyed with the owner."""
        client = self._client_for_calls(srv_type, name)
        cond = self._cond if self._cond is not None else threading.Condition()
        clock = self._clock or WallClock()
        interrupted = self._interrupted or (lambda: False)
        deadline = clock.now() + timeout_s
        full = self.node.resolve_service_name(name)
        while not client.service_is_ready():  # no event for this: look in short slices
            if interrupted():
                raise Interrupted(f"{self.owner}: interrupted while waiting for {full!r}")
            if clock.now() >= deadline:
                raise WaitTimeout(f"service {full!r} is not available after {timeout_s} s")
            with cond:
                clock.wait(cond, interrupted, min(0.02, deadline - clock.now()))
        future = client.call_async(request)

        def answered(_: Any) -> None:
            with cond:
                cond.notify_all()

        future.add_done_callback(answered)
        with cond:
            clock.wait(cond, lambda: future.done() or interrupted(),
                       max(0.0, deadline - clock.now()))
        if not future.done():
            future.cancel()
            if interrupted():
                raise Interrupted(f"{self.owner}: interrupted while calling {full!r}")
            raise WaitTimeout(f"service {full!r} did not answer within {timeout_s} s")
        return future.result()

    def _client_for_calls(self, srv_type: type, name: str) -> Any:
        key = (srv_type, self.node.resolve_service_name(name))
        with self._lock:
            client = self._call_clients.get(key)
        if client is None:
            client = self.client(srv_type, name)  # refused once the owner has ended
            with self._lock:
                # Two threads of one owner may race here: keep the first, drop the other.
                kept = self._call_clients.setdefault(key, client)
            if kept is not client:
                self._untrack("client", client)
                client = kept
        return client

    def _untrack(self, kind: str, entity: Any) -> None:
        with self._lock:
            try:
                self._entities.remove((kind, entity))
            except ValueError:
                return  # destroy_all() took it already
        self._destroy(kind, entity)

    @property
    def entities(self) -> list[tuple[str, Any]]:
        with self._lock:
            return list(self._entities)

    def destroy_all(self) -> None:
        """Destroy everything created here; later creations are refused."""
        with self._lock:
            self._closed = True
            entities, self._entities = self._entities, []
            self._call_clients.clear()
        for kind, entity in reversed(entities):
            self._destroy(kind, entity)

    def _destroy(self, kind: str, entity: Any) -> None:
        destroy = getattr(self.node, f"destroy_{kind}")
        destroy(entity)
