"""Worlds for the simulation, described in YAML and validated with pydantic.

A world is a rectangular floor (optionally with holes: pits, a loading-dock edge) with
walls, shelves and obstacles on it, lane tape polylines for line following, named stations
(pick-up, drop-off, charging) and the robots that start in it. A factory world adds
machines that consume material (each with a delivery area in front of it), depots where
material is loaded, and speed zones (polygons with a speed limit); the physics of those
lives in :mod:`robots.factory`. All coordinates are metres in
the world frame (x right/east, y up/north, origin at the floor's lower-left corner); angles
in YAML are degrees (``yaw_deg``) because people write them. A minimal world::

    name: tiny
    floor: {size_m: [6, 4]}
    walls:
      - {from_m: [0, 0], to_m: [6, 0]}
    lanes:
      - {name: main, points_m: [[1, 2], [5, 2]]}
    stations:
      - {name: dock, kind: charging, center_m: [0.6, 0.6], size_m: [1.0, 1.0]}
    robots:
      - {namespace: emili1, kind: emili, start: {x_m: 1, y_m: 2, yaw_deg: 0},
         charging_station: dock}

Load one with :func:`load_world` (a path, or the name of a world shipped in
``robots/worlds/``: ``load_world("warehouse")``). Every mistake is reported at once with
the file, the key path and what was expected (:class:`robots.errors.WorldError`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from robots.errors import UnknownMachine, UnknownStation, UnknownWorld, UnknownZone, WorldError

if TYPE_CHECKING:
    from beehave.planning import OccupancyMap

WORLDS_DIR = Path(__file__).parent / "worlds"
"""Where the worlds shipped with beehave live; ``load_world(name)`` looks here."""

Vec2 = tuple[float, float]
RGB = tuple[float, float, float]


class _Model(BaseModel):
    # Unknown keys are typos: reject them rather than silently ignore them.
    model_config = ConfigDict(extra="forbid", frozen=True)


class Pose(_Model):
    """A pose on the floor: position in metres, heading in degrees (0 = +x, 90 = +y)."""

    x_m: float
    y_m: float
    yaw_deg: float = 0.0

    @property
    def yaw_rad(self) -> float:
        return math.radians(self.yaw_deg)


class Floor(_Model):
    """The floor: a slab whose top is at z = 0, ``size_m`` wide (x) and deep (y)."""

    size_m: Vec2 = Field(description="floor extent in x and y, metres")
    color: RGB = (0.78, 0.78, 0.75)

    @model_validator(mode="after")
    def _positive(self) -> Floor:
        if min(self.size_m) <= 0:
            raise ValueError(f"size_m must be positive, got {self.size_m}")
        return self


class Hole(_Model):
    """An axis-aligned area with no floor (a pit, a dock edge): cliff sensors see it."""

    center_m: Vec2
    size_m: Vec2


class Wall(_Model):
    """A straight wall from ``from_m`` to ``to_m`` (its centre line)."""

    from_m: Vec2
    to_m: Vec2
    thickness_m: float = Field(0.2, gt=0)
    height_m: float = Field(1.5, gt=0)


class Box(_Model):
    """A box standing on the floor: a shelf or an obstacle."""

    center_m: Vec2
    size_m: Vec2
    height_m: float = Field(1.0, gt=0)
    yaw_deg: float = 0.0
    color: RGB | None = None


class Cylinder(_Model):
    """A cylinder standing on the floor (a pillar, a bin)."""

    center_m: Vec2
    radius_m: float = Field(gt=0)
    height_m: float = Field(1.0, gt=0)
    color: RGB | None = None


class Lane(_Model):
    """Lane tape glued to the floor along a polyline, for line following."""

    name: str
    points_m: list[Vec2] = Field(min_length=2)
    width_m: float = Field(0.05, gt=0)
    color: RGB = (0.95, 0.80, 0.10)


StationKind = Literal["pickup", "dropoff", "charging"]


class Station(_Model):
    """A named rectangular area on the floor. A robot whose centre is inside a ``charging``
    station charges; ``pickup`` and ``dropoff`` stations are targets for behaviours."""

    name: str
    kind: StationKind
    center_m: Vec2
    size_m: Vec2 = (1.0, 1.0)
    yaw_deg: float = 0.0

    def contains(self, x_m: float, y_m: float) -> bool:
        """Whether the point (x_m, y_m) lies inside the station's (rotated) rectangle."""
        return _in_rect(self.center_m, self.size_m, self.yaw_deg, x_m, y_m)


class Area(_Model):
    """A rectangle on the floor (flat: it blocks nothing): a delivery spot, a depot."""

    center_m: Vec2
    size_m: Vec2 = (0.8, 0.8)
    yaw_deg: float = 0.0

    @model_validator(mode="after")
    def _positive(self) -> Area:
        if min(self.size_m) <= 0:
            raise ValueError(f"size_m must be positive, got {self.size_m}")
        return self

    def contains(self, x_m: float, y_m: float) -> bool:
        """Whether the point (x_m, y_m) lies inside the (rotated) rectangle."""
        return _in_rect(self.center_m, self.size_m, self.yaw_deg, x_m, y_m)

    def corners(self) -> list[Vec2]:
        """The four corners, counter-clockwise."""
        return _rect_corners(self.center_m, self.size_m, self.yaw_deg)


class Machine(_Model):
    """A production machine: a box that blocks the floor and consumes material.

    ``level`` runs from 0 to ``capacity`` (units of material, whatever the scenario counts:
    parts, kilograms); it starts at ``initial_level`` and falls by ``consumption_per_s``
    each second of sim time, never below 0. A robot that carries a load and stands still
    for ``unload_s`` in the ``delivery`` area (flat, in front of the machine) unloads it:
    the level rises by the load's amount, capped at ``capacity``.
    """

    name: str
    center_m: Vec2
    size_m: Vec2 = (1.6, 1.2)
    yaw_deg: float = 0.0
    height_m: float = Field(1.2, gt=0)
    capacity: float = Field(gt=0)
    initial_level: float = Field(ge=0)
    consumption_per_s: float = Field(ge=0)
    unload_s: float = Field(2.0, ge=0)
    delivery: Area
    color: RGB = (0.30, 0.42, 0.60)

    @model_validator(mode="after")
    def _consistent(self) -> Machine:
        if min(self.size_m) <= 0:
            raise ValueError(f"size_m must be positive, got {self.size_m}")
        if self.initial_level > self.capacity:
            raise ValueError(f"initial_level {self.initial_level} exceeds capacity "
                             f"{self.capacity}")
        if _rects_overlap(self.center_m, self.size_m, self.yaw_deg, self.delivery.center_m,
                          self.delivery.size_m, self.delivery.yaw_deg):
            raise ValueError(f"delivery area at {self.delivery.center_m} overlaps the "
                             f"machine's body (centre {self.center_m}, size {self.size_m}): "
                             "put it in front of the machine, where a robot can stand")
        return self

    def contains(self, x_m: float, y_m: float) -> bool:
        """Whether the point lies on the machine's footprint."""
        return _in_rect(self.center_m, self.size_m, self.yaw_deg, x_m, y_m)


class Depot(_Model):
    """Where material is loaded: a robot with no load that stands still for ``load_s``
    inside ``area`` picks up one load of ``load_amount`` units (a Kobuki carries one)."""

    name: str
    area: Area
    load_amount: float = Field(40.0, gt=0)
    load_s: float = Field(2.0, ge=0)


class Zone(_Model):
    """A speed zone: a polygon (``points_m``, at least 3 corners, not closed: the last
    corner connects to the first) where no robot may drive faster than ``max_speed_mps``.
    Flat: it blocks nothing; :mod:`robots.factory` measures the speeds in it."""

    name: str
    points_m: list[Vec2] = Field(min_length=3)
    max_speed_mps: float = Field(gt=0)

    @model_validator(mode="after")
    def _has_area(self) -> Zone:
        if abs(_polygon_area(self.points_m)) < 1e-6:
            raise ValueError(f"points_m {self.points_m} enclose no area (the corners lie "
                             "on one line)")
        return self

    def contains(self, x_m: float, y_m: float) -> bool:
        """Whether the point lies inside the polygon (even-odd rule; an edge counts as
        inside for the lower/left edges only, so two zones sharing an edge never both
        hold a point on it)."""
        inside = False
        pts = self.points_m
        j = len(pts) - 1
        for i in range(len(pts)):
            (xi, yi), (xj, yj) = pts[i], pts[j]
            if (yi > y_m) != (yj > y_m):
                x_cross = xi + (y_m - yi) * (xj - xi) / (yj - yi)
                if x_m < x_cross:
                    inside = not inside
            j = i
        return inside


class Battery(_Model):
    """Battery parameters of one robot; the defaults depend on the robot kind."""

    # An infinite capacity or draw makes the state of charge NaN or empties the battery
    # at once: refused, as NaN is (by the bound).
    capacity_wh: float | None = Field(None, gt=0, allow_inf_nan=False)
    initial_fraction: float = Field(1.0, ge=0, le=1)
    idle_w: float | None = Field(None, ge=0, allow_inf_nan=False)
    """The draw standing still (electronics, sensors), where it differs from the kind's:
    a demo battery made small so that driving empties it in minutes can keep the idle
    loss of the real one by shrinking this with it."""


class Laser(_Model):
    """The robot's laser scanner, where it differs from its kind's (360 beams)."""

    beams: int | None = Field(None, ge=8, le=4096)
    """Beams per 360° scan. Casting them is the simulation's largest cost per robot
    (about 5 µs a beam): a large fleet may use fewer."""


class Physics(_Model):
    """How pybullet solves the world; the defaults are pybullet's own."""

    solver_iterations: int | None = Field(None, ge=1, le=1000)
    """Constraint solver iterations per step (pybullet's ``numSolverIterations``, 50 by
    default). Fewer make each step cheaper: a fleet of light robots on a flat floor needs
    far fewer than a lift pressing a load."""


class RobotSpec(_Model):
    """A robot in the world: its ROS namespace, its kind and where it starts."""

    namespace: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    kind: Literal["emili", "kobuki", "quad"]
    start: Pose
    battery: Battery = Battery()
    laser: Laser = Laser()
    charging_station: str | None = None
    pickup_station: str | None = None
    dropoff_station: str | None = None


class MavlinkOptions(_Model):
    """Expose every robot as a MAVLink vehicle (``robots.mavlink_endpoint``): robot i (in
    the order of ``robots``) sends to ``udpout:HOST:base_port + i`` with system id i + 1."""

    base_port: int = Field(14560, ge=1024, le=65000)
    host: str = "127.0.0.1"
    key_file: str | None = None
    """MAVLink 2 signing: every vehicle signs with, and requires, the key in this file (a
    passphrase or 64 hex digits; a relative path is taken from the current directory)."""


class World(_Model):
    """A whole world. Build it with :func:`load_world` or ``World.model_validate(dict)``."""

    name: str
    floor: Floor
    physics: Physics = Physics()
    holes: list[Hole] = []
    walls: list[Wall] = []
    shelves: list[Box] = []
    obstacles: list[Box | Cylinder] = []
    lanes: list[Lane] = []
    stations: list[Station] = []
    machines: list[Machine] = []
    depots: list[Depot] = []
    zones: list[Zone] = []
    robots: list[RobotSpec] = []
    mavlink: MavlinkOptions | None = None

    @model_validator(mode="after")
    def _names_resolve(self) -> World:
        names = [s.name for s in self.stations]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"duplicate station names {duplicates}")
        for key in ("machines", "depots", "zones"):
            own = [item.name for item in getattr(self, key)]
            duplicates = sorted({n for n in own if own.count(n) > 1})
            if duplicates:
                raise ValueError(f"{key}: duplicate names {duplicates}")
        self._factory_on_floor()
        namespaces = [r.namespace for r in self.robots]
        duplicates = sorted({n for n in namespaces if namespaces.count(n) > 1})
        if duplicates:
            raise ValueError(f"duplicate robot namespaces {duplicates}")
        for i, robot in enumerate(self.robots):
            for key in ("charging_station", "pickup_station", "dropoff_station"):
                ref = getattr(robot, key)
                if ref is not None and ref not in names:
                    raise ValueError(
                        f"robots.{i}.{key}: unknown station {ref!r}; stations: "
                        f"{', '.join(repr(n) for n in sorted(names)) or 'none'}")
        return self

    def _factory_on_floor(self) -> None:
        """Machines, delivery areas, depots and zones must lie on the floor: one off it is a
        typo in a coordinate, and a delivery area no robot can reach makes a scenario that
        cannot be served."""
        width, depth = self.floor.size_m

        def off(points: list[Vec2]) -> bool:
            return any(not (-1e-9 <= x <= width + 1e-9 and -1e-9 <= y <= depth + 1e-9)
                       for x, y in points)

        where = f"the floor (0..{width:g} x 0..{depth:g} m)"
        for i, machine in enumerate(self.machines):
            if off(_rect_corners(machine.center_m, machine.size_m, machine.yaw_deg)):
                raise ValueError(f"machines.{i} ({machine.name!r}): the machine reaches off "
                                 f"{where}")
            if off(machine.delivery.corners()):
                raise ValueError(f"machines.{i}.delivery ({machine.name!r}): the delivery "
                                 f"area reaches off {where}")
            for j, other in enumerate(self.machines):
                if j != i and _rects_overlap(other.center_m, other.size_m, other.yaw_deg,
                                             machine.delivery.center_m,
                                             machine.delivery.size_m,
                                             machine.delivery.yaw_deg):
                    raise ValueError(f"machines.{i}.delivery ({machine.name!r}): the delivery "
                                     f"area overlaps machine {other.name!r}")
        for i, depot in enumerate(self.depots):
            if off(depot.area.corners()):
                raise ValueError(f"depots.{i}.area ({depot.name!r}): reaches off {where}")
            a = depot.area
            for other in self.machines:
                if _rects_overlap(other.center_m, other.size_m, other.yaw_deg, a.center_m,
                                  a.size_m, a.yaw_deg):
                    raise ValueError(f"depots.{i}.area ({depot.name!r}): overlaps machine "
                                     f"{other.name!r}")
        for i, zone in enumerate(self.zones):
            if off(list(zone.points_m)):
                raise ValueError(f"zones.{i}.points_m ({zone.name!r}): a corner lies off "
                                 f"{where}")

    def machine(self, name: str) -> Machine:
        """The machine called ``name``; :class:`UnknownMachine` lists the others."""
        for machine in self.machines:
            if machine.name == name:
                return machine
        raise UnknownMachine(name, [m.name for m in self.machines])

    def zone(self, name: str) -> Zone:
        """The speed zone called ``name``; :class:`UnknownZone` lists the others."""
        for zone in self.zones:
            if zone.name == name:
                return zone
        raise UnknownZone(name, [z.name for z in self.zones])

    def zone_at(self, x_m: float, y_m: float) -> Zone | None:
        """The speed zone the point (x_m, y_m) lies in, or None outside every zone. Where
        zones overlap, the one with the lowest ``max_speed_mps`` (the one that binds)."""
        found: Zone | None = None
        for zone in self.zones:
            if zone.contains(x_m, y_m) and (found is None
                                            or zone.max_speed_mps < found.max_speed_mps):
                found = zone
        return found

    def with_robots(self, count: int) -> World:
        """This world with only its first ``count`` robots (``beehave sim factory --robots
        N``). Raises :class:`WorldError` when it has fewer."""
        if not 0 <= count <= len(self.robots):
            raise WorldError(self.name, [
                f"robots: asked for {count} robot(s); this world starts 0 to "
                f"{len(self.robots)} ({', '.join(r.namespace for r in self.robots) or 'none'})"])
        return self.model_copy(update={"robots": self.robots[:count]})

    def station(self, name: str) -> Station:
        """The station called ``name``; :class:`UnknownStation` lists the others."""
        for station in self.stations:
            if station.name == name:
                return station
        raise UnknownStation(name, [s.name for s in self.stations])

    def stations_of_kind(self, kind: StationKind) -> list[Station]:
        return [s for s in self.stations if s.kind == kind]

    def floor_rects(self) -> list[tuple[float, float, float, float]]:
        """The floor minus its holes as axis-aligned rectangles (x0, y0, x1, y1)."""
        width, depth = self.floor.size_m
        xs = {0.0, width}
        ys = {0.0, depth}
        for h in self.holes:
            xs |= {min(max(h.center_m[0] + d * h.size_m[0] / 2, 0.0), width) for d in (-1, 1)}
            ys |= {min(max(h.center_m[1] + d * h.size_m[1] / 2, 0.0), depth) for d in (-1, 1)}
        xv, yv = sorted(xs), sorted(ys)
        rects = []
        for y0, y1 in zip(yv, yv[1:], strict=False):
            row: list[tuple[float, float, float, float]] = []
            for x0, x1 in zip(xv, xv[1:], strict=False):
                cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
                if any(abs(cx - h.center_m[0]) < h.size_m[0] / 2
                       and abs(cy - h.center_m[1]) < h.size_m[1] / 2 for h in self.holes):
                    continue
                # Merge with the previous cell of this row when they touch: fewer bodies.
                if row and row[-1][2] == x0:
                    row[-1] = (row[-1][0], y0, x1, y1)
                else:
                    row.append((x0, y0, x1, y1))
            rects.extend(row)
        return rects


def occupancy_map(world: World) -> OccupancyMap:
    """The world as a planner sees it (:mod:`beehave.planning`): the floor's size, with
    walls, shelves, obstacles, machines and holes as blocking shapes. Lanes, stations,
    delivery areas, depots and speed zones are flat: they do not block. Robots are not on
    the map (they move; the laser sees them)."""
    from beehave.planning import Disc, OccupancyMap, Rect

    shapes: list[Disc | Rect] = []
    for wall in world.walls:
        (ax, ay), (bx, by) = wall.from_m, wall.to_m
        shapes.append(Rect(((ax + bx) / 2, (ay + by) / 2),
                           (math.hypot(bx - ax, by - ay), wall.thickness_m),
                           math.atan2(by - ay, bx - ax)))
    for box in [*world.shelves, *world.obstacles]:
        if isinstance(box, Cylinder):
            shapes.append(Disc(box.center_m, box.radius_m))
        else:
            shapes.append(Rect(box.center_m, box.size_m, math.radians(box.yaw_deg)))
    shapes += [Rect(hole.center_m, hole.size_m) for hole in world.holes]
    # Machines block; their delivery areas, the depots and the zones are flat floor.
    shapes += [Rect(m.center_m, m.size_m, math.radians(m.yaw_deg)) for m in world.machines]
    return OccupancyMap(size_m=world.floor.size_m, obstacles=tuple(shapes))


def available_worlds() -> list[str]:
    """Names of the worlds shipped in ``robots/worlds/``."""
    return sorted(p.stem for p in WORLDS_DIR.glob("*.yaml"))


def load_world(path_or_name: str | Path) -> World:
    """Read and validate a world.

    ``path_or_name`` is a YAML file, or the name of a shipped world (``"warehouse"``).
    Raises :class:`UnknownWorld` (listing the shipped worlds) when it is neither, and
    :class:`WorldError` naming the file, each bad key path and the expected type.
    """
    path = Path(path_or_name)
    if not path.is_file():
        shipped = WORLDS_DIR / f"{path_or_name}.yaml"
        if isinstance(path_or_name, str) and "/" not in path_or_name and shipped.is_file():
            path = shipped
        else:
            raise UnknownWorld(str(path_or_name), available_worlds())
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise WorldError(str(path), [f"not valid YAML: {exc}"]) from exc
    return world_from_dict(data, source=str(path))


def world_from_dict(data: Any, *, source: str = "<dict>") -> World:
    """Validate an already parsed world (e.g. built in a test); errors name ``source``."""
    if not isinstance(data, dict):
        raise WorldError(source, [f"(top level): expected a mapping, got {type(data).__name__}"])
    try:
        return World.model_validate(data)
    except ValidationError as exc:
        raise WorldError(source, [_describe(e) for e in exc.errors()]) from None


def _describe(error: Any) -> str:
    """One pydantic error as 'key.path: what was expected, got what'."""
    loc = ".".join(str(part) for part in error["loc"]
                   # pydantic puts the union member's class name into the path; not a key.
                   if not (isinstance(part, str) and part[:1].isupper()))
    kind = error["type"]
    if kind == "extra_forbidden":
        return f"{loc}: unknown key (check the spelling)"
    if kind == "missing":
        return f"{loc}: required key missing"
    got = error.get("input")
    shown = repr(got) if not isinstance(got, dict | list) else type(got).__name__
    message = str(error["msg"])
    if message.startswith("Value error, "):
        message = message[len("Value error, "):]
    return f"{loc or '(top level)'}: {message}, got {shown}"


# ---- geometry helpers --------------------------------------------------------------------

def _in_rect(center: Vec2, size: Vec2, yaw_deg: float, x_m: float, y_m: float) -> bool:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    dx, dy = x_m - center[0], y_m - center[1]
    u, v = c * dx + s * dy, -s * dx + c * dy
    return abs(u) <= size[0] / 2 and abs(v) <= size[1] / 2


def _rect_corners(center: Vec2, size: Vec2, yaw_deg: float) -> list[Vec2]:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    half_w, half_h = size[0] / 2, size[1] / 2
    return [(center[0] + c * u - s * v, center[1] + s * u + c * v)
            for u, v in ((half_w, half_h), (-half_w, half_h), (-half_w, -half_h),
                         (half_w, -half_h))]


def _rects_overlap(ca: Vec2, sa: Vec2, ya: float, cb: Vec2, sb: Vec2, yb: float) -> bool:
    """Whether two rotated rectangles share area (separating axis test; touching edges do
    not count)."""
    a, b = _rect_corners(ca, sa, ya), _rect_corners(cb, sb, yb)
    for yaw in (ya, ya + 90.0, yb, yb + 90.0):
        ax, ay = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        pa = [x * ax + y * ay for x, y in a]
        pb = [x * ax + y * ay for x, y in b]
        if max(pa) <= min(pb) + 1e-9 or max(pb) <= min(pa) + 1e-9:
            return False
    return True


def _polygon_area(points: list[Vec2]) -> float:
    """Signed area (shoelace): positive when the corners run counter-clockwise."""
    return sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1)
               in zip(points, [*points[1:], points[0]], strict=True)) / 2
