"""Robot I/O for behaviours and actions: publishers, subscriptions, clients, action goals
and timers that are destroyed (goals: cancelled) when their owner ends; :class:`Latest` —
the newest message of a topic, with a thread-safe wait for a condition on it; and
:class:`Goal` — a ROS 2 action goal that a thread can wait for, interruptibly.

Inside ``run()`` use ``self.ros``::

    class Drive(Action):
        action_type = "driving"

        def run(self) -> None:
            cmd = self.ros.publisher(Twist, "cmd_vel")
            odom = self.ros.latest(Odometry, "odom")
            cmd.publish(forward(0.3))
            odom.wait_for(lambda m: m.pose.pose.position.x > 2.0, timeout_s=20.0)

A ROS 2 action (the ready-made :class:`~beehave.ros.actions.RosActionGoal` wraps this)::

            goal = self.ros.send_goal(NavigateToPose, "navigate_to_pose", request,
                                      feedback=lambda fb: log.info("%s m to go",
                                                                   fb.distance_remaining))
            result = goal.wait(timeout_s=120.0)  # cancels the goal if interrupted

Topic names are relative to the robot's namespace (the manager's node).
"""

from __future__ import annotations

import collections
import functools
import logging
import math
import threading
import time
import uuid
import weakref
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from beehave.clock import WallClock
from beehave.errors import BeehaveError, ConfigError, GoalFailed, Interrupted

log = logging.getLogger(__name__)

LATCHED = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""Reliable, transient-local, depth 1 (ROS 1's "latched"): a subscriber that joins late
still gets the last message at once. For state topics (LEDs, display, the factory)."""

M = TypeVar("M")

FLUSH_S = 0.1
"""How long a publisher about to be destroyed waits for its reliable subscribers to
acknowledge what it sent: the zero velocity a ``safe_state()`` publishes right before its
owner's publishers are destroyed must not be lost with them."""


def flush(publisher: Any, timeout_s: float = FLUSH_S) -> bool:
    """Wait (at most ``timeout_s``) until every reliable subscriber acknowledged what
    ``publisher`` sent; True when they have (or there are none)."""
    from rclpy.duration import Duration

    try:
        return bool(publisher.wait_for_all_acked(Duration(nanoseconds=int(timeout_s * 1e9))))
    except Exception:  # destroyed already, or an rmw without acknowledgements
        return False


def check_duration(owner: str, label: str, value: object, *, optional: bool = False) -> None:
    """Refuse a timeout that is not a finite number of seconds >= 0 (None allowed when
    ``optional``): NaN compares false with everything, so a wait bounded by it would last
    forever (or end at once), and infinity overflows the waiting primitives."""
    if value is None and optional:
        return
    if not (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value) and value >= 0):
        raise ConfigError(f"{owner}: {label} must be a finite number of seconds >= 0"
                          f"{' or None' if optional else ''}, got {value!r}")


_node_publishers: weakref.WeakKeyDictionary[Node, dict[tuple[Any, ...], Any]] = \
    weakref.WeakKeyDictionary()
_node_publishers_lock = threading.Lock()


def _qos_key(qos: QoSProfile | int) -> tuple[Any, ...]:
    if isinstance(qos, int):
        qos = QoSProfile(depth=qos)
    return (qos.history, qos.depth, qos.reliability, qos.durability, qos.liveliness,
            qos.deadline.nanoseconds, qos.lifespan.nanoseconds)


def node_publisher(node: Node, msg_type: type, topic: str,
                   qos: QoSProfile | int = 10) -> Any:
    """The publisher of ``msg_type`` on ``topic`` that ``node`` keeps for its whole life,
    made on first use (``destroy_node`` destroys it with the node's other entities)."""
    key = (msg_type, node.resolve_topic_name(topic), _qos_key(qos))
    with _node_publishers_lock:
        publishers = _node_publishers.setdefault(node, {})
        publisher = publishers.get(key)
        if publisher is None:
            publisher = publishers[key] = node.create_publisher(msg_type, topic, qos)
        return publisher


class SharedPublisher:
    """One owner's use of a publisher its node keeps (:meth:`RosIO.publisher` with
    ``shared=True``): :meth:`publish` works until the owner ends, then raises — as a
    destroyed publisher would, so an action that went STUCK cannot command the robot —
    while the publisher itself stays matched for the next owner."""

    def __init__(self, publisher: Any, owner: str) -> None:
        self._publisher, self._owner = publisher, owner
        self._lock = threading.Lock()
        self._closed = False

    @property
    def topic_name(self) -> str:
        return str(self._publisher.topic_name)

    def publish(self, msg: Any) -> None:
        with self._lock:  # a publish never follows close()
            if self._closed:
                raise BeehaveError(f"{self._owner}: has ended; cannot publish on "
                                   f"{self.topic_name}")
            self._publisher.publish(msg)

    def get_subscription_count(self) -> int:
        return int(self._publisher.get_subscription_count())

    def close(self) -> None:
        """No flush, unlike a publisher about to be destroyed: this one lives on and
        still delivers what it was given."""
        with self._lock:
            self._closed = True


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
        self._waiting = 0  # wait_for calls under way
        self.received_at: float | None = None  # time.monotonic() of the newest message

    def _on_message(self, msg: M) -> None:
        with self._cond:
            self._msg = msg
            self._count += 1
            self.received_at = time.monotonic()
            # Only a wait_for looks at the message. The condition is the owner's, shared
            # with its sleeps: waking them for every odometry message (50 Hz) would cost a
            # thread switch each while a control loop sleeps between its steps.
            if self._waiting:
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
        check_duration(f"waiting on {self.topic!r}", "timeout_s", timeout_s, optional=True)
        with self._cond:
            start_count = self._count

            def ready() -> bool:
                msg = self._msg
                if self._interrupted():
                    return True
                if msg is None or (newer and self._count == start_count):
                    return False
                return predicate is None or bool(predicate(msg))

            self._waiting += 1
            try:
                ok = self._clock.wait(self._cond, ready, timeout_s)
            finally:
                self._waiting -= 1
            if self._interrupted():
                raise Interrupted(f"interrupted while waiting on {self.topic!r}")
            if not ok:
                last = "no message yet" if self._msg is None else f"last: {self._msg!r:.200}"
                raise WaitTimeout(f"no message on {self.topic!r} satisfied the condition "
                                  f"within {timeout_s} s ({last})")
            assert self._msg is not None
            return self._msg


# action_msgs/GoalStatus values (not imported: action_msgs loads only with rclpy.action).
_STATUS_NAMES = {0: "UNKNOWN", 1: "ACCEPTED", 2: "EXECUTING", 3: "CANCELING", 4: "SUCCEEDED",
                 5: "CANCELED", 6: "ABORTED"}
_SUCCEEDED = 4
_UNKNOWN = 0
_ENDED = (4, 5, 6)  # SUCCEEDED, CANCELED, ABORTED


class Goal:
    """A goal accepted by a ROS 2 action server (made by :meth:`RosIO.send_goal`).

    ``feedback`` is the newest feedback message (None before the first); ``status`` the
    goal's status name (``"ACCEPTED"`` … ``"SUCCEEDED"``, ``"ABORTED"``, ``"CANCELED"``);
    ``done`` whether the server sent the result. :meth:`wait` waits for the result and
    :meth:`cancel` cancels; both are safe from any thread. When the owner ends, a goal still
    running is cancelled.
    """

    def __init__(self, handle: Any, action: str, *, cond: threading.Condition,
                 interrupted: Callable[[], bool], clock: WallClock, owner: str) -> None:
        self.action = action
        self._handle = handle
        self._cond = cond
        self._interrupted = interrupted
        self._clock = clock
        self._owner = owner
        self.feedback: Any = None
        self.feedback_error: BaseException | None = None
        self._cancel_future: Any = None
        #: ``time.monotonic()`` when the cancel was first asked for, or None.
        self.cancel_requested_at: float | None = None
        self._result_future = handle.get_result_async()
        self._result_future.add_done_callback(self._wake)

    def _wake(self, _: Any = None) -> None:
        with self._cond:
            self._cond.notify_all()

    @property
    def done(self) -> bool:
        return bool(self._result_future.done())

    @property
    def status(self) -> str:
        if self.done:
            return _STATUS_NAMES.get(self._result_future.result().status, "UNKNOWN")
        if self._cancel_future is not None:
            return "CANCELING"
        return _STATUS_NAMES.get(self._handle.status, "UNKNOWN")

    def wait(self, *, timeout_s: float | None = None, cancel_timeout_s: float = 0.5) -> Any:
        """Wait for the result and return it (the action's ``Result`` message).

        Raises :class:`~beehave.errors.GoalFailed` when the server aborts the goal or
        reports it cancelled by another client; :class:`WaitTimeout` after ``timeout_s``
        (the clock's time) and :class:`~beehave.errors.Interrupted` as soon as the owner is
        interrupted — in both cases after cancelling the goal (see :meth:`cancel`). An
        exception raised by the feedback callback is raised here, after cancelling too."""
        check_duration(self._owner, "timeout_s", timeout_s, optional=True)
        check_duration(self._owner, "cancel_timeout_s", cancel_timeout_s)
        deadline = None if timeout_s is None else self._clock.now() + timeout_s
        with self._cond:
            self._clock.wait(self._cond, lambda: (self.done or self._interrupted()
                                                  or self.feedback_error is not None),
                             None if deadline is None
                             else max(0.0, deadline - self._clock.now()))
        if self.feedback_error is not None:
            self.cancel(timeout_s=cancel_timeout_s)
            raise self.feedback_error
        if not self.done:
            interrupted = self._interrupted()
            self.cancel(timeout_s=cancel_timeout_s)
            if interrupted:
                raise Interrupted(f"{self._owner}: interrupted while its goal on "
                                  f"{self.action!r} ran; the goal was cancelled")
            raise WaitTimeout(f"{self._owner}: the goal on {self.action!r} did not finish "
                              f"within {timeout_s} s; it was cancelled")
        response = self._result_future.result()
        status = _STATUS_NAMES.get(response.status, "UNKNOWN")
        if response.status != _SUCCEEDED:
            raise GoalFailed(f"{self._owner}: the server of {self.action!r} ended the goal "
                             f"{status} (result: {response.result!r:.200})",
                             status=status, result=response.result)
        return response.result

    def cancel(self, *, timeout_s: float = 0.5) -> bool:
        """Ask the server to cancel the goal and wait, at most ``timeout_s`` (wall time, as
        every bound on stopping), until it has ended. Returns whether it has ended.
        Idempotent; does nothing when the goal is done already."""
        check_duration(self._owner, "timeout_s", timeout_s)
        if self.done:
            return True
        with self._cond:
            if self._cancel_future is None:
                self.cancel_requested_at = time.monotonic()
                self._cancel_future = self._handle.cancel_goal_async()
                self._cancel_future.add_done_callback(self._wake)
            cancel = self._cancel_future

        def settled() -> bool:
            if self.done:
                return True
            # A server that refuses to cancel answers with no goals canceling.
            return bool(cancel.done() and not cancel.result().goals_canceling)

        with self._cond:
            self._cond.wait_for(settled, timeout_s)
        return self.done

    def _on_feedback(self, msg: Any, user: Callable[[Any], None] | None) -> None:
        # In the executor thread.
        self.feedback = msg.feedback
        if user is not None and self.feedback_error is None:
            try:
                user(msg.feedback)
            except Exception as exc:  # surfaced by wait(): the owner fails, not the executor
                self.feedback_error = exc
        self._wake()


def _wait_answered(future: Any, cond: threading.Condition, clock: WallClock,
                   interrupted: Callable[[], bool], deadline: float) -> None:
    """Wait until the rclpy ``future`` is done, the owner is interrupted or ``deadline``
    (the clock's time) passes; the caller looks at which."""

    def answered(_: Any) -> None:
        with cond:
            cond.notify_all()

    future.add_done_callback(answered)
    with cond:
        clock.wait(cond, lambda: future.done() or interrupted(),
                   max(0.0, deadline - clock.now()))


_watchers: dict[int, list[Callable[[type, str], None]]] = {}
_watchers_lock = threading.Lock()


def watch_subscriptions(node: Any, callback: Callable[[type, str], None]) -> Callable[[], None]:
    """Call ``callback(msg_type, topic)`` (the fully resolved topic) whenever a behaviour,
    action or HAL subscribes on ``node`` through :class:`RosIO`; returns a function that
    stops it. The recorder uses it to record what the high level reads
    (:mod:`beehave.recording.inputs`), in the thread that subscribes: keep it short."""
    with _watchers_lock:
        _watchers.setdefault(id(node), []).append(callback)

    def unwatch() -> None:
        with _watchers_lock:
            callbacks = _watchers.get(id(node), [])
            if callback in callbacks:
                callbacks.remove(callback)
            if not callbacks:
                _watchers.pop(id(node), None)

    return unwatch


@functools.cache
def _whole_action_client() -> type:
    """``rclpy.action.ActionClient`` with two races of rclpy 9.1.2 closed.

    - Its constructor adds the client to the node (``add_waitable``) and only then makes
      ``self._lock``: an executor spinning in another thread that counts the node's
      entities in between raises ``AttributeError: ... '_lock'`` and misses the client's
      entities, so a goal answer is lost (a 5 s ``WaitTimeout``). Here the lock is made
      first, and the constructor's own later assignment keeps it (one lock for the
      client's whole life, never swapped while someone holds it).
    - Its ``send_goal_async`` files the request's future under the lock and then, outside
      it, files a second future in its place and returns that one (a merge left the code
      from before the fix of rclpy#1123 behind it): an answer the executor thread handles
      in between completes the first future, and the returned one never completes — a
      goal answer lost on a loaded host. Here one future is filed, under the lock, and the
      feedback callback before the request goes out (feedback that overtakes the answer
      was dropped), and taken off again when the server refuses the goal.

    And one race of rmw_fastrtps: a server drops its answer to a goal when its own
    discovery has not yet matched the client's answer reader after 100 ms (``failed to
    send response (timeout): client will not receive response``; the client's
    ``server_is_ready`` only says what the client has discovered). The server runs the
    goal all the same, and lists it on its status topic (transient local): here a goal
    whose answer is still pending is taken as accepted once the status lists it (logged),
    and its answer, should it come later, is dropped."""
    from rclpy.action.client import ActionClient, ClientGoalHandle
    from rclpy.task import Future
    from unique_identifier_msgs.msg import UUID

    class WholeActionClient(ActionClient[Any, Any, Any]):
        @property
        def _lock(self) -> threading.Lock:
            lock: threading.Lock = self.__dict__["_whole_lock"]
            return lock

        @_lock.setter
        def _lock(self, value: threading.Lock) -> None:
            self.__dict__.setdefault("_whole_lock", value)

        def __init__(self, *args: Any, node_lived: bool = False, **kwargs: Any) -> None:
            self._lock = threading.Lock()
            self._node_lived = node_lived
            # Requests answered from the status: their answer, if it comes, is dropped.
            # The latest few (a lost answer never comes to take its number off again).
            self._answered_by_status: collections.deque[int] = collections.deque(maxlen=64)
            super().__init__(*args, **kwargs)

        async def execute(self, taken_data: Any) -> None:
            answer = taken_data.get("goal")
            if answer is not None and answer[0] in self._answered_by_status:
                self._answered_by_status.remove(answer[0])  # late: the status told already
                taken_data = {k: v for k, v in taken_data.items() if k != "goal"}
            await super().execute(taken_data)
            if "status" in taken_data:
                self._accept_listed(taken_data["status"].status_list)

        def _accept_listed(self, listed: Any) -> None:
            """Goals whose answer is pending but which the server's status lists: accepted
            (their answer was lost, see above)."""
            done = []
            with self._lock:
                # (A copy first: rclpy takes entries off without this lock.)
                pending = {bytes(goal_id.uuid): seq for seq, goal_id
                           in list(self._goal_sequence_number_to_goal_id.items())}
                for entry in listed if pending else ():
                    key = bytes(entry.goal_info.goal_id.uuid)
                    seq = pending.get(key)
                    if seq is None or entry.status == _UNKNOWN:
                        continue
                    future = self._pending_goal_requests.get(seq)
                    if future is None or future.done():
                        continue
                    answer = self._action_type.Impl.SendGoalService.Response(
                        accepted=True, stamp=entry.goal_info.stamp)
                    handle = ClientGoalHandle(self, entry.goal_info.goal_id, answer)
                    handle._status = entry.status
                    if entry.status not in _ENDED:
                        self._goal_handles[key] = weakref.ref(handle)
                    self._answered_by_status.append(seq)
                    done.append((future, handle))
            for future, handle in done:
                # Not a warning: the status may just have overtaken the answer (another
                # topic), which is then dropped when it comes.
                log.info("action server %r: its status lists goal %s before its answer "
                         "came; taken as accepted (an answer the server's middleware "
                         "dropped never comes)", self._action_name,
                         uuid.UUID(bytes=bytes(handle.goal_id.uuid)))
                future.set_result(handle)

        def destroy(self) -> None:
            if self._node_lived:  # shared by every owner on the node: see node_action_client
                log.warning("action client of %r: not destroyed; it is the node's, shared by "
                            "every owner on it, and goes with the node", self._action_name)
                return
            super().destroy()

        def _release(self) -> None:
            self._node_lived = False
            self.destroy()

        def send_goal_async(self, goal: Any, feedback_callback: Callable[[Any], None] | None
                            = None, goal_uuid: Any = None) -> Any:
            if not isinstance(goal, self._action_type.Goal):
                raise TypeError(f"Expected goal type ({self._action_type.Goal}) but received "
                                f"({type(goal)})")
            request = self._action_type.Impl.SendGoalService.Request()
            request.goal_id = (UUID(uuid=list(uuid.uuid4().bytes)) if goal_uuid is None
                               else goal_uuid)
            request.goal = goal
            key = bytes(request.goal_id.uuid)
            future: Any = Future()
            with self._lock:
                if feedback_callback is not None:
                    self._feedback_callbacks[key] = feedback_callback
                try:
                    sequence_number = self._client_handle.send_goal_request(request)
                except BaseException:
                    self._feedback_callbacks.pop(key, None)
                    raise
                if sequence_number in self._pending_goal_requests:
                    self._feedback_callbacks.pop(key, None)
                    raise RuntimeError(f"Sequence ({sequence_number}) conflicts with pending "
                                       "goal request")
                self._pending_goal_requests[sequence_number] = future
                self._goal_sequence_number_to_goal_id[sequence_number] = request.goal_id
                future.add_done_callback(self._remove_pending_goal_request)
                self.add_future(future)

            def refused(answered: Any) -> None:
                if (answered.cancelled() or answered.exception() is not None
                        or not answered.result().accepted):
                    self._feedback_callbacks.pop(key, None)

            future.add_done_callback(refused)
            return future

    return WholeActionClient


_node_action_clients_lock = threading.Lock()


def node_action_client(node: Node, action_type: type, name: str) -> Any:
    """The action client of ``action_type`` for the server ``name`` that ``node`` keeps for
    its whole life, made on first use and shared by every owner on the node
    (:meth:`RosContext.destroy_node` destroys it with the node).

    Why for the node's life, not the owner's: rclpy 9.1.2's ``EventsExecutor`` crashes the
    process (SIGSEGV) when an action client — any Waitable — leaves it while an answer for
    it is queued: the queued event, dropped, releases the last reference to a context
    manager without the interpreter lock. Action clients destroyed when their owner ended,
    while the server still sent status, feedback or results, did exactly that. A client
    that stays also keeps its DDS endpoints matched, so once one goal went to a server,
    a later owner's goal does not meet a server that has not discovered the client yet.
    Its ``destroy()`` only warns: the node's clients go with the node."""
    key = (action_type, node.resolve_topic_name(name))
    with _node_action_clients_lock:
        # Kept on the node itself: collected with it, and no walk over node.waitables,
        # which other threads change meanwhile (every publisher and subscription adds to
        # it, every owner that ends takes from it).
        clients: dict[tuple[type, str], Any] = node.__dict__.setdefault(_NODE_CLIENTS, {})
        client = clients.get(key)
        if client is None:
            client = clients[key] = _whole_action_client()(node, action_type, name,
                                                           node_lived=True)
        return client


_NODE_CLIENTS = "_beehave_action_clients"


def destroy_node_action_clients(node: Node) -> None:
    """Destroy the clients :func:`node_action_client` made on ``node`` (with the node)."""
    with _node_action_clients_lock:
        clients: dict[tuple[type, str], Any] = node.__dict__.pop(_NODE_CLIENTS, {})
    for client in clients.values():
        client._release()


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
        # send_goal() uses the node's action client (node_action_client).
        self._call_clients: dict[tuple[type, str], Any] = {}

    def _track(self, kind: str, entity: Any) -> Any:
        with self._lock:
            if self._closed:
                self._destroy(kind, entity)
                raise BeehaveError(f"{self.owner}: has ended; cannot create a {kind}")
            self._entities.append((kind, entity))
        return entity

    def publisher(self, msg_type: type, topic: str, *, qos: QoSProfile | int = 10,
                  shared: bool = False) -> Any:
        """A publisher destroyed when the owner ends. ``shared=True``: a
        :class:`SharedPublisher` on the one publisher the node keeps for ``topic``, so
        the robot hears the first message at once — a new publisher is new to DDS, and
        what it sends before discovery matched it is lost. For the topics every action of
        a kind commands (``cmd_vel``, the lift)."""
        if not shared:
            return self._track("publisher", self.node.create_publisher(msg_type, topic, qos))
        return self._track("shared_publisher", SharedPublisher(
            node_publisher(self.node, msg_type, topic, qos), self.owner))

    def subscription(self, msg_type: type, topic: str, callback: Callable[[Any], None], *,
                     qos: QoSProfile | int = 10) -> Any:
        """``callback(msg)`` runs in the executor thread: keep it short."""
        with _watchers_lock:
            watchers = list(_watchers.get(id(self.node), ()))
        if watchers:
            # Before subscribing: a recorder must not miss the first message it gets.
            resolved = self.node.resolve_topic_name(topic)
            for watch in watchers:
                watch(msg_type, resolved)
        return self._track("subscription",
                           self.node.create_subscription(msg_type, topic, callback, qos))

    def client(self, srv_type: type, name: str) -> Any:
        return self._track("client", self.node.create_client(srv_type, name))

    def timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        return self._track("timer", self.node.create_timer(period_s, callback))

    def action_client(self, action_type: type, name: str) -> Any:
        """The ``rclpy.action.ActionClient`` for the action server ``name`` that the node
        keeps for its whole life, shared by every owner on the node (see
        :func:`node_action_client`; do not destroy it). Prefer :meth:`send_goal`, which
        waits interruptibly and cancels the owner's goals when it ends."""
        self._refuse_when_ended("action client")
        make = getattr(self.node, "create_action_client", None)
        if make is not None:  # a stand-in node (a replay's) makes its own, or refuses
            return make(action_type, name)
        return node_action_client(self.node, action_type, name)

    def send_goal(self, action_type: type, name: str, goal: Any, *,
                  feedback: Callable[[Any], None] | None = None,
                  server_timeout_s: float = 5.0) -> Goal:
        """Send ``goal`` to the action server ``name`` and return the accepted :class:`Goal`
        (``.wait()`` for its result).

        Waits for the server to be available and to accept, ``server_timeout_s`` in all
        (the clock's time): :class:`WaitTimeout` when it is not there,
        :class:`~beehave.errors.GoalFailed` (``status="REJECTED"``) when it refuses,
        :class:`~beehave.errors.Interrupted` as soon as the owner is interrupted.
        ``feedback(msg)`` runs in the executor thread for each feedback message (keep it
        short); ``Goal.feedback`` always holds the newest. Goals to one server share the
        node's client; a goal still running when the owner ends is cancelled, and so is one
        the server accepts after its sender gave up.
        """
        check_duration(self.owner, "server_timeout_s", server_timeout_s)
        client = self.action_client(action_type, name)
        cond = self._cond if self._cond is not None else threading.Condition()
        clock = self._clock or WallClock()
        interrupted = self._interrupted or (lambda: False)
        deadline = clock.now() + server_timeout_s
        full = self.node.resolve_topic_name(name)
        self._wait_ready(client.server_is_ready, cond, clock, interrupted, deadline,
                         f"action server {full!r} is not available after "
                         f"{server_timeout_s} s")
        box: list[Goal] = []
        early: list[Any] = []
        gave_up: list[bool] = []

        def on_feedback(msg: Any) -> None:
            with cond:
                if gave_up:  # a late-accepted goal, being cancelled: nobody reads it
                    return
                if not box:  # feedback can overtake the acceptance: keep it for later
                    early.append(msg)
                    return
            box[0]._on_feedback(msg, feedback)  # user code: never under the owner's lock

        sent = client.send_goal_async(goal, feedback_callback=on_feedback)
        _wait_answered(sent, cond, clock, interrupted, deadline)
        if not sent.done():
            # The server may still accept it: then cancel at once, so that no goal runs on
            # without an owner (the node's client outlives the owner to do so), and ask for
            # its result, whose answer makes rclpy forget the goal's feedback callback.
            def cancel_if_accepted(answered: Any) -> None:
                handle = (None if answered.cancelled() or answered.exception() is not None
                          else answered.result())
                if handle is not None and handle.accepted:
                    handle.cancel_goal_async()
                    handle.get_result_async()

            with cond:
                gave_up.append(True)
                early.clear()
            sent.add_done_callback(cancel_if_accepted)
            if interrupted():
                raise Interrupted(f"{self.owner}: interrupted while sending a goal to {full!r}")
            raise WaitTimeout(f"action server {full!r} did not answer the goal within "
                              f"{server_timeout_s} s")
        handle = sent.result()
        if not handle.accepted:
            raise GoalFailed(f"{self.owner}: action server {full!r} REJECTED the goal "
                             f"{goal!r:.200}", status="REJECTED")
        accepted = Goal(handle, full, cond=cond, interrupted=interrupted, clock=clock,
                        owner=self.owner)
        with cond:
            box.append(accepted)
            overtaken = list(early)
        for msg in overtaken:
            accepted._on_feedback(msg, feedback)
        try:
            self._track("goal", accepted)
        except BeehaveError:
            accepted.cancel(timeout_s=0.0)  # the owner ended meanwhile
            raise
        # A finished goal has nothing left to cancel: an owner that sends goals in a loop
        # must not keep every one of them.
        accepted._result_future.add_done_callback(lambda _: self._forget("goal", accepted))
        return accepted

    def _forget(self, kind: str, entity: Any) -> None:
        with self._lock:
            try:
                self._entities.remove((kind, entity))
            except ValueError:
                pass

    def _cached_client(self, srv_type: type, name: str) -> Any:
        key = (srv_type, self.node.resolve_service_name(name))
        cache = self._call_clients
        with self._lock:
            client = cache.get(key)
        if client is None:
            client = self.client(srv_type, name)  # refused once the owner has ended
            with self._lock:
                # Two threads of one owner may race here: keep the first, drop the other.
                kept = cache.setdefault(key, client)
            if kept is not client:
                self._untrack("client", client)
                client = kept
        return client

    def _refuse_when_ended(self, what: str) -> None:
        with self._lock:
            if self._closed:
                raise BeehaveError(f"{self.owner}: has ended; cannot create a {what}")

    def _wait_ready(self, ready: Callable[[], bool], cond: threading.Condition,
                    clock: WallClock, interrupted: Callable[[], bool], deadline: float,
                    missing: str) -> None:
        while not ready():  # no event for this: look in short slices
            if interrupted():
                raise Interrupted(f"{self.owner}: interrupted while waiting: {missing}")
            if clock.now() >= deadline:
                raise WaitTimeout(missing)
            with cond:
                clock.wait(cond, interrupted, min(0.02, deadline - clock.now()))

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
        check_duration(self.owner, "timeout_s", timeout_s)
        client = self._cached_client(srv_type, name)
        cond = self._cond if self._cond is not None else threading.Condition()
        clock = self._clock or WallClock()
        interrupted = self._interrupted or (lambda: False)
        deadline = clock.now() + timeout_s
        full = self.node.resolve_service_name(name)
        self._wait_ready(client.service_is_ready, cond, clock, interrupted, deadline,
                         f"service {full!r} is not available after {timeout_s} s")
        future = client.call_async(request)
        _wait_answered(future, cond, clock, interrupted, deadline)
        if not future.done():
            future.cancel()
            if interrupted():
                raise Interrupted(f"{self.owner}: interrupted while calling {full!r}")
            raise WaitTimeout(f"service {full!r} did not answer within {timeout_s} s")
        return future.result()

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
        """Destroy everything created here; later creations are refused.

        Goals still running are asked to cancel (not waited for); publishers first wait,
        :data:`FLUSH_S` at most, for their reliable subscribers' acknowledgements. The node's
        action clients stay (:func:`node_action_client`)."""
        with self._lock:
            self._closed = True
            entities, self._entities = self._entities, []
            self._call_clients.clear()
        for kind, entity in reversed(entities):
            self._destroy(kind, entity)

    def _destroy(self, kind: str, entity: Any) -> None:
        if kind == "goal":
            # The owner ended (after safe_state): a goal still running must not go on
            # driving the robot. Ask once, do not wait here.
            entity.cancel(timeout_s=0.0)
        elif kind == "shared_publisher":
            entity.close()
        else:
            if kind == "publisher":
                flush(entity)
            getattr(self.node, f"destroy_{kind}")(entity)
