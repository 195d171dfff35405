"""The physics of a factory world: machines that consume material, loads carried from a
depot to the machines, charging stations any robot may use, and speed zones — with the
facts a fleet is judged by, measured here, in the simulation, not reported by the robots.

::

    from robots.factory import Factory
    from robots.sim import Simulation

    sim = Simulation("factory", real_time_factor=None)
    factory = Factory(sim)                 # hooks itself into the sim step (on_step)
    sim.run_for(60.0)
    factory.facts().machine("press1").level
    factory.facts().as_dict()              # JSON-ready: the report of `beehave sim --report`
    factory.close()                        # unhooks it; the simulation goes on

A world without machines, depots or zones (the warehouse) needs no Factory and is
unaffected by this module: nothing here runs unless a Factory is created.

The rules, checked ``rate_hz`` times per sim second (default 48 Hz: every 5th step at
240 Hz), in the simulation's stepping thread:

- **Machines.** A machine's level falls by ``consumption_per_s`` × dt, never below 0.
  The time it spends at 0 is counted (``empty_s``, to the exact sim time it ran out).
- **Standing still** means ``|linear speed| < still_speed_mps`` (0.05 m/s) — the body's
  velocity along its heading, as odometry reports it; turning on the spot counts as still.
- **Loading.** A robot with no load whose centre stays still inside a depot's ``area`` for
  the depot's ``load_s`` picks up one load of ``load_amount`` units. A robot carries at
  most one load (a Kobuki's top plate holds one box): a loaded robot in a depot gets
  nothing more. The load shows as a coloured box on top of the robot in pybullet (visual
  only: it collides with nothing and the laser does not see it).
- **Unloading.** A loaded robot whose centre stays still inside a machine's ``delivery``
  area for the machine's ``unload_s`` unloads: the level rises by the load's amount,
  capped at the capacity (what does not fit is lost and the delivery records what was
  accepted). Moving, or leaving the area, restarts the wait.
- **Charging.** A robot whose centre is inside any ``charging`` station charges (the
  robot's battery model, :mod:`robots.robot`; stations belong to no robot). The facts
  count, per station, how many robots are in it at once.
- **Speed zones.** While a robot's centre is inside a zone, its speed — ``|linear speed|``
  averaged over the last ``speed_window_s`` (0.2 s) of sim time, so that a one-step jolt
  of the physics (a wheel catching an edge) is no violation — divided by the zone's
  ``max_speed_mps`` is the zone's ratio; the facts keep the largest. The average also
  carries the speed from just before the robot entered into its first 0.2 s inside: a
  robot must slow down *before* it enters.

Threads. Every public method may be called from any thread: :meth:`Factory.facts` and
:meth:`Factory.state` return snapshots taken under a lock the update holds briefly.
Listeners (:meth:`Factory.on_event`) are called in the stepping thread right after a
pick-up or a delivery; like ``on_step`` callbacks they must be quick, and one that raises
ends the simulation thread (:class:`~robots.errors.SimulationError` from ``stop()``).
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robots.errors import UnknownMachine, UnknownRobot, UnknownStation, UnknownZone
from robots.world import Depot, Machine, Station, Zone

if TYPE_CHECKING:
    from pybullet_utils.bullet_client import BulletClient  # type: ignore[import-untyped]

    from robots.robot import SimRobot
    from robots.sim import Simulation

log = logging.getLogger(__name__)

__all__ = ["STATE_SCHEMA", "REPORT_SCHEMA", "Delivery", "Factory", "FactoryFacts",
           "MachineFacts", "Pickup", "RobotFacts", "StationFacts", "ZoneFacts"]

STATE_SCHEMA = "beehave/factory/state/1"
"""The ``schema`` of :meth:`Factory.state` (published on ``/factory/state``)."""
REPORT_SCHEMA = "beehave/factory/report/1"
"""The ``schema`` of :meth:`Factory.report` (``beehave sim --report FILE.json``)."""

_LOAD_RGBA = [0.95, 0.55, 0.10, 1.0]
_LOAD_HALF_M = (0.09, 0.09, 0.04)
_LOAD_Z_M = 0.20  # above a Kobuki's scanner (0.123 m): it must not hide the laser's view


# ---- what happened ----------------------------------------------------------------------

@dataclass(frozen=True)
class Pickup:
    """A robot picked up a load at a depot."""

    depot: str
    robot: str
    time_s: float
    amount: float


@dataclass(frozen=True)
class Delivery:
    """A robot unloaded at a machine: ``amount`` is what the machine accepted (the load,
    or less when it was nearly full), ``level_after`` its level just after."""

    machine: str
    robot: str
    time_s: float
    amount: float
    level_after: float


FactoryEvent = Pickup | Delivery
"""What :meth:`Factory.on_event` listeners receive."""


# ---- the facts --------------------------------------------------------------------------

@dataclass(frozen=True)
class MachineFacts:
    """One machine: its level now and what it went through since the start."""

    name: str
    capacity: float
    level: float
    min_level: float
    min_level_at_s: float
    empty_s: float
    """Sim seconds spent with the level at 0."""
    first_empty_at_s: float | None
    received: float
    """Units accepted from deliveries."""
    deliveries: int


@dataclass(frozen=True)
class StationFacts:
    """One charging station: who is in it now, and the most robots that were at once."""

    name: str
    occupants: tuple[str, ...]
    max_charging: int
    max_charging_at_s: float | None
    """When ``max_charging`` was first reached (None: no robot ever charged here)."""
    max_charging_robots: tuple[str, ...]


@dataclass(frozen=True)
class RobotFacts:
    """One robot: its load, zone and battery now, and its lowest battery so far."""

    namespace: str
    load: float | None
    """The amount it carries, None when empty."""
    zone: str | None
    zone_max_speed_mps: float | None
    charging_at: str | None
    battery_fraction: float
    min_battery_fraction: float
    min_battery_at_s: float
    speed_mps: float
    """|linear speed| averaged over the speed window."""
    pickups: int
    deliveries: int
    distance_m: float = 0.0
    """The distance it drove: |linear speed| integrated over sim time."""
    charging_s: float = 0.0
    """Sim seconds its centre spent inside a charging station."""


@dataclass(frozen=True)
class ZoneFacts:
    """One speed zone: the largest measured speed / limit ratio of any robot inside."""

    name: str
    max_speed_mps: float
    max_ratio: float
    """0.0 while no robot has moved inside it."""
    max_ratio_robot: str | None
    max_ratio_at_s: float | None
    max_measured_mps: float


@dataclass(frozen=True)
class FactoryFacts:
    """Everything measured since the start, at sim time ``time_s`` (a snapshot).

    Look one up by name with :meth:`machine`, :meth:`station`, :meth:`robot`,
    :meth:`zone`; :meth:`as_dict` is the JSON form (lists keyed by name);
    :meth:`problems` lists what a fleet must not do.
    """

    time_s: float
    speed_window_s: float
    machines: tuple[MachineFacts, ...]
    stations: tuple[StationFacts, ...]
    robots: tuple[RobotFacts, ...]
    zones: tuple[ZoneFacts, ...]
    pickups: tuple[Pickup, ...]
    deliveries: tuple[Delivery, ...]

    def machine(self, name: str) -> MachineFacts:
        for item in self.machines:
            if item.name == name:
                return item
        raise UnknownMachine(name, [m.name for m in self.machines])

    def station(self, name: str) -> StationFacts:
        for item in self.stations:
            if item.name == name:
                return item
        raise UnknownStation(name, [s.name for s in self.stations])

    def robot(self, namespace: str) -> RobotFacts:
        for item in self.robots:
            if item.namespace == namespace:
                return item
        raise UnknownRobot(namespace, [r.namespace for r in self.robots])

    def zone(self, name: str) -> ZoneFacts:
        for item in self.zones:
            if item.name == name:
                return item
        raise UnknownZone(name, [z.name for z in self.zones])

    def problems(self, *, speed_tolerance: float = 0.05) -> list[str]:
        """What went wrong, one line each, measured in the physics: a machine that ran
        empty, two or more robots charging at one station at once, a battery that reached
        zero, a zone's limit exceeded by more than ``speed_tolerance`` (0.05: 5 %)."""
        found = [f"machine {m.name} ran empty at {m.first_empty_at_s:.1f} s and stayed "
                 f"empty {m.empty_s:.1f} s" for m in self.machines if m.empty_s > 0
                 and m.first_empty_at_s is not None]
        found += [f"station {s.name}: {s.max_charging} robots charged at once "
                  f"({', '.join(s.max_charging_robots)} at {s.max_charging_at_s:.1f} s)"
                  for s in self.stations if s.max_charging > 1]
        found += [f"robot {r.namespace}: battery reached zero at {r.min_battery_at_s:.1f} s"
                  for r in self.robots if r.min_battery_fraction <= 0.0]
        found += [f"zone {z.name}: {z.max_ratio_robot} drove {z.max_measured_mps:.3f} m/s "
                  f"at {z.max_ratio_at_s:.1f} s, {z.max_ratio:.2f} x the limit of "
                  f"{z.max_speed_mps:g} m/s"
                  for z in self.zones if z.max_ratio > 1.0 + speed_tolerance]
        return found

    def as_dict(self) -> dict[str, Any]:
        """The facts as plain JSON-ready data: ``machines``, ``stations``, ``robots`` and
        ``zones`` as objects keyed by name, ``pickups`` and ``deliveries`` as lists in the
        order they happened."""
        def keyed(items: tuple[Any, ...], key: str) -> dict[str, dict[str, Any]]:
            out = {}
            for item in items:
                data = asdict(item)
                out[data.pop(key)] = data
            return out

        return {"time_s": self.time_s, "speed_window_s": self.speed_window_s,
                "machines": keyed(self.machines, "name"),
                "stations": keyed(self.stations, "name"),
                "robots": keyed(self.robots, "namespace"),
                "zones": keyed(self.zones, "name"),
                "pickups": [asdict(p) for p in self.pickups],
                "deliveries": [asdict(d) for d in self.deliveries]}


# ---- the mutable state (sim thread, under the lock) ---------------------------------------

class _MachineState:
    def __init__(self, spec: Machine) -> None:
        self.spec = spec
        self.level = float(spec.initial_level)
        self.min_level = self.level
        self.min_level_at_s = 0.0
        self.empty_s = 0.0
        self.first_empty_at_s: float | None = 0.0 if self.level <= 0 else None
        self.received = 0.0
        self.deliveries = 0

    def consume(self, start_s: float, dt_s: float) -> None:
        rate = self.spec.consumption_per_s
        if self.level > 0.0:
            use = rate * dt_s
            if use < self.level:
                self.level -= use
            else:
                # Ran out inside this interval: count only the part after it did.
                ran_out_s = start_s + (self.level / rate if rate > 0 else 0.0)
                self.empty_s += start_s + dt_s - ran_out_s
                if self.first_empty_at_s is None:
                    self.first_empty_at_s = ran_out_s
                self.level = 0.0
        else:
            self.empty_s += dt_s
        if self.level < self.min_level:
            self.min_level = self.level
            self.min_level_at_s = start_s + dt_s

    def facts(self) -> MachineFacts:
        s = self.spec
        return MachineFacts(s.name, s.capacity, self.level, self.min_level,
                            self.min_level_at_s, self.empty_s, self.first_empty_at_s,
                            self.received, self.deliveries)


class _StationState:
    def __init__(self, spec: Station) -> None:
        self.spec = spec
        self.occupants: tuple[str, ...] = ()
        self.max_charging = 0
        self.max_charging_at_s: float | None = None
        self.max_charging_robots: tuple[str, ...] = ()

    def facts(self) -> StationFacts:
        return StationFacts(self.spec.name, self.occupants, self.max_charging,
                            self.max_charging_at_s, self.max_charging_robots)


class _ZoneState:
    def __init__(self, spec: Zone) -> None:
        self.spec = spec
        self.max_ratio = 0.0
        self.max_ratio_robot: str | None = None
        self.max_ratio_at_s: float | None = None
        self.max_measured_mps = 0.0

    def facts(self) -> ZoneFacts:
        return ZoneFacts(self.spec.name, self.spec.max_speed_mps, self.max_ratio,
                         self.max_ratio_robot, self.max_ratio_at_s, self.max_measured_mps)


class _RobotState:
    def __init__(self, robot: SimRobot, window: int) -> None:
        self.robot = robot
        self.load: Pickup | None = None
        self.load_body: int | None = None
        self.zone: Zone | None = None
        self.charging_at: str | None = None
        battery = robot.battery().fraction
        self.battery = battery
        self.min_battery = battery
        self.min_battery_at_s = 0.0
        self.speeds: deque[float] = deque(maxlen=window)
        self.speed_sum = 0.0
        self.speed = 0.0
        self.dwell_at: Depot | Machine | None = None
        self.dwell_since_s = 0.0
        self.pickups = 0
        self.deliveries = 0
        self.distance_m = 0.0
        self.charging_s = 0.0

    def add_speed(self, speed: float) -> float:
        """The mean of the last ``window`` speeds (a running sum: O(1) per sample)."""
        speeds = self.speeds
        if len(speeds) == speeds.maxlen:
            self.speed_sum -= speeds[0]
        speeds.append(speed)
        self.speed_sum += speed
        self.speed = max(0.0, self.speed_sum / len(speeds))
        return self.speed

    def facts(self) -> RobotFacts:
        zone = self.zone
        return RobotFacts(
            self.robot.namespace, None if self.load is None else self.load.amount,
            None if zone is None else zone.name, None if zone is None else zone.max_speed_mps,
            self.charging_at, self.battery, self.min_battery, self.min_battery_at_s,
            self.speed, self.pickups, self.deliveries, self.distance_m, self.charging_s)


# ---- the factory ------------------------------------------------------------------------

class Factory:
    """The factory physics of ``sim``'s world (see the module docstring).

    Creating it hooks an ``on_step`` callback into ``sim`` at ``rate_hz`` (sim time);
    :meth:`close` removes it. Options (keyword-only): ``still_speed_mps`` — below it a
    robot stands still (loads, unloads); ``speed_window_s`` — the averaging window of the
    zone speeds; ``show_loads`` — put a box on top of loaded robots in pybullet (off: the
    load is only a flag, for benchmarks).
    """

    def __init__(self, sim: Simulation, *, rate_hz: float = 50.0,
                 still_speed_mps: float = 0.05, speed_window_s: float = 0.2,
                 show_loads: bool = True) -> None:
        for name, value in (("rate_hz", rate_hz), ("still_speed_mps", still_speed_mps),
                            ("speed_window_s", speed_window_s)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"Factory: {name} must be positive and finite, got {value}")
        self.sim = sim
        self.world = sim.world
        self.still_speed_mps = float(still_speed_mps)
        self.show_loads = show_loads
        every = max(1, round(sim.rate_hz / rate_hz))
        self.period_s = every / sim.rate_hz
        """Sim seconds between two updates (the on_step period actually used)."""
        window = max(1, round(speed_window_s / self.period_s))
        self.speed_window_s = window * self.period_s
        self._lock = threading.Lock()
        self._machines = [_MachineState(m) for m in self.world.machines]
        self._stations = [_StationState(s) for s in self.world.stations_of_kind("charging")]
        self._zones = {z.name: _ZoneState(z) for z in self.world.zones}
        self._robots = [_RobotState(r, window) for r in sim.robots.values()]
        self._pickups: list[Pickup] = []
        self._deliveries: list[Delivery] = []
        self._listeners: list[Callable[[FactoryEvent], None]] = []
        self._last_s = sim.time_s
        self._closed = False
        self._remove = sim.on_step(self._update, rate_hz=sim.rate_hz / every)

    # ---- readings (any thread) ------------------------------------------------------

    def facts(self) -> FactoryFacts:
        """A snapshot of everything measured so far (see :class:`FactoryFacts`)."""
        with self._lock:
            return FactoryFacts(
                self._last_s, self.speed_window_s,
                tuple(m.facts() for m in self._machines),
                tuple(s.facts() for s in self._stations),
                tuple(r.facts() for r in self._robots),
                tuple(z.facts() for z in self._zones.values()),
                tuple(self._pickups), tuple(self._deliveries))

    def levels(self) -> dict[str, float]:
        """Each machine's level now, by name."""
        with self._lock:
            return {m.spec.name: m.level for m in self._machines}

    def loads(self) -> dict[str, float]:
        """The amount each loaded robot carries, by namespace (empty robots left out)."""
        with self._lock:
            return {r.robot.namespace: r.load.amount for r in self._robots
                    if r.load is not None}

    def state(self) -> dict[str, Any]:
        """The ``/factory/state`` message (schema :data:`STATE_SCHEMA`): machines (level,
        capacity), robots (load, zone and its limit, position, speed, battery, the
        station it charges at), charging stations (occupants) and the cumulative facts."""
        facts = self.facts()
        return {
            "schema": STATE_SCHEMA, "world": self.world.name, "time_s": facts.time_s,
            "machines": {m.name: {"level": m.level, "capacity": m.capacity}
                         for m in facts.machines},
            "robots": {r.namespace: {
                "load": r.load, "zone": r.zone, "zone_max_speed_mps": r.zone_max_speed_mps,
                "x_m": pose.x_m, "y_m": pose.y_m, "speed_mps": r.speed_mps,
                "battery_fraction": r.battery_fraction, "charging_at": r.charging_at}
                for r, pose in zip(facts.robots, self._poses(), strict=True)},
            "stations": {s.name: {"occupants": list(s.occupants)} for s in facts.stations},
            "facts": facts.as_dict(),
        }

    def report(self) -> dict[str, Any]:
        """The facts report (schema :data:`REPORT_SCHEMA`) with its problem list."""
        facts = self.facts()
        return {"schema": REPORT_SCHEMA, "world": self.world.name,
                "problems": facts.problems(), **facts.as_dict()}

    def render_topdown(self, path: str | Path, *, scale_px_per_m: float = 40.0) -> Path:
        """The top-down picture with the machines' levels and the loads now (see
        :meth:`robots.sim.Simulation.render_topdown`)."""
        return self.sim.render_topdown(path, scale_px_per_m=scale_px_per_m,
                                       levels=self.levels(), loads=set(self.loads()),
                                       title=f"{self.world.name}  t = {self._last_s:.0f} s")

    def _poses(self) -> list[Any]:
        return [r.robot.pose() for r in self._robots]

    # ---- listeners ------------------------------------------------------------------

    def on_event(self, callback: Callable[[FactoryEvent], None]) -> Callable[[], None]:
        """Call ``callback(event)`` (a :class:`Pickup` or :class:`Delivery`) in the
        stepping thread as it happens; returns a function that removes it."""
        with self._lock:
            self._listeners = [*self._listeners, callback]

        def remove() -> None:
            with self._lock:
                self._listeners = [c for c in self._listeners if c is not callback]

        return remove

    def close(self) -> None:
        """Unhook from the simulation (idempotent); the facts stay readable."""
        if self._closed:
            return
        self._closed = True
        self._remove()

    # ---- sim thread -----------------------------------------------------------------

    def _update(self, time_s: float) -> None:
        events: list[FactoryEvent] = []
        with self._lock:
            dt = time_s - self._last_s
            start = self._last_s
            self._last_s = time_s
            if dt <= 0:
                return
            for machine in self._machines:
                machine.consume(start, dt)
            for station in self._stations:
                station.occupants = ()
            for state in self._robots:
                self._update_robot(state, time_s, dt, events)
            for station in self._stations:
                n = len(station.occupants)
                if n > station.max_charging:
                    station.max_charging = n
                    station.max_charging_at_s = time_s
                    station.max_charging_robots = station.occupants
            listeners = self._listeners
        for event in events:
            for callback in listeners:
                callback(event)

    def _update_robot(self, state: _RobotState, time_s: float, dt_s: float,
                      events: list[FactoryEvent]) -> None:
        robot = state.robot
        odom = robot.odometry()
        x, y = odom.x_m, odom.y_m
        speed = state.add_speed(abs(odom.linear_mps))
        state.distance_m += abs(odom.linear_mps) * dt_s
        battery = robot.battery().fraction
        state.battery = battery
        if battery < state.min_battery:
            state.min_battery = battery
            state.min_battery_at_s = time_s

        state.zone = self.world.zone_at(x, y)
        for zone in self.world.zones:
            if zone.contains(x, y):
                z = self._zones[zone.name]
                ratio = speed / zone.max_speed_mps
                if ratio > z.max_ratio:
                    z.max_ratio, z.max_ratio_robot, z.max_ratio_at_s = ratio, robot.namespace, \
                        time_s
                    z.max_measured_mps = speed

        state.charging_at = None
        for station in self._stations:
            if station.spec.contains(x, y):
                station.occupants = (*station.occupants, robot.namespace)
                state.charging_at = station.spec.name
                state.charging_s += dt_s

        # Where this robot could load or unload now, if it stands still long enough.
        place: Depot | Machine | None = None
        if abs(odom.linear_mps) < self.still_speed_mps:
            if state.load is None:
                place = next((d for d in self.world.depots if d.area.contains(x, y)), None)
            else:
                place = next((m for m in self.world.machines if m.delivery.contains(x, y)),
                             None)
        if place is not state.dwell_at:
            state.dwell_at = place
            state.dwell_since_s = time_s
        if place is None:
            pass
        elif isinstance(place, Depot):
            if time_s - state.dwell_since_s + 1e-9 >= place.load_s:
                pickup = Pickup(place.name, robot.namespace, time_s, float(place.load_amount))
                state.load = pickup
                state.pickups += 1
                state.dwell_at = None
                self._pickups.append(pickup)
                events.append(pickup)
                self._show_load(state)
        elif time_s - state.dwell_since_s + 1e-9 >= place.unload_s and state.load is not None:
            machine = next(m for m in self._machines if m.spec is place)
            accepted = min(state.load.amount, machine.spec.capacity - machine.level)
            machine.level += accepted
            machine.received += accepted
            machine.deliveries += 1
            delivery = Delivery(place.name, robot.namespace, time_s, accepted, machine.level)
            state.load = None
            state.deliveries += 1
            state.dwell_at = None
            self._deliveries.append(delivery)
            events.append(delivery)
            self._show_load(state)
        if state.load_body is not None:
            self._move_load(state, odom.x_m, odom.y_m, odom.yaw_rad)

    # ---- the load box in pybullet (sim thread) ----------------------------------------

    def _show_load(self, state: _RobotState) -> None:
        if not self.show_loads:
            return
        if state.load is None and state.load_body is not None:
            body = state.load_body
            state.load_body = None
            self.sim.call(lambda c: c.removeBody(body))
        elif state.load is not None and state.load_body is None:
            def create(c: BulletClient) -> int:
                visual = c.createVisualShape(c.GEOM_BOX, halfExtents=list(_LOAD_HALF_M),
                                             rgbaColor=_LOAD_RGBA)
                body: int = c.createMultiBody(0.0, -1, visual, [0.0, 0.0, _LOAD_Z_M])
                return body

            state.load_body = self.sim.call(create)

    def _move_load(self, state: _RobotState, x: float, y: float, yaw: float) -> None:
        body = state.load_body
        quat = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        self.sim.call(lambda c: c.resetBasePositionAndOrientation(body, [x, y, _LOAD_Z_M],
                                                                  quat))

    def __repr__(self) -> str:
        return (f"<Factory {self.world.name!r} machines={len(self._machines)} "
                f"robots={len(self._robots)} deliveries={len(self._deliveries)}>")
