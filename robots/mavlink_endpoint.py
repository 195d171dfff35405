"""A simulated robot as a MAVLink vehicle, following ArduPilot's conventions — so that the
MAVLink HALs (:mod:`hal.mavlink`) drive the simulation exactly as they would drive a real
ArduPilot or its SITL.

::

    sim = Simulation("droid")
    rover = MavlinkEndpoint(sim, "rover1", url="udpout:127.0.0.1:14561", system_id=1)
    sim.start()
    # a ground station listens with  udp:127.0.0.1:14561
    ...
    rover.close(); sim.close()

Like MAVProxy's ``--out``, an endpoint *sends* to its address (``udpout:``); the ground
station listens there (``udp:``/``udpin:``) and its replies come back to the endpoint's
socket. ``beehave sim --mavlink`` (or ``mavlink: {base_port: 14560}`` in the world YAML)
opens one endpoint per robot: robot i sends to port ``base_port + i`` with system id i + 1.

What it implements (ArduPilot 4.x behaviour, simplified):

- **Vehicles.** Ground robots (EMILI, Kobuki) are a Rover (``MAV_TYPE_GROUND_ROVER``,
  modes of ``mavutil.mode_mapping_rover``, starts in HOLD); the ``quad`` is a Copter
  (``MAV_TYPE_QUADROTOR``, Copter modes, starts in STABILIZE on the floor).
- **Telemetry** at ``stream_rate_hz`` of sim time: GLOBAL_POSITION_INT, LOCAL_POSITION_NED,
  ATTITUDE, SYS_STATUS; once a second of wall time HEARTBEAT (autopilot ARDUPILOTMEGA, armed flag,
  custom mode), BATTERY_STATUS, MISSION_CURRENT and GPS_GLOBAL_ORIGIN.
- **Frames.** The local NED frame's origin is the world origin: north = world y, east =
  world x, down = −altitude. Its geodetic position is ``origin`` (default: ArduPilot
  SITL's CMAC field); global positions are flat-earth around it.
- **Commands** (COMMAND_LONG → COMMAND_ACK): ARM_DISARM, DO_SET_MODE (and SET_MODE),
  NAV_TAKEOFF (Copter, armed, GUIDED), REQUEST_MESSAGE (GPS_GLOBAL_ORIGIN); others are
  answered UNSUPPORTED. SET_POSITION_TARGET_LOCAL_NED / _GLOBAL_INT steer in GUIDED.
- **Modes.** GUIDED (go to the position target), AUTO (fly the mission from the current
  item; MISSION_ITEM_REACHED on arrival; at the end it stays put), RTL (home; a Copter
  climbs to ``RTL_ALT``, returns, lands and disarms), LAND (Copter), HOLD / LOITER / BRAKE
  and every other mode (stand still). Disarmed vehicles do not move.
- **Mission protocol** (upload): MISSION_COUNT → MISSION_REQUEST_INT(0..n−1) ↔
  MISSION_ITEM_INT → MISSION_ACK. A request unanswered for ``rerequest_s`` is sent again
  (at most 5 times, then the upload is cancelled); a repeated COUNT restarts the upload; a
  duplicate of the previous item is answered by re-requesting the expected one; other
  out-of-order items are ignored. Frames other than GLOBAL(_RELATIVE_ALT)(_INT) are refused
  with MAV_MISSION_UNSUPPORTED_FRAME, commands other than NAV_WAYPOINT / TAKEOFF / LAND /
  RETURN_TO_LAUNCH with MAV_MISSION_UNSUPPORTED. Item 0 is home (not flown).
- **Parameters**: PARAM_REQUEST_READ / PARAM_REQUEST_LIST / PARAM_SET → PARAM_VALUE for
  the parameters in :data:`DEFAULT_PARAMS`; unknown names get no answer (as ArduPilot).

**Faults** (:class:`Faults`, for tests): drop the next n outgoing or incoming messages of
a type, or go silent (a lost radio link).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hal.mavlink import (
    COPTER,
    GCS_COMPONENT_ID,
    GCS_SYSTEM_ID,
    ROVER,
    LocalFrame,
    mode_name,
    mode_names,
    param_name,
)
from robots.quad import Quad
from robots.robot import SimRobot
from robots.sim import Simulation

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # type: ignore[import-untyped]  # noqa: E402

log = logging.getLogger(__name__)
mavlink = mavutil.mavlink

__all__ = ["DEFAULT_ORIGIN", "DEFAULT_PARAMS", "Faults", "MavlinkEndpoint", "open_endpoints"]

DEFAULT_ORIGIN = LocalFrame(-35.363262, 149.165237)
"""ArduPilot SITL's default home (the CMAC model-aircraft field near Canberra)."""

DEFAULT_PARAMS: dict[str, dict[str, float]] = {
    ROVER: {"WP_RADIUS": 0.3, "WP_SPEED": 0.6, "BATT_LOW_PCT": 20.0, "SYSID_THISMAV": 1.0},
    COPTER: {"WPNAV_RADIUS": 50.0, "WPNAV_SPEED": 200.0, "RTL_ALT": 300.0, "LAND_SPEED": 70.0,
             "BATT_LOW_PCT": 25.0, "SYSID_THISMAV": 1.0},
}
"""The parameters an endpoint answers for, with their defaults, in ArduPilot's units: Rover's
WP_* in m and m/s, Copter's WPNAV_*, RTL_ALT and LAND_SPEED in cm and cm/s."""

_START_MODE = {ROVER: "HOLD", COPTER: "STABILIZE"}
_SUPPORTED_FRAMES = {mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                     mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
_SUPPORTED_ITEMS = {mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_TAKEOFF,
                    mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH}
_REREQUESTS = 5


@dataclass
class Faults:
    """Faults to inject (tests). Counters are decremented as messages are dropped."""

    drop_outgoing: Counter[str] = field(default_factory=Counter)
    """Message type → how many of the next ones the endpoint does not send."""
    drop_incoming: Counter[str] = field(default_factory=Counter)
    """Message type → how many of the next ones the endpoint does not read."""
    silent: bool = False
    """Send nothing at all (a lost link: the heartbeat stops)."""
    dropped: Counter[str] = field(default_factory=Counter)
    """What was dropped so far, by ``out:TYPE`` / ``in:TYPE``."""


@dataclass
class _Item:
    seq: int
    command: int
    x_m: float
    y_m: float
    alt_m: float


@dataclass
class _Upload:
    count: int
    items: list[_Item]
    expected: int = 0
    asked_at: float = 0.0
    asks: int = 0


class MavlinkEndpoint:
    """One robot of ``sim`` as a MAVLink vehicle (see the module doc).

    ``url``: where it sends (``udpout:HOST:PORT``; any pymavlink connection string works).
    ``system_id``: its MAVLink system id. Creating it opens the socket, starts its reader
    thread and hooks the control and telemetry into ``sim.on_step``; :meth:`close` undoes
    all of it (the robot stops)."""

    def __init__(self, sim: Simulation, namespace: str, *, url: str, system_id: int = 1,
                 origin: LocalFrame = DEFAULT_ORIGIN, stream_rate_hz: float = 10.0,
                 control_rate_hz: float = 20.0, rerequest_s: float = 1.0,
                 faults: Faults | None = None) -> None:
        self.sim = sim
        self.robot: SimRobot = sim.robot(namespace)
        self.namespace = namespace
        self.url = url
        self.system_id = system_id
        self.origin = origin
        self.kind = COPTER if isinstance(self.robot, Quad) else ROVER
        self.mav_type = (mavlink.MAV_TYPE_QUADROTOR if self.kind == COPTER
                         else mavlink.MAV_TYPE_GROUND_ROVER)
        self.faults = faults if faults is not None else Faults()
        self.rerequest_s = rerequest_s
        self.params = dict(DEFAULT_PARAMS[self.kind])
        self.params["SYSID_THISMAV"] = float(system_id)
        self.modes = mode_names(self.kind)
        #: What the endpoint refused to take, by reason (for tests and logs).
        self.ignored: Counter[str] = Counter()
        self._lock = threading.RLock()
        self._send_lock = threading.Lock()
        self.armed = False
        self.mode = _START_MODE[self.kind]
        start = self.robot.spec.start
        self.home = (start.x_m, start.y_m)
        self._target: tuple[float, float, float | None] | None = None
        self._mission: list[_Item] = []
        self.current_seq = 0
        self.reached: list[int] = []
        self._upload: _Upload | None = None
        self._landing = False
        self._next_beat_s = 0.0
        self._stop = threading.Event()
        self.conn = mavutil.mavlink_connection(url, source_system=system_id,
                                               source_component=1)
        self._thread = threading.Thread(target=self._read, name=f"beehave:mav-endpoint:"
                                        f"{namespace}", daemon=True)
        self._thread.start()
        self._removers = [sim.on_step(self._control, rate_hz=control_rate_hz),
                          sim.on_step(self._stream, rate_hz=stream_rate_hz)]

    # ---- sending --------------------------------------------------------------------

    def _send(self, kind: str, build: Callable[[Any], Any]) -> None:
        faults = self.faults
        if faults.silent:
            return
        if faults.drop_outgoing[kind] > 0:
            faults.drop_outgoing[kind] -= 1
            faults.dropped[f"out:{kind}"] += 1
            return
        with self._send_lock:
            try:
                build(self.conn.mav)
            except OSError as exc:  # nobody listens yet (ICMP port unreachable)
                log.debug("endpoint %s: %s not sent: %s", self.namespace, kind, exc)

    def _ack(self, command: int, result: int) -> None:
        self._send("COMMAND_ACK", lambda mav: mav.command_ack_send(command, result))

    # ---- where the robot is -----------------------------------------------------------

    def _where(self) -> tuple[float, float, float, float, float, float, float]:
        """x, y, alt, yaw, vx, vy, vz (world frame)."""
        robot = self.robot
        if isinstance(robot, Quad):
            p = robot.position()
            return p.x_m, p.y_m, p.z_m, p.yaw_rad, p.vx_mps, p.vy_mps, p.vz_mps
        o = robot.odometry()
        c, s = math.cos(o.yaw_rad), math.sin(o.yaw_rad)
        return o.x_m, o.y_m, 0.0, o.yaw_rad, o.linear_mps * c, o.linear_mps * s, 0.0

    def _world(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        north, east = self.origin.to_local(lat_deg, lon_deg)
        return east, north

    # ---- telemetry (sim thread) -------------------------------------------------------

    def _stream(self, time_s: float) -> None:
        x, y, alt, yaw, vx, vy, vz = self._where()
        boot_ms = int(time_s * 1000) & 0xFFFFFFFF
        lat, lon = self.origin.to_global(y, x)
        hdg = round(math.degrees(math.pi / 2 - yaw) % 360 * 100)  # compass: 0 north, cw
        self._send("GLOBAL_POSITION_INT", lambda mav: mav.global_position_int_send(
            boot_ms, round(lat * 1e7), round(lon * 1e7), round(alt * 1000),
            round(alt * 1000), round(vy * 100), round(vx * 100), round(-vz * 100), hdg))
        self._send("LOCAL_POSITION_NED", lambda mav: mav.local_position_ned_send(
            boot_ms, y, x, -alt, vy, vx, -vz))
        self._send("ATTITUDE", lambda mav: mav.attitude_send(
            boot_ms, 0.0, 0.0, math.remainder(math.pi / 2 - yaw, 2 * math.pi), 0.0, 0.0, 0.0))
        battery = self.robot.battery()
        self._send("SYS_STATUS", lambda mav: mav.sys_status_send(
            0, 0, 0, 0, round(battery.voltage_v * 1000), round(-battery.current_a * 100),
            round(battery.percentage), 0, 0, 0, 0, 0, 0))
        with self._lock:
            upload = self._upload
            if upload is not None and time.monotonic() - upload.asked_at > self.rerequest_s:
                if upload.asks >= _REREQUESTS:
                    self._upload = None
                    self._send("MISSION_ACK", lambda mav: mav.mission_ack_send(
                        0, 0, mavlink.MAV_MISSION_OPERATION_CANCELLED))
                else:
                    self._request(upload)

    def _beat(self) -> None:
        percentage = self.robot.battery().percentage
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        state = mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY
        number = self.modes[self.mode]
        self._send("HEARTBEAT", lambda mav: mav.heartbeat_send(
            self.mav_type, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, number, state))
        self._send("BATTERY_STATUS", lambda mav: mav.battery_status_send(
            0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 32767,
            [65535] * 10, -1, -1, -1, round(percentage)))
        self._send("MISSION_CURRENT", lambda mav: mav.mission_current_send(self.current_seq))
        self._send_origin()

    def _send_origin(self) -> None:
        self._send("GPS_GLOBAL_ORIGIN", lambda mav: mav.gps_global_origin_send(
            round(self.origin.lat_deg * 1e7), round(self.origin.lon_deg * 1e7), 0))

    # ---- control (sim thread) ---------------------------------------------------------

    def _control(self, time_s: float) -> None:
        with self._lock:
            goal = self._goal()
        robot = self.robot
        x, y, alt, yaw, *_ = self._where()
        if isinstance(robot, Quad):
            self._fly(robot, goal, x, y, alt)
        elif self.armed:
            self._drive(goal, x, y, yaw)

    def _goal(self) -> tuple[float, float, float | None] | None:
        """Where the current mode wants the vehicle (x, y, alt or None: keep it)."""
        if not self.armed:
            return None
        if self.mode == "GUIDED":
            return self._target
        if self.mode == "AUTO":
            item = self._mission_item()
            if item is None:
                return None
            return (item.x_m, item.y_m, item.alt_m)
        if self.mode in ("RTL", "SMART_RTL"):
            return (*self.home, None)
        return None

    def _mission_item(self) -> _Item | None:
        while 0 < self.current_seq < len(self._mission):
            item = self._mission[self.current_seq]
            if item.command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                self._set_mode("RTL")
                return None
            if item.command == mavlink.MAV_CMD_NAV_LAND:
                self._set_mode("LAND")
                return None
            return item
        return None

    def _arrived(self) -> None:
        """The goal of the current mode is reached (sim thread, under the lock)."""
        if self.mode == "AUTO":
            seq = self.current_seq
            self.reached.append(seq)
            self._send("MISSION_ITEM_REACHED", lambda mav: mav.mission_item_reached_send(seq))
            if seq + 1 < len(self._mission):
                self.current_seq = seq + 1
            self._send("MISSION_CURRENT", lambda mav: mav.mission_current_send(
                self.current_seq, len(self._mission),
                mavlink.MISSION_STATE_COMPLETE if seq + 1 >= len(self._mission)
                else mavlink.MISSION_STATE_ACTIVE))
            if seq + 1 >= len(self._mission):
                self.current_seq = len(self._mission)  # done: nothing left to fly
        elif self.mode in ("RTL", "SMART_RTL"):
            if self.kind == COPTER:
                self._set_mode("LAND")
            else:
                self._set_mode("HOLD")
        elif self.mode == "GUIDED":
            pass  # stays at the target until a new one comes

    def _drive(self, goal: tuple[float, float, float | None] | None, x: float, y: float,
               yaw: float) -> None:
        if goal is None:
            self.robot.stop()
            return
        dx, dy = goal[0] - x, goal[1] - y
        dist = math.hypot(dx, dy)
        if dist <= self.params["WP_RADIUS"]:
            self.robot.stop()
            with self._lock:
                if self._goal() == goal:
                    self._arrived()
            return
        err = math.remainder(math.atan2(dy, dx) - yaw, 2 * math.pi)
        speed = self.params["WP_SPEED"]
        v = min(speed, 0.8 * dist) * max(0.0, math.cos(err)) ** 2
        self.robot.set_cmd_vel(v, max(-1.5, min(1.5, 2.5 * err)))

    def _fly(self, quad: Quad, goal: tuple[float, float, float | None] | None, x: float,
             y: float, alt: float) -> None:
        if not self.armed:
            return
        if self.mode == "LAND" or self._landing:
            quad.set_velocity(0.0, 0.0, -self.params["LAND_SPEED"] / 100.0)
            if quad.landed:
                with self._lock:
                    self._landing = False
                    self.armed = False  # ArduCopter disarms itself after landing
            return
        if goal is None:
            quad.set_velocity(0.0, 0.0, 0.0)
            return
        gx, gy, galt = goal
        if galt is None:  # RTL: at least RTL_ALT_M on the way home
            galt = max(alt, self.params["RTL_ALT"] / 100.0)
        dx, dy, dz = gx - x, gy - y, galt - alt
        dist = math.hypot(dx, dy)
        # GUIDED holds its target exactly (a position controller); AUTO and RTL count a
        # waypoint reached within WPNAV_RADIUS and go on.
        if self.mode != "GUIDED" and dist <= self.params["WPNAV_RADIUS"] / 100.0 \
                and abs(dz) <= 0.1:
            quad.set_velocity(0.0, 0.0, 0.0)
            with self._lock:
                if self._goal() == goal:
                    self._arrived()
            return
        climb = max(-1.0, min(1.0, 1.5 * dz))
        if alt < 0.8 * galt and galt > 0.5 and dist > 1.0:
            quad.set_velocity(0.0, 0.0, climb)  # climb first: never drag across the floor
            return
        speed = min(self.params["WPNAV_SPEED"] / 100.0, 1.5 * dist)
        scale = speed / dist if dist > 1e-6 else 0.0
        quad.set_velocity(dx * scale, dy * scale, climb)

    # ---- receiving (reader thread) ------------------------------------------------------

    def _read(self) -> None:
        while not self._stop.is_set():
            # The heartbeat goes by wall time, as an autopilot's does: a simulation slowed
            # down by a loaded host must not look like a lost link.
            if time.monotonic() >= self._next_beat_s:
                self._next_beat_s = time.monotonic() + 1.0
                self._beat()
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.05)
            except OSError:
                self._stop.wait(0.05)  # not bound yet, or the peer went away
                continue
            if msg is None:
                continue
            kind = msg.get_type()
            if self.faults.drop_incoming[kind] > 0:
                self.faults.drop_incoming[kind] -= 1
                self.faults.dropped[f"in:{kind}"] += 1
                continue
            target = getattr(msg, "target_system", 0)
            if target not in (0, self.system_id):
                continue  # for another vehicle on the same link
            handler = getattr(self, f"_on_{kind.lower()}", None)
            if handler is None:
                continue
            try:
                with self._lock:
                    handler(msg)
            except Exception:  # a bad message must never end the vehicle
                log.exception("endpoint %s: handling %s failed", self.namespace, kind)

    def _ignore(self, reason: str) -> None:
        self.ignored[reason] += 1
        log.info("endpoint %s: ignored %s", self.namespace, reason)

    def _set_mode(self, name: str) -> None:
        if name != self.mode:
            log.debug("endpoint %s: mode %s -> %s", self.namespace, self.mode, name)
        self.mode = name
        self._landing = False
        if name == "GUIDED":
            x, y, alt, *_ = self._where()
            self._target = (x, y, alt if self.kind == COPTER else None)

    def _mode_allowed(self, name: str) -> bool:
        if name == "AUTO":
            return len(self._mission) > 1  # ArduPilot refuses AUTO without a mission
        return True

    def _on_command_long(self, msg: Any) -> None:
        cmd = msg.command
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if msg.param1 >= 0.5:
                self.armed = True
            elif self.kind == COPTER and isinstance(self.robot, Quad) \
                    and not self.robot.landed and msg.param2 != 21196:
                self._ack(cmd, mavlink.MAV_RESULT_DENIED)  # not in the air (unless forced)
                return
            else:
                self.armed = False
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED)
        elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
            number = int(msg.param2)
            name = mode_name(self.kind, number)
            if name not in self.modes or not self._mode_allowed(name):
                self._ack(cmd, mavlink.MAV_RESULT_DENIED
                          if name in self.modes else mavlink.MAV_RESULT_UNSUPPORTED)
                return
            self._set_mode(name)
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED)
        elif cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            if self.kind != COPTER:
                self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED)
            elif not self.armed or self.mode != "GUIDED":
                self._ack(cmd, mavlink.MAV_RESULT_DENIED)
            else:
                x, y, *_ = self._where()
                self._target = (x, y, float(msg.param7))
                self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED)
        elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE \
                and int(msg.param1) == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            self._ack(cmd, mavlink.MAV_RESULT_ACCEPTED)
            self._send_origin()
        else:
            self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED)

    def _on_set_mode(self, msg: Any) -> None:
        name = mode_name(self.kind, msg.custom_mode)
        if name in self.modes and self._mode_allowed(name):
            self._set_mode(name)

    def _on_set_position_target_local_ned(self, msg: Any) -> None:
        if self.mode != "GUIDED" or not self.armed:
            self._ignore("position target outside GUIDED or disarmed")
            return
        alt = -msg.z if self.kind == COPTER else None
        self._target = (msg.y, msg.x, alt)

    def _on_set_position_target_global_int(self, msg: Any) -> None:
        if self.mode != "GUIDED" or not self.armed:
            self._ignore("position target outside GUIDED or disarmed")
            return
        x, y = self._world(msg.lat_int / 1e7, msg.lon_int / 1e7)
        self._target = (x, y, msg.alt if self.kind == COPTER else None)

    # -- mission protocol

    def _on_mission_count(self, msg: Any) -> None:
        count = msg.count
        if count == 0:
            self._mission = []
            self.current_seq = 0
            self._upload = None
            self._send("MISSION_ACK", lambda mav: mav.mission_ack_send(
                msg.get_srcSystem(), msg.get_srcComponent(), mavlink.MAV_MISSION_ACCEPTED))
            return
        self._upload = _Upload(count, [])
        self._request(self._upload)

    def _request(self, upload: _Upload) -> None:
        upload.asked_at = time.monotonic()
        upload.asks += 1
        seq = upload.expected
        self._send("MISSION_REQUEST_INT", lambda mav: mav.mission_request_int_send(
            mavlink_gcs[0], mavlink_gcs[1], seq))

    def _on_mission_item_int(self, msg: Any) -> None:
        upload = self._upload
        if upload is None:
            self._ignore(f"MISSION_ITEM_INT {msg.seq} outside an upload")
            return
        if msg.seq != upload.expected:
            if msg.seq == upload.expected - 1:
                self._request(upload)  # our request was lost: ask again
            else:
                self._ignore(f"MISSION_ITEM_INT {msg.seq} out of order (expected "
                             f"{upload.expected})")
            return
        result = None
        if msg.frame not in _SUPPORTED_FRAMES and msg.seq != 0:
            result = mavlink.MAV_MISSION_UNSUPPORTED_FRAME
        elif msg.command not in _SUPPORTED_ITEMS:
            result = mavlink.MAV_MISSION_UNSUPPORTED
        if result is not None:
            self._upload = None
            self._send("MISSION_ACK", lambda mav: mav.mission_ack_send(
                msg.get_srcSystem(), msg.get_srcComponent(), result))
            return
        x, y = self._world(msg.x / 1e7, msg.y / 1e7)
        upload.items.append(_Item(msg.seq, msg.command, x, y, float(msg.z)))
        upload.expected += 1
        upload.asks = 0
        if upload.expected < upload.count:
            self._request(upload)
            return
        self._mission = upload.items
        self._mission[0] = _Item(0, mavlink.MAV_CMD_NAV_WAYPOINT, *self.home, 0.0)
        self.current_seq = 1 if len(self._mission) > 1 else 0
        self.reached = []
        self._upload = None
        self._send("MISSION_ACK", lambda mav: mav.mission_ack_send(
            msg.get_srcSystem(), msg.get_srcComponent(), mavlink.MAV_MISSION_ACCEPTED))

    def _on_mission_set_current(self, msg: Any) -> None:
        if 0 <= msg.seq < len(self._mission):
            self.current_seq = msg.seq
            self._send("MISSION_CURRENT", lambda mav: mav.mission_current_send(msg.seq))
        else:
            self._ignore(f"MISSION_SET_CURRENT {msg.seq} of {len(self._mission)}")

    # -- parameters

    def _param_value(self, name: str) -> None:
        names = sorted(self.params)
        value = self.params[name]
        index = names.index(name)
        self._send("PARAM_VALUE", lambda mav: mav.param_value_send(
            name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, len(names), index))

    def _on_param_request_read(self, msg: Any) -> None:
        name = param_name(msg)
        names = sorted(self.params)
        if msg.param_index >= 0 and msg.param_index < len(names):
            name = names[msg.param_index]
        if name in self.params:
            self._param_value(name)
        else:
            self._ignore(f"PARAM_REQUEST_READ of unknown {name!r}")

    def _on_param_request_list(self, msg: Any) -> None:
        for name in sorted(self.params):
            self._param_value(name)

    def _on_param_set(self, msg: Any) -> None:
        name = param_name(msg)
        if name not in self.params or not math.isfinite(msg.param_value):
            self._ignore(f"PARAM_SET of unknown {name!r} or a non-finite value")
            return
        self.params[name] = float(msg.param_value)
        self._param_value(name)

    # ---- state for tests and checks ------------------------------------------------------

    @property
    def mission(self) -> list[tuple[float, float, float]]:
        """The stored mission as world (x, y, alt) per item (item 0 is home)."""
        with self._lock:
            return [(i.x_m, i.y_m, i.alt_m) for i in self._mission]

    # ---- lifecycle ---------------------------------------------------------------------

    def close(self) -> None:
        """Unhook from the simulation, stop the reader thread, close the socket."""
        for remove in self._removers:
            remove()
        self._removers = []
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()
        self.conn.close()

    def __repr__(self) -> str:
        return (f"<MavlinkEndpoint {self.namespace} {self.kind} sys={self.system_id} "
                f"{self.url} mode={self.mode} armed={self.armed}>")


mavlink_gcs = (GCS_SYSTEM_ID, GCS_COMPONENT_ID)
"""Where mission requests go (the ground station's ids, as ArduPilot replies to them)."""


def open_endpoints(sim: Simulation, *, base_port: int, host: str = "127.0.0.1",
                   **options: Any) -> dict[str, MavlinkEndpoint]:
    """One endpoint per robot of ``sim``: robot i sends to ``udpout:host:base_port + i``
    with system id i + 1 (by namespace). Close each when done."""
    endpoints: dict[str, MavlinkEndpoint] = {}
    try:
        for i, namespace in enumerate(sim.robots):
            endpoints[namespace] = MavlinkEndpoint(
                sim, namespace, url=f"udpout:{host}:{base_port + i}", system_id=i + 1,
                **options)
    except BaseException:
        for endpoint in endpoints.values():
            endpoint.close()
        raise
    return endpoints
