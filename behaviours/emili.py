"""EMILI's behaviours, reproducing the paper's evaluation.

- :class:`Tour` drives to several stations; while it drives, a sub-behaviour (:class:`Chime`)
  plays a sound in parallel; at each station the lift goes up and down.
- :class:`Commanded` takes position orders from another agent — any process publishing on
  ``orders`` — and reports its progress on ``orders/progress``.
- :class:`Maintenance` parks the robot: lift down, a sound, nothing moves.

Switch between them at runtime (``behavior`` parameter, ``hl.switch``): the running one is
interrupted, its actions reach their safe states, then the next starts.
"""

from __future__ import annotations

import json
import queue
from typing import Any

from std_msgs.msg import String

from beehave import Behavior, Status
from behaviours.actions import (
    Goal,
    Lift,
    Navigation,
    NavigationError,
    PlaySound,
    lockstep_sleeps,
    resolve_goal,
)


class Chime(Behavior):
    """Plays ``sound`` every ``interval_s`` until interrupted (runs beside the driving)."""

    def __init__(self, sound: str = "chime", interval_s: float = 2.0) -> None:
        self.sound, self.interval_s = sound, interval_s

    def run(self) -> int:
        played = 0
        # In lockstep with a simulation: each sound comes on time in sim time, also when
        # a loaded host starves this thread (and a replay then agrees with the recording).
        with lockstep_sleeps(self) as sleep:
            while not self.interrupted:
                self.start_action(PlaySound(self.sound)).wait()
                played += 1
                sleep(self.interval_s)
        return played


class Tour(Behavior):
    """Visit ``stops`` (station names of ``world``) in order, ``rounds`` times, along paths
    planned on the world's map; lift to ``lift_m`` and back down at each. Returns the
    stations visited."""

    logic = "emili"

    def __init__(self, stops: list[str], *, world: str = "warehouse", rounds: int = 1,
                 lift_m: float = 0.2, speed_mps: float = 0.6) -> None:
        self.goals = [resolve_goal(s, world) for s in stops]  # unknown stations fail now
        self.world = world
        self.rounds, self.lift_m, self.speed_mps = rounds, lift_m, speed_mps
        self.visited: list[str] = []
        self.lift_heights: list[float] = []

    def run(self) -> list[str]:
        for _ in range(self.rounds):
            for goal in self.goals:
                self.visit(goal)
                if self.interrupted:
                    return self.visited
        return self.visited

    def visit(self, goal: Goal) -> None:
        chime = self.start_behavior(Chime())
        nav = self.start_action(Navigation(goal, world=self.world, speed_mps=self.speed_mps))
        nav.wait()
        chime.interrupt()
        chime.wait()
        if nav.status is not Status.SUCCEEDED:
            if self.interrupted:
                return
            raise NavigationError(f"could not reach {goal.name}: {nav.error!r}")
        up = self.start_action(Lift(self.lift_m))
        up.wait()
        if up.status is Status.SUCCEEDED:
            self.lift_heights.append(float(up.result))
        self.start_action(Lift(0.0)).wait()
        self.visited.append(goal.name)


class Commanded(Behavior):
    """Drive to the positions other agents order on ``orders`` (std_msgs/String, JSON)::

        {"id": "o1", "goal": [12.0, 3.5]}        or        {"id": "o2", "station": "emili_pickup"}

    Progress goes out on ``orders/progress`` (std_msgs/String, JSON)::

        {"id": "o1", "status": "accepted" | "reached" | "failed" | "rejected",
         "detail": "...", "x_m": ..., "y_m": ...}

    A malformed order is answered ``rejected`` with the reason; orders are served in turn,
    each along a path planned on ``world``'s map (a goal no path reaches is ``failed``,
    saying why).
    """

    logic = "emili"

    def __init__(self, *, world: str = "warehouse", speed_mps: float = 0.6) -> None:
        self.world, self.speed_mps = world, speed_mps
        self.reached: list[str] = []
        self._orders: queue.SimpleQueue[String] = queue.SimpleQueue()

    def run(self) -> None:
        self.progress = self.ros.publisher(String, "orders/progress")
        self.ros.subscription(String, "orders", self._orders.put)
        while not self.interrupted:
            try:  # polled on the behaviour's clock (sim time, a replay's), not on wall time
                msg = self._orders.get_nowait()
            except queue.Empty:
                self.sleep(0.05)
                continue
            self.serve(msg.data)

    def report(self, order_id: str, status: str, detail: str = "", **extra: Any) -> None:
        self.progress.publish(String(data=json.dumps(
            {"id": order_id, "status": status, "detail": detail, **extra})))

    def serve(self, text: str) -> None:
        order_id = ""
        try:
            order = json.loads(text)
            if not isinstance(order, dict):
                raise ValueError("an order is a JSON object")
            order_id = str(order.get("id", ""))
            if "goal" in order:
                goal = resolve_goal(tuple(order["goal"]), None)
            elif "station" in order:
                goal = resolve_goal(str(order["station"]), self.world)
            else:
                raise ValueError('an order needs "goal": [x_m, y_m] or "station": name')
        except Exception as exc:  # answered, never dropped
            self.report(order_id, "rejected", f"{exc}")
            return
        self.report(order_id, "accepted", goal.name or f"({goal.x_m}, {goal.y_m})")
        try:
            nav = self.start_action(Navigation(goal, world=self.world,
                                               speed_mps=self.speed_mps))
        except Exception as exc:  # busy "driving" type, or we are being stopped
            self.report(order_id, "failed", f"{exc}")
            raise
        nav.wait()
        if nav.status is Status.SUCCEEDED:
            x, y = nav.result
            self.reached.append(order_id)
            self.report(order_id, "reached", x_m=round(x, 3), y_m=round(y, 3))
        else:
            self.report(order_id, "failed", f"{nav.status.name}: {nav.error!r}")


class Maintenance(Behavior):
    """Park: lift down, one sound, then nothing moves until switched away."""

    logic = "emili_maintenance"

    def run(self) -> None:
        self.start_action(Lift(0.0)).wait()
        self.start_action(PlaySound("maintenance")).wait()
        while self.sleep(1.0):
            pass
