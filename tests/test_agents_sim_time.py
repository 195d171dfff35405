"""An agent on a robot's node that runs on simulation time keeps its lease in wall time.

Leases are judged in wall time by every other process (the order source, a zone keeper):
an agent whose announcements were paced by the simulation's clock fell silent whenever
that clock stood still — a stalled simulator on a loaded host, a lockstep wait — and every
robot left the directory at once (issue 11: the serve scenario's CI failure, all three
robots "left the directory (lease expired)" 5 s after the start).
"""

from __future__ import annotations

import threading
import time

import pytest

pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402

from beehave.agents import Agent, Change, DirectoryEvent  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S  # noqa: E402

LEASE_S = 0.5
WAIT_S = WALL_TIMEOUT_S  # the suite's one bound (beehave.testing): the machine may be loaded


def test_an_agent_on_a_sim_time_node_stays_alive_while_the_sim_clock_stands_still() -> None:
    with RosContext() as ros:
        # The simulator published its clock once and then stalled.
        sim = ros.create_node("stalled_sim_s2")
        clock_pub = sim.create_publisher(Clock, "/clock", 10)
        clock_pub.publish(Clock(clock=Time(sec=10)))
        robot_node = ros.create_node("sim_time_robot_s2", use_sim_time=True)
        left: list[str] = []
        seen = threading.Event()

        def note(event: DirectoryEvent) -> None:
            if event.agent.name != "sim_robot_s2":
                return
            if event.change is Change.APPEARED:
                seen.set()
            elif event.change is Change.DISAPPEARED:
                left.append(event.reason)

        with Agent("sim_watcher_s2", ros=ros, probe_s=0.3, lease_s=LEASE_S) as watcher:
            watcher.directory.subscribe("serve", note)
            with Agent("sim_robot_s2", node=robot_node, probe_s=0.3, lease_s=LEASE_S,
                       services={"serve": {}}):
                assert seen.wait(WAIT_S), "the robot's agent never appeared"
                # Eight leases of wall time while the sim clock stands still: a robot that
                # announces on sim time falls silent and is declared dead after one.
                end = time.monotonic() + 8 * LEASE_S
                while time.monotonic() < end and not left:
                    clock_pub.publish(Clock(clock=Time(sec=10)))  # still 10 s: stalled
                    time.sleep(0.05)
                assert left == [], f"the robot left the directory: {left}"
                assert watcher.directory.alive("sim_robot_s2")
