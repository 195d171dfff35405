"""Actions for MAVLink vehicles (ArduPilot Rover and Copter): arm, modes, take-off and
landing, GUIDED goals, and missions with the full upload protocol.

::

    class Survey(Behavior):
        def run(self) -> None:
            link = "udp:127.0.0.1:14550"
            self.start_action(RunMission(connection=link, waypoints=[[10, 0, 5], [10, 10, 5]]
                                         )).wait()

Every action opens (shares) the link of its ``connection`` (:func:`hal.mavlink.open_link`),
so it runs beside the MAVLink HALs of the same process on one socket. All of them hold the
action type ``"vehicle"``: one thing at a time commands the vehicle.

**Safe state.** An action that ends without success (interrupted, failed, STUCK, or the
vehicle was lost) sends the vehicle its hold mode once — HOLD for a Rover, BRAKE for a
Copter (:data:`hal.mavlink.HOLD_MODE`) — without waiting for the answer.

**Pause.** ``hl.pause()`` puts the vehicle in its hold mode and keeps the action's place
(:meth:`MavlinkAction.on_pause`); ``hl.resume()`` gives it the mode it had back (AUTO: the
mission goes on at its current waypoint, as ArduPilot does; GUIDED: the target is sent
again). The other way round, a ground station that puts a vehicle in its hold mode while a
mission or a GUIDED goal of beehave drives it pauses the robot (``hl.request_pause()``):
beehave stops fighting the operator; resume it through beehave (ROS 2, the web page,
``hl.resume()``), which sets the mode back.

**Lost heartbeat.** Every wait ends with :class:`~beehave.errors.VehicleLost` when the
heartbeat stops for the link's ``heartbeat_timeout_s``: the action FAILS (and tries its
safe state, which reaches the vehicle if the link comes back).

**Sim time and lockstep.** Under ``use_sim_time`` every wait of these actions
(:meth:`MavlinkAction.pause`) lasts simulated seconds. An action whose class sets
``lockstep = True`` (:class:`~behaviours.droid.FollowLeader`, a control loop) also asks the
simulator on ``/lockstep`` to hold where each pause ends until it has answered, as the
driving actions do (``docs/simulation.md``): a simulation faster than real time, or a
loaded host, never outruns its loop. The vehicle's own autopilot work (AUTO, RTL) runs in
the simulation and needs no holding.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Sequence
from typing import Any

from beehave.action import Action
from beehave.clock import SimClock
from beehave.errors import (
    ConfigError,
    Interrupted,
    MavlinkTimeout,
    MissionStalled,
    UnknownMode,
    VehicleLost,
)
from behaviours.actions import LockstepLine  # one /lockstep line per node, shared
from hal.mavlink import (
    COPTER,
    HOLD_MODE,
    KEY_FILE_ENV,
    ROVER,
    MavlinkLink,
    Waypoint,
    mode_names,
    open_link,
)

log = logging.getLogger(__name__)

__all__ = ["Arm", "Disarm", "GotoPosition", "Land", "MavlinkAction", "RunMission", "SetMode",
           "Takeoff", "UploadMission", "parse_waypoints"]


def parse_waypoints(waypoints: object, *, where: str = "waypoints") -> list[Waypoint]:
    """A list of :class:`~hal.mavlink.Waypoint` from dicts or ``[north, east, alt]`` lists;
    ConfigError names the bad entry."""
    if not isinstance(waypoints, list | tuple) or not waypoints:
        raise ConfigError(f"{where}: expected a non-empty list of waypoints, got "
                          f"{waypoints!r:.80}")
    return [Waypoint.parse(w, where=f"{where}[{i}]") for i, w in enumerate(waypoints)]


class MavlinkAction(Action):
    """Base of the MAVLink actions: opens the link, runs :meth:`perform`, holds the vehicle
    in the safe state. Parameters every action takes: ``connection`` (a pymavlink
    connection string), ``system_id`` (None: the first autopilot heard),
    ``heartbeat_timeout_s``, ``connect_timeout_s`` (how long to wait for the first
    heartbeat) and ``signing_key_file`` (MAVLink 2 signing, see
    :class:`hal.mavlink.MavlinkLink`; default ``BEEHAVE_MAVLINK_KEY_FILE``; None on a link
    a HAL opened already: that link's signing)."""

    action_type = "vehicle"
    lockstep = False
    """True: under sim time, hold the simulation where each :meth:`pause` ends until this
    action has answered (a control loop); see the module doc."""
    _lockstep: LockstepLine | None = None

    def __init__(self, *, connection: str, system_id: int | None = None,
                 heartbeat_timeout_s: float = 3.0, connect_timeout_s: float = 5.0,
                 signing_key_file: str | None = None) -> None:
        self.connection = connection
        self.signing_key_file = signing_key_file or os.environ.get(KEY_FILE_ENV) or None
        self.system_id = system_id
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.connect_timeout_s = connect_timeout_s
        self._link: MavlinkLink | None = None
        self.pause_held = False  # paused: in the hold mode, run() keeps its place
        self._mode_before_pause: str | None = None
        #: The mode this action drives the vehicle in (what a resume gives back; the
        #: heartbeat's mode may lag a change just made).
        self.drive_mode: str | None = None
        self._held = threading.Event()  # run() asked for the hold mode since the pause

    def perform(self, link: MavlinkLink) -> Any:
        """Do the action's work on ``link`` (alive); the return value is the result."""
        raise NotImplementedError

    def run(self) -> Any:
        link = self._link = open_link(self.connection, system_id=self.system_id,
                                      heartbeat_timeout_s=self.heartbeat_timeout_s,
                                      signing_key_file=self.signing_key_file)
        ok = False
        try:
            self._open_lockstep()
            self._wait_alive(link)
            result = self.perform(link)
            ok = not self.interrupted
            return result
        finally:
            self._let_go()
            if ok:  # safe_state (which still needs the link) is not called after success
                self._link = None
                link.close()

    def _wait_alive(self, link: MavlinkLink) -> None:
        deadline = time.monotonic() + self.connect_timeout_s
        while not link.alive:
            if time.monotonic() > deadline:
                raise VehicleLost(f"{self.path}: no heartbeat from {link.describe()} within "
                                  f"{self.connect_timeout_s} s")
            self.pause(0.05)

    def pause(self, seconds: float) -> None:
        """Sleep, raising Interrupted when interrupted (ends the action's wait loops). In
        lockstep the simulator holds where the pause ends until the next pause or the
        end of the action. While the robot is paused, it first holds the vehicle, then
        stands still."""
        self._hold_if_paused()
        clock = self.manager.clock
        if self._lockstep is not None and isinstance(clock, SimClock):
            with clock.announcing(self._hold_at):
                awake = self.sleep(seconds)
        else:
            awake = self.sleep(seconds)
        if not awake:
            raise Interrupted(f"{self.path}: interrupted")

    def _open_lockstep(self) -> None:
        node = self.manager.node
        if not self.lockstep or node is None or not isinstance(self.manager.clock, SimClock):
            return
        line = LockstepLine.of(node)
        self._lockstep = line
        # No hold before the first pause: the set-up (mode, arming) waits for the vehicle's
        # heartbeat, which a held simulation still sends, but on wall time.
        line.wait_matched(lambda: self.interrupted)

    def _hold_at(self, until_s: float | None) -> None:
        line = self._lockstep
        if line is not None:
            line.announce(self, until_s)

    def _let_go(self) -> None:
        if self._lockstep is None:
            return
        try:
            self._hold_at(None)
        except Exception:  # the node is gone: the simulator's lockstep timeout lets go
            log.debug("%s: could not let the simulation go", self.path, exc_info=True)
        self._lockstep = None

    def check_alive(self, link: MavlinkLink, what: str) -> None:
        if not link.alive:
            raise VehicleLost(f"{self.path}: heartbeat of {link.describe()} lost while "
                              f"{what}")

    def on_pause(self) -> None:
        """``hl.pause()``: the vehicle to its hold mode (HOLD for a Rover, BRAKE for a
        Copter); ``run`` keeps its place (its waits stand still) until :meth:`on_resume`
        gives the vehicle back the mode this action drives it in.

        A command ``run`` had under way (a mode change, the mission start) could undo
        the hold when it completes: ``run`` asks for the hold mode once more at its next
        wait while paused."""
        if self._mode_before_pause is None:
            self._mode_before_pause = self.drive_mode
        self._held.clear()
        self.pause_held = True
        self._hold_now()

    def _hold_if_paused(self) -> None:
        if self.pause_held and not self._held.is_set():
            self._held.set()
            self._hold_now()

    def _hold_now(self) -> None:
        link = self._link
        if link is not None and link.alive and link.kind is not None:
            link.request_mode(HOLD_MODE[link.kind])

    def on_resume(self) -> None:
        """``hl.resume()``: the mode the vehicle had before the pause, back."""
        link, mode = self._link, self._mode_before_pause
        self._mode_before_pause = None
        try:
            if link is not None and link.alive and mode is not None:
                link.set_mode(mode)
        finally:
            self.pause_held = False

    def operator_held(self, link: MavlinkLink, *, resume_in: str) -> bool:
        """Whether someone else (a ground station) put the vehicle in its hold mode; if so,
        the robot is paused (see the module docstring), ``resume_in`` is the mode the
        resume gives back, and True is returned."""
        if self.pause_held or link.kind is None or link.mode != HOLD_MODE[link.kind]:
            return False
        if self._mode_before_pause is None:  # once: the pause takes effect in a moment
            log.warning("%s: %s was put in %s from outside; pausing the robot (resume it "
                        "through beehave to go on)", self.path, link.describe(), link.mode)
            self._mode_before_pause = resume_in
            self.manager.request_pause()
        return True

    def safe_state(self) -> None:
        link, self._link = self._link, None
        if link is None:
            return
        try:
            if link.alive and link.kind is not None:
                link.request_mode(HOLD_MODE[link.kind])
        except Exception as exc:  # best effort: the vehicle may be gone
            log.warning("%s: could not put %s in its hold mode: %r", self.path,
                        link.describe(), exc)
        finally:
            link.close()


class Arm(MavlinkAction):
    """Arm the motors (waits until the heartbeat shows it)."""

    def perform(self, link: MavlinkLink) -> None:
        link.arm(True)


class Disarm(MavlinkAction):
    """Disarm the motors (a Copter in the air refuses: land first)."""

    def perform(self, link: MavlinkLink) -> None:
        link.arm(False)


class SetMode(MavlinkAction):
    """Switch the flight mode, by ArduPilot name (``HOLD``, ``GUIDED``, ``AUTO``, ``RTL``…).

    A name neither firmware knows is refused when the action is made; one this vehicle's
    firmware lacks (``LAND`` on a Rover) when it runs — both with
    :class:`~beehave.errors.UnknownMode` listing the valid modes."""

    def __init__(self, mode: str, **link: Any) -> None:
        super().__init__(**link)
        known = {**mode_names(ROVER), **mode_names(COPTER)}
        if not isinstance(mode, str) or mode.upper() not in known:
            raise UnknownMode(str(mode), known, vehicle="Rover or Copter")
        self.mode = mode.upper()

    def perform(self, link: MavlinkLink) -> str:
        link.set_mode(self.mode)
        return self.mode


class Takeoff(MavlinkAction):
    """Copter: GUIDED, arm, take off to ``alt_m`` above home and wait until it is there
    (within 10 %)."""

    def __init__(self, alt_m: float, *, timeout_s: float = 30.0, **link: Any) -> None:
        super().__init__(**link)
        if not (isinstance(alt_m, int | float) and 0 < alt_m <= 100):
            raise ConfigError(f"Takeoff: alt_m must be 0–100 m, got {alt_m!r}")
        self.alt_m = float(alt_m)
        self.timeout_s = timeout_s

    def perform(self, link: MavlinkLink) -> float:
        return take_off(self, link, self.alt_m, self.timeout_s)


def take_off(action: MavlinkAction, link: MavlinkLink, alt_m: float, timeout_s: float) -> float:
    if link.require_kind() != COPTER:
        raise ConfigError(f"{action.path}: {link.describe()} is a {link.kind}; only a "
                          f"copter takes off")
    link.set_mode("GUIDED")
    if not link.armed:
        link.arm(True)
    link.takeoff(alt_m)
    deadline = time.monotonic() + timeout_s
    while True:
        alt = link.local_position()[2]
        if alt >= 0.9 * alt_m:
            return alt
        if time.monotonic() > deadline:
            raise MavlinkTimeout(f"{action.path}: climbed to {alt:.1f} m of {alt_m} m in "
                                 f"{timeout_s} s")
        action.check_alive(link, "taking off")
        action.pause(0.1)


class Land(MavlinkAction):
    """Copter: LAND, and wait until it has landed and disarmed."""

    def __init__(self, *, timeout_s: float = 60.0, **link: Any) -> None:
        super().__init__(**link)
        self.timeout_s = timeout_s

    def perform(self, link: MavlinkLink) -> None:
        link.set_mode("LAND")
        deadline = time.monotonic() + self.timeout_s
        while link.armed:
            if time.monotonic() > deadline:
                raise MavlinkTimeout(f"{self.path}: still armed {self.timeout_s} s after LAND")
            self.check_alive(link, "landing")
            self.pause(0.1)


class GotoPosition(MavlinkAction):
    """Drive or fly to ``north_m``, ``east_m`` (local NED frame of the vehicle; ``alt_m``
    above home for a Copter, None: keep it) in GUIDED, sending the target at 2 Hz until
    the vehicle is within ``radius_m``. Arms when needed. The result is the distance left."""

    def __init__(self, north_m: float, east_m: float, alt_m: float | None = None, *,
                 radius_m: float = 0.5, timeout_s: float = 120.0, **link: Any) -> None:
        super().__init__(**link)
        Waypoint.parse([north_m, east_m, alt_m or 0.0], where="GotoPosition")
        self.target = (float(north_m), float(east_m), alt_m)
        self.radius_m = radius_m
        self.timeout_s = timeout_s

    def perform(self, link: MavlinkLink) -> float:
        self.drive_mode = "GUIDED"  # (before the change: a pause may come while it waits)
        if link.mode != "GUIDED":
            link.set_mode("GUIDED")
        if not link.armed:
            link.arm(True)
        north, east, alt = self.target
        deadline = time.monotonic() + self.timeout_s
        while True:
            n, e, a = link.local_position()
            left = math.hypot(north - n, east - e)
            if alt is not None and link.kind == COPTER:
                left = math.hypot(left, alt - a)
            if left <= self.radius_m:
                return left
            if time.monotonic() > deadline:
                raise MavlinkTimeout(f"{self.path}: {left:.2f} m from the target after "
                                     f"{self.timeout_s} s")
            self.check_alive(link, "going to a position")
            if self.pause_held or self.operator_held(link, resume_in="GUIDED"):
                self.pause(0.1)  # stands still while paused
                continue
            link.goto_local(north, east, alt)
            self.pause(0.5)


class UploadMission(MavlinkAction):
    """Upload ``waypoints`` (home as item 0, then one NAV_WAYPOINT each) with the mission
    protocol; the result is how many messages had to be sent again."""

    def __init__(self, waypoints: Sequence[Any], **link: Any) -> None:
        super().__init__(**link)
        self.waypoints = parse_waypoints(list(waypoints))

    def perform(self, link: MavlinkLink) -> int:
        return link.upload_mission(link.mission_items(self.waypoints))


def _vehicle_time_s(link: MavlinkLink) -> float:
    """The vehicle's clock (LOCAL_POSITION_NED.time_boot_ms) in seconds."""
    local = link.latest("LOCAL_POSITION_NED")
    return float(local.time_boot_ms) / 1000.0 if local is not None else time.monotonic()


class RunMission(MavlinkAction):
    """Fly or drive ``waypoints`` in AUTO and wait until the last one is reached.

    Uploads them first; a Copter on the ground takes off to the first waypoint's altitude
    (GUIDED) before AUTO. The result is ``{"reached": [seq, …], "resends": n}``.

    ``stall_s``: when set, a vehicle that moved less than ``stall_m`` in that time (the
    vehicle's own clock, ``time_boot_ms``: a simulation running slower than real time
    does not stall) without reaching its next waypoint raises
    :class:`~beehave.errors.MissionStalled` with the waypoints it has not reached — the
    rover's "I cannot pass" (the safe state then holds it). ``timeout_s`` bounds the whole
    mission."""

    def __init__(self, waypoints: Sequence[Any], *, stall_s: float | None = None,
                 stall_m: float = 0.2, timeout_s: float = 600.0, **link: Any) -> None:
        super().__init__(**link)
        self.waypoints = parse_waypoints(list(waypoints))
        self.stall_s = stall_s
        self.stall_m = stall_m
        self.timeout_s = timeout_s
        #: Sequence numbers reached so far (1 = the first waypoint).
        self.reached: list[int] = []

    @property
    def remaining(self) -> list[Waypoint]:
        """The waypoints not reached yet."""
        done = max(self.reached, default=0)
        return self.waypoints[done:]

    def perform(self, link: MavlinkLink) -> dict[str, Any]:
        resends = link.upload_mission(link.mission_items(self.waypoints))
        last = len(self.waypoints)
        with link.listen("MISSION_ITEM_REACHED") as reached:
            if link.require_kind() == COPTER and link.local_position()[2] < 0.3:
                take_off(self, link, max(1.0, self.waypoints[0].alt_m), 30.0)
            if not link.armed:
                link.arm(True)
            self.drive_mode = "AUTO"  # (before the start: a pause may come while it waits)
            link.start_mission(1)
            clock = self.manager.run_clock  # the mission's timeout does not run while paused
            deadline = clock.now() + self.timeout_s
            anchor = link.local_position()
            anchor_at = _vehicle_time_s(link)
            while True:
                msg = reached.wait(timeout_s=0.2, what="mission progress")
                if msg is not None:
                    if msg.seq not in self.reached:
                        self.reached.append(int(msg.seq))
                    anchor, anchor_at = link.local_position(), _vehicle_time_s(link)
                    if msg.seq >= last:
                        return {"reached": list(self.reached), "resends": resends}
                    continue
                if clock.now() > deadline:
                    raise MavlinkTimeout(f"{self.path}: mission not done after "
                                         f"{self.timeout_s} s (reached {self.reached})")
                if self.pause_held or self.operator_held(link, resume_in="AUTO"):
                    self.pause(0.1)  # stands still while paused
                    anchor, anchor_at = link.local_position(), _vehicle_time_s(link)
                    continue
                if link.mode != "AUTO":
                    raise MissionStalled(
                        f"{self.path}: the vehicle left AUTO (now {link.mode}) before the "
                        f"last waypoint", remaining=list(self.remaining),
                        position=link.local_position())
                if self.stall_s is not None:
                    here, vehicle_now = link.local_position(), _vehicle_time_s(link)
                    if math.dist(here[:2], anchor[:2]) >= self.stall_m:
                        anchor, anchor_at = here, vehicle_now
                    elif vehicle_now - anchor_at > self.stall_s:
                        raise MissionStalled(
                            f"{self.path}: no progress for {self.stall_s} s at "
                            f"({here[0]:.1f}, {here[1]:.1f}); {len(self.remaining)} "
                            f"waypoint(s) left", remaining=list(self.remaining),
                            position=here)
                if self.interrupted:
                    raise Interrupted(f"{self.path}: interrupted")
