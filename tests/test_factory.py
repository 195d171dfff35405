"""The factory world and its physics (robots/factory.py): machines consume, robots load at
the depot and deliver to machines, charging stations and speed zones are measured — in
pybullet, stepped by hand (no ROS) — then /factory/state over real DDS, the factory HAL,
and `beehave sim factory` writing its report and picture on SIGINT.
"""

from __future__ import annotations

import asyncio
import importlib.metadata
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import pytest

pytest.importorskip("pybullet")

from beehave.planning import GridPlanner  # noqa: E402
from robots.errors import UnknownMachine, WorldError  # noqa: E402
from robots.factory import REPORT_SCHEMA, STATE_SCHEMA, Delivery, Factory, Pickup  # noqa: E402
from robots.robot import SimRobot  # noqa: E402
from robots.sim import Simulation  # noqa: E402
from robots.world import World, load_world, occupancy_map, world_from_dict  # noqa: E402

# One pytest-xdist worker runs this module: its module-scoped rig is built once.
pytestmark = pytest.mark.xdist_group("test_factory")

ROOT = Path(__file__).resolve().parent.parent


def shop(**changes: Any) -> dict[str, Any]:
    """An 8 x 6 m shop: a depot on the left, machine m1 on the right with its delivery
    area in front of it, a slow zone between them, one Kobuki in the depot facing the
    machine."""
    world: dict[str, Any] = {
        "name": "shop", "floor": {"size_m": [8, 6]},
        "depots": [{"name": "depot", "area": {"center_m": [1.5, 3.0], "size_m": [1.0, 1.0]},
                    "load_amount": 30, "load_s": 1.0}],
        "machines": [{"name": "m1", "center_m": [6.8, 3.0], "size_m": [1.0, 1.0],
                      "capacity": 100, "initial_level": 50, "consumption_per_s": 0.5,
                      "unload_s": 1.0,
                      "delivery": {"center_m": [5.8, 3.0], "size_m": [0.6, 0.6]}}],
        "zones": [{"name": "slow", "max_speed_mps": 0.15,
                   "points_m": [[2.5, 0], [3.5, 0], [3.5, 6], [2.5, 6]]}],
        "robots": [{"namespace": "k1", "kind": "kobuki",
                    "start": {"x_m": 1.5, "y_m": 3.0, "yaw_deg": 0}}],
    }
    world.update(changes)
    return world


def drive_along_x(sim: Simulation, robot: SimRobot, to_x_m: float, *,
                  speed_mps: float = 0.4, slow: tuple[float, float, float] | None = None
                  ) -> None:
    """Drive ``robot`` straight along +x to ``to_x_m`` (commands at 20 Hz of sim time,
    stepping by hand), at ``speed_mps`` — or at ``slow[2]`` between x = slow[0] and slow[1]
    (slowing down before it gets there) — then stop and settle."""
    for _ in range(2000):
        x = robot.pose().x_m
        if x >= to_x_m - 0.02:
            break
        v = speed_mps
        if slow is not None and slow[0] - 0.4 <= x <= slow[1]:
            v = slow[2]
        robot.set_cmd_vel(min(v, max(0.05, to_x_m - x)), 0.0)
        sim.run_for(0.05)
    robot.stop()
    sim.run_for(0.3)


@pytest.fixture
def sim_of() -> Iterator[Any]:
    sims: list[Simulation] = []

    def make(data: dict[str, Any]) -> tuple[Simulation, Factory]:
        sim = Simulation(world_from_dict(data), real_time_factor=None)
        sims.append(sim)
        for robot in sim.robots.values():
            robot.scan_enabled = False  # no test here looks: the lasers would cost half
        return sim, Factory(sim)

    yield make
    for sim in sims:
        sim.close()


# ---- the world ------------------------------------------------------------------------

def problems_of(data: dict[str, Any]) -> str:
    with pytest.raises(WorldError) as caught:
        world_from_dict(data, source="shop.yaml")
    return str(caught.value)


def machine(**changes: Any) -> dict[str, Any]:
    m = dict(shop()["machines"][0])
    m.update(changes)
    return m


@pytest.mark.parametrize(("data", "expected"), [
    (shop(machines=[machine(initial_level=120)]),
     r"machines\.0: initial_level 120(\.0)? exceeds capacity 100"),
    (shop(machines=[machine(delivery={"center_m": [6.5, 3.0]})]),
     r"machines\.0: delivery area at \(6\.5, 3\.0\) overlaps the machine's body"),
    (shop(machines=[machine(consumption_per_s=-1)]),
     r"machines\.0\.consumption_per_s: .*greater than or equal to 0"),
    (shop(machines=[machine(center_m=[7.8, 3.0])]),
     r"machines\.0 \('m1'\): the machine reaches off the floor \(0\.\.8 x 0\.\.6 m\)"),
    (shop(machines=[machine(), machine()]), r"machines: duplicate names \['m1'\]"),
    (shop(machines=[machine(delivery={"centre_m": [5.8, 3.0]})]),
     r"machines\.0\.delivery\.centre_m: unknown key"),
    (shop(zones=[{"name": "z", "max_speed_mps": 0.2, "points_m": [[0, 0], [1, 1]]}]),
     r"zones\.0\.points_m: .*at least 3"),
    (shop(zones=[{"name": "z", "max_speed_mps": 0.2,
                  "points_m": [[0, 0], [1, 1], [2, 2]]}]), r"zones\.0: .*enclose no area"),
    (shop(zones=[{"name": "z", "max_speed_mps": 0,
                  "points_m": [[0, 0], [1, 0], [1, 1]]}]),
     r"zones\.0\.max_speed_mps: .*greater than 0"),
    (shop(zones=[{"name": "z", "max_speed_mps": 0.2,
                  "points_m": [[0, 0], [9, 0], [9, 1]]}]),
     r"zones\.0\.points_m \('z'\): a corner lies off the floor"),
    (shop(depots=[{"name": "d", "area": {"center_m": [0.2, 3.0]}}]),
     r"depots\.0\.area \('d'\): reaches off the floor"),
    (shop(depots=[{"name": "d", "area": {"center_m": [6.8, 3.0]}}]),
     r"depots\.0\.area \('d'\): overlaps machine 'm1'"),
    (shop(machines=[machine(), machine(name="m2", center_m=[5.8, 3.6],
                                   delivery={"center_m": [5.8, 4.8]})]),
     r"machines\.0\.delivery \('m1'\): the delivery area overlaps machine 'm2'"),
])
def test_bad_factory_parts_are_named_with_their_key_path(data: dict[str, Any],
                                                         expected: str) -> None:
    message = problems_of(data)
    assert "shop.yaml" in message
    import re
    assert re.search(expected, message), message


def test_the_factory_world_has_what_the_fleet_needs_and_stays_plannable() -> None:
    world = load_world("factory")
    assert world.floor.size_m == (24, 16)
    assert len(world.machines) >= 4 and len(world.depots) >= 1
    chargers = world.stations_of_kind("charging")
    assert len(chargers) == 3
    assert all(r.charging_station is None for r in world.robots)  # tied to no robot
    assert 2 <= len(world.zones) <= 3
    assert [r.namespace for r in world.robots] == [f"atv{i}" for i in range(1, 11)]
    assert {r.kind for r in world.robots} == {"kobuki"}
    passage = world.zone("passage")
    assert world.zone_at(18.5, 8.0) == passage and passage.max_speed_mps == 0.15
    assert world.zone_at(3.0, 1.0) is None
    # The map a Kobuki plans on: machines block, their delivery areas do not.
    planner = GridPlanner(occupancy_map(world), robot_radius_m=0.18, clearance_m=0.1)
    m = world.machines[0]
    assert not planner.is_free(m.center_m)
    assert planner.is_free(m.delivery.center_m)
    goals = [world.depots[0].area.center_m, *(m.delivery.center_m for m in world.machines),
             *(s.center_m for s in chargers)]
    for robot in world.robots[::3]:
        for goal in goals:
            assert planner.plan((robot.start.x_m, robot.start.y_m), goal).length_m > 0


def test_with_robots_keeps_the_first_n_and_refuses_more_than_there_are() -> None:
    world = load_world("factory")
    assert [r.namespace for r in world.with_robots(3).robots] == ["atv1", "atv2", "atv3"]
    with pytest.raises(WorldError, match=r"asked for 11 robot\(s\); this world starts 0 to 10"):
        world.with_robots(11)
    with pytest.raises(UnknownMachine, match=r"unknown machine 'oven'; registered: .*'mill'"):
        world.machine("oven")


def test_where_zones_overlap_the_stricter_one_holds() -> None:
    world: World = world_from_dict(shop(zones=[
        {"name": "hall", "max_speed_mps": 0.25, "points_m": [[0, 0], [8, 0], [8, 6], [0, 6]]},
        {"name": "door", "max_speed_mps": 0.1, "points_m": [[3, 2], [4, 2], [4, 4], [3, 4]]}]))
    assert world.zone_at(3.5, 3.0).name == "door"  # type: ignore[union-attr]
    assert world.zone_at(6.0, 1.0).name == "hall"  # type: ignore[union-attr]


# ---- the physics ------------------------------------------------------------------------

def test_a_machine_level_falls_at_its_rate_and_its_empty_time_is_counted(sim_of: Any) -> None:
    sim, factory = sim_of(shop(machines=[machine(initial_level=10, consumption_per_s=0.5)],
                               robots=[]))
    sim.run_for(10.0)
    m = factory.facts().machine("m1")
    assert m.level == pytest.approx(5.0, abs=1e-6)
    assert m.empty_s == 0.0 and m.first_empty_at_s is None
    sim.run_for(20.0)
    m = factory.facts().machine("m1")
    assert m.level == 0.0 and m.min_level == 0.0  # never below 0
    assert m.first_empty_at_s == pytest.approx(20.0, abs=1e-6)
    assert m.empty_s == pytest.approx(10.0, abs=1e-6)
    assert any("machine m1 ran empty at 20.0 s" in p for p in factory.facts().problems())


def test_a_kobuki_loads_at_the_depot_and_delivers_to_the_machine(sim_of: Any) -> None:
    sim, factory = sim_of(shop())
    events: list[Any] = []
    factory.on_event(events.append)
    k1 = sim.robot("k1")
    sim.run_for(0.5)
    assert factory.loads() == {}  # still, but not yet for load_s
    sim.run_for(0.8)
    assert factory.loads() == {"k1": 30.0}
    assert isinstance(events[0], Pickup) and events[0].robot == "k1"
    sim.run_for(2.0)
    assert len(factory.facts().pickups) == 1  # one load at a time

    # Through the slow zone at 0.12 m/s, elsewhere at 0.4 m/s, into the delivery area.
    drive_along_x(sim, k1, 5.8, slow=(2.5, 3.5, 0.12))
    before = factory.levels()["m1"]
    sim.run_for(1.2)
    facts = factory.facts()
    (delivery,) = facts.deliveries
    assert (delivery.machine, delivery.robot, delivery.amount) == ("m1", "k1", 30.0)
    assert isinstance(events[-1], Delivery)
    assert facts.machine("m1").level == pytest.approx(before + 30.0, abs=1.0)
    assert facts.machine("m1").received == 30.0 and facts.robot("k1").deliveries == 1
    assert factory.loads() == {}
    # Driving within the limit is no violation, although the robot slowed down from 0.4.
    assert 0.5 < facts.zone("slow").max_ratio <= 1.0, facts.zone("slow")
    assert facts.problems() == []


def test_passing_through_the_depot_without_stopping_loads_nothing(sim_of: Any) -> None:
    sim, factory = sim_of(shop(robots=[{"namespace": "k1", "kind": "kobuki",
                                        "start": {"x_m": 0.5, "y_m": 3.0}}]))
    drive_along_x(sim, sim.robot("k1"), 2.4, speed_mps=0.3)
    assert factory.facts().pickups == ()


def test_a_delivery_is_capped_at_the_machine_capacity(sim_of: Any) -> None:
    sim, factory = sim_of(shop(
        machines=[machine(initial_level=90, consumption_per_s=0.0)],
        depots=[{"name": "depot", "area": {"center_m": [5.8, 3.0], "size_m": [0.6, 0.6]},
                 "load_amount": 30, "load_s": 0.5}],
        robots=[{"namespace": "k1", "kind": "kobuki", "start": {"x_m": 5.8, "y_m": 3.0}}]))
    sim.run_for(0.7)   # loads (the depot is the delivery area here) …
    sim.run_for(1.2)   # … and unloads, standing still
    (delivery,) = factory.facts().deliveries
    assert delivery.amount == pytest.approx(10.0) and delivery.level_after == 100.0


def test_two_robots_in_one_charging_station_are_counted(sim_of: Any) -> None:
    sim, factory = sim_of(shop(
        stations=[{"name": "big", "kind": "charging", "center_m": [2, 2], "size_m": [1, 1]},
                  {"name": "small", "kind": "charging", "center_m": [6, 5],
                   "size_m": [0.7, 0.7]}],
        robots=[{"namespace": "k1", "kind": "kobuki", "start": {"x_m": 1.75, "y_m": 2}},
                {"namespace": "k2", "kind": "kobuki", "start": {"x_m": 2.25, "y_m": 2}},
                {"namespace": "k3", "kind": "kobuki", "start": {"x_m": 6, "y_m": 5}}]))
    sim.run_for(0.5)
    facts = factory.facts()
    big, small = facts.station("big"), facts.station("small")
    assert (big.max_charging, big.max_charging_robots) == (2, ("k1", "k2"))
    assert (small.max_charging, small.occupants) == (1, ("k3",))
    assert all(sim.robot(ns).battery().charging for ns in ("k1", "k2", "k3"))
    assert facts.robot("k2").charging_at == "big"
    assert [p for p in facts.problems() if "station" in p] == [
        f"station big: 2 robots charged at once (k1, k2 at {big.max_charging_at_s:.1f} s)"]


def test_speeding_in_a_zone_is_measured_over_the_limit(sim_of: Any) -> None:
    sim, factory = sim_of(shop(robots=[{"namespace": "k1", "kind": "kobuki",
                                        "start": {"x_m": 1.0, "y_m": 1.0}}]))
    drive_along_x(sim, sim.robot("k1"), 5.0, speed_mps=0.3)
    zone = factory.facts().zone("slow")
    assert zone.max_ratio > 1.05 and zone.max_ratio_robot == "k1"
    assert zone.max_measured_mps == pytest.approx(0.3, abs=0.03)
    assert any(p.startswith("zone slow: k1 drove") for p in factory.facts().problems())


def test_a_battery_that_runs_flat_is_measured_at_zero(sim_of: Any) -> None:
    # A Kobuki idles at 5 W: half of a 0.01 Wh battery (18 J) is gone in 3.6 s of sim time.
    sim, factory = sim_of(shop(robots=[{
        "namespace": "k1", "kind": "kobuki", "start": {"x_m": 4.5, "y_m": 1.0},
        "battery": {"capacity_wh": 0.01, "initial_fraction": 0.5}}]))
    sim.run_for(0.2)
    assert factory.facts().robot("k1").min_battery_fraction > 0.0
    assert not [p for p in factory.facts().problems() if "battery" in p]
    sim.run_for(6.0)
    robot = factory.facts().robot("k1")
    assert robot.min_battery_fraction == 0.0 and robot.battery_fraction == 0.0
    assert any(p.startswith("robot k1: battery reached zero at") for p in
               factory.facts().problems())


def test_the_facts_are_plain_json_keyed_by_name(sim_of: Any) -> None:
    sim, factory = sim_of(shop())
    sim.run_for(1.5)
    data = json.loads(json.dumps(factory.facts().as_dict()))
    assert data["machines"]["m1"]["capacity"] == 100
    assert data["robots"]["k1"]["load"] == 30.0
    assert data["pickups"][0]["robot"] == "k1"
    state = json.loads(json.dumps(factory.state()))
    assert state["schema"] == STATE_SCHEMA
    assert state["robots"]["k1"]["zone"] is None and state["robots"]["k1"]["load"] == 30.0
    assert factory.report()["schema"] == REPORT_SCHEMA


def test_the_warehouse_has_no_factory_parts() -> None:
    world = load_world("warehouse")
    assert (world.machines, world.depots, world.zones) == ([], [], [])
    assert world.zone_at(3.0, 2.0) is None


def test_the_picture_shows_levels_zones_and_each_robot(sim_of: Any, tmp_path: Path) -> None:
    from PIL import Image

    sim, factory = sim_of(shop())
    sim.run_for(1.5)
    path = factory.render_topdown(tmp_path / "shop.png")
    image = Image.open(path).convert("RGB")
    assert image.size == (360, 280)  # (8 + 1) x (6 + 1) m at 40 px/m
    # The slow zone is tinted red over the floor; the floor outside it is not.
    zone = image.getpixel((round((3.0 + 0.5) * 40), round((6.5 - 5.5) * 40)))
    floor = image.getpixel((round((6.0 + 0.5) * 40), round((6.5 - 5.5) * 40)))
    assert isinstance(zone, tuple) and isinstance(floor, tuple)
    assert zone[0] > zone[1] + 30 and abs(floor[0] - floor[1]) < 15


def test_a_robot_in_a_station_leaves_the_station_name_readable(tmp_path: Path) -> None:
    """A robot charging at charger1 once had its name drawn over the station's (issue
    24 item 7): its name then goes below it."""
    from PIL import Image, ImageDraw, ImageFont

    from robots.render import PATH_COLORS, RobotSketch, render_topdown

    world = load_world("factory")
    station = next(s for s in world.stations if s.name == "charger1")
    # Where an ATV stops to charge: inside the station, short of its centre.
    at = (station.center_m[0], station.center_m[1] - 0.25)
    sketch = RobotSketch("atv4", "kobuki", *at, math.pi / 2, (), [])
    image = Image.open(render_topdown(world, [sketch], tmp_path / "f.png")).convert("RGB")
    # Where render_topdown writes the station's name (40 px/m, 0.5 m margin, y upwards).
    draw = ImageDraw.Draw(image)
    draw.font = ImageFont.load_default(size=12)
    x = (station.center_m[0] - station.size_m[0] / 2 + 0.5) * 40 + 3
    y = (world.floor.size_m[1] + 0.5 - station.center_m[1] - station.size_m[1] / 2) * 40 + 2
    x0, y0, x1, y1 = draw.textbbox((x, y), station.name)
    label = PATH_COLORS[0]
    covered = [(i, j) for i in range(int(x0), int(x1) + 1) for j in range(int(y0), int(y1) + 1)
               if image.getpixel((i, j)) == label]
    assert not covered, f"atv4's name covers charger1's at {covered[:5]}"
    # ... and it is still written, next to the robot.
    cx, cy = (at[0] + 0.5) * 40, (world.floor.size_m[1] + 0.5 - at[1]) * 40
    near = [(i, j) for i in range(int(cx) - 30, int(cx) + 30)
            for j in range(int(cy) - 40, int(cy) + 40) if image.getpixel((i, j)) == label]
    assert near


def test_a_world_may_give_a_robot_its_idle_draw_and_the_facts_count_distance(
        sim_of: Any) -> None:
    # 0.01 Wh is 36 J: at the Kobuki's own 5 W idle that is 7.2 s, at 0.05 W 720 s.
    sim, factory = sim_of(shop(robots=[{
        "namespace": "k1", "kind": "kobuki", "start": {"x_m": 4.5, "y_m": 1.0},
        "battery": {"capacity_wh": 0.01, "initial_fraction": 1.0, "idle_w": 0.05}}]))
    sim.run_for(3.6)
    robot = factory.facts().robot("k1")
    assert robot.battery_fraction == pytest.approx(1.0 - 3.6 / 720, abs=2e-3)
    assert robot.distance_m == pytest.approx(0.0, abs=0.01) and robot.charging_s == 0.0
    drive_along_x(sim, sim.robot("k1"), 5.5)
    assert factory.facts().robot("k1").distance_m == pytest.approx(1.0, abs=0.1)
    for bad in (-1, math.nan, math.inf, "high"):
        problem = problems_of(shop(robots=[{
            "namespace": "k1", "kind": "kobuki", "start": {"x_m": 4.5, "y_m": 1.0},
            "battery": {"idle_w": bad}}]))
        assert "idle_w" in problem, (bad, problem)
    assert "capacity_wh" in problems_of(shop(robots=[{
        "namespace": "k1", "kind": "kobuki", "start": {"x_m": 4.5, "y_m": 1.0},
        "battery": {"capacity_wh": math.inf}}]))


# ---- ROS 2 ----------------------------------------------------------------------------

def unique(prefix: str) -> str:
    return f"{prefix}_{os.getpid()}_{time.monotonic_ns() % 1_000_000}"


@dataclass
class Rig:
    sim: Simulation
    factory: Factory
    ros: Any
    sim_node: Any
    low_node: Any
    ns: str
    world: str


@pytest.fixture(scope="module")
def rig() -> Iterator[Rig]:
    """One Kobuki standing in the depot of a shop on ROS 2; the simulation is started by
    the first test that uses it (the /factory/state test, which must see the pick-up)."""
    pytest.importorskip("rclpy")
    from beehave.ros.context import RosContext
    from robots.node import SimNode

    ns, name = unique("atv"), unique("shop")
    data = shop(name=name, robots=[{"namespace": ns, "kind": "kobuki",
                                    "start": {"x_m": 1.5, "y_m": 3.0}}])
    sim = Simulation(world_from_dict(data), real_time_factor=2.0)
    factory = Factory(sim)
    ros = RosContext()
    sim_node = SimNode(sim, ros, factory=factory, lockstep=False)
    low_node = ros.create_node("beehave_low_level", namespace=ns)
    ros.start()
    try:
        yield Rig(sim, factory, ros, sim_node, low_node, ns, name)
    finally:
        sim.stop()
        sim_node.destroy()
        ros.shutdown()
        factory.close()
        sim.close()


def test_factory_state_goes_out_latched_periodically_and_on_every_load(rig: Rig) -> None:
    from ros_probe import Probe
    from std_msgs.msg import String

    from robots import topics

    probe = Probe()
    try:
        got = probe.record(String, topics.FACTORY_STATE, latched=True)

        def ours() -> list[dict[str, Any]]:
            decoded = [json.loads(m.data) for m in list(got)]
            return [d for d in decoded if d.get("world") == rig.world]

        assert probe.wait(lambda: bool(ours())), "no latched /factory/state"
        first = ours()[0]
        assert first["schema"] == STATE_SCHEMA
        assert first["machines"]["m1"] == {"level": 50.0, "capacity": 100.0}
        assert first["robots"][rig.ns]["load"] is None
        assert not any(s["facts"]["pickups"] for s in ours())
        rig.sim.start()  # the robot stands in the depot: it loads after load_s (1 s)
        assert probe.wait(lambda: any(s["facts"]["pickups"] for s in ours()))
        pickup = next(s for s in ours() if s["facts"]["pickups"])
        # Published by the pick-up itself, not by the next 5 Hz tick (a 0.2 s multiple).
        assert pickup["time_s"] == pickup["facts"]["pickups"][0]["time_s"]
        assert pickup["robots"][rig.ns]["load"] == 30.0
        assert probe.wait(lambda: ours()[-1]["time_s"] > pickup["time_s"] + 0.5)
        times = [s["time_s"] for s in ours()]
        assert times == sorted(times)
    finally:
        probe.close()


class TestFactoryHAL:
    """The HAL contract for hal.factory against the running rig (hal_contract)."""

    @pytest.fixture(autouse=True)
    def _contract(self, rig: Rig) -> None:
        self.rig = rig
        if rig.sim.state.value != "running":
            rig.sim.start()

    def contract(self) -> Any:
        from hal_contract import HALContract

        from beehave.hal import HALManager
        from hal.factory import FACTORY_KEYS, FactoryHAL

        rig = self.rig

        class Contract(HALContract):
            hal_cls = FactoryHAL
            expected_keys: ClassVar[tuple[str, ...]] = FACTORY_KEYS

            def configure(self, manager: HALManager) -> None:
                manager.node = rig.low_node
                self.manager = manager

            async def settle(self, turns: int = 20) -> None:  # type: ignore[override]
                board = self.manager.blackboard
                deadline = time.monotonic() + 10.0
                while any(board.is_stale(k) for k in self.expected_keys):
                    assert time.monotonic() < deadline, "factory keys never became fresh"
                    await asyncio.sleep(0.01)

        return Contract()

    def test_loads_runs_and_reports_started(self) -> None:
        self.contract().test_loads_runs_and_reports_started()

    def test_publishes_its_keys_fresh_and_as_its_writer(self) -> None:
        self.contract().test_publishes_its_keys_fresh_and_as_its_writer()

    def test_entries_read_as_stale_after_unload(self) -> None:
        self.contract().test_entries_read_as_stale_after_unload()

    def test_can_be_loaded_again_after_unload(self) -> None:
        self.contract().test_can_be_loaded_again_after_unload()

    def test_its_own_robot_load_and_zone(self) -> None:
        contract = self.contract()

        async def body(manager: Any, events: list[Any]) -> dict[str, Any]:
            await manager.load("factory")
            await contract.settle()
            board = manager.blackboard
            # The first state this HAL hears may predate the pick-up the first test saw (a
            # loaded machine delivers the latched one late): wait for the current one.
            deadline = time.monotonic() + 10.0
            while not board.get("factory/loaded") and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            return {k: board.get(k) for k in ("factory/load", "factory/loaded",
                                              "factory/zone", "factory/zone_max_speed_mps",
                                              "factory/charging_at")}

        values = contract.run_with_manager(body)
        assert values == {"factory/load": 30.0, "factory/loaded": True, "factory/zone": "",
                          "factory/zone_max_speed_mps": math.inf, "factory/charging_at": ""}

    def test_found_through_its_entry_point(self) -> None:
        from hal.factory import FactoryHAL

        names = {ep.name for ep in importlib.metadata.entry_points(group="beehave.hals")}
        if "factory" not in names:
            pytest.skip("'factory' is in pyproject.toml but not yet in the installed entry "
                        "points (reinstall the package)")
        contract = self.contract()
        type(contract).entry_point = "factory"
        assert FactoryHAL.name == "factory"
        contract.test_found_through_its_entry_point()


def test_factory_entries_refuse_another_schema_and_skip_an_unknown_robot() -> None:
    pytest.importorskip("rclpy")
    from beehave.errors import HALError
    from hal.factory import factory_entries

    with pytest.raises(HALError, match=r"schema 'other/1'; this HAL reads "
                                       r"'beehave/factory/state/1'"):
        factory_entries({"schema": "other/1"}, "atv1")
    assert factory_entries({"schema": STATE_SCHEMA, "robots": {}}, "atv1") is None


# ---- beehave sim factory ----------------------------------------------------------------

def test_beehave_sim_factory_writes_report_and_picture_on_sigint(tmp_path: Path) -> None:
    pytest.importorskip("rclpy")
    report, picture = tmp_path / "facts.json", tmp_path / "fleet.png"
    proc = subprocess.Popen(
        [sys.executable, "-m", "robots.node", "factory", "--robots", "3", "--fast",
         "--clock-rate-hz", "50", "--report", str(report), "--picture", str(picture)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        ready = proc.stdout.readline()
        assert "world 'factory' running" in ready and "atv3 (kobuki)" in ready, ready
        assert "atv4" not in ready
        assert "/clock at 50 Hz" in ready, ready  # the rate in use, not the default
        time.sleep(0.5)  # let it step a little: the report then has a positive sim time
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "stopped cleanly" in out and "Traceback" not in err
    data = json.loads(report.read_text())
    assert data["schema"] == REPORT_SCHEMA and data["problems"] == []
    assert set(data["robots"]) == {"atv1", "atv2", "atv3"}
    assert data["time_s"] > 0 and len(data["machines"]) == 5
    assert picture.stat().st_size > 5000 and picture.read_bytes()[:4] == b"\x89PNG"


def test_beehave_sim_refuses_more_robots_than_the_world_has(
        capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("rclpy")
    from robots.node import sim_main

    assert sim_main(["factory", "--robots", "11"]) == 2
    assert "asked for 11 robot(s)" in capsys.readouterr().err
    assert sim_main(["factory", "--report", "facts.txt"]) == 2
    assert "--report must name a .json file" in capsys.readouterr().err


def test_a_world_may_thin_a_robot_laser_and_its_physics_solver(sim_of: Any) -> None:
    sim, _ = sim_of(shop(physics={"solver_iterations": 10},
                         robots=[{"namespace": "k1", "kind": "kobuki", "laser": {"beams": 120},
                                  "start": {"x_m": 1.5, "y_m": 3.0}},
                                 {"namespace": "k2", "kind": "kobuki",
                                  "start": {"x_m": 1.5, "y_m": 1.0}}]))
    for robot in sim.robots.values():
        robot.scan_enabled = True
    sim.run_for(0.2)
    thin, full = sim.robot("k1").scan(), sim.robot("k2").scan()
    assert thin is not None and full is not None
    assert len(thin.ranges_m) == 120 and thin.angle_increment_rad == pytest.approx(math.pi / 60)
    assert len(full.ranges_m) == 360  # the kind's default
    params = sim.call(lambda c: c.getPhysicsEngineParameters())
    assert params["numSolverIterations"] == 10
    assert "laser.beams" in problems_of(shop(robots=[
        {"namespace": "k1", "kind": "kobuki", "laser": {"beams": 4},
         "start": {"x_m": 1, "y_m": 1}}])).replace("robots.0.", "")


def test_snapshots_read_while_the_sim_thread_runs_are_consistent() -> None:
    """Another thread reads facts and states while the sim thread updates them: every
    snapshot keeps its invariants and time never goes back."""
    import threading

    sim = Simulation(world_from_dict(shop(depots=[
        {"name": "depot", "area": {"center_m": [1.5, 3.0], "size_m": [1.0, 1.0]},
         "load_amount": 30, "load_s": 0.1}])), real_time_factor=None)
    factory = Factory(sim)
    bad: list[str] = []
    stop = threading.Event()

    def read() -> None:
        last = -1.0
        while not stop.is_set():
            facts = factory.facts()
            m = facts.machine("m1")
            if facts.time_s < last:
                bad.append(f"time went back: {facts.time_s} < {last}")
            if not 0.0 <= m.min_level <= m.level <= m.capacity:
                bad.append(f"level out of order: {m}")
            if len(facts.pickups) != facts.robot("k1").pickups:
                bad.append(f"pick-ups disagree: {facts}")
            state = factory.state()
            json.dumps(state)
            last = facts.time_s

    reader = threading.Thread(target=read)
    reader.start()
    try:
        sim.start()
        assert factory.facts().time_s >= 0.0
        deadline = time.monotonic() + 20.0
        while factory.facts().time_s < 5.0 and time.monotonic() < deadline:
            time.sleep(0.01)
        sim.stop()
    finally:
        stop.set()
        reader.join()
        sim.close()
    assert factory.facts().time_s >= 5.0
    assert factory.facts().robot("k1").pickups == 1
    assert bad == []
