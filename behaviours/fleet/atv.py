"""The ATV (a Kobuki) of the factory fleet: its two top-level behaviours and its one action.

``work``
    Offers ``transport`` in the directory and answers the machines' calls for proposals
    (:class:`Transport`, a :class:`~beehave.agents.protocols.ContractNetResponder` that
    queues accepted orders). Its bid is the time the order would take *after the work it
    already accepted*: the planned path from where it will be to the depot and on to the
    machine, at its cruise speed, plus a penalty for a low battery; it refuses when the
    battery would not last. When the battery falls below ``charge_below_pct`` and its
    current delivery is done (or below ``critical_pct`` at once) it switches the robot to
    ``charge``; orders still queued get a failure, so their machines re-award them.
``charge``
    Finds the charging stations in the directory, reserves the nearest free one (FIPA
    request; the reservation is a lease it renews while it needs it, so a robot that dies
    frees its station), drives there, charges to ``charged_pct``, releases the station and
    switches back to ``work``. A station that vanishes (its agent killed) or refuses a
    renewal sends it to the next one.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

from beehave.agents import AgentBehavior, Message
from beehave.agents.protocols import ContractNetResponder, request
from beehave.errors import AgentError, BeehaveError, Interrupted, NoReply, ProtocolFailed
from beehave.status import Status
from behaviours.actions import Goal, Navigation, SpeedLimit
from behaviours.fleet.site import ATV_CLEARANCE_M, ATV_RADIUS_M, site

log = logging.getLogger(__name__)

LOAD_KEY = "factory/load"
BATTERY_KEY = "battery/percentage"
POSE_KEYS = ("odom/x_m", "odom/y_m")

#: How the ATVs drive (Kobuki: 0.7 m/s at most; zones slow it further).
CRUISE_MPS = 0.4


class DeliveryError(BeehaveError):
    """A delivery could not be completed (no load at the depot, not unloaded in time)."""


def _nav_options(tolerance_m: float) -> dict[str, Any]:
    return {"speed_mps": CRUISE_MPS, "tolerance_m": tolerance_m, "stop_distance_m": 0.45,
            "slow_distance_m": 0.9, "robot_radius_m": ATV_RADIUS_M,
            "clearance_m": ATV_CLEARANCE_M, "replan_after_s": 2.0, "blocked_timeout_s": 60.0,
            "forget_obstacles_after_s": 10.0}


class Deliver(Navigation):
    """Fetch one load at ``depot`` and unload it at ``machine``'s delivery area.

    Two legs of :class:`~behaviours.actions.Navigation` (planned paths, the laser safety
    field, re-planning around other robots) with a stop at each end: at the depot until
    the load is on (``factory/load`` ≥ 1, from the factory HAL), at the machine until it is
    off. An ATV that already carries a load (an earlier order was cancelled after loading)
    drives straight to the machine. Returns what happened, for the initiator's inform."""

    def __init__(self, order: str, depot: str, machine: str, *, world: str,
                 wait_timeout_s: float = 30.0) -> None:
        places = site(world)
        self.order, self.depot_place = order, places.depots[depot]
        self.machine_place = places.machines[machine]
        super().__init__(Goal(*self.depot_place.xy, name=depot), world=world,
                         **_nav_options(self.depot_place.tolerance_m))
        self.name = f"Deliver→{machine}"
        self.wait_timeout_s = wait_timeout_s
        self.phase = "planned"

    def drive(self) -> dict[str, Any]:  # type: ignore[override]
        started = self.manager.clock.now()
        if (self.blackboard.get(LOAD_KEY) or 0) < 1:
            self.phase = "to_depot"
            super().drive()
            self.phase = "loading"
            self._wait_load(lambda load: load >= 1, "loaded at the depot")
        if self.interrupted:
            return {"order": self.order, "delivered": False}
        place = self.machine_place
        self.goal = Goal(*place.xy, name=place.name)
        self.tolerance_m = place.tolerance_m
        self.phase = "to_machine"
        super().drive()
        self.phase = "unloading"
        self._wait_load(lambda load: load < 1, f"unloaded at {place.name}")
        self.phase = "done"
        return {"order": self.order, "machine": place.name,
                "duration_s": round(self.manager.clock.now() - started, 2)}

    def _wait_load(self, done: Any, what: str) -> None:
        self.command(0.0, 0.0)
        clock = self.manager.clock
        deadline = clock.now() + self.wait_timeout_s
        while not self.interrupted:
            if done(self.blackboard.get(LOAD_KEY) or 0):
                return
            if clock.now() > deadline:
                raise DeliveryError(f"{self.name}: not {what} within {self.wait_timeout_s} s "
                                    f"(factory/load={self.blackboard.get(LOAD_KEY)!r})")
            self.command(0.0, 0.0)
            self.tick()


class Transport(ContractNetResponder):
    """Bids for transport orders and performs them, one after the other."""

    service = "transport"
    queue_tasks = True
    # Two machines that order at once must not both get the ATV that was idle for each.
    answer_cfps_in_turn = True

    def __init__(self, world: str, *, max_queue: int = 2, power_w: float = 10.0,
                 capacity_wh: float | None = None, reserve_pct: float = 20.0) -> None:
        self.world = world
        self.max_queue = max_queue
        self.power_w = power_w  # a Kobuki: 5 W idle + 12 W per m/s at CRUISE_MPS
        self.capacity_wh = capacity_wh
        self.reserve_pct = reserve_pct
        self.refusing: str | None = None  # set by Work when the battery asks for a charge

    def service_properties(self) -> dict[str, Any]:
        return {"kind": "kobuki", "world": site(self.world).world_name}

    def _pose(self) -> tuple[float, float] | None:
        x, y = (self.blackboard.get(k) for k in POSE_KEYS)
        return (x, y) if isinstance(x, float) and isinstance(y, float) else None

    def _queued(self) -> list[Message]:
        """Accepted orders not finished yet, in the order they will be done."""
        running = [t.request for t in self.tasks.values()
                   if t.action is not None and not t.action.status.finished]
        return running + [t.request for t in self.waiting]

    def estimate(self, cfp: Message) -> dict[str, Any] | str:
        """The bid for ``cfp`` (its content: ``{"order", "machine", "depot"}``), or why it
        makes none."""
        places = site(self.world)
        content = cfp.content if isinstance(cfp.content, dict) else {}
        machine, depot = content.get("machine"), content.get("depot")
        if machine not in places.machines or depot not in places.depots:
            raise DeliveryError(f"unknown machine {machine!r} or depot {depot!r}: this world "
                                f"has machines {sorted(places.machines)} and depots "
                                f"{sorted(places.depots)}")
        pose = self._pose()
        if pose is None:
            return "no odometry yet"  # no honest bid without it
        queue = self._queued()
        if len(queue) >= self.max_queue:
            return f"{len(queue)} orders queued already"
        # Where it stands now, then every accepted order in turn, then this one.
        at, length = pose, 0.0
        loaded = (self.blackboard.get(LOAD_KEY) or 0) >= 1
        for i, accepted in enumerate(queue):
            job = accepted.content if isinstance(accepted.content, dict) else {}
            if not (i == 0 and loaded):
                length += places.path_length_m(at, places.depots[job["depot"]].xy)
                at = places.depots[job["depot"]].xy
            length += places.path_length_m(at, places.machines[job["machine"]].xy)
            at = places.machines[job["machine"]].xy
        own = places.path_length_m(at, places.depots[depot].xy) + places.path_length_m(
            places.depots[depot].xy, places.machines[machine].xy)
        length += own
        if not math.isfinite(length):
            return f"no path to {machine} via {depot}"
        battery = self.blackboard.get(BATTERY_KEY)
        if not isinstance(battery, float):
            return "no battery reading"
        eta_s = length / CRUISE_MPS + 4.0 * (len(queue) + 1)  # + loading and unloading
        capacity_wh = self.capacity_wh or places.battery_wh.get(self.agent.name, 32.6)
        need_pct = 100.0 * eta_s * self.power_w / 3600.0 / capacity_wh
        if battery - need_pct < self.reserve_pct:
            return (f"battery {battery:.0f} % would fall to {battery - need_pct:.0f} %, "
                    f"below the reserve of {self.reserve_pct:g} %")
        cost = eta_s + 0.5 * max(0.0, 60.0 - battery)  # prefer the fuller battery
        # The accept-proposal carries this back: the job travels with the bid.
        return {"order": content.get("order"), "machine": machine, "depot": depot,
                "cost": round(cost, 2), "eta_s": round(eta_s, 1), "path_m": round(length, 1),
                "queue": len(queue), "battery_pct": round(battery, 1)}

    def propose(self, cfp: Message) -> Any:
        offer = self.refusing if self.refusing is not None else self.estimate(cfp)
        if isinstance(offer, str):
            log.info("%s: no bid for %s: %s", self.path, cfp.conversation_id, offer)
            return None
        return offer

    def perform(self, task: Message) -> Any:
        job = task.content
        return Deliver(job["order"], job["depot"], job["machine"], world=self.world)

    def busy(self) -> bool:
        return bool(self._queued())


class Work(AgentBehavior):
    """The ATV's working behaviour: transport, until the battery asks for a charge."""

    def __init__(self, world: str = "factory", *, charge_below_pct: float = 35.0,
                 critical_pct: float = 15.0) -> None:
        self.world = world
        self.charge_below_pct = charge_below_pct
        self.critical_pct = critical_pct

    @classmethod
    def prepare_node(cls, node: Any) -> None:
        # The zones logic sets max_speed_mps from its first odometry: declared before.
        SpeedLimit.of(node)

    def run(self) -> str:
        if self.manager.node is not None:
            SpeedLimit.of(self.manager.node)
        transport = self.start_behavior(Transport(self.world))
        while self.sleep(0.25):
            if transport.status.finished:
                raise BeehaveError(f"{self.path}: the transport responder ended "
                                   f"{transport.status.name}: {transport.error!r}")
            battery = self.blackboard.get(BATTERY_KEY)
            if not isinstance(battery, float):
                continue
            if battery < self.charge_below_pct:
                transport.refusing = f"battery at {battery:.0f} %"
                if battery < self.critical_pct or not transport.busy():
                    log.info("%s: battery %.0f %%: going to charge", self.path, battery)
                    self.manager.request_switch("charge")
                    return "charge"
        return "interrupted"


class StationLost(BeehaveError):
    """The reserved charging station went away or withdrew the reservation."""


class Charge(AgentBehavior):
    """Reserve the nearest free charging station, drive there, charge, release it."""

    def __init__(self, world: str = "factory", *, charged_pct: float = 90.0,
                 lease_s: float = 6.0, then: str = "work") -> None:
        self.world = world
        self.charged_pct = charged_pct
        self.lease_s = lease_s
        self.then = then
        self.station: str | None = None

    def _candidates(self) -> list[str]:
        places = site(self.world)
        x, y = (self.blackboard.get(k) for k in POSE_KEYS)
        here = (x, y) if isinstance(x, float) and isinstance(y, float) else (0.0, 0.0)
        found = []
        for info in self.agent.directory.search("charging"):
            station = info.properties("charging").get("station")
            if station in places.stations:
                found.append((places.path_length_m(here, places.stations[station].xy),
                              info.name))
        return [name for _, name in sorted(found)]

    def _ask(self, station: str, op: str) -> Any:
        return request(self.agent, station, {"op": op, "lease_s": self.lease_s},
                       protocol="charging", timeout_s=3.0)

    @classmethod
    def prepare_node(cls, node: Any) -> None:
        SpeedLimit.of(node)

    def run(self) -> str:
        if self.manager.node is not None:
            SpeedLimit.of(self.manager.node)
        try:
            while True:
                station = self._reserve()
                if station is None:
                    if not self.sleep(2.0):
                        return "interrupted"
                    continue
                try:
                    self._charge_at(station)
                    return self._done(station)
                except StationLost as exc:
                    log.warning("%s: %s; looking for another station", self.path, exc)
                    self.station = None
        finally:
            if self.station is not None:  # interrupted: let the others have it
                try:
                    self._ask(self.station, "release")
                except (AgentError, ProtocolFailed, NoReply, Interrupted):
                    pass  # its lease ends it anyway

    def _reserve(self) -> str | None:
        for name in self._candidates():
            try:
                self._ask(name, "reserve")
            except (ProtocolFailed, NoReply, AgentError) as exc:
                log.info("%s: %s refused: %s", self.path, name, exc)
                continue
            self.station = name
            return name
        return None

    def _charge_at(self, station: str) -> None:
        info = self.agent.directory.get(station)
        if info is None:
            raise StationLost(f"{station} left the directory")
        place = site(self.world).stations[info.properties("charging")["station"]]
        nav = self.start_action(Navigation(Goal(*place.xy, name=place.name), world=self.world,
                                           **_nav_options_charging(place.tolerance_m)))
        renewed = time.monotonic()
        try:
            while True:
                if not self.sleep(0.25):
                    raise Interrupted(f"{self.path} was interrupted")
                if time.monotonic() - renewed > self.lease_s / 3:
                    self._renew(station)
                    renewed = time.monotonic()
                if nav.status.finished:
                    if nav.status is not Status.SUCCEEDED:
                        raise BeehaveError(f"{self.path}: could not reach {place.name}: "
                                           f"{nav.error!r}")
                    battery = self.blackboard.get(BATTERY_KEY)
                    if isinstance(battery, float) and battery >= self.charged_pct:
                        return
        finally:
            if not nav.status.finished:  # heading for a station it lost: stop first
                nav.interrupt()
                nav.wait(5.0)

    def _renew(self, station: str) -> None:
        if self.agent.directory.get(station) is None:
            raise StationLost(f"{station} left the directory")
        try:
            self._ask(station, "renew")
        except ProtocolFailed as exc:
            raise StationLost(f"{station} withdrew the reservation: {exc}") from exc
        except NoReply as exc:
            raise StationLost(f"{station} does not answer: {exc}") from exc

    def _done(self, station: str) -> str:
        try:
            self._ask(station, "release")
        except (ProtocolFailed, NoReply, AgentError) as exc:
            log.info("%s: release at %s: %s (its lease ends it)", self.path, station, exc)
        self.station = None
        self.manager.request_switch(self.then)
        return self.then


def _nav_options_charging(tolerance_m: float) -> dict[str, Any]:
    # Into a station a robot wide: slow, and let the robot come close to walls.
    return {**_nav_options(tolerance_m), "speed_mps": 0.25}
