"""MAVLink vehicles (ArduPilot Rover and Copter, real or simulated): one link per vehicle,
HALs that put its telemetry on the blackboard, and the client side of its protocols.

::

    hals:
      - {class: "hal.mavlink:MavlinkHeartbeatHAL", params: {connection: "udp:127.0.0.1:14550"}}
      - {class: "hal.mavlink:MavlinkPositionHAL", params: {connection: "udp:127.0.0.1:14550"}}

The connection string is pymavlink's: ``udp:HOST:PORT`` / ``udpin:HOST:PORT`` (listen there:
the vehicle, SITL or MAVProxy ``--out``, sends to it), ``udpout:HOST:PORT`` (send there
first), ``tcp:HOST:PORT`` (SITL's 5760), or a serial device ``/dev/ttyUSB0`` (with
``baud``). Every HAL and every action that names the same connection string in one process
shares one :class:`MavlinkLink` (:func:`open_link`, reference counted).

==========================  ========================================================
HAL ``name``                blackboard keys (writer ``hal:<name>``)
==========================  ========================================================
``mavlink_heartbeat``       ``vehicle/connected``, ``vehicle/armed``, ``vehicle/mode``,
                            ``vehicle/system_status``, ``vehicle/type``
``mavlink_position``        ``position/lat_deg``, ``position/lon_deg``, ``position/alt_m``
                            (above home), ``position/north_m``, ``position/east_m``,
                            ``position/down_m``, ``position/vn_mps``, ``position/ve_mps``,
                            ``position/heading_deg``
``mavlink_attitude``        ``attitude/roll_rad``, ``attitude/pitch_rad``,
                            ``attitude/yaw_rad``
``mavlink_battery``         ``battery/percentage``, ``battery/voltage_v``,
                            ``battery/current_a``
``mavlink_mission``         ``mission/current``, ``mission/reached`` (sequence numbers)
``mavlink_params``          ``param/<NAME>`` for every PARAM_VALUE heard; methods
                            ``get(name)``, ``set(name, value)``
==========================  ========================================================

**Lost heartbeat.** The link expects the vehicle's HEARTBEAT at least every
``heartbeat_timeout_s`` (default 3 s; ArduPilot sends 1 Hz). Past that it reports the
vehicle lost: every HAL marks all of its entries stale and sets ``vehicle/connected`` to
False, and every wait of the protocol functions below raises
:class:`~beehave.errors.VehicleLost` — so the actions waiting on it stop. The first
heartbeat that comes back makes the link alive again (the entries become fresh with the
next messages). The silence is judged only once the link has read everything waiting in
its socket: a process starved past the timeout (a loaded host) finds the vehicle's latest
heartbeats behind a backlog of telemetry, and does not call it lost for that.

**What is ignored.** Messages from another system id than the vehicle's (the first
autopilot heartbeat fixes it unless ``system_id`` is given), MAVLink frames that fail
their checksum, and protocol messages nobody waits for (a MISSION_REQUEST_INT outside an
upload, an out-of-order one) are counted in :attr:`MavlinkLink.ignored` and logged at
debug level; nothing of that reaches a HAL or raises.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import select
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from beehave import runnable as _runnable
from beehave.errors import (
    CommandRejected,
    ConfigError,
    Interrupted,
    MavlinkError,
    MavlinkTimeout,
    UnknownMode,
    VehicleLost,
)
from beehave.hal import HAL, check_duration_s
from beehave.lifecycle import Closing

os.environ.setdefault("MAVLINK20", "1")  # MISSION_*_INT and mission_type need MAVLink 2
from pymavlink import mavutil  # type: ignore[import-untyped]  # noqa: E402

log = logging.getLogger(__name__)

mavlink = mavutil.mavlink

__all__ = ["COPTER", "ROVER", "LocalFrame", "MavlinkHAL", "MavlinkLink", "MissionItem",
           "Waypoint", "close_all_links", "load_signing_key", "mode_names", "open_link",
           "vehicle_kind"]

ROVER = "rover"
COPTER = "copter"
CONNECTION_ENV = "BEEHAVE_MAVLINK_CONNECTION"
"""Where a MAVLink HAL loaded by name only (an entry point, no params) finds its link."""
GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = mavlink.MAV_COMP_ID_MISSIONPLANNER
#: At most this many messages are read in one pass of the reader thread.
_BURST = 100

_CONNECTION_FORMS = ("udp:HOST:PORT", "udpin:HOST:PORT", "udpout:HOST:PORT", "tcp:HOST:PORT",
                     "a serial device such as /dev/ttyUSB0 or /dev/ttyACM0")

#: HEARTBEAT.type values that are ground vehicles (Rover firmware) or multicopters
#: (Copter firmware); other types are refused with the list.
_ROVER_TYPES = {mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_TYPE_SURFACE_BOAT}
_COPTER_TYPES = {mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_TYPE_HEXAROTOR,
                 mavlink.MAV_TYPE_OCTOROTOR, mavlink.MAV_TYPE_TRICOPTER,
                 mavlink.MAV_TYPE_COAXIAL, mavlink.MAV_TYPE_HELICOPTER}
MAV_TYPE_OF = {ROVER: mavlink.MAV_TYPE_GROUND_ROVER, COPTER: mavlink.MAV_TYPE_QUADROTOR}

HOLD_MODE = {ROVER: "HOLD", COPTER: "BRAKE"}
"""The mode a vehicle is put in to stand still (an action's safe state)."""

KEY_FILE_ENV = "BEEHAVE_MAVLINK_KEY_FILE"
"""Where a MAVLink HAL loaded by name only finds its signing key file (if any)."""

UNSIGNED_ACCEPTED = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS,
                               mavlink.MAVLINK_MSG_ID_RADIO})
"""Messages a signing vehicle still takes unsigned, as ArduPilot does: what a telemetry
radio injects into the link (it cannot sign)."""


def load_signing_key(path: object) -> bytes:
    """The 32-byte MAVLink 2 signing key in the file ``path``: 64 hexadecimal digits are
    the key itself; any other text is a passphrase, hashed with SHA-256 as MAVProxy's
    ``signing setup`` and QGroundControl do. Leading and trailing blanks are ignored.
    A missing, unreadable or empty file raises :class:`ConfigError` naming it."""
    import hashlib

    if not isinstance(path, str | os.PathLike) or not str(path):
        raise ConfigError(f"MAVLink signing key file must be a path, got {path!r}")
    try:
        text = open(path, encoding="utf-8").read().strip()  # noqa: SIM115
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"MAVLink signing key file {str(path)!r} cannot be read: {exc}") \
            from None
    if not text:
        raise ConfigError(f"MAVLink signing key file {str(path)!r} is empty: write a "
                          f"passphrase or 64 hexadecimal digits into it")
    if len(text) == 64 and all(c in "0123456789abcdefABCDEF" for c in text):
        return bytes.fromhex(text)
    return hashlib.sha256(text.encode("utf-8")).digest()


def signature_refusal(msg: Any) -> str | None:
    """For a BAD_DATA that pymavlink made of a message that failed the signature check:
    ``"unsigned"`` or ``"wrongly signed"`` (a replayed or stale signature counts as wrong);
    None for any other bad data."""
    if getattr(msg, "reason", "") != "Invalid signature":
        return None
    data = bytes(getattr(msg, "data", b"") or b"")
    signed = len(data) > 2 and data[0] == mavlink.PROTOCOL_MARKER_V2 \
        and bool(data[2] & mavlink.MAVLINK_IFLAG_SIGNED)
    return "wrongly signed" if signed else "unsigned"


def vehicle_kind(mav_type: int) -> str:
    """``rover`` or ``copter`` for a HEARTBEAT.type; MavlinkError for other types."""
    if mav_type in _ROVER_TYPES:
        return ROVER
    if mav_type in _COPTER_TYPES:
        return COPTER
    raise MavlinkError(f"vehicle type {mav_type} is neither an ArduPilot Rover "
                       f"({sorted(_ROVER_TYPES)}) nor a Copter ({sorted(_COPTER_TYPES)})")


def mode_names(kind: str) -> dict[str, int]:
    """The firmware's mode numbers by name (ArduPilot's tables as pymavlink ships them)."""
    if kind not in MAV_TYPE_OF:
        raise ConfigError(f"vehicle kind {kind!r} is not known; kinds: {ROVER}, {COPTER}")
    mapping: dict[str, int] = mavutil.mode_mapping_byname(MAV_TYPE_OF[kind])
    return dict(mapping)


def mode_number(kind: str, name: object) -> int:
    """The custom mode number of ``name``; :class:`UnknownMode` lists the valid ones."""
    modes = mode_names(kind)
    if not isinstance(name, str) or name.upper() not in modes:
        raise UnknownMode(str(name), modes, vehicle=kind) from None
    return modes[name.upper()]


def mode_name(kind: str, number: int) -> str:
    for name, value in mode_names(kind).items():
        if value == number:
            return name
    return f"MODE_{number}"


# ---- geometry ---------------------------------------------------------------------------

_EARTH_RADIUS_M = 6378137.0


@dataclass(frozen=True)
class LocalFrame:
    """A flat-earth north/east frame around ``origin`` (lat, lon in degrees): good to a
    few centimetres over the hundreds of metres a mission spans."""

    lat_deg: float
    lon_deg: float

    def to_local(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """(north_m, east_m) of a geodetic position."""
        north = math.radians(lat_deg - self.lat_deg) * _EARTH_RADIUS_M
        east = (math.radians(lon_deg - self.lon_deg) * _EARTH_RADIUS_M
                * math.cos(math.radians(self.lat_deg)))
        return north, east

    def to_global(self, north_m: float, east_m: float) -> tuple[float, float]:
        """(lat_deg, lon_deg) of a local position."""
        lat = self.lat_deg + math.degrees(north_m / _EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(
            east_m / (_EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))))
        return lat, lon


@dataclass(frozen=True)
class Waypoint:
    """A mission waypoint in the vehicle's local frame: metres north and east of its EKF
    origin, ``alt_m`` above home (ignored by rovers)."""

    north_m: float
    east_m: float
    alt_m: float = 0.0

    @classmethod
    def parse(cls, value: object, *, where: str = "waypoint") -> Waypoint:
        """From ``{"north_m": …, "east_m": …, "alt_m": …}`` or ``[north, east(, alt)]``;
        ConfigError names ``where`` and the accepted forms."""
        try:
            if isinstance(value, Waypoint):
                return value
            if isinstance(value, dict):
                unknown = set(value) - {"north_m", "east_m", "alt_m"}
                if unknown:
                    raise ValueError(f"unknown keys {sorted(unknown)}")
                point = cls(float(value["north_m"]), float(value["east_m"]),
                            float(value.get("alt_m", 0.0)))
            elif isinstance(value, list | tuple) and len(value) in (2, 3):
                point = cls(*(float(v) for v in value))
            else:
                raise ValueError("wrong shape")
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: expected {{north_m, east_m, alt_m}} or [north_m, "
                              f"east_m(, alt_m)] with finite numbers, got {value!r:.80} "
                              f"({exc})") from None
        if not all(math.isfinite(v) for v in (point.north_m, point.east_m, point.alt_m)):
            raise ConfigError(f"{where}: coordinates must be finite, got {value!r:.80}")
        return point

    def as_dict(self) -> dict[str, float]:
        return {"north_m": self.north_m, "east_m": self.east_m, "alt_m": self.alt_m}


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT as the mission protocol carries it."""

    seq: int
    command: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    frame: int = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


# ---- the link ---------------------------------------------------------------------------

def _check_url(url: object) -> str:
    if not isinstance(url, str) or not url:
        raise ConfigError(f"MAVLink connection must be a string: {', '.join(_CONNECTION_FORMS)}; "
                          f"got {url!r}")
    scheme = url.split(":", 1)[0]
    if scheme in ("udp", "udpin", "udpout", "tcp", "tcpin"):
        parts = url.split(":")
        if len(parts) != 3 or not parts[2].isdigit() or not 0 < int(parts[2]) < 65536:
            raise ConfigError(f"MAVLink connection {url!r}: expected {scheme}:HOST:PORT with a "
                              f"port 1–65535")
        return url
    if url.startswith(("/dev/", "COM")):
        return url
    raise ConfigError(f"MAVLink connection {url!r} is not supported; use one of: "
                      f"{', '.join(_CONNECTION_FORMS)}")


class Inbox(Closing):
    """Messages of some types that arrive after it was opened (:meth:`MavlinkLink.listen`),
    for a protocol step that sends, then waits for the answer. Close it (``with``)."""

    def __init__(self, link: MavlinkLink, types: frozenset[str]) -> None:
        self.link = link
        self.types = types
        self._items: list[Any] = []
        self._cond = threading.Condition()

    def _put(self, msg: Any) -> None:
        with self._cond:
            self._items.append(msg)
            self._cond.notify_all()

    def _poke(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def wait(self, predicate: Callable[[Any], bool] = lambda m: True, *,
             timeout_s: float, what: str) -> Any | None:
        """The first message (of this inbox's types) for which ``predicate`` is true, or
        None after ``timeout_s``. Raises :class:`VehicleLost` when the heartbeat is lost
        meanwhile and :class:`Interrupted` when the calling Behavior or Action is."""
        deadline = time.monotonic() + timeout_s
        node = _runnable.current()
        while True:
            with self._cond:
                while self._items:
                    msg = self._items.pop(0)
                    if predicate(msg):
                        return msg
                    self.link._ignore(f"unexpected {msg.get_type()} while waiting for {what}",
                                      msg)
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(min(left, 0.05))
            if not self.link.alive:
                raise VehicleLost(f"{self.link.describe()}: heartbeat lost while waiting for "
                                  f"{what}")
            if node is not None and node._interrupt_requested:
                raise Interrupted(f"{node.path}: interrupted while waiting for {what} from "
                                  f"{self.link.describe()}")

    def close(self) -> None:
        self.link._remove_inbox(self)



MessageCallback = Callable[[Any], None]
LinkCallback = Callable[[bool], None]


class MavlinkLink(Closing):
    """One MAVLink connection to one vehicle, with a reader thread it owns.

    Made by :func:`open_link` (shared per connection string); :meth:`close` ends it once
    the last user closed it. The reader thread parses every message, drops what is not
    from the vehicle, keeps the latest of each type, calls the callbacks of
    :meth:`on_message` (in the reader thread: keep them short) and sends the ground
    station's own HEARTBEAT once a second (ArduPilot's GCS failsafe expects it; over
    ``udpout``/``udpin`` it also tells the vehicle where to send).

    ``system_id``: the vehicle's MAVLink system id (None: the first autopilot heartbeat
    decides). ``heartbeat_timeout_s``: see the module doc. ``retries`` / ``timeout_s``:
    how often and how long each protocol step waits for its answer before it resends.
    ``signing_key_file``: MAVLink 2 signing with the key in that file
    (:func:`load_signing_key`): everything sent is signed, and only messages signed with
    the key are taken — unsigned or wrongly signed ones are dropped, counted in
    :attr:`ignored` and logged (the first of each kind).
    """

    def __init__(self, url: str, *, system_id: int | None = None,
                 heartbeat_timeout_s: float = 3.0, timeout_s: float = 1.0, retries: int = 3,
                 baud: int = 57600, source_system: int = GCS_SYSTEM_ID,
                 signing_key_file: str | None = None) -> None:
        self.url = _check_url(url)
        self.signing_key_file = signing_key_file
        key = None if signing_key_file is None else load_signing_key(signing_key_file)
        if system_id is not None and not (isinstance(system_id, int) and 1 <= system_id <= 255):
            raise ConfigError(f"MAVLink {url}: system_id must be 1–255, got {system_id!r}")
        self.heartbeat_timeout_s = check_duration_s(f"MAVLink {url}: heartbeat_timeout_s",
                                                    heartbeat_timeout_s)
        self.timeout_s = check_duration_s(f"MAVLink {url}: timeout_s", timeout_s)
        if not isinstance(retries, int) or retries < 0:
            raise ConfigError(f"MAVLink {url}: retries must be an int ≥ 0, got {retries!r}")
        self.retries = retries
        self.system_id = system_id
        self.component_id = 1
        self.kind: str | None = None
        self.armed = False
        self.mode = ""
        self.origin: LocalFrame | None = None
        #: Messages that were not taken, by reason (wrong system id, bad CRC, unexpected).
        self.ignored: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._latest: dict[str, tuple[Any, float]] = {}
        self._callbacks: dict[str, list[MessageCallback]] = {}
        self._link_callbacks: list[LinkCallback] = []
        self._inboxes: list[Inbox] = []
        self._last_heartbeat = -math.inf
        self._alive = False
        self._alive_event = threading.Event()
        self._stop = threading.Event()
        self._users = 1
        try:
            self.conn = mavutil.mavlink_connection(
                url, baud=baud, source_system=source_system,
                source_component=GCS_COMPONENT_ID, autoreconnect=True)
        except Exception as exc:
            raise MavlinkError(f"MAVLink {url}: cannot open the connection: {exc}") from exc
        if key is not None:  # before the reader thread: nothing unsigned slips through
            self.conn.setup_signing(key, sign_outgoing=True)
        self._thread = threading.Thread(target=self._read, name=f"beehave:mavlink:{url}",
                                        daemon=True)
        self._thread.start()

    # ---- state ------------------------------------------------------------------------

    @property
    def alive(self) -> bool:
        """True while the vehicle's heartbeat comes within ``heartbeat_timeout_s``."""
        return self._alive

    def describe(self) -> str:
        return f"MAVLink {self.url} (system {self.system_id or '?'})"

    def wait_heartbeat(self, *, timeout_s: float = 10.0) -> None:
        """Block until the vehicle is alive (its first heartbeat); MavlinkTimeout names
        the connection otherwise."""
        if not self._alive_event.wait(timeout_s):
            raise MavlinkTimeout(f"{self.describe()}: no heartbeat from a vehicle within "
                                 f"{timeout_s} s (is it running and sending to this "
                                 f"address?)")

    def latest(self, msg_type: str) -> Any | None:
        """The newest message of ``msg_type`` from the vehicle (None: none yet)."""
        with self._lock:
            entry = self._latest.get(msg_type)
        return None if entry is None else entry[0]

    def require_kind(self) -> str:
        if self.kind is None:
            self.wait_heartbeat(timeout_s=self.heartbeat_timeout_s * 2)
        assert self.kind is not None
        return self.kind

    # ---- subscriptions ----------------------------------------------------------------

    def on_message(self, types: Iterable[str], callback: MessageCallback) -> Callable[[], None]:
        """Call ``callback(msg)`` in the reader thread for each message of ``types`` from
        the vehicle; returns the function that removes it."""
        names = list(types)
        with self._lock:
            for name in names:
                self._callbacks.setdefault(name, []).append(callback)

        def remove() -> None:
            with self._lock:
                for name in names:
                    if callback in self._callbacks.get(name, []):
                        self._callbacks[name].remove(callback)

        return remove

    def on_link(self, callback: LinkCallback) -> Callable[[], None]:
        """``callback(alive)`` when the heartbeat is lost (False) or back (True)."""
        with self._lock:
            self._link_callbacks.append(callback)

        def remove() -> None:
            with self._lock:
                if callback in self._link_callbacks:
                    self._link_callbacks.remove(callback)

        return remove

    def listen(self, *types: str) -> Inbox:
        """An :class:`Inbox` for the messages of ``types`` from now on."""
        inbox = Inbox(self, frozenset(types))
        with self._lock:
            self._inboxes.append(inbox)
        return inbox

    def _remove_inbox(self, inbox: Inbox) -> None:
        with self._lock:
            if inbox in self._inboxes:
                self._inboxes.remove(inbox)

    def _ignore(self, reason: str, msg: Any = None) -> None:
        self.ignored[reason.split(" while")[0]] += 1
        log.debug("%s: ignored %s: %s", self.describe(), reason, msg)

    # ---- sending ----------------------------------------------------------------------

    def send(self, build: Callable[[Any], Any]) -> None:
        """``build(mav)`` sends one message with pymavlink's ``mav.*_send`` (serialised:
        the sequence number and the socket are shared)."""
        with self._send_lock:
            build(self.conn.mav)

    # ---- reader thread ----------------------------------------------------------------

    def _read(self) -> None:
        next_beat = 0.0
        backlog_since: float | None = None  # since when each pass left messages waiting
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_beat:
                next_beat = now + 1.0
                try:
                    self.send(lambda mav: mav.heartbeat_send(
                        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                        mavlink.MAV_STATE_ACTIVE))
                except OSError as exc:  # udpin before the peer is known, a closed port
                    log.debug("%s: GCS heartbeat not sent: %s", self.describe(), exc)
            try:
                messages, drained = self._receive()
            except Exception as exc:  # a broken socket must not end the link for good
                if self._stop.is_set():
                    return
                log.warning("%s: receive failed: %r", self.describe(), exc)
                self._stop.wait(0.1)
                messages, drained = [], True
            for msg in messages:
                try:
                    self._dispatch(msg)
                except Exception:
                    log.exception("%s: handling %s failed", self.describe(), msg.get_type())
            # Not while a backlog waits (a heartbeat may wait behind it, after this process
            # was starved), unless it lasted a whole heartbeat timeout (a flood must not
            # keep a lost vehicle from being called lost).
            if drained:
                backlog_since = None
            elif backlog_since is None:
                backlog_since = now
            if backlog_since is None or now - backlog_since > self.heartbeat_timeout_s:
                self._check_heartbeat()

    def _receive(self) -> tuple[list[Any], bool]:
        """The messages that arrived, waiting at most 50 ms for the first, and whether
        nothing more waits (a burst is read at most :data:`_BURST` at a time: after this
        process was starved, the vehicle's latest heartbeat may still wait behind the
        backlog, and its silence is not to be judged before it is read).

        pymavlink's connections are not thread-safe: reading a UDP server socket adds to
        the set of clients that a write iterates. So the wait happens outside the send
        lock (``select`` on the connection's descriptor) and the reading inside it; the
        messages are handled after it is released (a callback may send)."""
        fd = getattr(self.conn, "fd", None)
        if fd is None:  # no descriptor to wait on: pymavlink waits (not shared with writes)
            # One message a call tells nothing of a backlog: taken as drained, or a link
            # that always has a message waiting would never judge the heartbeat.
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            return ([], True) if msg is None else ([msg], True)
        ready, _, _ = select.select([fd], [], [], 0.05)
        if not ready:
            return [], True
        messages: list[Any] = []
        with self._send_lock:
            for _ in range(_BURST):  # the rest comes with the next pass
                msg = self.conn.recv_match(blocking=False)
                if msg is None:
                    return messages, True
                messages.append(msg)
        return messages, False

    def _dispatch(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            refusal = signature_refusal(msg)
            if refusal is None:
                self._ignore("bad data (CRC or framing)")
                return
            reason = f"{refusal} message"
            if not self.ignored[reason]:
                log.warning("%s: ignored %s %s (signing is on: check that the vehicle has "
                            "the key of %s)", self.describe(),
                            "an" if refusal == "unsigned" else "a", reason,
                            self.signing_key_file)
            self._ignore(reason)
            return
        source = msg.get_srcSystem()
        if kind == "HEARTBEAT":
            if msg.type == mavlink.MAV_TYPE_GCS or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
                return  # another ground station (or our own echo), not the vehicle
            if self.system_id is None:
                self.system_id = source
                self.component_id = msg.get_srcComponent()
        if self.system_id is None or source != self.system_id:
            self._ignore(f"message from system {source}", msg)
            return
        now = time.monotonic()
        if kind == "HEARTBEAT":
            try:
                self.kind = vehicle_kind(msg.type)
            except MavlinkError as exc:
                self._ignore(str(exc), msg)
                return
            self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.mode = mode_name(self.kind, msg.custom_mode)
            self._last_heartbeat = now
        elif kind == "GPS_GLOBAL_ORIGIN":
            self.origin = LocalFrame(msg.latitude / 1e7, msg.longitude / 1e7)
        with self._lock:
            self._latest[kind] = (msg, now)
            callbacks = list(self._callbacks.get(kind, ()))
            inboxes = [i for i in self._inboxes if kind in i.types]
        if kind == "HEARTBEAT" and not self._alive:
            self._set_alive(True)
        for inbox in inboxes:
            inbox._put(msg)
        for callback in callbacks:
            try:
                callback(msg)
            except Exception:  # one broken consumer must not starve the others
                log.exception("%s: callback for %s failed", self.describe(), kind)

    def _check_heartbeat(self) -> None:
        if self._alive and time.monotonic() - self._last_heartbeat > self.heartbeat_timeout_s:
            log.warning("%s: no heartbeat for %.1f s: vehicle lost", self.describe(),
                        self.heartbeat_timeout_s)
            self._set_alive(False)

    def _set_alive(self, alive: bool) -> None:
        self._alive = alive
        if alive:
            self._alive_event.set()
        else:
            self._alive_event.clear()
        with self._lock:
            callbacks = list(self._link_callbacks)
            inboxes = list(self._inboxes)
        for inbox in inboxes:
            inbox._poke()
        for callback in callbacks:
            try:
                callback(alive)
            except Exception:
                log.exception("%s: link callback failed", self.describe())

    # ---- protocols (blocking; for Actions, or asyncio.to_thread in Logics) --------------

    def _require_alive(self, what: str) -> None:
        if not self._alive:
            raise VehicleLost(f"{self.describe()}: cannot {what}: no heartbeat from the "
                              f"vehicle (lost, or not heard yet)")

    def command(self, command: int, *params: float, what: str = "") -> None:
        """COMMAND_LONG with retries (``confirmation`` counts up, as the spec asks) until
        its COMMAND_ACK; CommandRejected when the result is not ACCEPTED."""
        label = what or mavlink.enums["MAV_CMD"][command].name
        self._require_alive(label)
        values = [*params, *([0.0] * (7 - len(params)))]
        with self.listen("COMMAND_ACK") as inbox:
            for attempt in range(self.retries + 1):
                def send(mav: Any, confirmation: int = attempt) -> None:
                    mav.command_long_send(self.system_id, self.component_id, command,
                                          confirmation, *values)

                self.send(send)
                ack = inbox.wait(lambda m: m.command == command, timeout_s=self.timeout_s,
                                 what=f"the COMMAND_ACK of {label}")
                if ack is None:
                    continue
                if ack.result == mavlink.MAV_RESULT_IN_PROGRESS:
                    continue
                if ack.result != mavlink.MAV_RESULT_ACCEPTED:
                    result = mavlink.enums["MAV_RESULT"][ack.result].name
                    raise CommandRejected(f"{self.describe()}: {label} rejected: {result}",
                                          result=result)
                return
        raise MavlinkTimeout(f"{self.describe()}: no COMMAND_ACK for {label} after "
                             f"{self.retries + 1} tries of {self.timeout_s} s")

    def request_mode(self, name: str) -> None:
        """Send the mode change once and do not wait (safe states: they must be short)."""
        kind = self.require_kind()
        number = mode_number(kind, name)
        self.send(lambda mav: mav.command_long_send(
            self.system_id, self.component_id, mavlink.MAV_CMD_DO_SET_MODE, 0,
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number, 0, 0, 0, 0, 0))

    def set_mode(self, name: str) -> None:
        """Switch the flight mode (MAV_CMD_DO_SET_MODE) and wait until the heartbeat shows
        it. :class:`UnknownMode` lists the modes of this vehicle's firmware."""
        kind = self.require_kind()
        number = mode_number(kind, name)
        self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                     number, what=f"set mode {name.upper()}")
        self._wait_state(lambda: self.mode == name.upper(), f"mode {name.upper()}")

    def arm(self, armed: bool = True) -> None:
        """Arm (or disarm) the motors and wait until the heartbeat shows it."""
        self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if armed else 0.0,
                     what="arm" if armed else "disarm")
        self._wait_state(lambda: self.armed == armed, "armed" if armed else "disarmed")

    def _wait_state(self, done: Callable[[], bool], what: str) -> None:
        with self.listen("HEARTBEAT") as inbox:
            if done():
                return
            if inbox.wait(lambda m: done(), timeout_s=self.heartbeat_timeout_s * 2,
                          what=f"a heartbeat showing {what}") is None:
                raise MavlinkTimeout(f"{self.describe()}: the vehicle acknowledged but its "
                                     f"heartbeat did not show {what}")

    def takeoff(self, alt_m: float) -> None:
        """MAV_CMD_NAV_TAKEOFF to ``alt_m`` above home (Copter, armed, in GUIDED)."""
        _require_finite("takeoff altitude", alt_m)
        if alt_m <= 0:
            raise ConfigError(f"takeoff altitude must be above 0 m, got {alt_m}")
        self.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, alt_m,
                     what=f"take off to {alt_m} m")

    def goto_local(self, north_m: float, east_m: float, alt_m: float | None = None) -> None:
        """SET_POSITION_TARGET_LOCAL_NED (position only) in GUIDED; no answer is expected
        (the vehicle's position tells). ``alt_m`` None keeps the altitude."""
        _require_finite("position target", north_m, east_m,
                        *(() if alt_m is None else (alt_m,)))
        self._require_alive("send a position target")
        down = -alt_m if alt_m is not None else self._down_now()
        mask = 0b0000_1101_1111_1000  # use x, y, z; ignore velocity, acceleration, yaw rate
        self.send(lambda mav: mav.set_position_target_local_ned_send(
            0, self.system_id, self.component_id, mavlink.MAV_FRAME_LOCAL_NED, mask,
            north_m, east_m, down, 0, 0, 0, 0, 0, 0, 0, 0))

    def _down_now(self) -> float:
        local = self.latest("LOCAL_POSITION_NED")
        return float(local.z) if local is not None else 0.0

    def local_position(self) -> tuple[float, float, float]:
        """(north_m, east_m, alt_m) from the newest LOCAL_POSITION_NED (the first one is
        waited for, at most ``heartbeat_timeout_s``: it follows the first heartbeat)."""
        local = self.latest("LOCAL_POSITION_NED")
        if local is None:
            with self.listen("LOCAL_POSITION_NED") as inbox:
                local = self.latest("LOCAL_POSITION_NED") or inbox.wait(
                    timeout_s=self.heartbeat_timeout_s, what="the first LOCAL_POSITION_NED")
        if local is None:
            raise MavlinkError(f"{self.describe()}: no LOCAL_POSITION_NED within "
                               f"{self.heartbeat_timeout_s} s (does the vehicle have a "
                               f"position estimate?)")
        return float(local.x), float(local.y), -float(local.z)

    def frame(self) -> LocalFrame:
        """The vehicle's local frame origin (GPS_GLOBAL_ORIGIN; asked for if not heard)."""
        if self.origin is None:
            self._require_alive("read the origin")
            with self.listen("GPS_GLOBAL_ORIGIN") as inbox:
                for _ in range(self.retries + 1):
                    self.send(lambda mav: mav.command_long_send(
                        self.system_id, self.component_id, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                        mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0))
                    if inbox.wait(timeout_s=self.timeout_s, what="GPS_GLOBAL_ORIGIN"):
                        break
        if self.origin is None:
            raise MavlinkTimeout(f"{self.describe()}: the vehicle sent no GPS_GLOBAL_ORIGIN")
        return self.origin

    def mission_items(self, waypoints: Sequence[Waypoint]) -> list[MissionItem]:
        """ArduPilot's layout: item 0 is home (its position is replaced by the vehicle),
        then one NAV_WAYPOINT per waypoint, altitudes relative to home."""
        frame = self.frame()
        items = [MissionItem(0, mavlink.MAV_CMD_NAV_WAYPOINT, frame.lat_deg, frame.lon_deg,
                             0.0)]
        for i, point in enumerate(waypoints, start=1):
            lat, lon = frame.to_global(point.north_m, point.east_m)
            items.append(MissionItem(i, mavlink.MAV_CMD_NAV_WAYPOINT, lat, lon, point.alt_m))
        return items

    def upload_mission(self, items: Sequence[MissionItem]) -> int:
        """The mission upload protocol: MISSION_COUNT → (MISSION_REQUEST_INT(seq) →
        MISSION_ITEM_INT(seq))* → MISSION_ACK. When the vehicle stays silent for
        ``timeout_s`` the last message is sent again (the COUNT, or the item it answered
        last), at most ``retries`` times in a row; requests out of order are served (the
        vehicle may re-request), requests for sequence numbers beyond the count are
        ignored. Returns how many resends it took. CommandRejected on a MISSION_ACK
        that is not ACCEPTED; MavlinkTimeout when the retries run out."""
        self._require_alive("upload a mission")
        count = len(items)
        resends = 0
        with self.listen("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK") as inbox:
            def send_count(mav: Any) -> None:
                mav.mission_count_send(self.system_id, self.component_id, count)

            last: Callable[[Any], None] = send_count
            self.send(last)
            silent = 0
            while True:
                msg = inbox.wait(timeout_s=self.timeout_s, what="the next mission request")
                if msg is None:
                    silent += 1
                    if silent > self.retries:
                        raise MavlinkTimeout(f"{self.describe()}: mission upload of {count} "
                                             f"items stalled: no answer after {silent} tries "
                                             f"of {self.timeout_s} s")
                    resends += 1
                    self.send(last)
                    continue
                if getattr(msg, "mission_type", 0) != mavlink.MAV_MISSION_TYPE_MISSION:
                    self._ignore("request for another mission type", msg)
                    continue
                if msg.get_type() == "MISSION_ACK":
                    if msg.type != mavlink.MAV_MISSION_ACCEPTED:
                        result = mavlink.enums["MAV_MISSION_RESULT"][msg.type].name
                        raise CommandRejected(f"{self.describe()}: mission of {count} items "
                                              f"rejected: {result}", result=result)
                    return resends
                seq = msg.seq
                if not 0 <= seq < count:
                    self._ignore(f"mission request for item {seq} of {count}", msg)
                    continue
                silent = 0
                item = items[seq]
                last = self._item_sender(item)
                self.send(last)

    def _item_sender(self, item: MissionItem) -> Callable[[Any], None]:
        def send(mav: Any) -> None:
            mav.mission_item_int_send(
                self.system_id, self.component_id, item.seq, item.frame, item.command,
                0, 1, *item.params, round(item.lat_deg * 1e7), round(item.lon_deg * 1e7),
                item.alt_m)
        return send

    def start_mission(self, first_seq: int = 1) -> None:
        """MISSION_SET_CURRENT to ``first_seq``, then AUTO."""
        self._require_alive("start the mission")
        self.send(lambda mav: mav.mission_set_current_send(self.system_id, self.component_id,
                                                           first_seq))
        self.set_mode("AUTO")

    def get_param(self, name: str) -> float:
        """PARAM_REQUEST_READ → PARAM_VALUE (with retries)."""
        self._require_alive(f"read parameter {name}")
        with self.listen("PARAM_VALUE") as inbox:
            for _ in range(self.retries + 1):
                self.send(lambda mav: mav.param_request_read_send(
                    self.system_id, self.component_id, name.encode(), -1))
                msg = inbox.wait(lambda m: param_name(m) == name, timeout_s=self.timeout_s,
                                 what=f"PARAM_VALUE {name}")
                if msg is not None:
                    return float(msg.param_value)
        raise MavlinkTimeout(f"{self.describe()}: parameter {name!r} not answered (does the "
                             f"vehicle have it?)")

    def set_param(self, name: str, value: float) -> float:
        """PARAM_SET, confirmed by the PARAM_VALUE echo; returns the value the vehicle
        took (the one it had when it refused the new one)."""
        _require_finite(f"parameter {name}", value)
        self._require_alive(f"set parameter {name}")
        with self.listen("PARAM_VALUE") as inbox:
            for _ in range(self.retries + 1):
                self.send(lambda mav: mav.param_set_send(
                    self.system_id, self.component_id, name.encode(), float(value),
                    mavlink.MAV_PARAM_TYPE_REAL32))
                msg = inbox.wait(lambda m: param_name(m) == name, timeout_s=self.timeout_s,
                                 what=f"PARAM_VALUE {name}")
                if msg is not None:
                    return float(msg.param_value)
        raise MavlinkTimeout(f"{self.describe()}: PARAM_SET {name} not confirmed")

    # ---- lifecycle --------------------------------------------------------------------

    def close(self) -> None:
        """Give back one reference; the last one stops the reader thread and closes the
        connection."""
        with _LINKS_LOCK:
            self._users -= 1
            if self._users > 0:
                return
            if _LINKS.get(self.url) is self:
                del _LINKS[self.url]
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()
        try:
            self.conn.close()
        except OSError:
            pass


    def __repr__(self) -> str:
        return (f"<MavlinkLink {self.url} system={self.system_id} kind={self.kind} "
                f"{'alive' if self._alive else 'no heartbeat'} mode={self.mode}>")


def _require_finite(what: str, *values: float) -> None:
    """ConfigError unless every value is a finite number (a vehicle refuses the others:
    better to say so here, where the mistake is)."""
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
        raise ConfigError(f"{what} must be finite numbers, got {values}")


def param_name(msg: Any) -> str:
    """The parameter name of a PARAM_* message (``param_id``, bytes or str, NUL-padded)."""
    pid = msg.param_id
    return (pid.decode(errors="replace") if isinstance(pid, bytes) else str(pid)).rstrip("\0")


_LINKS: dict[str, MavlinkLink] = {}
_LINKS_LOCK = threading.Lock()


def open_link(url: str, **options: Any) -> MavlinkLink:
    """The process's link for connection ``url`` (made on first use, with ``options`` —
    see :class:`MavlinkLink`); each call takes a reference, give it back with
    ``close()``. Options given to a later call must match the first one's."""
    with _LINKS_LOCK:
        link = _LINKS.get(url)
        if link is not None:
            for key, value in options.items():
                current = getattr(link, key, value)
                # None: no wish (the vehicle the link found; the link's signing, if any).
                if current != value and not (key in ("system_id", "signing_key_file")
                                             and value is None):
                    raise ConfigError(f"MAVLink {url}: opened already with {key}={current!r}; "
                                      f"a second user asks for {value!r} (one link per "
                                      f"connection: give every HAL and action the same "
                                      f"options)")
            link._users += 1
            return link
        link = MavlinkLink(url, **options)
        _LINKS[url] = link
        return link


def close_all_links() -> None:
    """Close every link of the process, whoever holds it (tests, shutdown)."""
    with _LINKS_LOCK:
        links = list(_LINKS.values())
    for link in links:
        link._users = 1
        link.close()


# ---- HALs -------------------------------------------------------------------------------

class MavlinkHAL(HAL):
    """Base of the MAVLink HALs: opens (shares) the link of ``connection`` and turns the
    messages of :attr:`messages` into blackboard entries with :meth:`entries`.

    Parameters: ``connection`` (see the module doc; default: the environment variable
    ``BEEHAVE_MAVLINK_CONNECTION``, so that ``hals: [mavlink_position]`` works),
    ``system_id`` (None: the first autopilot heard), ``heartbeat_timeout_s`` (3 s),
    ``signing_key_file`` (MAVLink 2 signing, see :class:`MavlinkLink`; default: the
    environment variable ``BEEHAVE_MAVLINK_KEY_FILE``, else none). When the heartbeat is
    lost every entry this HAL wrote is marked stale."""

    messages: ClassVar[tuple[str, ...]] = ()
    link: MavlinkLink

    def __init__(self, *, connection: str | None = None, system_id: int | None = None,
                 heartbeat_timeout_s: float = 3.0, signing_key_file: str | None = None
                 ) -> None:
        self.signing_key_file = signing_key_file or os.environ.get(KEY_FILE_ENV) or None
        if self.signing_key_file is not None:
            load_signing_key(self.signing_key_file)  # a bad file fails at load, named
        connection = connection or os.environ.get(CONNECTION_ENV)
        if not connection:
            raise ConfigError(f"HAL {self.name!r} needs a MAVLink connection: give it "
                              f"params {{connection: 'udp:HOST:PORT'}} or set "
                              f"{CONNECTION_ENV}")
        self.connection = _check_url(connection)
        self.system_id = system_id
        self.heartbeat_timeout_s = check_duration_s(f"HAL {self.name!r}: heartbeat_timeout_s",
                                                    heartbeat_timeout_s)
        self._removers: list[Callable[[], None]] = []

    def entries(self, msg: Any) -> dict[str, Any]:
        """The blackboard entries of one message (override)."""
        return {}

    async def on_load(self) -> None:
        self.link = await asyncio.to_thread(
            open_link, self.connection, system_id=self.system_id,
            heartbeat_timeout_s=self.heartbeat_timeout_s,
            signing_key_file=self.signing_key_file)
        self._removers = [self.link.on_message(self.messages, self._on_message),
                          self.link.on_link(self._on_link)]

    def _on_message(self, msg: Any) -> None:
        for key, value in self.entries(msg).items():
            self.blackboard.set(key, value)

    def _on_link(self, alive: bool) -> None:
        if not alive:
            self.blackboard.board.mark_stale(writer=self.blackboard.writer)

    def on_unload(self) -> None:
        for remove in self._removers:
            remove()
        self._removers = []
        link = getattr(self, "link", None)
        if link is not None:
            link.close()


class MavlinkHeartbeatHAL(MavlinkHAL):
    """Armed, mode, system status and vehicle kind, from HEARTBEAT; ``vehicle/connected``
    goes False (fresh) when the heartbeat is lost, while every other entry goes stale."""

    name = "mavlink_heartbeat"
    messages = ("HEARTBEAT",)

    def entries(self, msg: Any) -> dict[str, Any]:
        kind = vehicle_kind(msg.type)
        status = mavlink.enums["MAV_STATE"].get(msg.system_status)
        return {"vehicle/connected": True,
                "vehicle/armed": bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED),
                "vehicle/mode": mode_name(kind, msg.custom_mode),
                "vehicle/system_status": status.name.removeprefix("MAV_STATE_")
                if status is not None else str(msg.system_status),
                "vehicle/type": kind}

    def _on_link(self, alive: bool) -> None:
        super()._on_link(alive)
        if not alive:
            self.blackboard.set("vehicle/connected", False)


class MavlinkPositionHAL(MavlinkHAL):
    """Where the vehicle is, from GLOBAL_POSITION_INT and LOCAL_POSITION_NED."""

    name = "mavlink_position"
    messages = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED")

    def entries(self, msg: Any) -> dict[str, Any]:
        if msg.get_type() == "GLOBAL_POSITION_INT":
            return {"position/lat_deg": msg.lat / 1e7, "position/lon_deg": msg.lon / 1e7,
                    "position/alt_m": msg.relative_alt / 1000.0,
                    "position/heading_deg": msg.hdg / 100.0 if msg.hdg != 65535 else math.nan}
        return {"position/north_m": msg.x, "position/east_m": msg.y, "position/down_m": msg.z,
                "position/vn_mps": msg.vx, "position/ve_mps": msg.vy}


class MavlinkAttitudeHAL(MavlinkHAL):
    """Roll, pitch and yaw (radians), from ATTITUDE."""

    name = "mavlink_attitude"
    messages = ("ATTITUDE",)

    def entries(self, msg: Any) -> dict[str, Any]:
        return {"attitude/roll_rad": msg.roll, "attitude/pitch_rad": msg.pitch,
                "attitude/yaw_rad": msg.yaw}


class MavlinkBatteryHAL(MavlinkHAL):
    """State of charge (%), voltage and current, from SYS_STATUS (BATTERY_STATUS's
    remaining charge when the vehicle sends it)."""

    name = "mavlink_battery"
    messages = ("SYS_STATUS", "BATTERY_STATUS")

    def entries(self, msg: Any) -> dict[str, Any]:
        if msg.get_type() == "BATTERY_STATUS":
            return ({"battery/percentage": float(msg.battery_remaining)}
                    if msg.battery_remaining >= 0 else {})
        out: dict[str, Any] = {"battery/voltage_v": msg.voltage_battery / 1000.0,
                               "battery/current_a": msg.current_battery / 100.0
                               if msg.current_battery != -1 else math.nan}
        if msg.battery_remaining >= 0:
            out["battery/percentage"] = float(msg.battery_remaining)
        return out


class MavlinkMissionHAL(MavlinkHAL):
    """Mission progress: the item flown now (MISSION_CURRENT) and the last one reached
    (MISSION_ITEM_REACHED)."""

    name = "mavlink_mission"
    messages = ("MISSION_CURRENT", "MISSION_ITEM_REACHED")

    def entries(self, msg: Any) -> dict[str, Any]:
        if msg.get_type() == "MISSION_CURRENT":
            return {"mission/current": int(msg.seq)}
        return {"mission/reached": int(msg.seq)}


class MavlinkParamsHAL(MavlinkHAL):
    """The vehicle's parameters as the paper's Droid gets and sets them:
    ``await hal.get("WP_RADIUS")``, ``await hal.set("WP_RADIUS", 0.5)``; every PARAM_VALUE
    heard lands in ``param/<NAME>``."""

    name = "mavlink_params"
    messages = ("PARAM_VALUE",)

    def entries(self, msg: Any) -> dict[str, Any]:
        return {f"param/{param_name(msg)}": float(msg.param_value)}

    async def get(self, name: str) -> float:
        return await asyncio.to_thread(self.link.get_param, name)

    async def set(self, name: str, value: float) -> float:
        return await asyncio.to_thread(self.link.set_param, name, value)
