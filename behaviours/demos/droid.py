"""The MAVLink Droid scenarios: a rover follows a rover leading a tour (``follow``); a rover
meets a wall it cannot pass and the quadrotor finishes its mission over the wall while the
rover returns home (``handover``); or both at once, the copter following the rover before
it takes the mission over (``droid``).

``python -m behaviours.demos.droid [--scenario follow|handover|droid] [--fast]
[--picture docs/img/follow.png] [--timeout-s 150]`` (``beehave fleet --scenario …`` runs
the same).

What runs, each in its own process, as on a real fleet:

1. this process: the physics (pybullet, real time; ``--fast``: up to 2.5x, as fast as the robots
   keep up) with ``robots/worlds/follow.yaml`` or ``robots/worlds/droid.yaml``, each robot
   exposed as an ArduPilot-style MAVLink vehicle (:mod:`robots.mavlink_endpoint`) on a
   free UDP port — a Kobuki as a Rover, the ``quad`` as a Copter — and its time on
   ``/clock``. The robots run on that sim time (``use_sim_time``): a follower's control
   loop holds the simulation where each period ends until it has answered (lockstep), so
   neither ``--fast`` nor a loaded host lets the physics outrun it;
2. the other vehicle's robot (``python -m behaviours.droid CONFIG.yaml``): its MAVLink
   HALs, its agent and fleet state. ``follow``: ``robots/config/follower.yaml`` (rover2
   keeps 2 m from rover1's shared state); ``handover``: ``robots/config/copter.yaml``
   without following (it waits on its pad and offers the ``mission`` service); ``droid``:
   the same copter, which takes off and follows the rover at 2 m;
3. rover1's robot: ``robots/config/tour.yaml`` (its tour, at 0.45 m/s set as WP_SPEED)
   or ``robots/config/rover.yaml`` (its mission is stopped by the wall; it hands the
   remaining waypoints to the best bidder over the agent layer — contract net on DDS,
   this ``ROS_DOMAIN_ID`` — and returns home).

It ends with a table of checks measured in the physics (not in what the robots believe).
``follow``: the leader reached every waypoint of its tour; the follower never came closer
than the safety distance; its gap stayed within [d − 0.2 m, d + 0.5 m] once settled.
``handover``: the copter reached every remaining waypoint (3-D, and the vehicle reported
each item reached); the rover is back home. ``droid``: all of these. Exit code 0 only if
every check passes. ``--picture`` writes the top-down picture with the paths and the
planned mission.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml

from beehave.procs import dies_with_parent
from beehave.ros.context import RosContext
from robots.mavlink_endpoint import MavlinkEndpoint, free_udp_ports
from robots.node import SimNode
from robots.quad import Quad
from robots.sim import SimState, Simulation
from robots.world import load_world

ROOT = Path(__file__).resolve().parents[2]
WORLD = ROOT / "robots" / "worlds" / "droid.yaml"
ROVER_CONFIG = ROOT / "robots" / "config" / "rover.yaml"
COPTER_CONFIG = ROOT / "robots" / "config" / "copter.yaml"
FOLLOW_WORLD = ROOT / "robots" / "worlds" / "follow.yaml"
FAST_FACTOR = 2.5
"""``--fast``: at most this many times real time. Only the follower's control loop holds the
lockstep; the leader's robot does not, so every wall second its telemetry takes to reach
the fleet state (MAVLink, HAL, blackboard, DDS) is that many sim seconds of lag. As fast
as the follower kept up (3x on an idle host) the follower fell 1.4 m behind its band once.
"""
TOUR_CONFIG = ROOT / "robots" / "config" / "tour.yaml"
FOLLOWER_CONFIG = ROOT / "robots" / "config" / "follower.yaml"

#: How often the physics samples the gaps and paths the checks measure.
SAMPLE_HZ = 20.0

#: How long (sim time) a follower gets to close up behind a leader that stopped.
SETTLE_S = 3.0

SCENARIOS = ("follow", "handover", "droid")
"""``follow``: rover1 leads a tour, rover2 follows it at 2 m; ``handover``: rover1 meets
a wall, the quadrotor finishes its mission; ``droid``: both at once (the copter follows the
rover, then takes its mission over)."""


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
    tour_at_s: float = math.inf
    """When rover1 started its mission (AUTO)."""


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
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                     preexec_fn=dies_with_parent)
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

    def wait_line(self, prefix: str, timeout_s: float | None) -> bool:
        """Wait for a line starting with ``prefix``; False when the process ended first
        or ``timeout_s`` (None: no bound) passed."""
        deadline = math.inf if timeout_s is None else time.monotonic() + timeout_s
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


def _variant(config: Path, folder: Path, **params: Any) -> Path:
    """A copy of a robot configuration on the simulation's time, with other ``droid``
    behaviour parameters."""
    data = yaml.safe_load(config.read_text(encoding="utf-8"))
    data["use_sim_time"] = True
    data["behaviors"]["droid"]["params"].update(params)
    path = folder / config.name
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def shown(value_m: float, *bounds_m: float) -> str:
    """``value_m`` with two decimals, or as many more (up to six) as it takes for the
    printed number to stand on the same side of every bound as the value itself: a minimum
    of 1.7996 m against a band from 1.8 m reads "1.7996", not "1.80" beside a FAIL."""
    for digits in range(2, 7):
        text = f"{value_m:.{digits}f}"
        printed = float(text)
        if all((printed < b) == (value_m < b) and (printed > b) == (value_m > b)
               for b in bounds_m):
            return text
    return repr(value_m)


def _gap_checks(gaps: list[tuple[float, float]], *, start_s: float, band_end_s: float,
                safety_end_s: float, distance_m: float, safety_m: float,
                who: str) -> tuple[list[Check], float]:
    """The follow checks: never closer than the safety distance while following
    (``start_s`` … ``safety_end_s``), and the gap in [d − 0.2, d + 0.5] m from the moment it
    first came within 0.2 m of d (settled) until ``band_end_s``."""
    following = [g for t, g in gaps if start_s <= t < safety_end_s]
    min_gap = min(following, default=math.inf)
    band = [g for t, g in gaps if start_s <= t <= band_end_s]
    low, high = distance_m - 0.2, distance_m + 0.5
    settled = next((i for i, g in enumerate(band) if abs(g - distance_m) <= 0.2), None)
    after = band[settled:] if settled is not None else []
    return [
        Check(f"following, {who} never came closer than {safety_m} m (safety)",
              bool(following) and min_gap >= safety_m,
              f"closest {shown(min_gap, safety_m)} m over {len(following) / SAMPLE_HZ:.1f} s"),
        Check(f"while following, the gap stayed in [{low:.1f}, {high:.1f}] m after settling",
              bool(after) and min(after) >= low and max(after) <= high,
              f"{shown(min(after), low, high)}–{shown(max(after), low, high)} m over "
              f"{len(after) / SAMPLE_HZ:.1f} s" if after else "never settled"),
    ], min_gap


def run(*, scenario: str = "droid", timeout_s: float = 150.0, picture: Path | None = None,
        verbose: bool = False, fast: bool = False, start_timeout_s: float = 60.0,
        ) -> tuple[list[Check], dict[str, Any]]:
    """Run ``scenario`` (one of :data:`SCENARIOS`); returns the checks and what was
    measured. ``fast``: the physics as fast as the robots keep up (lockstep, at most
    :data:`FAST_FACTOR` x real time), not at real
    time; the checks are the same, in sim time. ``timeout_s`` bounds (wall time) the
    leading rover's run, ``start_timeout_s`` each robot process's start (its
    ``running`` line; a process that ends first fails at once)."""
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; there are {', '.join(SCENARIOS)}")
    tour = scenario == "follow"
    world = load_world(FOLLOW_WORLD if tour else WORLD)
    rover_config = TOUR_CONFIG if tour else ROVER_CONFIG
    other, other_config = ("rover2", FOLLOWER_CONFIG) if tour else ("copter1", COPTER_CONFIG)
    rover_cfg = yaml.safe_load(rover_config.read_text(encoding="utf-8"))
    other_cfg = yaml.safe_load(other_config.read_text(encoding="utf-8"))
    rover_params = rover_cfg["behaviors"]["droid"]["params"]
    waypoints = rover_params["waypoints"]
    follow = other_cfg["behaviors"]["droid"]["params"]
    distance_m, safety_m = float(follow["distance_m"]), float(follow["safety_m"])
    # Real time while the robots' processes start (nothing to simulate yet; with --fast
    # the physics would run minutes ahead and take the CPU they start on), then --fast.
    sim = Simulation(world, real_time_factor=1.0)
    ports = dict(zip(("rover1", other), free_udp_ports(2), strict=True))
    endpoints = {name: MavlinkEndpoint(sim, name, url=f"udpout:127.0.0.1:{port}",
                                       system_id=i + 1)
                 for i, (name, port) in enumerate(ports.items())}
    rover, follower = sim.robot("rover1"), sim.robot(other)
    trace = Trace()

    def sample(time_s: float) -> None:
        r = rover.pose()
        c = follower.position() if isinstance(follower, Quad) else follower.pose()
        z_m = c.z_m if isinstance(follower, Quad) else 0.0  # type: ignore[union-attr]
        trace.gaps.append((time_s, math.hypot(r.x_m - c.x_m, r.y_m - c.y_m)))
        trace.copter_points.append((c.x_m, c.y_m, z_m))
        if trace.rtl_at_s == math.inf and endpoints["rover1"].mode == "RTL":
            trace.rtl_at_s = time_s
        if trace.auto_at_s == math.inf and endpoints[other].mode == "AUTO":
            trace.auto_at_s = time_s
        if trace.airborne_at_s == math.inf and z_m > 1.5:
            trace.airborne_at_s = time_s
        if trace.tour_at_s == math.inf and endpoints["rover1"].mode == "AUTO":
            trace.tour_at_s = time_s

    sim.on_step(sample, rate_hz=SAMPLE_HZ)
    # /clock for the robots (they run on sim time) and the lockstep gate their control
    # loops hold the physics with.
    ros = RosContext()
    try:
        node = SimNode(sim, ros)
    except BaseException:
        ros.shutdown()
        raise
    ros.start()
    sim.start()
    procs: list[_Process] = []
    measured: dict[str, Any] = {"scenario": scenario, "fast": fast}
    wall_start = time.monotonic()
    try:
        with tempfile.TemporaryDirectory(prefix="beehave-droid-") as folder:
            rover_config = _variant(rover_config, Path(folder))
            # handover: the copter waits on its pad, no following.
            other_config = _variant(other_config, Path(folder),
                                    **({"follow": None} if scenario == "handover" else {}))

            def launch(name: str, config: Path) -> _Process:
                proc = _Process(name, [str(config), "--connection",
                                       f"udp:127.0.0.1:{ports[name]}"])
                procs.append(proc)
                if not proc.wait_line(f"droid {name}: running", start_timeout_s):
                    raise RuntimeError(f"the robot of {name} did not start:\n"
                                       + "\n".join(proc.log[-30:]))
                return proc

            launch(other, other_config)
            # The rover's robot starts while the other one gets ready (the copter takes off).
            rover_proc = launch("rover1", rover_config)
            if fast:
                sim.real_time_factor = FAST_FACTOR
            rover_proc.wait_line("RESULT ", timeout_s)
            measured["rover_result"] = rover_proc.result
            # A helper informs the rover when it is done, so the rover's RESULT comes last;
            # a follower gets a moment (sim time) to close up behind the leader that stopped.
            if tour:
                settled_s, wall_limit = sim.time_s + SETTLE_S, time.monotonic() + 60.0
                while sim.time_s < settled_s and sim.state is SimState.RUNNING \
                        and time.monotonic() < wall_limit:
                    time.sleep(0.02)
            end_s = sim.time_s
    finally:
        for proc in procs:
            proc.stop()
        sim.stop()
        node.destroy()
        ros.shutdown()
        for endpoint in endpoints.values():
            endpoint.close()
    measured["wall_s"] = time.monotonic() - wall_start
    # Why a follower fell behind, when it did: controllers the simulation stopped waiting
    # for, and periods that went on with a leader state that stayed old.
    measured["lockstep_dropped"] = dict(node.dropped)
    measured["went_on_stale"] = sum("going on with one" in line
                                    for proc in procs for line in proc.log)
    if verbose:
        for proc in procs:
            lines = [line for line in proc.log if "watchdog" not in line]
            print(f"---- {proc.name}", *lines[-60:], sep="\n")
    result = (measured.get("rover_result") or {}).get("result") or {}
    checks: list[Check] = []
    home = world.robots[0].start
    rover_end = rover.pose()
    home_m = math.hypot(rover_end.x_m - home.x_m, rover_end.y_m - home.y_m)
    if tour:
        # [north, east] → world (x, y); the closest the leader came to each waypoint.
        misses = [min((math.hypot(x - float(w[1]), y - float(w[0])) for x, y in rover.path()),
                      default=math.inf) for w in waypoints]
        checks.append(Check(
            f"the leader drove its whole tour ({len(waypoints)} waypoints)",
            result.get("status") == "completed" and max(misses) <= 0.5
            and endpoints["rover1"].reached == list(range(1, len(waypoints) + 1)),
            f"{result.get('status')}; farthest miss {max(misses):.2f} m, vehicle reached "
            f"items {endpoints['rover1'].reached}"))
        gap_checks, min_gap = _gap_checks(
            trace.gaps, start_s=trace.tour_at_s, band_end_s=end_s, safety_end_s=math.inf,
            distance_m=distance_m, safety_m=safety_m, who="rover2")
        checks += gap_checks
        widest = max(((g, t) for t, g in trace.gaps if t >= trace.tour_at_s),
                     default=(math.nan, math.nan))
        measured.update({"min_gap_m": min_gap, "misses_m": misses,
                         "widest_gap": {"m": widest[0], "at_s": widest[1],
                                        "tour_at_s": trace.tour_at_s, "end_s": end_s}})
    else:
        remaining = [(float(w["east_m"]), float(w["north_m"]), float(w["alt_m"]))
                     for w in result.get("remaining") or []]
        # The closest the copter came (3-D) to each remaining waypoint, in the physics.
        misses = [min((math.dist(p, w) for p in trace.copter_points), default=math.inf)
                  for w in remaining]
        checks += [
            Check("the rover handed its remaining mission over",
                  result.get("status") == "handed-over" and result.get("awardee") == "copter1",
                  f"{result.get('status')} to {result.get('awardee')}"),
            Check(f"the copter reached every remaining waypoint ({len(remaining)})",
                  bool(remaining) and max(misses) <= 0.8
                  and endpoints["copter1"].reached == list(range(1, len(remaining) + 1)),
                  f"farthest miss {max(misses, default=math.inf):.2f} m (3-D), vehicle "
                  f"reached items {endpoints['copter1'].reached}"),
            Check("the rover is home", home_m <= 0.5, f"{home_m:.2f} m from its start"),
        ]
        measured.update({"misses_m": misses})
        if scenario == "droid":
            # Following: from the copter's take-off until it starts the handed-over mission.
            # The gap band applies until the rover turns home (it then drives towards its
            # follower, which backs off: the gap dips below d by design, never below the
            # safety distance).
            gap_checks, min_gap = _gap_checks(
                trace.gaps, start_s=trace.airborne_at_s, band_end_s=trace.rtl_at_s,
                safety_end_s=trace.auto_at_s, distance_m=distance_m, safety_m=safety_m,
                who="the copter")
            checks += gap_checks
            measured["min_gap_m"] = min_gap
    measured.update({"home_m": home_m, "sim_time_s": sim.time_s})
    if picture is not None:
        start = world.robots[0].start
        planned = [[(start.x_m, start.y_m)] + [(float(w[1]), float(w[0])) for w in waypoints]]
        sim.render_topdown(picture, planned=planned)
    sim.close()
    return checks, measured


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m behaviours.demos.droid",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", choices=SCENARIOS, default="droid",
                        help="follow: a rover leads a tour, another follows; handover: a "
                             "rover meets a wall, the quadrotor finishes its mission; "
                             "droid (default): both at once")
    parser.add_argument("--picture", type=Path, default=None)
    parser.add_argument("--fast", action="store_true",
                        help="the physics as fast as the robots keep up (lockstep), not at "
                             "real time; the same checks, in sim time")
    parser.add_argument("--timeout-s", type=float, default=150.0)
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    checks, measured = run(scenario=args.scenario, timeout_s=args.timeout_s,
                           picture=args.picture, verbose=args.verbose, fast=args.fast)
    width = max(len(c.name) for c in checks)
    print(f"{'check'.ljust(width)}  result  measured")
    for c in checks:
        print(f"{c.name.ljust(width)}  {'PASS' if c.passed else 'FAIL':6}  {c.measured}")
    print(f"(sim time {measured['sim_time_s']:.1f} s in {measured['wall_s']:.1f} s of wall "
          f"time{', --fast' if args.fast else ''})")
    if args.picture is not None:
        print(f"picture: {args.picture}")
    return 0 if all(c.passed for c in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
