"""Ready-made actions for the simulated (and real) EMILI and Kobuki, over ROS 2.

They talk to the robot through the topics of :mod:`robots.topics`, relative to the robot's
namespace (the high-level node's), using ``self.ros``; everything they create is destroyed
when they end. Control loops run at ``rate_hz`` on the manager's clock (sim time under
``use_sim_time``).

=================  ============  =========================================================
action             action_type   safe state
=================  ============  =========================================================
Navigation         driving       zero velocity
LaneFollowing      driving       zero velocity
Lift               lifting       hold the height it has now
PlaySound          sound         —
=================  ============  =========================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Float64, String

from beehave import Action
from beehave.errors import BeehaveError
from robots import topics


class NavigationError(BeehaveError):
    """Navigation could not reach its goal (blocked for too long, no odometry …)."""


class LaneLost(BeehaveError):
    """Lane following lost the tape for longer than it may."""


class LiftError(BeehaveError):
    """The lift did not reach its target."""


@dataclass(frozen=True)
class Goal:
    x_m: float
    y_m: float
    name: str = ""


def resolve_goal(goal: Goal | tuple[float, float] | str, world: str | None) -> Goal:
    """A goal from coordinates, or from a station name in a world (by name or path)."""
    if isinstance(goal, Goal):
        return goal
    if isinstance(goal, str):
        if world is None:
            raise BeehaveError(f"goal {goal!r} is a station name: pass world= (a world name "
                               "or YAML path) to look it up")
        from robots.world import load_world

        station = load_world(world).station(goal)  # UnknownStation lists the names
        return Goal(*station.center_m, name=goal)
    if (isinstance(goal, (tuple, list)) and len(goal) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                    and math.isfinite(v) for v in goal)):
        return Goal(float(goal[0]), float(goal[1]))
    raise BeehaveError(f"goal must be (x_m, y_m) with finite numbers, a station name or a "
                       f"Goal, got {goal!r}")


def yaw_of(odom: Odometry) -> float:
    q = odom.pose.pose.orientation
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi


def sector_min(scan: LaserScan, center_rad: float, half_width_rad: float) -> float:
    """The nearest hit within ±``half_width_rad`` of ``center_rad`` (robot frame)."""
    best = math.inf
    angle = scan.angle_min
    for r in scan.ranges:
        if abs(_wrap(angle - center_rad)) <= half_width_rad and scan.range_min <= r < best:
            best = r
        angle += scan.angle_increment
    return best


def twist(linear_mps: float = 0.0, angular_rps: float = 0.0) -> Twist:
    msg = Twist()
    msg.linear.x = float(linear_mps)
    msg.angular.z = float(angular_rps)
    return msg


class _Drive(Action):
    """Shared by the driving actions: a cmd_vel publisher, odometry, zero velocity as the
    safe state."""

    action_type = "driving"
    rate_hz = 20.0
    _cmd: Any = None

    def _open(self) -> None:
        self._cmd = self.ros.publisher(Twist, topics.CMD_VEL)
        self.odom = self.ros.latest(Odometry, topics.ODOM)

    def command(self, linear_mps: float, angular_rps: float) -> None:
        self._cmd.publish(twist(linear_mps, angular_rps))

    def safe_state(self) -> None:
        if self._cmd is not None:
            self._cmd.publish(twist())


class Navigation(_Drive):
    """Drive to a point or a named station, laser-based: slow down inside
    ``slow_distance_m`` and stop inside ``stop_distance_m`` of an obstacle ahead (distances
    from the robot's centre, in a ±``field_half_angle_rad`` field); wait while blocked,
    fail after ``blocked_timeout_s``. Returns the final ``(x_m, y_m)``.
    """

    def __init__(self, goal: Goal | tuple[float, float] | str, *, world: str | None = None,
                 speed_mps: float = 0.5, tolerance_m: float = 0.15,
                 stop_distance_m: float = 0.75, slow_distance_m: float = 1.5,
                 field_half_angle_rad: float = 0.5, blocked_timeout_s: float = 30.0,
                 timeout_s: float = 300.0) -> None:
        self.goal = resolve_goal(goal, world)
        if speed_mps <= 0 or tolerance_m <= 0:
            raise BeehaveError("speed_mps and tolerance_m must be positive")
        self.speed_mps, self.tolerance_m = speed_mps, tolerance_m
        self.stop_distance_m, self.slow_distance_m = stop_distance_m, slow_distance_m
        self.field_half_angle_rad = field_half_angle_rad
        self.blocked_timeout_s, self.timeout_s = blocked_timeout_s, timeout_s
        self.name = f"Navigation→{self.goal.name or f'({self.goal.x_m:g}, {self.goal.y_m:g})'}"
        self.blocked = False

    def run(self) -> tuple[float, float]:
        self._open()
        scan = self.ros.latest(LaserScan, topics.SCAN)
        odom = self.odom.wait_for(timeout_s=10.0)
        clock = self.manager.clock
        start = clock.now()
        blocked_since: float | None = None
        period = 1.0 / self.rate_hz
        while not self.interrupted:
            odom = self.odom.get() or odom
            p = odom.pose.pose.position
            dx, dy = self.goal.x_m - p.x, self.goal.y_m - p.y
            dist = math.hypot(dx, dy)
            if dist <= self.tolerance_m:
                self.command(0.0, 0.0)
                return (p.x, p.y)
            heading_err = _wrap(math.atan2(dy, dx) - yaw_of(odom))
            angular = max(-1.2, min(1.2, 2.0 * heading_err))
            linear = min(self.speed_mps, 0.8 * dist) * max(0.0, math.cos(heading_err)) ** 2
            if abs(heading_err) > 0.8:
                linear = 0.0  # turn on the spot first
            nearest = math.inf
            last = scan.get()
            if last is not None:
                nearest = sector_min(last, 0.0, self.field_half_angle_rad)
            if nearest < self.stop_distance_m and linear > 0:
                linear = 0.0
                angular = 0.0 if abs(heading_err) < 0.8 else angular
                if blocked_since is None:
                    blocked_since = clock.now()
                elif clock.now() - blocked_since > self.blocked_timeout_s:
                    self.command(0.0, 0.0)
                    raise NavigationError(
                        f"{self.name}: blocked by an obstacle {nearest:.2f} m ahead for "
                        f"{self.blocked_timeout_s} s at ({p.x:.2f}, {p.y:.2f})")
                self.blocked = True
            else:
                blocked_since = None
                self.blocked = False
                if nearest < self.slow_distance_m:
                    scale = (nearest - self.stop_distance_m) / (
                        self.slow_distance_m - self.stop_distance_m)
                    linear *= max(0.2, min(1.0, scale))
            self.command(linear, angular)
            if clock.now() - start > self.timeout_s:
                raise NavigationError(f"{self.name}: not there after {self.timeout_s} s "
                                      f"({dist:.2f} m to go)")
            self.sleep(period)
        p = odom.pose.pose.position
        return (p.x, p.y)


class LaneFollowing(_Drive):
    """Follow the lane tape under the robot with the line sensor (EMILI) for
    ``distance_m`` of travel, or until ``until`` (a goal or station) is within
    ``tolerance_m``. Slows down where the tape bends; raises :class:`LaneLost` when no tape
    was seen for ``lost_timeout_s``. Returns the distance travelled (m).

    ``max_abs_offset_m`` records the largest lateral error seen after the first
    ``settle_m`` metres (for tests and reports).
    """

    def __init__(self, *, distance_m: float | None = None,
                 until: Goal | tuple[float, float] | str | None = None,
                 world: str | None = None, speed_mps: float = 0.3, gain: float = 8.0,
                 tolerance_m: float = 0.3, lost_timeout_s: float = 1.0,
                 settle_m: float = 0.5) -> None:
        if distance_m is None and until is None:
            raise BeehaveError("LaneFollowing needs distance_m or until=")
        self.distance_m = distance_m
        self.until = None if until is None else resolve_goal(until, world)
        self.speed_mps, self.gain, self.tolerance_m = speed_mps, gain, tolerance_m
        self.lost_timeout_s, self.settle_m = lost_timeout_s, settle_m
        self.max_abs_offset_m = 0.0

    def run(self) -> float:
        self._open()
        line = self.ros.latest(Float64, topics.LINE_SENSOR)
        odom = self.odom.wait_for(timeout_s=10.0)
        clock = self.manager.clock
        travelled = 0.0
        last_xy = (odom.pose.pose.position.x, odom.pose.pose.position.y)
        lost_since: float | None = None
        while not self.interrupted:
            odom = self.odom.get() or odom
            p = odom.pose.pose.position
            travelled += math.hypot(p.x - last_xy[0], p.y - last_xy[1])
            last_xy = (p.x, p.y)
            if self.distance_m is not None and travelled >= self.distance_m:
                break
            if self.until is not None and math.hypot(self.until.x_m - p.x,
                                                     self.until.y_m - p.y) <= self.tolerance_m:
                break
            reading = line.get()
            offset = None if reading is None or math.isnan(reading.data) else reading.data
            if offset is None:
                lost_since = clock.now() if lost_since is None else lost_since
                if clock.now() - lost_since > self.lost_timeout_s:
                    self.command(0.0, 0.0)
                    raise LaneLost(f"no lane tape seen for {self.lost_timeout_s} s at "
                                   f"({p.x:.2f}, {p.y:.2f})")
                self.command(0.05, 0.0)  # creep: the tape may come back
            else:
                lost_since = None
                if travelled > self.settle_m:
                    self.max_abs_offset_m = max(self.max_abs_offset_m, abs(offset))
                angular = max(-1.5, min(1.5, self.gain * offset))
                linear = self.speed_mps / (1.0 + 6.0 * abs(offset) / 0.05)
                self.command(max(0.08, linear), angular)
            self.sleep(1.0 / self.rate_hz)
        self.command(0.0, 0.0)
        return travelled


class Lift(Action):
    """Move EMILI's scissor lift to ``height_m`` (0–0.3 m); returns the height reached.
    Safe state: hold the height it has now."""

    action_type = "lifting"

    def __init__(self, height_m: float, *, tolerance_m: float = 0.005,
                 timeout_s: float = 20.0) -> None:
        if not 0.0 <= height_m <= 0.3:
            raise LiftError(f"lift height {height_m} m is outside 0–0.3 m")
        self.height_m, self.tolerance_m, self.timeout_s = height_m, tolerance_m, timeout_s
        self.name = f"Lift→{height_m:g}m"
        self._cmd: Any = None
        self._state: Any = None

    def run(self) -> float:
        self._cmd = self.ros.publisher(Float64, topics.LIFT_COMMAND)
        self._state = self.ros.latest(Float64, topics.LIFT_STATE)
        self._state.wait_for(timeout_s=10.0)
        self._cmd.publish(Float64(data=float(self.height_m)))
        try:
            reached = self._state.wait_for(
                lambda m: abs(m.data - self.height_m) <= self.tolerance_m,
                timeout_s=self.timeout_s)
        except TimeoutError as exc:
            now = self._state.get()
            raise LiftError(f"lift did not reach {self.height_m} m within {self.timeout_s} s "
                            f"(at {now.data if now else float('nan'):.3f} m)") from exc
        return float(reached.data)

    def safe_state(self) -> None:
        state = None if self._state is None else self._state.get()
        if self._cmd is not None and state is not None:
            self._cmd.publish(Float64(data=float(state.data)))  # hold where it is


class PlaySound(Action):
    """Play ``name`` ``times`` times, ``interval_s`` apart."""

    action_type = "sound"

    def __init__(self, name: str, *, times: int = 1, interval_s: float = 1.0) -> None:
        self.sound, self.times, self.interval_s = name, times, interval_s
        self.name = f"PlaySound:{name}"

    def run(self) -> int:
        pub = self.ros.publisher(String, topics.SOUND)
        played = 0
        for i in range(self.times):
            if i and not self.sleep(self.interval_s):
                break
            pub.publish(String(data=self.sound))
            played += 1
        return played
