"""MAVLink: the HALs, the actions and the mission protocol against the simulation's
MAVLink endpoints (real UDP sockets, real pybullet), with faults injected by the endpoint."""

from __future__ import annotations

import asyncio
import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from beehave import Behavior, HighLevelBehaviorManager, Status
from beehave.blackboard import Blackboard
from beehave.errors import (
    ConfigError,
    MavlinkTimeout,
    MissionStalled,
    UnknownMode,
    VehicleLost,
)
from beehave.hal import HALManager
from beehave.testing import WALL_TIMEOUT_S, wait_until
from behaviours.mavlink import GotoPosition, RunMission, SetMode
from hal.mavlink import (
    MavlinkBatteryHAL,
    MavlinkHeartbeatHAL,
    MavlinkMissionHAL,
    MavlinkPositionHAL,
    Waypoint,
    close_all_links,
    open_link,
)
from robots.mavlink_endpoint import MavlinkEndpoint, free_udp_ports
from robots.sim import Simulation
from robots.world import world_from_dict

WORLD = {"name": "mav", "floor": {"size_m": [12, 8]},
         "walls": [{"from_m": [4, 0], "to_m": [4, 8], "height_m": 1.5}],
         "robots": [{"namespace": "rover1", "kind": "kobuki", "start": {"x_m": 2, "y_m": 2}},
                    {"namespace": "quad1", "kind": "quad", "start": {"x_m": 2, "y_m": 5}}]}


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@pytest.fixture
def cleanup(hl: HighLevelBehaviorManager) -> Iterator[Callable[[Callable[[], None]], None]]:
    """Clean-ups that run before the ``hl`` fixture checks for leaked threads."""
    cleanups: list[Callable[[], None]] = []
    yield cleanups.append
    for undo in reversed(cleanups):
        undo()


@dataclass
class Vehicles:
    sim: Simulation
    rover: MavlinkEndpoint
    quad: MavlinkEndpoint
    rover_url: str
    quad_url: str


@pytest.fixture
def vehicles() -> Iterator[Vehicles]:
    sim = Simulation(world_from_dict(WORLD), real_time_factor=1.0)
    ports = free_udp_ports(2)
    rover = MavlinkEndpoint(sim, "rover1", url=f"udpout:127.0.0.1:{ports[0]}", system_id=1,
                            rerequest_s=30.0)  # the client's retries must do the work
    quad = MavlinkEndpoint(sim, "quad1", url=f"udpout:127.0.0.1:{ports[1]}", system_id=2)
    sim.start()
    try:
        yield Vehicles(sim, rover, quad, f"udp:127.0.0.1:{ports[0]}",
                       f"udp:127.0.0.1:{ports[1]}")
    finally:
        close_all_links()
        rover.close()
        quad.close()
        sim.close()


#: How long a test's link waits for an answer before it sends again: long enough that a
#: loaded host's slow answer (the vehicle shares its process with the physics) is not taken
#: for a lost one, so ``resends`` counts only the drops a test injects.
RESEND_S = 2.0


def link_to(url: str, **options: Any) -> Any:
    link = open_link(url, timeout_s=RESEND_S, **options)
    link.wait_heartbeat(timeout_s=WALL_TIMEOUT_S)
    return link


WAYPOINTS = [Waypoint(2.0, 3.0), Waypoint(3.0, 3.0), Waypoint(3.0, 4.0), Waypoint(2.5, 4.5),
             Waypoint(2.0, 4.0)]


def world_xy(point: Waypoint) -> tuple[float, float]:
    return point.east_m, point.north_m  # the sim's NED origin is the world origin


# ---- mission protocol ---------------------------------------------------------------------

def test_mission_upload_round_trip_stores_every_item_where_it_was_meant(
        vehicles: Vehicles) -> None:
    link = link_to(vehicles.rover_url)
    resends = link.upload_mission(link.mission_items(WAYPOINTS))
    stored = vehicles.rover.mission
    assert resends == 0
    assert len(stored) == len(WAYPOINTS) + 1  # item 0 is home
    assert stored[0][:2] == (2.0, 2.0)
    for (x, y, _), point in zip(stored[1:], WAYPOINTS, strict=True):
        assert math.dist((x, y), world_xy(point)) < 0.01


def test_a_dropped_mission_request_is_recovered_by_the_clients_retry(
        vehicles: Vehicles) -> None:
    vehicles.rover.faults.drop_outgoing["MISSION_REQUEST_INT"] = 1
    link = link_to(vehicles.rover_url)
    resends = link.upload_mission(link.mission_items(WAYPOINTS))
    assert vehicles.rover.faults.dropped["out:MISSION_REQUEST_INT"] == 1
    assert resends == 1
    assert len(vehicles.rover.mission) == len(WAYPOINTS) + 1


def test_a_dropped_mission_item_is_sent_again(vehicles: Vehicles) -> None:
    vehicles.rover.faults.drop_incoming["MISSION_ITEM_INT"] = 1
    link = link_to(vehicles.rover_url)
    resends = link.upload_mission(link.mission_items(WAYPOINTS))
    assert vehicles.rover.faults.dropped["in:MISSION_ITEM_INT"] == 1
    assert resends == 1
    assert [round(x, 2) for x, _, _ in vehicles.rover.mission[1:]] == \
        [round(world_xy(p)[0], 2) for p in WAYPOINTS]


def test_unexpected_and_foreign_messages_are_ignored_with_a_count(
        vehicles: Vehicles, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="hal.mavlink")
    link = link_to(vehicles.rover_url)
    port = int(vehicles.rover_url.rsplit(":", 1)[1])
    from pymavlink import mavutil  # type: ignore[import-untyped]

    stranger = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=42,
                                          source_component=1)
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1,
                                         source_component=1)
    try:
        stranger.mav.heartbeat_send(10, 3, 128, 15, 4)  # an armed rover in GUIDED: not ours
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
            raw.sendto(b"\xfd\x09garbage-that-is-no-frame", ("127.0.0.1", port))
        vehicle.mav.mission_request_int_send(255, 190, 7)  # outside any upload: stray
        deadline = time.monotonic() + WALL_TIMEOUT_S
        while time.monotonic() < deadline and not link.ignored["message from system 42"]:
            time.sleep(0.02)
        assert link.ignored["message from system 42"] >= 1
        assert any("ignored message from system 42" in r.getMessage()
                   for r in caplog.records if r.name == "hal.mavlink"), caplog.text
        assert link.system_id == 1 and not link.armed  # the stranger changed nothing
        # The link still works: a full upload goes through afterwards.
        assert link.upload_mission(link.mission_items(WAYPOINTS[:2])) == 0
    finally:
        stranger.close()
        vehicle.close()


def test_out_of_order_items_are_ignored_by_the_vehicle(
        vehicles: Vehicles, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="robots.mavlink_endpoint")
    link = link_to(vehicles.rover_url)
    items = link.mission_items(WAYPOINTS)
    with link.listen("MISSION_REQUEST_INT") as inbox:
        link.send(lambda mav: mav.mission_count_send(1, 1, len(items)))
        assert inbox.wait(timeout_s=WALL_TIMEOUT_S, what="request 0").seq == 0
        link.send(link._item_sender(items[3]))  # seq 3 when 0 is expected
        deadline = time.monotonic() + WALL_TIMEOUT_S
        while time.monotonic() < deadline and not vehicles.rover.ignored:
            time.sleep(0.02)
    assert any("out of order" in reason for reason in vehicles.rover.ignored)
    assert "out of order" in caplog.text  # logged, not only counted
    assert link.upload_mission(items) == 0  # a new COUNT starts over cleanly


# ---- modes --------------------------------------------------------------------------------

def test_an_unknown_mode_is_refused_listing_the_valid_modes(vehicles: Vehicles) -> None:
    with pytest.raises(UnknownMode, match="valid modes: .*HOLD.*") as err:
        SetMode("FLY", connection=vehicles.rover_url)
    assert "GUIDED" in err.value.choices
    link = link_to(vehicles.rover_url)
    with pytest.raises(UnknownMode, match="for a rover; valid modes: ACRO, AUTO") as err:
        link.set_mode("LAND")  # a Copter mode: not in Rover's firmware
    assert "LAND" not in err.value.choices
    link.set_mode("guided")
    assert link.mode == "GUIDED"


def test_a_malformed_connection_names_the_supported_forms() -> None:
    with pytest.raises(ConfigError, match="udpin:HOST:PORT"):
        open_link("bluetooth:rover")
    with pytest.raises(ConfigError, match="port 1–65535"):
        open_link("udp:127.0.0.1:notaport")


def test_the_link_refuses_non_finite_targets_before_sending_them() -> None:
    """A NaN target, takeoff altitude or parameter is a mistake of the caller: ConfigError
    at once, naming it (the vehicle would refuse it anyway)."""
    link = open_link(f"udp:127.0.0.1:{free_port()}")
    try:
        with pytest.raises(ConfigError, match="position target must be finite"):
            link.goto_local(math.nan, 1.0, 2.0)
        with pytest.raises(ConfigError, match="takeoff altitude must be finite"):
            link.takeoff(math.inf)
        with pytest.raises(ConfigError, match="above 0 m"):
            link.takeoff(0.0)
        with pytest.raises(ConfigError, match="parameter WP_SPEED must be finite"):
            link.set_param("WP_SPEED", math.nan)
    finally:
        link.close()


def test_a_bad_waypoint_names_its_index() -> None:
    with pytest.raises(ConfigError, match=r"waypoints\[1\]"):
        RunMission([[1, 2], {"north": 3}], connection="udp:127.0.0.1:14550")


# ---- HALs ---------------------------------------------------------------------------------

def run_hals(url: str, body: Callable[[Blackboard], Any]) -> Any:
    async def main() -> Any:
        board = Blackboard()
        manager = HALManager(board, stop_timeout_s=0.5)
        for cls in (MavlinkHeartbeatHAL, MavlinkPositionHAL, MavlinkBatteryHAL,
                    MavlinkMissionHAL):
            manager.register(cls, connection=url, heartbeat_timeout_s=1.5)
            await manager.load(cls.name)
        try:
            return await body(board)
        finally:
            await manager.close()

    return asyncio.run(main())


async def until(predicate: Callable[[], bool], timeout_s: float = WALL_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.02)


def test_hals_fill_the_blackboard_and_a_lost_heartbeat_makes_every_value_stale(
        vehicles: Vehicles) -> None:
    async def body(board: Blackboard) -> None:
        await until(lambda: board.get("position/east_m") is not None
                    and board.get("battery/percentage") is not None
                    and board.get("vehicle/mode") is not None)
        assert board.get("vehicle/type") == "rover"
        assert board.get("vehicle/mode") == "HOLD"
        assert board.get("position/east_m") == pytest.approx(2.0, abs=0.05)
        assert board.get("position/north_m") == pytest.approx(2.0, abs=0.05)
        assert board.get("battery/percentage") == pytest.approx(100, abs=1)
        vehicles.rover.faults.silent = True
        await until(lambda: board.get("vehicle/connected") is False)
        for key in ("vehicle/mode", "position/east_m", "battery/percentage"):
            assert board.is_stale(key), key
        vehicles.rover.faults.silent = False
        await until(lambda: board.get("vehicle/connected") is True)
        await until(lambda: not board.is_stale("position/east_m"))

    run_hals(vehicles.rover_url, body)


# ---- actions ------------------------------------------------------------------------------

class Run(Behavior):
    """Starts one action and waits for it (the test keeps the handle)."""

    started: list[Any] = []

    def __init__(self, make: Callable[[], Any]) -> None:
        self.make = make

    def run(self) -> None:
        action = self.start_action(self.make())
        Run.started.append(action)
        action.wait()


def run_to_end(hl: HighLevelBehaviorManager, name: str, make: Callable[[], Any],
               timeout_s: float) -> Any:
    """Switch to a :class:`Run` of ``make()`` and return the action once it has ended."""
    Run.started = []
    hl.register(name, Run, make=make)
    hl.switch(name)
    deadline = time.monotonic() + timeout_s
    while not (Run.started and Run.started[0].wait(0.1)):
        assert time.monotonic() < deadline
    return Run.started[0]


def test_a_lost_heartbeat_stops_the_running_action_and_holds_the_vehicle(
        vehicles: Vehicles, hl: HighLevelBehaviorManager,
        cleanup: Callable[[Callable[[], None]], None]) -> None:
    url = vehicles.rover_url
    link = link_to(url, heartbeat_timeout_s=1.5)  # the action shares this link
    cleanup(link.close)
    Run.started = []
    hl.register("go", Run, make=lambda: GotoPosition(2.0, 10.0, connection=url,
                                                     heartbeat_timeout_s=1.5))
    hl.switch("go")
    deadline = time.monotonic() + WALL_TIMEOUT_S
    while not (Run.started and vehicles.rover.mode == "GUIDED" and vehicles.rover.armed):
        assert time.monotonic() < deadline, (Run.started, hl.snapshot())
        time.sleep(0.02)
    action = Run.started[0]
    vehicles.rover.faults.silent = True
    assert action.wait(WALL_TIMEOUT_S)
    assert action.status is Status.FAILED
    assert isinstance(action.error, VehicleLost)
    vehicles.rover.faults.silent = False
    # Its safe state asked for HOLD; the vehicle got it once the link came back or before.
    deadline = time.monotonic() + WALL_TIMEOUT_S
    while vehicles.rover.mode != "HOLD" and time.monotonic() < deadline:
        if link.alive:
            link.request_mode("HOLD")  # the safe state's single message may have been lost
        time.sleep(0.1)
    assert vehicles.rover.mode == "HOLD"


def test_a_rover_blocked_by_a_wall_stalls_with_its_remaining_waypoints(
        vehicles: Vehicles, hl: HighLevelBehaviorManager) -> None:
    url = vehicles.rover_url
    # Across the wall at x = 4: the rover reaches the first waypoint, then pushes the wall.
    waypoints = [[2.0, 3.0], [2.0, 9.0], [4.0, 9.0]]
    action = run_to_end(hl, "mission",
                        lambda: RunMission(waypoints, connection=url, stall_s=1.0),
                        WALL_TIMEOUT_S)
    assert action.status is Status.FAILED
    assert vehicles.sim.error is None
    assert isinstance(action.error, MissionStalled), vehicles.sim.time_s
    assert action.reached == [1]
    assert [(w.north_m, w.east_m) for w in action.error.remaining] == [(2.0, 9.0), (4.0, 9.0)]
    assert action.error.position[1] < 4.0  # in front of the wall (east = world x)
    # The safe state sends HOLD and does not wait for it (safe states are short).
    assert wait_until(lambda: vehicles.rover.mode == "HOLD"), vehicles.rover.mode


MISSION = [[2.0, 3.0], [4.0, 3.0], [3.5, 1.5]]


def rover_xy(vehicles: Vehicles) -> tuple[float, float]:
    """Where the physics has the rover (ground truth)."""
    odom = vehicles.rover.robot.odometry()
    return odom.x_m, odom.y_m


def held_still(vehicles: Vehicles, for_s: float) -> float:
    """Once braking is over, how far the rover moves in ``for_s`` (sim time)."""
    def settled() -> bool:
        before, t0 = rover_xy(vehicles), vehicles.sim.time_s
        while vehicles.sim.time_s < t0 + 0.5:
            time.sleep(0.02)
        return math.dist(before, rover_xy(vehicles)) < 0.01

    assert wait_until(settled), "the rover did not stop"
    start, t0 = rover_xy(vehicles), vehicles.sim.time_s
    while vehicles.sim.time_s < t0 + for_s:
        time.sleep(0.02)
    return math.dist(start, rover_xy(vehicles))


def start_mission(vehicles: Vehicles, hl: HighLevelBehaviorManager) -> Any:
    url = vehicles.rover_url
    Run.started = []
    hl.register("mission", Run, make=lambda: RunMission(MISSION, connection=url))
    hl.switch("mission")
    def driving() -> bool:
        # The vehicle drives its mission, and the action has seen it start (its link's
        # heartbeat says AUTO): from here on the mission loop watches the mode.
        link = Run.started[0]._link if Run.started else None
        return (link is not None and link.mode == "AUTO" and vehicles.rover.mode == "AUTO"
                and vehicles.rover.robot.odometry().linear_mps > 0.2)

    assert wait_until(driving)
    return Run.started[0]


def test_a_pause_holds_the_rover_and_the_resume_finishes_its_mission(
        vehicles: Vehicles, hl: HighLevelBehaviorManager) -> None:
    mission = start_mission(vehicles, hl)
    events: list[Any] = []
    hl.subscribe(events.append)
    hl.pause()
    assert wait_until(lambda: vehicles.rover.mode == "HOLD")
    assert held_still(vehicles, 1.5) < 0.02
    assert mission.status is Status.RUNNING and mission.pause_held  # kept its place
    hl.resume()
    assert wait_until(lambda: vehicles.rover.mode == "AUTO"), [e.as_dict() for e in events]
    assert mission.wait(WALL_TIMEOUT_S)
    assert mission.status is Status.SUCCEEDED, mission.error
    assert mission.result["reached"] == [1, 2, 3]  # the mission went on, not again
    assert math.dist(rover_xy(vehicles), (1.5, 3.5)) < 0.6  # the last waypoint (x=E, y=N)


def test_a_ground_station_hold_pauses_the_robot_until_beehave_resumes_it(
        vehicles: Vehicles, hl: HighLevelBehaviorManager,
        cleanup: Callable[[Callable[[], None]], None]) -> None:
    mission = start_mission(vehicles, hl)
    gcs = open_link(vehicles.rover_url)  # MAV_CMD_DO_SET_MODE, as a ground station sends it
    cleanup(gcs.close)
    gcs.request_mode("HOLD")
    assert wait_until(lambda: hl.paused and mission.pause_held)
    assert mission.status is Status.RUNNING  # not a failed mission: the operator holds it
    assert held_still(vehicles, 1.0) < 0.02
    hl.resume()
    assert wait_until(lambda: vehicles.rover.mode == "AUTO")
    assert mission.wait(WALL_TIMEOUT_S)
    assert mission.status is Status.SUCCEEDED, mission.error


def test_the_worlds_mavlink_option_is_checked_and_numbers_the_vehicles() -> None:
    from robots.errors import WorldError
    from robots.mavlink_endpoint import open_endpoints

    with pytest.raises(WorldError, match=r"mavlink\.base_port"):
        world_from_dict({**WORLD, "mavlink": {"base_port": 80}})
    world = world_from_dict({**WORLD, "mavlink": {"base_port": 14900}})
    assert world.mavlink is not None and world.mavlink.base_port == 14900
    sim = Simulation(world, real_time_factor=None)
    try:
        endpoints = open_endpoints(sim, base_port=free_port())
        try:
            assert [(e.namespace, e.kind, e.system_id) for e in endpoints.values()] == \
                [("rover1", "rover", 1), ("quad1", "copter", 2)]
        finally:
            for endpoint in endpoints.values():
                endpoint.close()
    finally:
        sim.close()

# How long writes race the newcomers: a negative check (nothing breaks) runs to its end, so
# it is short; a loaded machine makes it race less, never fail a right test.
CHURN_S = 1.5


def test_sending_while_new_peers_appear_never_breaks_the_link() -> None:
    """pymavlink's UDP server adds each new peer to a set that every write iterates: reads
    (the reader thread) and writes (any thread) must not interleave."""
    from pymavlink import mavutil

    port = free_port()
    link = open_link(f"udp:127.0.0.1:{port}")
    stop = threading.Event()

    def newcomers() -> None:  # every socket is a new address for the server
        while not stop.is_set():
            peer = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=9)
            peer.mav.heartbeat_send(6, 8, 0, 0, 4)
            peer.close()

    threads = [threading.Thread(target=newcomers, daemon=True) for _ in range(2)]
    for thread in threads:
        thread.start()
    errors: list[BaseException] = []
    try:
        deadline = time.monotonic() + CHURN_S
        while time.monotonic() < deadline:
            try:
                link.send(lambda mav: mav.heartbeat_send(6, 8, 0, 0, 4))
            except RuntimeError as exc:  # "Set changed size during iteration"
                errors.append(exc)
                break
    finally:
        stop.set()
        for thread in threads:
            thread.join()
        link.close()
    assert not errors
    assert link.ignored["message from system 9"] == 0  # GCS heartbeats are not the vehicle


def test_return_home_that_takes_too_long_fails_with_a_mavlink_timeout(
        vehicles: Vehicles, hl: HighLevelBehaviorManager,
        cleanup: Callable[[Callable[[], None]], None]) -> None:
    from behaviours.droid import ReturnHome

    url = vehicles.quad_url
    link = link_to(url)
    cleanup(link.close)
    link.set_mode("GUIDED")
    link.arm(True)
    link.takeoff(2.0)
    deadline = time.monotonic() + WALL_TIMEOUT_S
    while link.local_position()[2] < 1.0:
        assert time.monotonic() < deadline, "the quad did not climb"
        time.sleep(0.05)
    # Airborne, the quad draws hover_w (150 W) on top of idle: amperes, not a trickle.
    assert vehicles.sim.robot("quad1").battery().current_a < -5.0
    # Climbing to RTL_ALT and landing takes seconds: 0.3 s is not enough.
    action = run_to_end(hl, "home", lambda: ReturnHome(timeout_s=0.3, connection=url),
                        WALL_TIMEOUT_S)
    assert action.status is Status.FAILED
    assert isinstance(action.error, MavlinkTimeout), action.error
    assert "not home after 0.3 s" in str(action.error)


def test_beehave_sim_mavlink_opens_one_port_per_vehicle() -> None:
    """``beehave sim WORLD --mavlink-base-port B``: robot i is a MAVLink vehicle on B + i
    (system i + 1), the Kobuki a Rover, the quad a Copter, and they take commands."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    base = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "beehave.cli", "sim", "robots/worlds/droid.yaml",
         "--mavlink-base-port", str(base), "--duration-s", "30"],
        cwd=root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        rover = open_link(f"udp:127.0.0.1:{base}")
        copter = open_link(f"udp:127.0.0.1:{base + 1}")
        rover.wait_heartbeat(timeout_s=WALL_TIMEOUT_S)
        copter.wait_heartbeat(timeout_s=WALL_TIMEOUT_S)
        assert (rover.kind, rover.system_id) == ("rover", 1)
        assert (copter.kind, copter.system_id) == ("copter", 2)
        rover.set_mode("GUIDED")
        assert rover.mode == "GUIDED"
        assert copter.get_param("WPNAV_SPEED") == 200.0
    finally:
        close_all_links()
        proc.terminate()
        out, _ = proc.communicate(timeout=WALL_TIMEOUT_S)
    assert "rover1 is MAVLink rover system 1" in out and f":{base + 1}" in out, out


def test_a_starved_reader_reads_its_backlog_before_it_calls_the_vehicle_lost() -> None:
    """A process starved past ``heartbeat_timeout_s`` (a loaded host) finds the vehicle's
    heartbeats waiting in its socket behind more telemetry than one pass reads: the link
    stays alive, as the vehicle never went silent (seen: a follower's link "lost" at
    start-up beside busy loops)."""
    from pymavlink import mavutil

    port = free_port()
    link = open_link(f"udp:127.0.0.1:{port}", timeout_s=0.3, heartbeat_timeout_s=0.5)
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1,
                                         source_component=1)
    changes: list[bool] = []
    beating: threading.Thread | None = None
    try:
        def beat() -> None:
            vehicle.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GROUND_ROVER,
                                       mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)

        beat()
        link.wait_heartbeat(timeout_s=WALL_TIMEOUT_S)
        link.on_link(changes.append)
        with link._send_lock:  # the reader thread stops here, once data waits: as if starved
            for i in range(250):  # two and a half passes of telemetry, a heartbeat in it
                vehicle.mav.attitude_send(i, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                if i == 150:
                    time.sleep(1.0)  # twice the heartbeat timeout
                    beat()
        # The vehicle beats on (behind the backlog), so that a slow test thread cannot see
        # a loss that comes only after the backlog was read.
        stop_beating = threading.Event()

        def beat_on() -> None:
            while not stop_beating.wait(0.1):
                beat()

        beating = threading.Thread(target=beat_on)
        beating.start()
        # Read to its end: a link that judged the silence before reading the heartbeat
        # (pass one, 100 messages) has called the vehicle lost by now.
        assert wait_until(lambda: link.latest("ATTITUDE") is not None
                          and link.latest("ATTITUDE").time_boot_ms == 249)
        assert changes == [] and link.alive, changes
    finally:
        if beating is not None:
            stop_beating.set()
            beating.join()
        vehicle.close()
        link.close()


def test_a_backlog_that_never_drains_still_lets_a_silent_vehicle_be_lost() -> None:
    """Fault injection: every pass of the reader leaves messages waiting (a flood of
    foreign traffic): the heartbeat is judged after one heartbeat timeout of backlog, so
    a vehicle that went silent is still called lost."""
    from pymavlink import mavutil

    port = free_port()
    link = open_link(f"udp:127.0.0.1:{port}", timeout_s=0.3, heartbeat_timeout_s=0.3)
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1,
                                         source_component=1)
    try:
        vehicle.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GROUND_ROVER,
                                   mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)
        link.wait_heartbeat(timeout_s=WALL_TIMEOUT_S)
        link._receive = lambda: ([], False)  # type: ignore[method-assign]
        assert wait_until(lambda: not link.alive)
    finally:
        vehicle.close()
        link.close()


def test_free_ports_are_distinct_never_repeated_and_outside_the_kernels_range(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A port chosen by bind(0) and closed went to another socket before the link bound it
    ("Address already in use", a stress run): ports come from outside the kernel's
    ephemeral range, and never twice in a process."""
    from pathlib import Path

    import robots.mavlink_endpoint as endpoint

    lo, hi = (int(n) for n in Path("/proc/sys/net/ipv4/ip_local_port_range")
              .read_text(encoding="ascii").split())
    seen = [p for _ in range(20) for p in free_udp_ports(3)]
    assert len(set(seen)) == len(seen) == 60
    window = endpoint._port_window()
    if window is not None:
        assert not any(lo <= p <= hi for p in seen), (lo, hi, seen)
    # Without a window (a range of 1024-65535): the kernel's ports, still distinct.
    monkeypatch.setattr(endpoint, "_port_start", lambda: (range(0), 0))
    kernel = free_udp_ports(5)
    assert len(set(kernel)) == 5
