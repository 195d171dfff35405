"""Top-down pictures of a world drawn with PIL from its known geometry.

Faster and crisper than a rendered camera image: floor (holes black), speed zones
(translucent, with their limit written in), walls, shelves, obstacles, lane tape, stations
(green charging, blue pick-up, orange drop-off, with their names), depots, machines with a
level bar and their delivery areas, each robot's driven path in its own colour and the
robot itself — EMILI as its body outlined in its LED strip colour, Kobuki as a disc with
its two LEDs, an orange box on it when it carries a load — with an arrow for its heading
and its name in its path's colour.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from PIL import Image, ImageDraw, ImageFont

from robots.world import Box, Cylinder, Machine, World

if TYPE_CHECKING:
    from beehave.planning import GridPlanner

RGB8 = tuple[int, int, int]

STATION_COLORS: dict[str, RGB8] = {"charging": (60, 170, 80), "pickup": (60, 110, 210),
                                   "dropoff": (230, 140, 40)}
PATH_COLORS: tuple[RGB8, ...] = ((200, 30, 120), (20, 140, 160), (120, 60, 200),
                                 (190, 90, 20), (40, 120, 40), (220, 40, 40),
                                 (30, 80, 200), (150, 150, 0), (0, 160, 110),
                                 (110, 70, 40))
"""One colour per robot (ten before they repeat), in the order the world lists them."""
ZONE_COLOR: RGB8 = (235, 70, 60)
DEPOT_COLOR: RGB8 = (140, 100, 50)
DELIVERY_COLOR: RGB8 = (215, 190, 75)


@dataclass(frozen=True)
class RobotSketch:
    """What the picture shows of one robot."""

    namespace: str
    kind: str
    x_m: float
    y_m: float
    yaw_rad: float
    leds: tuple[tuple[float, float, float], ...]
    path: Sequence[tuple[float, float]]
    loaded: bool = False


def _rgb8(color: Sequence[float]) -> RGB8:
    r, g, b = (max(0, min(255, round(c * 255))) for c in color[:3])
    return (r, g, b)


def render_topdown(world: World, robots: Sequence[RobotSketch], path: str | Path, *,
                   scale_px_per_m: float = 40.0, margin_m: float = 0.5,
                   planned: Sequence[Sequence[tuple[float, float]]] = (),
                   planner: GridPlanner | None = None,
                   levels: Mapping[str, float] | None = None, title: str | None = None
                   ) -> Path:
    """Draw ``world`` and ``robots`` from above into the PNG file ``path``; returns it.

    One metre is ``scale_px_per_m`` pixels; ``margin_m`` of background surrounds the floor.
    ``planned``: planned paths (waypoint lists) drawn as white lines with their corners;
    ``planner``: shade the cells its inflation blocks (where the robot's centre may not go);
    ``levels``: each machine's level by name for its bar (default: the initial levels);
    ``title``: a line of text in the top margin.
    """
    width_m, depth_m = world.floor.size_m
    size = (round((width_m + 2 * margin_m) * scale_px_per_m),
            round((depth_m + 2 * margin_m) * scale_px_per_m))
    image = Image.new("RGB", size, (30, 30, 34))
    draw = ImageDraw.Draw(image)
    # Every label in one font that scales with the picture (readable at 40 px/m).
    draw.font = ImageFont.load_default(size=max(10, round(0.3 * scale_px_per_m)))

    def px(x_m: float, y_m: float) -> tuple[float, float]:
        # Image rows grow downwards; the world's y grows upwards.
        return ((x_m + margin_m) * scale_px_per_m, (depth_m + margin_m - y_m) * scale_px_per_m)

    def rect(cx: float, cy: float, w: float, h: float, yaw: float) -> list[tuple[float, float]]:
        c, s = math.cos(yaw), math.sin(yaw)
        corners = ((w / 2, h / 2), (-w / 2, h / 2), (-w / 2, -h / 2), (w / 2, -h / 2))
        return [px(cx + c * u - s * v, cy + s * u + c * v) for u, v in corners]

    def width_px(m: float) -> int:
        return max(1, round(m * scale_px_per_m))

    floor_rgb = _rgb8(world.floor.color)
    for x0, y0, x1, y1 in world.floor_rects():
        draw.rectangle([px(x0, y1), px(x1, y0)], fill=floor_rgb)
    grid = (max(0, floor_rgb[0] - 18),) * 3
    for gx in range(1, math.ceil(width_m)):
        draw.line([px(gx, 0), px(gx, depth_m)], fill=grid, width=1)
    for gy in range(1, math.ceil(depth_m)):
        draw.line([px(0, gy), px(width_m, gy)], fill=grid, width=1)
    for hole in world.holes:
        draw.polygon(rect(*hole.center_m, *hole.size_m, 0.0), fill=(10, 10, 10))
    if planner is not None:
        # The inflation first: walls and shelves are drawn over it, leaving their halo.
        res = planner.resolution_m
        halo = (floor_rgb[0], max(0, floor_rgb[1] - 45), max(0, floor_rgb[2] - 45))
        rows, cols = planner.blocked.shape
        for j in range(rows):
            for i in range(cols):
                if planner.blocked[j, i]:
                    draw.rectangle([px(i * res, (j + 1) * res), px((i + 1) * res, j * res)],
                                   fill=halo)

    if world.zones:
        # Translucent: the floor grid and the paths stay visible through them.
        overlay = Image.new("RGBA", size, (0, 0, 0, 0))
        shade = ImageDraw.Draw(overlay)
        for zone in world.zones:
            # The stricter the limit, the stronger the tint.
            alpha = 90 if zone.max_speed_mps <= 0.15 else 55
            shade.polygon([px(*p) for p in zone.points_m], fill=(*ZONE_COLOR, alpha),
                          outline=(*ZONE_COLOR, 200), width=2)
        image.paste(overlay, (0, 0), overlay)
        for zone in world.zones:
            x = min(px(*p)[0] for p in zone.points_m)
            y = min(px(*p)[1] for p in zone.points_m)
            draw.text((x + 3, y + 2), f"{zone.name}: max {zone.max_speed_mps:g} m/s",
                      fill=(150, 20, 20))

    for depot in world.depots:
        pale = tuple((c + 2 * f) // 3 for c, f in zip(DEPOT_COLOR, floor_rgb, strict=True))
        area = depot.area
        draw.polygon(rect(*area.center_m, *area.size_m, math.radians(area.yaw_deg)),
                     fill=pale, outline=DEPOT_COLOR, width=2)
        x, y = px(area.center_m[0] - area.size_m[0] / 2, area.center_m[1] + area.size_m[1] / 2)
        draw.text((x + 3, y + 2), depot.name, fill=(20, 20, 20))
    for machine in world.machines:
        area = machine.delivery
        draw.polygon(rect(*area.center_m, *area.size_m, math.radians(area.yaw_deg)),
                     fill=None, outline=DELIVERY_COLOR, width=2)

    # Where names are written already: a robot's name goes where it covers none of them.
    taken: list[tuple[float, float, float, float]] = []
    for station in world.stations:
        color = STATION_COLORS[station.kind]
        pale = ((color[0] + 2 * floor_rgb[0]) // 3, (color[1] + 2 * floor_rgb[1]) // 3,
                (color[2] + 2 * floor_rgb[2]) // 3)
        draw.polygon(rect(*station.center_m, *station.size_m, math.radians(station.yaw_deg)),
                     fill=pale, outline=color, width=2)
        x, y = px(station.center_m[0] - station.size_m[0] / 2,
                  station.center_m[1] + station.size_m[1] / 2)
        draw.text((x + 3, y + 2), station.name, fill=(20, 20, 20))
        taken.append(draw.textbbox((x + 3, y + 2), station.name))

    for lane in world.lanes:
        draw.line([px(*p) for p in lane.points_m], fill=_rgb8(lane.color),
                  width=max(2, width_px(lane.width_m)), joint="curve")

    for wall in world.walls:
        (ax, ay), (bx, by) = wall.from_m, wall.to_m
        length = math.hypot(bx - ax, by - ay)
        yaw = math.atan2(by - ay, bx - ax)
        draw.polygon(rect((ax + bx) / 2, (ay + by) / 2, length, wall.thickness_m, yaw),
                     fill=(95, 95, 105))
    for shelf in world.shelves:
        draw.polygon(rect(*shelf.center_m, *shelf.size_m, math.radians(shelf.yaw_deg)),
                     fill=_rgb8(shelf.color or (0.45, 0.33, 0.22)), outline=(60, 40, 20))
    for obstacle in world.obstacles:
        fill = _rgb8(obstacle.color or (0.5, 0.5, 0.55))
        if isinstance(obstacle, Cylinder):
            x, y = px(*obstacle.center_m)
            r = obstacle.radius_m * scale_px_per_m
            draw.ellipse([x - r, y - r, x + r, y + r], fill=fill, outline=(40, 40, 40))
        elif isinstance(obstacle, Box):
            draw.polygon(rect(*obstacle.center_m, *obstacle.size_m,
                              math.radians(obstacle.yaw_deg)), fill=fill, outline=(40, 40, 40))

    for machine in world.machines:
        level = (levels or {}).get(machine.name, machine.initial_level)
        _draw_machine(draw, machine, level, px, rect, scale_px_per_m)

    for plan in planned:
        if len(plan) >= 2:
            draw.line([px(*p) for p in plan], fill=(255, 255, 255), width=3, joint="curve")
        for p in plan:
            x, y = px(*p)
            draw.ellipse([x - 4, y - 4, x + 4, y + 4], fill=(255, 255, 255),
                         outline=(20, 20, 20))
    for i, robot in enumerate(robots):
        color = PATH_COLORS[i % len(PATH_COLORS)]
        if len(robot.path) >= 2:
            draw.line([px(*p) for p in robot.path], fill=color, width=2, joint="curve")
    for i, robot in enumerate(robots):
        _draw_robot(draw, robot, PATH_COLORS[i % len(PATH_COLORS)], px, rect, scale_px_per_m,
                    taken)

    if title:
        draw.text((6, 4), title, fill=(235, 235, 235))

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    image.save(out, format="PNG", optimize=True)
    return out


def _draw_machine(draw: ImageDraw.ImageDraw, machine: Machine, level: float, px: Any,
                  rect: Any, scale: float) -> None:
    """The machine's body, its name, and a level bar along its lower edge: green above
    half, orange above a fifth, red below, black when empty."""
    draw.polygon(rect(*machine.center_m, *machine.size_m, math.radians(machine.yaw_deg)),
                 fill=_rgb8(machine.color), outline=(30, 30, 40))
    fraction = max(0.0, min(1.0, level / machine.capacity))
    x0, y0 = px(machine.center_m[0] - machine.size_m[0] / 2 + 0.1,
                machine.center_m[1] - machine.size_m[1] / 2 + 0.35)
    x1, y1 = px(machine.center_m[0] + machine.size_m[0] / 2 - 0.1,
                machine.center_m[1] - machine.size_m[1] / 2 + 0.1)
    draw.rectangle([x0, y0, x1, y1], fill=(25, 25, 25))
    color = ((60, 190, 80) if fraction > 0.5 else (240, 150, 30) if fraction > 0.2
             else (220, 40, 40))
    if fraction > 0:
        draw.rectangle([x0, y0, x0 + (x1 - x0) * fraction, y1], fill=color)
    # Outside the body (a label is wider than a small machine), on the side away from
    # its delivery area so the label never covers where the robots stop.
    below = machine.delivery.center_m[1] > machine.center_m[1]
    tx, ty = px(machine.center_m[0], machine.center_m[1]
                + (-1 if below else 1) * (machine.size_m[1] / 2 + 0.05))
    draw.text((tx, ty), f"{machine.name}: {level:.0f}/{machine.capacity:g}",
              fill=(20, 30, 90), anchor="mt" if below else "mb")


def _overlaps(a: tuple[float, float, float, float],
              b: tuple[float, float, float, float]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _draw_robot(draw: ImageDraw.ImageDraw, robot: RobotSketch, label: RGB8, px: object,
                rect: object, scale: float,
                taken: list[tuple[float, float, float, float]] | None = None) -> None:
    """Draw ``robot`` and its name: above it, or below it where the name would cover a
    label in ``taken`` (a station's name, where a robot charging there stands); the box
    written is added to ``taken``."""
    to_px = px  # typed loosely above to keep the signature short
    assert callable(to_px) and callable(rect)
    c, s = math.cos(robot.yaw_rad), math.sin(robot.yaw_rad)
    if robot.kind == "emili":
        led = _rgb8(robot.leds[0]) if robot.leds else (60, 60, 60)
        draw.polygon(rect(robot.x_m, robot.y_m, 0.92, 0.62, robot.yaw_rad), fill=led)
        draw.polygon(rect(robot.x_m, robot.y_m, 0.70, 0.45, robot.yaw_rad),
                     fill=(205, 205, 200), outline=(90, 90, 90))
        nose = 0.45
    else:
        x, y = to_px(robot.x_m, robot.y_m)
        r = 0.175 * scale
        draw.ellipse([x - r, y - r, x + r, y + r], fill=(70, 70, 75), outline=(20, 20, 20))
        for led_rgb, side in zip(robot.leds, (1, -1), strict=False):
            lx, ly = to_px(robot.x_m + 0.10 * c - side * 0.05 * s,
                           robot.y_m + 0.10 * s + side * 0.05 * c)
            lr = max(2.0, 0.035 * scale)
            draw.ellipse([lx - lr, ly - lr, lx + lr, ly + lr], fill=_rgb8(led_rgb))
        nose = 0.175
    if robot.loaded:
        draw.polygon(rect(robot.x_m, robot.y_m, 0.18, 0.18, robot.yaw_rad),
                     fill=(240, 140, 25), outline=(60, 30, 0))
    tip = to_px(robot.x_m + nose * c, robot.y_m + nose * s)
    back = to_px(robot.x_m + (nose - 0.2) * c, robot.y_m + (nose - 0.2) * s)
    draw.line([back, tip], fill=(20, 20, 20), width=max(2, round(0.03 * scale)))
    x, y = to_px(robot.x_m, robot.y_m)
    # Centred above the robot: robots parked side by side keep their names apart.
    above_m = 0.55 if robot.kind == "emili" else 0.3
    taken = [] if taken is None else taken
    place, anchor = (x, y - above_m * scale), "mb"
    box = draw.textbbox(place, robot.namespace, anchor=anchor)
    if any(_overlaps(box, other) for other in taken):
        place, anchor = (x, y + above_m * scale), "mt"
        box = draw.textbbox(place, robot.namespace, anchor=anchor)
    draw.text(place, robot.namespace, fill=label, anchor=anchor)
    taken.append(box)
