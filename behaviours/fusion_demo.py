"""Priority fusion on the Kobuki: a bump-and-cliff safety reflex beside joystick-or-wander.

Three sources propose ``cmd_vel`` to one arbiter (``fusion:`` section of
``robots/config/kobuki_fusion.yaml``, docs/fusion.md):

==========  ========  =====================================================================
source      priority  proposes
==========  ========  =====================================================================
``bumper``  safety    while a bumper is pressed or a cliff is seen: back off; then turn away
                      for a while; stop while a wheel hangs or the sensors are silent
``joystick``   50     what a teleop wrote to ``joystick/cmd_vel`` while it is fresh
``wander``     10     straight ahead, always
==========  ========  =====================================================================

Wander never looks at the bumpers: it keeps proposing forward into the wall, and the
arbiter forwards the safety proposal instead until the safety logic lets go. That is the
point: the reflex is written once, and no driving logic has to remember it.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from beehave.errors import BadProposal
from beehave.fusion import Arbiter, arbiter_name, check_twist
from beehave.hal import check_duration_s
from beehave.logic import Logic

log = logging.getLogger(__name__)

__all__ = ["BumpSafety", "FusionDemo", "JoystickOrWander"]

_TRIPLE = ("left", "center", "right")


class BumpSafety(Logic):
    """The safety source: reacts to the Kobuki's bumpers, cliff sensors and wheel drops.

    While a bumper is pressed or a cliff is seen it proposes backing off at
    ``backoff_mps``; once released it keeps backing off for ``backoff_s``, then turns at
    ``turn_rps`` for ``turn_s`` (away from the obstacle: a left hit turns right), then
    withdraws so the other sources drive again. While a wheel hangs in the air, or while
    the sensor entries are stale (no data: the robot is blind), it proposes to stand
    still. It looks every ``period_s`` (the sensors arrive at 50 Hz).
    """

    def __init__(self, *, source: str = "bumper", actuator: str = "cmd_vel",
                 backoff_mps: float = 0.1, backoff_s: float = 0.8, turn_rps: float = 1.0,
                 turn_s: float = 0.8, period_s: float = 0.02) -> None:
        self.source, self.actuator = source, actuator
        self.backoff_mps, self.turn_rps = check_twist((backoff_mps, turn_rps))
        self.backoff_s = check_duration_s("backoff_s", backoff_s)
        self.turn_s = check_duration_s("turn_s", turn_s)
        self.period_s = check_duration_s("period_s", period_s)

    def _read(self, prefix: str, names: tuple[str, ...]) -> list[bool] | None:
        values = [self.blackboard.get(f"{prefix}/{n}", fresh=True) for n in names]
        return None if any(v is None for v in values) else [bool(v) for v in values]

    async def run(self) -> None:
        drive = await self.hal(arbiter_name(self.actuator), Arbiter)
        await self.hal("kobuki_bumpers")
        await self.hal("kobuki_cliffs")
        loop = asyncio.get_running_loop()
        back_until = turn_until = 0.0
        turn = self.turn_rps
        holding = False
        try:
            while True:
                now = loop.time()
                bumpers = self._read("bumper", _TRIPLE)
                cliffs = self._read("cliff", _TRIPLE)
                drops = self._read("wheel_drop", ("left", "right"))
                command: tuple[float, float] | None = None
                if bumpers is None or cliffs is None or drops is None or any(drops):
                    command = (0.0, 0.0)
                elif any(bumpers) or any(cliffs):
                    hit = [b or c for b, c in zip(bumpers, cliffs, strict=True)]
                    # Turn away from the side that hit (a centre hit turns left).
                    turn = -self.turn_rps if hit[0] and not hit[2] else self.turn_rps
                    back_until = now + self.backoff_s
                    turn_until = back_until + self.turn_s
                    command = (-self.backoff_mps, 0.0)
                elif now < back_until:
                    command = (-self.backoff_mps, 0.0)
                elif now < turn_until:
                    command = (0.0, turn)
                if command is not None:
                    drive.propose(self.source, command)
                    holding = True
                elif holding:
                    drive.withdraw(self.source)  # hand back at once, not after max_age_s
                    holding = False
                await asyncio.sleep(self.period_s)
        finally:
            if holding:
                drive.withdraw(self.source)


class JoystickOrWander(Logic):
    """Two non-safety sources: ``joystick`` relays ``joystick/cmd_vel`` (``[linear_mps,
    angular_rps]``, written by a teleop) while it is younger than ``joystick_max_age_s``;
    ``wander`` always proposes ``(speed_mps, 0)``. The arbiter lets the joystick win."""

    def __init__(self, *, speed_mps: float = 0.3, actuator: str = "cmd_vel",
                 joystick_key: str = "joystick/cmd_vel", joystick_max_age_s: float = 0.5,
                 period_s: float = 0.05) -> None:
        self.speed_mps = check_twist((speed_mps, 0.0))[0]
        self.actuator = actuator
        self.joystick_key = joystick_key
        self.joystick_max_age_s = check_duration_s("joystick_max_age_s", joystick_max_age_s)
        self.period_s = check_duration_s("period_s", period_s)

    async def run(self) -> None:
        drive = await self.hal(arbiter_name(self.actuator), Arbiter)
        refused: Any = None
        while True:
            drive.propose("wander", (self.speed_mps, 0.0))
            entry = self.blackboard.entry(self.joystick_key)
            # The entry's age, not its arrival: a teleop holding the stick re-sends the
            # same value, which refreshes the entry without waking anybody.
            if entry is not None and not entry.stale and entry.age_s <= self.joystick_max_age_s:
                try:
                    drive.propose("joystick", entry.value)
                except BadProposal as exc:
                    if entry.value is not refused:  # say it once per bad value, keep wandering
                        log.error("logic %r: %s (from %r)", self.path, exc, self.joystick_key)
                        refused = entry.value
            await asyncio.sleep(self.period_s)


class FusionDemo(Logic):
    """The top-level logic of ``kobuki_fusion.yaml``: both proposers as sub-logics."""

    def __init__(self, *, speed_mps: float = 0.3, backoff_s: float = 0.8,
                 turn_s: float = 0.8) -> None:
        self.safety = BumpSafety(backoff_s=backoff_s, turn_s=turn_s)
        self.driver = JoystickOrWander(speed_mps=speed_mps)

    async def run(self) -> None:
        self.start_logic(self.safety, name="safety")
        self.start_logic(self.driver, name="driver")
        await asyncio.Event().wait()  # the sub-logics propose until we are cancelled
