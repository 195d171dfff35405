"""The physics simulation: driving, watchdog, sensors, lift, LEDs, battery, Kobuki's bumpers
and cliffs, several robots, the stepping thread. Stepped by hand (faster than real time)
except where the thread itself is under test."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from PIL import Image

from beehave.testing import beehave_threads, wait_until
from robots.emili import Emili
from robots.errors import CommandOutOfRange, SimulationError, UnknownRobot
from robots.kobuki import Kobuki
from robots.sim import SimState, Simulation
from robots.world import World, world_from_dict


def arena(*robots: dict[str, Any], **extra: Any) -> World:
    """A 10 x 10 m floor with one wall whose face is at x = 8.0, and the given robots."""
    data: dict[str, Any] = {
        "name": "arena",
        "floor": {"size_m": [10, 10]},
        "walls": [{"from_m": [8.1, 0], "to_m": [8.1, 10], "thickness_m": 0.2}],
        "robots": list(robots),
    }
    data.update(extra)
    return world_from_dict(data)


def emili_at(x: float, y: float, yaw_deg: float = 0.0, ns: str = "emili1",
             **extra: Any) -> dict[str, Any]:
    return {"namespace": ns, "kind": "emili",
            "start": {"x_m": x, "y_m": y, "yaw_deg": yaw_deg}, **extra}


def kobuki_at(x: float, y: float, yaw_deg: float = 0.0, ns: str = "kobuki1",
              **extra: Any) -> dict[str, Any]:
    return {"namespace": ns, "kind": "kobuki",
            "start": {"x_m": x, "y_m": y, "yaw_deg": yaw_deg}, **extra}


@pytest.fixture
def make_sim() -> Iterator[Any]:
    """Builds hand-stepped simulations and closes them; checks no sim thread is left."""
    sims: list[Simulation] = []

    def make(world: World | str, **options: Any) -> Simulation:
        options.setdefault("real_time_factor", None)
        sim = Simulation(world, **options)
        sims.append(sim)
        return sim

    yield make
    for sim in sims:
        sim.close()
    assert not [t for t in beehave_threads() if t.name == "beehave-sim"]


def drive(sim: Simulation, robot: Any, linear_mps: float, angular_rps: float,
          duration_s: float) -> None:
    """Command at 10 Hz (as a ROS node would) for ``duration_s`` of sim time."""
    for _ in range(round(duration_s * 10)):
        robot.set_cmd_vel(linear_mps, angular_rps)
        sim.run_for(0.1)


# ---- driving ----------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["emili", "kobuki"])
def test_drives_straight_as_commanded(make_sim: Any, kind: str) -> None:
    start = emili_at(2, 5) if kind == "emili" else kobuki_at(2, 5)
    sim = make_sim(arena(start))
    robot = sim.robot(start["namespace"])
    drive(sim, robot, 0.5, 0.0, 3.0)
    pose = robot.pose()
    # 1.5 m minus the short acceleration phase.
    assert pose.x_m - 2 == pytest.approx(1.5, abs=0.06)
    assert pose.y_m == pytest.approx(5, abs=0.03)
    assert pose.yaw_rad == pytest.approx(0, abs=0.03)
    odom = robot.odometry()
    assert odom.linear_mps == pytest.approx(0.5, abs=0.02)
    assert odom.time_s == pytest.approx(3.0)


@pytest.mark.parametrize("kind", ["emili", "kobuki"])
def test_turns_on_the_spot_as_commanded(make_sim: Any, kind: str) -> None:
    start = emili_at(2, 5) if kind == "emili" else kobuki_at(2, 5)
    sim = make_sim(arena(start))
    robot = sim.robot(start["namespace"])
    drive(sim, robot, 0.0, 0.5, 2.0)
    pose = robot.pose()
    assert pose.yaw_rad == pytest.approx(1.0, abs=0.05)
    assert math.hypot(pose.x_m - 2, pose.y_m - 5) < 0.03
    # The instantaneous rate jitters with the wheels' contacts; the mean is exact.
    assert robot.odometry().angular_rps == pytest.approx(0.5, abs=0.08)


def test_commands_are_clamped_to_the_limits(make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(1, 5)))
    emili = sim.emili("emili1")
    emili.set_cmd_vel(5.0, -9.0)
    sim.step()
    assert emili.cmd_vel() == (Emili.limits.max_linear_mps, -Emili.limits.max_angular_rps)
    with pytest.raises(CommandOutOfRange, match="finite"):
        emili.set_cmd_vel(math.nan, 0.0)


def test_watchdog_stops_a_robot_without_fresh_commands(make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(2, 5)), cmd_timeout_s=0.5)
    emili = sim.emili("emili1")
    emili.set_cmd_vel(0.5, 0.0)
    sim.run_for(0.4)
    assert emili.cmd_vel() == (0.5, 0.0)
    sim.run_for(0.2)  # 0.6 s after the only command
    assert emili.cmd_vel() == (0.0, 0.0)
    sim.run_for(1.0)
    stopped_at = emili.pose().x_m
    assert emili.odometry().linear_mps == pytest.approx(0.0, abs=0.01)
    sim.run_for(1.0)
    assert emili.pose().x_m == pytest.approx(stopped_at, abs=0.005)
    assert stopped_at - 2 < 0.35  # ~0.5 s at 0.5 m/s, then braking


# ---- sensors ----------------------------------------------------------------------------

def test_laser_sees_the_wall_at_the_right_distance(make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(2, 5), kobuki_at(5, 2, 90)))
    sim.run_for(0.2)
    scan = sim.emili("emili1").scan()
    assert scan is not None
    assert len(scan.ranges_m) == 360
    assert scan.angle_increment_rad == pytest.approx(2 * math.pi / 360)
    assert scan.range_at(0.0) == pytest.approx(6.0, abs=0.02)  # wall face at x = 8
    assert scan.range_at(math.pi) == math.inf  # nothing behind within 20 m
    assert min(scan.ranges_m) >= scan.range_min_m
    # The Kobuki, turned by 90°, has the wall on its right (3 m away).
    kscan = sim.kobuki("kobuki1").scan()
    assert kscan is not None
    assert kscan.range_at(-math.pi / 2) == pytest.approx(3.0, abs=0.02)


@pytest.mark.parametrize(("y", "yaw_deg", "expected"), [
    (4.95, 0, 0.05),     # tape 5 cm to the left
    (5.03, 0, -0.03),    # tape 3 cm to the right
    (4.95, 180, -0.05),  # facing the other way, the same tape is on the right
    (5.50, 0, None),     # no tape within the camera's ±0.10 m
])
def test_line_sensor_gives_the_tape_offset(make_sim: Any, y: float, yaw_deg: float,
                                           expected: float | None) -> None:
    lanes = [{"name": "l", "points_m": [[0.5, 5.0], [7.5, 5.0]]}]
    sim = make_sim(arena(emili_at(4, y, yaw_deg), lanes=lanes))
    sim.step()
    offset = sim.emili("emili1").line_sensor()
    if expected is None:
        assert offset is None
    else:
        assert offset == pytest.approx(expected, abs=0.003)


def test_line_sensor_follows_a_tape_around_a_corner(make_sim: Any) -> None:
    lanes = [{"name": "l", "points_m": [[3.5, 2], [6, 2], [6, 7]]}]
    sim = make_sim(arena(emili_at(4, 2.05), lanes=lanes))
    emili = sim.emili("emili1")
    for _ in range(250):  # 25 s of a proportional line follower at 10 Hz, slow at 0.2 m/s
        offset = emili.line_sensor()
        assert offset is not None, f"lost the tape at {emili.pose()}"
        emili.set_cmd_vel(0.2, 10.0 * offset)
        sim.run_for(0.1)
    pose = emili.pose()
    assert pose.y_m > 4.0  # went round the corner and up the second leg
    assert pose.x_m == pytest.approx(6.0, abs=0.03)
    assert pose.yaw_rad == pytest.approx(math.pi / 2, abs=0.05)


def test_lift_reaches_its_height_and_rejects_out_of_range(make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(2, 5)))
    emili = sim.emili("emili1")
    emili.set_lift(0.25)
    sim.run_for(1.0)
    assert 0.05 < emili.lift_height() < 0.2  # on its way at 0.1 m/s
    sim.run_for(2.0)
    assert emili.lift_height() == pytest.approx(0.25, abs=0.003)
    emili.set_lift(0.0)
    sim.run_for(3.0)
    assert emili.lift_height() == pytest.approx(0.0, abs=0.003)
    with pytest.raises(CommandOutOfRange, match=r"emili1: lift height 0.4 m .* 0–0.3 m"):
        emili.set_lift(0.4)


def test_led_colour_shows_in_the_visual_shape_and_the_picture(make_sim: Any,
                                                              tmp_path: Path) -> None:
    sim = make_sim(arena(emili_at(3, 5)))
    emili = sim.emili("emili1")
    emili.set_leds(0.0, 1.0, 0.0)
    sim.step()
    link = emili._links["led_strip"]
    rgba = [v[7] for v in sim.call(lambda c: c.getVisualShapeData(emili.body_id))
            if v[1] == link]
    assert rgba == [pytest.approx((0.0, 1.0, 0.0, 1.0))]
    assert emili.leds() == (0.0, 1.0, 0.0)

    image = Image.open(sim.render_topdown(tmp_path / "top.png", scale_px_per_m=40))
    # The strip's rim, 0.455 m behind the centre: (3 - 0.455 + 0.5 margin) * 40 px.
    rim = image.getpixel((round((3 - 0.455 + 0.5) * 40), round((10 - 5 + 0.5) * 40)))
    assert rim == (0, 255, 0)

    camera = sim.camera_image(center_m=(3, 5), height_m=2.0, width_px=64, height_px=64)
    green = (camera[:, :, 1] > 200) & (camera[:, :, 0] < 60) & (camera[:, :, 2] < 60)
    assert green.sum() > 20, "no green LED pixels in the rendered camera image"
    with pytest.raises(CommandOutOfRange, match="0–1"):
        emili.set_leds(0, 2, 0)


def test_battery_drains_when_driving_and_charges_on_a_station(make_sim: Any) -> None:
    stations = [{"name": "dock", "kind": "charging", "center_m": [2, 8], "size_m": [1, 1]}]
    battery = {"capacity_wh": 1.0, "initial_fraction": 0.5}
    sim = make_sim(arena(emili_at(2, 2, battery=battery, ns="driver"),
                         emili_at(2, 5, battery=battery, ns="idler"),
                         emili_at(2, 8, battery=battery, ns="docked"),
                         stations=stations))
    driver, idler, docked = (sim.robot(n) for n in ("driver", "idler", "docked"))
    for _ in range(30):
        driver.set_cmd_vel(0.8, 0.3)
        sim.run_for(0.1)
    drained = 0.5 - driver.battery().fraction
    idle = 0.5 - idler.battery().fraction
    assert idle == pytest.approx(30 * 3 / 3600, rel=0.05)  # 30 W for 3 s out of 1 Wh
    assert drained > 2 * idle
    assert driver.battery().current_a < 0 and not driver.battery().charging
    state = docked.battery()
    assert state.charging and state.current_a > 0
    assert state.fraction == pytest.approx(0.5 + 300 * 3 / 3600, abs=0.01)
    assert state.voltage_v > idler.battery().voltage_v
    assert state.percentage == pytest.approx(state.fraction * 100)


def test_an_empty_battery_stops_the_drive(make_sim: Any) -> None:
    battery = {"capacity_wh": 0.001, "initial_fraction": 0.01}
    sim = make_sim(arena(kobuki_at(2, 5, battery=battery)))
    kobuki = sim.kobuki("kobuki1")
    drive(sim, kobuki, 0.3, 0.0, 1.0)
    assert kobuki.battery().fraction == 0.0
    assert kobuki.cmd_vel() == (0.0, 0.0)


# ---- Kobuki -----------------------------------------------------------------------------

@pytest.mark.parametrize(("yaw_deg", "pressed"), [(0, "center"), (50, "right"),
                                                  (-50, "left")])
def test_kobuki_bumper_triggers_on_driving_into_a_wall(make_sim: Any, yaw_deg: float,
                                                       pressed: str) -> None:
    sim = make_sim(arena(kobuki_at(7.6, 5, yaw_deg)))
    kobuki = sim.kobuki("kobuki1")
    assert not kobuki.bumpers().any()
    hits: set[str] = set()
    for _ in range(30):
        kobuki.set_cmd_vel(0.2, 0.0)
        sim.run_for(0.1)
        bumpers = kobuki.bumpers()
        hits |= {name for name in ("left", "center", "right") if getattr(bumpers, name)}
        if hits:
            break
    assert hits == {pressed}


def test_kobuki_cliff_sensor_sees_a_hole_before_the_wheels_drop(make_sim: Any) -> None:
    holes = [{"center_m": [6, 5], "size_m": [2, 2]}]  # edge at x = 5
    sim = make_sim(arena(kobuki_at(4.7, 5), holes=holes))
    kobuki = sim.kobuki("kobuki1")
    sim.run_for(0.1)
    assert not kobuki.cliffs().any()
    for _ in range(100):
        kobuki.set_cmd_vel(0.1, 0.0)
        sim.run_for(0.02)
        if kobuki.cliffs().center:
            break
    assert kobuki.cliffs().center
    # The centre sensor is 0.16 m ahead: it sees the edge while the wheels are on the floor.
    assert kobuki.pose().x_m == pytest.approx(5 - 0.16, abs=0.03)
    assert kobuki.wheel_drop() == (kobuki.wheel_drop().__class__(False, False))


def test_kobuki_wheels_drop_over_a_hole(make_sim: Any) -> None:
    holes = [{"center_m": [5, 5], "size_m": [2, 2]}]
    sim = make_sim(arena(kobuki_at(5, 5), holes=holes))
    sim.run_for(0.3)
    kobuki = sim.kobuki("kobuki1")
    drop = kobuki.wheel_drop()
    assert drop.left and drop.right
    assert kobuki.cliffs().left and kobuki.cliffs().center and kobuki.cliffs().right


def test_kobuki_buttons_leds_and_sounds(make_sim: Any) -> None:
    sim = make_sim(arena(kobuki_at(2, 5)))
    kobuki = sim.kobuki("kobuki1")
    kobuki.press_button(1, hold_s=0.2)
    assert kobuki.buttons() == (False, True, False)
    sim.run_for(0.25)
    assert kobuki.buttons() == (False, False, False)
    with pytest.raises(CommandOutOfRange, match="buttons: 0, 1, 2"):
        kobuki.press_button(3)
    kobuki.set_leds("green", "red")
    assert kobuki.leds() == ("green", "red")
    with pytest.raises(CommandOutOfRange, match="colours: off, green, orange, red"):
        kobuki.set_leds("green", "blue")  # type: ignore[arg-type]
    kobuki.play_sound("recharge")
    assert [(s.name, s.time_s) for s in kobuki.sounds()] == [("recharge", sim.time_s)]
    with pytest.raises(CommandOutOfRange, match="sounds: on, off"):
        kobuki.play_sound("tada")


def test_emili_display_and_speaker_are_recorded(make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(2, 5)))
    emili = sim.emili("emili1")
    emili.set_display("loading")
    emili.play_sound("beep.wav")
    assert emili.display() == "loading"
    assert [s.name for s in emili.sounds()] == ["beep.wav"]


# ---- several robots, the thread ---------------------------------------------------------

def test_two_robots_in_one_world_move_independently(make_sim: Any) -> None:
    sim = make_sim("warehouse")
    assert set(sim.robots) == {"emili1", "kobuki1"}
    emili, kobuki = sim.emili("emili1"), sim.kobuki("kobuki1")
    assert isinstance(emili, Emili) and isinstance(kobuki, Kobuki)
    start_k = kobuki.pose()
    drive(sim, emili, 0.5, 0.0, 2.0)
    assert emili.pose().x_m - 3.0 == pytest.approx(1.0, abs=0.06)
    assert kobuki.pose().x_m == pytest.approx(start_k.x_m, abs=0.005)
    with pytest.raises(UnknownRobot, match="registered: 'emili1', 'kobuki1'"):
        sim.robot("husky1")
    with pytest.raises(UnknownRobot, match="registered: 'emili1'$"):
        sim.emili("kobuki1")


def test_the_thread_steps_at_the_real_time_factor_and_is_joined_at_stop(
        make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(2, 5)), real_time_factor=2.0)
    ticks: list[float] = []
    sim.on_step(ticks.append, rate_hz=48.0)
    t0 = time.monotonic()
    sim.start()
    assert sim.state is SimState.RUNNING
    with pytest.raises(SimulationError, match="cannot step by hand"):
        sim.step()
    # The thread steps on its own (how fast, a loaded machine decides: no wall-time bound).
    assert wait_until(lambda: sim.time_s > 0.3)
    emili = sim.emili("emili1")
    emili.set_cmd_vel(0.5, 0.0)  # from this thread while the sim thread steps
    assert wait_until(lambda: emili.odometry().linear_mps > 0.3)
    sim.stop()
    wall_s = time.monotonic() - t0
    assert sim.state is SimState.IDLE
    assert not [t for t in threading.enumerate() if t.name == "beehave-sim"]
    # 2x real time at most: it never outruns the factor (a loaded machine only slows it).
    assert sim.time_s <= 2.0 * wall_s + 0.05, (sim.time_s, wall_s)
    assert 0.3 < ticks[-1] <= sim.time_s
    steps = [round(t * 240) for t in ticks]
    assert all(b - a == 5 for a, b in zip(steps, steps[1:], strict=False))
    sim.step(10)  # stepping by hand works again once stopped


def test_as_fast_as_possible_outruns_real_time(make_sim: Any) -> None:
    with Simulation(arena(emili_at(2, 5)), real_time_factor=None) as sim:
        assert sim.state is SimState.RUNNING
        assert wait_until(lambda: sim.time_s >= 2.0)
        assert sim.measured_real_time_factor() > 1.0
        height = sim.call(lambda c: c.getNumBodies())
        assert height > 1
    assert sim.state is SimState.CLOSED
    with pytest.raises(SimulationError, match="closed"):
        sim.start()


def test_a_failing_callback_stops_the_thread_and_surfaces_at_stop(make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(2, 5)))

    def explode(time_s: float) -> None:
        if time_s > 0.1:
            raise RuntimeError("publisher gone")

    sim.on_step(explode)
    sim.start()
    assert wait_until(lambda: sim.state is SimState.FAILED)
    with pytest.raises(SimulationError, match="publisher gone") as caught:
        sim.stop()
    assert isinstance(caught.value.__cause__, RuntimeError)
    assert sim.state is SimState.IDLE


def test_on_step_callbacks_can_be_removed(make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(2, 5)))
    seen: list[float] = []
    remove = sim.on_step(seen.append)
    sim.step(3)
    remove()
    sim.step(3)
    assert seen == pytest.approx([1 / 240, 2 / 240, 3 / 240])


def test_a_gate_holds_the_thread_serves_calls_meanwhile_and_stop_ends_it(
        make_sim: Any) -> None:
    sim = make_sim(arena(emili_at(2, 5)))
    hold_at = threading.Event()
    asked: list[float] = []

    def gate(time_s: float) -> bool:
        asked.append(time_s)
        return hold_at.is_set() and time_s >= 0.5

    hold_at.set()
    sim.set_gate(gate)
    sim.start()
    assert wait_until(lambda: sim.time_s >= 0.5)
    held = sim.steps
    assert sim.call(lambda client: sim.steps) == held  # served while holding
    assert wait_until(lambda: len(asked) > 3)  # the gate is asked again
    assert sim.steps == held and sim.time_s < 0.5 + 2 * sim.step_s
    hold_at.clear()
    sim.wake()
    assert wait_until(lambda: sim.time_s > 1.0)
    hold_at.set()
    sim.set_gate(lambda time_s: True)  # hold for good: stop() must still end the thread
    sim.stop()
    assert sim.state is SimState.IDLE
