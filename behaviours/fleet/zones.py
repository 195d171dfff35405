"""Speed zones, the reflex way: a low-level logic that sets the robot's maximum speed.

Seed paper 000's dynamic request controller changes a robot's maximum speed as it enters
and leaves speed zones. :class:`SpeedZones` watches the odometry on the blackboard and,
whenever the binding limit changes, sets the ``max_speed_mps`` parameter of the robot's
high-level node through the ``speed_limit`` HAL (a ROS 2 parameter call) — every driving
action clamps its speed to it at once, whatever behaviour runs. It looks ``lookahead_m``
ahead along the heading, so the robot has slowed down *before* it crosses into a slower
zone, and keeps ``margin`` (0.9) of the zone's limit, since a base overshoots its speed
command by a few per cent; leaving every zone lifts the limit (``inf``).

It writes ``fleet/zone`` (the binding zone's name or None) and ``fleet/max_speed_mps``
(the limit in force; ``inf`` outside) to the blackboard once the robot accepted it.
"""

from __future__ import annotations

import logging
import math
from typing import cast

from beehave.errors import HALError
from beehave.logic import Logic
from behaviours.fleet.site import site
from hal.fleet import SpeedLimitHAL

log = logging.getLogger(__name__)


class SpeedZones(Logic):
    """See the module docstring."""

    def __init__(self, world: str = "factory", *, lookahead_m: float = 0.6,
                 margin: float = 0.9, hal: str = "speed_limit") -> None:
        if not (isinstance(lookahead_m, (int, float)) and 0 <= lookahead_m <= 10):
            raise ValueError(f"lookahead_m must be in [0, 10] m, got {lookahead_m!r}")
        if not (isinstance(margin, (int, float)) and 0 < margin <= 1):
            raise ValueError(f"margin must be in (0, 1], got {margin!r}")
        self.site = site(world)
        self.lookahead_m = float(lookahead_m)
        self.margin = float(margin)
        self.hal_name = hal

    async def run(self) -> None:
        limiter = cast(SpeedLimitHAL, await self.hal(self.hal_name))
        applied: float | None = None
        failing = ""  # the last failure, logged once (retried at every odometry change)
        board = self.blackboard
        async for _change in board.watch("odom/*"):
            x, y, yaw = (board.get(k) for k in ("odom/x_m", "odom/y_m", "odom/yaw_rad"))
            if not all(isinstance(v, float) for v in (x, y, yaw)):
                continue
            zone, limit = self.site.limit_at(cast(float, x), cast(float, y), cast(float, yaw),
                                             lookahead_m=self.lookahead_m)
            if limit == applied:
                continue
            try:
                # Below the limit by `margin`: a base overshoots its command a little.
                await limiter.set_max_speed(limit * self.margin)
            except HALError as exc:  # tried again at the next odometry change
                if str(exc) != failing:
                    failing = str(exc)
                    log.warning("%s: %s (retrying as the robot moves)", self.path, exc)
                continue
            failing = ""
            applied = limit
            board.set("fleet/zone", zone)
            board.set("fleet/max_speed_mps", limit if math.isfinite(limit) else None)


class AtvLogic(Logic):
    """The ATV's top-level logic: keeps the HALs its behaviours read loaded —
    ``feeds`` (odometry, battery and the factory's load and zone by default; a HAL is
    loaded while a logic holds it) — and runs :class:`SpeedZones` as a child."""

    def __init__(self, world: str = "factory", *,
                 feeds: tuple[str, ...] = ("odometry", "battery", "factory"),
                 lookahead_m: float = 0.6) -> None:
        self.zones = SpeedZones(world, lookahead_m=lookahead_m)
        self.feeds = tuple(feeds)

    async def run(self) -> None:
        for name in self.feeds:
            await self.hal(name)
        child = self.start_logic(self.zones)
        await child.wait()
        if child.error is not None:  # never silently without speed zones
            raise child.error
