"""The sim node over real DDS: what any ROS 2 program sees of a running simulation.

Each test runs its own small world (robots in namespaces of their own) faster than real
time, and observes it with a plain rclpy probe in a separate context (its own DDS
participant), as another process would.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("pybullet")

from geometry_msgs.msg import Twist  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from ros_probe import Probe  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import BatteryState, LaserScan  # noqa: E402
from std_msgs.msg import ColorRGBA, Float64, Int32, String  # noqa: E402

from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, beehave_threads, wait_until  # noqa: E402
from robots import topics  # noqa: E402
from robots.node import SimNode, sim_main  # noqa: E402
from robots.sim import SimState, Simulation  # noqa: E402
from robots.world import World, world_from_dict  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
REAL_TIME_FACTOR = 4.0
# Negative checks (the robot stays put, no more odometry, the sim holds) run to their end:
# short on purpose. A loaded machine can only make them see less, never fail a right node.
QUIET_S = 0.3
_ids = itertools.count()


def unique(prefix: str) -> str:
    """A namespace no other test (or earlier run in this domain) uses."""
    return f"{prefix}_{os.getpid()}_{next(_ids)}"


def arena(emili_ns: str, kobuki_ns: str) -> World:
    """10 x 10 m, a wall whose face is at x = 8.0, lane tape along y = 8 from x = 1 to 6, a
    charging station at (1.5, 1.5). EMILI at (6, 5) facing the wall (2 m away), Kobuki at
    (7.3, 2) facing it (0.525 m between bumper and wall)."""
    return world_from_dict({
        "name": "node_arena",
        "floor": {"size_m": [10, 10]},
        "walls": [{"from_m": [8.1, 0], "to_m": [8.1, 10], "thickness_m": 0.2}],
        "lanes": [{"name": "tape", "points_m": [[1, 8], [6, 8]]}],
        "stations": [{"name": "dock", "kind": "charging", "center_m": [1.5, 1.5],
                      "size_m": [1.0, 1.0]}],
        "robots": [
            {"namespace": emili_ns, "kind": "emili", "start": {"x_m": 6, "y_m": 5}},
            {"namespace": kobuki_ns, "kind": "kobuki", "start": {"x_m": 7.3, "y_m": 2}},
        ],
    })


@dataclass
class Rig:
    sim: Simulation
    node: SimNode
    probe: Probe
    emili: str
    kobuki: str

    def topic(self, robot: str, name: str) -> str:
        return f"/{robot}/{name}"

    def publisher(self, msg_type: type, topic: str) -> Any:
        """A probe publisher, returned once the sim node's subscription has matched."""
        pub: Any = self.probe.node.create_publisher(msg_type, topic, 10)
        assert self.probe.wait(lambda: pub.get_subscription_count() >= 1), f"no sub on {topic}"
        return pub

    def repeat(self, publish: Callable[[], None], until: Callable[[], bool],
               timeout_s: float = 10.0, period_s: float = 0.02) -> bool:
        """Publish every ``period_s`` (wall) until ``until()``: a driver's command loop."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            publish()
            if until():
                return True
            time.sleep(period_s)
        return until()


@pytest.fixture
def rig() -> Iterator[Rig]:
    before = set(beehave_threads())
    emili, kobuki = unique("emili"), unique("kobuki")
    sim = Simulation(arena(emili, kobuki), real_time_factor=REAL_TIME_FACTOR)
    ros = RosContext()
    node = SimNode(sim, ros)
    ros.start()
    probe = Probe()
    sim.start()
    try:
        yield Rig(sim, node, probe, emili, kobuki)
    finally:
        sim.stop()
        node.destroy()
        ros.shutdown()
        probe.close()
        sim.close()
    leaked = [t.name for t in beehave_threads() if t not in before]
    assert not leaked, f"threads left after teardown: {leaked}"


def forward(speed_mps: float) -> Twist:
    msg = Twist()
    msg.linear.x = speed_mps
    return msg


def test_odometry_frames_and_quaternion(rig: Rig) -> None:
    odom = rig.probe.record(Odometry, rig.topic(rig.emili, "odom"))
    assert rig.probe.wait(lambda: len(odom) >= 3)
    msg = odom[-1]
    assert msg.header.frame_id == "map"
    assert msg.child_frame_id == f"{rig.emili}/base_link"
    assert msg.pose.pose.position.x == pytest.approx(6.0, abs=0.02)
    q = msg.pose.pose.orientation
    assert (q.x, q.y) == (0.0, 0.0) and q.z ** 2 + q.w ** 2 == pytest.approx(1.0)
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(0.0, abs=0.01)  # facing +x
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in odom]
    assert stamps == sorted(stamps) and stamps[-1] > 0  # sim time, advancing


def test_cmd_vel_drives_the_robot_and_the_watchdog_stops_it(rig: Rig) -> None:
    odom = rig.probe.record(Odometry, rig.topic(rig.emili, "odom"))
    cmd = rig.publisher(Twist, rig.topic(rig.emili, "cmd_vel"))
    assert rig.repeat(lambda: cmd.publish(forward(0.5)),
                      lambda: bool(odom) and odom[-1].pose.pose.position.x > 6.3)
    assert odom[-1].twist.twist.linear.x == pytest.approx(0.5, abs=0.1)
    # No more commands: the robot stops within the watchdog's 0.5 s of sim time.
    stopped_at = rig.sim.time_s
    assert rig.probe.wait(lambda: abs(odom[-1].twist.twist.linear.x) < 0.01
                          and rig.sim.time_s > stopped_at + 1.0)
    assert rig.sim.robot(rig.emili).cmd_vel() == (0.0, 0.0)
    x = odom[-1].pose.pose.position.x
    assert x < 7.0  # stopped well before the wall
    time.sleep(QUIET_S)
    assert odom[-1].pose.pose.position.x == pytest.approx(x, abs=0.005)


def test_scan_has_the_robot_frame_and_sees_the_wall(rig: Rig) -> None:
    scans = rig.probe.record(LaserScan, rig.topic(rig.emili, "scan"))
    assert rig.probe.wait(lambda: len(scans) >= 2)
    scan = scans[-1]
    assert scan.header.frame_id == f"{rig.emili}/base_link"
    assert len(scan.ranges) == 360
    assert scan.angle_min == pytest.approx(-math.pi)
    ahead = round((0.0 - scan.angle_min) / scan.angle_increment)
    assert scan.ranges[ahead] == pytest.approx(2.0, abs=0.02)  # centre to the wall's face
    left = round((math.pi / 2 - scan.angle_min) / scan.angle_increment)
    assert math.isinf(scan.ranges[left])  # nothing to the left within 20 m
    # Only new scans are published: 10 Hz of sim time, each stamped differently.
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in list(scans)]
    assert len(set(stamps)) == len(stamps)
    gaps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
    assert statistics.median(gaps) == pytest.approx(0.1, abs=0.01)


def test_clock_advances_at_100_hz_of_sim_time(rig: Rig) -> None:
    clock = rig.probe.record(Clock, topics.CLOCK)
    assert rig.probe.wait(lambda: len(clock) >= 50)
    stamps = [m.clock.sec + m.clock.nanosec * 1e-9 for m in list(clock)]
    assert stamps == sorted(stamps) and stamps[-1] > stamps[0]
    steps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
    # At 240 Hz physics a tick falls every 2 or 3 steps: 8.3 or 12.5 ms, 10 ms on average.
    assert statistics.median(steps) == pytest.approx(0.01, abs=0.0025)
    assert min(steps) >= 1 / 240 * 2 - 1e-6


def test_battery_state(rig: Rig) -> None:
    battery = rig.probe.record(BatteryState, rig.topic(rig.kobuki, "battery_state"))
    assert rig.probe.wait(lambda: len(battery) >= 2)
    msg = battery[-1]
    truth = rig.sim.robot(rig.kobuki).battery()
    assert 0.0 < msg.percentage <= 1.0
    assert msg.percentage == pytest.approx(truth.fraction, abs=0.01)
    assert msg.voltage == pytest.approx(truth.voltage_v, abs=0.05)
    assert msg.current < 0  # discharging
    assert msg.power_supply_status == BatteryState.POWER_SUPPLY_STATUS_DISCHARGING
    assert msg.present


def test_battery_state_charging_on_a_station() -> None:
    ns = unique("dock")
    world = world_from_dict({
        "name": "dock", "floor": {"size_m": [4, 4]},
        "stations": [{"name": "dock", "kind": "charging", "center_m": [1, 1]}],
        "robots": [{"namespace": ns, "kind": "kobuki", "start": {"x_m": 1, "y_m": 1}}]})
    sim = Simulation(world, real_time_factor=REAL_TIME_FACTOR)
    ros = RosContext()
    node = SimNode(sim, ros)
    ros.start()
    probe = Probe()
    try:
        battery = probe.record(BatteryState, f"/{ns}/battery_state")
        sim.start()
        assert probe.wait(lambda: bool(battery))
        assert battery[-1].power_supply_status == BatteryState.POWER_SUPPLY_STATUS_CHARGING
        assert battery[-1].current > 0
    finally:
        sim.stop()
        node.destroy()
        ros.shutdown()
        probe.close()
        sim.close()


def test_lift_command_reaches_the_height(rig: Rig) -> None:
    state = rig.probe.record(Float64, rig.topic(rig.emili, "lift/state"))
    command = rig.publisher(Float64, rig.topic(rig.emili, "lift/command"))
    command.publish(Float64(data=0.2))
    assert rig.probe.wait(lambda: bool(state) and abs(state[-1].data - 0.2) < 0.005)
    assert rig.sim.emili(rig.emili).lift_target() == 0.2


def test_line_sensor_is_nan_off_the_tape(rig: Rig) -> None:
    line = rig.probe.record(Float64, rig.topic(rig.emili, "line_sensor"))
    assert rig.probe.wait(lambda: len(line) >= 2)
    assert math.isnan(line[-1].data)


def test_emili_leds_display_and_sound_over_ros(rig: Rig) -> None:
    emili = rig.sim.emili(rig.emili)
    led_state = rig.probe.record(ColorRGBA, rig.topic(rig.emili, "leds/state"))
    display_state = rig.probe.record(String, rig.topic(rig.emili, "display/state"))
    rig.publisher(ColorRGBA, rig.topic(rig.emili, "leds")).publish(
        ColorRGBA(r=0.0, g=1.0, b=0.5, a=1.0))
    rig.publisher(String, rig.topic(rig.emili, "display")).publish(String(data="loading"))
    rig.publisher(String, rig.topic(rig.emili, "sound")).publish(String(data="horn"))
    assert wait_until(lambda: emili.leds() == (0.0, 1.0, 0.5))
    assert wait_until(lambda: emili.display() == "loading")
    assert wait_until(lambda: [s.name for s in emili.sounds()] == ["horn"])
    # The state echoes follow on change (long before their 1 Hz repeat).
    assert rig.probe.wait(lambda: bool(led_state) and (led_state[-1].g, led_state[-1].b)
                          == (1.0, 0.5))
    assert rig.probe.wait(lambda: bool(display_state) and display_state[-1].data == "loading")


def test_kobuki_leds_and_sound_over_ros(rig: Rig) -> None:
    kobuki = rig.sim.kobuki(rig.kobuki)
    rig.publisher(String, rig.topic(rig.kobuki, "leds/led1")).publish(String(data="green"))
    assert wait_until(lambda: kobuki.leds() == ("green", "off"))
    rig.publisher(String, rig.topic(rig.kobuki, "leds/led2")).publish(String(data="red"))
    assert wait_until(lambda: kobuki.leds() == ("green", "red"))
    rig.publisher(String, rig.topic(rig.kobuki, "sound")).publish(String(data="recharge"))
    assert wait_until(lambda: [s.name for s in kobuki.sounds()] == ["recharge"])


def test_invalid_commands_are_refused_counted_and_logged(
        rig: Rig, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR, logger="robots.node")
    emili, kobuki = rig.sim.emili(rig.emili), rig.sim.kobuki(rig.kobuki)
    lift = rig.publisher(Float64, rig.topic(rig.emili, "lift/command"))
    leds = rig.publisher(ColorRGBA, rig.topic(rig.emili, "leds"))
    cmd = rig.publisher(Twist, rig.topic(rig.emili, "cmd_vel"))
    sound = rig.publisher(String, rig.topic(rig.emili, "sound"))
    led1 = rig.publisher(String, rig.topic(rig.kobuki, "leds/led1"))
    beep = rig.publisher(String, rig.topic(rig.kobuki, "sound"))
    lift.publish(Float64(data=0.5))
    lift.publish(Float64(data=math.nan))
    leds.publish(ColorRGBA(r=2.0, g=0.0, b=0.0, a=1.0))
    cmd.publish(forward(math.nan))
    sound.publish(String(data=""))
    led1.publish(String(data="purple"))
    beep.publish(String(data="beep"))
    expected = {f"/{rig.emili}/lift/command": 2, f"/{rig.emili}/leds": 1,
                f"/{rig.emili}/cmd_vel": 1, f"/{rig.emili}/sound": 1,
                f"/{rig.kobuki}/leds/led1": 1, f"/{rig.kobuki}/sound": 1}
    assert wait_until(lambda: dict(rig.node.rejected) == expected), rig.node.rejected
    # The robots kept their state.
    assert emili.lift_target() == 0.0 and emili.leds() == (0.0, 0.0, 0.0)
    assert emili.cmd_vel() == (0.0, 0.0) and emili.sounds() == []
    assert kobuki.leds() == ("off", "off") and kobuki.sounds() == []
    # Each error names the robot, the topic, the value and what is valid.
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert f"robot {rig.emili!r} refused lift height 0.5 m on /{rig.emili}/lift/command; " \
           "valid: a height of 0–0.3 m" in text
    assert "LED colour r=2.0" in text and "each 0–1" in text
    assert "linear.x=nan" in text and "finite numbers" in text
    assert f"refused LED colour 'purple' on /{rig.kobuki}/leds/led1; valid: off, green, " \
           "orange, red" in text
    assert "sound 'beep'" in text and "cleaning_start" in text
    # The node goes on: a valid command after the bad ones still works.
    lift.publish(Float64(data=0.1))
    assert wait_until(lambda: emili.lift_target() == 0.1)


def test_kobuki_bumper_bit_set_when_driving_into_a_wall(rig: Rig) -> None:
    bumpers = rig.probe.record(Int32, rig.topic(rig.kobuki, "bumpers"))
    cliffs = rig.probe.record(Int32, rig.topic(rig.kobuki, "cliffs"))
    buttons = rig.probe.record(Int32, rig.topic(rig.kobuki, "buttons"))
    cmd = rig.publisher(Twist, rig.topic(rig.kobuki, "cmd_vel"))
    assert rig.probe.wait(lambda: bool(bumpers) and bumpers[-1].data == 0)
    assert rig.repeat(lambda: cmd.publish(forward(0.3)),
                      lambda: bool(bumpers) and bool(bumpers[-1].data & topics.CENTER))
    assert not bumpers[-1].data & (topics.LEFT | topics.RIGHT)
    assert cliffs[-1].data == 0  # the floor is everywhere here
    rig.sim.kobuki(rig.kobuki).press_button(1, hold_s=1.0)
    assert rig.probe.wait(lambda: bool(buttons) and buttons[-1].data == 0b010)


def test_destroy_removes_the_nodes_and_callbacks(rig: Rig) -> None:
    topic = rig.topic(rig.emili, "odom")
    odom = rig.probe.record(Odometry, topic)
    assert rig.probe.wait(lambda: bool(odom) and rig.probe.publishers(topic) == 1)
    rig.node.destroy()
    assert rig.probe.wait(lambda: rig.probe.publishers(topic) == 0
                          and rig.probe.publishers(topics.CLOCK) == 0)
    count = len(odom)
    time.sleep(QUIET_S)
    assert len(odom) == count
    assert rig.sim.state.value == "running"  # the simulation goes on without ROS
    rig.node.destroy()  # idempotent


def test_sim_main_rejects_a_bad_world_and_speed(capsys: pytest.CaptureFixture[str]) -> None:
    assert sim_main(["no_such_world"]) == 2
    assert "warehouse" in capsys.readouterr().err  # the shipped worlds are listed
    assert sim_main(["--real-time-factor", "0"]) == 2
    assert "--fast" in capsys.readouterr().err
    assert sim_main(["--fast", "--real-time-factor", "2"]) == 2  # mutually exclusive


def test_beehave_sim_runs_until_sigint(tmp_path: Path) -> None:
    ns = unique("cli")
    world = tmp_path / "one.yaml"
    world.write_text(
        "name: one\nfloor: {size_m: [4, 4]}\n"
        f"robots:\n  - {{namespace: {ns}, kind: kobuki, start: {{x_m: 2, y_m: 2}}}}\n")
    probe = Probe()
    proc = subprocess.Popen([sys.executable, "-m", "robots.node", str(world), "--fast"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None
        ready = proc.stdout.readline()
        assert "beehave sim: world 'one' running as fast as possible" in ready, ready
        assert f"{ns} (kobuki)" in ready
        odom = probe.record(Odometry, f"/{ns}/odom")
        assert probe.wait(lambda: bool(odom))
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=WALL_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        probe.close()
    assert proc.returncode == 0, err
    assert "stopped cleanly" in out
    assert "Traceback" not in err


def lockstep(participant: str, until_s: float | None) -> String:
    return String(data=json.dumps({"participant": participant, "until_s": until_s}))


def test_lockstep_holds_the_sim_where_a_participant_is_due_until_it_answers(rig: Rig) -> None:
    clocks = rig.probe.record(Clock, topics.CLOCK)
    pub = rig.publisher(String, topics.LOCKSTEP)
    me = unique("controller")
    hold_s = rig.sim.time_s + 0.5
    pub.publish(lockstep(me, hold_s))
    assert rig.probe.wait(lambda: rig.node.participants.get(me) == hold_s)
    # A live participant keeps announcing (a silent one is let go after 1 s of wall time,
    # which a loaded machine may take between two of this test's steps).
    alive = threading.Event()

    def keep_announcing() -> None:
        while not alive.wait(0.1):
            pub.publish(lockstep(me, hold_s))

    keeper = threading.Thread(target=keep_announcing, daemon=True)
    keeper.start()
    try:
        assert rig.probe.wait(lambda: rig.sim.time_s >= hold_s - 1e-6)
        # Held there: the sim runs at 4x, so 0.3 s of wall time would be 1.2 s of sim time.
        # (Measured from where it stopped: on a loaded machine the announcement may reach
        # the node after the sim passed hold_s; it then holds at once.)
        time.sleep(0.05)
        held_at = rig.sim.time_s
        time.sleep(QUIET_S)
        assert not rig.node.dropped, rig.node.dropped
        assert rig.sim.time_s <= held_at + 2 * rig.sim.step_s
        # While held, /clock says the held time again and again: it is best effort (so
        # is rclpy's time source), and a process that lost it would wait for it.
        held_s = rig.sim.time_s
        assert rig.probe.wait(lambda: sum(abs(stamp_s(c) - held_s) < 1e-6
                                          for c in list(clocks)) >= 3), \
            [stamp_s(c) for c in clocks[-5:]]
    finally:
        alive.set()
        keeper.join(WALL_TIMEOUT_S)
    # ...and /clock says it has reached the held time, so the participant wakes.
    assert rig.probe.wait(lambda: bool(clocks) and stamp_s(clocks[-1]) >= hold_s - 1e-6)
    pub.publish(lockstep(me, None))  # let go
    assert rig.probe.wait(lambda: rig.sim.time_s > hold_s + 0.5)
    assert me not in rig.node.participants and not rig.node.dropped


def test_lockstep_lets_a_silent_participant_go_after_its_timeout(
        rig: Rig, caplog: pytest.LogCaptureFixture) -> None:
    pub = rig.publisher(String, topics.LOCKSTEP)
    ghost = unique("crashed")
    hold_s = rig.sim.time_s + 0.2
    with caplog.at_level(logging.WARNING, logger="robots.node"):
        pub.publish(lockstep(ghost, hold_s))  # and never again, as a crashed process
        assert rig.probe.wait(lambda: rig.sim.time_s > hold_s + 1.0)
    assert rig.node.dropped[ghost] == 1
    assert ghost in caplog.text and "did not answer" in caplog.text


def test_lockstep_refuses_a_malformed_announcement(rig: Rig) -> None:
    pub = rig.publisher(String, topics.LOCKSTEP)
    pub.publish(String(data=json.dumps({"participant": "x", "until_s": "soon"})))
    assert rig.probe.wait(lambda: rig.node.rejected[topics.LOCKSTEP] == 1)
    assert not rig.node.participants


def test_a_release_with_stop_zeroes_the_wheels_before_the_sim_runs_on(rig: Rig) -> None:
    """The release names the robot's cmd_vel: the sim stops that robot as it lets go, so a
    release that overtakes the zero command on cmd_vel (no order between two topics) cannot
    let the robot drive on with its old one."""
    me = unique("driver")
    lock = rig.publisher(String, topics.LOCKSTEP)
    robot = rig.sim.robot(rig.emili)
    hold_s = rig.sim.time_s + 0.2
    lock.publish(lockstep(me, hold_s))
    assert rig.probe.wait(lambda: me in rig.node.participants)
    robot.set_cmd_vel(0.4, 0.0)  # the command the robot drove on, not yet overtaken
    lock.publish(String(data=json.dumps({"participant": me, "until_s": None,
                                         "stop": rig.topic(rig.emili, "cmd_vel")})))
    assert rig.probe.wait(lambda: me not in rig.node.participants)
    assert robot.cmd_vel() == (0.0, 0.0)
    # A stop that names no robot of this simulation is refused, naming the valid ones.
    before = rig.node.rejected[topics.LOCKSTEP]
    lock.publish(String(data=json.dumps({"participant": me, "until_s": None,
                                         "stop": "/nobody/cmd_vel"})))
    assert rig.probe.wait(lambda: rig.node.rejected[topics.LOCKSTEP] == before + 1)


def stamp_s(msg: Clock) -> float:
    return float(msg.clock.sec + msg.clock.nanosec * 1e-9)


def test_destroy_leaves_a_gate_that_is_not_its_own(rig: Rig) -> None:
    # Someone else (a second node, a test harness) gates the sim after this node did:
    # destroying this node must take away only its own gate, not theirs.
    holding = True
    remove = rig.sim.set_gate(lambda time_s: holding)
    rig.node.destroy()
    held_at = rig.sim.time_s
    time.sleep(QUIET_S)  # at 4x, 1.2 s of sim time if it ran
    assert rig.sim.time_s <= held_at + rig.sim.step_s
    assert rig.sim.gate is not None
    holding = False
    remove()
    assert rig.sim.gate is None
    assert rig.probe.wait(lambda: rig.sim.time_s > held_at + 0.2)


def test_a_message_fast_dds_refuses_is_dropped_and_logged_and_the_simulation_goes_on(
        rig: Rig, caplog: pytest.LogCaptureFixture) -> None:
    """Fast DDS refuses a write whose history stays full for max_blocking_time (readers on
    a starved host): raised in the stepping thread, that stopped a fleet's simulation in a
    stress run. Fault injection: the odometry publisher refuses three messages."""
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

    from robots.node import publish_drops

    ports = rig.node.ports[rig.emili]
    real = ports._odom_pub
    refusals = itertools.count()

    class Refusing:
        def __getattr__(self, name: str) -> Any:
            return getattr(real, name)

        def publish(self, msg: Any) -> None:
            if next(refusals) < 3:
                raise _rclpy.RCLError("Failed to publish: cannot publish data, at "
                                      "rmw_publish.cpp:66")
            real.publish(msg)

    odom: list[Odometry] = []
    rig.probe.node.create_subscription(Odometry, rig.topic(rig.emili, "odom"), odom.append,
                                       10)
    before = publish_drops().get(real.topic_name, 0)
    with caplog.at_level(logging.WARNING, logger="robots.node"):
        ports._odom_pub = Refusing()
        start_s = rig.sim.time_s
        assert rig.probe.wait(lambda: len(odom) >= 5 and rig.sim.time_s > start_s + 0.5)
    assert rig.sim.state is SimState.RUNNING, rig.sim.state
    assert publish_drops()[real.topic_name] == before + 3
    assert f"Fast DDS refused a message on {real.topic_name}" in caplog.text, caplog.text
