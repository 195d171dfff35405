"""Brokers that bid the time a role takes a mobile robot: the drive there, planned on the
floor map around the obstacles inflated by the robot's radius, after the roles it has
queued, plus handling time — refusing when the battery or the deadline would not allow it.
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
    """Bids seconds: ``(metres along the planned path) / speed_mps + handling_s`` for each
    role ahead of this one (the queue) and for this one, starting from where the robot
    stands. Refuses without odometry or a battery reading, beyond ``max_queue`` roles,
    without a path, when the battery would fall below ``reserve_pct``, and when it would
    miss the task's deadline.

    Where a role happens: ``role.params["at"]`` (or ``"meeting_point"``), else the task's
    ``route`` (driven end to end) or ``location``. Subclass it, set ``capabilities`` and
    write :meth:`~beehave.agents.market.Broker.perform_role`."""

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

    def cost(self, job: Job, queue: list[Job]) -> float | str | None:
        pose = self.pose()
        if pose is None:
            return "no odometry yet"  # no honest bid without it
        if len(queue) >= self.max_queue:
            return f"{len(queue)} roles queued already (at most {self.max_queue})"
        metres, at = 0.0, pose
        for role in [*queue, job]:
            for stop in self.stops(role):
                try:
                    metres += self.planner.plan(at, stop).length_m
                except NoPath as exc:
                    return f"no path from {at} to {stop}: {exc}"
                at = stop
        eta_s = metres / self.speed_mps + self.handling_s * (len(queue) + 1)
        if not math.isfinite(eta_s):
            return "no finite time to get there"
        battery = self.battery_pct()
        if battery is None:
            return "no battery reading"
        need_pct = 100.0 * eta_s * self.power_w / 3600.0 / self.capacity_wh
        if battery - need_pct < self.reserve_pct:
            return (f"battery {battery:.0f} % would fall to {battery - need_pct:.0f} %, "
                    f"below the reserve of {self.reserve_pct:g} %")
        if job.task.deadline is not None and time.time() + eta_s > job.task.deadline:
            return f"would miss the deadline by {time.time() + eta_s - job.task.deadline:.0f} s"
        return round(eta_s, 3)
