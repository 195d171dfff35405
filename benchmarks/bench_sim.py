"""The physics simulation alone: real-time factor at 240 Hz for 1, 10 and 25 EMILIs.

Each robot drives a circle, commanded at 10 Hz from an ``on_step`` callback (as the ROS
wrapper will), with its 360-beam laser at 10 Hz and its other sensors at 50 Hz, in the
simulation's own thread at ``real_time_factor=None``. Beside it, a floor: the same URDFs
on the same floor and walls stepped by bare pybullet (wheel motors set once, no sensors),
so the wrapper's cost per robot-step shows.

Targets (issue: for the later full stack, printed here for the sim alone): 1 robot ≥ 10×
real time, 10 robots ≥ 2×. Reference measured on this kind of machine: a husky (mesh
model) steps at about 7,300 robot-steps/s.

The factory world (``robots/worlds/factory.yaml``) with 4 and 10 Kobuki ATVs and its
:class:`~robots.factory.Factory` physics (levels, loads, zones measured every 5th step),
no controllers: each ATV drives a circle commanded from an ``on_step`` callback, every
laser casting (120 beams at 10 Hz, as when Navigation subscribes to ``scan``). Target: ≥ 3×
real time at 10 ATVs — what ``beehave fleet --fast`` needs to stay ≥ 1× with the
controllers' processes on the same cores. ``cpu_real_time_factor`` divides by the
process's CPU time instead of the wall time: on a shared machine it shows what the
simulation would do alone.

The path planner (``beehave.planning``) on the warehouse map, for EMILI (0.55 m radius +
0.1 m clearance, 0.1 m cells): building the inflated grid once, and the median time of one
``plan`` over a set of station-to-station orders — what Navigation pays per (re-)plan and an
agent per bid. Target: median plan ≤ 50 ms (a re-plan must not stall a 20 Hz control loop
for more than one period). The same target for a re-plan after 100 looks at one wall: the
hits Navigation remembers are kept one per cell, so that cost must not grow with the looks.
"""

from __future__ import annotations

import math
import time
from typing import Any

import pybullet
from pybullet_utils.bullet_client import BulletClient

from benchmarks._util import report
from robots.robot import URDF_DIR
from robots.sim import Simulation, quiet_stdout
from robots.world import World, world_from_dict

RATE_HZ = 240.0
SPACING_M = 4.0
COLUMNS = 5


def fleet_world(n: int) -> World:
    """``n`` EMILIs on a grid, 4 m apart, inside four walls, with a shelf row."""
    rows = math.ceil(n / COLUMNS)
    width, depth = COLUMNS * SPACING_M + 2, rows * SPACING_M + 2
    robots = [{"namespace": f"emili{i}", "kind": "emili",
               "start": {"x_m": 3 + (i % COLUMNS) * SPACING_M,
                         "y_m": 3 + (i // COLUMNS) * SPACING_M, "yaw_deg": 0}}
              for i in range(n)]
    walls = [{"from_m": [0, 0], "to_m": [width, 0]}, {"from_m": [0, depth], "to_m": [width, depth]},
             {"from_m": [0, 0], "to_m": [0, depth]}, {"from_m": [width, 0], "to_m": [width, depth]}]
    return world_from_dict({
        "name": f"fleet{n}", "floor": {"size_m": [width, depth]}, "walls": walls,
        "shelves": [{"center_m": [width / 2, depth - 0.6], "size_m": [width - 4, 0.6]}],
        "robots": robots})


def bare(world: World, duration_s: float) -> float:
    """Robot-steps per wall second for the same bodies stepped by bare pybullet."""
    with quiet_stdout():
        client = BulletClient(connection_mode=pybullet.DIRECT)
    try:
        client.setGravity(0, 0, -9.81)
        client.setTimeStep(1 / RATE_HZ)
        w, d = world.floor.size_m
        floor = client.createCollisionShape(client.GEOM_BOX, halfExtents=[w / 2, d / 2, 0.05])
        client.createMultiBody(0, floor, -1, [w / 2, d / 2, -0.05])
        for wall in world.walls:
            (ax, ay), (bx, by) = wall.from_m, wall.to_m
            shape = client.createCollisionShape(
                client.GEOM_BOX, halfExtents=[math.hypot(bx - ax, by - ay) / 2, 0.1, 0.75])
            client.createMultiBody(0, shape, -1, [(ax + bx) / 2, (ay + by) / 2, 0.75],
                                   client.getQuaternionFromEuler(
                                       [0, 0, math.atan2(by - ay, bx - ax)]))
        for spec in world.robots:
            body = client.loadURDF(str(URDF_DIR / "emili.urdf"),
                                   [spec.start.x_m, spec.start.y_m, 0.102])
            client.setJointMotorControlArray(body, [0, 1], client.VELOCITY_CONTROL,
                                             targetVelocities=[4.25, 5.75], forces=[40, 40])
        step = client.stepSimulation
        steps = 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < duration_s:
            for _ in range(24):
                step()
            steps += 24
        wall_s = time.perf_counter() - t0
        return steps * len(world.robots) / wall_s
    finally:
        client.disconnect()


def wrapped(world: World, duration_s: float) -> tuple[float, float]:
    """(robot-steps per wall second, real-time factor) of the Simulation's own thread."""
    sim = Simulation(world, rate_hz=RATE_HZ, real_time_factor=None)
    robots = list(sim.robots.values())

    def command(time_s: float) -> None:
        for robot in robots:
            robot.set_cmd_vel(0.5, 0.3)

    sim.on_step(command, rate_hz=10.0)
    try:
        steps0 = sim.steps
        t0 = time.perf_counter()
        sim.start()
        time.sleep(duration_s)
        sim.stop()
        wall_s = time.perf_counter() - t0
        steps = sim.steps - steps0
        assert all(r.scan() is not None for r in robots)
        return steps * len(robots) / wall_s, steps / RATE_HZ / wall_s
    finally:
        sim.close()


def factory(n: int, duration_s: float) -> tuple[float, float]:
    """(real-time factor by wall time, by process CPU time) of the factory with ``n`` ATVs
    in the simulation's own thread."""
    from robots.factory import Factory
    from robots.world import load_world

    sim = Simulation(load_world("factory").with_robots(n), rate_hz=RATE_HZ,
                     real_time_factor=None)
    physics = Factory(sim)
    robots = list(sim.robots.values())

    def command(time_s: float) -> None:
        for robot in robots:
            robot.set_cmd_vel(0.3, 0.3)

    sim.on_step(command, rate_hz=10.0)
    try:
        t0, cpu0 = time.perf_counter(), time.process_time()
        sim.start()
        time.sleep(duration_s)
        sim.stop()
        wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - cpu0
        assert all(r.scan() is not None for r in robots)
        assert physics.facts().time_s > 0
        return sim.time_s / wall_s, sim.time_s / cpu_s
    finally:
        physics.close()
        sim.close()


def factory_rows() -> list[dict[str, Any]]:
    rows = []
    for n, target in ((4, None), (10, 3.0)):
        factor, cpu_factor = factory(n, 4.0)
        rows.append(report(f"sim_factory_{n}_kobukis_real_time_factor", factor, "x",
                           f">= {target:g} x" if target else None,
                           (factor >= target) if target else None,
                           cpu_real_time_factor=round(cpu_factor, 2), rate_hz=RATE_HZ,
                           laser_beams=120, scan_rate_hz=10.0, solver_iterations=10))
    return rows


def planner_rows() -> list[dict[str, Any]]:
    from beehave.planning import GridPlanner
    from benchmarks._util import median, percentile
    from robots.world import load_world, occupancy_map

    world = load_world("warehouse")
    floor = occupancy_map(world)
    builds = []
    for _ in range(5):
        t0 = time.perf_counter()
        planner = GridPlanner(floor, robot_radius_m=0.55, clearance_m=0.1)
        builds.append(time.perf_counter() - t0)
    points = [(r.start.x_m, r.start.y_m) for r in world.robots if r.kind == "emili"]
    points += [s.center_m for s in world.stations if s.name.startswith("emili")]
    points += [(10.0, 5.5), (3.0, 8.0), (16.5, 3.0)]
    pairs = [(a, b) for a in points for b in points if a != b]
    times, lengths = [], []
    for _ in range(3):
        for a, b in pairs:
            t0 = time.perf_counter()
            plan = planner.plan(a, b)
            times.append(time.perf_counter() - t0)
            lengths.append(plan.length_m)
    rows = [report("planner_warehouse_build_grid", median(builds) * 1e3, "ms", None, None,
                   cells=planner.width * planner.height)]
    med = median(times) * 1e3
    rows.append(report("planner_warehouse_plan_median", med, "ms", "<= 50 ms", med <= 50.0,
                       p95_ms=round(percentile(times, 95) * 1e3, 2), plans=len(times),
                       mean_path_m=round(sum(lengths) / len(lengths), 2)))
    rows.append(replan_row(planner, pairs))
    return rows


def replan_row(planner: Any, pairs: list[Any]) -> dict[str, Any]:
    """A Navigation stuck in front of the same wall for 100 re-plans: the laser's ~50 hits
    of each look go into a SeenObstacles, then the map gets them and the path is planned."""
    from beehave.errors import NoPath
    from beehave.planning import Disc, SeenObstacles
    from benchmarks._util import median

    hits = [Disc((9.0 + 0.75 * math.cos(a / 100), 6.0 + 0.75 * math.sin(a / 100)), 0.05)
            for a in range(-50, 50, 2)]
    seen = SeenObstacles(cell_m=planner.resolution_m)
    times = []
    for look in range(100):
        t0 = time.perf_counter()
        seen.add(hits, now_s=float(look))
        try:
            planner.with_obstacles(seen.shapes()).plan(*pairs[look % len(pairs)])
        except NoPath:
            pass
        times.append(time.perf_counter() - t0)
    last = median(times[-10:]) * 1e3
    return report("planner_replan_after_100_looks", last, "ms", "<= 50 ms", last <= 50.0,
                  first_ms=round(median(times[:10]) * 1e3, 2), hits_kept=len(seen),
                  hits_looked_at=100 * len(hits))


def main() -> list[dict[str, Any]]:
    rows = planner_rows()
    rows += factory_rows()
    targets = {1: 10.0, 10: 2.0}
    for n in (1, 10, 25):
        world = fleet_world(n)
        duration_s = 2.0 if n == 1 else 3.0
        floor_rsps = bare(world, duration_s)
        rows.append(report(f"sim_bare_pybullet_{n}_robots", floor_rsps, "robot-steps/s",
                           None, None, real_time_factor=round(floor_rsps / n / RATE_HZ, 2)))
        rsps, factor = wrapped(world, duration_s)
        rows.append(report(f"sim_{n}_robots_robot_steps", rsps, "robot-steps/s", None, None,
                           rate_hz=RATE_HZ, scan_rate_hz=10.0, sensor_rate_hz=50.0))
        target = targets.get(n)
        rows.append(report(f"sim_{n}_robots_real_time_factor", factor, "x",
                           f">= {target:g} x" if target else None,
                           (factor >= target) if target else None))
        overhead_us = (1 / rsps - 1 / floor_rsps) * 1e6
        rows.append(report(f"sim_{n}_robots_wrapper_overhead_per_robot_step", overhead_us,
                           "us", None, None,
                           note="sensors, lasers, commands and snapshots over bare stepping"))
    return rows


if __name__ == "__main__":
    main()
