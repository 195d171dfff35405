"""Breakpoints (issue 28, item 4): on a state, a tree node or an action type the robot
pauses when it gets there; "continue" lets it go on. Over HTTP as a plain client sees it
(httpx against a real uvicorn server): set, list, the 4xx naming the valid choices, the
token rules, the structure of the engines that the graphs draw."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

pytest.importorskip("transitions")
pytest.importorskip("py_trees")
pytest.importorskip("fastapi")
httpx = pytest.importorskip("httpx")

from beehave import HighLevelBehaviorManager  # noqa: E402
from beehave.breakpoints import Breakpoints, UnknownBreakpointTarget  # noqa: E402
from beehave.breakpoints import of as breakpoints_of  # noqa: E402
from beehave.engines import EngineBehavior  # noqa: E402
from beehave.errors import BadRequest  # noqa: E402
from beehave.interfaces import ControlPlane  # noqa: E402
from beehave.interfaces.http import TOKEN_ENV, HttpServer  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until, wall_timeout  # noqa: E402
from behaviours.demos.graphs import delivery_machine, patrol_tree  # noqa: E402
from tests.http_fixtures import served  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_breakpoints")

#: conftest's ``hl`` fixture, with a stop timeout for a loaded machine: a breakpoint pauses
#: the robot through its actions' safe states (see test_http_graph, where 0.3 s failed).
HL_STOP_TIMEOUT_S = wall_timeout(0.05)


@pytest.fixture
def robot(hl: HighLevelBehaviorManager) -> HighLevelBehaviorManager:
    hl.register("delivery", EngineBehavior, engine=delivery_machine())
    hl.register("patrol", EngineBehavior, engine=patrol_tree())
    hl.blackboard.set("battery/percentage", 80.0)
    return hl


@pytest.fixture
def points(robot: HighLevelBehaviorManager) -> Iterator[Breakpoints]:
    bps = Breakpoints(robot)
    yield bps
    bps.close()


def test_a_state_breakpoint_pauses_on_entry_and_continue_goes_on(
        robot: HighLevelBehaviorManager, points: Breakpoints) -> None:
    points.add("state", "pick")
    robot.switch("delivery")
    assert wait_until(lambda: robot.paused)
    assert points.hit is not None
    assert points.hit["kind"] == "state" and points.hit["target"] == "pick"
    assert robot.top is not None and robot.top.engine.state == "pick"
    points.remove("state", "pick")
    assert points.resume()
    assert wait_until(lambda: not robot.paused and robot.top.engine.state == "to_drop")
    assert points.hit is None


def test_an_action_type_breakpoint_pauses_before_the_action_and_continue_runs_it(
        robot: HighLevelBehaviorManager, points: Breakpoints) -> None:
    points.add("action_type", "waiting")
    robot.switch("delivery")
    assert wait_until(lambda: robot.paused)
    hit = points.hit
    assert hit is not None and hit["kind"] == "action_type" and hit["target"] == "waiting"
    assert hit["path"].startswith("delivery/"), hit
    assert robot.top.engine.state == "pick"  # the first state with a waiting action
    points.clear()
    points.resume()
    assert wait_until(lambda: robot.top.engine.state == "to_drop")


def test_a_tree_node_breakpoint_by_name_pauses_when_the_leaf_starts(
        robot: HighLevelBehaviorManager, points: Breakpoints) -> None:
    points.add("node", "look")
    robot.switch("patrol")
    assert wait_until(lambda: robot.paused)
    assert points.hit is not None and points.hit["target"] == "look"
    statuses = {n["path"]: n["status"] for n in robot.top.engine.describe()["nodes"]}
    assert statuses["root/patrol/look"] == "RUNNING", statuses
    assert statuses["root/patrol/to B"] == "INVALID", statuses  # it stopped there
    points.clear()
    points.resume()
    assert wait_until(lambda: not robot.paused)


def test_unknown_targets_and_kinds_are_refused_naming_the_valid_ones(
        robot: HighLevelBehaviorManager, points: Breakpoints) -> None:
    with pytest.raises(UnknownBreakpointTarget) as caught:
        points.add("state", "pikc")
    text = str(caught.value)
    assert "'pick'" in text and "'to_drop'" in text and "'pikc'" in text
    with pytest.raises(UnknownBreakpointTarget, match="'driving'"):
        points.add("action_type", "drivng")
    with pytest.raises(UnknownBreakpointTarget, match="'root/patrol/look'"):
        points.add("node", "nope")
    with pytest.raises(BadRequest, match="'state', 'node', 'action_type'"):
        points.add("transition", "x")


@pytest.fixture
def server(robot: HighLevelBehaviorManager, monkeypatch: pytest.MonkeyPatch
           ) -> Iterator[HttpServer]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with served(robot) as srv:
        yield srv


def test_http_breakpoint_pause_where_and_continue(
        server: HttpServer, robot: HighLevelBehaviorManager) -> None:
    api = f"http://127.0.0.1:{server.port}/api/robots/emili1"
    with httpx.Client(timeout=WALL_TIMEOUT_S) as client:
        listed = client.get(f"{api}/breakpoints").json()
        assert "pick" in listed["choices"]["state"]
        assert "waiting" in listed["choices"]["action_type"]
        answer = client.post(f"{api}/breakpoints", json={"kind": "state", "target": "drop"})
        assert answer.status_code == 201, answer.text
        assert answer.json()["breakpoints"]["state"] == ["drop"]
        client.post(f"{api}/switch", json={"behavior": "delivery"})
        assert wait_until(lambda: client.get(f"{api}/breakpoints").json()["hit"] is not None)
        where = client.get(f"{api}/breakpoints").json()
        assert where["paused"] is True
        assert where["hit"]["kind"] == "state" and where["hit"]["target"] == "drop"
        status = client.get(f"{api}/status").json()
        assert status["paused"] is True
        assert [e["state"] for e in status["engines"]] == ["drop"]
        removed = client.post(f"{api}/breakpoints/remove",
                              json={"kind": "state", "target": "drop"}).json()
        assert removed["breakpoints"]["state"] == []
        assert client.post(f"{api}/continue", json={}).json() == {"resumed": True}
        assert wait_until(lambda: not client.get(f"{api}/status").json()["paused"])


def test_http_bad_breakpoints_get_4xx_naming_the_choices(server: HttpServer) -> None:
    api = f"http://127.0.0.1:{server.port}/api/robots/emili1"
    with httpx.Client(timeout=WALL_TIMEOUT_S) as client:
        unknown = client.post(f"{api}/breakpoints", json={"kind": "state", "target": "pikc"})
        assert unknown.status_code == 404
        assert "'pick'" in unknown.json()["detail"] and "'to_drop'" in unknown.json()["detail"]
        kind = client.post(f"{api}/breakpoints", json={"kind": "edge", "target": "pick"})
        assert kind.status_code == 400 and "'action_type'" in kind.json()["detail"]
        shape = client.post(f"{api}/breakpoints", json={"kind": "state"})
        assert shape.status_code == 422 and "target" in shape.json()["detail"]
        action = client.post(f"{api}/breakpoints",
                             json={"kind": "action_type", "target": "flying"})
        assert action.status_code == 404 and "'driving'" in action.json()["detail"]


def test_http_hostile_breakpoint_bodies_get_4xx_naming_the_problem(
        server: HttpServer, robot: HighLevelBehaviorManager) -> None:
    """What a plain client may send: empty, huge, non-string, unicode, extra fields,
    malformed JSON, a remove with a typo (which would leave the meant breakpoint set)."""
    api = f"http://127.0.0.1:{server.port}/api/robots/emili1"
    robot.switch("delivery")
    with httpx.Client(timeout=WALL_TIMEOUT_S) as client:
        assert wait_until(lambda: "pick" in client.get(f"{api}/breakpoints").json()["choices"]
                          ["state"])
        for body, status, named in [
                ({"kind": "state", "target": ""}, 400, "1 to 500 characters"),
                ({"kind": "state", "target": "p" * 501}, 400, "1 to 500 characters"),
                ({"kind": "state", "target": "p" * 70_000}, 413, "65536 bytes"),
                ({"kind": "state", "target": 5}, 422, "body.target"),
                ({"kind": ["state"], "target": "pick"}, 422, "body.kind"),
                ({"kind": "state", "target": None}, 422, "body.target"),
                ({"kind": "state", "target": "pick", "once": True}, 422, "body.once"),
                ({"kind": "state", "target": "pïck"}, 404, "'pick'"),
                ([1, 2], 422, "valid dictionary")]:
            answer = client.post(f"{api}/breakpoints", json=body)
            assert answer.status_code == status, (body, answer.text)
            assert named in answer.json()["detail"], (body, answer.text)
        answer = client.post(f"{api}/breakpoints", content=b'{"kind": "state",',
                             headers={"Content-Type": "application/json"})
        assert answer.status_code == 422 and "JSON" in answer.json()["detail"]
        assert client.post(f"{api}/breakpoints",
                           json={"kind": "state", "target": "drop"}).status_code == 201
        typo = client.post(f"{api}/breakpoints/remove", json={"kind": "state", "target": "dorp"})
        assert typo.status_code == 404, typo.text
        assert "'dorp'" in typo.json()["detail"] and "'drop'" in typo.json()["detail"]
        unset = client.post(f"{api}/breakpoints/remove", json={"kind": "state", "target": "pick"})
        assert unset.status_code == 200, unset.text  # a valid one not set: nothing to do
        assert unset.json()["breakpoints"]["state"] == ["drop"]
        kind = client.post(f"{api}/breakpoints/remove", json={"kind": "edge", "target": "x"})
        assert kind.status_code == 400 and "'action_type'" in kind.json()["detail"]


def test_breakpoint_endpoints_off_loopback_need_the_token(
        robot: HighLevelBehaviorManager, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    # 0.0.0.0 listens on every interface; the test talks to it over loopback only.
    with served(robot, host="0.0.0.0", token="t0ken") as srv, \
            httpx.Client(timeout=WALL_TIMEOUT_S) as client:
        api = f"http://127.0.0.1:{srv.port}/api/robots/emili1"
        body = {"kind": "state", "target": "pick"}
        for method, path, payload in (("GET", "/breakpoints", None),
                                      ("POST", "/breakpoints", body),
                                      ("POST", "/breakpoints/remove", body),
                                      ("POST", "/continue", {}),
                                      ("GET", "/structure", None)):
            refused = client.request(method, api + path, json=payload)
            assert refused.status_code == 401, (path, refused.text)
            wrong = client.request(method, api + path, json=payload,
                                   headers={"Authorization": "Bearer nope"})
            assert wrong.status_code == 401, (path, wrong.text)
        points = breakpoints_of(robot)
        assert points is None or points.listing()["state"] == []  # nothing was set
        ok = client.post(api + "/breakpoints", json=body,
                         headers={"Authorization": "Bearer t0ken"})
        assert ok.status_code == 201, ok.text
        assert ok.json()["breakpoints"]["state"] == ["pick"]


def test_the_structure_endpoint_gives_states_labelled_transitions_and_tree_nodes(
        server: HttpServer, robot: HighLevelBehaviorManager) -> None:
    """Item 1's data: the structure once (by structure_id), the statuses per update."""
    api = f"http://127.0.0.1:{server.port}/api/robots/emili1"
    with httpx.Client(timeout=WALL_TIMEOUT_S) as client:
        client.post(f"{api}/switch", json={"behavior": "delivery"})
        assert wait_until(lambda: client.get(f"{api}/status").json()["engines"])
        engine = client.get(f"{api}/status").json()["engines"][0]
        structure = client.get(f"{api}/structure").json()["engines"][0]
        assert structure["structure_id"] == engine["structure_id"]
        assert structure["path"] == engine["path"] == "delivery"
        assert {s["name"] for s in structure["states"]} >= {"to_pick", "pick", "done"}
        labels = {(t["source"], t["dest"]): t["label"] for t in structure["transitions"]}
        assert labels[("drop", "charge")] == "succeeded [battery/percentage < 20]"
        assert labels[("*", "done")] == "abort"
        assert "nodes" not in engine and "transitions" not in engine  # not in every update
        client.post(f"{api}/switch", json={"behavior": "patrol"})
        assert wait_until(lambda: [e["kind"] for e in client.get(f"{api}/status").json()
                                   ["engines"]] == ["behaviour_tree"])
        seen: list[dict[str, Any]] = []

        def tree_shown() -> bool:  # the structure is read apart from the status: ask again
            seen[:] = client.get(f"{api}/structure").json()["engines"]
            return bool(seen) and "nodes" in seen[0]

        assert wait_until(tree_shown), seen
        tree = seen[0]
        names = [n["name"] for n in tree["nodes"]]
        parents = {n["name"]: names[n["parent"]] if n["parent"] is not None else None
                   for n in tree["nodes"]}
        assert parents["look"] == "patrol" and parents["patrol"] == "root"
        assert tree["nodes"][0]["type"] == "Selector"


def test_breakpoints_set_through_a_second_plane_hold_after_the_first_plane_closed(
        robot: HighLevelBehaviorManager) -> None:
    """Two planes of one manager (e.g. VDA 5050's own and the robot's HTTP one): the
    first made the breakpoints and closed them with itself; the second's still pause."""
    first, second = ControlPlane(robot, name="emili1"), ControlPlane(robot, name="emili1")
    try:
        first.set_breakpoint("state", "drop")  # the first plane makes them
        assert second.breakpoints()["breakpoints"]["state"] == ["drop"]  # shared
        first.close()  # its Breakpoints go with it
        second.set_breakpoint("state", "pick")
        robot.switch("delivery")
        assert wait_until(lambda: robot.paused), "the second plane's breakpoint did not hold"
        assert second.breakpoints()["hit"]["target"] == "pick"
        assert second.continue_() == {"resumed": True}
    finally:
        first.close()
        second.close()
