"""The EMILI and Kobuki HALs against a running simulation over real DDS.

One simulation for the module (EMILI and Kobuki, faster than real time) with its sim node
and a low-level node per robot namespace. Every HAL keeps the HAL contract
(:class:`SimHALContract` gives the contract a ROS node and waits for the first messages
instead of a few loop turns), then the tests check the values and the way back to the sim.
"""

from __future__ import annotations

import asyncio
import importlib.metadata
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("pybullet")

from hal_contract import HALContract  # noqa: E402
from rclpy.node import Node  # noqa: E402

import hal.emili as emili_hals  # noqa: E402
import hal.kobuki as kobuki_hals  # noqa: E402
from beehave import Logic, LowLevelBehaviorManager  # noqa: E402
from beehave.hal import ENTRY_POINT_GROUP, HAL, HALManager  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, beehave_threads, wait_until  # noqa: E402
from robots.errors import CommandOutOfRange  # noqa: E402
from robots.kobuki import LED_COLORS, Kobuki  # noqa: E402
from robots.node import SimNode  # noqa: E402
from robots.sim import Simulation  # noqa: E402
from robots.world import world_from_dict  # noqa: E402

# One pytest-xdist worker runs this module: its module-scoped rig is built once.
pytestmark = pytest.mark.xdist_group("test_robot_hals")

T = TypeVar("T")
EMILI = f"hal_emili_{os.getpid()}"
KOBUKI = f"hal_kobuki_{os.getpid()}"
# A negative check (no wake-up while standing still) runs to its end: short on purpose; a
# loaded machine can only make it see fewer messages, never fail a right HAL.
STILL_S = 0.3


@dataclass
class Rig:
    sim: Simulation
    sim_node: SimNode
    ros: RosContext
    nodes: dict[str, Node]  # the low level's node per robot kind


@pytest.fixture(scope="module")
def rig() -> Iterator[Rig]:
    """EMILI at (6, 5) facing +x: a wall's face 2 m ahead (x = 8), another 1.5 m to its
    left (y = 6.5, from x = 5 on), nothing behind. The Kobuki at (7, 1) facing the first
    wall, 0.825 m from its bumper."""
    before = set(beehave_threads())
    world = world_from_dict({
        "name": "hal_arena", "floor": {"size_m": [10, 10]},
        "walls": [{"from_m": [8.1, 0], "to_m": [8.1, 10], "thickness_m": 0.2},
                  {"from_m": [5, 6.6], "to_m": [10, 6.6], "thickness_m": 0.2}],
        "robots": [{"namespace": EMILI, "kind": "emili", "start": {"x_m": 6, "y_m": 5}},
                   {"namespace": KOBUKI, "kind": "kobuki", "start": {"x_m": 7, "y_m": 1}}]})
    sim = Simulation(world, real_time_factor=4.0)
    ros = RosContext()
    sim_node = SimNode(sim, ros)
    nodes = {"emili": ros.create_node("beehave_low_level", namespace=EMILI),
             "kobuki": ros.create_node("beehave_low_level", namespace=KOBUKI)}
    ros.start()
    sim.start()
    try:
        yield Rig(sim, sim_node, ros, nodes)
    finally:
        sim.stop()
        sim_node.destroy()
        ros.shutdown()
        sim.close()
    leaked = [t.name for t in beehave_threads() if t not in before]
    assert not leaked, f"threads left after teardown: {leaked}"


class SimHALContract(HALContract):
    """The HAL contract for a ROS-backed HAL of ``robot`` ("emili" or "kobuki")."""

    robot: ClassVar[str] = "emili"
    settle_timeout_s: ClassVar[float] = WALL_TIMEOUT_S

    @pytest.fixture(autouse=True)
    def _rig(self, rig: Rig) -> None:
        self.rig = rig

    def configure(self, manager: HALManager) -> None:
        manager.node = self.rig.nodes[self.robot]  # the low level's ROS node, for the HAL
        self.manager = manager

    async def settle(self, turns: int = 20) -> None:  # type: ignore[override]
        """Wait until every expected key holds a fresh value: messages need DDS, not just a
        few loop turns."""
        board = self.manager.blackboard
        deadline = time.monotonic() + self.settle_timeout_s
        while any(board.is_stale(k) for k in self.expected_keys):
            assert time.monotonic() < deadline, (
                f"HAL {self.hal_cls.name!r}: no fresh "
                f"{[k for k in self.expected_keys if board.is_stale(k)]} after "
                f"{self.settle_timeout_s} s")
            await asyncio.sleep(0.005)
        await HALContract.settle(turns)

    def test_found_through_its_entry_point(self) -> None:
        names = {ep.name for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
        if self.hal_cls.name not in names:
            pytest.skip(f"{self.hal_cls.name!r} is not in the {ENTRY_POINT_GROUP!r} entry "
                        "points yet (pyproject.toml)")
        self.entry_point = self.hal_cls.name  # type: ignore[misc]
        super().test_found_through_its_entry_point()


# ---- the contract, per HAL ----------------------------------------------------------------

class TestOdometryHAL(SimHALContract):
    hal_cls = emili_hals.OdometryHAL
    expected_keys = ("odom/x_m", "odom/y_m", "odom/yaw_rad", "odom/linear_mps",
                     "odom/angular_rps")


class TestKobukiOdometry(SimHALContract):
    hal_cls = kobuki_hals.OdometryHAL
    robot = "kobuki"
    expected_keys = ("odom/x_m", "odom/y_m", "odom/yaw_rad")


class TestBatteryHAL(SimHALContract):
    hal_cls = emili_hals.BatteryHAL
    expected_keys = ("battery/percentage", "battery/charging", "battery/voltage_v")


class TestLaserHAL(SimHALContract):
    hal_cls = emili_hals.LaserHAL
    expected_keys = ("laser/front_m", "laser/left_m", "laser/back_m", "laser/right_m")


class TestLineSensorHAL(SimHALContract):
    hal_cls = emili_hals.LineSensorHAL
    expected_keys = ("line/offset_m", "line/visible")


class TestLiftHAL(SimHALContract):
    hal_cls = emili_hals.LiftHAL
    expected_keys = ("lift/height_m",)


class TestEmiliLedsHAL(SimHALContract):
    hal_cls = emili_hals.EmiliLedsHAL
    expected_keys = ("leds/color",)


class TestDisplayHAL(SimHALContract):
    hal_cls = emili_hals.DisplayHAL
    expected_keys = ("display/text",)


class TestSoundHAL(SimHALContract):
    hal_cls = emili_hals.SoundHAL


class TestKobukiBumpersHAL(SimHALContract):
    hal_cls = kobuki_hals.KobukiBumpersHAL
    robot = "kobuki"
    expected_keys = ("bumper/left", "bumper/center", "bumper/right")


class TestKobukiCliffsHAL(SimHALContract):
    hal_cls = kobuki_hals.KobukiCliffsHAL
    robot = "kobuki"
    expected_keys = ("cliff/left", "cliff/center", "cliff/right", "wheel_drop/left",
                     "wheel_drop/right")


class TestKobukiButtonsHAL(SimHALContract):
    hal_cls = kobuki_hals.KobukiButtonsHAL
    robot = "kobuki"
    expected_keys = ("button/0", "button/1", "button/2")


class TestKobukiLedsHAL(SimHALContract):
    hal_cls = kobuki_hals.KobukiLedsHAL
    robot = "kobuki"


class TestKobukiSoundHAL(SimHALContract):
    hal_cls = kobuki_hals.KobukiSoundHAL
    robot = "kobuki"


# ---- values and outputs, through a running low level ----------------------------------------

ALL_HALS: list[type[HAL]] = [
    emili_hals.OdometryHAL, emili_hals.BatteryHAL, emili_hals.LaserHAL,
    emili_hals.LineSensorHAL, emili_hals.LiftHAL, emili_hals.EmiliLedsHAL,
    emili_hals.DisplayHAL, emili_hals.SoundHAL, kobuki_hals.KobukiBumpersHAL,
    kobuki_hals.KobukiCliffsHAL, kobuki_hals.KobukiButtonsHAL, kobuki_hals.KobukiLedsHAL,
    kobuki_hals.KobukiSoundHAL]


@pytest.fixture
def low_level(rig: Rig) -> Iterator[Callable[[str], LowLevelBehaviorManager]]:
    """A running low level per robot kind (node set, every HAL registered); shut down at
    the end of the test."""
    managers: list[LowLevelBehaviorManager] = []

    def make(robot: str) -> LowLevelBehaviorManager:
        ll = LowLevelBehaviorManager(stop_timeout_s=1.0)
        ll.hals.node = rig.nodes[robot]
        for cls in ALL_HALS:
            ll.hals.register(cls)
        ll.__enter__()
        managers.append(ll)
        return ll

    yield make
    for ll in managers:
        ll.shutdown()


def load(ll: LowLevelBehaviorManager, name: str, cls: type[T]) -> T:
    hal = ll.call(ll.hals.load(name), timeout_s=WALL_TIMEOUT_S)
    assert isinstance(hal, cls)
    return hal


def fresh(ll: LowLevelBehaviorManager, key: str, predicate: Callable[[Any], bool] = bool,
          timeout_s: float = WALL_TIMEOUT_S) -> Any:
    """Wait for a fresh value of ``key`` that satisfies ``predicate``; return it."""
    assert wait_until(lambda: not ll.blackboard.is_stale(key)
                      and predicate(ll.blackboard.get(key)), timeout_s), \
        f"{key} = {ll.blackboard.get(key)!r} (stale: {ll.blackboard.is_stale(key)})"
    return ll.blackboard.get(key)


def test_laser_sectors_when_facing_a_wall(low_level: Callable[[str], LowLevelBehaviorManager]
                                          ) -> None:
    ll = low_level("emili")
    load(ll, "laser", emili_hals.LaserHAL)
    fresh(ll, "laser/front_m", lambda v: v is not None)
    values = {s: ll.blackboard.get(f"laser/{s}_m") for s in ("front", "left", "back", "right")}
    assert values["front"] == pytest.approx(2.0, abs=0.02)  # the wall straight ahead
    assert values["left"] == pytest.approx(1.5, abs=0.02)   # the wall on the left
    assert math.isinf(values["back"])                      # nothing behind
    # Right: the first wall seen by the beam at -46°, the nearest one in that sector.
    assert values["right"] == pytest.approx(2.0 / math.cos(math.radians(46)), abs=0.03)


def test_odometry_battery_and_line_values(low_level: Callable[[str], LowLevelBehaviorManager],
                                          rig: Rig) -> None:
    ll = low_level("emili")
    for name in ("odometry", "battery", "line_sensor"):
        ll.call(ll.hals.load(name), timeout_s=WALL_TIMEOUT_S)
    assert fresh(ll, "odom/x_m", lambda v: v is not None) == pytest.approx(6.0, abs=0.02)
    assert ll.blackboard.get("odom/y_m") == pytest.approx(5.0, abs=0.02)
    assert ll.blackboard.get("odom/yaw_rad") == pytest.approx(0.0, abs=0.01)
    assert ll.blackboard.entry("odom/x_m").writer == "hal:odometry"  # type: ignore[union-attr]
    truth = rig.sim.robot(EMILI).battery()
    percentage = fresh(ll, "battery/percentage", lambda v: v is not None)
    assert percentage == pytest.approx(truth.percentage, abs=1.0)
    assert ll.blackboard.get("battery/charging") is False
    assert ll.blackboard.get("battery/voltage_v") == pytest.approx(truth.voltage_v, abs=0.1)
    assert fresh(ll, "line/visible", lambda v: v is False) is False
    assert ll.blackboard.get("line/offset_m") is None


def test_odometry_deadband_wakes_only_for_relevant_moves(
        low_level: Callable[[str], LowLevelBehaviorManager], rig: Rig) -> None:
    ll = low_level("kobuki")
    load(ll, "odometry", emili_hals.OdometryHAL)
    fresh(ll, "odom/x_m", lambda v: v is not None)
    seen: list[float] = []
    ll.call(_subscribe(ll, "odom/x_m", seen))
    time.sleep(STILL_S)  # ~1 s of sim time standing still: ~50 messages, no relevant change
    assert len(seen) <= 1
    kobuki = rig.sim.kobuki(KOBUKI)
    start = len(seen)
    deadline = time.monotonic() + WALL_TIMEOUT_S
    while kobuki.pose().x_m < 7.3 and time.monotonic() < deadline:
        kobuki.set_cmd_vel(0.3, 0.0)
        time.sleep(0.02)
    kobuki.stop()
    moved = seen[start:]
    # Each wake-up is at least the deadband away from the previous one.
    assert moved and all(b - a >= 0.01 for a, b in zip(moved, moved[1:], strict=False))
    assert len(moved) <= 0.3 / 0.01 + 2


async def _subscribe(ll: LowLevelBehaviorManager, key: str, seen: list[float]) -> None:
    ll.blackboard.subscribe(key, lambda change: seen.append(change.value))


def test_lift_set_height_reaches_the_sim(low_level: Callable[[str], LowLevelBehaviorManager],
                                         rig: Rig) -> None:
    ll = low_level("emili")
    lift = load(ll, "lift", emili_hals.LiftHAL)
    fresh(ll, "lift/height_m", lambda v: v is not None)
    lift.set_height(0.1)
    assert fresh(ll, "lift/height_m", lambda v: abs(v - 0.1) < 0.005) == pytest.approx(
        0.1, abs=0.005)
    assert rig.sim.emili(EMILI).lift_target() == 0.1
    with pytest.raises(CommandOutOfRange, match=r"HAL 'lift': lift height 0.5 m is out of "
                                                r"range 0–0.3 m"):
        lift.set_height(0.5)
    lift.set_height(0.0)


def test_emili_leds_display_and_sound_reach_the_sim(
        low_level: Callable[[str], LowLevelBehaviorManager], rig: Rig) -> None:
    ll = low_level("emili")
    emili = rig.sim.emili(EMILI)
    leds = load(ll, "emili_leds", emili_hals.EmiliLedsHAL)
    display = load(ll, "display", emili_hals.DisplayHAL)
    sound = load(ll, "sound", emili_hals.SoundHAL)
    leds.set_color(0.0, 0.5, 1.0)
    display.show("to dock")
    sound.play("chime")
    assert wait_until(lambda: emili.leds() == (0.0, 0.5, 1.0))
    assert wait_until(lambda: emili.display() == "to dock")
    assert wait_until(lambda: any(s.name == "chime" for s in emili.sounds()))
    # The state comes back from the robot onto the blackboard.
    assert fresh(ll, "leds/color", lambda v: v == (0.0, 0.5, 1.0))
    assert fresh(ll, "display/text", lambda v: v == "to dock")
    with pytest.raises(CommandOutOfRange, match=r"each channel must be 0–1"):
        leds.set_color(1.5, 0.0, 0.0)
    # Unloading the LED HAL runs its safe state: the strip goes dark.
    ll.call(ll.hals.release("emili_leds"))
    assert wait_until(lambda: emili.leds() == (0.0, 0.0, 0.0))
    display.show("")


def test_kobuki_leds_and_sound_reach_the_sim_and_bad_names_raise(
        low_level: Callable[[str], LowLevelBehaviorManager], rig: Rig) -> None:
    ll = low_level("kobuki")
    kobuki = rig.sim.kobuki(KOBUKI)
    leds = load(ll, "kobuki_leds", kobuki_hals.KobukiLedsHAL)
    sound = load(ll, "kobuki_sound", kobuki_hals.KobukiSoundHAL)
    assert wait_until(lambda: leds.node.count_subscribers(f"/{KOBUKI}/leds/led2") == 1)
    leds.set("orange", "green")
    sound.play("cleaning_end")
    assert wait_until(lambda: kobuki.leds() == ("orange", "green"))
    assert wait_until(lambda: any(s.name == "cleaning_end" for s in kobuki.sounds()))
    with pytest.raises(CommandOutOfRange) as err:
        leds.set("green", "purple")
    assert str(err.value) == ("HAL 'kobuki_leds': unknown LED2 colour 'purple'; valid: off, "
                              "green, orange, red")
    with pytest.raises(CommandOutOfRange, match=r"unknown sound 'beep'; valid: on, off, "):
        sound.play("beep")
    assert kobuki.leds() == ("orange", "green")  # nothing was sent
    assert kobuki_hals.LED_COLORS == LED_COLORS and kobuki_hals.SOUNDS == Kobuki.sound_names
    ll.call(ll.hals.release("kobuki_leds"))  # safe state: both off
    assert wait_until(lambda: kobuki.leds() == ("off", "off"))


class BumpLeds(Logic):
    """Red LED1 while the centre bumper is pressed, green otherwise."""

    async def run(self) -> Any:
        leds = await self.hal("kobuki_leds", kobuki_hals.KobukiLedsHAL)
        await self.hal("kobuki_bumpers")
        async for change in self.blackboard.watch("bumper/center"):
            if not change.stale:
                leds.set("red" if change.value else "green", "off")


def test_a_logic_reacts_to_the_bumper_of_the_simulated_kobuki(rig: Rig) -> None:
    kobuki = rig.sim.kobuki(KOBUKI)
    ll = LowLevelBehaviorManager(default="bump_leds", stop_timeout_s=1.0)
    ll.hals.node = rig.nodes["kobuki"]
    for cls in ALL_HALS:
        ll.hals.register(cls)
    ll.register("bump_leds", BumpLeds)
    with ll:
        assert wait_until(lambda: kobuki.leds()[0] == "green")
        deadline = time.monotonic() + WALL_TIMEOUT_S
        while not kobuki.bumpers().center and time.monotonic() < deadline:
            kobuki.set_cmd_vel(0.3, 0.0)
            time.sleep(0.02)
        assert fresh(ll, "bumper/center", lambda v: v is True)
        assert wait_until(lambda: kobuki.leds()[0] == "red")
        # Back off: the bumper releases, the LED turns green again.
        deadline = time.monotonic() + WALL_TIMEOUT_S
        while kobuki.bumpers().center and time.monotonic() < deadline:
            kobuki.set_cmd_vel(-0.2, 0.0)
            time.sleep(0.02)
        kobuki.stop()
        assert wait_until(lambda: kobuki.leds()[0] == "green")
    assert wait_until(lambda: kobuki.leds() == ("off", "off"))  # the HAL's safe state


def test_unload_destroys_the_hals_ros_entities(
        low_level: Callable[[str], LowLevelBehaviorManager], rig: Rig) -> None:
    ll = low_level("emili")
    node = rig.nodes["emili"]
    subs, pubs = len(list(node.subscriptions)), len(list(node.publishers))
    for name in ("lift", "emili_leds", "display", "laser"):
        ll.call(ll.hals.load(name), timeout_s=WALL_TIMEOUT_S)
    assert len(list(node.subscriptions)) == subs + 4
    assert len(list(node.publishers)) == pubs + 3
    sim_side = rig.sim_node.ports[EMILI].node
    assert wait_until(lambda: sim_side.count_subscribers(f"/{EMILI}/scan") == 1)
    for name in ("lift", "emili_leds", "display", "laser"):
        ll.call(ll.hals.release(name))
    assert len(list(node.subscriptions)) == subs
    assert len(list(node.publishers)) == pubs
    assert wait_until(lambda: sim_side.count_subscribers(f"/{EMILI}/scan") == 0)
