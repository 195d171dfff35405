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
  ATTITUDE, SYS_STATUS, GPS_RAW_INT, VFR_HUD; at 1 Hz of sim time BATTERY_STATUS and
  MISSION_CURRENT — each rate changeable with SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM
  (:attr:`MavlinkEndpoint.intervals`); once a second of wall time HEARTBEAT (autopilot
  ARDUPILOTMEGA, base mode and system status as ArduPilot computes them, custom mode),
  GPS_GLOBAL_ORIGIN and HOME_POSITION.
- **Frames.** The local NED frame's origin is the world origin: north = world y, east =
  world x, down = −altitude. Its geodetic position is ``origin`` (default: ArduPilot
  SITL's CMAC field); global positions are flat-earth around it.
- **Input is validated where it enters**: every field of every handled message must be a
  finite number in range (latitudes within ±90°, longitudes within ±180°, positions inside
  the fence). A bad one is refused with the protocol's answer — a COMMAND_ACK with
  DENIED (a parameter is invalid), FAILED (valid, but not now) or UNSUPPORTED, a MISSION_ACK
  with MAV_MISSION_INVALID_PARAMn — or, for messages without an answer, ignored with a log
  line and a count in :attr:`MavlinkEndpoint.ignored`. Nothing a ground station sends
  can stop the simulation.
- **Commands** (COMMAND_LONG and COMMAND_INT → always a COMMAND_ACK, addressed to the
  sender): ARM_DISARM (param1 exactly 1 or 0, else UNSUPPORTED; a flying Copter disarms
  only when forced with 21196 — and then falls), DO_SET_MODE (and SET_MODE, acknowledged
  with command 11 as ArduPilot does), NAV_TAKEOFF (Copter, armed, GUIDED, on the ground,
  upwards), DO_REPOSITION, MISSION_START, NAV_RETURN_TO_LAUNCH, NAV_LAND (Copter),
  REQUEST_MESSAGE (GPS_GLOBAL_ORIGIN, HOME_POSITION, AUTOPILOT_VERSION, HEARTBEAT,
  MISSION_CURRENT), GET_HOME_POSITION, REQUEST_AUTOPILOT_CAPABILITIES; others are
  answered UNSUPPORTED. Refusals are explained in a STATUSTEXT.
- **GUIDED targets.** SET_POSITION_TARGET_LOCAL_NED (frames LOCAL_NED, LOCAL_OFFSET_NED,
  BODY_NED, BODY_OFFSET_NED) and _GLOBAL_INT honour ``type_mask`` as ArduPilot does: a
  group (position, velocity, acceleration) is ignored when any of its bits is set;
  position, velocity (renewed within :data:`GUIDED_TIMEOUT_S`, else the vehicle holds),
  position + velocity (flown as the position), yaw and yaw rate. A Copter given nothing
  usable (or a bad value) stops and holds — ArduCopter's "input is not valid so stop"; a
  Rover keeps its previous target and also takes heading-only and turn-rate-only targets.
- **Signing** (``signing_key``; ``beehave sim --mavlink-key-file``): as ArduPilot's
  GCS_Signing, the vehicle signs what it sends and takes only messages signed with its key
  (RADIO and RADIO_STATUS also unsigned); the rest, a replay included, is dropped without
  an answer, counted in :attr:`MavlinkEndpoint.ignored` and logged. SETUP_SIGNING sets a
  new key (all zeros and timestamp 0: off), refused while armed.
- **Fence.** The world's floor (:class:`Fence`, :data:`FENCE_MARGIN_M` inside its edges, up
  to the quad's 30 m ceiling) is an inclusion fence: targets and mission items outside are
  refused, and velocity towards an edge is slowed so that the vehicle stops at it.
- **Modes.** GUIDED (go to the position target), AUTO (fly the mission from the current
  item; MISSION_ITEM_REACHED on arrival; at the end it stays put), RTL (home; a Copter
  climbs to ``RTL_ALT``, returns, lands and disarms), LAND (Copter), HOLD / LOITER / BRAKE
  and every other mode (stand still). Disarmed vehicles do not move.
- **Mission protocol** (download: MISSION_REQUEST_LIST → MISSION_COUNT →
  MISSION_REQUEST_INT or MISSION_REQUEST → the items as uploaded; MISSION_CLEAR_ALL)
  (upload): MISSION_COUNT → MISSION_REQUEST_INT(0..n−1) ↔
  MISSION_ITEM_INT → MISSION_ACK. A request unanswered for ``rerequest_s`` is sent again
  (at most 5 times, then the upload is cancelled); a repeated COUNT restarts the upload; a
  duplicate of the previous item is answered by re-requesting the expected one; other
  out-of-order items are ignored. Frames other than GLOBAL(_RELATIVE_ALT)(_INT) are refused
  with MAV_MISSION_UNSUPPORTED_FRAME, commands other than NAV_WAYPOINT / TAKEOFF / LAND /
  RETURN_TO_LAUNCH with MAV_MISSION_UNSUPPORTED, bad coordinates with
  MAV_MISSION_INVALID_PARAM5_X / 6_Y / 7 (more than :data:`MAX_MISSION_ITEMS`:
  MAV_MISSION_NO_SPACE). Item 0 is home (not flown). Latitude and longitude 0, 0 mean
  "where the vehicle is when the item starts"; a TAKEOFF item climbs straight up
  wherever it is (both as ArduPilot).
- **Parameters**: PARAM_REQUEST_READ / PARAM_REQUEST_LIST / PARAM_SET → PARAM_VALUE for
  the parameters in :data:`DEFAULT_PARAMS`; unknown names get no answer (as ArduPilot);
  values outside :data:`PARAM_RANGES` are refused (the unchanged PARAM_VALUE is sent).

**Faults** (:class:`Faults`, for tests): drop the next n outgoing or incoming messages of
a type, or go silent (a lost radio link).
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
import os
import random
import socket
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
    UNSIGNED_ACCEPTED,
    LocalFrame,
    mode_name,
    mode_names,
    param_name,
    signature_refusal,
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
_HERE_ITEMS = {mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_TAKEOFF,
               mavlink.MAV_CMD_NAV_LAND}
"""Mission items whose latitude and longitude 0, 0 mean "where the vehicle is" (ArduPilot)."""
_REREQUESTS = 5
MAX_MISSION_ITEMS = 500
"""The largest mission an endpoint stores (home included); a bigger MISSION_COUNT is
refused with MAV_MISSION_NO_SPACE, as a flight controller with full storage does."""

# SET_POSITION_TARGET_* type_mask bits (MAVLink POSITION_TARGET_TYPEMASK). ArduPilot reads a
# group as ignored when any of its bits is set.
_POS_IGNORE = 0b111
_VEL_IGNORE = 0b111 << 3
_ACC_IGNORE = 0b111 << 6
_FORCE_SET = 1 << 9
_YAW_IGNORE = 1 << 10
_YAW_RATE_IGNORE = 1 << 11
_LOCAL_FRAMES = {mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
                 mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED}
_BODY_FRAMES = {mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED}
_GLOBAL_TARGET_FRAMES = {mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT,
                         mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                         mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                         mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
                         mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT}
_TAKEOFF_FRAMES = {mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                   mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
MAX_STREAM_RATE_HZ = 50.0
"""The fastest a message is streamed (ArduPilot's SRx_ rates stop at 50 Hz too); a shorter
SET_MESSAGE_INTERVAL is accepted and served at this rate."""
_FAST = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "ATTITUDE", "SYS_STATUS", "GPS_RAW_INT",
         "VFR_HUD")
"""Streamed at ``stream_rate_hz`` by default; BATTERY_STATUS and MISSION_CURRENT at 1 Hz."""
_DATA_STREAMS: dict[int, tuple[str, ...]] = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "GPS_RAW_INT", "MISSION_CURRENT"),
    mavlink.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    mavlink.MAV_DATA_STREAM_EXTRA3: ("BATTERY_STATUS",),
}
"""REQUEST_DATA_STREAM's groups, as ArduPilot's SRx_EXT_STAT, _POSITION, _EXTRA1/2/3 (only
the messages the simulated vehicles send); MAV_DATA_STREAM_ALL is all of them."""
GUIDED_TIMEOUT_S = 3.0
"""A velocity, heading or turn-rate target not renewed for this long (sim time) is dropped
and the vehicle holds where it is (ArduPilot's GUID_TIMEOUT, 3 s)."""
FENCE_MARGIN_M = 0.3
"""How far inside the floor's edge the fence is."""
_ACCEPTED: int = mavlink.MAV_RESULT_ACCEPTED
_DENIED: int = mavlink.MAV_RESULT_DENIED  # MAVLink: supported, but a parameter is invalid
_FAILED: int = mavlink.MAV_RESULT_FAILED  # valid, but it cannot be done now
_UNSUPPORTED: int = mavlink.MAV_RESULT_UNSUPPORTED
_FORCE_DISARM = 21196.0
FIRMWARE_VERSION = (4, 5, 0)
"""The ArduPilot version the endpoint claims in AUTOPILOT_VERSION (the behaviour it copies)."""
_CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                 | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
                 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                 | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                 | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
                 | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2)
# HEARTBEAT base_mode as ArduPilot 4.x computes it (GCS_MAVLINK_Copter/_Rover::base_mode):
# Copter: always STABILIZE_ENABLED and MANUAL_INPUT_ENABLED, GUIDED_ENABLED in the modes
# that navigate; Rover: MANUAL_INPUT_ENABLED in the manual modes, GUIDED_ENABLED in the
# autopilot modes. Both: CUSTOM_MODE_ENABLED, and SAFETY_ARMED when armed.
_COPTER_GUIDED_MODES = {"AUTO", "RTL", "LOITER", "AVOID_ADSB", "FOLLOW", "GUIDED", "CIRCLE",
                        "POSHOLD", "BRAKE", "SMART_RTL"}
_ROVER_MANUAL_MODES = {"MANUAL", "ACRO", "STEERING"}
_ROVER_GUIDED_MODES = {"AUTO", "GUIDED", "RTL", "SMART_RTL", "LOITER", "FOLLOW", "SIMPLE",
                       "DOCK", "CIRCLE"}
_MAX_UINT32 = 2**32 - 1

PARAM_RANGES: dict[str, tuple[float, float]] = {
    "WP_RADIUS": (0.05, 100.0), "WP_SPEED": (0.05, 100.0),
    "WPNAV_RADIUS": (5.0, 1000.0), "WPNAV_SPEED": (10.0, 2000.0),
    "RTL_ALT": (30.0, 300000.0), "LAND_SPEED": (30.0, 200.0),
    "BATT_LOW_PCT": (0.0, 100.0), "SYSID_THISMAV": (1.0, 255.0),
}
"""The values PARAM_SET accepts (ArduPilot's documented ranges, in its units; a zero speed or
radius, which would freeze the vehicle, is not allowed). Others are refused: the endpoint
answers with the unchanged PARAM_VALUE and a STATUSTEXT."""


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _whole(value: float, low: float, high: float) -> bool:
    """``value`` is an integer (as a float may carry one) in [low, high]."""
    return math.isfinite(value) and value == int(value) and low <= value <= high


def _valid_lat_lon(lat_e7: int, lon_e7: int) -> bool:
    return -900_000_000 <= lat_e7 <= 900_000_000 and -1_800_000_000 <= lon_e7 <= 1_800_000_000


@dataclass(frozen=True)
class Fence:
    """An inclusion fence: the world's floor, ``FENCE_MARGIN_M`` inside its edges, up to the
    quad's ceiling — ArduPilot's polygon fence with FENCE_ALT_MAX, as AC_Avoid uses it:
    targets outside are refused and motion towards the edge slows down so the vehicle stops
    at it (world frame, metres)."""

    x_min: float
    y_min: float
    x_max: float
    y_max: float
    alt_max_m: float

    @classmethod
    def of_world(cls, width_m: float, depth_m: float, alt_max_m: float) -> Fence:
        margin = min(FENCE_MARGIN_M, width_m / 4, depth_m / 4)
        return cls(margin, margin, width_m - margin, depth_m - margin, alt_max_m)

    def contains(self, x: float, y: float) -> bool:
        return self.x_min <= x <= self.x_max and self.y_min <= y <= self.y_max

    def limit(self, x: float, y: float, vx: float, vy: float, accel_mps2: float
              ) -> tuple[float, float]:
        """The velocity (vx, vy) with each component towards an edge no faster than the
        vehicle can brake before it (AC_Avoid's rule: v ≤ √(2·a·d), with d shortened by
        one control period's travel)."""

        def cap(v: float, low_gap: float, high_gap: float) -> float:
            gap = high_gap if v > 0 else low_gap
            allowed = math.sqrt(2 * accel_mps2 * max(0.0, gap - 0.05 * abs(v)))
            return max(-allowed, min(allowed, v))

        return (cap(vx, x - self.x_min, self.x_max - x), cap(vy, y - self.y_min, self.y_max - y))

    def scale(self, x: float, y: float, vx: float, vy: float, accel_mps2: float) -> float:
        """How much of the velocity (vx, vy) may be kept (0–1) without crossing the fence,
        for a vehicle that can only move along that velocity (a Rover)."""
        lx, ly = self.limit(x, y, vx, vy, accel_mps2)
        ratios = [lim / v for lim, v in ((lx, vx), (ly, vy)) if abs(v) > 1e-9]
        return max(0.0, min([1.0, *ratios]))


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
    """A stored mission item: what the ground station sent (for download) and where it
    leads in the world (``x_m``/``y_m`` None: where the vehicle is when the item starts)."""

    seq: int
    command: int
    x_m: float | None
    y_m: float | None
    alt_m: float
    frame: int = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    lat_e7: int = 0
    lon_e7: int = 0
    autocontinue: int = 1


@dataclass
class _Upload:
    count: int
    items: list[_Item]
    peer: tuple[int, int] = (GCS_SYSTEM_ID, GCS_COMPONENT_ID)
    expected: int = 0
    asked_at: float = 0.0
    asks: int = 0


@dataclass
class _Velocity:
    """A GUIDED velocity target (world frame: x east, y north, z up, m/s) with an optional
    heading (world yaw, rad) or turn rate (rad/s, counter-clockwise); a Rover drives
    ``speed`` (signed, m/s) along the heading. Dropped at ``until_s`` (sim time)."""

    vx: float
    vy: float
    vz: float
    speed: float
    heading: float | None
    yaw_rate: float | None
    until_s: float


class MavlinkEndpoint:
    """One robot of ``sim`` as a MAVLink vehicle (see the module doc).

    ``url``: where it sends (``udpout:HOST:PORT``; any pymavlink connection string works).
    ``system_id``: its MAVLink system id. ``signing_key``: a 32-byte MAVLink 2 signing key
    (:func:`hal.mavlink.load_signing_key` reads one from a file): the vehicle then signs
    what it sends and takes only messages signed with it (see the module doc). Creating
    it opens the socket, starts its reader thread and hooks the control and telemetry into
    ``sim.on_step``; :meth:`close` undoes all of it (the robot stops)."""

    def __init__(self, sim: Simulation, namespace: str, *, url: str, system_id: int = 1,
                 origin: LocalFrame = DEFAULT_ORIGIN, stream_rate_hz: float = 10.0,
                 control_rate_hz: float = 20.0, rerequest_s: float = 1.0,
                 faults: Faults | None = None, signing_key: bytes | None = None) -> None:
        if signing_key is not None and (not isinstance(signing_key, bytes)
                                        or len(signing_key) != 32):
            raise ValueError(f"endpoint {namespace}: signing_key must be 32 bytes "
                             f"(hal.mavlink.load_signing_key reads one from a file), got "
                             f"{signing_key!r:.40}")
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
        width, depth = sim.world.floor.size_m
        self.fence = Fence.of_world(width, depth, Quad.max_alt_m)
        #: What the endpoint refused to take, by reason (for tests and logs).
        self.ignored: Counter[str] = Counter()
        #: Exceptions caught in the control or telemetry step (each logged; the vehicle
        #: then holds). Always 0 unless there is a bug: no input may get that far.
        self.errors = 0
        self._lock = threading.RLock()
        self._send_lock = threading.Lock()
        self.armed = False
        self._was_armed = False
        self.mode = _START_MODE[self.kind]
        start = self.robot.spec.start
        self.home = (start.x_m, start.y_m)
        self._target: tuple[float, float, float | None] | None = None
        self._velocity: _Velocity | None = None
        self._yaw_target: float | None = None  # world yaw (rad) while holding a position
        self._yaw_rate_target: float | None = None
        self._mission: list[_Item] = []
        self.current_seq = 0
        self.reached: list[int] = []
        self._upload: _Upload | None = None
        self._landing = False
        self._next_beat_s = 0.0
        self._reason: str | None = None
        self._refusals_told: set[tuple[str, Any]] = set()  # (reason, system) logged once
        self._stop = threading.Event()
        self.conn = mavutil.mavlink_connection(url, source_system=system_id,
                                               source_component=1)
        if signing_key is not None:
            self._sign_with(signing_key)
        self._thread = threading.Thread(target=self._read, name=f"beehave:mav-endpoint:"
                                        f"{namespace}", daemon=True)
        self._thread.start()
        #: REQUEST_MESSAGE: message id → how to send it now.
        self._on_request: dict[int, Callable[[], None]] = {
            mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: self._send_origin,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: self._send_home,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._send_version,
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._beat,
            mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: self._send_mission_current,
        }
        #: Streamed message → its interval (s of sim time; None: not sent). Changed by
        #: SET_MESSAGE_INTERVAL and REQUEST_DATA_STREAM.
        self._defaults: dict[str, float] = {
            **{name: 1.0 / stream_rate_hz for name in _FAST},
            "BATTERY_STATUS": 1.0, "MISSION_CURRENT": 1.0}
        self.intervals: dict[str, float | None] = dict(self._defaults)
        self._due: dict[str, float] = dict.fromkeys(self._defaults, 0.0)
        self._removers = [sim.on_step(self._control, rate_hz=control_rate_hz),
                          sim.on_step(self._stream, rate_hz=max(stream_rate_hz,
                                                                 MAX_STREAM_RATE_HZ))]

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

    def _ack(self, command: int, result: int, msg: Any = None) -> None:
        """COMMAND_ACK addressed to the sender of ``msg`` (0/0: everyone, when unknown)."""
        system, component = (msg.get_srcSystem(), msg.get_srcComponent()) if msg is not None \
            else (0, 0)
        self._send("COMMAND_ACK", lambda mav: mav.command_ack_send(
            command, result, 0, 0, system, component))

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

    def _airborne(self) -> bool:
        robot = self.robot
        return isinstance(robot, Quad) and not robot.landed

    # ---- telemetry (sim thread) -------------------------------------------------------

    def _stream(self, time_s: float) -> None:
        try:
            self._stream_step(time_s)
        except Exception:  # a telemetry bug must not stop the simulation
            self.errors += 1
            log.exception("endpoint %s: telemetry step failed", self.namespace)

    def _stream_step(self, time_s: float) -> None:
        due = []
        for name, interval in self.intervals.items():
            if interval is not None and time_s >= self._due[name]:
                due.append(name)
                # Keep the average rate; after a gap (a new interval), start from now.
                nxt = self._due[name] + interval
                self._due[name] = nxt if nxt > time_s else time_s + interval
        if due:
            self._send_telemetry(time_s, due)
        self._upload_watch()

    def _send_telemetry(self, time_s: float, names: list[str]) -> None:
        x, y, alt, yaw, vx, vy, vz = self._where()
        boot_ms = int(time_s * 1000) & 0xFFFFFFFF
        lat, lon = self.origin.to_global(y, x)
        hdg = round(math.degrees(math.pi / 2 - yaw) % 360 * 100)  # compass: 0 north, cw
        battery = self.robot.battery()
        ground = math.hypot(vx, vy)
        cog = round(math.degrees(math.atan2(vx, vy)) % 360 * 100) if ground > 0.05 else 65535
        senders: dict[str, Callable[[Any], Any]] = {
            "GLOBAL_POSITION_INT": lambda mav: mav.global_position_int_send(
                boot_ms, round(lat * 1e7), round(lon * 1e7), round(alt * 1000),
                round(alt * 1000), round(vy * 100), round(vx * 100), round(-vz * 100), hdg),
            "LOCAL_POSITION_NED": lambda mav: mav.local_position_ned_send(
                boot_ms, y, x, -alt, vy, vx, -vz),
            "ATTITUDE": lambda mav: mav.attitude_send(
                boot_ms, 0.0, 0.0, math.remainder(math.pi / 2 - yaw, 2 * math.pi), 0.0, 0.0,
                0.0),
            "SYS_STATUS": lambda mav: mav.sys_status_send(
                0, 0, 0, 0, round(battery.voltage_v * 1000), round(-battery.current_a * 100),
                round(battery.percentage), 0, 0, 0, 0, 0, 0),
            "GPS_RAW_INT": lambda mav: mav.gps_raw_int_send(
                int(time_s * 1e6), mavlink.GPS_FIX_TYPE_3D_FIX, round(lat * 1e7),
                round(lon * 1e7), round(alt * 1000), 121, 200, round(ground * 100), cog, 10),
            "VFR_HUD": lambda mav: mav.vfr_hud_send(
                ground, ground, round(hdg / 100) % 360, self._throttle(), alt, vz),
        }
        for name in names:
            if name == "BATTERY_STATUS":
                self._send_battery()
            elif name == "MISSION_CURRENT":
                self._send_mission_current()
            else:
                self._send(name, senders[name])

    def _upload_watch(self) -> None:
        with self._lock:
            upload = self._upload
            if upload is not None and time.monotonic() - upload.asked_at > self.rerequest_s:
                if upload.asks >= _REREQUESTS:
                    self._upload = None
                    self._send("MISSION_ACK", lambda mav: mav.mission_ack_send(
                        *upload.peer, mavlink.MAV_MISSION_OPERATION_CANCELLED))
                else:
                    self._request(upload)

    def _base_mode(self) -> int:
        mode = self.mode
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.kind == COPTER:
            base |= (mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
                     | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED)
            if mode in _COPTER_GUIDED_MODES:
                base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        else:
            if mode in _ROVER_MANUAL_MODES:
                base |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            if mode in _ROVER_GUIDED_MODES:
                base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        return int(base)

    def _system_status(self) -> int:
        """ArduCopter: STANDBY while landed, ACTIVE in the air; ArduRover: ACTIVE while
        armed. CRITICAL below BATT_LOW_PCT (a battery failsafe)."""
        if self.robot.battery().percentage < self.params["BATT_LOW_PCT"]:
            return int(mavlink.MAV_STATE_CRITICAL)
        active = self._airborne() if self.kind == COPTER else self.armed
        return int(mavlink.MAV_STATE_ACTIVE if active else mavlink.MAV_STATE_STANDBY)

    def _throttle(self) -> int:
        if not self.armed:
            return 0
        if isinstance(self.robot, Quad):
            return 50 if self._airborne() else 10
        return min(100, round(100 * abs(self.robot.cmd_vel()[0])
                              / max(1e-6, self.robot.limits.max_linear_mps)))

    def _beat(self) -> None:
        base, number, state = self._base_mode(), self.modes[self.mode], self._system_status()
        self._send("HEARTBEAT", lambda mav: mav.heartbeat_send(
            self.mav_type, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, number, state))
        self._send_origin()
        self._send_home()

    def _send_battery(self) -> None:
        battery = self.robot.battery()
        # One pack voltage in cell 0, the other cells "not present" (UINT16_MAX), as
        # ArduPilot does when it does not know the cells.
        voltages = [min(65534, round(battery.voltage_v * 1000))] + [65535] * 9
        self._send("BATTERY_STATUS", lambda mav: mav.battery_status_send(
            0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 32767,
            voltages, round(-battery.current_a * 100), -1, -1, round(battery.percentage)))

    def _send_mission_current(self) -> None:
        """MISSION_CURRENT with its total and state, the one builder of it (ArduPilot sends
        one stream of it)."""
        seq, total = self.current_seq, len(self._mission)
        if total <= 1:
            state = mavlink.MISSION_STATE_NO_MISSION
        elif seq >= total:
            state = mavlink.MISSION_STATE_COMPLETE
        elif self.mode == "AUTO":
            state = mavlink.MISSION_STATE_ACTIVE
        else:
            state = mavlink.MISSION_STATE_NOT_STARTED if not self.reached \
                else mavlink.MISSION_STATE_PAUSED
        shown = min(seq, max(0, total - 1))  # ArduPilot shows the last item when complete
        self._send("MISSION_CURRENT", lambda mav: mav.mission_current_send(
            shown, total, state))

    def _send_home(self) -> None:
        lat, lon = self.origin.to_global(self.home[1], self.home[0])
        self._send("HOME_POSITION", lambda mav: mav.home_position_send(
            round(lat * 1e7), round(lon * 1e7), 0, self.home[1], self.home[0], 0.0,
            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0))

    def _send_version(self) -> None:
        major, minor, patch = FIRMWARE_VERSION
        version = major << 24 | minor << 16 | patch << 8 | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL
        self._send("AUTOPILOT_VERSION", lambda mav: mav.autopilot_version_send(
            _CAPABILITIES, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0,
            self.system_id))

    def _statustext(self, severity: int, text: str) -> None:
        data = text.encode("utf-8", errors="replace")[:50]
        self._send("STATUSTEXT", lambda mav: mav.statustext_send(severity, data))

    def _send_origin(self) -> None:
        self._send("GPS_GLOBAL_ORIGIN", lambda mav: mav.gps_global_origin_send(
            round(self.origin.lat_deg * 1e7), round(self.origin.lon_deg * 1e7), 0))

    # ---- control (sim thread) ---------------------------------------------------------

    def _control(self, time_s: float) -> None:
        try:
            self._control_step(time_s)
        except Exception:  # never reached by any input (validated on arrival): a bug
            self.errors += 1
            log.exception("endpoint %s: control step failed; holding", self.namespace)
            with self._lock:
                self._hold()
            if isinstance(self.robot, Quad):
                self.robot.set_velocity(0.0, 0.0, 0.0)
            else:
                self.robot.stop()

    def _control_step(self, time_s: float) -> None:
        robot = self.robot
        with self._lock:
            velocity = self._velocity
            if velocity is not None and (self.mode != "GUIDED" or time_s > velocity.until_s):
                self._hold()  # the target timed out (or the mode changed): stay here
                velocity = None
            goal = None if velocity is not None else self._goal()
        x, y, alt, yaw, *_ = self._where()
        armed = self.armed
        if armed != self._was_armed:  # on arming and disarming only: ROS may drive it else
            self._was_armed = armed
            if isinstance(robot, Quad):
                robot.set_motors(armed)  # disarmed motors stop: in the air it falls
            if not armed:
                robot.stop()
        if isinstance(robot, Quad):
            if not armed:
                return
            if velocity is not None:
                self._fly_velocity(robot, velocity, x, y, alt, yaw)
            else:
                self._fly(robot, goal, x, y, alt, yaw)
        elif armed:
            if velocity is not None:
                self._drive_velocity(velocity, x, y, yaw)
            else:
                self._drive(goal, x, y, yaw)

    def _hold(self) -> None:
        """Drop velocity targets and hold the current position (GUIDED's "stop")."""
        self._velocity = None
        self._yaw_rate_target = None
        if self.mode == "GUIDED":
            x, y, alt, *_ = self._where()
            self._target = (x, y, alt if self.kind == COPTER else None)

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
            if item.x_m is None or item.y_m is None:  # 0, 0: here (ArduPilot)
                x, y, *_ = self._where()
                item.x_m, item.y_m = x, y
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
            if item.command == mavlink.MAV_CMD_NAV_TAKEOFF:
                # A Copter takes off straight up, wherever the item says (ArduPilot).
                if item.x_m is None:
                    x, y, *_ = self._where()
                    item.x_m, item.y_m = x, y
            return item
        return None

    def _arrived(self) -> None:
        """The goal of the current mode is reached (sim thread, under the lock)."""
        if self.mode == "AUTO":
            seq = self.current_seq
            self.reached.append(seq)
            self._send("MISSION_ITEM_REACHED", lambda mav: mav.mission_item_reached_send(seq))
            self.current_seq = seq + 1  # past the end: done, nothing left to fly
            self._send_mission_current()
        elif self.mode in ("RTL", "SMART_RTL"):
            if self.kind == COPTER:
                self._set_mode("LAND")
            else:
                self._set_mode("HOLD")
        elif self.mode == "GUIDED":
            pass  # stays at the target until a new one comes

    def _turn_rate(self, yaw: float, heading: float) -> float:
        return max(-1.5, min(1.5, 2.5 * math.remainder(heading - yaw, 2 * math.pi)))

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

    def _drive_velocity(self, target: _Velocity, x: float, y: float, yaw: float) -> None:
        """GUIDED heading and speed, or turn rate and speed (ArduRover's
        set_desired_heading_and_speed / set_desired_turn_rate_and_speed)."""
        speed = max(-self.params["WP_SPEED"], min(self.params["WP_SPEED"], target.speed))
        if target.yaw_rate is not None:
            turn = target.yaw_rate
        elif target.heading is not None:
            err = math.remainder(target.heading - yaw, 2 * math.pi)
            turn = self._turn_rate(yaw, target.heading)
            speed *= max(0.0, math.cos(err)) ** 2  # turn towards it first
        else:
            turn = 0.0
        # The fence: slow down along the heading so the rover stops at the edge.
        speed *= self.fence.scale(x, y, speed * math.cos(yaw), speed * math.sin(yaw), 0.5)
        self.robot.set_cmd_vel(speed, turn)

    def _yaw_command(self, yaw: float) -> float:
        """The yaw rate (world, rad/s) for the current yaw target or rate, if any."""
        if self._yaw_rate_target is not None:
            return self._yaw_rate_target
        if self._yaw_target is not None:
            return self._turn_rate(yaw, self._yaw_target)
        return 0.0

    def _fly_velocity(self, quad: Quad, target: _Velocity, x: float, y: float, alt: float,
                      yaw: float) -> None:
        vx, vy = self.fence.limit(x, y, target.vx, target.vy, 0.5 * quad.max_accel_mps2)
        vz = target.vz
        if vz > 0:  # the fence's ceiling
            vz = min(vz, math.sqrt(2 * 0.5 * quad.max_accel_mps2
                                   * max(0.0, self.fence.alt_max_m - alt)))
        if target.yaw_rate is not None:
            rate = target.yaw_rate
        elif target.heading is not None:
            rate = self._turn_rate(yaw, target.heading)
        else:
            rate = 0.0
        quad.set_velocity(vx, vy, vz, rate)

    def _fly(self, quad: Quad, goal: tuple[float, float, float | None] | None, x: float,
             y: float, alt: float, yaw: float) -> None:
        if self.mode == "LAND" or self._landing:
            quad.set_velocity(0.0, 0.0, -self.params["LAND_SPEED"] / 100.0)
            if quad.landed:
                with self._lock:
                    self._landing = False
                    self.armed = False  # ArduCopter disarms itself after landing
            return
        rate = self._yaw_command(yaw) if self.mode == "GUIDED" else 0.0
        if goal is None:
            quad.set_velocity(0.0, 0.0, 0.0, rate)
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
            quad.set_velocity(0.0, 0.0, climb, rate)  # climb first: never drag across the floor
            return
        speed = min(self.params["WPNAV_SPEED"] / 100.0, 1.5 * dist)
        scale = speed / dist if dist > 1e-6 else 0.0
        vx, vy = self.fence.limit(x, y, dx * scale, dy * scale, 0.5 * quad.max_accel_mps2)
        quad.set_velocity(vx, vy, climb, rate)

    # ---- receiving (reader thread) ------------------------------------------------------

    def _read(self) -> None:
        while not self._stop.is_set():
            # The heartbeat goes by wall time, as an autopilot's does: a simulation slowed
            # down by a loaded host must not look like a lost link.
            if time.monotonic() >= self._next_beat_s:
                self._next_beat_s = time.monotonic() + 1.0
                try:
                    self._beat()
                except Exception:
                    self.errors += 1
                    log.exception("endpoint %s: heartbeat failed", self.namespace)
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.05)
            except OSError:
                self._stop.wait(0.05)  # not bound yet, or the peer went away
                continue
            except Exception:  # pymavlink choked on the bytes: drop them, keep reading
                self.ignored["undecodable input"] += 1
                log.info("endpoint %s: ignored undecodable input", self.namespace,
                         exc_info=True)
                continue
            if msg is None:
                continue
            kind = msg.get_type()
            if self.faults.drop_incoming[kind] > 0:
                self.faults.drop_incoming[kind] -= 1
                self.faults.dropped[f"in:{kind}"] += 1
                continue
            if kind == "BAD_DATA":
                refusal = signature_refusal(msg)
                if refusal is not None:
                    self._refuse_signature(refusal, msg)
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
                self.errors += 1
                log.exception("endpoint %s: handling %s failed", self.namespace, kind)

    # ---- signing -------------------------------------------------------------------------

    @property
    def signing(self) -> bool:
        """True while the vehicle signs what it sends and takes only signed messages."""
        return self.conn.mav.signing.secret_key is not None

    def _sign_with(self, key: bytes, initial_timestamp: int | None = None) -> None:
        with self._send_lock:  # not while a message is being signed
            self.conn.setup_signing(key, sign_outgoing=True,
                                    allow_unsigned_callback=self._accept_unsigned,
                                    initial_timestamp=initial_timestamp)

    @staticmethod
    def _accept_unsigned(mav: Any, msg_id: int) -> bool:
        return msg_id in UNSIGNED_ACCEPTED

    def _refuse_signature(self, refusal: str, msg: Any) -> None:
        """A message that failed the signature check (pymavlink dropped it): counted, and
        logged the first time per kind and sender and every 100th — a flood must not flood
        the log."""
        data = bytes(msg.data)
        v2 = data[:1] == bytes([mavlink.PROTOCOL_MARKER_V2])
        msg_id = (int.from_bytes(data[7:10], "little") if v2 and len(data) >= 10
                  else data[5] if not v2 and len(data) > 5 else -1)
        known = mavlink.mavlink_map.get(msg_id)
        kind = known.msgname if known is not None else f"message id {msg_id}"
        source = data[5 if v2 else 3] if len(data) > 6 else "?"
        reason = f"{refusal} {kind}"
        self.ignored[reason] += 1
        count = self.ignored[reason]
        first = (reason, source) not in self._refusals_told
        if first and len(self._refusals_told) < 1000:  # bounded: system ids can be forged
            self._refusals_told.add((reason, source))
        if first or count % 100 == 0:
            log.warning("endpoint %s: ignored %s %s from system %s (signing is on; %d so "
                        "far)", self.namespace, "an" if refusal == "unsigned" else "a",
                        reason, source, count)

    def _on_setup_signing(self, msg: Any) -> None:
        """SETUP_SIGNING: a new key (all zeros with timestamp 0: signing off). As
        ArduPilot: refused while armed; on a signing link it only arrives signed with the
        current key (anything else was dropped before it got here)."""
        if self.armed:
            self._ignore("SETUP_SIGNING while armed")
            self._statustext(mavlink.MAV_SEVERITY_ERROR,
                             "ERROR: Won't setup signing when armed")
            return
        key = bytes(msg.secret_key)
        if len(key) != 32:
            self._ignore("SETUP_SIGNING with a key that is not 32 bytes")
            return
        if not any(key) and msg.initial_timestamp == 0:
            with self._send_lock:
                self.conn.disable_signing()
            log.warning("endpoint %s: signing turned off by system %d", self.namespace,
                        msg.get_srcSystem())
            return
        self._sign_with(key, max(int(msg.initial_timestamp),
                                 int(self.conn.mav.signing.timestamp or 0)) or None)
        log.warning("endpoint %s: signing key set by system %d", self.namespace,
                    msg.get_srcSystem())

    def _ignore(self, reason: str) -> None:
        self.ignored[reason] += 1
        self._reason = reason
        log.info("endpoint %s: ignored %s", self.namespace, reason)

    def _tell(self, reason: str | None) -> None:
        """A refusal, told to the ground station as a STATUSTEXT (ArduPilot explains its
        refusals the same way: "Arm: …", "Mode change failed", "Param write denied")."""
        if reason:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, reason)

    def _set_mode(self, name: str) -> None:
        if name != self.mode:
            log.debug("endpoint %s: mode %s -> %s", self.namespace, self.mode, name)
        self.mode = name
        self._landing = False
        self._velocity = None
        self._yaw_target = self._yaw_rate_target = None
        if name == "GUIDED":
            x, y, alt, *_ = self._where()
            self._target = (x, y, alt if self.kind == COPTER else None)

    def _mode_allowed(self, name: str) -> bool:
        if name == "AUTO":
            return len(self._mission) > 1  # ArduPilot refuses AUTO without a mission
        return True

    def _set_mode_common(self, base_mode: float, custom_mode: float) -> int:
        """ArduPilot's _set_mode_common: the custom mode, when the base mode's
        CUSTOM_MODE_ENABLED flag is set. A malformed number is DENIED (invalid parameter),
        a mode the vehicle lacks or cannot enter now FAILED, as ArduPilot answers."""
        if not (_whole(base_mode, 0, 255) and _whole(custom_mode, 0, _MAX_UINT32)):
            self._ignore(f"mode change with base mode {base_mode}, custom mode {custom_mode}: "
                         f"not integers in range")
            return _DENIED
        if not int(base_mode) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            self._ignore(f"mode change without MAV_MODE_FLAG_CUSTOM_MODE_ENABLED "
                         f"(base mode {int(base_mode)})")
            return _DENIED
        name = mode_name(self.kind, int(custom_mode))
        if name not in self.modes or not self._mode_allowed(name):
            self._ignore(f"mode {name} for a {self.kind}" + (
                "" if name in self.modes else f" (valid: {', '.join(sorted(self.modes))})"))
            return _FAILED
        self._set_mode(name)
        return _ACCEPTED

    # -- commands (COMMAND_LONG and COMMAND_INT: always answered with a COMMAND_ACK)

    def _on_command_long(self, msg: Any) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                  msg.param7)
        self._answer(msg, msg.command, params, frame=None)

    def _on_command_int(self, msg: Any) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x / 1e7, msg.y / 1e7,
                  msg.z)
        self._answer(msg, msg.command, params, frame=msg.frame, lat_lon_e7=(msg.x, msg.y))

    def _answer(self, msg: Any, command: int, params: tuple[float, ...], *,
                frame: int | None, lat_lon_e7: tuple[int, int] | None = None) -> None:
        self._reason = None
        try:
            result = self._command(command, params, frame, lat_lon_e7)
        except Exception:  # answered even then: a ground station waits for it
            self.errors += 1
            log.exception("endpoint %s: command %d failed", self.namespace, command)
            result = _FAILED
        self._ack(command, result, msg)
        if result in (_DENIED, _FAILED):
            self._tell(self._reason)

    def _command(self, cmd: int, p: tuple[float, ...], frame: int | None,
                 lat_lon_e7: tuple[int, int] | None) -> int:
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_disarm(p[0], p[1])
        if cmd == mavlink.MAV_CMD_DO_SET_MODE:
            return self._set_mode_common(p[0], p[1])
        if cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            return self._takeoff(p[6], frame)
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            if not _whole(p[0], 0, 2**24 - 1):
                self._ignore(f"REQUEST_MESSAGE of message id {p[0]}")
                return _DENIED
            send = self._on_request.get(int(p[0]))
            if send is None:
                self._ignore(f"REQUEST_MESSAGE of message id {int(p[0])}: not sent by "
                             f"this vehicle")
                return _UNSUPPORTED
            send()
            return _ACCEPTED
        if cmd == mavlink.MAV_CMD_GET_HOME_POSITION:
            self._send_home()
            return _ACCEPTED
        if cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            if p[0] != 1.0:  # "1: request autopilot version"
                return _ACCEPTED
            self._send_version()
            return _ACCEPTED
        if cmd == mavlink.MAV_CMD_MISSION_START:
            # ArduPilot: switch to AUTO and run the mission from its current item;
            # param1/param2 (first/last item) are not honoured by ArduPilot either.
            return self._set_mode_common(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                         self.modes["AUTO"])
        if cmd == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._set_mode_common(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                         self.modes["RTL"])
        if cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(p[0], p[1])
        if cmd == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            name = self._streamed(p[0])
            if name is None:
                return _DENIED
            interval = self.intervals[name]
            micros = -1 if interval is None else round(interval * 1e6)
            msg_id = int(p[0])
            self._send("MESSAGE_INTERVAL", lambda mav: mav.message_interval_send(
                msg_id, micros))
            return _ACCEPTED
        if cmd == mavlink.MAV_CMD_DO_REPOSITION:
            return self._reposition(p, frame, lat_lon_e7)
        if cmd == mavlink.MAV_CMD_NAV_LAND and self.kind == COPTER:
            return self._set_mode_common(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                         self.modes["LAND"])
        self._ignore(f"command {cmd}: not supported")
        return _UNSUPPORTED

    def _arm_disarm(self, action: float, force: float) -> int:
        """ArduPilot: param1 exactly 1 arms, exactly 0 disarms, anything else is
        UNSUPPORTED; a flying Copter disarms only when forced (param2 = 21196)."""
        if action == 1.0:
            self.armed = True
            return _ACCEPTED
        if action != 0.0:  # NaN, 0.5, 2 …
            self._ignore(f"ARM_DISARM with param1 = {action} (1 arms, 0 disarms)")
            return _UNSUPPORTED
        if not self.armed:
            return _ACCEPTED
        if self._airborne() and force != _FORCE_DISARM:
            self._ignore("disarm in the air without force (param2 = 21196)")
            return _FAILED
        self.armed = False
        self._velocity = None
        return _ACCEPTED

    def _takeoff(self, alt_m: float, frame: int | None) -> int:
        """ArduCopter's user takeoff: armed, in GUIDED, on the ground, upwards; the
        altitude must be a number under the fence's ceiling."""
        if self.kind != COPTER:
            return _UNSUPPORTED
        if frame is not None and frame not in _TAKEOFF_FRAMES:
            self._ignore(f"NAV_TAKEOFF in frame {frame} (GLOBAL_RELATIVE_ALT only)")
            return _DENIED
        if not math.isfinite(alt_m) or alt_m > self.fence.alt_max_m:
            self._ignore(f"NAV_TAKEOFF to {alt_m} m (0 < altitude ≤ "
                         f"{self.fence.alt_max_m:g} m)")
            return _DENIED
        if not self.armed or self.mode != "GUIDED" or self._airborne() or alt_m <= 0:
            self._ignore(f"NAV_TAKEOFF to {alt_m} m: needs armed, GUIDED, on the ground, "
                         f"upwards (armed={self.armed}, mode {self.mode}, "
                         f"airborne={self._airborne()})")
            return _FAILED
        x, y, *_ = self._where()
        self._velocity = None
        self._target = (x, y, float(alt_m))
        return _ACCEPTED

    def _streamed(self, msg_id: float) -> str | None:
        """The name of a streamed message by id, or None (ignored with the reason)."""
        if not _whole(msg_id, 0, 2**24 - 1):
            self._ignore(f"message id {msg_id}: not an integer id")
            return None
        name = mavlink.mavlink_map[int(msg_id)].msgname \
            if int(msg_id) in mavlink.mavlink_map else None
        if name not in self.intervals:
            self._ignore(f"message id {int(msg_id)} ({name or 'unknown'}) is not streamed; "
                         f"streamed: {', '.join(sorted(self.intervals))}")
            return None
        return str(name)

    def _set_interval(self, msg_id: float, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: param2 −1 stops the message, 0 restores its
        default, > 0 is the interval in µs (at most :data:`MAX_STREAM_RATE_HZ`)."""
        name = self._streamed(msg_id)
        if name is None:
            return _DENIED
        if not math.isfinite(interval_us) or (interval_us < 0 and interval_us != -1):
            self._ignore(f"SET_MESSAGE_INTERVAL of {name} to {interval_us} µs (−1 stops it, "
                         f"0 is the default, > 0 an interval)")
            return _DENIED
        if interval_us == -1:
            self.intervals[name] = None
        elif interval_us == 0:
            self.intervals[name] = self._defaults[name]
        else:
            self.intervals[name] = max(interval_us / 1e6, 1.0 / MAX_STREAM_RATE_HZ)
        self._due[name] = 0.0  # from the next step on
        return _ACCEPTED

    def _on_request_data_stream(self, msg: Any) -> None:
        """The older way (MAVProxy, Mission Planner): a group of messages at a rate in Hz,
        started (start_stop 1) or stopped (0 or rate 0)."""
        if msg.req_stream_id == mavlink.MAV_DATA_STREAM_ALL:
            names = tuple(n for group in _DATA_STREAMS.values() for n in group)
        elif msg.req_stream_id in _DATA_STREAMS:
            names = _DATA_STREAMS[msg.req_stream_id]
        else:
            self._ignore(f"REQUEST_DATA_STREAM of stream {msg.req_stream_id} (known: "
                         f"{sorted(_DATA_STREAMS)} and 0, all)")
            return
        for name in names:
            if msg.start_stop == 0 or msg.req_message_rate == 0:
                self.intervals[name] = None
            else:
                self.intervals[name] = 1.0 / min(float(msg.req_message_rate),
                                                 MAX_STREAM_RATE_HZ)
            self._due[name] = 0.0

    def _reposition(self, p: tuple[float, ...], frame: int | None,
                    lat_lon_e7: tuple[int, int] | None) -> int:
        """DO_REPOSITION ("go to this point" on a ground station's map), as ArduPilot's
        handle_command_int_do_reposition: in GUIDED, or with the CHANGE_MODE flag (param2
        bit 0) from any mode; param5/6 latitude and longitude, param7 altitude."""
        if lat_lon_e7 is None:  # COMMAND_LONG: degrees as floats
            if not _finite(p[4], p[5]):
                self._ignore(f"DO_REPOSITION to {p[4]}, {p[5]}: not a position")
                return _DENIED
            lat_lon_e7 = (round(p[4] * 1e7), round(p[5] * 1e7))
        lat_e7, lon_e7 = lat_lon_e7
        change_mode = _whole(p[1], 0, _MAX_UINT32) and int(p[1]) & 1
        if self.mode != "GUIDED" and not change_mode:
            self._ignore("DO_REPOSITION outside GUIDED without the CHANGE_MODE flag")
            return _DENIED
        if frame is not None and frame not in _GLOBAL_TARGET_FRAMES:
            self._ignore(f"DO_REPOSITION in frame {frame}")
            return _DENIED
        if not _valid_lat_lon(lat_e7, lon_e7) or (lat_e7 == 0 and lon_e7 == 0) \
                or not math.isfinite(p[6]):
            self._ignore(f"DO_REPOSITION to {lat_e7 / 1e7}°, {lon_e7 / 1e7}°, {p[6]} m: not "
                         f"a position")
            return _DENIED
        x, y = self._world(lat_e7 / 1e7, lon_e7 / 1e7)
        alt = float(p[6])
        if not self.fence.contains(x, y) or (self.kind == COPTER and not
                                             0.0 <= alt <= self.fence.alt_max_m):
            self._ignore(f"DO_REPOSITION to ({x:.2f}, {y:.2f}, {alt:.2f}): outside the fence")
            return _FAILED
        if not self.armed:
            self._ignore("DO_REPOSITION while disarmed")
            return _FAILED
        if self.mode != "GUIDED":
            self._set_mode("GUIDED")
        self._velocity = None
        self._target = (x, y, alt if self.kind == COPTER else None)
        return _ACCEPTED

    def _on_set_mode(self, msg: Any) -> None:
        # ArduPilot answers this (deprecated) message with a COMMAND_ACK whose command is
        # the message id, 11.
        self._reason = None
        result = self._set_mode_common(float(msg.base_mode), float(msg.custom_mode))
        self._ack(mavlink.MAVLINK_MSG_ID_SET_MODE, result, msg)
        if result != _ACCEPTED:
            self._tell(self._reason)

    # -- GUIDED targets

    def _guided(self, what: str) -> bool:
        if self.mode != "GUIDED" or not self.armed:
            self._ignore(f"{what} outside GUIDED or disarmed")
            return False
        return True

    def _refuse_target(self, what: str) -> None:
        """ArduPilot's "input is not valid so stop": a Copter holds where it is; a Rover
        keeps its previous target."""
        self._ignore(what)
        if self.kind == COPTER:
            self._hold()

    def _on_set_position_target_local_ned(self, msg: Any) -> None:
        if not self._guided("position target"):
            return
        if msg.coordinate_frame not in _LOCAL_FRAMES:
            self._refuse_target(f"SET_POSITION_TARGET_LOCAL_NED in frame "
                                f"{msg.coordinate_frame} (LOCAL_NED, LOCAL_OFFSET_NED, "
                                f"BODY_NED, BODY_OFFSET_NED)")
            return
        x, y, alt, yaw, *_ = self._where()
        ned_yaw = math.pi / 2 - yaw
        body = msg.coordinate_frame in _BODY_FRAMES

        def to_world(north: float, east: float) -> tuple[float, float]:
            if body:  # forward, right → north, east
                c, s = math.cos(ned_yaw), math.sin(ned_yaw)
                north, east = north * c - east * s, north * s + east * c
            return east, north

        position = None
        if not msg.type_mask & _POS_IGNORE:
            if not _finite(msg.x, msg.y, msg.z):
                self._refuse_target(f"position target ({msg.x}, {msg.y}, {msg.z}): not finite")
                return
            px, py = to_world(msg.x, msg.y)
            up = -msg.z
            if msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:  # offsets from here
                px, py, up = px + x, py + y, up + alt
            position = (px, py, up)
        self._guided_target(msg, position, to_world, yaw, body)

    def _on_set_position_target_global_int(self, msg: Any) -> None:
        if not self._guided("position target"):
            return
        x, y, alt, yaw, *_ = self._where()
        position = None
        if not msg.type_mask & _POS_IGNORE:
            if not _valid_lat_lon(msg.lat_int, msg.lon_int):
                self._refuse_target(f"position target at {msg.lat_int / 1e7}°, "
                                    f"{msg.lon_int / 1e7}°: not a latitude and longitude")
                return
            if msg.coordinate_frame not in _GLOBAL_TARGET_FRAMES:
                self._refuse_target(f"SET_POSITION_TARGET_GLOBAL_INT in frame "
                                    f"{msg.coordinate_frame} (GLOBAL, GLOBAL_RELATIVE_ALT, "
                                    f"GLOBAL_TERRAIN_ALT and their _INT forms)")
                return
            if not math.isfinite(msg.alt):
                self._refuse_target(f"position target at altitude {msg.alt}: not finite")
                return
            px, py = self._world(msg.lat_int / 1e7, msg.lon_int / 1e7)
            position = (px, py, float(msg.alt))  # the origin is at 0 m: every frame agrees

        def to_world(north: float, east: float) -> tuple[float, float]:
            return east, north

        self._guided_target(msg, position, to_world, yaw, False)

    def _guided_target(self, msg: Any, position: tuple[float, float, float] | None,
                       to_world: Callable[[float, float], tuple[float, float]], yaw: float,
                       body: bool) -> None:
        """What ArduPilot does with a SET_POSITION_TARGET_* once it is decoded: the
        type_mask picks position, velocity, both, or nothing (Copter: stop)."""
        mask = msg.type_mask
        kind = msg.get_type()
        vel_ignore = bool(mask & _VEL_IGNORE)
        acc_ignore = bool(mask & _ACC_IGNORE)
        yaw_ignore = bool(mask & _YAW_IGNORE)
        rate_ignore = bool(mask & _YAW_RATE_IGNORE)
        if mask & _FORCE_SET and not acc_ignore:
            self._refuse_target(f"{kind}: force targets are not supported")
            return
        heading = None
        if not yaw_ignore:
            if not math.isfinite(msg.yaw):
                self._refuse_target(f"{kind}: yaw {msg.yaw} is not finite")
                return
            # NED yaw (0 north, clockwise) → world yaw (0 east, counter-clockwise)
            heading = (yaw + -msg.yaw) if body else math.pi / 2 - msg.yaw
        yaw_rate = None
        if not rate_ignore:
            if not math.isfinite(msg.yaw_rate):
                self._refuse_target(f"{kind}: yaw rate {msg.yaw_rate} is not finite")
                return
            yaw_rate = -float(msg.yaw_rate)
        velocity = None
        if not vel_ignore:
            if not _finite(msg.vx, msg.vy, msg.vz):
                self._refuse_target(f"{kind}: velocity ({msg.vx}, {msg.vy}, {msg.vz}) is not "
                                    f"finite")
                return
            vx, vy = to_world(msg.vx, msg.vy)
            velocity = (vx, vy, -float(msg.vz))
        if position is not None:
            px, py, up = position
            if not self.fence.contains(px, py) or (self.kind == COPTER and not
                                                   0.0 <= up <= self.fence.alt_max_m):
                # ArduPilot refuses a destination outside its fence and keeps the old one.
                self._ignore(f"{kind}: target ({px:.2f}, {py:.2f}, {up:.2f}) outside the "
                             f"fence x {self.fence.x_min:g}–{self.fence.x_max:g}, "
                             f"y {self.fence.y_min:g}–{self.fence.y_max:g}, "
                             f"altitude 0–{self.fence.alt_max_m:g} m")
                return
        if self.kind == COPTER:
            self._copter_target(kind, position, velocity, heading, yaw_rate, acc_ignore)
        else:
            self._rover_target(kind, msg, position, velocity, heading, yaw_rate, yaw,
                               acc_ignore)

    def _copter_target(self, kind: str, position: tuple[float, float, float] | None,
                       velocity: tuple[float, float, float] | None, heading: float | None,
                       yaw_rate: float | None, acc_ignore: bool) -> None:
        if position is not None:  # position, or position and velocity (as a position)
            self._velocity = None
            self._target = position
            self._yaw_target, self._yaw_rate_target = heading, yaw_rate
        elif velocity is not None:
            self._velocity = _Velocity(*velocity, 0.0, heading, yaw_rate,
                                       self.sim.time_s + GUIDED_TIMEOUT_S)
        else:  # acceleration only (not simulated) or nothing: ArduPilot stops
            self._refuse_target(f"{kind}: neither position nor velocity"
                                + ("" if acc_ignore else " (acceleration is not simulated)"))

    def _rover_target(self, kind: str, msg: Any, position: tuple[float, float, float] | None,
                      velocity: tuple[float, float, float] | None, heading: float | None,
                      yaw_rate: float | None, yaw: float, acc_ignore: bool) -> None:
        until = self.sim.time_s + GUIDED_TIMEOUT_S
        if position is not None and velocity is None and heading is None \
                and yaw_rate is None and acc_ignore:
            self._velocity = None
            self._target = (position[0], position[1], None)
            return
        if position is not None or not acc_ignore:
            self._ignore(f"{kind}: this combination of type_mask fields is not used by a "
                         f"rover (type_mask {msg.type_mask:#06x})")
            return
        if velocity is not None:
            vx, vy, _ = velocity
            speed = math.hypot(vx, vy)
            direction = math.atan2(vy, vx) if speed > 0 else yaw
            if heading is not None or yaw_rate is not None:
                # ArduRover: the sign of the velocity's x says forward or reverse
                if msg.vx < 0:
                    speed = -speed
            self._velocity = _Velocity(0.0, 0.0, 0.0, speed,
                                       heading if heading is not None else
                                       (None if yaw_rate is not None else direction),
                                       yaw_rate, until)
        elif heading is not None:
            self._velocity = _Velocity(0.0, 0.0, 0.0, 0.0, heading, None, until)
        elif yaw_rate is not None:
            self._velocity = _Velocity(0.0, 0.0, 0.0, 0.0, None, yaw_rate, until)
        else:
            self._ignore(f"{kind}: nothing to do (type_mask {msg.type_mask:#06x})")

    # -- mission protocol

    def _mission_ack(self, peer: tuple[int, int], result: int, kind: int = 0) -> None:
        self._send("MISSION_ACK", lambda mav: mav.mission_ack_send(*peer, result, kind))

    def _on_mission_count(self, msg: Any) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        if getattr(msg, "mission_type", 0) != mavlink.MAV_MISSION_TYPE_MISSION:
            self._ignore(f"MISSION_COUNT of mission type {msg.mission_type} (fences and "
                         f"rally points are not supported)")
            self._mission_ack(peer, mavlink.MAV_MISSION_UNSUPPORTED)
            return
        count = msg.count
        if count > MAX_MISSION_ITEMS:
            self._ignore(f"MISSION_COUNT {count} > {MAX_MISSION_ITEMS}")
            self._mission_ack(peer, mavlink.MAV_MISSION_NO_SPACE)
            return
        if count == 0:
            self._mission = []
            self.current_seq = 0
            self._upload = None
            self._mission_ack(peer, mavlink.MAV_MISSION_ACCEPTED)
            return
        self._upload = _Upload(count, [], peer)
        self._request(self._upload)

    def _request(self, upload: _Upload) -> None:
        upload.asked_at = time.monotonic()
        upload.asks += 1
        seq = upload.expected
        self._send("MISSION_REQUEST_INT", lambda mav: mav.mission_request_int_send(
            *upload.peer, seq))

    def _check_item(self, msg: Any) -> int | None:
        """The MAV_MISSION_RESULT that refuses item ``msg``, or None when it is good."""
        if msg.seq == 0:
            return None  # home: ArduPilot replaces it
        if msg.frame not in _SUPPORTED_FRAMES:
            return int(mavlink.MAV_MISSION_UNSUPPORTED_FRAME)
        if msg.command not in _SUPPORTED_ITEMS:
            return int(mavlink.MAV_MISSION_UNSUPPORTED)
        for index, value in enumerate((msg.param1, msg.param2, msg.param3, msg.param4)):
            if math.isinf(value):  # NaN is MAVLink's "unset"; infinity is no value
                return int(mavlink.MAV_MISSION_INVALID_PARAM1) + index
        if not math.isfinite(msg.z) or (self.kind == COPTER and not
                                        0.0 <= msg.z <= self.fence.alt_max_m):
            return int(mavlink.MAV_MISSION_INVALID_PARAM7)
        if msg.command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return None
        if not -900_000_000 <= msg.x <= 900_000_000:
            return int(mavlink.MAV_MISSION_INVALID_PARAM5_X)
        if not -1_800_000_000 <= msg.y <= 1_800_000_000:
            return int(mavlink.MAV_MISSION_INVALID_PARAM6_Y)
        if msg.x == 0 and msg.y == 0 and msg.command in _HERE_ITEMS:
            return None
        x, y = self._world(msg.x / 1e7, msg.y / 1e7)
        if not self.fence.y_min <= y <= self.fence.y_max:
            return int(mavlink.MAV_MISSION_INVALID_PARAM5_X)
        if not self.fence.x_min <= x <= self.fence.x_max:
            return int(mavlink.MAV_MISSION_INVALID_PARAM6_Y)
        return None

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
        result = self._check_item(msg)
        if result is not None:
            self._ignore(f"mission item {msg.seq} (command {msg.command}, frame {msg.frame}, "
                         f"x {msg.x}, y {msg.y}, z {msg.z}): "
                         f"{mavlink.enums['MAV_MISSION_RESULT'][result].name}")
            self._upload = None
            self._mission_ack(upload.peer, result)
            self._tell(f"Mission item {msg.seq} refused: "
                       f"{mavlink.enums['MAV_MISSION_RESULT'][result].name[12:]}")
            return
        here = msg.x == 0 and msg.y == 0 and msg.command in _HERE_ITEMS
        if msg.command == mavlink.MAV_CMD_NAV_TAKEOFF or here or msg.seq == 0:
            x, y = None, None  # straight up / where the vehicle is when the item starts
        else:
            x, y = self._world(msg.x / 1e7, msg.y / 1e7)
        upload.items.append(_Item(
            msg.seq, msg.command, x, y, float(msg.z), msg.frame,
            (msg.param1, msg.param2, msg.param3, msg.param4), msg.x, msg.y, msg.autocontinue))
        upload.expected += 1
        upload.asks = 0
        if upload.expected < upload.count:
            self._request(upload)
            return
        self._mission = upload.items
        self._mission[0] = self._home_item()
        self.current_seq = 1 if len(self._mission) > 1 else 0
        self.reached = []
        self._upload = None
        self._mission_ack(upload.peer, mavlink.MAV_MISSION_ACCEPTED)

    def _home_item(self) -> _Item:
        lat, lon = self.origin.to_global(self.home[1], self.home[0])
        return _Item(0, mavlink.MAV_CMD_NAV_WAYPOINT, *self.home, 0.0,
                     mavlink.MAV_FRAME_GLOBAL_INT, (0.0, 0.0, 0.0, 0.0), round(lat * 1e7),
                     round(lon * 1e7))

    def _on_mission_set_current(self, msg: Any) -> None:
        if 0 <= msg.seq < len(self._mission):
            self.current_seq = msg.seq
            self._send_mission_current()
        else:
            self._ignore(f"MISSION_SET_CURRENT {msg.seq} of {len(self._mission)}")

    def _on_mission_clear_all(self, msg: Any) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        kind = getattr(msg, "mission_type", 0)
        if kind == mavlink.MAV_MISSION_TYPE_MISSION:
            self._mission = []
            self.current_seq = 0
            self.reached = []
            self._upload = None
            if self.mode == "AUTO":
                self._set_mode("LOITER" if self.kind == COPTER else "HOLD")
            self._mission_ack(peer, mavlink.MAV_MISSION_ACCEPTED, kind)
        elif kind in (mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_RALLY):
            self._mission_ack(peer, mavlink.MAV_MISSION_ACCEPTED, kind)  # there are none
        else:
            self._ignore(f"MISSION_CLEAR_ALL of mission type {kind}")
            self._mission_ack(peer, mavlink.MAV_MISSION_UNSUPPORTED, kind)

    # -- mission download: MISSION_REQUEST_LIST → MISSION_COUNT → (REQUEST_INT → ITEM_INT)*

    def _on_mission_request_list(self, msg: Any) -> None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        kind = getattr(msg, "mission_type", 0)
        if kind == mavlink.MAV_MISSION_TYPE_MISSION:
            count = len(self._mission)
        elif kind in (mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_RALLY):
            count = 0  # no fence items or rally points (the floor's fence is implicit)
        else:
            self._ignore(f"MISSION_REQUEST_LIST of mission type {kind}")
            self._mission_ack(peer, mavlink.MAV_MISSION_UNSUPPORTED, kind)
            return
        self._send("MISSION_COUNT", lambda mav: mav.mission_count_send(*peer, count, kind))

    def _download_item(self, msg: Any) -> _Item | None:
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        kind = getattr(msg, "mission_type", 0)
        if kind != mavlink.MAV_MISSION_TYPE_MISSION or not 0 <= msg.seq < len(self._mission):
            self._ignore(f"{msg.get_type()} {msg.seq} of mission type {kind} "
                         f"({len(self._mission)} items)")
            self._mission_ack(peer, mavlink.MAV_MISSION_INVALID_SEQUENCE, kind)
            return None
        item: _Item = self._mission[int(msg.seq)]
        return item

    def _on_mission_request_int(self, msg: Any) -> None:
        item = self._download_item(msg)
        if item is None:
            return
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        current = int(item.seq == self.current_seq)
        self._send("MISSION_ITEM_INT", lambda mav: mav.mission_item_int_send(
            *peer, item.seq, item.frame, item.command, current, item.autocontinue,
            *item.params, item.lat_e7, item.lon_e7, item.alt_m))

    def _on_mission_request(self, msg: Any) -> None:
        """The deprecated float form (older ground stations): MISSION_ITEM in degrees."""
        item = self._download_item(msg)
        if item is None:
            return
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        current = int(item.seq == self.current_seq)
        frame = {mavlink.MAV_FRAME_GLOBAL_INT: mavlink.MAV_FRAME_GLOBAL,
                 mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT:
                     mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT}.get(item.frame, item.frame)
        self._send("MISSION_ITEM", lambda mav: mav.mission_item_send(
            *peer, item.seq, frame, item.command, current, item.autocontinue, *item.params,
            item.lat_e7 / 1e7, item.lon_e7 / 1e7, item.alt_m))

    def _on_mission_ack(self, msg: Any) -> None:
        pass  # the end of a download (or a ground station's refusal): nothing to do

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
        if name not in self.params:
            self._ignore(f"PARAM_SET of unknown {name!r}")
            return
        low, high = PARAM_RANGES[name]
        value = msg.param_value
        if not (math.isfinite(value) and low <= value <= high):
            self._ignore(f"PARAM_SET {name} = {value}: outside {low:g}–{high:g}")
            self._tell(f"Param write denied: {name} {low:g}..{high:g}")
            self._param_value(name)  # the unchanged value: the set did not take
            return
        self.params[name] = float(value)
        self._param_value(name)

    # ---- state for tests and checks ------------------------------------------------------

    @property
    def mission(self) -> list[tuple[float, float, float]]:
        """The stored mission as world (x, y, alt) per item (item 0 is home; an item that
        means "where the vehicle is" has x, y NaN until it starts)."""
        with self._lock:
            return [(math.nan if i.x_m is None else i.x_m,
                     math.nan if i.y_m is None else i.y_m, i.alt_m) for i in self._mission]

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


def _port_window() -> range | None:
    """The UDP ports :func:`free_udp_ports` hands out: outside the kernel's ephemeral range
    (Linux: ``/proc/sys/net/ipv4/ip_local_port_range``, 32768-60999 by default), so that
    no socket bound to port 0 — a DDS participant's sender, another test's probe — can be
    given one between the choice and the link's bind: above it when there is room,
    else just below it; None when neither has 1,000 ports (a range of 1024-65535, as some
    containers set)."""
    lo, hi = 32768, 60999
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range", encoding="ascii") as f:
            lo, hi = (int(n) for n in f.read().split())
    except (OSError, ValueError):
        pass
    above, below = range(hi + 1, 65536), range(max(1024, lo - 4000), lo)
    return next((w for w in (above, below) if len(w) >= 1000), None)


_ports_lock = threading.Lock()
_port_cursor = itertools.count()


@functools.cache
def _port_start() -> tuple[range, int]:
    """The window of :func:`_port_window` and this process's random place in it; the
    kernel's ports (bind to port 0) when there is no window."""
    window = _port_window()
    if window is None:
        log.info("MAVLink ports: the kernel's ephemeral range leaves no 1,000 ports free "
                 "around it; ports come from bind(0), which another socket may take "
                 "before the link binds")
        return range(0), 0
    return window, random.randrange(len(window))


def free_udp_ports(count: int) -> list[int]:
    """``count`` distinct free UDP ports on 127.0.0.1 for endpoints' links.

    Never one the kernel gives a socket bound to port 0 (see :func:`_port_window`), never
    the same twice in one process (a vehicle closed late may still send to a port it was
    given), never one of this process's DDS domain's well-known ports
    (7400 + 250 × ``ROS_DOMAIN_ID`` and the 249 after it), and each is free when chosen.
    Processes start at random places in the window, so that two of them rarely meet."""
    domain = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    dds = range(7400 + 250 * domain, 7400 + 250 * domain + 250)
    window, start = _port_start()
    # Port 0 for each without a window: the kernel's, held together so they are distinct.
    candidates = ((window[(start + next(_port_cursor)) % len(window)] for _ in window)
                  if window else iter([0] * count))
    ports: list[int] = []
    held: list[socket.socket] = []
    with _ports_lock:
        try:
            for port in candidates:
                if len(ports) == count:
                    break
                if port in dds:
                    continue
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                held.append(s)
                try:
                    s.bind(("127.0.0.1", port))
                except OSError:
                    continue  # in use
                ports.append(s.getsockname()[1])
        finally:
            for s in held:
                s.close()
    if len(ports) == count:
        return ports
    raise RuntimeError(f"no {count} free UDP ports left in {window.start}-{window.stop - 1}")


def open_endpoints(sim: Simulation, *, base_port: int, host: str = "127.0.0.1",
                   **options: Any) -> dict[str, MavlinkEndpoint]:
    """One endpoint per robot of ``sim``: robot i sends to ``udpout:host:base_port + i``
    with system id i + 1 (by namespace), each with ``options`` (e.g. ``signing_key``).
    Close each when done."""
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
