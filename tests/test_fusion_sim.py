"""Priority fusion on the simulated Kobuki over real DDS: the safety reflex beats wander.

``robots/config/kobuki_fusion.yaml`` runs (its low level, as ``beehave run`` builds it) next
to a pybullet simulation in which the Kobuki faces a wall 0.8 m ahead. Wander proposes
driving forward the whole time; the bumper logic must stop the robot at the wall and back
it off — checked in the physics, not in the arbiter's bookkeeping.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("pybullet")

from geometry_msgs.msg import Twist  # noqa: E402

from beehave.config import load_config  # noqa: E402
from beehave.robot import Robot  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import beehave_threads, wait_until  # noqa: E402
from robots.kobuki import Kobuki  # noqa: E402
from robots.node import SimNode  # noqa: E402
from robots.sim import Simulation  # noqa: E402
from robots.world import world_from_dict  # noqa: E402

NS = f"fusion_kobuki_{os.getpid()}"
CONFIG = Path(__file__).parent.parent / "robots" / "config" / "kobuki_fusion.yaml"
WALL_FACE_X_M = 8.0


@dataclass
class Rig:
    sim: Simulation
    ros: RosContext
    kobuki: Kobuki


@pytest.fixture
def rig() -> Iterator[Rig]:
    """The Kobuki at (7, 1) facing +x; a wall's face at x = 8 (0.825 m from its bumper)."""
    before = set(beehave_threads())
    world = world_from_dict({
        "name": "fusion_arena", "floor": {"size_m": [10, 10]},
        "walls": [{"from_m": [8.1, 0], "to_m": [8.1, 10], "thickness_m": 0.2}],
        "robots": [{"namespace": NS, "kind": "kobuki", "start": {"x_m": 7, "y_m": 1}}]})
    sim = Simulation(world, real_time_factor=1.0)
    ros = RosContext()
    sim_node = SimNode(sim, ros)
    ros.start()
    sim.start()
    try:
        yield Rig(sim, ros, sim.kobuki(NS))
    finally:
        sim.stop()
        sim_node.destroy()
        ros.shutdown()
        sim.close()
    leaked = [t.name for t in beehave_threads() if t not in before]
    assert not leaked, f"threads left after teardown: {leaked}"


def test_the_bumper_reflex_stops_and_backs_off_the_kobuki_while_wander_pushes_on(
        rig: Rig) -> None:
    config = load_config(CONFIG).model_copy(update={"namespace": NS})
    kobuki = rig.kobuki
    start_x = kobuki.pose().x_m
    # What reaches the robot's cmd_vel topic, as any other node on the bus sees it.
    probe = rig.ros.create_node("fusion_probe", namespace=NS)
    heard: list[tuple[float, float]] = []
    probe.create_subscription(Twist, "cmd_vel",
                              lambda m: heard.append((m.linear.x, m.angular.z)), 50)
    with Robot(config, only="low", ros=rig.ros) as robot:
        low = robot.low
        assert low is not None
        # Wander drives it forward until the bumper hits the wall.
        assert wait_until(lambda: kobuki.pose().x_m > start_x + 0.2)
        assert wait_until(lambda: kobuki.bumpers().center)
        hit_x = kobuki.pose().x_m
        assert hit_x < WALL_FACE_X_M - Kobuki.radius_m + 0.02  # the wall held, no tunnelling
        # The safety proposal wins: the robot backs off although wander still proposes
        # full speed ahead (fresh, on the blackboard).
        assert wait_until(lambda: kobuki.pose().x_m < hit_x - 0.05)
        wander = low.blackboard.entry("fusion/cmd_vel/wander")
        assert wander is not None and not wander.stale and list(wander.value) == [0.3, 0.0]
        assert kobuki.cmd_vel()[0] < 0
        assert not kobuki.bumpers().center
        # Then it turns away and hands back to wander, which drives again.
        yaw0 = kobuki.pose().yaw_rad
        assert wait_until(lambda: abs(kobuki.pose().yaw_rad - yaw0) > 0.3)
        assert wait_until(lambda: low.blackboard.get("fusion/cmd_vel/winner", {}).get("source")
                          == "wander")
        assert wait_until(lambda: kobuki.cmd_vel()[0] > 0.2)
        assert heard[-1] == (0.3, 0.0)
    # Unloaded at shutdown, the arbiter's safe state sends zero: the last word on the bus.
    assert wait_until(lambda: heard[-1] == (0.0, 0.0))
    assert (-0.1, 0.0) in heard and any(w != 0.0 for _, w in heard)  # backed off, turned
