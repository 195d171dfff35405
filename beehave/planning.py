"""Path planning on a 2-D floor: grid A* around obstacles inflated by the robot's radius.

Robot-agnostic: the planner knows a floor (its size) and the shapes that block it — discs
and (rotated) rectangles in metres — nothing about worlds, URDFs or ROS. A simulator, a map
server or a test builds the :class:`OccupancyMap`; ``robots.world.occupancy_map(world)``
is the adapter for the simulated worlds. Navigation follows the waypoints; agents that bid
for a job compare :attr:`PlannedPath.length_m` (the path cost) of their candidate robots::

    from beehave.planning import Disc, GridPlanner, OccupancyMap, Rect

    floor = OccupancyMap(size_m=(10.0, 6.0),
                         obstacles=(Disc((5.0, 3.0), 0.3), Rect((8.0, 1.0), (0.4, 2.0))))
    planner = GridPlanner(floor, robot_radius_m=0.55)   # rasterised and inflated once
    path = planner.plan((1.0, 3.0), (9.0, 3.0))
    path.waypoints_m     # ((1.0, 3.0), (4.75, 3.95), (5.45, 3.95), (9.0, 3.0)): corners only
    path.length_m        # the cost: metres along the waypoints (8.24)

How it works. The floor becomes a grid of ``resolution_m`` cells; a cell is blocked when
its centre lies within ``robot_radius_m + clearance_m`` of an obstacle or of the floor's
edge, so the robot may be treated as a point (its radius must be the circumscribed one:
EMILI turns on the spot). A* on the 8-connected grid (octile distance, no corner cutting)
finds the cell path, which is then pulled tight: every waypoint that the previous one can
see past is dropped, leaving straight segments between corners. A start inside the
inflation (a robot parked close to a wall) leaves by the nearest free cell; a goal inside it
is reached at the nearest free cell within ``goal_tolerance_m``, otherwise planning fails
with :class:`~beehave.errors.NoPath`, as it does when no path exists.

Obstacles that are not on the map (a parked pallet seen by the laser) are added with
:meth:`GridPlanner.with_obstacles`, which returns a new planner and leaves this one as it
was — plans never share mutable state, so several threads may plan at once. Only the cells
an added shape can reach are touched, so adding laser hits costs little; keep them in a
:class:`SeenObstacles`, which holds one hit per cell and forgets old ones, so that re-planning
again and again in front of the same obstacle does not grow its cost.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from beehave.errors import NoPath

__all__ = ["Disc", "GridPlanner", "NoPath", "OccupancyMap", "PlannedPath", "Rect",
           "SeenObstacles", "path_length_m"]

Point = tuple[float, float]

_SQRT2 = math.sqrt(2.0)
_NEIGHBOURS = ((1, 0, 1.0), (-1, 0, 1.0), (0, 1, 1.0), (0, -1, 1.0),
               (1, 1, _SQRT2), (1, -1, _SQRT2), (-1, 1, _SQRT2), (-1, -1, _SQRT2))


@dataclass(frozen=True)
class Disc:
    """A round obstacle (pillar, bin, laser hit): centre and radius in metres."""

    center_m: Point
    radius_m: float


@dataclass(frozen=True)
class Rect:
    """A rectangular obstacle (wall, shelf, pallet, a hole in the floor): centre, size
    along its own x and y, and its heading (counter-clockwise from the map's x axis)."""

    center_m: Point
    size_m: Point
    yaw_rad: float = 0.0


Shape = Disc | Rect


@dataclass(frozen=True)
class OccupancyMap:
    """A floor for planning: ``size_m`` (x, y) from the origin, and what blocks it. Outside
    the floor counts as blocked."""

    size_m: Point
    obstacles: tuple[Shape, ...] = ()

    def __post_init__(self) -> None:
        if not (all(math.isfinite(v) and v > 0 for v in self.size_m)):
            raise ValueError(f"OccupancyMap size_m must be positive and finite, got "
                             f"{self.size_m}")


def path_length_m(points: Sequence[Point]) -> float:
    """The length of a polyline in metres (0 for fewer than two points)."""
    return sum(math.hypot(b[0] - a[0], b[1] - a[1])
               for a, b in zip(points, points[1:], strict=False))


@dataclass(frozen=True)
class PlannedPath:
    """A plan: straight segments between ``waypoints_m`` (the start first, the goal — or the
    free point nearest it — last)."""

    waypoints_m: tuple[Point, ...]

    @property
    def length_m(self) -> float:
        """The path's cost: its length along the waypoints, in metres."""
        return path_length_m(self.waypoints_m)

    @property
    def goal_m(self) -> Point:
        return self.waypoints_m[-1]


class SeenObstacles:
    """Obstacles a robot's sensors found that the map lacks, remembered for a while.

    A laser sees the same box again on every re-plan: hits are kept one per ``cell_m``
    square (the newest wins), so the memory — and the cost of planning with it — stays
    bounded by the area seen, not by the time spent looking. A hit not seen again for
    ``forget_after_s`` is dropped (the pallet may have gone; if not, the laser finds it
    again). Times are in the caller's clock (sim time under ``use_sim_time``)::

        seen = SeenObstacles(cell_m=planner.resolution_m, forget_after_s=30.0)
        seen.add(hits, now_s=clock.now())
        detour = planner.with_obstacles(seen.shapes()).plan(here, goal)
    """

    def __init__(self, *, cell_m: float = 0.1, forget_after_s: float = 30.0) -> None:
        if not (math.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"cell_m must be positive and finite, got {cell_m}")
        if not forget_after_s > 0:  # math.inf: never forget
            raise ValueError(f"forget_after_s must be positive, got {forget_after_s}")
        self.cell_m = float(cell_m)
        self.forget_after_s = float(forget_after_s)
        self._hits: dict[tuple[int, int], tuple[float, Shape]] = {}

    def add(self, shapes: Iterable[Shape], *, now_s: float) -> None:
        """Remember ``shapes`` as seen at ``now_s``, and forget those too old by now."""
        for shape in shapes:
            key = (math.floor(shape.center_m[0] / self.cell_m),
                   math.floor(shape.center_m[1] / self.cell_m))
            self._hits[key] = (now_s, shape)
        self._hits = {key: (t, shape) for key, (t, shape) in self._hits.items()
                      if now_s - t <= self.forget_after_s}

    def shapes(self) -> list[Shape]:
        """What is remembered now, one shape per cell."""
        return [shape for _, shape in self._hits.values()]

    def __len__(self) -> int:
        return len(self._hits)


class GridPlanner:
    """Grid A* on ``occupancy`` for a robot of ``robot_radius_m`` (circumscribed), keeping
    a further ``clearance_m`` from everything; cells of ``resolution_m``.

    Building one rasterises and inflates the map (tens of milliseconds for a warehouse);
    keep it and call :meth:`plan` as often as needed.
    """

    def __init__(self, occupancy: OccupancyMap, *, robot_radius_m: float,
                 clearance_m: float = 0.1, resolution_m: float = 0.1) -> None:
        for name, value in (("robot_radius_m", robot_radius_m), ("clearance_m", clearance_m)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
        if not (math.isfinite(resolution_m) and resolution_m > 0):
            raise ValueError(f"resolution_m must be positive and finite, got {resolution_m}")
        self.occupancy = occupancy
        self.robot_radius_m = float(robot_radius_m)
        self.clearance_m = float(clearance_m)
        self.resolution_m = float(resolution_m)
        self.inflation_m = self.robot_radius_m + self.clearance_m
        self.width = max(1, math.ceil(occupancy.size_m[0] / resolution_m))
        self.height = max(1, math.ceil(occupancy.size_m[1] / resolution_m))
        xs = (np.arange(self.width) + 0.5) * resolution_m
        ys = (np.arange(self.height) + 0.5) * resolution_m
        self._cx, self._cy = np.meshgrid(xs, ys)  # [row = y, column = x]
        r = self.inflation_m
        sx, sy = occupancy.size_m
        # The floor's edge is a wall too: the robot's body must stay on the floor.
        self.blocked = ((self._cx < r) | (self._cx > sx - r)
                        | (self._cy < r) | (self._cy > sy - r))
        self._add(occupancy.obstacles)

    def _add(self, shapes: Iterable[Shape]) -> None:
        self._flat_cache: list[bool] | None = None  # derived from blocked: made again
        self._regions_cache: list[int] | None = None
        r = self.inflation_m
        res = self.resolution_m
        for shape in shapes:
            # Only the cells the inflated shape can reach: a laser hit touches a few hundred
            # cells, not the whole floor (re-plans add many of them).
            if isinstance(shape, Disc):
                half_x = half_y = shape.radius_m + r
            else:
                half_x = half_y = math.hypot(*shape.size_m) / 2 + r
            x, y = shape.center_m
            i0, i1 = max(0, math.floor((x - half_x) / res)), min(self.width,
                                                                 math.ceil((x + half_x) / res) + 1)
            j0, j1 = max(0, math.floor((y - half_y) / res)), min(self.height,
                                                                 math.ceil((y + half_y) / res) + 1)
            if i0 < i1 and j0 < j1:
                self.blocked[j0:j1, i0:i1] |= _within(shape, self._cx[j0:j1, i0:i1],
                                                      self._cy[j0:j1, i0:i1], r)

    def with_obstacles(self, shapes: Iterable[Shape]) -> GridPlanner:
        """A copy that also avoids ``shapes`` (inflated like the map's); this planner is
        unchanged."""
        twin = object.__new__(GridPlanner)
        twin.__dict__.update(self.__dict__)
        twin.blocked = self.blocked.copy()
        twin._add(shapes)
        return twin

    # ---- queries ----------------------------------------------------------------------

    def cell(self, point: Point) -> tuple[int, int]:
        """The (column, row) of the cell holding ``point`` (may be outside the grid)."""
        return (math.floor(point[0] / self.resolution_m),
                math.floor(point[1] / self.resolution_m))

    def center(self, cell: tuple[int, int]) -> Point:
        return ((cell[0] + 0.5) * self.resolution_m, (cell[1] + 0.5) * self.resolution_m)

    def is_free(self, point: Point) -> bool:
        """Whether the robot's centre may be at ``point`` (off the floor: no)."""
        i, j = self.cell(point)
        return 0 <= i < self.width and 0 <= j < self.height and not self.blocked[j, i]

    def segment_free(self, a: Point, b: Point) -> bool:
        """Whether the straight move from ``a`` to ``b`` stays in free cells (sampled at a
        quarter cell)."""
        n = max(1, math.ceil(math.hypot(b[0] - a[0], b[1] - a[1]) / (self.resolution_m / 4)))
        t = np.linspace(0.0, 1.0, n + 1)
        i = np.floor((a[0] + (b[0] - a[0]) * t) / self.resolution_m).astype(np.int64)
        j = np.floor((a[1] + (b[1] - a[1]) * t) / self.resolution_m).astype(np.int64)
        if i.min() < 0 or j.min() < 0 or i.max() >= self.width or j.max() >= self.height:
            return False
        return not bool(self.blocked[j, i].any())

    # ---- planning ---------------------------------------------------------------------

    def plan(self, start: Point, goal: Point, *, goal_tolerance_m: float = 0.0
             ) -> PlannedPath:
        """The shortest grid path from ``start`` to ``goal``, pulled tight into straight
        segments. Raises :class:`~beehave.errors.NoPath` (saying why) when the goal is off
        the floor, inside an obstacle's inflation with no free cell within
        ``goal_tolerance_m``, or cut off."""
        start_cell, goal_cell = self._endpoints(start, goal, goal_tolerance_m)
        cells = self._astar(start_cell, goal_cell)
        if cells is None:
            raise self._cut_off(start, goal)
        end = goal if goal_cell == self.cell(goal) else self.center(goal_cell)
        points: list[Point] = [(float(start[0]), float(start[1]))]
        if start_cell != self.cell(start):
            points.append(self.center(start_cell))  # leave the inflation first
        points += [self.center(c) for c in cells[1:-1]]
        points.append((float(end[0]), float(end[1])))
        return PlannedPath(tuple(self._pull_tight(points)))

    def check_reachable(self, start: Point, goal: Point, *, goal_tolerance_m: float = 0.0
                        ) -> None:
        """Raise :class:`~beehave.errors.NoPath` exactly when :meth:`plan` would, without
        planning: whether two cells are connected is one look-up in the map's free regions,
        labelled once per planner (tens of milliseconds for a warehouse). For checking a
        long route before driving it, e.g. every leg of an order when it arrives."""
        start_cell, goal_cell = self._endpoints(start, goal, goal_tolerance_m)
        regions, width = self.regions(), self.width
        if regions[start_cell[1] * width + start_cell[0]] != regions[
                goal_cell[1] * width + goal_cell[0]]:
            raise self._cut_off(start, goal)

    def _endpoints(self, start: Point, goal: Point, goal_tolerance_m: float
                   ) -> tuple[tuple[int, int], tuple[int, int]]:
        """The free cells a plan from ``start`` to ``goal`` runs between (see :meth:`plan`)."""
        for name, p in (("start", start), ("goal", goal)):
            if not (len(p) == 2 and all(math.isfinite(v) for v in p)):
                raise NoPath(f"{name} must be (x_m, y_m) with finite numbers, got {p!r}")
        sx, sy = self.occupancy.size_m
        if not (0 <= goal[0] <= sx and 0 <= goal[1] <= sy):
            raise NoPath(f"goal ({goal[0]:.2f}, {goal[1]:.2f}) is off the floor "
                         f"(0–{sx:g} × 0–{sy:g} m)")
        start_cell = self._nearest_free(start, math.inf)
        if start_cell is None:
            raise NoPath(f"no free cell anywhere near the start ({start[0]:.2f}, "
                         f"{start[1]:.2f}): the map is blocked for a robot of radius "
                         f"{self.robot_radius_m} m")
        goal_cell = self._nearest_free(goal, goal_tolerance_m)
        if goal_cell is None:
            raise NoPath(f"goal ({goal[0]:.2f}, {goal[1]:.2f}) is {self._why_blocked(goal)}"
                         f", and no free point lies within goal_tolerance_m="
                         f"{goal_tolerance_m:.3g} m")
        return start_cell, goal_cell

    def _cut_off(self, start: Point, goal: Point) -> NoPath:
        return NoPath(f"no path from ({start[0]:.2f}, {start[1]:.2f}) to ({goal[0]:.2f}, "
                      f"{goal[1]:.2f}) for a robot of radius {self.robot_radius_m} m with "
                      f"{self.clearance_m} m clearance: obstacles cut the goal off")

    def _flat(self) -> list[bool]:
        """``blocked`` as a flat list (indexing it is several times faster than numpy
        scalars), made once per planner."""
        if self._flat_cache is None:
            self._flat_cache = self.blocked.ravel().tolist()
        return self._flat_cache

    def regions(self) -> list[int]:
        """A label per cell: free cells joined by 4-neighbour moves share one (0 for
        blocked ones). A* moves diagonally only past two free side cells, so it connects
        exactly the cells one label joins."""
        if self._regions_cache is None:
            blocked, width = self._flat(), self.width
            n = len(blocked)
            regions = [0] * n
            label = 0
            for seed in range(n):
                if blocked[seed] or regions[seed]:
                    continue
                label += 1
                regions[seed] = label
                stack = [seed]
                while stack:
                    k = stack.pop()
                    i = k % width
                    for m in (k - 1 if i > 0 else -1, k + 1 if i < width - 1 else -1,
                              k - width, k + width):
                        if 0 <= m < n and not blocked[m] and not regions[m]:
                            regions[m] = label
                            stack.append(m)
            self._regions_cache = regions
        return self._regions_cache

    def _nearest_free(self, point: Point, within_m: float) -> tuple[int, int] | None:
        """The cell holding ``point`` when it is free, else the free cell whose centre is
        nearest ``point`` and no farther than ``within_m`` from it (None if there is none).

        Distances are measured from the point itself to cell centres, so the promise of
        ``goal_tolerance_m`` holds in metres, not merely in cell indices."""
        cell = self.cell(point)
        i, j = cell
        if 0 <= i < self.width and 0 <= j < self.height and not self.blocked[j, i]:
            return cell
        if not within_m > 0:
            return None
        # Only the window of cells that can lie within reach (the whole grid for inf).
        reach = min(within_m, math.hypot(*self.occupancy.size_m)) / self.resolution_m + 1
        i0, i1 = max(0, math.floor(i - reach)), min(self.width, math.ceil(i + reach) + 1)
        j0, j1 = max(0, math.floor(j - reach)), min(self.height, math.ceil(j + reach) + 1)
        if i0 >= i1 or j0 >= j1:
            return None
        d2 = ((self._cx[j0:j1, i0:i1] - point[0]) ** 2
              + (self._cy[j0:j1, i0:i1] - point[1]) ** 2)
        d2 = np.where(self.blocked[j0:j1, i0:i1], np.inf, d2)
        best = np.unravel_index(int(np.argmin(d2)), d2.shape)
        if not d2[best] <= within_m * within_m:
            return None
        return (i0 + int(best[1]), j0 + int(best[0]))

    def _why_blocked(self, point: Point) -> str:
        """What keeps the robot's centre off ``point``: the floor's edge or an obstacle."""
        sx, sy = self.occupancy.size_m
        r = self.inflation_m
        if min(point[0], sx - point[0], point[1], sy - point[1]) < r:
            return (f"within {r:.2f} m of the floor's edge (robot radius "
                    f"{self.robot_radius_m} m + clearance {self.clearance_m} m: its centre "
                    f"must stay within x {r:.2f}–{sx - r:.2f} m, y {r:.2f}–{sy - r:.2f} m)")
        return (f"within {r:.2f} m (robot radius {self.robot_radius_m} m + clearance "
                f"{self.clearance_m} m) of an obstacle")

    def _astar(self, start: tuple[int, int], goal: tuple[int, int]
               ) -> list[tuple[int, int]] | None:
        width, height = self.width, self.height
        blocked = self._flat()
        s = start[1] * width + start[0]
        g = goal[1] * width + goal[0]
        gi, gj = goal

        def h(index: int) -> float:  # octile distance: exact on an empty 8-connected grid
            dx = abs(index % width - gi)
            dy = abs(index // width - gj)
            return (dx + dy) + (_SQRT2 - 2.0) * min(dx, dy)

        cost = {s: 0.0}
        parent = {s: -1}
        heap = [(h(s), 0.0, s)]
        closed = set()
        while heap:
            _, c, index = heapq.heappop(heap)
            if index == g:
                out = []
                while index != -1:
                    out.append((index % width, index // width))
                    index = parent[index]
                return out[::-1]
            if index in closed:
                continue
            closed.add(index)
            i, j = index % width, index // width
            for di, dj, step in _NEIGHBOURS:
                ni, nj = i + di, j + dj
                if not (0 <= ni < width and 0 <= nj < height):
                    continue
                n = nj * width + ni
                if blocked[n]:
                    continue
                if di and dj and (blocked[j * width + ni] or blocked[nj * width + i]):
                    continue  # no cutting a blocked corner
                nc = c + step
                if nc < cost.get(n, math.inf):
                    cost[n] = nc
                    parent[n] = index
                    heapq.heappush(heap, (nc + h(n), nc, n))
        return None

    def _pull_tight(self, points: list[Point]) -> list[Point]:
        """Keep only the corners: from each kept point, jump to the farthest point it sees."""
        if len(points) <= 2:
            return points
        out = [points[0]]
        anchor = 0
        last = len(points) - 1
        while anchor < last:
            nxt = anchor + 1
            # Greedy forward: one visibility test per cell of the path, not per pair.
            while nxt < last and self.segment_free(points[anchor], points[nxt + 1]):
                nxt += 1
            out.append(points[nxt])
            anchor = nxt
        return out


def _within(shape: Shape, cx: np.ndarray, cy: np.ndarray, r: float) -> np.ndarray:
    """Cells whose centre is within ``r`` of ``shape``."""
    if isinstance(shape, Disc):
        reach = shape.radius_m + r
        return np.asarray((cx - shape.center_m[0]) ** 2 + (cy - shape.center_m[1]) ** 2
                          <= reach * reach, dtype=bool)
    c, s = math.cos(shape.yaw_rad), math.sin(shape.yaw_rad)
    dx, dy = cx - shape.center_m[0], cy - shape.center_m[1]
    u = np.abs(c * dx + s * dy) - shape.size_m[0] / 2
    v = np.abs(-s * dx + c * dy) - shape.size_m[1] / 2
    return np.asarray(np.maximum(u, 0.0) ** 2 + np.maximum(v, 0.0) ** 2 <= r * r, dtype=bool)
