"""Behaviours, actions and logics for the ROS 2 tests (importable by `beehave run`)."""

from __future__ import annotations

from typing import Any

from geometry_msgs.msg import Twist
from std_msgs.msg import String

from beehave import Action, Behavior, Logic


class Cruise(Action):
    """Publishes a forward velocity on cmd_vel until interrupted; zero in its safe state."""

    action_type = "driving"

    def __init__(self, speed_mps: float = 0.2) -> None:
        self.speed_mps = speed_mps

    def run(self) -> None:
        self.cmd = self.ros.publisher(Twist, "cmd_vel")
        msg = Twist()
        msg.linear.x = self.speed_mps
        while not self.interrupted:
            self.cmd.publish(msg)
            self.sleep(0.05)

    def safe_state(self) -> None:
        self.cmd.publish(Twist())


class Patrol(Behavior):
    """Drives (Cruise) and asks the low level for the 'driving' logic."""

    logic = "driving"

    def __init__(self, speed_mps: float = 0.2) -> None:
        self.speed_mps = speed_mps

    def run(self) -> None:
        self.start_action(Cruise(self.speed_mps))
        while self.sleep(1.0):
            pass


class Parked(Behavior):
    logic = "parked"

    def run(self) -> None:
        while self.sleep(1.0):
            pass


class Announce(Logic):
    """Writes its ``mode`` to the blackboard and publishes it on ``mode``."""

    def __init__(self, mode: str = "parked") -> None:
        self.mode = mode

    async def run(self) -> Any:
        import asyncio

        await self.hal("debug")  # keeps battery/* current on the blackboard
        self.blackboard.set("mode", self.mode)
        while True:
            await asyncio.sleep(3600)


__all__ = ["Announce", "Cruise", "Parked", "Patrol", "String"]
