"""Real-time factor of the full stack: sim + ROS 2 + both managers per robot.

Targets (issue 5), physics at 240 Hz: full stack, 1 robot ≥ 10× and 10 robots ≥ 2× real
time. The wandering Kobukis read their bumpers, not their lasers, so the sim node leaves
the lasers off in both runs (it casts them only while someone subscribes to ``scan``).
Each figure is beside the sim alone in the same run (same world, robots driving from an
on_step callback instead of beehave), and the framework's overhead per robot-step is
printed. Kobukis wander (bumper-reactive) with their LED logic; one shared RosContext
(one executor thread, one DDS participant) for the sim node and all robots.
"""

from __future__ import annotations

import math
import os
import random
import time
from typing import Any

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(101, 200)))

from beehave.config import parse_config  # noqa: E402
from beehave.robot import Robot  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from benchmarks._util import report  # noqa: E402
from robots.node import SimNode  # noqa: E402
from robots.sim import Simulation  # noqa: E402
from robots.world import world_from_dict  # noqa: E402

MEASURE_S = 6.0
WARMUP_S = 2.0


def world(n: int) -> Any:
    side = max(4, math.ceil(math.sqrt(n)))
    size = 2.0 * side + 2.0
    robots = [{"namespace": f"kobuki{i}", "kind": "kobuki",
               "start": {"x_m": 2.0 + 2.0 * (i % side), "y_m": 2.0 + 2.0 * (i // side),
                         "yaw_deg": 90 * (i % 4)}} for i in range(n)]
    return world_from_dict({
        "name": f"bench_{n}", "floor": {"size_m": [size, size]},
        "walls": [{"from_m": [0, 0.1], "to_m": [size, 0.1]},
                  {"from_m": [0, size - 0.1], "to_m": [size, size - 0.1]},
                  {"from_m": [0.1, 0], "to_m": [0.1, size]},
                  {"from_m": [size - 0.1, 0], "to_m": [size - 0.1, size]}],
        "robots": robots})


def config(i: int) -> Any:
    return parse_config({
        "namespace": f"kobuki{i}", "use_sim_time": True, "stop_timeout_s": 2.0,
        "behaviors": {"wander": {"class": "behaviours.kobuki:Wander", "params": {"seed": i}}},
        "logics": {"kobuki": {"class": "behaviours.logics:KobukiLedLogic"}},
        "default_logic": "kobuki", "ros": {"state_period_s": 1.0}}, source=f"bench:{i}")


def measure(sim: Simulation) -> float:
    time.sleep(WARMUP_S)
    s0, w0 = sim.time_s, time.monotonic()
    time.sleep(MEASURE_S)
    return (sim.time_s - s0) / (time.monotonic() - w0)


def sim_alone(n: int) -> float:
    sim = Simulation(world(n), real_time_factor=None)
    for robot in sim.robots.values():
        robot.scan_enabled = False  # as in the full stack, where nobody subscribes to scan

    def drive(t: float) -> None:
        for k, robot in enumerate(sim.robots.values()):
            robot.set_cmd_vel(0.25, 0.4 * math.sin(0.3 * t + k))

    sim.on_step(drive, rate_hz=20.0)
    with sim:
        return measure(sim)


def full_stack(n: int) -> float:
    sim = Simulation(world(n), real_time_factor=None)
    ros = RosContext()
    node = SimNode(sim, ros)
    robots = [Robot(config(i), ros=ros) for i in range(n)]
    try:
        ros.start()
        sim.start()
        for robot in robots:
            robot.start()
        for robot in robots:
            assert robot.high is not None
            robot.high.switch("wander")
        return measure(sim)
    finally:
        for robot in robots:
            robot.shutdown()
        sim.stop()
        node.destroy()
        ros.shutdown()
        sim.close()


def main() -> list[dict[str, Any]]:
    rows = []
    targets = {1: 10.0, 10: 2.0}
    for n in (1, 10, 25):
        alone = sim_alone(n)
        full = full_stack(n)
        rows.append(report(f"sim_alone_{n}_robots_rtf", alone, "x", None, None))
        target = targets.get(n)
        rows.append(report(f"full_stack_{n}_robots_rtf", full, "x",
                           None if target is None else f">= {target:g} x",
                           None if target is None else full >= target,
                           ratio_to_sim_alone=round(full / alone, 3)))
        steps_alone, steps_full = alone * 240 * n, full * 240 * n
        overhead = (1 / steps_full - 1 / steps_alone) * 1e6
        rows.append(report(f"framework_overhead_{n}_robots_per_robot_step", overhead, "us",
                           None, None, note="(wall per robot-step) full stack − sim alone"))
    return rows


if __name__ == "__main__":
    main()
