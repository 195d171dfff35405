"""The route check hands its plans to the drive (``docs/vda5050.md``, "Order → wheels").

An order's released base is planned leg by leg when it is accepted (``noRouteError``
before acceptance otherwise); each node keeps the plan of the leg that ends there, and
``Navigation(initial_path=...)`` follows it instead of planning the same leg again — but
only from where the plan starts: a robot standing elsewhere plans anew. Navigation runs
here on a real manager and planner; only its ROS I/O is a stand-in (odometry that reports
the start, then the goal).
"""

from __future__ import annotations

import math
from typing import Any

import pytest

from beehave.testing import WALL_TIMEOUT_S

pytest.importorskip("rclpy")

from nav_msgs.msg import Odometry  # noqa: E402

from beehave import Behavior, HighLevelBehaviorManager, Status  # noqa: E402
from beehave.interfaces.vda5050 import AgvOrders, OrderRejected  # noqa: E402
from beehave.interfaces.vda5050.order import Drive  # noqa: E402
from beehave.planning import PlannedPath  # noqa: E402
from behaviours.actions import Goal, Navigation, world_planner  # noqa: E402
from behaviours.demos.vda5050_master import edge, node  # noqa: E402
from behaviours.vda5050 import CLEARANCE_M, ROBOT_RADIUS_M, WorldNodes  # noqa: E402

START = (3.0, 2.0)
"""EMILI's start in the warehouse."""


def _order(nodes: list[dict[str, Any]]) -> dict[str, Any]:
    return {"orderId": "o1", "orderUpdateId": 0, "nodes": nodes,
            "edges": [edge(a, b) for a, b in zip(nodes, nodes[1:], strict=False)]}


def _orders(nodes: WorldNodes) -> AgvOrders:
    return AgvOrders(locate=nodes.locate, check_route=nodes.check_route,
                     position=lambda: START)


def test_the_planner_is_built_with_the_node_map_and_is_the_drives() -> None:
    nodes = WorldNodes("warehouse")
    # The same (cached) planner Navigation uses: built when the AGV is set up.
    assert nodes.planner is world_planner("warehouse", ROBOT_RADIUS_M, CLEARANCE_M)
    assert Navigation((1.0, 1.0), world="warehouse").planner is nodes.planner


def test_the_first_leg_that_moves_carries_its_plan_the_later_ones_are_only_checked() -> None:
    orders = _orders(WorldNodes("warehouse"))
    assert orders.accept(_order([node("start", 0, x=3.0, y=2.0), node("emili_pickup", 2),
                                 node("emili_dropoff", 4), node("far", 6, released=False,
                                                                x=1.0, y=1.0)]))
    pickup = WorldNodes("warehouse").world.station("emili_pickup").center_m
    legs = []
    while isinstance(task := orders.next_task(), Drive):
        legs.append(task.node.route)
        orders.node_reached(task.node)
    assert len(legs) == 3  # the horizon node is not driven
    # The AGV stands on the first node: its leg moves nothing; the next one is planned.
    assert isinstance(legs[0], PlannedPath) and legs[0].length_m <= 0.1
    assert isinstance(legs[1], PlannedPath) and legs[1].waypoints_m[0] == (3.0, 2.0)
    assert math.dist(legs[1].goal_m, pickup) <= 0.1
    assert legs[2] is None  # only checked for a path; planned when driven


def test_a_base_no_path_reaches_is_still_refused_before_acceptance() -> None:
    orders = _orders(WorldNodes("warehouse"))
    inside_a_shelf = _shelf_point(WorldNodes("warehouse"))
    with pytest.raises(OrderRejected, match="noRouteError") as caught:
        orders.accept(_order([node("start", 0, x=3.0, y=2.0),
                              node("wall", 2, x=inside_a_shelf[0], y=inside_a_shelf[1])]))
    assert caught.value.entry["errorReferences"] == [
        {"referenceKey": "nodeId", "referenceValue": "wall"}]
    assert orders.order_id == ""  # nothing accepted


def _shelf_point(nodes: WorldNodes) -> tuple[float, float]:
    """A point on the floor that no path reaches (the middle of an obstacle)."""
    from beehave.errors import NoPath

    width, depth = nodes.world.floor.size_m
    for i in range(1, 40):
        for j in range(1, 40):
            p = (width * i / 40, depth * j / 40)
            try:
                nodes.planner.plan(START, p, goal_tolerance_m=0.1)
            except NoPath:
                return p
    raise AssertionError("the warehouse has no unreachable point")


# ---- Navigation with an initial path ----------------------------------------------------

class _Latest:
    """``self.ros.latest`` stand-in: no message (no laser: nothing ahead)."""

    def wait_for(self, *, timeout_s: float) -> Any:
        return None

    def get(self) -> Any:
        return None


class _Odometry:
    """``self.odom`` stand-in: the robot stands at ``at``, then at each waypoint of the
    navigation's plan in turn (it "arrives" at one per control period)."""

    def __init__(self, nav: Navigation, at: tuple[float, float]) -> None:
        self.nav, self.at, self.reached = nav, at, 0

    def wait_for(self, *, timeout_s: float) -> Odometry:
        return _odom(*self.at)

    def get(self) -> Odometry:
        assert self.nav.planned is not None
        waypoints = self.nav.planned.waypoints_m
        self.reached = min(self.reached + 1, len(waypoints) - 1)
        return _odom(*waypoints[self.reached])


def _odom(x: float, y: float) -> Odometry:
    msg = Odometry()
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    return msg


class _Planner:
    """Counts the plans made through it (a spy around the real planner)."""

    def __init__(self, planner: Any) -> None:
        self.planner, self.plans = planner, 0
        self.resolution_m = planner.resolution_m

    def plan(self, *args: Any, **kwargs: Any) -> PlannedPath:
        self.plans += 1
        return self.planner.plan(*args, **kwargs)


def _navigate(at: tuple[float, float], goal: tuple[float, float],
              path: PlannedPath | None) -> tuple[Navigation, _Planner]:
    class _Ros:
        def latest(self, *_args: Any) -> _Latest:
            return _Latest()

    class Nav(Navigation):
        ros = _Ros()  # type: ignore[assignment]

        def _open(self) -> None:
            self.commands: list[tuple[float, float]] = []
            self._cmd = self
            self.odom = _Odometry(self, at)

        def publish(self, msg: Any) -> None:  # the cmd_vel publisher
            self.commands.append((msg.linear.x, msg.angular.z))

    class Go(Behavior):
        def __init__(self, action: Navigation) -> None:
            self.action = action

        def run(self) -> None:
            self.start_action(self.action).wait()

    nav = Nav(Goal(*goal), world="warehouse", tolerance_m=0.15, initial_path=path)
    spy = _Planner(nav.planner)
    nav.planner = spy  # type: ignore[assignment]
    with HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        hl.register("go", Go, action=nav)
        assert hl.switch("go").wait(WALL_TIMEOUT_S)
        assert nav.wait(WALL_TIMEOUT_S)
    assert nav.status is Status.SUCCEEDED, nav.error
    return nav, spy


def _leg() -> tuple[tuple[float, float], PlannedPath]:
    nodes = WorldNodes("warehouse")
    pickup = nodes.world.station("emili_pickup").center_m
    [plan] = nodes.check_route([("start", START), ("emili_pickup", pickup)])
    return (float(pickup[0]), float(pickup[1])), plan


def test_navigation_follows_the_handed_over_plan_without_planning() -> None:
    goal, plan = _leg()
    # Standing within tolerance_m of the plan's start: no plan before the first command.
    nav, spy = _navigate((START[0] + 0.1, START[1]), goal, plan)
    assert spy.plans == 0
    assert nav.planned is plan


def test_a_plan_that_does_not_start_where_the_robot_stands_is_planned_again() -> None:
    goal, plan = _leg()
    nav, spy = _navigate((START[0] + 1.0, START[1]), goal, plan)
    assert spy.plans == 1
    assert nav.planned is not plan
    assert nav.planned is not None and nav.planned.waypoints_m[0] == (START[0] + 1.0, START[1])


def test_a_plan_that_ends_elsewhere_is_planned_again() -> None:
    goal, plan = _leg()
    nav, spy = _navigate(START, (goal[0], goal[1] - 0.5), plan)
    assert spy.plans == 1
    assert nav.planned is not plan


def test_without_an_initial_path_navigation_plans_as_before() -> None:
    goal, _plan = _leg()
    _nav, spy = _navigate(START, goal, None)
    assert spy.plans == 1


def test_a_node_the_agv_already_stands_on_is_reached_without_driving() -> None:
    from behaviours.vda5050 import OrderExecution

    orders = _orders(WorldNodes("warehouse"))
    assert orders.accept(_order([node("start", 0, x=START[0] + 0.1, y=START[1]),
                                 node("emili_pickup", 2)]))
    execution = OrderExecution(orders=orders, world="warehouse")
    task = orders.next_task()
    assert isinstance(task, Drive) and task.node.node_id == "start"
    execution.drive(task)  # outside a manager: starting an action here would raise
    assert orders.last_node_id == "start"
    task = orders.next_task()
    assert isinstance(task, Drive) and task.node.node_id == "emili_pickup"
