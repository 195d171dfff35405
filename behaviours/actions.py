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

import functools
import json
import logging
import math
import threading
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Float64, String

from beehave import Action, Status
from beehave.clock import SimClock
from beehave.errors import BeehaveError, NoPath
from beehave.events import Event, EventKind
from beehave.planning import (
    Disc,
    GridPlanner,
    OccupancyMap,
    PlannedPath,
    SeenObstacles,
    path_length_m,
)
from beehave.ros.io import Latest, WaitTimeout, node_publisher
from beehave.runnable import Runnable
from robots import topics

log = logging.getLogger(__name__)


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


@dataclass(frozen=True)
class Via:
    """A point :class:`Navigation` drives through without stopping, before its goal (a
    VDA 5050 node without actions): passed once the robot comes within ``tolerance_m``;
    ``speed_mps`` is the speed of the leg that ends here (None: Navigation's
    ``speed_mps``)."""

    x_m: float
    y_m: float
    tolerance_m: float = 0.15
    speed_mps: float | None = None
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


def first_message(latest: Latest[Any], *, timeout_s: float = 10.0) -> Any:
    """The first message of a subscription just made (``self.ros.latest``). Finding the
    publisher (DDS discovery) takes wall time, which at full simulation speed is many
    seconds of sim time: give up only when ``timeout_s`` has passed on both the manager's
    clock and the wall clock. Raises :class:`~beehave.ros.io.WaitTimeout`."""
    wall_deadline = time.monotonic() + timeout_s
    while True:
        try:
            return latest.wait_for(timeout_s=timeout_s)
        except WaitTimeout:
            if time.monotonic() >= wall_deadline:
                raise


class LockstepLine:
    """One node's ``/lockstep`` publisher, shared by all the driving actions of that node.

    Made on first use and kept for the node's life (``destroy_node`` destroys it with the
    node's other entities): a publisher made per action is new to DDS each time, and the
    simulator does not hear its first announcements until discovery has matched it — the
    robot then drives that long without being held.
    """

    MATCH_TIMEOUT_S = topics.LOCKSTEP_TIMEOUT_S
    """Wall seconds a new line waits for the simulator's subscription (no lockstep
    subscriber, e.g. ``beehave sim --no-lockstep``: each action waits this long only until
    the line is this old)."""

    _lines: weakref.WeakKeyDictionary[Any, LockstepLine] = weakref.WeakKeyDictionary()
    _lines_lock = threading.Lock()

    def __init__(self, node: Any) -> None:
        self.publisher = node_publisher(node, String, topics.LOCKSTEP)  # the node's own
        self.node_name = node.get_fully_qualified_name()
        self.made_s = time.monotonic()

    def announce(self, runnable: Runnable, until_s: float | None, *,
                 stop: str | None = None) -> None:
        """Hold the simulation for ``runnable`` at sim time ``until_s`` (None: let go;
        ``stop``, a ``cmd_vel`` topic the simulator zeroes as it lets go). A STUCK
        runnable lets go: one that ignores its interrupt must not keep holding it."""
        if runnable.status is Status.STUCK:
            until_s = None
        announcement: dict[str, Any] = {
            "participant": f"{self.node_name}/{runnable.path}#{id(runnable):x}",
            "until_s": until_s}
        if until_s is None and stop is not None:
            announcement["stop"] = stop
        self.publisher.publish(String(data=json.dumps(announcement)))

    @classmethod
    def of(cls, node: Any) -> LockstepLine:
        with cls._lines_lock:
            line = cls._lines.get(node)
            if line is None:
                line = cls._lines[node] = cls(node)
            return line

    def wait_matched(self, interrupted: Callable[[], bool]) -> bool:
        """Wait (wall time, at most until the line is :attr:`MATCH_TIMEOUT_S` old) until
        the simulator subscribes; True once it has."""
        # rclpy has no portable "matched" event: poll the graph, briefly.
        while self.publisher.get_subscription_count() < 1:
            if interrupted() or time.monotonic() - self.made_s > self.MATCH_TIMEOUT_S:
                return False
            time.sleep(0.005)
        return True


@contextmanager
def lockstep_sleeps(runnable: Runnable) -> Iterator[Callable[[float], bool]]:
    """Yields a ``sleep(seconds) -> bool`` for ``runnable`` (a behaviour or action whose
    timed steps matter beside driving: a chime every 2 s) that holds a simulation in
    lockstep where each sleep ends, until the runnable sleeps again or leaves the block,
    as :class:`DriveBase` does for control periods. On wall time (no :class:`SimClock`) or
    without a node it is ``runnable.sleep``; on sim time it announces its holds whether or
    not a simulator listens (its first use waits up to :attr:`LockstepLine.MATCH_TIMEOUT_S`
    of wall time for one, as a driving action's does).

    Without it a simulation at ``--fast`` runs on while a starved thread has not woken
    yet: live the step then comes late in sim time (a chime after the drive it should have
    sounded during), and a replay of the recording, which runs it on time, diverges."""
    manager = runnable.manager
    clock, node = manager.clock, manager.node
    if not isinstance(clock, SimClock) or node is None:
        yield runnable.sleep
        return
    line = LockstepLine.of(node)
    line.wait_matched(lambda: runnable.interrupted)

    def hold(until_s: float | None) -> None:
        line.announce(runnable, until_s)

    def sleep(seconds: float) -> bool:
        if not math.isfinite(seconds):
            hold(None)  # no end to hold at: the last hold must not stand
        with clock.announcing(hold):
            return runnable.sleep(seconds)

    def on_event(event: Event) -> None:
        # A pause freezes this runnable's time (and may hold it in a start_action): the
        # simulation, and every other robot in it, must not wait for it meanwhile. After
        # the resume its sleep announces its deadline again.
        if event.kind is EventKind.PAUSE_REQUESTED:
            try:
                hold(None)
            except Exception:
                log.debug("%s: could not let the simulation go", runnable.name,
                          exc_info=True)

    unsubscribe = manager.subscribe(on_event)
    try:
        yield sleep
    finally:
        unsubscribe()
        try:
            hold(None)
        except Exception:  # the node is gone: the simulator's lockstep timeout lets go
            log.debug("%s: could not let the simulation go", runnable.name, exc_info=True)


class SpeedLimit:
    """The robot's maximum speed: the ``max_speed_mps`` parameter of its high-level node
    (m/s, > 0; ``inf`` — the default — means no limit besides each action's own speed).

    Every driving action clamps its linear velocity to it at every command, so changing the
    parameter while a robot drives slows it at once: what seed paper 000's dynamic request
    controller does for speed zones, and what ``ros2 param set /atv1/beehave_high_level
    max_speed_mps 0.2`` does from a terminal. Declared on a node the first time a driving
    action runs there (or :meth:`of` is called); a value that is not a number > 0 is
    refused with the reason.
    """

    PARAM = "max_speed_mps"
    _limits: weakref.WeakKeyDictionary[Any, SpeedLimit] = weakref.WeakKeyDictionary()
    _limits_lock = threading.Lock()

    def __init__(self, node: Any) -> None:
        from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult

        self.node = node
        if not node.has_parameter(self.PARAM):
            node.declare_parameter(self.PARAM, math.inf, ParameterDescriptor(
                description="maximum linear speed of every driving action (m/s, > 0; inf: "
                            "no limit) — speed zones set it"))

        def check(params: list[Any]) -> Any:
            for param in params:
                if param.name != self.PARAM:
                    continue
                value = param.value
                if isinstance(value, bool) or not isinstance(value, float) or not value > 0:
                    return SetParametersResult(
                        successful=False,
                        reason=f"{self.PARAM} must be a float > 0 (m/s; inf: no limit), "
                               f"got {value!r}")
            return SetParametersResult(successful=True)

        self._check = check  # rclpy identifies the callback by the function: keep it
        node.add_on_set_parameters_callback(check)

    @classmethod
    def of(cls, node: Any) -> SpeedLimit:
        with cls._limits_lock:
            limit = cls._limits.get(node)
            if limit is None:
                limit = cls._limits[node] = cls(node)
            return limit

    @property
    def mps(self) -> float:
        value = self.node.get_parameter(self.PARAM).value
        return float(value) if isinstance(value, float) and value > 0 else math.inf


def prepare_driving(node: Any) -> None:
    """Make ``node``'s shared driving entities now — its ``/lockstep`` line (whose first
    use waits for the simulator's subscription) and its :class:`SpeedLimit` parameter — so
    the first driving action does not wait for them (e.g. when a robot is set up)."""
    LockstepLine.of(node)
    SpeedLimit.of(node)


def twist(linear_mps: float = 0.0, angular_rps: float = 0.0) -> Twist:
    msg = Twist()
    msg.linear.x = float(linear_mps)
    msg.angular.z = float(angular_rps)
    return msg


class DriveBase(Action):
    """Shared by the driving actions: a cmd_vel publisher, odometry, zero velocity as the
    safe state, and lockstep with a simulator.

    Subclasses write :meth:`drive` (not ``run``) and pace their loop with :meth:`tick`.
    Under sim time (a :class:`~beehave.clock.SimClock`) every ``tick`` asks the simulator,
    on ``/lockstep``, to hold at the sim time the tick ends until this action has answered
    again, so a simulation running faster than real time never outruns the control loop
    (``docs/simulation.md``, "Lockstep"). When ``drive`` ends, however it ends, the robot
    is commanded to stand still and the simulator is let go — in that order, so the stop
    reaches the robot before the simulation runs on.
    """

    action_type = "driving"
    rate_hz = 20.0
    uses_odometry = True
    _cmd: Any = None
    _lockstep: LockstepLine | None = None
    _cmd_topic: str = ""
    _limit: SpeedLimit | None = None

    def run(self) -> Any:
        self._open()
        try:
            result = self.drive()
        except BaseException as exc:
            self._stop(failed_with=exc)
            raise
        self._stop(failed_with=None)
        return result

    def _stop(self, *, failed_with: BaseException | None) -> None:
        """Command zero velocity, then let the simulator go. A stop that fails after the
        drive succeeded fails the action (the robot may still move: its safe state tries
        again); after the drive failed, the drive's error stays the one reported, with the
        stop's failure noted on it — the first cause is what the user must see."""
        try:
            self.command(0.0, 0.0)
            if self._lockstep is not None and failed_with is None and not self.interrupted:
                # Held one more period: the zero command travels on another topic than the
                # release, and a simulator let go first would run on at the old speed
                # until it arrives (0.3 m past the goal at full speed on a loaded host).
                self.tick()
        except Exception as stop_error:
            if failed_with is None:
                raise
            failed_with.add_note(f"{self.name}: commanding zero velocity afterwards failed "
                                 f"too: {stop_error!r}")
        finally:
            self._let_go()

    def drive(self) -> Any:
        """The control loop (runs in the action's thread); pace it with :meth:`tick`."""
        raise NotImplementedError

    def _open(self) -> None:
        node = self.manager.node
        self._limit = SpeedLimit.of(node) if node is not None else None
        self._cmd = self.ros.publisher(Twist, topics.CMD_VEL, shared=True)
        if self.uses_odometry:
            self.odom = self.ros.latest(Odometry, topics.ODOM)
        clock = self.manager.clock
        node = self.manager.node
        if isinstance(clock, SimClock) and node is not None:
            line = LockstepLine.of(node)
            self._cmd_topic = node.resolve_topic_name(topics.CMD_VEL)
            self._lockstep = line
            # Held before the first command: the sim may not run past the first period
            # until this action has spoken again.
            line.wait_matched(lambda: self.interrupted)
            self._hold_at(clock.now() + 1.0 / self.rate_hz)

    def tick(self) -> bool:
        """Sleep one control period (``1 / rate_hz`` on the manager's clock); False when
        interrupted. In lockstep the simulator holds where the period ends until the next
        command or the release."""
        clock = self.manager.clock
        if self._lockstep is None or not isinstance(clock, SimClock):
            return self.sleep(1.0 / self.rate_hz)
        with clock.announcing(self._hold_at):
            return self.sleep(1.0 / self.rate_hz)

    def _hold_at(self, until_s: float | None) -> None:
        # (STUCK: its own publishers are destroyed, not the node's shared line, which
        # lets go for it.) Released at the end of a drive, the simulator stops the wheels
        # as it lets go: the zero command went out first, but on cmd_vel, and nothing
        # orders two topics: a release that overtook it let the sim run on the old command.
        if self._lockstep is not None:
            self._lockstep.announce(self, until_s, stop=self._cmd_topic)

    def _let_go(self) -> None:
        try:
            self._hold_at(None)
        except Exception:
            # The node's publisher is gone (the node or its ROS context was shut down under
            # us): the sim node's lockstep timeout lets the simulation go in our place.
            log.debug("%s: could not let the simulation go", self.name, exc_info=True)
        self._lockstep = None  # the line stays with the node, for the next action

    def command(self, linear_mps: float, angular_rps: float) -> None:
        """Command the base, the linear speed clamped to the robot's :class:`SpeedLimit`."""
        if self._cmd is not None:
            limit = self._limit.mps if self._limit is not None else math.inf
            self._cmd.publish(twist(max(-limit, min(limit, linear_mps)), angular_rps))

    def safe_state(self) -> None:
        if self._cmd is not None:
            self._cmd.publish(twist())


@functools.lru_cache(maxsize=16)
def world_planner(world: str, robot_radius_m: float, clearance_m: float) -> GridPlanner:
    """The planner for a world (name or YAML path) and robot size; built once per process
    (tens of milliseconds), then shared — planners are never modified."""
    from robots.world import load_world, occupancy_map

    return GridPlanner(occupancy_map(load_world(world)), robot_radius_m=robot_radius_m,
                       clearance_m=clearance_m)


class Navigation(DriveBase):
    """Drive to a point or a named station along a planned path, with a laser safety field.

    With a map — ``world`` (a world name or YAML path) or ``occupancy`` (a
    :class:`~beehave.planning.OccupancyMap`) — a :class:`~beehave.planning.GridPlanner`
    plans around the known obstacles with ``robot_radius_m`` (circumscribed: EMILI turns on
    the spot) plus ``clearance_m``, and the robot follows the waypoints; without one it
    drives straight at the goal. ``planned`` is the current plan (None without a map).

    Safety field: slow down inside ``slow_distance_m`` and stop inside ``stop_distance_m``
    of an obstacle ahead (distances from the robot's centre, in a ±``field_half_angle_rad``
    field). When blocked for ``replan_after_s`` with a map, what the laser sees ahead is
    added to the map as obstacles and the path is planned again from where the robot
    stands (``replans`` counts it); it waits while no way around exists, and fails after
    ``blocked_timeout_s`` without progress. ``seen`` (a
    :class:`~beehave.planning.SeenObstacles`) holds those laser hits, one per map cell; a
    hit not seen again for ``forget_obstacles_after_s`` is forgotten.

    It succeeds once the robot stands within ``tolerance_m`` of the goal it was given,
    and returns the final ``(x_m, y_m)``. A goal inside the inflation (a station that hugs
    a shelf) is approached at the nearest free point, which must lie within
    ``tolerance_m`` of it (less :attr:`end_precision_m`); otherwise the action fails with
    :class:`~beehave.errors.NoPath` saying so.

    ``initial_path``: a plan already made for this leg (on the same map, robot size and
    clearance, e.g. when an order was checked), followed from the start instead of planning
    again — only when the robot stands within ``tolerance_m`` of its first waypoint and it
    ends within ``tolerance_m`` less :attr:`end_precision_m` of the goal; otherwise the
    leg is planned from where the robot stands, as without it. Re-planning when blocked is
    unchanged.

    ``via``: points (:class:`Via`) to drive through, in order, before the goal, without
    slowing down for them: the robot slows only for the goal. Each leg is straight where
    the map lets it, planned otherwise (re-planning when blocked goes through the vias not
    passed yet); each is driven at its via's ``speed_mps``, the last one at ``speed_mps``.
    ``on_via(i)`` is called (in the action's thread) when ``via[i]`` is passed;
    ``initial_path`` is then the plan of the first leg, to ``via[0]``. A corner sharper
    than :attr:`TURN_ON_SPOT_RAD` still turns on the spot.
    """

    TURN_ON_SPOT_RAD = 0.8
    """Heading error (rad) beyond which the robot stops and turns on the spot…"""
    ALIGNED_RAD = 0.25
    """…until the error is below this; then it drives (and steers) again."""

    def __init__(self, goal: Goal | tuple[float, float] | str, *, world: str | None = None,
                 occupancy: OccupancyMap | None = None,
                 speed_mps: float = 0.5, tolerance_m: float = 0.15,
                 stop_distance_m: float = 0.75, slow_distance_m: float = 1.5,
                 field_half_angle_rad: float = 0.5, blocked_timeout_s: float = 30.0,
                 replan_after_s: float = 3.0, robot_radius_m: float = 0.55,
                 clearance_m: float = 0.1, waypoint_tolerance_m: float = 0.3,
                 forget_obstacles_after_s: float = 60.0, timeout_s: float = 300.0,
                 initial_path: PlannedPath | None = None, via: Sequence[Via] = (),
                 on_via: Callable[[int], None] | None = None) -> None:
        self.goal = resolve_goal(goal, world)
        self.initial_path = initial_path
        if speed_mps <= 0 or tolerance_m <= 0:
            raise BeehaveError("speed_mps and tolerance_m must be positive")
        self.via = tuple(via)
        for i, point in enumerate(self.via):
            if not point.tolerance_m > 0 or not (point.speed_mps is None
                                                  or point.speed_mps > 0):
                raise BeehaveError(f"via[{i}] ({point.name or (point.x_m, point.y_m)}): "
                                   f"tolerance_m and speed_mps must be positive, got "
                                   f"{point.tolerance_m} and {point.speed_mps}")
        self.on_via = on_via
        #: How many of ``via`` the robot has passed.
        self.passed = 0
        self.speed_mps, self.tolerance_m = speed_mps, tolerance_m
        self.stop_distance_m, self.slow_distance_m = stop_distance_m, slow_distance_m
        self.field_half_angle_rad = field_half_angle_rad
        self.blocked_timeout_s, self.timeout_s = blocked_timeout_s, timeout_s
        self.replan_after_s, self.waypoint_tolerance_m = replan_after_s, waypoint_tolerance_m
        self.name = f"Navigation→{self.goal.name or f'({self.goal.x_m:g}, {self.goal.y_m:g})'}"
        self.blocked = False
        self.replans = 0
        self.planned: PlannedPath | None = None
        # Built here, not in run(): a bad map or robot size fails when the action is made.
        if occupancy is not None:
            self.planner: GridPlanner | None = GridPlanner(
                occupancy, robot_radius_m=robot_radius_m, clearance_m=clearance_m)
        elif world is not None:
            self.planner = world_planner(world, robot_radius_m, clearance_m)
        else:
            self.planner = None
        if not forget_obstacles_after_s > 0:
            raise BeehaveError(f"forget_obstacles_after_s must be positive (math.inf: never), "
                               f"got {forget_obstacles_after_s}")
        self.seen = SeenObstacles(
            cell_m=self.planner.resolution_m if self.planner is not None else 0.1,
            forget_after_s=forget_obstacles_after_s)

    @property
    def end_precision_m(self) -> float:
        """How close the robot drives to the end of its plan when that end is not the goal
        itself (a goal that hugs an obstacle): the plan ends at most ``tolerance_m -
        end_precision_m`` from the goal, so stopping there is within ``tolerance_m``."""
        return min(0.05, self.tolerance_m / 2)

    def _plan(self, planner: GridPlanner, x: float, y: float,
              first_leg: PlannedPath | None = None) -> list[tuple[float, float]]:
        """The waypoints from ``(x, y)`` through the vias not passed yet to the goal
        (``first_leg``: the plan of the first of those legs, already made); sets
        :attr:`planned` and, per waypoint, which via it is (:attr:`_marks`)."""
        targets: list[tuple[tuple[float, float], float, int | None]] = [
            ((v.x_m, v.y_m), v.tolerance_m, i) for i, v in enumerate(self.via)
            if i >= self.passed]
        # A goal that hugs an obstacle ends at the nearest reachable point rather than
        # fail — but only one close enough for the robot to stop within tolerance_m of the
        # goal it was given: success is always judged against that goal.
        targets.append(((self.goal.x_m, self.goal.y_m),
                        self.tolerance_m - self.end_precision_m, None))
        points: list[tuple[float, float]] = [(x, y)]
        marks: list[int | None] = []
        for leg, (target, tolerance, mark) in enumerate(targets):
            start = points[-1]
            if leg == 0 and first_leg is not None:
                legs = list(first_leg.waypoints_m[1:])
            elif leg > 0 and planner.segment_free(start, target):
                legs = [target]  # node to node in a straight line: no search needed
            else:
                try:
                    legs = list(planner.plan(start, target,
                                             goal_tolerance_m=tolerance).waypoints_m[1:])
                except NoPath as exc:
                    raise NoPath(f"{self.name}: {exc} (tolerance_m={self.tolerance_m:g} "
                                 f"less end_precision_m={self.end_precision_m:g})"
                                 if mark is None else f"{self.name}: via[{mark}]: {exc}"
                                 ) from exc
            points += legs
            marks += [None] * (len(legs) - 1) + [mark]
        self.planned = PlannedPath(tuple(points))
        self._marks = marks
        log.info("%s: planned %.1f m via %d waypoint(s)", self.name, self.planned.length_m,
                 len(points) - 2)
        return points[1:]

    _marks: list[int | None]

    def _pass_waypoint(self, marks: list[int | None]) -> None:
        """The first waypoint is reached: if it is a via, it is passed."""
        mark = marks.pop(0)
        if mark is not None:
            self.passed = mark + 1
            if self.on_via is not None:
                self.on_via(mark)

    def _leg_speed_mps(self, x: float, y: float) -> float:
        """The speed of the leg being driven; near the via just passed (within its
        tolerance, on either side of it) the slower of the two legs that meet there, so
        each leg's speed holds up to its end."""
        speed = (self.via[self.passed].speed_mps if self.passed < len(self.via)
                 else None) or self.speed_mps
        if self.passed:
            last = self.via[self.passed - 1]
            if math.hypot(last.x_m - x, last.y_m - y) <= last.tolerance_m:
                speed = min(speed, last.speed_mps or self.speed_mps)
        return speed

    def _reach_m(self, mark: int | None) -> float:
        """How close the robot must come to a waypoint to head for the next one."""
        if mark is None:
            return self.waypoint_tolerance_m
        return min(self.waypoint_tolerance_m, self.via[mark].tolerance_m)

    def _initial_path_fits(self, x: float, y: float) -> bool:
        """Whether :attr:`initial_path` may be followed from ``(x, y)`` (see the class)."""
        path = self.initial_path
        if path is None or len(path.waypoints_m) < 2:
            return False
        (sx, sy), (gx, gy) = path.waypoints_m[0], path.goal_m
        # With vias the initial path is the first leg's, to via[0].
        first = self.via[0] if self.via else self.goal
        fits = (math.hypot(sx - x, sy - y) <= self.tolerance_m
                and math.hypot(gx - first.x_m, gy - first.y_m)
                <= self.tolerance_m - self.end_precision_m + 1e-9)
        if not fits:
            log.info("%s: the initial path (%.2f, %.2f) → (%.2f, %.2f) does not start where "
                     "the robot stands (%.2f, %.2f) or end at the goal: planning again",
                     self.name, sx, sy, gx, gy, x, y)
        return fits

    def drive(self) -> tuple[float, float]:
        scan = self.ros.latest(LaserScan, topics.SCAN)
        odom = first_message(self.odom)
        clock = self.manager.clock
        start = clock.now()
        p = odom.pose.pose.position
        planner = self.planner
        if planner is None:
            waypoints = [*((v.x_m, v.y_m) for v in self.via), (self.goal.x_m, self.goal.y_m)]
            marks: list[int | None] = [*range(len(self.via)), None]
        elif self.initial_path is not None and self._initial_path_fits(p.x, p.y):
            if self.via:
                waypoints = self._plan(planner, p.x, p.y, first_leg=self.initial_path)
            else:
                self.planned = self.initial_path
                waypoints = list(self.initial_path.waypoints_m[1:])
                self._marks = [None] * len(waypoints)
            marks = self._marks
        else:
            waypoints = self._plan(planner, p.x, p.y)  # NoPath fails the action
            marks = self._marks
        blocked_since: float | None = None
        last_replan = -math.inf
        turning = False
        while not self.interrupted:
            odom = self.odom.get() or odom
            p = odom.pose.pose.position
            while len(waypoints) > 1 and math.hypot(waypoints[0][0] - p.x, waypoints[0][1] - p.y
                                                    ) <= self._reach_m(marks[0]):
                waypoints.pop(0)  # corner (or via) reached: head for the next one
                self._pass_waypoint(marks)
            tx, ty = waypoints[0]
            dx, dy = tx - p.x, ty - p.y
            # Slow down for the goal, not for every corner on the way.
            remaining = math.hypot(dx, dy) + path_length_m(waypoints)
            dist = math.hypot(self.goal.x_m - p.x, self.goal.y_m - p.y)
            if len(waypoints) == 1 and (dist <= self.tolerance_m
                                        or math.hypot(dx, dy) <= self.end_precision_m):
                # Within tolerance_m of the goal, either way (see end_precision_m).
                self.command(0.0, 0.0)
                return (p.x, p.y)
            heading_err = _wrap(math.atan2(dy, dx) - yaw_of(odom))
            # Far off the path's bearing: turn on the spot until nearly on it (hysteresis,
            # so it does not set off driving a wide arc just under the threshold).
            if abs(heading_err) > self.TURN_ON_SPOT_RAD:
                turning = True
            elif abs(heading_err) < self.ALIGNED_RAD:
                turning = False
            angular = max(-1.2, min(1.2, 2.0 * heading_err))
            leg_speed = self._leg_speed_mps(p.x, p.y)
            linear = min(leg_speed, 0.8 * remaining) * max(0.0, math.cos(heading_err)) ** 2
            if turning:
                linear = 0.0
            nearest = math.inf
            last = scan.get()
            if last is not None:
                nearest = sector_min(last, 0.0, self.field_half_angle_rad)
            if nearest < self.stop_distance_m and linear > 0:
                # Stop driving but keep turning towards the waypoint: turning on the spot is
                # safe (the planner's radius is the circumscribed one), and a detour's first
                # leg usually points away from what blocks the way — standing still here
                # would face the obstacle for ever and re-plan the same path.
                linear = 0.0
                now = clock.now()
                if blocked_since is None:
                    blocked_since = now
                elif now - blocked_since > self.blocked_timeout_s:
                    self.command(0.0, 0.0)
                    raise NavigationError(
                        f"{self.name}: blocked by an obstacle {nearest:.2f} m ahead for "
                        f"{self.blocked_timeout_s} s at ({p.x:.2f}, {p.y:.2f})")
                if (planner is not None and last is not None
                        and now - max(blocked_since, last_replan) >= self.replan_after_s):
                    last_replan = now
                    self.seen.add(self._obstacles_ahead(last, p.x, p.y, yaw_of(odom)),
                                  now_s=now)
                    try:
                        waypoints = self._plan(planner.with_obstacles(self.seen.shapes()),
                                               p.x, p.y)
                        marks = self._marks
                        self.replans += 1
                        turning = True  # face the new path before driving on
                    except NoPath as exc:  # no way around (yet): wait, try again later
                        log.info("%s: blocked, no way around: %s", self.name, exc)
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
            self.tick()
        return (p.x, p.y)

    def _obstacles_ahead(self, scan: LaserScan, x: float, y: float, yaw: float
                         ) -> list[Disc]:
        """The laser's hits in the safety field within ``slow_distance_m``, in map
        coordinates, as small discs (the planner inflates them by the robot's radius)."""
        found = []
        angle = scan.angle_min
        for r in scan.ranges:
            if (abs(_wrap(angle)) <= self.field_half_angle_rad
                    and scan.range_min <= r <= self.slow_distance_m):
                found.append(Disc((x + r * math.cos(yaw + angle), y + r * math.sin(yaw + angle)),
                                  0.05))
            angle += scan.angle_increment
        return found


class LaneFollowing(DriveBase):
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

    def drive(self) -> float:
        line = self.ros.latest(Float64, topics.LINE_SENSOR)
        odom = first_message(self.odom)
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
            self.tick()
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
        self._cmd = self.ros.publisher(Float64, topics.LIFT_COMMAND, shared=True)
        self._state = self.ros.latest(Float64, topics.LIFT_STATE)
        first_message(self._state)
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
        pub = self.ros.publisher(String, topics.SOUND, shared=True)
        played = 0
        for i in range(self.times):
            if i and not self.sleep(self.interval_s):
                break
            pub.publish(String(data=self.sound))
            played += 1
        return played
