"""``beehave/execute_behavior``: run a top-level behaviour as a goal, from any ROS 2 program.

A goal names a behaviour and its parameters; the robot switches to it, sends feedback
while it runs (the engine's state, the running actions) and a result when it ends; a cancel
switches to ``idle``. What happens to a second goal while one runs is the robot's policy
(``ros.second_goal`` in its YAML): ``reject`` it, or ``preempt`` the running one.

Why not a ROS 2 action type. beehave keeps to standard message types, and no action type
that the ROS 2 wheels on PyPI ship (``test_msgs`` has the only ones: ``Fibonacci``,
``NestedMessage``) can carry a behaviour's name, let alone its parameters;
``example_interfaces``, ``action_tutorials_interfaces`` and ``nav2_msgs`` are not on PyPI.
So the action's parts travel as they would in a ROS 2 action, with the goal, feedback and
result as JSON in ``std_msgs/String`` (as the other beehave topics) and the cancel as the
standard ``action_msgs/srv/CancelGoal``. Names are relative to the robot's namespace:

==================================  ========================  ==============================
``beehave/execute_behavior/goal``     topic, client → robot     std_msgs/String, JSON goal
``beehave/execute_behavior/status``   topic, robot → clients    std_msgs/String, JSON status
``beehave/execute_behavior/feedback`` topic, robot → clients    std_msgs/String, JSON feedback
``beehave/execute_behavior/cancel``   service                   action_msgs/srv/CancelGoal
==================================  ========================  ==============================

Goal (``goal_id``: a UUID the client makes, as a ROS 2 action client does)::

    {"schema": "beehave/execute_behavior/goal/1", "goal_id": "5f0c…", "behavior": "patrol",
     "params": {"speed_mps": 0.3}}

Status — every change of a goal's status, the result with the terminal one (reliable,
transient-local, the last :data:`STATUS_DEPTH` kept)::

    {"schema": "beehave/execute_behavior/status/1", "goal_id": "5f0c…", "behavior": "patrol",
     "status": "ACCEPTED" | "REJECTED" | "EXECUTING" | "CANCELING"
               | "SUCCEEDED" | "CANCELED" | "ABORTED",
     "message": "why (a rejection names the valid choices)", "stamp": 1795240691.7,
     "result": null | {"status": "SUCCEEDED" | "FAILED" | "INTERRUPTED" | "STUCK",
                       "value": <the behaviour's return value, JSON>, "error": null | "…",
                       "elapsed_s": 12.5}}

Feedback — while a goal executes, on every change of what runs and every
``feedback_period_s``::

    {"schema": "beehave/execute_behavior/feedback/1", "goal_id": "5f0c…",
     "behavior": "patrol", "elapsed_s": 3.2,
     "state": {"behavior", "logic", "running", "engines", "locks", "stuck"}}

``state`` is the ``beehave/high_level/state`` message's content (see ``docs/ros.md``).
Everything is validated by the control-plane core (:meth:`ControlPlane.check_switch`), so a
goal is accepted or refused exactly as a switch over HTTP or VDA 5050 would be.
"""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Literal

from action_msgs.msg import GoalInfo
from action_msgs.srv import CancelGoal
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from beehave.behavior import Behavior
from beehave.blackboard import to_json
from beehave.errors import BeehaveError, ConfigError
from beehave.events import Event, EventKind
from beehave.highlevel import IDLE
from beehave.interfaces.core import ControlPlane, bounded, shorten
from beehave.status import Status

log = logging.getLogger(__name__)

GOAL_TOPIC = "beehave/execute_behavior/goal"
STATUS_TOPIC = "beehave/execute_behavior/status"
FEEDBACK_TOPIC = "beehave/execute_behavior/feedback"
CANCEL_SERVICE = "beehave/execute_behavior/cancel"
GOAL_SCHEMA = "beehave/execute_behavior/goal/1"
STATUS_SCHEMA = "beehave/execute_behavior/status/1"
FEEDBACK_SCHEMA = "beehave/execute_behavior/feedback/1"

#: What to do with a goal that arrives while another one executes.
SecondGoal = Literal["reject", "preempt"]
SECOND_GOAL_POLICIES: tuple[str, ...] = ("reject", "preempt")

#: Status messages kept for late joiners (a client that subscribed a moment after its goal).
STATUS_DEPTH = 20
STATUS_QOS = QoSProfile(depth=STATUS_DEPTH, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: A goal message larger than this is refused unread (an outsider must not make the robot
#: parse megabytes).
MAX_GOAL_BYTES = 64 * 1024
#: How often the running goal is looked at (feedback on change, a request that never ran).
_TICK_S = 0.1


class GoalMessage(BaseModel):
    """``beehave/execute_behavior/goal`` (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)
    schema_: Literal["beehave/execute_behavior/goal/1"] = Field(alias="schema")
    goal_id: uuid.UUID
    behavior: Any  # checked by the control plane, whose message lists the behaviours
    params: Any = None


@dataclass(eq=False)
class _Goal:
    goal_id: uuid.UUID
    name: str
    behavior: Behavior
    accepted_at: float = field(default_factory=time.monotonic)
    lock: threading.Lock = field(default_factory=threading.Lock)
    executing: bool = False
    done: bool = False
    cancel_requested: bool = False
    preempted_by: uuid.UUID | None = None
    #: Ticks on which the behaviour was seen neither running nor queued (see _tick).
    unqueued_ticks: int = 0
    last_feedback: str | None = None
    last_feedback_at: float = 0.0


class ExecuteBehaviorServer:
    """Serves ``beehave/execute_behavior`` for one robot on its high-level ``node``.

    ``plane``: the robot's control plane (validation, state); ``second_goal``: ``"reject"``
    (a goal that arrives while one executes is refused, naming the running one) or
    ``"preempt"`` (the running goal is ABORTED with "preempted by goal …" and the new one
    runs; the switch replaces one behaviour by the other as any switch does);
    ``feedback_period_s``: the feedback heartbeat (feedback also goes out at once when
    what runs changes). At most one goal executes at a time: the robot runs one top-level
    behaviour.

    A switch made by other means (the ``behavior`` parameter, ``beehave/stop``, HTTP, VDA
    5050) while a goal executes ends that goal: ABORTED, the message names the switch. A
    behaviour that ends on its own ends its goal: SUCCEEDED when its ``run`` returned (its
    return value is the result's ``value``), ABORTED when it failed or went STUCK.
    :meth:`destroy` aborts a goal that still executes and removes what it added to the node.
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
        self.plane = plane
        self.high = plane.high
        self.node = node
        self.second_goal = second_goal
        self.feedback_period_s = float(feedback_period_s)
        self._lock = threading.Lock()  # the goal slot and publishing vs. destroy()
        self._goal: _Goal | None = None  # the latest accepted goal
        #: Accepted goals not ended yet: the latest, and one it preempted while that ends.
        self._following: tuple[_Goal, ...] = ()
        self._closed = False
        self._status_pub = node.create_publisher(String, STATUS_TOPIC, STATUS_QOS)
        self._feedback_pub = node.create_publisher(String, FEEDBACK_TOPIC, 10)
        self._goal_sub = node.create_subscription(String, GOAL_TOPIC, self._on_goal, 10)
        self._cancel_srv = node.create_service(CancelGoal, CANCEL_SERVICE, self._on_cancel)
        self._timer = node.create_timer(_TICK_S, self._tick)
        self._unsubscribe = self.high.subscribe(self._on_event)

    # -- goals -------------------------------------------------------------------------------
    def _on_goal(self, msg: String) -> None:
        """A goal arrives (executor thread: goals and cancels are handled one at a time)."""
        if len(msg.data) > MAX_GOAL_BYTES:
            self._publish_status(None, None, "REJECTED",
                                 f"goal refused: {len(msg.data)} characters, more than "
                                 f"{MAX_GOAL_BYTES}")
            return
        try:
            goal = GoalMessage.model_validate_json(msg.data)
        except ValidationError as exc:
            raw_id = _raw_goal_id(msg.data)
            problems = "; ".join(
                f"{'.'.join(str(p) for p in e['loc']) or '<top>'}: {e['msg']}"
                for e in exc.errors())
            self._publish_status(raw_id, None, "REJECTED", shorten(
                f"malformed goal refused: {problems}; expected {{\"schema\": "
                f"\"{GOAL_SCHEMA}\", \"goal_id\": <UUID>, \"behavior\": <name>, "
                f"\"params\": {{…}}}}"))
            return
        gid = goal.goal_id
        name = goal.behavior
        with self._lock:
            if self._closed:
                return
            active = self._goal if self._goal is not None and not self._goal.done else None
        if active is not None and active.goal_id == gid:
            self._publish_status(gid, name, "REJECTED",
                                 f"goal {gid} is already executing ({active.name!r})")
            return
        try:
            params = self.plane.check_switch(name, goal.params)
        except Exception as exc:  # BeehaveError: the reason; anything else must not crash
            if not isinstance(exc, BeehaveError):
                log.exception("execute_behavior: checking goal %s failed", gid)
            self._publish_status(gid, name if isinstance(name, str) else None, "REJECTED",
                                 shorten(str(exc) if isinstance(exc, BeehaveError)
                                         else f"goal refused: {exc!r}"))
            return
        if active is not None and self.second_goal == "reject":
            self._publish_status(gid, name, "REJECTED", (
                f"goal {active.goal_id} ({active.name!r}) is executing and this robot's "
                f"policy for a second goal is 'reject' (ros.second_goal: reject | "
                f"preempt); cancel it first"))
            return
        if active is not None:
            with active.lock:
                active.preempted_by = gid
        try:
            behavior = self.high.request_switch(name, **params)
        except Exception as exc:  # the constructor raised, or the manager shuts down
            if active is not None:
                with active.lock:
                    active.preempted_by = None
            self._publish_status(gid, name, "REJECTED", shorten(
                str(exc) if isinstance(exc, BeehaveError) else f"goal refused: {exc!r}"))
            return
        new = _Goal(gid, name, behavior)
        with self._lock:
            self._goal = new
            self._following = (*self._following, new)
        self._publish_status(gid, name, "ACCEPTED", (
            f"switching to {name!r}" + (f"; preempts goal {active.goal_id}"
                                        if active is not None else "")))
        self._check(new)  # it may have started (or ended) already

    def _on_cancel(self, request: CancelGoal.Request,
                   response: CancelGoal.Response) -> CancelGoal.Response:
        """Cancel the executing goal: a switch to ``idle``. As in ROS 2 actions, a zero
        goal id (with a zero stamp) means every goal."""
        info = request.goal_info
        wanted = uuid.UUID(bytes=bytes(info.goal_id.uuid))
        every = wanted.int == 0
        with self._lock:
            goal = self._goal
        if goal is None or goal.done or (not every and goal.goal_id != wanted):
            if goal is not None and goal.goal_id == wanted:
                response.return_code = CancelGoal.Response.ERROR_GOAL_TERMINATED
            elif every:
                response.return_code = CancelGoal.Response.ERROR_NONE  # nothing to cancel
            else:
                response.return_code = CancelGoal.Response.ERROR_UNKNOWN_GOAL_ID
            return response
        with goal.lock:  # before the switch: its end must read as this cancel's
            first = not goal.cancel_requested and not goal.done
            goal.cancel_requested = True
        try:
            self.plane.stop()
        except BeehaveError as exc:
            with goal.lock:
                goal.cancel_requested = not first
            log.error("execute_behavior: cancel of goal %s refused: %s", goal.goal_id, exc)
            response.return_code = CancelGoal.Response.ERROR_REJECTED
            return response
        if first:
            self._publish_status(goal.goal_id, goal.name, "CANCELING",
                                 f"switching to {IDLE!r}")
        stamp = GoalInfo()
        stamp.goal_id.uuid = list(goal.goal_id.bytes)
        stamp.stamp = self.node.get_clock().now().to_msg()
        response.goals_canceling = [stamp]
        response.return_code = CancelGoal.Response.ERROR_NONE
        self._check(goal)
        return response

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
        status = goal.behavior.status
        if status.finished:
            self._finish(goal, status)
        elif status is Status.RUNNING:
            with goal.lock:
                first = not goal.executing and not goal.done
                goal.executing = True
            if first:
                self._publish_status(goal.goal_id, goal.name, "EXECUTING",
                                     f"{goal.name!r} runs")

    def _tick(self) -> None:
        """Executor thread, every :data:`_TICK_S`: feedback on change and every
        ``feedback_period_s``; a goal whose behaviour never started (another switch
        overtook it while it waited) is aborted."""
        following = self._following
        for item in following:
            self._check(item)
            if item.behavior.status is Status.PENDING and not item.done:
                # Neither running nor waiting in the manager's queue: it never will. Seen
                # on two ticks in a row, since the manager takes a request off its queue a
                # moment before it shows it as being executed.
                high = self.high
                unqueued = high.top is not item.behavior and high.requested is None
                item.unqueued_ticks = item.unqueued_ticks + 1 if unqueued else 0
                if item.unqueued_ticks >= 2:
                    self._finish(item, None)
        if any(item.done for item in following):
            with self._lock:
                self._following = tuple(g for g in self._following if not g.done)
        goal = self._goal
        if goal is None or goal.done:
            return
        behavior = goal.behavior
        if behavior.status is not Status.RUNNING:
            return
        state = self.plane.status()
        state.pop("schema", None)
        state.pop("stamp", None)
        encoded = json.dumps(state, sort_keys=True)
        now = time.monotonic()
        if encoded == goal.last_feedback and now - goal.last_feedback_at < self.feedback_period_s:
            return
        goal.last_feedback, goal.last_feedback_at = encoded, now
        self._publish(self._feedback_pub, {
            "schema": FEEDBACK_SCHEMA, "goal_id": str(goal.goal_id), "behavior": goal.name,
            "elapsed_s": behavior.elapsed_s, "state": state})

    def _finish(self, goal: _Goal, status: Status | None) -> None:
        """The goal's end: ``status`` is its behaviour's final status (None: it never ran)."""
        with goal.lock:
            if goal.done:
                return
            goal.done = True
            cancel, preempted_by = goal.cancel_requested, goal.preempted_by
        behavior = goal.behavior
        result: dict[str, Any] | None = None
        if status is not None:
            error = behavior.error
            result = {"status": status.name, "value": bounded(to_json(behavior.result)),
                      "error": None if error is None else shorten(f"{error!r}"),
                      "elapsed_s": behavior.elapsed_s}
        if status is Status.SUCCEEDED:
            outcome, why = "SUCCEEDED", f"{goal.name!r} succeeded"
        elif cancel:
            outcome, why = "CANCELED", f"cancelled: {goal.name!r} stopped, {IDLE!r} runs"
        elif preempted_by is not None:
            outcome, why = "ABORTED", f"preempted by goal {preempted_by}"
        elif status is None:
            outcome, why = "ABORTED", (f"{goal.name!r} never started: another switch "
                                       f"overtook it (now {self.high.current!r})")
        elif status is Status.FAILED:
            outcome, why = "ABORTED", f"{goal.name!r} failed: {behavior.error!r}"
        elif status is Status.STUCK:
            outcome, why = "ABORTED", (f"{goal.name!r} went STUCK: it ignored its interrupt "
                                       f"for stop_timeout_s")
        else:  # INTERRUPTED by a switch made by other means, or the manager's shutdown
            asked = self.high.requested or self.high.current
            outcome, why = "ABORTED", (f"{goal.name!r} was interrupted by a switch to "
                                       f"{asked!r} made outside this goal"
                                       if asked is not None else
                                       f"{goal.name!r} was interrupted: the robot shuts down")
        self._publish_status(goal.goal_id, goal.name, outcome, shorten(why), result)

    # -- output ------------------------------------------------------------------------------
    def _publish_status(self, goal_id: uuid.UUID | str | None, name: str | None, status: str,
                        message: str, result: dict[str, Any] | None = None) -> None:
        self._publish(self._status_pub, {
            "schema": STATUS_SCHEMA, "goal_id": None if goal_id is None else str(goal_id),
            "behavior": name, "status": status, "message": message, "stamp": time.time(),
            "result": result})

    def _publish(self, publisher: Any, data: dict[str, Any]) -> None:
        text = json.dumps(data, allow_nan=False)
        with self._lock:
            if self._closed:
                return
            publisher.publish(String(data=text))

    def destroy(self) -> None:
        """Abort a goal that still executes ("the server shuts down") and remove the
        topics, the service and the timer from the node (the node stays)."""
        self._unsubscribe()
        for goal in self._following:
            with goal.lock:
                first = not goal.done
                goal.done = True
            if first:
                self._publish_status(goal.goal_id, goal.name, "ABORTED",
                                     "the robot's execute_behavior server shuts down")
        with self._lock:
            self._closed = True
        node = self.node
        node.destroy_timer(self._timer)
        node.destroy_service(self._cancel_srv)
        node.destroy_subscription(self._goal_sub)
        node.destroy_publisher(self._feedback_pub)
        node.destroy_publisher(self._status_pub)


def _raw_goal_id(data: str) -> str | None:
    """The ``goal_id`` of a goal refused as malformed, if it has one, so its client learns
    why (anything but a short string is not echoed)."""
    try:
        raw = json.loads(data)
    except ValueError:
        return None
    gid = raw.get("goal_id") if isinstance(raw, dict) else None
    return gid if isinstance(gid, str) and len(gid) <= 64 else None


__all__ = ["CANCEL_SERVICE", "FEEDBACK_TOPIC", "GOAL_TOPIC", "SECOND_GOAL_POLICIES",
           "STATUS_TOPIC", "ExecuteBehaviorServer", "GoalMessage", "SecondGoal"]
