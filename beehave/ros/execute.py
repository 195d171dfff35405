"""``beehave/execute_behavior``: a ROS 2 action that runs a top-level behaviour as a goal.

Any ROS 2 program with an ``rclpy.action.ActionClient`` (or ``ros2 action send_goal``)
sends a goal — a behaviour's name and its parameters as JSON — and the robot switches to
that behaviour, sends feedback while it runs (the running actions, each engine's state),
and a result when it ends; a cancel switches to ``idle``. What happens to a second goal
while one executes is the robot's policy (``ros.second_goal`` in its YAML): ``reject`` it,
or ``preempt`` the running one.

The type is beehave's own, ``beehave_interfaces/action/ExecuteBehavior``
(``ros_interfaces/beehave_interfaces``), generated with rosidl at set-up time
(``scripts/build_ros_interfaces.sh``): no action type among the ROS 2 wheels on PyPI can
carry a behaviour's name and parameters under fields that say so.

A ROS 2 goal response carries no reason (``accepted`` is a bool), so this server rejects
no goal it can name a reason for: a goal it will not run — an unknown behaviour, bad
parameters, a second goal under ``reject`` — is accepted and ABORTED at once, before
anything is switched, with ``result.refused = true`` and ``result.message`` naming the
valid choices. Everything is validated by the control-plane core
(:meth:`ControlPlane.check_switch`), so a goal is refused exactly as a switch over HTTP
or VDA 5050 would be, with the same words. ``docs/ros.md`` is the specification.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Literal

from rclpy.action.server import ActionServer, CancelResponse, GoalResponse, ServerGoalHandle
from rclpy.node import Node
from rclpy.task import Future

from beehave.behavior import Behavior
from beehave.blackboard import to_json
from beehave.errors import BeehaveError, ConfigError
from beehave.events import Event, EventKind
from beehave.highlevel import IDLE
from beehave.interfaces.core import ControlPlane, bounded, shorten
from beehave.status import Status

log = logging.getLogger(__name__)

#: The action's name, relative to the robot's namespace.
ACTION_NAME = "beehave/execute_behavior"

#: What to do with a goal that arrives while another one executes.
SecondGoal = Literal["reject", "preempt"]
SECOND_GOAL_POLICIES: tuple[str, ...] = ("reject", "preempt")

#: A ``params_json`` longer than this is refused unread (an outsider must not make the
#: robot parse megabytes).
MAX_PARAMS_CHARS = 64 * 1024
#: How often the running goal is looked at (feedback on change, a request that never ran).
_TICK_S = 0.1
#: How long :meth:`ExecuteBehaviorServer.destroy` waits (wall time) for the results of the
#: goals it ends to be handed to rclpy before the action server goes away.
_RESULT_FLUSH_S = 1.0
#: And then, when it ended goals, how long it keeps the server (wall time): a result is
#: sent reliably, and a sample lost on its first way (a loaded host) is sent again only
#: while its writer exists (a client once never got the result of a goal its robot ended
#: by shutting down).
_RESULT_GRACE_S = 0.5


class InterfacesMissing(ConfigError):
    """The ``beehave_interfaces`` package (the ExecuteBehavior action type) is not built."""


def load_action_type() -> type[Any]:
    """The ``ExecuteBehavior`` action type, or :class:`InterfacesMissing` saying how to
    build it."""
    try:
        from beehave_interfaces.action import ExecuteBehavior
    except ImportError as exc:
        raise InterfacesMissing(
            f"beehave/execute_behavior needs the ROS 2 interface package beehave_interfaces, "
            f"which is built at set-up time: run `make setup` (or "
            f"`bash scripts/build_ros_interfaces.sh .venv`); import failed: {exc}") from exc
    action: type[Any] = ExecuteBehavior
    return action


@dataclass(eq=False)
class _Goal:
    """One accepted goal, from its acceptance to its result."""

    handle: ServerGoalHandle[Any, Any, Any]
    goal_id: uuid.UUID
    name: str
    #: Completed with the Result message once the goal has ended (any thread may complete
    #: it; the action server's execute coroutine awaits it in the executor thread).
    result: Future[Any]
    behavior: Behavior | None = None  # None: refused before anything was switched
    lock: threading.Lock = field(default_factory=threading.Lock)
    done: bool = False
    #: The terminal status the execute coroutine gives the goal handle.
    outcome: Literal["SUCCEEDED", "CANCELED", "ABORTED"] = "ABORTED"
    cancel_requested: bool = False
    preempted_by: uuid.UUID | None = None
    #: Ticks on which the behaviour was seen neither running nor queued (see _tick).
    unqueued_ticks: int = 0
    #: The ``idle`` a cancel switched to: the goal ends once it runs, so that a client
    #: reading the robot's state after CANCELED finds it idle (see _check).
    idle: Behavior | None = None
    #: Set before the cancel asks for ``idle`` (the behaviour may end before the request
    #: returns): the goal waits for that ``idle`` even before it is known.
    idle_asked: bool = False
    idle_unqueued_ticks: int = 0
    last_feedback: str | None = None
    last_feedback_at: float = 0.0
    sent: threading.Event = field(default_factory=threading.Event)


class ExecuteBehaviorServer:
    """Serves the ``beehave/execute_behavior`` action for one robot on its high-level
    ``node``.

    ``plane``: the robot's control plane (validation, state); ``second_goal``: ``"reject"``
    (a goal that arrives while one executes is refused — ABORTED at once, naming the
    running one) or ``"preempt"`` (the running goal is ABORTED with "preempted by goal …"
    and the new one runs; the switch replaces one behaviour by the other as any switch
    does); ``feedback_period_s``: the feedback heartbeat (feedback also goes out at once
    when what runs changes). At most one goal executes at a time: the robot runs one
    top-level behaviour.

    A switch made by other means (the ``behavior`` parameter, ``beehave/stop``, HTTP, VDA
    5050) while a goal executes ends that goal: ABORTED, the message names the switch. A
    behaviour that ends on its own ends its goal: SUCCEEDED when its ``run`` returned (its
    return value is the result's ``value_json``), ABORTED when it failed or went STUCK.
    :meth:`destroy` aborts a goal that still executes and removes the action server and
    its timer from the node. Raises :class:`InterfacesMissing` when ``beehave_interfaces``
    has not been built.
    """

    def __init__(self, plane: ControlPlane, node: Node, *,
                 second_goal: SecondGoal = "reject", feedback_period_s: float = 1.0) -> None:
        if second_goal not in SECOND_GOAL_POLICIES:
            raise ConfigError(f"ExecuteBehaviorServer: second_goal must be one of "
                              f"{', '.join(SECOND_GOAL_POLICIES)}, got {second_goal!r}")
        if not (isinstance(feedback_period_s, (int, float))
                and not isinstance(feedback_period_s, bool)
                and 0 < feedback_period_s < float("inf")):
            raise ConfigError(f"ExecuteBehaviorServer: feedback_period_s must be a finite "
                              f"number of seconds > 0, got {feedback_period_s!r}")
        self.action_type = load_action_type()
        self.plane = plane
        self.high = plane.high
        self.node = node
        self.second_goal = second_goal
        self.feedback_period_s = float(feedback_period_s)
        self._lock = threading.Lock()  # the goal slot and the list of goals followed
        self._goal: _Goal | None = None  # the latest goal that switched the robot
        #: Goals not ended yet: the latest, one it preempted while that ends, refused ones
        #: until their result is out.
        self._following: tuple[_Goal, ...] = ()
        self._closed = False
        self._server: ActionServer[Any, Any, Any] = ActionServer(
            node, self.action_type, ACTION_NAME, self._execute,
            goal_callback=self._on_goal_request,
            handle_accepted_callback=self._on_accepted,
            cancel_callback=self._on_cancel)
        self._timer = node.create_timer(_TICK_S, self._tick)
        self._unsubscribe = self.high.subscribe(self._on_event)

    # -- goals (executor thread: goals and cancels are handled one at a time) -----------------
    def _on_goal_request(self, request: Any) -> GoalResponse:
        """Accept every goal while the server runs: a goal that will not run is ABORTED
        with its reason (a goal response has no room for one)."""
        return GoalResponse.REJECT if self._closed else GoalResponse.ACCEPT

    def _on_accepted(self, handle: ServerGoalHandle[Any, Any, Any]) -> None:
        """Check the goal, switch to its behaviour (or refuse it), then let rclpy run
        :meth:`_execute`, which waits for the goal's end."""
        gid = uuid.UUID(bytes=bytes(handle.goal_id.uuid))
        request = handle.request
        name = str(request.behavior)
        goal = _Goal(handle, gid, name, Future(executor=self.node.executor))
        with self._lock:
            self._following = (*self._following, goal)
            closing = self._closed
        try:
            if closing:  # accepted just before destroy() began: nothing is switched
                raise _Refused("the robot's execute_behavior server shuts down")
            self._start(goal, request.params_json)
        except _Refused as refusal:
            self._finish(goal, None, refused=refusal.reason)
        except Exception as exc:  # a bug here must not leave an accepted goal unanswered
            log.exception("execute_behavior: goal %s could not be started", gid)
            self._finish(goal, None, refused=shorten(f"goal refused: {exc!r}"))
        handle.execute()

    def _start(self, goal: _Goal, params_json: str) -> None:
        """Validate ``goal`` and request its switch; :class:`_Refused` says why not."""
        name = goal.name
        params = _parse_params(params_json)
        try:
            checked = self.plane.check_switch(name, params)
        except Exception as exc:  # BeehaveError: the reason; anything else must not crash
            if not isinstance(exc, BeehaveError):
                log.exception("execute_behavior: checking goal %s failed", goal.goal_id)
            raise _Refused(str(exc) if isinstance(exc, BeehaveError)
                           else f"goal refused: {exc!r}") from exc
        with self._lock:
            active = self._goal if self._goal is not None and not self._goal.done else None
        if active is not None and self.second_goal == "reject":
            raise _Refused(
                f"goal {active.goal_id} ({active.name!r}) is executing and this robot's "
                f"policy for a second goal is 'reject' (ros.second_goal: reject | preempt); "
                f"cancel it first")
        if active is not None:
            with active.lock:
                active.preempted_by = goal.goal_id
        try:
            goal.behavior = self.high.request_switch(name, **checked)
        except Exception as exc:  # the constructor raised, or the manager shuts down
            if active is not None:
                with active.lock:
                    active.preempted_by = None
            raise _Refused(str(exc) if isinstance(exc, BeehaveError)
                           else f"goal refused: {exc!r}") from exc
        with self._lock:
            self._goal = goal
        self._check(goal)  # it may have started (or ended) already

    async def _execute(self, handle: ServerGoalHandle[Any, Any, Any]) -> Any:
        """rclpy's execute callback, a coroutine in the executor thread: waits for the
        goal's end without blocking the executor, then sets the terminal status."""
        goal = self._find(handle)
        if goal is None:  # cannot happen: _on_accepted registered it before execute()
            handle.abort()
            return self.action_type.Result(refused=True, message="unknown goal")
        result = await goal.result
        try:
            if goal.outcome == "SUCCEEDED":
                handle.succeed()
            elif goal.outcome == "CANCELED" and handle.is_cancel_requested:
                handle.canceled()
            else:
                handle.abort()
        except Exception as exc:  # an illegal transition must not lose the result
            log.error("execute_behavior: goal %s: setting %s failed: %s",
                      goal.goal_id, goal.outcome, exc)
        goal.sent.set()
        return result

    def _find(self, handle: ServerGoalHandle[Any, Any, Any]) -> _Goal | None:
        return next((g for g in self._following if g.handle is handle), None)

    def _on_cancel(self, handle: ServerGoalHandle[Any, Any, Any]) -> CancelResponse:
        """A cancel of the executing goal is a switch to ``idle``; the goal is CANCELED
        once its behaviour has stopped through its safe states and ``idle`` runs (or a
        later switch overtook that ``idle``)."""
        goal = self._find(handle)
        if goal is None or goal.behavior is None:
            return CancelResponse.REJECT  # ended (a refused goal ends at once)
        with goal.lock:  # before the switch: its end must read as this cancel's
            if goal.done:
                return CancelResponse.REJECT
            first = not goal.cancel_requested
            goal.cancel_requested = True
        with self._lock:
            latest = self._goal is goal
        if not latest:  # preempted, ending already: the cancel just marks it
            return CancelResponse.ACCEPT
        goal.idle_asked = True
        try:
            goal.idle = self.high.request_switch(IDLE, **self.plane.check_switch(IDLE))
        except BeehaveError as exc:
            with goal.lock:
                goal.cancel_requested = not first
            log.error("execute_behavior: cancel of goal %s refused: %s", goal.goal_id, exc)
            return CancelResponse.REJECT
        finally:
            if goal.idle is None:  # not asked after all
                goal.idle_asked = False
        self._check(goal)
        return CancelResponse.ACCEPT

    # -- following the goal's behaviour --------------------------------------------------------
    def _on_event(self, event: Event) -> None:
        """Any lifecycle event of the high level (in the thread that made it): the goal's
        behaviour may have started or ended."""
        if event.kind in (EventKind.STARTED, EventKind.ENDED, EventKind.STUCK,
                          EventKind.SWITCH_COMPLETED):
            for goal in self._following:
                if not goal.done:
                    self._check(goal)

    def _check(self, goal: _Goal) -> None:
        behavior = goal.behavior
        if behavior is not None and behavior.status.finished and self._idle_settled(goal):
            self._finish(goal, behavior.status)

    def _idle_settled(self, goal: _Goal) -> bool:
        """True unless the goal was cancelled and its ``idle`` has not started yet: the
        behaviour ends a moment before the switch starts ``idle``. A later switch that
        overtook the ``idle`` settles it too (seen by _tick)."""
        if not goal.idle_asked:
            return True
        idle = goal.idle  # None: asked for, the request not returned yet
        return idle is not None and (idle.status is not Status.PENDING
                                     or goal.idle_unqueued_ticks >= 2)

    def _tick(self) -> None:
        """Executor thread, every :data:`_TICK_S`: feedback on change and every
        ``feedback_period_s``; a goal whose behaviour never started (another switch
        overtook it while it waited) is aborted."""
        following = self._following
        for item in following:
            self._check(item)
            behavior = item.behavior
            if behavior is not None and behavior.status is Status.PENDING and not item.done:
                # Neither running nor waiting in the manager's queue: it never will. Seen
                # on two ticks in a row, since the manager takes a request off its queue a
                # moment before it shows it as being executed.
                high = self.high
                unqueued = high.top is not behavior and high.requested is None
                item.unqueued_ticks = item.unqueued_ticks + 1 if unqueued else 0
                if item.unqueued_ticks >= 2:
                    self._finish(item, None)
            idle = item.idle
            if idle is not None and idle.status is Status.PENDING and not item.done:
                high = self.high
                unqueued = high.top is not idle and high.requested != IDLE
                item.idle_unqueued_ticks = item.idle_unqueued_ticks + 1 if unqueued else 0
        if any(item.done and item.sent.is_set() for item in following):
            with self._lock:
                self._following = tuple(g for g in self._following
                                        if not (g.done and g.sent.is_set()))
        goal = self._goal
        if goal is None or goal.done or goal.behavior is None:
            return
        behavior = goal.behavior
        if behavior.status is not Status.RUNNING:
            return
        state = self.plane.status()
        state.pop("schema", None)
        state.pop("stamp", None)
        encoded = json.dumps(state, sort_keys=True, allow_nan=False)
        now = time.monotonic()
        if encoded == goal.last_feedback and now - goal.last_feedback_at < self.feedback_period_s:
            return
        goal.last_feedback, goal.last_feedback_at = encoded, now
        feedback = self.action_type.Feedback(
            elapsed_s=_finite(behavior.elapsed_s),
            running_actions=[str(r["path"]) for r in state.get("running", ())
                             if r.get("kind") == "action"],
            state_json=encoded)
        with self._lock:
            if not self._closed:
                goal.handle.publish_feedback(feedback)

    def _finish(self, goal: _Goal, status: Status | None, *, refused: str | None = None,
                why: str | None = None) -> None:
        """The goal's end: ``status`` is its behaviour's final status (None: it never
        ran); ``refused``: the reason it was refused before anything was switched."""
        with goal.lock:
            if goal.done:
                return
            goal.done = True
            cancel, preempted_by = goal.cancel_requested, goal.preempted_by
        behavior = goal.behavior
        result = self.action_type.Result(refused=refused is not None, value_json="null")
        if status is not None and behavior is not None:
            error = behavior.error
            result.behavior_status = status.name
            result.value_json = json.dumps(bounded(to_json(behavior.result)), allow_nan=False)
            result.error = "" if error is None else shorten(f"{error!r}")
            result.elapsed_s = _finite(behavior.elapsed_s)
        outcome: Literal["SUCCEEDED", "CANCELED", "ABORTED"] = "ABORTED"
        if why is not None:
            pass
        elif refused is not None:
            why = refused
        elif status is Status.SUCCEEDED:
            outcome, why = "SUCCEEDED", f"{goal.name!r} succeeded"
        elif cancel and preempted_by is not None:  # cancelled while it made way for another
            outcome, why = "CANCELED", (f"cancelled: {goal.name!r} stopped, preempted by "
                                        f"goal {preempted_by}")
        elif cancel and goal.idle is not None and goal.idle.status is Status.PENDING:
            # Its idle never ran: a switch made elsewhere overtook it, or the robot shuts down.
            asked = self.high.requested or self.high.current
            outcome, why = "CANCELED", (
                f"cancelled: {goal.name!r} stopped; {IDLE!r} was overtaken by a switch to "
                f"{asked!r}" if asked is not None else
                f"cancelled: {goal.name!r} stopped; the robot shuts down")
        elif cancel:
            outcome, why = "CANCELED", f"cancelled: {goal.name!r} stopped, {IDLE!r} runs"
        elif preempted_by is not None:
            why = f"preempted by goal {preempted_by}"
        elif status is None:
            why = (f"{goal.name!r} never started: another switch overtook it (now "
                   f"{self.high.current!r})")
        elif status is Status.FAILED:
            why = f"{goal.name!r} failed: {behavior.error if behavior else None!r}"
        elif status is Status.STUCK:
            why = f"{goal.name!r} went STUCK: it ignored its interrupt for stop_timeout_s"
        else:  # INTERRUPTED by a switch made by other means, or the manager's shutdown
            asked = self.high.requested or self.high.current
            why = (f"{goal.name!r} was interrupted by a switch to {asked!r} made outside "
                   f"this goal" if asked is not None else
                   f"{goal.name!r} was interrupted: the robot shuts down")
        result.message = shorten(why)
        goal.outcome = outcome
        goal.result.set_result(result)

    def destroy(self) -> None:
        """Abort the goals that still execute ("the robot's execute_behavior server shuts
        down"), wait (at most :data:`_RESULT_FLUSH_S`) until their results are handed to
        rclpy and :data:`_RESULT_GRACE_S` more for them to arrive, then remove the action
        server and the timer from the node (the node stays)."""
        self._unsubscribe()
        with self._lock:
            if self._closed:
                return
            # From here on goals are REJECTED: one accepted during the flush below would
            # switch the robot and never get its result.
            self._closed = True
            following = self._following
        for goal in following:
            self._finish(goal, None, why="the robot's execute_behavior server shuts down")
        deadline = time.monotonic() + _RESULT_FLUSH_S
        for goal in following:
            goal.sent.wait(max(0.0, deadline - time.monotonic()))
        # A client's pending result request is answered by a task the executor runs after
        # the goal's own: one more round through the executor before the server goes.
        flushed = threading.Event()
        marker: Future[None] = Future(executor=self.node.executor)
        marker.add_done_callback(lambda _: flushed.set())
        marker.set_result(None)
        flushed.wait(max(0.0, deadline - time.monotonic()))
        if following:
            time.sleep(_RESULT_GRACE_S)
        self.node.destroy_timer(self._timer)
        self._server.destroy()


class _Refused(Exception):
    """A goal that will not run; ``reason`` names the problem and the valid choices."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = shorten(reason)


def _parse_params(text: str) -> Any:
    """The goal's ``params_json``: "" means none; otherwise strict JSON (no NaN)."""
    if not text.strip():
        return None
    if len(text) > MAX_PARAMS_CHARS:
        raise _Refused(f"params_json refused: {len(text)} characters, more than "
                       f"{MAX_PARAMS_CHARS}")

    def no_constant(word: str) -> Any:
        raise ValueError(f"{word} is not JSON")

    try:
        return json.loads(text, parse_constant=no_constant)
    except ValueError as exc:
        raise _Refused(f"params_json is not a JSON object: {exc}; expected e.g. "
                       f"'{{\"speed_mps\": 0.3}}' or \"\" for none") from exc
    except RecursionError as exc:  # '[[[[…' within the size limit: deeper than Python goes
        raise _Refused("params_json refused: nested too deeply to parse; expected a flat "
                       "object of parameters, e.g. '{\"speed_mps\": 0.3}'") from exc


def _finite(value: float | None) -> float:
    return float(value) if value is not None and math.isfinite(value) else 0.0


__all__ = ["ACTION_NAME", "SECOND_GOAL_POLICIES", "ExecuteBehaviorServer",
           "InterfacesMissing", "SecondGoal", "load_action_type"]
