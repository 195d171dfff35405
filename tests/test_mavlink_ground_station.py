"""MAVLink from a ground station's side: the simulated vehicles flown the way QGroundControl
and MAVProxy fly ArduPilot, by a plain pymavlink client over UDP (issue 25).

What is checked on the wire comes from pymavlink alone (no beehave import for it); the
simulation runs in this process (``robots``) or as ``beehave sim`` in a subprocess, and
where a fact is physical (the copter is on the floor) it is measured in the physics too.
The expected answers are ArduPilot's (ArduCopter / ArduRover 4.x, SITL as the reference).
"""

from __future__ import annotations

import math
import os
import random
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # type: ignore[import-untyped]  # noqa: E402

from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402  (timeouts only)
from robots.mavlink_endpoint import free_udp_ports  # noqa: E402

mav = mavutil.mavlink
ROOT = Path(__file__).resolve().parents[1]
FLOOR = (12.0, 8.0)  # x (east) × y (north), metres; no walls around it: a fence must hold
WORLD = {"name": "gcs", "floor": {"size_m": list(FLOOR)},
         "robots": [{"namespace": "rover1", "kind": "kobuki", "start": {"x_m": 2, "y_m": 2}},
                    {"namespace": "quad1", "kind": "quad", "start": {"x_m": 5, "y_m": 4}}]}
# SET_POSITION_TARGET type_mask (MAVLink POSITION_TARGET_TYPEMASK)
USE_POSITION = 0b1101_1111_1000   # x, y, z (ignore velocity, acceleration, yaw, yaw rate)
USE_POSITION_YAW = 0b1001_1111_1000
USE_VELOCITY = 0b1101_1100_0111   # vx, vy, vz
# ArduPilot's SITL home (CMAC), the origin of the simulated vehicles' local frame
ORIGIN = (-35.363262, 149.165237)
R_EARTH = 6378137.0


def free_port_pair() -> int:
    """A free UDP port whose successor is free too (``beehave sim`` uses BASE and BASE+1)."""
    for _ in range(100):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as first:
            first.bind(("127.0.0.1", 0))
            base: int = first.getsockname()[1]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as second:
                try:
                    second.bind(("127.0.0.1", base + 1))
                except OSError:
                    continue
                return base
    raise AssertionError("no two consecutive free UDP ports")


def to_global(north_m: float, east_m: float) -> tuple[int, int]:
    """lat, lon × 1e7 of a point of the local frame (flat earth around the origin)."""
    lat = ORIGIN[0] + math.degrees(north_m / R_EARTH)
    lon = ORIGIN[1] + math.degrees(east_m / (R_EARTH * math.cos(math.radians(ORIGIN[0]))))
    return round(lat * 1e7), round(lon * 1e7)


class GroundStation:
    """A plain pymavlink ground station (system 255, component 190) listening on a UDP
    port; a reader thread keeps every message so tests can wait for one."""

    def __init__(self, port: int, *, connect: bool = True) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                               source_component=190)
        self.messages: list[Any] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()
        self.vehicle = 0
        if connect:
            self.connect()

    def connect(self) -> None:
        """Wait for the vehicle's heartbeat (a udpin link answers whoever spoke last).
        Bind first (``connect=False``) and start the vehicle after: its first heartbeat,
        sent as it starts, then arrives, and nobody waits a second for the next."""
        self.vehicle = self.wait("HEARTBEAT").get_srcSystem()

    def _read(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            with self._cond:
                self.messages.append(msg)
                self._cond.notify_all()

    def mark(self) -> int:
        with self._cond:
            return len(self.messages)

    def wait(self, kind: str, where: Callable[[Any], bool] = lambda m: True, *,
             since: int = 0, timeout_s: float = WALL_TIMEOUT_S) -> Any:
        """The first ``kind`` message after index ``since`` that ``where`` accepts."""
        deadline = time.monotonic() + timeout_s
        seen = since
        with self._cond:
            while True:
                for msg in self.messages[seen:]:
                    if msg.get_type() == kind and where(msg):
                        return msg
                seen = len(self.messages)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"no {kind} within {timeout_s} s")
                self._cond.wait(left)

    def latest(self, kind: str) -> Any:
        with self._cond:
            for msg in reversed(self.messages):
                if msg.get_type() == kind:
                    return msg
        return None

    def send(self, build: Callable[[Any], Any]) -> None:
        build(self.conn.mav)

    def command(self, command: int, *params: float) -> int:
        """COMMAND_LONG → the MAV_RESULT of its COMMAND_ACK."""
        values = [*params, *([0.0] * (7 - len(params)))]
        since = self.mark()
        self.send(lambda m: m.command_long_send(self.vehicle, 1, command, 0, *values))
        return int(self.wait("COMMAND_ACK", lambda a: a.command == command,
                             since=since).result)

    def mode(self, name: str) -> int:
        mapping = mavutil.mode_mapping_byname(self.latest("HEARTBEAT").type)
        return self.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                            mapping[name])

    def target_local(self, mask: int, x: float = 0, y: float = 0, z: float = 0,
                     vx: float = 0, vy: float = 0, vz: float = 0, yaw: float = 0,
                     yaw_rate: float = 0, frame: int = mav.MAV_FRAME_LOCAL_NED) -> None:
        self.send(lambda m: m.set_position_target_local_ned_send(
            0, self.vehicle, 1, frame, mask, x, y, z, vx, vy, vz, 0, 0, 0, yaw, yaw_rate))

    def upload(self, items: list[tuple[int, int, int, int, float]]) -> int:
        """The mission upload protocol with items (command, frame, lat_e7, lon_e7, z);
        item 0 (home) is added. Returns the MISSION_ACK's result."""
        rows = [(mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_FRAME_GLOBAL_INT, 0, 0, 0.0), *items]
        since = self.mark()
        self.send(lambda m: m.mission_count_send(self.vehicle, 1, len(rows)))
        while True:
            reply = self._next_of(("MISSION_REQUEST_INT", "MISSION_ACK"), since)
            since = self.messages.index(reply) + 1
            if reply.get_type() == "MISSION_ACK":
                return int(reply.type)
            self.send(self._item(reply.seq, *rows[reply.seq]))

    def _item(self, seq: int, command: int, frame: int, lat: int, lon: int, z: float
              ) -> Callable[[Any], Any]:
        return lambda m: m.mission_item_int_send(self.vehicle, 1, seq, frame, command, 0, 1,
                                                 0, 0, 0, 0, lat, lon, z)

    def _next_of(self, kinds: tuple[str, ...], since: int) -> Any:
        deadline = time.monotonic() + WALL_TIMEOUT_S
        with self._cond:
            while True:
                for msg in self.messages[since:]:
                    if msg.get_type() in kinds:
                        return msg
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"none of {kinds} within {WALL_TIMEOUT_S} s")
                self._cond.wait(left)

    def local(self) -> tuple[float, float, float]:
        """north, east, altitude from the latest LOCAL_POSITION_NED."""
        msg = self.wait("LOCAL_POSITION_NED", since=self.mark())
        return msg.x, msg.y, -msg.z

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.conn.close()


@dataclass
class Rig:
    sim: Any
    rover: GroundStation
    quad: GroundStation

    def quad_position(self) -> Any:
        return self.sim.robot("quad1").position()


@pytest.fixture
def rig() -> Iterator[Rig]:
    from robots.mavlink_endpoint import MavlinkEndpoint
    from robots.sim import Simulation
    from robots.world import world_from_dict

    sim = Simulation(world_from_dict(WORLD), real_time_factor=1.0)
    ports = free_udp_ports(2)
    stations: list[GroundStation] = []
    endpoints: list[MavlinkEndpoint] = []
    try:
        for port in ports:  # listening before the vehicles start
            stations.append(GroundStation(port, connect=False))
        endpoints += [MavlinkEndpoint(sim, ns, url=f"udpout:127.0.0.1:{port}",
                                      system_id=i + 1)
                      for i, (ns, port) in enumerate(zip(("rover1", "quad1"), ports,
                                                         strict=True))]
        sim.start()
        for station in stations:
            station.connect()
        yield Rig(sim, *stations)
        assert sim.error is None, sim.error
        assert [getattr(e, "errors", 0) for e in endpoints] == [0, 0]  # no input crashed it
    finally:
        for station in stations:
            station.close()
        for endpoint in endpoints:
            endpoint.close()
        sim.close()


def take_off(gs: GroundStation, alt_m: float) -> None:
    assert gs.mode("GUIDED") == mav.MAV_RESULT_ACCEPTED
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert gs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, alt_m) == \
        mav.MAV_RESULT_ACCEPTED
    assert wait_until(lambda: gs.local()[2] > alt_m - 0.1), gs.local()


def settle(gs: GroundStation, seconds: float) -> None:
    """Let ``seconds`` of the vehicle's own time pass (its time_boot_ms)."""
    start = gs.wait("LOCAL_POSITION_NED", since=gs.mark()).time_boot_ms
    gs.wait("LOCAL_POSITION_NED", lambda m: m.time_boot_ms >= start + seconds * 1000,
            since=gs.mark())


# ---- 1. one NaN must not stop the simulation --------------------------------------------

def test_a_nan_position_target_is_refused_and_the_copter_holds(rig: Rig) -> None:
    gs = rig.quad
    take_off(gs, 2.0)
    gs.target_local(USE_POSITION, math.nan, 4.0, -2.0)
    gs.target_local(USE_POSITION, 4.0, math.inf, -2.0)
    settle(gs, 1.0)
    assert rig.sim.error is None, rig.sim.error  # the simulation runs on
    north, east, alt = gs.local()
    assert math.dist((north, east), (4.0, 5.0)) < 0.3 and abs(alt - 2.0) < 0.3  # it held
    # and it still takes a good target
    gs.target_local(USE_POSITION, 5.0, 6.0, -2.5)
    assert wait_until(lambda: math.dist(gs.local(), (5.0, 6.0, 2.5)) < 0.2), gs.local()


# ---- 2. type_mask -------------------------------------------------------------------------

def test_a_velocity_target_flies_that_velocity_and_times_out_into_a_hover(rig: Rig) -> None:
    gs = rig.quad
    take_off(gs, 1.8)
    north0, east0, _ = gs.local()
    since = gs.mark()
    for _ in range(10):  # 0.5 m/s north for 1 s (ArduPilot wants them renewed)
        gs.target_local(USE_VELOCITY, vx=0.5)
        time.sleep(0.1)
    gs.wait("LOCAL_POSITION_NED", lambda m: m.vx > 0.4, since=since)
    # Not a position target at (0, 0, 0): it keeps its altitude and does not go east/west.
    north, east, alt = gs.local()
    assert north > north0 and abs(east - east0) < 0.1 and alt > 1.6, (north, east, alt)
    # Not renewed for 3 s: it stops and hovers where it is.
    gs.wait("LOCAL_POSITION_NED", lambda m: abs(m.vx) < 0.02 and abs(m.vy) < 0.02,
            since=gs.mark())
    hover = gs.local()
    settle(gs, 1.0)
    assert math.dist(gs.local(), hover) < 0.05 and hover[2] > 1.6


def test_a_velocity_target_drives_the_rover_that_way_not_to_the_origin(rig: Rig) -> None:
    gs = rig.rover
    assert gs.mode("GUIDED") == mav.MAV_RESULT_ACCEPTED
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    north0, east0, _ = gs.local()

    def driven_east() -> bool:
        gs.target_local(USE_VELOCITY, vy=0.3)  # east at 0.3 m/s, renewed at 10 Hz
        time.sleep(0.1)
        return gs.local()[1] > east0 + 0.5

    assert wait_until(driven_east), gs.local()
    north, east, _ = gs.local()
    assert abs(north - north0) < 0.25, (north, east)  # not towards the origin (0, 0)


def test_a_yaw_in_a_position_target_turns_the_copter(rig: Rig) -> None:
    gs = rig.quad
    take_off(gs, 1.5)
    assert abs(gs.wait("ATTITUDE", since=gs.mark()).yaw - math.pi / 2) < 0.05  # east
    gs.target_local(USE_POSITION_YAW, 4.0, 5.0, -1.5, yaw=-math.pi / 2)  # face west
    assert wait_until(lambda: abs(math.remainder(gs.wait(
        "ATTITUDE", since=gs.mark()).yaw + math.pi / 2, 2 * math.pi)) < 0.05)
    assert math.dist(gs.local(), (4.0, 5.0, 1.5)) < 0.2  # turning on the spot


def test_targets_outside_the_fence_are_refused_and_velocity_stops_at_its_edge(
        rig: Rig) -> None:
    gs = rig.quad
    take_off(gs, 1.5)
    gs.target_local(USE_POSITION, 4.0, 40.0, -1.5)   # 40 m east: off the 12 m floor
    lat, lon = to_global(95.0, 5.0)
    gs.send(lambda m: m.set_position_target_global_int_send(
        0, gs.vehicle, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, USE_POSITION,
        950_000_000, lon, 1.5, 0, 0, 0, 0, 0, 0, 0, 0))  # latitude 95°
    gs.send(lambda m: m.set_position_target_global_int_send(
        0, gs.vehicle, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, USE_POSITION,
        lat, 1_900_000_000, 1.5, 0, 0, 0, 0, 0, 0, 0, 0))  # longitude 190°
    settle(gs, 1.0)
    north, east, _ = gs.local()
    assert math.dist((north, east), (4.0, 5.0)) < 0.3

    def stopped_at_the_west_edge() -> bool:
        gs.target_local(USE_VELOCITY, vy=-3.0)  # west at 3 m/s: the edge is 5 m away
        time.sleep(0.1)
        last = gs.latest("LOCAL_POSITION_NED")
        return bool(last.y < 0.6 and abs(last.vy) < 0.05)

    assert wait_until(stopped_at_the_west_edge), gs.latest("LOCAL_POSITION_NED")
    east_min = min(m.y for m in gs.messages if m.get_type() == "LOCAL_POSITION_NED")
    assert east_min > 0.15, east_min  # it stopped at the fence (0.3 m inside), not beyond


# ---- 3. takeoff, arming, modes, coordinates -------------------------------------------------

def test_a_takeoff_item_at_lat_lon_zero_climbs_where_the_copter_is(rig: Rig) -> None:
    gs = rig.quad
    lat, lon = to_global(6.0, 7.0)
    assert gs.upload([(mav.MAV_CMD_NAV_TAKEOFF, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0, 0,
                       2.0),
                      (mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, lat,
                       lon, 2.0)]) == mav.MAV_MISSION_ACCEPTED
    assert gs.mode("GUIDED") == mav.MAV_RESULT_ACCEPTED
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    since = gs.mark()
    assert gs.mode("AUTO") == mav.MAV_RESULT_ACCEPTED
    gs.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 1, since=since)
    north, east, alt = gs.local()
    assert math.dist((north, east), (4.0, 5.0)) < 0.3 and abs(alt - 2.0) < 0.2  # straight up
    gs.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 2, since=since)
    assert math.dist(gs.local()[:2], (6.0, 7.0)) < 0.6


def test_takeoff_refuses_nonsense_and_a_copter_in_the_air(rig: Rig) -> None:
    gs = rig.quad
    assert gs.mode("GUIDED") == mav.MAV_RESULT_ACCEPTED
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    for alt in (math.nan, math.inf, 1e9):
        assert gs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt) == \
            mav.MAV_RESULT_DENIED, alt
    assert gs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0.0) == \
        mav.MAV_RESULT_FAILED  # not upwards
    settle(gs, 0.5)
    assert gs.local()[2] < 0.05  # none of them lifted it
    take_off(gs, 1.5)
    for alt in (0.0, 3.0):  # ArduCopter: "can't takeoff again"
        assert gs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt) == \
            mav.MAV_RESULT_FAILED
    settle(gs, 1.0)
    assert abs(gs.local()[2] - 1.5) < 0.1


def test_arm_disarm_takes_exactly_one_or_zero(rig: Rig) -> None:
    gs = rig.rover
    for value in (math.nan, 0.5, 2.0, -1.0):
        assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, value) == \
            mav.MAV_RESULT_UNSUPPORTED, value
    settle(gs, 1.2)
    assert not gs.latest("HEARTBEAT").base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, math.nan) == \
        mav.MAV_RESULT_UNSUPPORTED
    since = gs.mark()
    gs.wait("HEARTBEAT", since=since)
    assert gs.latest("HEARTBEAT").base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED  # still armed


def test_a_malformed_mode_is_denied_and_an_unknown_one_failed(rig: Rig) -> None:
    gs = rig.rover
    for base, custom in ((1, math.nan), (1, -1), (1, 2.5), (1, 1e12), (math.nan, 4),
                         (0, 4)):  # 0: no MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert gs.command(mav.MAV_CMD_DO_SET_MODE, base, custom) == mav.MAV_RESULT_DENIED, \
            (base, custom)
    assert gs.command(mav.MAV_CMD_DO_SET_MODE, 1, 77) == mav.MAV_RESULT_FAILED
    assert gs.command(mav.MAV_CMD_DO_SET_MODE, 1, 10) == mav.MAV_RESULT_FAILED  # AUTO, no mission
    assert gs.mode("GUIDED") == mav.MAV_RESULT_ACCEPTED


def test_mission_items_outside_the_globe_or_the_world_are_refused(rig: Rig) -> None:
    gs = rig.quad
    lat, lon = to_global(3.0, 3.0)
    wp, frame = mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    assert gs.upload([(wp, frame, 950_000_000, lon, 2.0)]) == \
        mav.MAV_MISSION_INVALID_PARAM5_X
    assert gs.upload([(wp, frame, lat, 1_900_000_000, 2.0)]) == \
        mav.MAV_MISSION_INVALID_PARAM6_Y
    far_lat, far_lon = to_global(3.0, 40.0)  # a real place, 28 m beyond the floor
    assert gs.upload([(wp, frame, far_lat, far_lon, 2.0)]) == mav.MAV_MISSION_INVALID_PARAM6_Y
    for z in (math.nan, 1e9, -5.0):
        assert gs.upload([(wp, frame, lat, lon, z)]) == mav.MAV_MISSION_INVALID_PARAM7, z
    assert gs.upload([(wp, frame, lat, lon, 2.0)]) == mav.MAV_MISSION_ACCEPTED


def test_a_parameter_set_to_nonsense_keeps_its_value(rig: Rig) -> None:
    gs = rig.quad
    for value in (math.nan, math.inf, -50.0, 0.0, 1e30):  # LAND_SPEED < 0 would climb
        since = gs.mark()
        gs.send(lambda m, v=value: m.param_set_send(gs.vehicle, 1, b"LAND_SPEED", v, 9))
        reply = gs.wait("PARAM_VALUE", lambda p: p.param_id == "LAND_SPEED", since=since)
        assert reply.param_value == 70.0, value  # the unchanged value is the answer
    since = gs.mark()
    gs.send(lambda m: m.param_set_send(gs.vehicle, 1, b"LAND_SPEED", 50.0, 9))
    assert gs.wait("PARAM_VALUE", lambda p: p.param_id == "LAND_SPEED",
                   since=since).param_value == 50.0


# ---- 4. a force-disarmed copter falls -------------------------------------------------------

def test_a_copter_disarmed_in_the_air_only_by_force_and_then_it_falls(rig: Rig) -> None:
    gs = rig.quad
    take_off(gs, 3.0)
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mav.MAV_RESULT_FAILED
    settle(gs, 0.5)
    assert gs.local()[2] > 2.8
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196) == mav.MAV_RESULT_ACCEPTED
    since = gs.mark()
    gs.wait("LOCAL_POSITION_NED", lambda m: -m.z < 0.01, since=since)
    assert max(m.vz for m in gs.messages[since:]
               if m.get_type() == "LOCAL_POSITION_NED") > 4.0  # a fall, not a descent
    assert rig.quad_position().z_m == 0.0  # in the physics: on the floor


# ---- 7. what a ground station relies on ---------------------------------------------------

def test_the_vehicle_sends_what_a_ground_station_shows_and_flies_by(rig: Rig) -> None:
    for gs, base in ((rig.rover, 1), (rig.quad, 81)):  # SITL: Rover HOLD 1, Copter 81
        since = gs.mark()
        beat = gs.wait("HEARTBEAT", since=since)
        assert (beat.base_mode, beat.system_status) == (base, mav.MAV_STATE_STANDBY)
        home = gs.wait("HOME_POSITION", since=since)
        gps = gs.wait("GPS_RAW_INT", since=since)
        assert gps.fix_type == mav.GPS_FIX_TYPE_3D_FIX and gps.satellites_visible > 5
        assert abs(gps.lat - home.latitude) < 100 and abs(gps.lon - home.longitude) < 100
        hud = gs.wait("VFR_HUD", since=since)
        assert 0 <= hud.heading < 360 and hud.groundspeed < 0.01
        battery = gs.wait("BATTERY_STATUS", since=since)
        status = gs.latest("SYS_STATUS")
        assert abs(battery.voltages[0] - status.voltage_battery) < 50  # mV, one pack
        assert battery.voltages[1:] == [65535] * 9
        since = gs.mark()
        assert gs.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION) \
            == mav.MAV_RESULT_ACCEPTED
        version = gs.wait("AUTOPILOT_VERSION", since=since)
        assert version.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        assert version.capabilities & mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    gs = rig.quad
    # COMMAND_INT is answered like COMMAND_LONG (QGroundControl sends many commands so)
    since = gs.mark()
    gs.send(lambda m: m.command_int_send(gs.vehicle, 1, 0, mav.MAV_CMD_DO_SET_MODE, 0, 0,
                                         1, 4, 0, 0, 0, 0, 0))  # GUIDED
    ack = gs.wait("COMMAND_ACK", lambda a: a.command == mav.MAV_CMD_DO_SET_MODE, since=since)
    assert ack.result == mav.MAV_RESULT_ACCEPTED
    assert (ack.target_system, ack.target_component) == (255, 190)  # addressed to us
    # SET_MODE (deprecated) is acknowledged with command 11, as ArduPilot does
    since = gs.mark()
    gs.send(lambda m: m.set_mode_send(gs.vehicle, 1, 5))  # LOITER
    assert gs.wait("COMMAND_ACK", lambda a: a.command == 11, since=since).result == \
        mav.MAV_RESULT_ACCEPTED
    # A refusal is explained in a STATUSTEXT
    assert gs.mode("GUIDED") == mav.MAV_RESULT_ACCEPTED
    since = gs.mark()
    assert gs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, math.nan) == \
        mav.MAV_RESULT_DENIED
    assert "NAV_TAKEOFF" in gs.wait("STATUSTEXT", since=since).text
    # Armed in GUIDED, on the ground: the heartbeat says so as SITL's does
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    since = gs.mark()
    assert gs.wait("HEARTBEAT", lambda b: b.base_mode & 128, since=since).base_mode == 217


def test_reposition_from_the_map_flies_there_and_refuses_nonsense(rig: Rig) -> None:
    """QGroundControl's "go to location": COMMAND_INT DO_REPOSITION with the CHANGE_MODE
    flag switches to GUIDED and flies there."""
    gs = rig.quad
    take_off(gs, 2.0)
    assert gs.mode("LOITER") == mav.MAV_RESULT_ACCEPTED
    lat, lon = to_global(6.0, 7.0)

    def reposition(flags: float, lat: int, lon: int, alt: float) -> int:
        since = gs.mark()
        gs.send(lambda m: m.command_int_send(
            gs.vehicle, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mav.MAV_CMD_DO_REPOSITION,
            0, 0, -1, flags, 0, math.nan, lat, lon, alt))
        return int(gs.wait("COMMAND_ACK", lambda a: a.command == mav.MAV_CMD_DO_REPOSITION,
                           since=since).result)

    assert reposition(0, lat, lon, 2.0) == mav.MAV_RESULT_DENIED  # not GUIDED, no flag
    assert reposition(1, 0, 0, 2.0) == mav.MAV_RESULT_DENIED
    assert reposition(1, 950_000_000, lon, 2.0) == mav.MAV_RESULT_DENIED
    assert reposition(1, lat, lon, math.nan) == mav.MAV_RESULT_DENIED
    assert reposition(1, *to_global(6.0, 70.0), 2.0) == mav.MAV_RESULT_FAILED  # off the floor
    assert reposition(1, lat, lon, 2.5) == mav.MAV_RESULT_ACCEPTED
    assert wait_until(lambda: math.dist(gs.local(), (6.0, 7.0, 2.5)) < 0.2), gs.local()
    assert gs.latest("HEARTBEAT").custom_mode == 4  # GUIDED


def test_mission_start_clear_all_and_a_single_mission_current_stream(rig: Rig) -> None:
    gs = rig.rover
    lat, lon = to_global(3.0, 2.0)
    assert gs.upload([(mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, lat,
                       lon, 0.0)]) == mav.MAV_MISSION_ACCEPTED
    since = gs.mark()
    assert gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert gs.command(mav.MAV_CMD_MISSION_START) == mav.MAV_RESULT_ACCEPTED
    assert gs.wait("HEARTBEAT", lambda b: b.custom_mode == 10, since=gs.mark())  # AUTO
    gs.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 1, since=since)
    done = gs.wait("MISSION_CURRENT", lambda m: m.mission_state == mav.MISSION_STATE_COMPLETE,
                   since=since)
    assert (done.seq, done.total) == (1, 2)
    currents = [m for m in gs.messages[since:] if m.get_type() == "MISSION_CURRENT"]
    assert all(m.total == 2 for m in currents), currents  # one stream, never (seq, 0, 0)
    since = gs.mark()
    gs.send(lambda m: m.mission_clear_all_send(gs.vehicle, 1))
    assert gs.wait("MISSION_ACK", since=since).type == mav.MAV_MISSION_ACCEPTED
    gs.send(lambda m: m.mission_request_list_send(gs.vehicle, 1))
    assert gs.wait("MISSION_COUNT", since=since).count == 0
    assert gs.command(mav.MAV_CMD_MISSION_START) == mav.MAV_RESULT_FAILED  # nothing to fly


def test_an_abandoned_upload_is_cancelled_towards_its_ground_station(rig: Rig) -> None:
    gs = rig.rover
    since = gs.mark()
    gs.send(lambda m: m.mission_count_send(gs.vehicle, 1, 3))  # then never answer
    ack = gs.wait("MISSION_ACK", since=since)
    assert ack.type == mav.MAV_MISSION_OPERATION_CANCELLED
    assert (ack.target_system, ack.target_component) == (255, 190)


# ---- 6. stream rates ------------------------------------------------------------------------

def rate_hz(gs: GroundStation, kind: str, window_ms: int = 2000,
            clock: str = "LOCAL_POSITION_NED") -> float:
    """How often ``kind`` comes, by the vehicle's own clock: the messages of ``kind`` over
    the next ``window_ms`` of its time_boot_ms (read from the ``clock`` messages)."""
    since = gs.mark()
    start = gs.wait(clock, since=since).time_boot_ms + 200  # messages already on the way
    gs.wait(clock, lambda m: m.time_boot_ms >= start + window_ms + 200, since=since)
    stamps = [m.time_boot_ms for m in gs.messages[since:] if m.get_type() == kind]
    return sum(start <= t < start + window_ms for t in stamps) / (window_ms / 1000)


def test_message_intervals_and_data_streams_set_the_rates(rig: Rig) -> None:
    gs = rig.quad
    assert 9 <= rate_hz(gs, "ATTITUDE") <= 11  # the default, 10 Hz
    attitude = mav.MAVLINK_MSG_ID_ATTITUDE
    assert gs.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, attitude, 40_000) == \
        mav.MAV_RESULT_ACCEPTED  # 25 Hz
    assert 22 <= rate_hz(gs, "ATTITUDE") <= 28
    since = gs.mark()
    assert gs.command(mav.MAV_CMD_GET_MESSAGE_INTERVAL, attitude) == mav.MAV_RESULT_ACCEPTED
    assert gs.wait("MESSAGE_INTERVAL", since=since).interval_us == 40_000
    assert gs.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, attitude, -1) == \
        mav.MAV_RESULT_ACCEPTED  # stopped
    assert rate_hz(gs, "ATTITUDE") == 0
    for bad in ((attitude, math.nan), (attitude, -5), (math.nan, 1000), (99999, 1000)):
        assert gs.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, *bad) == mav.MAV_RESULT_DENIED
    gs.send(lambda m: m.request_data_stream_send(gs.vehicle, 1, mav.MAV_DATA_STREAM_EXTRA1,
                                                 2, 1))  # ATTITUDE's group, 2 Hz
    assert 1.5 <= rate_hz(gs, "ATTITUDE", 4000) <= 2.5
    gs.send(lambda m: m.request_data_stream_send(gs.vehicle, 1, mav.MAV_DATA_STREAM_POSITION,
                                                 0, 0))  # stopped
    assert rate_hz(gs, "GLOBAL_POSITION_INT", clock="ATTITUDE") == 0
    gs.send(lambda m: m.request_data_stream_send(gs.vehicle, 1, mav.MAV_DATA_STREAM_POSITION,
                                                 5, 1))  # started again, 5 Hz
    assert 4 <= rate_hz(gs, "GLOBAL_POSITION_INT", clock="ATTITUDE") <= 6
    assert gs.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, attitude, 0) == \
        mav.MAV_RESULT_ACCEPTED  # back to the default
    assert 9 <= rate_hz(gs, "ATTITUDE") <= 11


# ---- 5. mission download --------------------------------------------------------------------

def download(gs: GroundStation, *, floats: bool = False) -> list[Any]:
    """MISSION_REQUEST_LIST → MISSION_COUNT → MISSION_REQUEST_INT (or MISSION_REQUEST)
    for each item → MISSION_ACK, as QGroundControl (or an older MAVProxy) does."""
    since = gs.mark()
    gs.send(lambda m: m.mission_request_list_send(gs.vehicle, 1))
    count = gs.wait("MISSION_COUNT", since=since).count
    items = []
    for seq in range(count):
        since = gs.mark()
        if floats:
            gs.send(lambda m, s=seq: m.mission_request_send(gs.vehicle, 1, s))
        else:
            gs.send(lambda m, s=seq: m.mission_request_int_send(gs.vehicle, 1, s))
        kind = "MISSION_ITEM" if floats else "MISSION_ITEM_INT"
        items.append(gs.wait(kind, lambda i, s=seq: i.seq == s, since=since))
    gs.send(lambda m: m.mission_ack_send(gs.vehicle, 1, mav.MAV_MISSION_ACCEPTED))
    return items


def test_a_downloaded_mission_is_what_was_uploaded(rig: Rig) -> None:
    gs = rig.quad
    a, b = to_global(6.0, 7.0), to_global(2.0, 9.0)
    sent = [(mav.MAV_CMD_NAV_TAKEOFF, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0, 0, 2.0),
            (mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, *a, 2.5),
            (mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_FRAME_GLOBAL_INT, *b, 3.0),
            (mav.MAV_CMD_NAV_RETURN_TO_LAUNCH, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0, 0,
             0.0)]
    assert gs.upload(sent) == mav.MAV_MISSION_ACCEPTED
    items = download(gs)
    assert len(items) == len(sent) + 1
    home = gs.wait("HOME_POSITION", since=gs.mark())
    assert (items[0].seq, items[0].x, items[0].y) == (0, home.latitude, home.longitude)
    for item, (command, frame, lat, lon, z) in zip(items[1:], sent, strict=True):
        assert (item.command, item.frame, item.x, item.y, item.z) == (command, frame, lat,
                                                                      lon, z)
    assert [i.current for i in items] == [0, 1, 0, 0, 0]
    floats = download(gs, floats=True)  # the float form: the same, to float32's precision
    for f, i in zip(floats, items, strict=True):
        assert (f.command, abs(f.x * 1e7 - i.x) < 200, abs(f.y * 1e7 - i.y) < 200) == \
            (i.command, True, True)
    since = gs.mark()
    gs.send(lambda m: m.mission_request_int_send(gs.vehicle, 1, 9))  # no such item
    assert gs.wait("MISSION_ACK", since=since).type == mav.MAV_MISSION_INVALID_SEQUENCE


# ---- the fuzz: random and non-finite values in every handled message ---------------------

FUZZ_SEED = 25


def _float(rng: random.Random) -> float:
    return rng.choice([math.nan, math.inf, -math.inf, 0.0, 1.0, -1.0, 0.5, 1e9, -1e9, 1e38,
                       rng.uniform(-20, 20), rng.uniform(-2, 2), rng.uniform(0, 10)])


def _int(rng: random.Random, bits: int, signed: bool = False) -> int:
    low, high = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if signed else (0, 2 ** bits - 1)
    return rng.choice([low, high, 0, 1, rng.randint(low, high), max(low, min(high, 4))])


def _commands() -> list[int]:
    return [mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_CMD_DO_SET_MODE, mav.MAV_CMD_NAV_TAKEOFF,
            mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_CMD_MISSION_START, mav.MAV_CMD_NAV_LAND,
            mav.MAV_CMD_NAV_RETURN_TO_LAUNCH, mav.MAV_CMD_DO_REPOSITION,
            mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAV_CMD_GET_MESSAGE_INTERVAL, 0, 65535]


def _fly_out(rng: random.Random, gs: GroundStation, noise: Callable[[], None]) -> None:
    """Valid flying among the noise, so that the vehicles do move — towards the edges:
    GUIDED, arm, take off, then 3 m/s in a random direction for 2 s. The position stream
    is set back to its default first (the noise may have stopped it)."""
    gs.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0)
    gs.mode("GUIDED")
    gs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    gs.send(lambda m: m.param_set_send(gs.vehicle, 1, b"WP_SPEED", 2.0, 9))
    if gs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, rng.uniform(1.0, 4.0)) == \
            mav.MAV_RESULT_ACCEPTED:
        time.sleep(1.5)  # let it climb (no assertion depends on it)
    heading = rng.uniform(-math.pi, math.pi)
    for _ in range(20):
        gs.target_local(USE_VELOCITY, vx=3 * math.cos(heading), vy=3 * math.sin(heading),
                        vz=rng.uniform(-0.5, 0.5))
        if rng.random() < 0.3:
            noise()
        time.sleep(0.1)


def _fuzz_one(rng: random.Random, gs: GroundStation) -> int | None:
    """Send one random message of a handled type; the command id when it wants an ACK."""
    f, t = (lambda: _float(rng)), gs.vehicle
    kind = rng.randrange(16)
    if kind == 0:
        cmd = rng.choice(_commands())
        # Mostly plausible: ARM 1, GUIDED, takeoff to a few metres — so the vehicles move.
        params = [f() for _ in range(7)]
        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM and rng.random() < 0.6:
            params[0] = 1.0
        if cmd == mav.MAV_CMD_DO_SET_MODE and rng.random() < 0.6:
            params[:2] = [1.0, 4.0 if rng.random() < 0.8 else 15.0]
        if cmd == mav.MAV_CMD_NAV_TAKEOFF and rng.random() < 0.5:
            params[6] = rng.uniform(0.5, 4.0)
        gs.send(lambda m: m.command_long_send(t, 1, cmd, 0, *params))
        return cmd
    if kind == 1:
        cmd = rng.choice(_commands())
        params = [f() for _ in range(4)]
        x, y, z = _int(rng, 32, True), _int(rng, 32, True), f()
        frame = rng.choice([0, 3, 5, 6, 11, 255])
        gs.send(lambda m: m.command_int_send(t, 1, frame, cmd, 0, 1, *params, x, y, z))
        return cmd
    if kind == 2:
        gs.send(lambda m: m.set_mode_send(t, _int(rng, 8), _int(rng, 32)))
        return mav.MAVLINK_MSG_ID_SET_MODE
    if kind == 3:
        mask = rng.choice([USE_POSITION, USE_VELOCITY, USE_POSITION_YAW, 0, 0xFFFF,
                           _int(rng, 16)])
        frame = rng.choice([1, 7, 8, 9, 0, 255])
        values = [f() for _ in range(11)]
        if rng.random() < 0.5:  # a plausible target or velocity, often near an edge
            values[:6] = [rng.uniform(-2, 10), rng.uniform(-2, 14), -rng.uniform(0, 5),
                          rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-1, 1)]
        gs.send(lambda m: m.set_position_target_local_ned_send(0, t, 1, frame, mask,
                                                               *values))
    elif kind == 4:
        mask = rng.choice([USE_POSITION, USE_VELOCITY, 0, _int(rng, 16)])
        frame = rng.choice([0, 3, 5, 6, 10, 11, 1, 255])
        gs.send(lambda m: m.set_position_target_global_int_send(
            0, t, 1, frame, mask, _int(rng, 32, True), _int(rng, 32, True),
            *[f() for _ in range(9)]))
    elif kind == 5:
        gs.send(lambda m: m.mission_count_send(t, 1, _int(rng, 16), rng.choice([0, 0, 1, 2])))
    elif kind == 6:
        gs.send(lambda m: m.mission_item_int_send(
            t, 1, rng.randrange(4), rng.choice([0, 3, 5, 6, 1, 255]),
            rng.choice([16, 22, 21, 20, 0, 65535]), _int(rng, 8), _int(rng, 8),
            *[f() for _ in range(4)], _int(rng, 32, True), _int(rng, 32, True), f(),
            rng.choice([0, 1, 2])))
    elif kind == 7:
        gs.send(lambda m: m.mission_set_current_send(t, 1, _int(rng, 16)))
    elif kind == 8:
        gs.send(lambda m: m.mission_request_list_send(t, 1, rng.choice([0, 1, 2, 255])))
    elif kind == 9:
        gs.send(lambda m: m.mission_request_int_send(t, 1, _int(rng, 16),
                                                      rng.choice([0, 1, 255])))
    elif kind == 10:
        gs.send(lambda m: m.mission_clear_all_send(t, 1, rng.choice([0, 1, 255])))
    elif kind == 11:
        name = rng.choice([b"WP_SPEED", b"WPNAV_SPEED", b"LAND_SPEED", b"RTL_ALT",
                           b"WP_RADIUS", b"NOPE", bytes(rng.randrange(256) for _ in range(16))])
        gs.send(lambda m: m.param_set_send(t, 1, name, f(), rng.choice([9, 0, 255])))
    elif kind == 12:
        gs.send(lambda m: m.param_request_read_send(t, 1, b"WP_SPEED", _int(rng, 16, True)))
    elif kind == 13:
        gs.send(lambda m: m.mission_request_send(t, 1, _int(rng, 16), rng.choice([0, 1, 9])))
    elif kind == 14:
        gs.send(lambda m: m.mission_ack_send(t, 1, _int(rng, 8), rng.choice([0, 1, 255])))
    else:
        gs.send(lambda m: m.request_data_stream_send(t, 1, _int(rng, 8), _int(rng, 16),
                                                     _int(rng, 8)))
    return None


@pytest.mark.timeout(300)  # about 45 s on an idle machine; a loaded one is slower
def test_fuzzing_every_handled_message_never_stops_beehave_sim(tmp_path: Path) -> None:
    """``beehave sim --mavlink`` under random and non-finite values in every message type
    the vehicles handle: it keeps running (heartbeats and telemetry go on), nothing leaves
    the world (LOCAL_POSITION_NED on the floor, under the ceiling), and every COMMAND_LONG,
    COMMAND_INT and SET_MODE gets its COMMAND_ACK."""
    import yaml  # type: ignore[import-untyped]

    world = tmp_path / "gcs.yaml"
    world.write_text(yaml.safe_dump(WORLD))
    base = free_port_pair()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    stations: list[GroundStation] = []
    proc: subprocess.Popen[str] | None = None
    try:
        for port in (base, base + 1):  # listening before the vehicles start
            stations.append(GroundStation(port, connect=False))
        proc = subprocess.Popen(
            [sys.executable, "-m", "beehave.cli", "sim", str(world), "--mavlink-base-port",
             str(base), "--no-lockstep"],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for station in stations:
            station.connect()
        rng = random.Random(FUZZ_SEED)

        def noise(gs: GroundStation) -> None:
            since = gs.mark()
            command = _fuzz_one(rng, gs)
            if command is not None:  # every command is answered, with its own id
                gs.wait("COMMAND_ACK", lambda a, c=command: a.command == c, since=since)

        for episode in range(10):
            gs = stations[episode % 2]
            for _ in range(80):
                noise(gs)
                time.sleep(0.005)
            _fly_out(rng, gs, lambda gs=gs: noise(gs))  # type: ignore[misc]
            assert proc.poll() is None, proc.communicate()[0]
        for gs in stations:  # the vehicles still live: a heartbeat and fresh telemetry
            assert gs.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL,
                              mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0) == \
                mav.MAV_RESULT_ACCEPTED  # the noise may have stopped it: the default again
            since = gs.mark()
            gs.wait("HEARTBEAT", since=since)
            boot = gs.latest("LOCAL_POSITION_NED").time_boot_ms
            gs.wait("LOCAL_POSITION_NED", lambda m, b=boot: m.time_boot_ms > b, since=since)
            positions = [m for m in gs.messages if m.get_type() == "LOCAL_POSITION_NED"]
            assert positions
            for m in positions:  # north = world y, east = world x, up = −z
                assert 0.0 <= m.x <= FLOOR[1] and 0.0 <= m.y <= FLOOR[0], m
                assert -30.0 <= m.z <= 0.01, m
        assert proc.poll() is None
    finally:
        for gs in stations:
            gs.close()
        out = ""
        if proc is not None:
            proc.terminate()
            out, _ = proc.communicate(timeout=WALL_TIMEOUT_S)
    assert "Traceback" not in out and " ERROR " not in out, out
