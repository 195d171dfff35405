"""VDA 5050 orders executed as a beehave behaviour (``docs/vda5050.md``).

The interface (:mod:`beehave.interfaces.vda5050`) keeps the order state; this module does
the driving and lifting:

- :class:`OrderExecution` is the top-level behaviour the interface switches to when an
  order arrives. It asks the order state what is due next, drives to each released node
  along the base (:class:`~behaviours.actions.Navigation`, planned on the world's map)
  and runs the node's actions: ``pick`` lifts EMILI's lift (:class:`~behaviours.actions.Lift`)
  to ``lift_pick_m``, ``drop`` lowers it to ``lift_drop_m``, ``startCharging`` checks that
  the AGV stands on a charging station (the simulation charges it there).
  A ``cancelOrder`` or ``startPause`` switches it away (to ``idle``): its actions are
  interrupted and reach their safe states (zero velocity; the lift holds its height).
- :class:`WorldNodes` maps the order's nodes to the world: a node's ``nodePosition``
  (``mapId`` = the world's name) or, without one, the station its ``nodeId`` names; and
  checks that the released base can be driven (``noRouteError`` otherwise).
"""

from __future__ import annotations

import abc
import functools
import logging
import math
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from beehave import Behavior, Status
from beehave.errors import NoPath
from beehave.interfaces.vda5050.order import (
    STANDSTILL_TIMEOUT_S,
    ActionState,
    ActionStatus,
    AgvOrders,
    Drive,
    Edge,
    Node,
    OrderRejected,
    Point,
    RunAction,
    error_entry,
)
from beehave.planning import PlannedPath
from behaviours.actions import Goal, Lift, Navigation, Via, prepare_driving, world_planner

if TYPE_CHECKING:
    from robots.world import World

log = logging.getLogger(__name__)

ROBOT_RADIUS_M = 0.55
CLEARANCE_M = 0.1
"""Navigation's defaults: the route check plans with the same inflation as the drive."""
TOLERANCE_M = 0.15
"""How close the drive brings the AGV to a node (``OrderExecution``'s default)."""
GOAL_TOLERANCE_M = 0.1
"""The route check's plans end this close to a node: ``Navigation``'s own planning
tolerance for ``TOLERANCE_M`` (less its ``end_precision_m``), so the drive can follow them."""


@functools.lru_cache(maxsize=8)
def _load_world(world: str) -> World:
    """Worlds are immutable: the interface and every order behaviour share one load."""
    from robots.world import load_world

    return load_world(world)


class WorldNodes:
    """Order nodes on a world's map (a world name or YAML path)."""

    def __init__(self, world: str) -> None:
        self.world_name = world
        self.world = _load_world(world)
        # Built now (~0.1 s, once per process), when the AGV is set up: not on its first
        # order, whose acceptance and first wheel command would wait for it.
        self.planner = world_planner(world, ROBOT_RADIUS_M, CLEARANCE_M)
        self.planner.regions()  # labelled now too: the route check looks legs up in them

    def locate(self, node_id: str, position: dict[str, Any] | None) -> Point:
        """``(x_m, y_m)`` of a node; :class:`OrderRejected` says why it cannot be placed."""
        stations = sorted(s.name for s in self.world.stations)
        if position is None:
            if node_id in stations:
                x, y = self.world.station(node_id).center_m
                return (float(x), float(y))
            raise OrderRejected("validationError", f"node {node_id!r} has no nodePosition "
                                f"and is not a station of world {self.world.name!r} "
                                f"(stations: {', '.join(stations)})")
        if position["mapId"] != self.world.name:
            raise OrderRejected("validationError", f"mapId {position['mapId']!r} is not this "
                                f"AGV's map; valid: {self.world.name!r}")
        x, y = float(position["x"]), float(position["y"])
        width, depth = self.world.floor.size_m
        if not (0.0 <= x <= width and 0.0 <= y <= depth):
            raise OrderRejected("validationError", f"({x:g}, {y:g}) lies outside the "
                                f"{width:g} x {depth:g} m floor of {self.world.name!r}")
        return (x, y)

    def check_route(self, points: Sequence[tuple[str, Point]]) -> list[PlannedPath | None]:
        """Check that every leg of the released base can be driven; ``noRouteError`` names
        the node that no path reaches. The first leg that moves the AGV is planned now and
        its plan returned in its place (:class:`OrderExecution` hands it to that leg's
        ``Navigation(initial_path=...)``, so the first wheel command does not wait for a
        second plan of it); the later legs are only checked for a path (one look-up, see
        :meth:`~beehave.planning.GridPlanner.check_reachable`) and planned when driven."""
        plans: list[PlannedPath | None] = []
        moving = False
        for (from_id, a), (to_id, b) in zip(points, points[1:], strict=False):
            try:
                if moving:
                    self.planner.check_reachable(a, b, goal_tolerance_m=GOAL_TOLERANCE_M)
                    plans.append(None)
                else:
                    plan = self.planner.plan(a, b, goal_tolerance_m=GOAL_TOLERANCE_M)
                    plans.append(plan)
                    moving = plan.length_m > GOAL_TOLERANCE_M
            except NoPath as exc:
                raise OrderRejected("noRouteError", f"no path from {from_id!r} to node "
                                    f"{to_id!r} on map {self.world.name!r}: {exc}",
                                    references={"nodeId": to_id}) from None
        return plans

    def charging_station_at(self, point: Point) -> str | None:
        for station in self.world.stations_of_kind("charging"):
            if station.contains(*point):
                return station.name
        return None


class OrderLoop(Behavior):
    """The order-execution loop: asks ``orders`` what is due next until switched away,
    waiting ``idle_wait_s`` when nothing is; subclasses say how to :meth:`drive` an edge
    and :meth:`execute` an action. :class:`OrderExecution` drives the robot; tests and
    benchmarks subclass it with stand-ins."""

    idle_wait_s = 0.05

    orders: AgvOrders

    def run(self) -> None:
        self.orders.set_executing(True)
        try:
            while not self.interrupted:
                task = self.orders.next_task()
                if task is None:
                    self.orders.wait_change(timeout_s=self.idle_wait_s)
                elif isinstance(task, Drive):
                    self.drive(task)
                elif isinstance(task, RunAction) and self.wait_standstill(task.action):
                    self.execute(task.action)
        finally:
            self.orders.set_executing(False)

    def wait_standstill(self, action: ActionState) -> bool:
        """A SOFT or HARD blocking action starts only once the AGV stands still (VDA 5050
        2.1, 6.12): a node counts as reached while the AGV still brakes. A robot that does
        not stop within ``STANDSTILL_TIMEOUT_S`` fails the action (with an error) instead
        of running it while moving. False when the action must not run (now)."""
        if action.blocking_type == "NONE":
            return True
        deadline = time.monotonic() + STANDSTILL_TIMEOUT_S
        while not self.interrupted and time.monotonic() < deadline:
            # In short steps, so a switch away (cancel, pause) is not held up.
            if self.orders.wait_standstill(timeout_s=self.idle_wait_s):
                return True
        if self.interrupted:
            return False
        self.orders.set_action(action.action_id, ActionStatus.FAILED,
                               "the AGV did not stand still")
        self.orders.add_error(error_entry(
            "actionError", f"action {action.action_id!r} ({action.action_type}, "
            f"{action.blocking_type} blocking): the AGV still moves "
            f"{STANDSTILL_TIMEOUT_S:g} s after reaching the node",
            references={"actionId": action.action_id}))
        return False

    @abc.abstractmethod
    def drive(self, task: Drive) -> None:
        """Go to ``task.node``; call ``orders.node_reached`` once there. A drive may go on
        through ``task.then`` without stopping, calling ``node_reached`` for each node as
        it is passed (one that does not is asked for the next drive, as usual)."""

    @abc.abstractmethod
    def execute(self, action: ActionState) -> None:
        """Run ``action``; report its status with ``orders.set_action``."""


class OrderExecution(OrderLoop):
    """Execute the VDA 5050 order held by ``orders`` (see the module docstring).

    It runs until switched away; with nothing due (no order, or the horizon not yet
    released) it waits. Node and edge actions run one after another, each to its end,
    before the AGV drives on (every action is treated as ``HARD`` blocking); between
    nodes that need no stop it drives on in one ``Navigation`` through them (``via``).
    """

    logic = None
    node_map = WorldNodes
    """How the interface places order nodes (``Vda5050Interface`` builds one per robot)."""

    def __init__(self, *, orders: AgvOrders, world: str = "warehouse", speed_mps: float = 0.6,
                 lift_pick_m: float = 0.2, lift_drop_m: float = 0.0,
                 tolerance_m: float = TOLERANCE_M) -> None:
        self.orders = orders
        self.world = world
        self.nodes = WorldNodes(world)
        self.speed_mps, self.tolerance_m = speed_mps, tolerance_m
        self.lift_pick_m, self.lift_drop_m = lift_pick_m, lift_drop_m

    @classmethod
    def prepare(cls, node: Any) -> None:
        """Called by the interface when it starts on the robot's high-level ``node``: the
        driving entities Navigation shares are made then, not on the first order."""
        prepare_driving(node)

    def drive(self, task: Drive) -> None:
        node, edge = task.node, task.edge
        here = self.orders.position()
        if here is not None and math.dist(here, node.position) <= self.tolerance_m:
            # Already there (typically an order's first node): what Navigation would
            # find after subscribing and waiting for odometry, without that wait.
            self.orders.node_reached(node)
            return
        # One drive through the nodes the AGV need not stop at (no actions, see
        # Drive.then), each passed within its allowedDeviationXY, each leg at its edge's
        # maxSpeed; it stops at the last.
        legs = [(node, edge), *task.then]
        passing = [n for n, _ in legs[:-1]]
        stop, last_edge = legs[-1]
        via = [Via(*n.position, tolerance_m=self._deviation_m(n),
                   speed_mps=self._speed_mps(e), name=n.node_id) for n, e in legs[:-1]]
        # The route check's plan of the first leg: followed when the AGV stands at its
        # start (Navigation plans again otherwise).
        path = node.route if isinstance(node.route, PlannedPath) else None
        nav = self.start_action(Navigation(
            Goal(*stop.position, name=stop.node_id), world=self.world,
            speed_mps=self._speed_mps(last_edge), tolerance_m=self.tolerance_m,
            initial_path=path, via=via,
            on_via=lambda i: self.orders.node_reached(passing[i])))
        nav.wait()
        if nav.status is Status.SUCCEEDED:
            self.orders.node_reached(stop)
        elif not self.interrupted:
            # The AGV cannot go on: say so, fail the order's remaining actions.
            missed = legs[min(nav.passed, len(legs) - 1)][0]
            self.orders.add_error(error_entry(
                "noRouteError", f"could not reach node {missed.node_id!r}: {nav.error}",
                references={"nodeId": missed.node_id, "orderId": self.orders.order_id},
                level="FATAL"))
            self.orders.cancel(f"node {missed.node_id!r} not reached")

    def _speed_mps(self, edge: Edge | None) -> float:
        """The speed on ``edge``: ``speed_mps``, lowered to the edge's ``maxSpeed``."""
        if edge is not None and edge.max_speed_mps:
            return min(self.speed_mps, edge.max_speed_mps)
        return self.speed_mps

    def _deviation_m(self, node: Node) -> float:
        """How close a node passed without stopping must be passed: its
        ``allowedDeviationXY``, else the drive's ``tolerance_m``."""
        allowed = float((node.raw_position or {}).get("allowedDeviationXY") or 0.0)
        return allowed or self.tolerance_m

    def execute(self, action: ActionState) -> None:
        self.orders.set_action(action.action_id, ActionStatus.RUNNING)
        kind = action.action_type
        if kind in ("pick", "drop"):
            height = self.lift_pick_m if kind == "pick" else self.lift_drop_m
            lift = self.start_action(Lift(height))
            lift.wait()
            if lift.status is Status.SUCCEEDED:
                load_id = str(action.parameters.get("loadId", ""))
                self.orders.set_loads([{"loadId": load_id}] if kind == "pick" and load_id
                                      else [{}] if kind == "pick" else [])
                self.orders.set_action(action.action_id, ActionStatus.FINISHED,
                                       f"lift at {float(lift.result):.3f} m")
            elif not self.interrupted:
                self.fail(action, f"lift: {lift.error}")
        elif kind == "startCharging":
            here = self.orders.position()
            station = None if here is None else self.nodes.charging_station_at(here)
            if station is None:
                self.fail(action, f"not on a charging station (at {here})")
            else:
                self.orders.set_action(action.action_id, ActionStatus.FINISHED,
                                       f"charging at {station}")
        elif kind == "stopCharging":
            self.orders.set_action(action.action_id, ActionStatus.FINISHED,
                                   "charging stops when the AGV leaves the station")
        else:  # the order state only lets supported types through
            self.fail(action, f"unsupported action type {kind!r}")

    def fail(self, action: ActionState, why: str) -> None:
        self.orders.set_action(action.action_id, ActionStatus.FAILED, why)
        self.orders.add_error(error_entry(
            "actionError", f"action {action.action_id!r} ({action.action_type}) failed: {why}",
            references={"actionId": action.action_id}))
