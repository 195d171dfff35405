"""Worlds: the shipped warehouse loads; bad files fail naming the file, key and type."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from robots.errors import UnknownStation, UnknownWorld, WorldError
from robots.world import available_worlds, load_world, world_from_dict


def minimal(**changes: Any) -> dict[str, Any]:
    world: dict[str, Any] = {
        "name": "tiny",
        "floor": {"size_m": [6, 4]},
        "stations": [{"name": "dock", "kind": "charging", "center_m": [1, 1]}],
        "robots": [{"namespace": "emili1", "kind": "emili",
                    "start": {"x_m": 2, "y_m": 2}}],
    }
    world.update(changes)
    return world


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return path


def test_the_warehouse_has_stations_for_each_robot() -> None:
    world = load_world("warehouse")
    assert "warehouse" in available_worlds()
    assert {r.kind for r in world.robots} == {"emili", "kobuki"}
    assert world.floor.size_m == (20, 12)
    assert world.lanes and world.walls and world.shelves and world.obstacles
    for robot in world.robots:
        for key, kind in (("charging_station", "charging"), ("pickup_station", "pickup"),
                          ("dropoff_station", "dropoff")):
            name = getattr(robot, key)
            assert name is not None, f"{robot.namespace} has no {key}"
            assert world.station(name).kind == kind
    start = world.robots[0].start
    assert not any(s.contains(start.x_m, start.y_m) for s in world.stations_of_kind("charging"))


def test_a_path_loads_like_a_name(tmp_path: Path) -> None:
    path = write(tmp_path, "name: t\nfloor: {size_m: [3, 3]}\n")
    assert load_world(path).name == "t"
    assert load_world(str(path)).robots == []


def test_a_wrong_type_names_file_key_path_and_expectation(tmp_path: Path) -> None:
    path = write(tmp_path, """
name: bad
floor: {size_m: [6, 4]}
robots:
  - {namespace: a, kind: emili, start: {x_m: 1, y_m: 1}}
  - {namespace: b, kind: kobuki, start: {x_m: left, y_m: 1}}
""")
    with pytest.raises(WorldError) as caught:
        load_world(path)
    message = str(caught.value)
    assert str(path) in message
    assert "robots.1.start.x_m" in message
    assert "number" in message and "'left'" in message


def test_every_problem_is_reported_at_once() -> None:
    data = minimal(floor={"size_m": [6, "wide"]}, lanes=[{"name": "l", "points_m": [[0, 0]]}])
    with pytest.raises(WorldError) as caught:
        world_from_dict(data, source="inline.yaml")
    problems = caught.value.problems
    assert any(p.startswith("floor.size_m.1:") for p in problems), problems
    assert any(p.startswith("lanes.0.points_m:") and "at least 2" in p for p in problems)
    assert caught.value.path == "inline.yaml"


def test_an_unknown_key_is_a_typo() -> None:
    with pytest.raises(WorldError, match=r"walls\.0\.thikness_m: unknown key"):
        world_from_dict(minimal(walls=[{"from_m": [0, 0], "to_m": [1, 0], "thikness_m": 1}]))


def test_a_missing_key_is_named() -> None:
    with pytest.raises(WorldError, match=r"robots\.0\.start: required key missing"):
        world_from_dict(minimal(robots=[{"namespace": "e", "kind": "emili"}]))


def test_an_unknown_robot_kind_lists_the_kinds() -> None:
    with pytest.raises(WorldError, match=r"robots\.0\.kind: .*'emili'.*'kobuki'.*'husky'"):
        world_from_dict(minimal(robots=[{"namespace": "h", "kind": "husky",
                                         "start": {"x_m": 1, "y_m": 1}}]))


def test_an_unknown_station_reference_lists_the_stations() -> None:
    robots = [{"namespace": "e", "kind": "emili", "start": {"x_m": 1, "y_m": 1},
               "charging_station": "garage"}]
    with pytest.raises(WorldError, match=r"robots\.0\.charging_station: unknown station "
                                         r"'garage'; stations: 'dock'"):
        world_from_dict(minimal(robots=robots))


def test_looking_up_an_unknown_station_lists_the_stations() -> None:
    world = world_from_dict(minimal())
    with pytest.raises(UnknownStation, match=r"unknown station 'garage'; registered: 'dock'"):
        world.station("garage")


def test_duplicate_namespaces_are_rejected() -> None:
    robot = {"namespace": "e", "kind": "emili", "start": {"x_m": 1, "y_m": 1}}
    with pytest.raises(WorldError, match=r"duplicate robot namespaces \['e'\]"):
        world_from_dict(minimal(robots=[robot, robot]))


def test_an_unknown_world_name_lists_the_shipped_worlds() -> None:
    with pytest.raises(UnknownWorld, match=r"unknown world 'moon'; registered: .*'warehouse'"):
        load_world("moon")


def test_broken_yaml_names_the_file(tmp_path: Path) -> None:
    path = write(tmp_path, "name: [unclosed\n")
    with pytest.raises(WorldError, match=r"(?s)bad\.yaml.*not valid YAML"):
        load_world(path)
    with pytest.raises(WorldError, match=r"expected a mapping, got list"):
        load_world(write(tmp_path, "- 1\n- 2\n"))


def test_holes_are_cut_out_of_the_floor() -> None:
    world = world_from_dict(minimal(holes=[{"center_m": [3, 2], "size_m": [1, 1]}]))
    rects = world.floor_rects()
    area = sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in rects)
    assert area == pytest.approx(6 * 4 - 1)
    assert not any(x0 < 3 < x1 and y0 < 2 < y1 for x0, y0, x1, y1 in rects)


def test_a_rotated_station_contains_points_in_its_own_frame() -> None:
    world = world_from_dict(minimal(stations=[{"name": "s", "kind": "pickup",
                                               "center_m": [0, 0], "size_m": [2.0, 0.2],
                                               "yaw_deg": 90}]))
    station = world.station("s")
    assert station.contains(0.0, 0.9)
    assert not station.contains(0.9, 0.0)
