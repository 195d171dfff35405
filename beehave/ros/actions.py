"""Ready-made Actions for ROS 2 interfaces: send a goal to an action server
(:class:`RosActionGoal`) and call a service (:class:`ServiceCall`).

They are ordinary :class:`~beehave.Action` s — type locks, interrupts, safe states and
STUCK reports apply — so a behaviour starts them like any other::

    class NavigateTo(RosActionGoal):
        action_type = "driving"          # the lock domain: one driver at a time

    class Deliver(Behavior):
        def run(self) -> None:
            nav = self.start_action(NavigateTo(
                NavigateToPose, "navigate_to_pose", NavigateToPose.Goal(pose=shelf),
                on_feedback=self.show_progress, timeout_s=120.0))
            nav.wait()                   # nav.result: the action's Result message

Subclass to give each use its own ``action_type`` (by default all goals of this class
share one lock named after the class). Names are relative to the robot's namespace.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from beehave.action import Action
from beehave.ros.io import Goal
from beehave.ros.io import check_duration as _duration


class RosActionGoal(Action):
    """Send one goal to a ROS 2 action server and wait for its result.

    - ``result``: the action's ``Result`` message when the server reports SUCCEEDED.
    - FAILED with :class:`~beehave.errors.GoalFailed` when the server rejects the goal
      (``status="REJECTED"``), aborts it (``"ABORTED"``; ``error.result`` holds what it
      sent) or reports it cancelled by someone else (``"CANCELED"``); with
      :class:`~beehave.ros.io.WaitTimeout` when the server is not there within
      ``server_timeout_s`` or the goal does not finish within ``timeout_s`` (the goal is
      cancelled first).
    - Interrupted (a switch, a preempting action): the goal is cancelled — its safe state —
      waiting at most ``cancel_timeout_s`` (wall time, part of the switch's
      ``stop_timeout_s``) for the server to end it.
    - ``on_feedback(feedback)`` runs in the ROS executor thread for every feedback message:
      keep it short. If it raises, the goal is cancelled and the action FAILS with that
      error. ``.feedback`` always holds the newest feedback (None before the first);
      ``.goal`` the :class:`~beehave.ros.io.Goal` once accepted.

    Timeouts follow the manager's clock (sim time with ``use_sim_time``).
    """

    def __init__(self, action: type, name: str, goal: Any, *,
                 on_feedback: Callable[[Any], None] | None = None,
                 timeout_s: float | None = None, server_timeout_s: float = 5.0,
                 cancel_timeout_s: float = 0.5) -> None:
        owner = type(self).__name__
        _duration(owner, "timeout_s", timeout_s, optional=True)
        _duration(owner, "server_timeout_s", server_timeout_s)
        _duration(owner, "cancel_timeout_s", cancel_timeout_s)
        self.action = action
        self.action_name = name
        self.request = goal
        self.on_feedback = on_feedback
        self.timeout_s = timeout_s
        self.server_timeout_s = server_timeout_s
        self.cancel_timeout_s = cancel_timeout_s
        self.goal: Goal | None = None

    @property
    def feedback(self) -> Any:
        """The newest feedback message, or None."""
        return None if self.goal is None else self.goal.feedback

    def run(self) -> Any:
        self.goal = self.ros.send_goal(self.action, self.action_name, self.request,
                                       feedback=self.on_feedback,
                                       server_timeout_s=self.server_timeout_s)
        return self.goal.wait(timeout_s=self.timeout_s, cancel_timeout_s=self.cancel_timeout_s)

    def safe_state(self) -> None:
        """Cancel the goal if it still runs (``wait`` has usually done so already),
        waiting for the server at most ``cancel_timeout_s`` since the cancel was asked for
        — once in all, not once in ``wait`` and again here (that made a slow-to-stop
        server's goal outlast ``stop_timeout_s``: the action was reported STUCK)."""
        goal = self.goal
        if goal is None or goal.done:
            return
        asked = goal.cancel_requested_at
        left_s = (self.cancel_timeout_s if asked is None
                  else self.cancel_timeout_s - (time.monotonic() - asked))
        goal.cancel(timeout_s=max(0.0, left_s))


class ServiceCall(Action):
    """Call a ROS 2 service once; the response is the result.

    FAILED with :class:`~beehave.ros.io.WaitTimeout` when the service is not available or
    does not answer within ``timeout_s`` (the manager's clock); interrupted at once by a
    switch (the pending call is dropped — a service call cannot be cancelled on the
    server). Subclass to give it an ``action_type`` of its own.
    """

    def __init__(self, service: type, name: str, request: Any, *,
                 timeout_s: float = 5.0) -> None:
        _duration(type(self).__name__, "timeout_s", timeout_s)
        self.service = service
        self.service_name = name
        self.request = request
        self.timeout_s = timeout_s

    def run(self) -> Any:
        return self.ros.call(self.service, self.service_name, self.request,
                             timeout_s=self.timeout_s)


__all__ = ["RosActionGoal", "ServiceCall"]
