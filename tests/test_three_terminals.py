"""The README's three-terminal example, as real processes over DDS:

1. ``beehave sim`` (here ``--fast``: lockstep keeps the robot's control loop in step),
2. ``beehave run robots/config/emili.yaml``,
3. ``python -m behaviours.demos.order_agent emili1 --switch commanded --station
   emili_pickup`` (sets EMILI's ``behavior`` parameter, then orders).

The straight line from EMILI's start to ``emili_pickup`` runs into a pillar; the order is
reached only because Navigation plans around it. Checked in the physics: the sim's
ground-truth odometry puts EMILI inside the station's tolerance.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("pybullet")
pytest.importorskip("rclpy")

from nav_msgs.msg import Odometry  # noqa: E402
from ros_probe import Probe  # noqa: E402

from beehave.testing import WALL_TIMEOUT_S, wall_timeout  # noqa: E402
from robots.world import load_world  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TOLERANCE_M = 0.15  # Navigation's default tolerance_m, which Commanded uses
# The order agent's own bound on the order (its --timeout-s), a share of the suite's bound.
ORDER_S = wall_timeout(1.5)


def _start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, env=dict(os.environ),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_readme_three_terminals_order_to_emili_pickup_goes_around_the_pillar() -> None:
    world = load_world("warehouse")
    pickup = world.station("emili_pickup")
    # Each process inherits this test's own ROS_DOMAIN_ID (conftest), localhost only.
    procs: list[subprocess.Popen[str]] = []
    probe = Probe()
    try:
        odom = probe.record(Odometry, "/emili1/odom")
        procs.append(_start("-m", "beehave.cli", "sim", "--fast"))
        procs.append(_start("-m", "beehave.cli", "run", "robots/config/emili.yaml"))
        assert probe.wait(lambda: bool(odom)), "no odometry from the sim"
        # Terminal 3, as the README gives it: switch to commanded, then the order.
        agent = _start("-m", "behaviours.demos.order_agent", "emili1", "--switch", "commanded",
                       "--station", "emili_pickup",
                       "--timeout-s", str(ORDER_S))
        procs.append(agent)
        out, _ = agent.communicate(timeout=ORDER_S + wall_timeout(0.25))
        assert agent.returncode == 0, out
        assert '"status": "reached"' in out, out
        # The physics: the sim's odometry is ground truth.
        assert probe.wait(lambda: bool(odom))
        p = odom[-1].pose.pose.position
        error = math.hypot(p.x - pickup.center_m[0], p.y - pickup.center_m[1])
        assert error <= TOLERANCE_M + 0.05, (p.x, p.y, error)
        assert pickup.contains(p.x, p.y)
    finally:
        # By PID, only what this test started: SIGTERM (each stops cleanly), then SIGKILL.
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in procs:
            try:
                proc.communicate(timeout=WALL_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
        probe.close()
