"""Kobuki's behaviour: wander, and back off and turn when a bumper hits something."""

from __future__ import annotations

import math
import random

from std_msgs.msg import Int32

from beehave import Behavior, Status
from behaviours.actions import DriveBase
from robots import topics


class BumperWander(DriveBase):
    """Drive straight at ``speed_mps``; on a bumper hit stop at once, back off, turn away
    from the hit (random extra angle), go on. Runs until interrupted or ``duration_s``;
    returns the number of bumps."""

    def __init__(self, *, speed_mps: float = 0.25, duration_s: float = 1e9,
                 seed: int = 0) -> None:
        self.speed_mps, self.duration_s = speed_mps, duration_s
        self.rng = random.Random(seed)
        self.bumps = 0

    uses_odometry = False

    def drive(self) -> int:
        bumpers = self.ros.latest(Int32, topics.BUMPERS)
        clock = self.manager.clock
        start = clock.now()
        while not self.interrupted and clock.now() - start < self.duration_s:
            hit = bumpers.get()
            if hit is not None and hit.data:
                self.command(0.0, 0.0)  # stop first
                self.bumps += 1
                turn = -1.0 if hit.data & topics.LEFT else 1.0
                self._for(0.6, -0.15, 0.0)
                self._for((math.pi / 2 + self.rng.uniform(0, math.pi / 2)) / 1.5, 0.0,
                          1.5 * turn)
                continue
            self.command(self.speed_mps, 0.0)
            self.tick()
        self.command(0.0, 0.0)
        return self.bumps

    def _for(self, duration_s: float, linear: float, angular: float) -> None:
        clock = self.manager.clock
        end = clock.now() + duration_s
        while not self.interrupted and clock.now() < end:
            self.command(linear, angular)
            self.tick()


class Wander(Behavior):
    logic = "kobuki"

    def __init__(self, *, speed_mps: float = 0.25, seed: int = 0) -> None:
        self.speed_mps, self.seed = speed_mps, seed

    def run(self) -> int:
        action = self.start_action(BumperWander(speed_mps=self.speed_mps, seed=self.seed))
        action.wait()
        if action.status is Status.FAILED:
            raise RuntimeError(f"wander failed: {action.error!r}")
        return int(action.result or 0)
