"""Brokers that bid the time a role takes a mobile robot: the drive there, planned on the
floor map around the obstacles inflated by the robot's radius, plus handling time, as the
marginal sum of completion times of its queue — refusing when the battery or a deadline
would not allow it.
"""

from __future__ import annotations

import math
import time
from typing import Any

from beehave.agents.market import Broker, Job
from beehave.errors import NoPath
from beehave.planning import GridPlanner

Point = tuple[float, float]


class TravelBroker(Broker):
    """Bids seconds, as the market's :meth:`~beehave.agents.market.Broker.queue_cost`: the
    sum of the completion times of its roles, each ``(drive along the planned path) +
    handling_s`` after the roles ahead of it, starting from where the robot stands. So a
    bid is the marginal cost of the cheapest place for the new role after the role that
    runs (its own completion time *and* the delay it puts on the roles behind it), and an
    awarded role takes that place.

    An order is not feasible (the bid names why) without odometry or a battery reading,
    beyond ``max_queue`` roles, without a path, when the battery would fall below
    ``reserve_pct``, and when a role of it would miss its task's deadline.

    Where a role happens: ``role.params["at"]`` (or ``"meeting_point"``), else the task's
    ``route`` (driven end to end) or ``location``. How long a leg takes is
    :meth:`leg_s` (a subclass adds speed limits and waits for reserved zones). Subclass
    it, set ``capabilities`` and write
    :meth:`~beehave.agents.market.Broker.perform_role`."""

    pose_keys: tuple[str, str] = ("odom/x_m", "odom/y_m")
    battery_key: str = "battery/percentage"

    def __init__(self, planner: GridPlanner, *, speed_mps: float = 0.4,
                 handling_s: float = 5.0, power_w: float = 10.0, capacity_wh: float = 32.6,
                 reserve_pct: float = 20.0, max_queue: int = 2) -> None:
        self.planner = planner  # built once: planning is the bid's whole cost
        self.speed_mps = speed_mps
        self.handling_s = handling_s
        self.power_w = power_w
        self.capacity_wh = capacity_wh
        self.reserve_pct = reserve_pct
        self.max_queue = max_queue

    def pose(self) -> Point | None:
        """Optional hook: where the robot is (default: the blackboard's odometry)."""
        x, y = (self.blackboard.get(k) for k in self.pose_keys)
        return (float(x), float(y)) if isinstance(x, (int, float)) \
            and isinstance(y, (int, float)) else None

    def battery_pct(self) -> float | None:
        """Optional hook: the battery charge in % (default: the blackboard's)."""
        value = self.blackboard.get(self.battery_key)
        return float(value) if isinstance(value, (int, float)) else None

    def stops(self, job: Job) -> list[Point]:
        """The points a role drives to, in order (a subclass may ask its own state)."""
        params: dict[str, Any] = job.role.params
        at = params.get("at", params.get("meeting_point"))
        if at is not None:
            return [(float(at[0]), float(at[1]))]
        if job.task.route:
            return list(job.task.route)
        return [job.task.location] if job.task.location is not None else []

    def leg_s(self, start: Point, stop: Point, *, at_s: float) -> float:
        """Optional hook: seconds from ``start`` to ``stop`` for a leg that begins
        ``at_s`` seconds from now (default: the planned path at ``speed_mps``). Raises
        :class:`~beehave.errors.NoPath`."""
        return self.planner.plan(start, stop).length_m / self.speed_mps

    def schedule(self, jobs: list[Job]) -> list[float] | str:
        """The completion time of each role of ``jobs`` done in this order (seconds from
        now), or why this order is not feasible."""
        pose = self.pose()
        if pose is None:
            return "no odometry yet"  # no honest bid without it
        if len(jobs) > self.max_queue:
            return f"{len(jobs) - 1} roles queued already (at most {self.max_queue})"
        done: list[float] = []
        t_s, at = 0.0, pose
        for role in jobs:
            for stop in self.stops(role):
                try:
                    t_s += self.leg_s(at, stop, at_s=t_s)
                except NoPath as exc:
                    return f"no path from {at} to {stop}: {exc}"
                at = stop
            t_s += self.handling_s
            if not math.isfinite(t_s):
                return "no finite time to get there"
            if role.task.deadline is not None and time.time() + t_s > role.task.deadline:
                return (f"would miss the deadline of {role.task.id}/{role.role.name} by "
                        f"{time.time() + t_s - role.task.deadline:.0f} s")
            done.append(t_s)
        battery = self.battery_pct()
        if battery is None:
            return "no battery reading"
        need_pct = 100.0 * (done[-1] if done else 0.0) * self.power_w / 3600.0 \
            / self.capacity_wh
        if battery - need_pct < self.reserve_pct:
            return (f"battery {battery:.0f} % would fall to {battery - need_pct:.0f} %, "
                    f"below the reserve of {self.reserve_pct:g} %")
        return done

    def queue_cost(self, queue: list[Job]) -> float | str | None:
        """The sum of the roles' completion times (seconds): what every order waits."""
        done = self.schedule(queue)
        return done if isinstance(done, str) else round(sum(done), 3)

    def cost(self, job: Job, queue: list[Job]) -> float | str | None:
        """The completion time of ``job`` done after ``queue`` (seconds from now). Not the
        bid (that is the marginal :meth:`queue_cost` of the cheapest place): what an
        operator reads as "when would it be done at the end of the queue"."""
        done = self.schedule([*queue, job])
        return done if isinstance(done, str) else round(done[-1], 3)
