"""What the fleet's agents know of the factory: places, speed zones and path costs, read
from the world YAML (``robots.world``) once per process."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

from beehave.planning import GridPlanner, NoPath

#: The ATVs' size for planning (a Kobuki's radius is 0.18 m) and their clearance.
ATV_RADIUS_M = 0.2
ATV_CLEARANCE_M = 0.1


@dataclass(frozen=True)
class Place:
    """A point a robot drives to, and how close counts as there."""

    name: str
    x_m: float
    y_m: float
    tolerance_m: float

    @property
    def xy(self) -> tuple[float, float]:
        return (self.x_m, self.y_m)


def _world_file(world: str) -> str:
    from pathlib import Path

    from robots.world import WORLDS_DIR

    path = Path(world)
    return str(path if path.is_file() else WORLDS_DIR / f"{world}.yaml")


def _inner_tolerance(size_m: tuple[float, float], margin_m: float = 0.1) -> float:
    """How far from an area's centre a robot's centre may stop and still be inside it."""
    return max(0.1, min(size_m) / 2 - margin_m)


def _place(name: str, center_m: tuple[float, float], size_m: tuple[float, float], *,
           margin_m: float = 0.1) -> Place:
    return Place(name, center_m[0], center_m[1], _inner_tolerance(size_m, margin_m))


class Site:
    """The factory as the agents see it (see :func:`site`)."""

    def __init__(self, world: str) -> None:
        from robots.world import load_world

        self.world_name = world
        w = load_world(world)
        #: The world's YAML file (what a web view draws).
        self.world_path = _world_file(world)
        self.depots = {d.name: _place(d.name, d.area.center_m, d.area.size_m)
                       for d in w.depots}
        self.machines = {m.name: _place(m.name, m.delivery.center_m, m.delivery.size_m)
                         for m in w.machines}
        self.capacity = {m.name: m.capacity for m in w.machines}
        self.consumption_per_s = {m.name: m.consumption_per_s for m in w.machines}
        self.stations = {s.name: _place(s.name, s.center_m, s.size_m, margin_m=0.15)
                         for s in w.stations_of_kind("charging")}
        #: The namespaces of the robots the world places, in its order.
        self.robots = [r.namespace for r in w.robots]
        #: Battery capacity (Wh) of each robot the world places, by namespace.
        self.battery_wh = {r.namespace: r.battery.capacity_wh for r in w.robots
                           if r.battery.capacity_wh}
        #: The speed zones (``robots.world.Zone``: name, points_m, max_speed_mps, contains).
        self.zones = list(w.zones)

    @functools.cached_property
    def planner(self) -> GridPlanner:
        from behaviours.actions import world_planner

        return world_planner(self.world_name, ATV_RADIUS_M, ATV_CLEARANCE_M)

    def path_length_m(self, start: tuple[float, float], goal: tuple[float, float]) -> float:
        """Along the planned path around the map's obstacles; inf when there is none.
        Cached (a plan costs tens of milliseconds): the legs between places repeat."""
        return self._length(start, goal)

    @functools.lru_cache(maxsize=4096)  # noqa: B019 - one Site per world, kept for the process
    def _length(self, start: tuple[float, float], goal: tuple[float, float]) -> float:
        try:
            return self.planner.plan(start, goal, goal_tolerance_m=0.3).length_m
        except NoPath:
            return math.inf

    def limit_at(self, x_m: float, y_m: float, yaw_rad: float, *,
                 lookahead_m: float) -> tuple[str | None, float]:
        """The binding zone (lowest limit) at the robot or up to ``lookahead_m`` ahead of
        it, and its limit (``inf`` outside every zone). Looking ahead lets a robot slow
        down *before* it crosses into a zone, so that it is never too fast inside."""
        best: tuple[str | None, float] = (None, math.inf)
        steps = max(1, math.ceil(lookahead_m / 0.1))
        for i in range(steps + 1):
            d = lookahead_m * i / steps
            px, py = x_m + d * math.cos(yaw_rad), y_m + d * math.sin(yaw_rad)
            for zone in self.zones:
                if zone.max_speed_mps < best[1] and zone.contains(px, py):
                    best = (zone.name, zone.max_speed_mps)
        return best


@functools.lru_cache(maxsize=4)
def site(world: str) -> Site:
    """The :class:`Site` of a world (name or YAML path), built once per process."""
    return Site(world)
