"""Behaviours, logics and HALs that the robot configurations of tests/data/config/ name
(importable by ``beehave run`` with ``tests/`` on the path)."""

from __future__ import annotations

import asyncio
import time

from beehave import HAL, Behavior, Logic
from beehave.testing import ScriptedAction


class Waits(Behavior):
    """Does nothing until interrupted; takes a parameter to check ``params:`` against."""

    def __init__(self, speed_mps: float = 0.2) -> None:
        self.speed_mps = speed_mps

    def run(self) -> None:
        while self.sleep(1.0):
            pass


class Drive(Behavior):
    """Drives to a station and waits there.

    More text that the listing leaves out (the control plane lists the first paragraph)."""

    def __init__(self, station: str, speed_mps: float = 0.5) -> None:
        self.station = station
        self.speed_mps = speed_mps
        self.action = ScriptedAction("driving", duration_s=60.0, name="to_station")

    def run(self) -> None:
        self.start_action(self.action)
        while self.sleep(0.01):
            pass


class Explodes(Behavior):
    """A behaviour whose constructor fails, as one that opens missing hardware does."""

    def __init__(self) -> None:
        raise RuntimeError("motor controller not found on /dev/ttyUSB0")

    def run(self) -> None:  # pragma: no cover - never constructed
        pass


class BrokenHAL(HAL):
    """A HAL whose ``on_load`` fails (the serial port is not there)."""

    name = "broken"

    async def on_load(self) -> None:
        raise OSError("no such device: /dev/ttyACM7")


class UsesBroken(Logic):
    """A logic that needs the broken HAL."""

    async def run(self) -> None:
        await self.hal("broken")


class BlocksTheLoop(Logic):
    """The mistake of issue 11: ``time.sleep`` in a logic holds the whole event loop.
    Starts blocking once the robot is up (the high level's state has reached this low
    level), and says so on stdout (the test waits for that line). A fixed 0.3 s was not
    enough on a loaded machine: it blocked before ``beehave run`` said "running"."""

    async def run(self) -> None:
        for _ in range(400):  # at most 20 s, then block anyway
            if self.blackboard.get("high_level/behavior") is not None:
                break
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.5)  # "running" is printed once the robot's start returned
        print("BlocksTheLoop: blocking the event loop now", flush=True)
        while True:
            time.sleep(0.05)  # noqa: ASYNC251 - the bug this fixture stands for
