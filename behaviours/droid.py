"""Droid-style cooperation between MAVLink vehicles (after "Platform for Communication and
Coordination of Agents using the MAVLink Protocol": the Droid, DroidRover and DroidCopter
classes), written as beehave Behaviors over the agent layer.

- **Shared state.** :func:`vehicle_state` turns the MAVLink HALs' blackboard entries into
  the fleet state every agent publishes (:class:`beehave.agents.fleet.Fleet`): position
  (local and geodetic), velocity, battery, mode, armed, the top-level behaviour and the
  mission.
- **Send a mission** to another agent: :class:`SendMission` (FIPA request); the receiver
  runs :class:`MissionRequestResponder`, which checks the mission and flies it or refuses
  with the reason.
- **Follow** a leader from its shared state: :class:`FollowLeader` keeps ``distance_m``
  (± ``tolerance_m``) from it and holds still while the leader's state is stale or the gap
  is below ``safety_m``.
- **Help request / handover** (the DroidRover): :class:`RoverDroid` runs its mission
  watching for progress; blocked for ``stall_s`` it holds, asks the vehicles offering the
  ``mission`` service for bids on the remaining waypoints (contract net: the nearest
  wins), returns home meanwhile and reports how the handover ended.
- **Low battery** (the DroidCopter): :class:`CopterDroid` follows, bids for missions, and
  when its battery falls below ``battery_low_pct`` returns and lands, telling every peer.

Missions travel between agents as geodetic waypoints (``lat_deg``, ``lon_deg``, ``alt_m``
above home), so vehicles with different local origins understand each other.

Run a vehicle's robot with ``python -m behaviours.droid robots/config/rover.yaml``: it
builds the robot from the YAML, attaches the fleet to its managers and switches to the
``droid`` behaviour (see :func:`main`).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import Any

from beehave.action import Action
from beehave.agents.agent import AgentAction, AgentBehavior
from beehave.agents.fleet import Fleet, PeerState, fleet_of
from beehave.agents.message import Message, Performative
from beehave.agents.protocols import ContractNetResponder, RequestResponder, contract_net
from beehave.agents.protocols import request as fipa_request
from beehave.behavior import Behavior
from beehave.blackboard import Blackboard
from beehave.errors import (
    AgentError,
    ConfigError,
    Interrupted,
    MavlinkTimeout,
    MissionStalled,
    NoReply,
    ProtocolFailed,
)
from beehave.hal import check_duration_s
from beehave.logic import Logic
from behaviours.mavlink import MavlinkAction, RunMission, take_off
from hal.mavlink import COPTER, LocalFrame, MavlinkLink, Waypoint

log = logging.getLogger(__name__)

__all__ = ["CopterDroid", "FollowLeader", "Follower", "MissionRequestResponder", "MissionResponder",
           "ReturnHome", "RoverDroid", "SendMission", "VehicleTelemetry", "main",
           "vehicle_state"]

MISSION_SERVICE = "mission"
"""The directory service of vehicles that take over missions."""

TELEMETRY_HALS = ("mavlink_heartbeat", "mavlink_position", "mavlink_battery",
                  "mavlink_mission")


# ---- shared state ---------------------------------------------------------------------------

def _num(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else None


def vehicle_state(board: Blackboard, *, behavior: str | None = None) -> dict[str, Any]:
    """The fleet state of a MAVLink vehicle from its HALs' blackboard entries (JSON: a
    value that is missing, stale or not finite is None). ``mission_item`` is the vehicle's
    progress; behaviours add ``mission`` (what they are doing) with ``fleet.update``."""
    def get(key: str) -> Any:
        return None if board.is_stale(key) else board.get(key)

    return {
        "kind": get("vehicle/type"), "mode": get("vehicle/mode"),
        "armed": get("vehicle/armed"), "connected": bool(board.get("vehicle/connected")),
        "position": {"north_m": _num(get("position/north_m")),
                     "east_m": _num(get("position/east_m")),
                     "alt_m": _num(get("position/alt_m")),
                     "lat_deg": _num(get("position/lat_deg")),
                     "lon_deg": _num(get("position/lon_deg"))},
        "velocity": {"vn_mps": _num(get("position/vn_mps")),
                     "ve_mps": _num(get("position/ve_mps"))},
        "battery_pct": _num(get("battery/percentage")),
        "behavior": behavior,
        "mission_item": {"current": get("mission/current"), "reached": get("mission/reached")},
    }


class VehicleTelemetry(Logic):
    """Keeps the MAVLink HALs loaded (they fill the blackboard for the fleet state and the
    behaviours). ``hals``: their names (default: heartbeat, position, battery, mission)."""

    def __init__(self, hals: Sequence[str] = TELEMETRY_HALS) -> None:
        self.hal_names = list(hals)

    async def run(self) -> None:
        for name in self.hal_names:
            await self.hal(name)
        await asyncio.Event().wait()  # until switched away: the HALs stay loaded


def peer_position(peer: PeerState, frame: LocalFrame) -> tuple[float, float, float] | None:
    """A peer's (north_m, east_m, alt_m) in ``frame`` (from its geodetic position)."""
    pos = peer.state.get("position") or {}
    lat, lon = pos.get("lat_deg"), pos.get("lon_deg")
    if not isinstance(lat, int | float) or not isinstance(lon, int | float):
        return None
    north, east = frame.to_local(lat, lon)
    return north, east, float(pos.get("alt_m") or 0.0)


# ---- missions between agents --------------------------------------------------------------

def mission_content(link: MavlinkLink, waypoints: Sequence[Waypoint]) -> dict[str, Any]:
    """The content of a mission message: geodetic waypoints."""
    frame = link.frame()
    points = []
    for point in waypoints:
        lat, lon = frame.to_global(point.north_m, point.east_m)
        points.append({"lat_deg": lat, "lon_deg": lon, "alt_m": point.alt_m})
    return {"waypoints": points}


def check_mission(content: Any, *, max_waypoints: int = 100) -> str | None:
    """Why ``content`` is not a mission this vehicle can take (None: it is)."""
    if not isinstance(content, dict) or not isinstance(content.get("waypoints"), list):
        return "content must be {\"waypoints\": [{lat_deg, lon_deg, alt_m}, …]}"
    points = content["waypoints"]
    if not points:
        return "the mission has no waypoints"
    if len(points) > max_waypoints:
        return f"{len(points)} waypoints; at most {max_waypoints}"
    for i, p in enumerate(points):
        if not isinstance(p, dict) or any(_num(p.get(k)) is None
                                          for k in ("lat_deg", "lon_deg", "alt_m")):
            return f"waypoints[{i}] needs finite lat_deg, lon_deg and alt_m, got {p!r:.80}"
        if not (-90 <= p["lat_deg"] <= 90 and -180 <= p["lon_deg"] <= 180):
            return f"waypoints[{i}] is not on Earth: {p!r:.80}"
    return None


def local_waypoints(frame: LocalFrame, content: dict[str, Any], *,
                    min_alt_m: float = 0.0) -> list[Waypoint]:
    out = []
    for p in content["waypoints"]:
        north, east = frame.to_local(p["lat_deg"], p["lon_deg"])
        out.append(Waypoint(north, east, max(float(p["alt_m"]), min_alt_m)))
    return out


class FlyMission(RunMission):
    """:class:`~behaviours.mavlink.RunMission` of a mission received from another agent
    (geodetic waypoints, converted to this vehicle's frame when it runs)."""

    def __init__(self, content: dict[str, Any], *, min_alt_m: float = 0.0,
                 **link: Any) -> None:
        # Placeholders until the link (and so the frame) is known; replaced in perform.
        first = content["waypoints"][0]
        super().__init__([[0.0, 0.0, float(first["alt_m"])]], **link)
        self.content = content
        self.min_alt_m = min_alt_m

    def perform(self, link: MavlinkLink) -> dict[str, Any]:
        self.waypoints = local_waypoints(link.frame(), self.content, min_alt_m=self.min_alt_m)
        return super().perform(link)


class SendMission(AgentBehavior):
    """Ask ``receiver`` to fly ``waypoints`` (this vehicle's local frame, via
    ``connection``) with a FIPA request; the result is the receiver's report. Raises
    :class:`~beehave.errors.ProtocolFailed` with the reason when it refuses."""

    def __init__(self, receiver: str, waypoints: Sequence[Any], *, connection: str,
                 timeout_s: float = 300.0) -> None:
        from behaviours.mavlink import parse_waypoints

        self.receiver = receiver
        self.waypoints = parse_waypoints(list(waypoints))
        self.connection = connection
        self.timeout_s = timeout_s

    def run(self) -> Any:
        from hal.mavlink import open_link

        with open_link(self.connection) as link:
            link.wait_heartbeat(timeout_s=10.0)
            content = mission_content(link, self.waypoints)
        return fipa_request(self.agent, self.receiver, content, timeout_s=self.timeout_s)


class _MissionTaker:
    """What both mission responders share: check, stop what conflicts, fly."""

    connection: str
    min_alt_m: float
    min_battery_pct: float
    before_task: Callable[[], None] | None
    manager: Any

    def why_not(self, content: Any) -> str | None:
        reason = check_mission(content)
        if reason is not None:
            return reason
        battery = self.manager.blackboard.get("battery/percentage")
        if isinstance(battery, int | float) and battery < self.min_battery_pct:
            return f"battery at {battery:.0f} % (needs {self.min_battery_pct:.0f} %)"
        return None

    def fly(self, content: dict[str, Any]) -> Action:
        if self.before_task is not None:
            self.before_task()
        return FlyMission(content, min_alt_m=self.min_alt_m, connection=self.connection)


class MissionRequestResponder(_MissionTaker, RequestResponder):
    """Takes missions sent with :class:`SendMission`: refuses one that is malformed or
    when the battery is low (with the reason), else flies it and informs when done."""

    def __init__(self, *, connection: str, min_alt_m: float = 0.0,
                 min_battery_pct: float = 30.0,
                 before_task: Callable[[], None] | None = None) -> None:
        self.connection = connection
        self.min_alt_m = min_alt_m
        self.min_battery_pct = min_battery_pct
        self.before_task = before_task

    def refuse(self, message: Message) -> str | None:
        return self.why_not(message.content)

    def perform(self, task: Message) -> Action:
        return self.fly(task.content)


class MissionResponder(_MissionTaker, ContractNetResponder):
    """Bids for missions of vehicles that need help (service ``mission``): the cost is the
    distance to the mission's first waypoint; refuses (no proposal) when it cannot take
    it. ``properties``: registered with the service (e.g. ``{"flies": true}``)."""

    service = MISSION_SERVICE

    def __init__(self, *, connection: str, min_alt_m: float = 0.0,
                 min_battery_pct: float = 30.0, properties: dict[str, Any] | None = None,
                 before_task: Callable[[], None] | None = None) -> None:
        self.connection = connection
        self.min_alt_m = min_alt_m
        self.min_battery_pct = min_battery_pct
        self.properties = dict(properties or {})
        self.before_task = before_task
        self._missions: dict[str, Any] = {}

    def service_properties(self) -> dict[str, Any]:
        return self.properties

    def propose(self, cfp: Message) -> Any:
        reason = self.why_not(cfp.content)
        if reason is not None:
            log.info("%s: no bid for %s: %s", self.path, cfp.sender, reason)
            return None
        board = self.manager.blackboard
        lat, lon = board.get("position/lat_deg"), board.get("position/lon_deg")
        if not isinstance(lat, int | float) or not isinstance(lon, int | float):
            return None  # where am I? no bid without a position
        first = cfp.content["waypoints"][0]
        north, east = LocalFrame(lat, lon).to_local(first["lat_deg"], first["lon_deg"])
        # Keep only the missions of proposals still open (rejected or expired ones are
        # gone from the responder's ``proposals``): without this the dict only grows.
        self._missions = {cid: mission for cid, mission in self._missions.items()
                          if cid in self.proposals}
        self._missions[cfp.conversation_id] = cfp.content
        return {"cost": math.hypot(north, east), "kind": board.get("vehicle/type")}

    def perform(self, task: Message) -> Action:
        # The accept-proposal carries our bid; the mission is in the cfp we bid for.
        content = self._missions.pop(task.conversation_id, None)
        if content is None:
            raise ValueError(f"no mission known for conversation {task.conversation_id!r}")
        return self.fly(content)


# ---- follow -------------------------------------------------------------------------------

class FollowLeader(MavlinkAction):
    """Keep ``distance_m`` (± ``tolerance_m``) from ``leader``, from the leader's shared
    state (the fleet of this action's manager), in GUIDED.

    Every ``1 / rate_hz`` s: while the leader's state is stale, or the gap is below
    ``safety_m``, the vehicle holds where it is (``holding`` says why); while the leader
    stands and the gap is within the tolerance it holds too; otherwise it heads for the
    point ``distance_m`` from the leader on the line towards itself, shifted by the
    leader's velocity × ``lead_s`` (where the leader will be). The leader's position is
    carried forward by its velocity over the state's age (at most ``MAX_EXTRAPOLATION_S``):
    a state that arrives late on a loaded host or network still says where the leader is.
    A Copter takes off to ``alt_m`` first and follows at that altitude. Runs until
    interrupted; with
    ``give_up_s`` it fails once the leader has been stale that long. From the first fresh
    state of the leader until the action ends, this vehicle's fleet state says
    ``"following": leader`` (a leader with ``followers`` waits for it before it sets off,
    see :class:`RoverDroid`). Its attributes ``min_gap_m`` and ``holding`` are for tests
    and pictures."""

    MAX_EXTRAPOLATION_S = 1.0
    """The longest a leader's state is carried forward by its velocity."""
    lockstep = True  # a control loop: under sim time the simulator waits for each period
    FRESH_PERIODS = 1.5
    """In lockstep, a leader state older than this many periods (sim time) is waited for
    (see :meth:`_fresh_peer`)."""
    FRESH_WAIT_S = 0.8
    """In lockstep, how long (wall) a period waits for the leader to make progress: a
    period whose leader state is late in sim time waits (the simulation held) while newer
    states keep coming, and goes on with what it has once none came for this long (the
    leader's process is gone or stuck). A leader that stayed silent through such a wait is
    not waited for again until it is heard."""
    MAX_FRESH_WAIT_S = 10.0
    """In lockstep, the longest (wall) one period waits for a leader that makes progress
    but does not catch up."""
    HOLD_REFRESH_S = 0.25
    """While a period waits, its hold on the simulation is announced again this often
    (wall), well inside the simulator's lockstep timeout (1 s): the wait is the control
    loop's own, not a loop that stopped answering."""

    def __init__(self, leader: str, *, distance_m: float = 2.0, tolerance_m: float = 0.2,
                 safety_m: float = 1.0, alt_m: float = 2.5, rate_hz: float = 10.0,
                 give_up_s: float | None = None, lead_s: float = 0.6,
                 **link: Any) -> None:
        super().__init__(**link)
        if not 0 < safety_m < distance_m:
            raise ConfigError(f"FollowLeader: need 0 < safety_m < distance_m, got "
                              f"safety_m={safety_m}, distance_m={distance_m}")
        self.leader = leader
        self.distance_m = distance_m
        self.tolerance_m = tolerance_m
        self.safety_m = safety_m
        self.alt_m = alt_m
        self.period_s = 1.0 / rate_hz
        self.give_up_s = give_up_s
        self.lead_s = lead_s
        self.min_gap_m = math.inf
        self.holding: str | None = None
        # In lockstep: the leader's seq when the last wait for it heard nothing newer (that
        # state is not waited on again), None while the leader is heard.
        self._silent_seq: int | None = None

    def perform(self, link: MavlinkLink) -> None:
        fleet = fleet_of(self.manager)
        frame = link.frame()
        if link.require_kind() == COPTER and link.local_position()[2] < 0.3:
            take_off(self, link, self.alt_m, 30.0)
        if link.mode != "GUIDED":
            link.set_mode("GUIDED")
        if not link.armed:
            link.arm(True)
        alt = self.alt_m if link.kind == COPTER else None
        try:
            self._follow(link, fleet, frame, alt)
        finally:
            fleet.update(following=None)

    def _follow(self, link: MavlinkLink, fleet: Fleet, frame: LocalFrame,
                alt: float | None) -> None:
        stale_since: float | None = None
        announced = False
        while True:
            self.check_alive(link, f"following {self.leader!r}")
            here = link.local_position()
            peer = self._fresh_peer(fleet)
            where = None if peer is None or peer.stale else peer_position(peer, frame)
            if where is None:
                now = self.manager.clock.now()  # sim time under use_sim_time
                stale_since = stale_since if stale_since is not None else now
                self._hold(link, here, alt,
                           f"no state of {self.leader!r} yet" if peer is None else
                           f"the state of {self.leader!r} is stale ({peer.age_s:.1f} s old)"
                           if peer.stale else f"{self.leader!r} has no position yet")
                if self.give_up_s is not None and now - stale_since > self.give_up_s:
                    raise NoReply(f"{self.path}: no fresh state of {self.leader!r} for "
                                  f"{self.give_up_s} s")
            else:
                stale_since = None
                if not announced:  # a leader that waits for its followers may start now
                    fleet.update(following=self.leader)
                    announced = True
                velocity = peer.state.get("velocity") or {} if peer is not None else {}
                vn = _num(velocity.get("vn_mps")) or 0.0
                ve = _num(velocity.get("ve_mps")) or 0.0
                age = min(peer.age_s, self.MAX_EXTRAPOLATION_S) if peer is not None else 0.0
                where = (where[0] + vn * age, where[1] + ve * age, where[2])
                gap = math.hypot(here[0] - where[0], here[1] - where[1])
                self.min_gap_m = min(self.min_gap_m, gap)
                if gap < self.safety_m:
                    self._hold(link, here, alt, f"gap {gap:.2f} m below the safety distance "
                                                f"{self.safety_m} m")
                elif abs(gap - self.distance_m) <= self.tolerance_m \
                        and math.hypot(vn, ve) < 0.1:
                    self._hold(link, here, alt, None)  # in place, and the leader stands
                else:
                    # Track continuously while the leader moves (holding inside the band
                    # would stop and go), aiming where the leader will be: a position
                    # controller chasing a moving point lags it by speed / gain otherwise.
                    un, ue = (here[0] - where[0]) / gap, (here[1] - where[1]) / gap
                    self.holding = None
                    link.goto_local(where[0] + un * self.distance_m + vn * self.lead_s,
                                    where[1] + ue * self.distance_m + ve * self.lead_s, alt)
            self.pause(self.period_s)

    def _fresh_peer(self, fleet: Fleet) -> PeerState | None:
        """The leader's latest state. In lockstep (the simulation waits for this loop, not
        for the leader's robot), a state older than :attr:`FRESH_PERIODS` periods of sim
        time is waited for, the simulation held meanwhile, as long as the leader makes
        progress (see :attr:`FRESH_WAIT_S`): a simulation faster than the leader's process
        must not make the leader look stale or far behind where it is. (Going on with a stale state,
        the follower held while the simulated leader drove on, and fell up to 2.7 m
        behind in stress runs.)"""
        peer = fleet.get(self.leader)
        if self._lockstep is None or peer is None \
                or peer.age_s <= self.FRESH_PERIODS * self.period_s:
            self._silent_seq = None
            return peer
        if peer.seq == self._silent_seq:
            return peer
        start = now = time.monotonic()
        progress_by = now + self.FRESH_WAIT_S
        refresh_at = now + self.HOLD_REFRESH_S
        held_s = self.manager.clock.now()
        while not self.interrupted:
            time.sleep(0.002)
            now = time.monotonic()
            newer = fleet.get(self.leader)
            if newer is not None and newer.seq != peer.seq:
                peer, progress_by = newer, now + self.FRESH_WAIT_S
                if peer.age_s <= self.FRESH_PERIODS * self.period_s:
                    break
            if now >= progress_by:  # silent: go on with what there is
                self._silent_seq = peer.seq
                log.info("%s: no newer state of %r for %g s (wall); going on with one "
                         "%.2f s old", self.path, self.leader, self.FRESH_WAIT_S, peer.age_s)
                return peer
            if now - start >= self.MAX_FRESH_WAIT_S:
                break
            if now >= refresh_at:
                refresh_at = now + self.HOLD_REFRESH_S
                self._hold_at(held_s)
        self._silent_seq = None
        return peer

    def _hold(self, link: MavlinkLink, here: tuple[float, float, float], alt: float | None,
              why: str | None) -> None:
        if why != self.holding and why is not None:
            log.info("%s: holding: %s", self.path, why)
        self.holding = why
        link.goto_local(here[0], here[1], alt)


class Follower(Behavior):
    """A vehicle that only follows: :class:`FollowLeader` of ``leader`` until switched away
    (the paper's follow mode for any Droid, a rover as well as a copter). It fails with
    the action's error (a lost link, ``give_up_s`` of stale leader state); its result,
    once interrupted, is the closest gap it saw."""

    def __init__(self, *, connection: str, leader: str, distance_m: float = 2.0,
                 tolerance_m: float = 0.2, safety_m: float = 1.0, alt_m: float = 2.5,
                 give_up_s: float | None = None, lead_s: float = 0.6) -> None:
        self.follow = FollowLeader(leader, distance_m=distance_m, tolerance_m=tolerance_m,
                                   safety_m=safety_m, alt_m=alt_m, give_up_s=give_up_s,
                                   lead_s=lead_s, connection=connection)

    def run(self) -> dict[str, Any]:
        follow = self.start_action(self.follow)
        follow.wait()
        if follow.error is not None:
            raise follow.error
        return {"min_gap_m": follow.min_gap_m}


# ---- return home --------------------------------------------------------------------------

class ReturnHome(MavlinkAction):
    """RTL, and wait until the vehicle is home: a Rover holds there, a Copter has landed
    and disarmed (ArduPilot's RTL does that)."""

    def __init__(self, *, timeout_s: float = 180.0, **link: Any) -> None:
        super().__init__(**link)
        self.timeout_s = timeout_s

    def perform(self, link: MavlinkLink) -> str:
        link.set_mode("RTL")
        deadline = time.monotonic() + self.timeout_s
        while True:
            done = (not link.armed) if link.kind == COPTER else link.mode == "HOLD"
            if done:
                return link.mode
            if time.monotonic() > deadline:
                raise MavlinkTimeout(f"{self.path}: not home after {self.timeout_s} s")
            self.check_alive(link, "returning home")
            self.pause(0.1)


class _Inform(AgentAction):
    """Tell every other agent of the directory something (one inform each; best effort)."""

    def __init__(self, content: dict[str, Any]) -> None:
        self.content = content

    def run(self) -> list[str]:
        names = [a.name for a in self.agent.directory.agents() if a.name != self.agent.name]
        if names:
            message = Message(performative=Performative.INFORM, sender=self.agent.name,
                              receivers=names, conversation_id=f"{self.agent.name}/news-"
                              f"{time.monotonic_ns()}", content=self.content)
            try:
                self.agent.send(message, timeout_s=1.0)
            except AgentError as exc:
                log.warning("%s: %s", self.path, exc)
        return names


# ---- the two vehicles ---------------------------------------------------------------------

def _not_following(peer: PeerState | None, leader: str) -> str | None:
    """Why ``peer`` does not (yet) count as following ``leader``; None when it does."""
    if peer is None:
        return "never heard"
    if peer.stale:
        return f"its state is stale ({peer.age_s:.1f} s old)"
    following = peer.state.get("following")
    if following != leader:
        return f"following {following!r}" if following is not None else "not following"
    return None


class RoverDroid(AgentBehavior):
    """The DroidRover: run ``waypoints`` (local NED, metres); if it makes no progress for
    ``stall_s`` s, hand the remaining waypoints to the best bidder for the ``mission``
    service (at ``helper_alt_m``) and return home. The result says how it ended:
    ``{"status": "completed" | "handed-over", "awardee", "remaining", "home"}``; when no
    vehicle takes the mission it still goes home, then fails with
    :class:`~beehave.errors.ProtocolFailed` naming why. ``speed_mps``, when given, is set
    as the vehicle's ``WP_SPEED`` parameter (PARAM_SET) before the mission starts.

    ``followers`` (agent names): before it sets off, the rover waits until each of them
    says in its fleet state that it follows this rover and has heard it (``"following"``,
    set by :class:`FollowLeader`), as a guide waits for the group: a follower that has
    not yet discovered its leader over DDS would hold while the leader drives away. After
    ``followers_timeout_s`` (the behaviour's clock) it sets off anyway and logs which
    follower was missing."""

    WAIT_PERIOD_S = 0.05
    """How often the fleet state is looked at while waiting for the followers."""

    def __init__(self, *, connection: str, waypoints: Sequence[Any], stall_s: float = 3.0,
                 helper_alt_m: float = 3.0, reply_by_s: float = 2.0,
                 done_timeout_s: float = 300.0, speed_mps: float | None = None,
                 followers: Sequence[str] = (), followers_timeout_s: float = 30.0) -> None:
        from behaviours.mavlink import parse_waypoints

        if followers is None or isinstance(followers, str) \
                or not isinstance(followers, Sequence) \
                or not all(isinstance(f, str) and f for f in followers):
            raise ConfigError(f"RoverDroid: followers must be a list of agent names, got "
                              f"{followers!r}")
        self.followers = list(followers)
        self.followers_timeout_s = check_duration_s("RoverDroid: followers_timeout_s",
                                                    followers_timeout_s)
        self.connection = connection
        self.waypoints = parse_waypoints(list(waypoints))
        self.stall_s = stall_s
        self.helper_alt_m = helper_alt_m
        self.reply_by_s = reply_by_s
        self.done_timeout_s = done_timeout_s
        self.speed_mps = speed_mps

    def _report(self, **mission: Any) -> None:
        try:
            self.fleet.update(mission=mission)
        except ConfigError:
            pass  # no fleet: nobody to tell

    def run(self) -> dict[str, Any]:
        from hal.mavlink import open_link

        # Held for the whole behaviour: its actions share it, and it stays up between them.
        with open_link(self.connection) as link:
            link.wait_heartbeat(timeout_s=10.0)
            return self._run(link)

    def _wait_for_followers(self) -> None:
        if not self.followers:
            return
        me = self.agent.name
        if me in self.followers:
            raise ConfigError(f"{self.path}: followers names this rover itself ({me!r}); "
                              f"name the agents that follow it")
        try:
            fleet = self.fleet
        except ConfigError as exc:
            raise ConfigError(f"{self.path}: followers {self.followers} are waited for in "
                              f"the fleet state, and this manager has none: {exc}") from exc
        # The run clock stands while the manager is paused: a pause does not use the wait up.
        clock = self.manager.run_clock
        self._report(status="waiting for followers", followers=self.followers)
        deadline = clock.now() + self.followers_timeout_s
        while True:
            missing = {name: _not_following(fleet.get(name), me) for name in self.followers}
            missing = {name: why for name, why in missing.items() if why is not None}
            if not missing:
                log.info("%s: every follower follows (%s); setting off", self.path,
                         ", ".join(self.followers))
                return
            if clock.now() >= deadline:
                log.warning("%s: setting off without %s after %g s", self.path,
                            "; ".join(f"{name!r} ({why})" for name, why in missing.items()),
                            self.followers_timeout_s)
                return
            if not self.sleep(self.WAIT_PERIOD_S):
                raise Interrupted(f"{self.path}: interrupted while waiting for followers")

    def _run(self, link: MavlinkLink) -> dict[str, Any]:
        if self.speed_mps is not None:
            link.set_param("WP_SPEED", self.speed_mps)
        self._wait_for_followers()
        self._report(status="running", waypoints=len(self.waypoints))
        mission = self.start_action(RunMission(self.waypoints, stall_s=self.stall_s,
                                               connection=self.connection))
        mission.wait()
        if mission.status.name == "SUCCEEDED":
            self._report(status="completed")
            return {"status": "completed", "awardee": None, "remaining": [], "home": False}
        error = mission.error
        if not isinstance(error, MissionStalled):
            raise error if error is not None else Interrupted(f"{self.path}: interrupted")
        remaining = [Waypoint(w.north_m, w.east_m, self.helper_alt_m)
                     for w in error.remaining if isinstance(w, Waypoint)]
        self._report(status="blocked", remaining=len(remaining))
        log.info("%s: blocked at %s; asking for help with %d waypoint(s)", self.path,
                 error.position, len(remaining))
        content = mission_content(link, remaining)
        home = self.start_action(ReturnHome(connection=self.connection))
        award = None
        failure: Exception | None = None
        try:
            award = contract_net(self.agent, MISSION_SERVICE, content,
                                 reply_by_s=self.reply_by_s,
                                 done_timeout_s=self.done_timeout_s)
        except ProtocolFailed as exc:
            failure = exc
            self._report(status="handover failed", reason=str(exc)[:200])
            log.warning("%s: nobody took the mission: %s", self.path, exc)
        home.wait()
        if failure is not None:
            raise ProtocolFailed(f"{self.path}: blocked with {len(remaining)} waypoint(s) "
                                 f"left and no vehicle took them ({failure}); the rover "
                                 f"went home ({home.status.name})") from failure
        assert award is not None
        self._report(status="handed-over", awardee=award.awardee)
        return {"status": "handed-over", "awardee": award.awardee,
                "remaining": [w.as_dict() for w in remaining],
                "home": home.status.name == "SUCCEEDED"}


class CopterDroid(AgentBehavior):
    """The DroidCopter: follows ``follow`` (a leader's agent name, or None), bids for and
    flies the missions of vehicles that need help (and takes missions sent to it), and
    when its battery drops below ``battery_low_pct`` returns and lands, telling every
    peer (an inform ``{"event": "battery-low", …}``)."""

    def __init__(self, *, connection: str, follow: str | None = None,
                 distance_m: float = 2.0, safety_m: float = 1.0, alt_m: float = 2.5,
                 battery_low_pct: float = 25.0, min_battery_pct: float = 40.0) -> None:
        self.connection = connection
        self.leader = follow
        self.distance_m = distance_m
        self.safety_m = safety_m
        self.alt_m = alt_m
        self.battery_low_pct = battery_low_pct
        self.min_battery_pct = min_battery_pct
        self._follow: FollowLeader | None = None
        self._lock = threading.Lock()

    def _stop_follow(self) -> None:
        with self._lock:
            follow, self._follow = self._follow, None
        if follow is not None:
            follow.interrupt()
            follow.wait(5.0)

    def run(self) -> dict[str, Any]:
        responders = [
            self.start_behavior(MissionResponder(
                connection=self.connection, min_alt_m=self.alt_m,
                min_battery_pct=self.min_battery_pct, properties={"flies": True},
                before_task=self._stop_follow)),
            self.start_behavior(MissionRequestResponder(
                connection=self.connection, min_alt_m=self.alt_m,
                min_battery_pct=self.min_battery_pct, before_task=self._stop_follow)),
        ]
        if self.leader is not None:
            with self._lock:
                self._follow = self.start_action(FollowLeader(
                    self.leader, distance_m=self.distance_m, safety_m=self.safety_m,
                    alt_m=self.alt_m, connection=self.connection))
        while True:
            battery = self.blackboard.get("battery/percentage")
            if isinstance(battery, int | float) and battery < self.battery_low_pct:
                break
            if not self.sleep(0.5):
                return {"status": "interrupted"}
        log.warning("%s: battery at %.0f %%: returning to land", self.path, battery)
        self._stop_follow()
        for responder in responders:
            responder.interrupt()
            responder.wait(5.0)
        told = self.start_action(_Inform({"event": "battery-low", "battery_pct": battery,
                                          "returning": True}))
        home = self.start_action(ReturnHome(connection=self.connection), preempt=True)
        told.wait(5.0)
        home.wait()
        return {"status": "battery-low", "battery_pct": battery, "told": told.result,
                "landed": home.status.name == "SUCCEEDED"}


# ---- a vehicle's robot process ----------------------------------------------------------------

def _connections(tree: Any) -> set[str]:
    """Every value of a ``connection`` key in a parsed YAML tree."""
    if isinstance(tree, dict):
        found = {v for k, v in tree.items() if k == "connection" and isinstance(v, str)}
        for value in tree.values():
            found |= _connections(value)
        return found
    if isinstance(tree, list):
        return set().union(*(_connections(v) for v in tree)) if tree else set()
    return set()


def _replace(tree: Any, old: str, new: str) -> Any:
    if isinstance(tree, dict):
        return {k: _replace(v, old, new) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_replace(v, old, new) for v in tree]
    return new if tree == old else tree


def main(argv: list[str] | None = None) -> int:
    """``python -m behaviours.droid CONFIG.yaml [--connection URL] [--name AGENT]
    [--behavior NAME] [--duration-s N]``: run one vehicle's robot (both managers, its agent
    and fleet) until SIGINT/SIGTERM, the duration, or the behaviour ends. ``--connection``
    replaces the MAVLink connection the YAML names (every ``connection:``), ``--name`` its
    agent name. Prints ``RESULT {json}`` when the behaviour ends. Exit code 0 when it
    succeeded (or still runs at the end), 1 when it failed, 2 for a bad configuration."""
    import yaml

    from beehave.config import parse_config
    from beehave.robot import Robot

    parser = argparse.ArgumentParser(prog="python -m behaviours.droid")
    parser.add_argument("config")
    parser.add_argument("--connection")
    parser.add_argument("--name")
    parser.add_argument("--behavior", default="droid")
    parser.add_argument("--duration-s", type=float, default=None)
    parser.add_argument("--fleet-rate-hz", type=float, default=10.0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    sys.setswitchinterval(0.001)
    path = Path(args.config)
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    if not isinstance(data, dict):
        print(f"{path}: expected a robot configuration mapping", file=sys.stderr)
        return 2
    if args.connection:
        found = _connections(data)
        if len(found) != 1:
            print(f"{path}: --connection replaces the one MAVLink connection the file "
                  f"names; it names {sorted(found) or 'none'}", file=sys.stderr)
            return 2
        data = _replace(data, found.pop(), args.connection)
    if args.name and isinstance(data.get("agent"), dict):
        data["agent"]["name"] = args.name
    try:
        config = parse_config(data, source=str(path))
        robot = Robot(config)
    except Exception as exc:  # ConfigError, or anything building the robot raised
        print(f"{path}: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    code = 0
    with robot:
        assert robot.high is not None and robot.low is not None and robot.agent is not None
        high, low = robot.high, robot.low
        fleet = Fleet(robot.agent, rate_hz=args.fleet_rate_hz, state=lambda: vehicle_state(
            low.blackboard, behavior=high.current))
        fleet.attach(high)
        fleet.attach(low)
        try:
            behavior = high.switch(args.behavior)
            print(f"droid {robot.agent.name}: running {args.behavior!r}", flush=True)
            deadline = None if args.duration_s is None else time.monotonic() + args.duration_s
            while not stop.is_set() and not behavior.wait(0.2):
                if deadline is not None and time.monotonic() > deadline:
                    break
            outcome = {"agent": robot.agent.name, "status": behavior.status.name,
                       "result": behavior.result,
                       "error": None if behavior.error is None else str(behavior.error)}
            print("RESULT " + json.dumps(outcome, default=repr), flush=True)
            code = 1 if behavior.status.name == "FAILED" else 0
        finally:
            fleet.close()
    return code


if __name__ == "__main__":
    sys.exit(main())
