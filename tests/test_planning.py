"""The grid planner (beehave/planning.py): paths that keep the robot's radius from every
obstacle, exact costs, clear errors, and the warehouse's README example around its pillar."""

from __future__ import annotations

import math
import random

import pytest

from beehave.errors import BeehaveError, NoPath
from beehave.planning import Disc, GridPlanner, OccupancyMap, PlannedPath, Rect, path_length_m


def distance_to(shape: Disc | Rect, x: float, y: float) -> float:
    """Exact distance from (x, y) to the shape's outline (0 inside)."""
    if isinstance(shape, Disc):
        return max(0.0, math.hypot(x - shape.center_m[0], y - shape.center_m[1])
                   - shape.radius_m)
    c, s = math.cos(shape.yaw_rad), math.sin(shape.yaw_rad)
    dx, dy = x - shape.center_m[0], y - shape.center_m[1]
    u = max(abs(c * dx + s * dy) - shape.size_m[0] / 2, 0.0)
    v = max(abs(-s * dx + c * dy) - shape.size_m[1] / 2, 0.0)
    return math.hypot(u, v)


def clearance_m(path: PlannedPath, shapes: tuple[Disc | Rect, ...]) -> float:
    """The smallest distance between the path (sampled every 1 cm) and any shape."""
    best = math.inf
    for (ax, ay), (bx, by) in zip(path.waypoints_m, path.waypoints_m[1:], strict=False):
        n = max(1, math.ceil(math.hypot(bx - ax, by - ay) / 0.01))
        for k in range(n + 1):
            x, y = ax + (bx - ax) * k / n, ay + (by - ay) * k / n
            best = min(best, *(distance_to(sh, x, y) for sh in shapes))
    return best


EMPTY = OccupancyMap(size_m=(10.0, 6.0))
PILLAR = Disc((5.0, 3.0), 0.3)


def test_free_floor_is_one_straight_segment_with_exact_cost() -> None:
    path = GridPlanner(EMPTY, robot_radius_m=0.5).plan((1.0, 1.0), (9.0, 5.0))
    assert path.waypoints_m == ((1.0, 1.0), (9.0, 5.0))
    assert path.length_m == pytest.approx(math.hypot(8.0, 4.0))


@pytest.mark.parametrize(("radius_m", "clearance"), [(0.2, 0.0), (0.55, 0.1), (0.8, 0.05)])
def test_path_around_a_pillar_keeps_radius_plus_clearance(radius_m: float,
                                                          clearance: float) -> None:
    floor = OccupancyMap(size_m=(10.0, 6.0), obstacles=(PILLAR,))
    planner = GridPlanner(floor, robot_radius_m=radius_m, clearance_m=clearance,
                          resolution_m=0.05)
    path = planner.plan((1.0, 3.0), (9.0, 3.0))
    assert len(path.waypoints_m) >= 3  # it had to bend
    # Cell centres are tested, so the exact clearance may fall short by half a diagonal.
    assert clearance_m(path, (PILLAR,)) >= radius_m + clearance - 0.05 * math.sqrt(2) / 2
    # Barely longer than the straight line: pulled tight, not a staircase.
    assert 8.0 < path.length_m < 8.0 + 2 * (radius_m + clearance + 0.3)
    assert path.length_m == pytest.approx(path_length_m(path.waypoints_m))


def test_gap_narrower_than_the_robot_is_no_path_and_says_why() -> None:
    # A wall across the floor with a 0.8 m gap: a Kobuki passes, an EMILI does not.
    wall = (Rect((5.0, 1.3), (0.2, 2.6)), Rect((5.0, 4.7), (0.2, 2.6)))
    floor = OccupancyMap(size_m=(10.0, 6.0), obstacles=wall)
    kobuki = GridPlanner(floor, robot_radius_m=0.18, clearance_m=0.05).plan((1, 3), (9, 3))
    assert clearance_m(kobuki, wall) >= 0.18
    with pytest.raises(NoPath, match=r"radius 0\.55 m") as info:
        GridPlanner(floor, robot_radius_m=0.55).plan((1, 3), (9, 3))
    assert isinstance(info.value, BeehaveError)


def test_goal_inside_an_obstacle_fails_or_stops_at_the_nearest_free_point() -> None:
    floor = OccupancyMap(size_m=(10.0, 6.0), obstacles=(PILLAR,))
    planner = GridPlanner(floor, robot_radius_m=0.5, clearance_m=0.0)
    with pytest.raises(NoPath, match=r"goal \(5\.00, 3\.00\) is within 0\.50 m"):
        planner.plan((1.0, 3.0), (5.0, 3.0))
    path = planner.plan((1.0, 3.0), (5.0, 3.0), goal_tolerance_m=1.0)
    gx, gy = path.goal_m
    assert 0.8 - 0.1 <= math.hypot(gx - 5.0, gy - 3.0) <= 0.8 + 0.15  # just outside


@pytest.mark.parametrize("goal", [(11.0, 3.0), (5.0, -1.0), (math.nan, 1.0)])
def test_goal_off_the_floor_or_not_a_number_is_refused(goal: tuple[float, float]) -> None:
    with pytest.raises(NoPath, match="goal"):
        GridPlanner(EMPTY, robot_radius_m=0.3).plan((1.0, 1.0), goal)


def test_start_inside_the_inflation_leaves_by_the_nearest_free_cell() -> None:
    # A robot parked 0.3 m from a wall though it plans with 0.5 m: it may still leave.
    planner = GridPlanner(EMPTY, robot_radius_m=0.5, clearance_m=0.0)
    path = planner.plan((0.3, 3.0), (9.0, 3.0))
    assert path.waypoints_m[0] == (0.3, 3.0)
    assert planner.is_free(path.waypoints_m[1])
    assert path.waypoints_m[1][0] == pytest.approx(0.55, abs=0.06)


def test_with_obstacles_replans_around_new_ones_and_leaves_the_original() -> None:
    planner = GridPlanner(EMPTY, robot_radius_m=0.4)
    straight = planner.plan((1.0, 3.0), (9.0, 3.0))
    blocked = planner.with_obstacles([Disc((5.0, 3.0), 0.5)])
    detour = blocked.plan((1.0, 3.0), (9.0, 3.0))
    assert len(detour.waypoints_m) > 2 and detour.length_m > straight.length_m
    assert planner.plan((1.0, 3.0), (9.0, 3.0)) == straight


def test_bad_options_are_refused_with_their_name() -> None:
    with pytest.raises(ValueError, match="robot_radius_m"):
        GridPlanner(EMPTY, robot_radius_m=math.inf)
    with pytest.raises(ValueError, match="resolution_m"):
        GridPlanner(EMPTY, robot_radius_m=0.3, resolution_m=0.0)
    with pytest.raises(ValueError, match="size_m"):
        OccupancyMap(size_m=(0.0, 3.0))


def test_warehouse_readme_order_goes_around_the_pillar() -> None:
    pytest.importorskip("pydantic")
    from robots.world import load_world, occupancy_map

    world = load_world("warehouse")
    floor = occupancy_map(world)
    start = (world.robots[0].start.x_m, world.robots[0].start.y_m)
    goal = world.station("emili_pickup").center_m
    path = GridPlanner(floor, robot_radius_m=0.55).plan(start, goal)
    # The straight line from EMILI's start to its pick-up touches the pillar at (8, 4.3).
    pillar = Disc((8.0, 4.3), 0.25)
    assert distance_to(pillar, 8.0, 2.0 + (8.0 - 3.0) * (9.6 - 2.0) / 14.0) < 0.55
    assert clearance_m(path, floor.obstacles) >= 0.55 + 0.1 - 0.08
    assert path.goal_m == goal
    assert math.dist(start, goal) < path.length_m < 1.2 * math.dist(start, goal)


def test_goal_tolerance_is_kept_in_metres_from_the_goal_point() -> None:
    # Goals around a pillar, just inside its inflation: every plan must end within
    # goal_tolerance_m of the goal itself (it used to measure between cell indices, and
    # ended up to 0.2 m away with a 0.15 m tolerance), or fail with NoPath.
    planner = GridPlanner(OccupancyMap(size_m=(10.0, 6.0), obstacles=(PILLAR,)),
                          robot_radius_m=0.55, clearance_m=0.1)
    tolerance_m = 0.15
    ended = 0
    for k in range(0, 40, 3):
        for degrees in range(0, 360, 10):
            r = 0.75 + k * 0.005
            goal = (5.0 + r * math.cos(math.radians(degrees)),
                    3.0 + r * math.sin(math.radians(degrees)))
            if planner.is_free(goal):
                continue
            try:
                end = planner.plan((1.0, 1.0), goal, goal_tolerance_m=tolerance_m).goal_m
            except NoPath:
                continue
            ended += 1
            assert math.dist(end, goal) <= tolerance_m, (goal, end)
            assert planner.is_free(end)
    assert ended > 50  # most of them are within reach


def test_goal_on_the_floors_edge_says_it_is_the_edge() -> None:
    planner = GridPlanner(EMPTY, robot_radius_m=0.3)
    with pytest.raises(NoPath, match=r"floor's edge .*x 0\.40–9\.60 m") as info:
        planner.plan((1.0, 1.0), (10.0, 3.0))
    assert "obstacle" not in str(info.value)
    end = planner.plan((1.0, 1.0), (10.0, 3.0), goal_tolerance_m=0.5).goal_m
    assert math.dist(end, (10.0, 3.0)) <= 0.5


def test_docstring_example_path_is_the_real_one() -> None:
    floor = OccupancyMap(size_m=(10.0, 6.0),
                         obstacles=(Disc((5.0, 3.0), 0.3), Rect((8.0, 1.0), (0.4, 2.0))))
    path = GridPlanner(floor, robot_radius_m=0.55).plan((1.0, 3.0), (9.0, 3.0))
    assert [pytest.approx(w) for w in ((1.0, 3.0), (4.75, 3.95), (5.45, 3.95), (9.0, 3.0))
            ] == list(path.waypoints_m)
    import beehave.planning

    assert "(4.75, 3.95), (5.45, 3.95)" in (beehave.planning.__doc__ or "")


def test_seen_obstacles_keep_one_hit_per_cell_and_forget_old_ones() -> None:
    # The same wall seen on every re-plan: the memory (and the re-plan's cost) must not
    # grow with the number of looks.
    from beehave.planning import SeenObstacles

    wall = [Disc((6.0 + 0.02 * k, 3.0), 0.05) for k in range(50)]  # 1 m: 10 cells
    seen = SeenObstacles(cell_m=0.1, forget_after_s=10.0)
    for look in range(100):
        seen.add(wall, now_s=0.1 * look)
    assert len(seen) == len({(math.floor(d.center_m[0] / 0.1), 30) for d in wall}) == 10
    seen.add([Disc((2.0, 2.0), 0.05)], now_s=15.0)  # the wall was last seen at 9.9 s
    assert len(seen) == 10 + 1
    seen.add([], now_s=20.0)
    assert seen.shapes() == [Disc((2.0, 2.0), 0.05)]
    with pytest.raises(ValueError, match="forget_after_s"):
        SeenObstacles(forget_after_s=0.0)


@pytest.mark.parametrize("shape", [Disc((9.9, 0.2), 0.3), Rect((0.3, 5.8), (1.0, 0.4), 0.7),
                                   Disc((5.0, 3.0), 0.05), Rect((5.0, 3.0), (3.0, 0.2), 1.1)])
def test_with_obstacles_rasterises_like_the_map(shape: Disc | Rect) -> None:
    # Adding a shape touches only the cells it can reach; the result must equal building
    # the map with that shape, edges and rotated rectangles included.
    added = GridPlanner(EMPTY, robot_radius_m=0.55).with_obstacles([shape])
    built = GridPlanner(OccupancyMap(size_m=(10.0, 6.0), obstacles=(shape,)),
                        robot_radius_m=0.55)
    assert (added.blocked == built.blocked).all()
    assert added.blocked.sum() > GridPlanner(EMPTY, robot_radius_m=0.55).blocked.sum()


def test_check_reachable_refuses_exactly_what_plan_refuses() -> None:
    """The route check's look-up agrees with A* on maps with pockets, slits one robot too
    narrow, diagonal corners and goals inside obstacles (every pair of probe points)."""
    rng = random.Random(7)
    for _ in range(12):
        shapes: list[Disc | Rect] = [Rect((rng.uniform(1, 9), rng.uniform(1, 5)),
                                          (rng.uniform(0.2, 4.0), rng.uniform(0.2, 4.0)),
                                          rng.uniform(0, math.pi)) for _ in range(6)]
        planner = GridPlanner(OccupancyMap(size_m=(10.0, 6.0), obstacles=tuple(shapes)),
                              robot_radius_m=0.3)
        probes = [(rng.uniform(0, 10), rng.uniform(0, 6)) for _ in range(8)]
        for a in probes:
            for b in probes:
                try:
                    planner.plan(a, b, goal_tolerance_m=0.2)
                    planned: str | None = None
                except NoPath as exc:
                    planned = str(exc)
                try:
                    planner.check_reachable(a, b, goal_tolerance_m=0.2)
                    checked: str | None = None
                except NoPath as exc:
                    checked = str(exc)
                assert checked == planned, (shapes, a, b)


def test_check_reachable_follows_added_obstacles_and_leaves_the_original() -> None:
    wall = Rect((5.0, 3.0), (0.2, 6.0))
    walled = GridPlanner(EMPTY, robot_radius_m=0.3).with_obstacles([wall])
    open_floor = GridPlanner(EMPTY, robot_radius_m=0.3)
    open_floor.check_reachable((1.0, 3.0), (9.0, 3.0))  # labelled before the copy
    cut = open_floor.with_obstacles([wall])
    with pytest.raises(NoPath, match="cut the goal off"):
        cut.check_reachable((1.0, 3.0), (9.0, 3.0))
    with pytest.raises(NoPath, match="cut the goal off"):
        walled.check_reachable((1.0, 3.0), (9.0, 3.0))
    open_floor.check_reachable((1.0, 3.0), (9.0, 3.0))
    assert max(cut.regions()) == 2 and max(open_floor.regions()) == 1
