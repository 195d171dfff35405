"""Worlds for the simulation, described in YAML and validated with pydantic.

A world is a rectangular floor (optionally with holes: pits, a loading-dock edge) with
walls, shelves and obstacles on it, lane tape polylines for line following, named stations
(pick-up, drop-off, charging) and the robots that start in it. All coordinates are metres in
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

from robots.errors import UnknownStation, UnknownWorld, WorldError

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
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        dx, dy = x_m - self.center_m[0], y_m - self.center_m[1]
        u, v = c * dx + s * dy, -s * dx + c * dy
        return abs(u) <= self.size_m[0] / 2 and abs(v) <= self.size_m[1] / 2


class Battery(_Model):
    """Battery parameters of one robot; the defaults depend on the robot kind."""

    capacity_wh: float | None = Field(None, gt=0)
    initial_fraction: float = Field(1.0, ge=0, le=1)


class RobotSpec(_Model):
    """A robot in the world: its ROS namespace, its kind and where it starts."""

    namespace: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$")
    kind: Literal["emili", "kobuki", "quad"]
    start: Pose
    battery: Battery = Battery()
    charging_station: str | None = None
    pickup_station: str | None = None
    dropoff_station: str | None = None


class MavlinkOptions(_Model):
    """Expose every robot as a MAVLink vehicle (``robots.mavlink_endpoint``): robot i (in
    the order of ``robots``) sends to ``udpout:HOST:base_port + i`` with system id i + 1."""

    base_port: int = Field(14560, ge=1024, le=65000)
    host: str = "127.0.0.1"


class World(_Model):
    """A whole world. Build it with :func:`load_world` or ``World.model_validate(dict)``."""

    name: str
    floor: Floor
    holes: list[Hole] = []
    walls: list[Wall] = []
    shelves: list[Box] = []
    obstacles: list[Box | Cylinder] = []
    lanes: list[Lane] = []
    stations: list[Station] = []
    robots: list[RobotSpec] = []
    mavlink: MavlinkOptions | None = None

    @model_validator(mode="after")
    def _names_resolve(self) -> World:
        names = [s.name for s in self.stations]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"duplicate station names {duplicates}")
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
    walls, shelves, obstacles and holes as blocking shapes. Lanes and stations are flat
    tape: they do not block. Robots are not on the map (they move; the laser sees them)."""
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
