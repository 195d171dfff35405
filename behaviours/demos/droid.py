"""The MAVLink Droid scenario: a rover meets a wall it cannot pass, and the quadrotor that
followed it finishes its mission over the wall while the rover returns home.

``python -m behaviours.demos.droid [--picture docs/img/droid.png] [--timeout-s 150]``

What runs, each in its own process, as on a real fleet:

1. this process: the physics (pybullet, real time) with ``robots/worlds/droid.yaml``, each
   robot exposed as an ArduPilot-style MAVLink vehicle (:mod:`robots.mavlink_endpoint`) on
   a free UDP port — the Kobuki as a Rover, the ``quad`` as a Copter;
2. the copter's robot (``python -m behaviours.droid robots/config/copter.yaml``): its
   MAVLink HALs, its agent and fleet state; it takes off and follows the rover at 2 m and
   offers the ``mission`` service;
3. the rover's robot (``robots/config/rover.yaml``): it runs its mission, is stopped by
   the wall, hands the remaining waypoints to the best bidder over the agent layer
   (contract net on DDS, this ``ROS_DOMAIN_ID``) and returns home.

It ends with a table of checks measured in the physics (not in what the robots believe):
the copter reached every remaining waypoint, the last one included; the rover is back
home; the copter never came closer to the rover than the safety distance; the follower's
gap stayed within [d − 0.2 m, d + 0.5 m] once settled. Exit code 0 only if every check
passes. ``--picture`` writes the top-down picture with both paths and the mission.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml

from robots.mavlink_endpoint import MavlinkEndpoint
from robots.quad import Quad
from robots.sim import Simulation
from robots.world import load_world

ROOT = Path(__file__).resolve().parents[2]
WORLD = ROOT / "robots" / "worlds" / "droid.yaml"
ROVER_CONFIG = ROOT / "robots" / "config" / "rover.yaml"
COPTER_CONFIG = ROOT / "robots" / "config" / "copter.yaml"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@dataclass
class Check:
    name: str
    passed: bool
    measured: str


@dataclass
class Trace:
    """Ground truth sampled in the sim thread."""

    gaps: list[tuple[float, float]] = field(default_factory=list)  # (time_s, gap_m)
    copter_points: list[tuple[float, float, float]] = field(default_factory=list)
    rtl_at_s: float = math.inf
    """When the rover turned home (it does so as it asks for help)."""
    auto_at_s: float = math.inf
    """When the copter started the handed-over mission (AUTO): its follow had ended."""
    airborne_at_s: float = math.inf
    """When the copter had taken off to follow."""


class _Process:
    """A robot process whose output lines are collected by a reader thread."""

    def __init__(self, name: str, args: list[str]) -> None:
        self.name = name
        self.lines: queue.Queue[str] = queue.Queue()
        self.log: list[str] = []
        self.result: dict[str, Any] | None = None
        self.proc = subprocess.Popen([sys.executable, "-m", "behaviours.droid", *args],
                                     cwd=ROOT, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self._reader = threading.Thread(target=self._read, args=(self.proc.stdout,),
                                        daemon=True)
        self._reader.start()

    def _read(self, stream: IO[str] | None) -> None:
        assert stream is not None
        for line in stream:
            line = line.rstrip("\n")
            self.log.append(line)
            if line.startswith("RESULT "):
                self.result = json.loads(line[len("RESULT "):])
            self.lines.put(line)

    def wait_line(self, prefix: str, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None:
                    return False
                continue
            if line.startswith(prefix):
                return True
        return False

    def stop(self, timeout_s: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(2.0)
        return self.proc.returncode


def run(*, timeout_s: float = 150.0, picture: Path | None = None,
        verbose: bool = False) -> tuple[list[Check], dict[str, Any]]:
    """Run the scenario; returns the checks and what was measured."""
    world = load_world(WORLD)
    rover_cfg = yaml.safe_load(ROVER_CONFIG.read_text(encoding="utf-8"))
    copter_cfg = yaml.safe_load(COPTER_CONFIG.read_text(encoding="utf-8"))
    waypoints = rover_cfg["behaviors"]["droid"]["params"]["waypoints"]
    follow = copter_cfg["behaviors"]["droid"]["params"]
    distance_m, safety_m = float(follow["distance_m"]), float(follow["safety_m"])
    sim = Simulation(world, real_time_factor=1.0)
    ports = {"rover1": free_udp_port(), "copter1": free_udp_port()}
    endpoints = {name: MavlinkEndpoint(sim, name, url=f"udpout:127.0.0.1:{port}",
                                       system_id=i + 1)
                 for i, (name, port) in enumerate(ports.items())}
    rover, copter = sim.robot("rover1"), sim.robot("copter1")
    assert isinstance(copter, Quad)
    trace = Trace()

    def sample(time_s: float) -> None:
        r, c = rover.pose(), copter.position()
        trace.gaps.append((time_s, math.hypot(r.x_m - c.x_m, r.y_m - c.y_m)))
        trace.copter_points.append((c.x_m, c.y_m, c.z_m))
        if trace.rtl_at_s == math.inf and endpoints["rover1"].mode == "RTL":
            trace.rtl_at_s = time_s
        if trace.auto_at_s == math.inf and endpoints["copter1"].mode == "AUTO":
            trace.auto_at_s = time_s
        if trace.airborne_at_s == math.inf and c.z_m > 1.5:
            trace.airborne_at_s = time_s

    sim.on_step(sample, rate_hz=20.0)
    sim.start()
    procs: list[_Process] = []
    measured: dict[str, Any] = {}
    try:
        def launch(name: str, config: Path, what: str) -> _Process:
            proc = _Process(name, [str(config), "--connection",
                                   f"udp:127.0.0.1:{ports[name]}"])
            procs.append(proc)
            if not proc.wait_line(f"droid {name}: running", 40.0):
                raise RuntimeError(f"the {what}'s robot did not start:\n"
                                   + "\n".join(proc.log[-30:]))
            return proc

        launch("copter1", COPTER_CONFIG, "copter")
        # The rover's robot starts while the copter takes off (it then follows).
        rover_proc = launch("rover1", ROVER_CONFIG, "rover")
        rover_proc.wait_line("RESULT ", timeout_s)
        follow_from_s = trace.airborne_at_s
        measured["rover_result"] = rover_proc.result
        # The helper informs the rover when it is done, so the rover's RESULT comes last.
    finally:
        for proc in procs:
            proc.stop()
        sim.stop()
        for endpoint in endpoints.values():
            endpoint.close()
    if verbose:
        for proc in procs:
            lines = [line for line in proc.log if "watchdog" not in line]
            print(f"---- {proc.name}", *lines[-60:], sep="\n")
    last = waypoints[-1]
    last_xy = (float(last[1]), float(last[0]))  # [north, east] → world (x, y)
    helper_alt = float(rover_cfg["behaviors"]["droid"]["params"]["helper_alt_m"])
    reached_last = min((math.hypot(x - last_xy[0], y - last_xy[1]) + abs(z - helper_alt)
                        for x, y, z in trace.copter_points), default=math.inf)
    home = world.robots[0].start
    rover_end = rover.pose()
    home_m = math.hypot(rover_end.x_m - home.x_m, rover_end.y_m - home.y_m)
    # Following: from the copter's take-off until it starts the handed-over mission. The
    # gap band applies until the rover turns home (it then drives towards its follower,
    # which backs off: the gap dips below d by design, never below the safety distance).
    following = [g for t, g in trace.gaps if follow_from_s <= t < trace.auto_at_s]
    min_gap = min(following, default=math.inf)
    band = [g for t, g in trace.gaps if follow_from_s <= t <= trace.rtl_at_s]
    low, high = distance_m - 0.2, distance_m + 0.5
    # Settled: the first time the gap came within 0.2 m of d (after the approach).
    settled = next((i for i, g in enumerate(band) if abs(g - distance_m) <= 0.2), None)
    after = band[settled:] if settled is not None else []
    result = (measured.get("rover_result") or {}).get("result") or {}
    checks = [
        Check("the rover handed its remaining mission over",
              result.get("status") == "handed-over" and result.get("awardee") == "copter1",
              f"{result.get('status')} to {result.get('awardee')}"),
        Check("the copter reached the mission's last waypoint",
              reached_last <= 0.8 and endpoints["copter1"].reached[-1:] == [
                  len(result.get("remaining") or []) or -1],
              f"closest approach {reached_last:.2f} m (3-D), vehicle reached items "
              f"{endpoints['copter1'].reached}"),
        Check("the rover is home", home_m <= 0.5, f"{home_m:.2f} m from its start"),
        Check(f"following, the copter never came closer than {safety_m} m (safety)",
              bool(following) and min_gap >= safety_m,
              f"closest {min_gap:.2f} m over {len(following) / 20:.1f} s"),
        Check(f"while following, the gap stayed in [{distance_m - 0.2:.1f}, "
              f"{distance_m + 0.5:.1f}] m after settling",
              bool(after) and min(after) >= low and max(after) <= high,
              f"{min(after):.2f}–{max(after):.2f} m over {len(after) / 20:.1f} s"
              if after else "never settled"),
    ]
    measured.update({"min_gap_m": min_gap, "home_m": home_m, "reached_last_m": reached_last,
                     "sim_time_s": sim.time_s})
    if picture is not None:
        planned = [[(2.0, 2.0)] + [(float(w[1]), float(w[0])) for w in waypoints]]
        sim.render_topdown(picture, planned=planned)
    sim.close()
    return checks, measured


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m behaviours.demos.droid",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--picture", type=Path, default=None)
    parser.add_argument("--timeout-s", type=float, default=150.0)
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    checks, measured = run(timeout_s=args.timeout_s, picture=args.picture,
                           verbose=args.verbose)
    width = max(len(c.name) for c in checks)
    print(f"{'check'.ljust(width)}  result  measured")
    for c in checks:
        print(f"{c.name.ljust(width)}  {'PASS' if c.passed else 'FAIL':6}  {c.measured}")
    print(f"(sim time {measured['sim_time_s']:.1f} s)")
    if args.picture is not None:
        print(f"picture: {args.picture}")
    return 0 if all(c.passed for c in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
