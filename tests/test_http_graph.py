"""The web view's graphs and breakpoints (issue 28, items 1 and 4) in a real browser:
Debian's chromium driven by playwright against a real server in this process.

A state machine is drawn as a graph (every state a node, every transition an edge labelled
with its event and conditions, the active state highlighted), a tree as a tree (each child
below its parent, nodes coloured by status); a nested machine sits in a box that a click
collapses; the wheel zooms and a drag pans; a breakpoint set from the page pauses the robot
and "Continue" resumes it. The checks read the page (``beehaveGraph.inspect``: what
cytoscape drew, where) and the screenshot's pixels (the colours a user sees at the nodes).

Screenshots go to out/; with BEEHAVE_DOCS_IMG=1 they are also written to docs/img/ (the
pictures of docs/http.md).
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("transitions")
pytest.importorskip("py_trees")
pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")
sync_api = pytest.importorskip("playwright.sync_api")
Image = pytest.importorskip("PIL.Image")
numpy = pytest.importorskip("numpy")

from beehave import HighLevelBehaviorManager  # noqa: E402
from beehave.engines import EngineBehavior  # noqa: E402
from beehave.interfaces.http import TOKEN_ENV, HttpServer  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until, wall_timeout  # noqa: E402
from behaviours.demos.graphs import delivery_machine, patrol_tree  # noqa: E402
from tests.chromium import CHROMIUM, chromium  # noqa: E402
from tests.http_fixtures import served  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_http_graph")

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "out"
DOCS_IMG = ROOT / "docs" / "img"
WAIT_MS = WALL_TIMEOUT_S * 1000
ACTIVE = (0xF2, 0xB0, 0x1E)  # graph.js: the active state's fill
STATUS = {"RUNNING": (0x2F, 0x7D, 0xE1), "SUCCESS": (0x2E, 0x9E, 0x4F)}
SIZES = {"desktop": {"width": 1280, "height": 800}, "phone": {"width": 390, "height": 844}}

if not Path(CHROMIUM).exists():  # pragma: no cover - `make setup` installs it
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)

LOOP_WINDOW_MS = 1000  # long enough for dozens of requests on loopback
INSPECT = "beehaveGraph.inspect(document.querySelector('#graphs'))"



def _empty_spot(seen: dict[str, Any]) -> tuple[float, float, float, float]:
    """A point of the canvas 20 px clear of every node and edge with its label (what a
    press there would hit), nearest the canvas's edge, and a drag step (pixels) towards
    the canvas's centre from there."""
    canvas = seen["canvas"]
    boxes = [e["box"] for e in seen["nodes"] + seen["edges"] if e["visible"]]
    left, top = canvas["x"] + 8, canvas["y"] + 8
    w, h = canvas["width"] - 16, canvas["height"] - 16
    spots = sorted(((fx / 8, fy / 8) for fx in range(9) for fy in range(9)),
                   key=lambda f: min(f[0], 1 - f[0], f[1], 1 - f[1]))
    for fx, fy in spots:
        x, y = left + fx * w, top + fy * h
        if all(x < b["x1"] - 20 or x > b["x2"] + 20 or y < b["y1"] - 20 or y > b["y2"] + 20
               for b in boxes):
            return x, y, (12 if fx < 0.5 else -12), (8 if fy < 0.5 else -8)
    raise AssertionError(f"no empty spot on the canvas: {canvas} {boxes}")


#: conftest's ``hl`` fixture, with a stop timeout for a loaded machine: a breakpoint
#: pauses the tree through its actions' safe states, and an action whose thread got no CPU
#: for conftest's 0.3 s was declared STUCK and failed the tree (a stress run).
HL_STOP_TIMEOUT_S = wall_timeout(0.05)


@pytest.fixture
def robot(hl: HighLevelBehaviorManager) -> HighLevelBehaviorManager:
    hl.register("delivery", EngineBehavior, engine=delivery_machine())
    hl.register("patrol", EngineBehavior, engine=patrol_tree())
    hl.blackboard.set("battery/percentage", 10.0)  # the delivery goes to charge
    return hl


@pytest.fixture
def server(robot: HighLevelBehaviorManager, monkeypatch: pytest.MonkeyPatch
           ) -> Iterator[HttpServer]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with served(robot) as srv:
        yield srv


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as b:
        yield b


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    context = browser.new_context(viewport=SIZES["desktop"])
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    yield page
    context.close()
    assert not errors, errors


def open_graph(page: Any, srv: HttpServer, engines: int) -> dict[str, Any]:
    page.goto(srv.url)
    page.wait_for_function(f"document.querySelector('#graphs') && "
                           f"+document.querySelector('#graphs').dataset.engines === {engines}"
                           f" && +document.querySelector('#graphs').dataset.nodes > 2",
                           timeout=WAIT_MS)
    return page.evaluate(INSPECT)


def set_breakpoint(page: Any, kind: str, target: str) -> None:
    page.select_option("#breakpoints .bp-kind", kind)
    page.fill("#breakpoints .bp-target", target)
    page.click("#breakpoints .bp-add")
    page.wait_for_selector(f'#breakpoints li[data-kind="{kind}"][data-target="{target}"]',
                           timeout=WAIT_MS)


def share(png: bytes, node: dict[str, Any], colour: tuple[int, int, int]) -> float:
    """The share of the pixels in ``node``'s box (as the page reports it) that have
    ``colour``: its fill, where the label's letters and the border leave it visible."""
    image = Image.open(io.BytesIO(png)).convert("RGB")
    c, size = node["center"], node["size"]
    box = (round(c["x"] - size["w"] / 2), round(c["y"] - size["h"] / 2),
           round(c["x"] + size["w"] / 2), round(c["y"] + size["h"] / 2))
    pixels = numpy.asarray(image.crop(box), dtype=int).reshape(-1, 3)
    close = (numpy.abs(pixels - numpy.array(colour)) <= 40).all(axis=1)
    return float(close.mean()) if len(pixels) else 0.0


def node_by(graph: dict[str, Any], **match: Any) -> dict[str, Any]:
    found = [n for n in graph["nodes"] if all(n.get(k) == v for k, v in match.items())]
    assert len(found) == 1, (match, [n["id"] for n in graph["nodes"]])
    return found[0]


def save(page: Any, name: str) -> bytes:
    png = page.screenshot(full_page=False)
    OUT.mkdir(exist_ok=True)
    (OUT / name).write_bytes(png)
    if os.environ.get("BEEHAVE_DOCS_IMG") == "1":
        page.locator("#graph-panel").screenshot(path=str(DOCS_IMG / name))
    return png


def test_a_state_machine_is_a_graph_with_labelled_transitions_and_its_active_state_lit(
        server: HttpServer, page: Any, robot: HighLevelBehaviorManager) -> None:
    page.goto(server.url)
    page.wait_for_selector("#breakpoints .bp-add", timeout=WAIT_MS)
    # Stop inside the nested charging machine: both engines run, nothing moves on.
    set_breakpoint(page, "state", "charge")
    robot.switch("delivery")
    assert wait_until(lambda: robot.paused)
    page.wait_for_selector('#breakpoints .bp-hit[data-hit="state:charge"]', timeout=WAIT_MS)
    page.wait_for_function(f"{INSPECT}.nodes.some(n => n.classes.includes('hit'))",
                           timeout=WAIT_MS)
    page.locator("#graph-panel").scroll_into_view_if_needed()
    graph = page.evaluate(INSPECT)
    outer = {n["state"] for n in graph["nodes"] if n["engine"] == "delivery" and n["state"]}
    assert outer == {"to_pick", "pick", "to_drop", "drop", "charge", "done"}
    labels = {(e["source"], e["target"]): e["label"] for e in graph["edges"]}
    ids = {n["state"]: n["id"] for n in graph["nodes"] if n["engine"] == "delivery"}
    assert labels[(ids["drop"], ids["charge"])] == "succeeded [battery/percentage < 20]"
    assert labels[(ids["drop"], ids["to_pick"])] == "succeeded"
    any_state = node_by(graph, label="any state", engine="delivery")
    assert labels[(any_state["id"], ids["done"])] == "abort"
    # The active state is the engine's, highlighted; the others are not.
    engine_state = robot.top.engine.state
    assert engine_state == "charge"
    lit = [n["state"] for n in graph["nodes"] if "active" in n["classes"]
           and n["engine"] == "delivery"]
    assert lit == ["charge"]
    png = save(page, "graph-state-machine.png")
    charge = node_by(graph, state="charge", engine="delivery")
    # Its fill, around the letters (a quarter is plenty: no other node has this colour).
    assert share(png, charge, ACTIVE) > 0.25, share(png, charge, ACTIVE)
    pick = node_by(graph, state="pick", engine="delivery")
    assert share(png, pick, ACTIVE) < 0.05 and share(png, pick, (255, 255, 255)) > 0.25
    # The nested machine is in a box; a click on the box collapses and expands it.
    boxes = [n for n in graph["nodes"] if "engine" in n["classes"]]
    assert len(boxes) == 1, boxes
    box = boxes[0]
    assert box["engine"].startswith("delivery/charging"), box
    nested = {n["state"] for n in graph["nodes"]
              if n["engine"] == box["engine"] and n["id"] != box["id"] and n["state"]}
    assert nested == {"dock", "charge", "undock", "charged"}
    x0 = box["center"]["x"] - box["size"]["w"] / 2 + 4
    y0 = box["center"]["y"] - box["size"]["h"] / 2 + 4
    page.mouse.click(x0, y0)
    page.wait_for_function(f"{INSPECT}.nodes.filter(n => n.engine && n.engine !== 'delivery'"
                           f").length === 1", timeout=WAIT_MS)  # the box alone
    collapsed = next(n for n in page.evaluate(INSPECT)["nodes"]
                     if "collapsed" in n["classes"])
    page.mouse.click(collapsed["center"]["x"], collapsed["center"]["y"])
    page.wait_for_function(f"{INSPECT}.nodes.filter(n => n.engine && n.engine !== 'delivery'"
                           f").length === 6", timeout=WAIT_MS)  # box, initial, 4 states
    # Continue from the page: the machine goes on.
    page.click("#breakpoints .bp-remove")
    page.wait_for_function("!document.querySelector('#breakpoints li[data-kind]')",
                           timeout=WAIT_MS)
    page.click("#breakpoints .bp-continue")
    assert wait_until(lambda: not robot.paused)
    assert wait_until(lambda: robot.top.engine.state not in (None, "charge"))


def test_a_tree_is_drawn_top_down_coloured_by_status_and_composites_collapse(
        server: HttpServer, page: Any, robot: HighLevelBehaviorManager) -> None:
    robot.blackboard.set("battery/percentage", 80.0)
    page.goto(server.url)
    page.wait_for_selector("#breakpoints .bp-add", timeout=WAIT_MS)
    set_breakpoint(page, "node", "to B")
    robot.switch("patrol")
    assert wait_until(lambda: robot.paused)
    page.locator("#graph-panel").scroll_into_view_if_needed()
    statuses = {n["path"]: n["status"] for n in robot.top.engine.describe()["nodes"]}
    assert statuses["root/patrol/to B"] == "RUNNING"
    page.wait_for_function(
        f"{INSPECT}.nodes.some(n => n.path === 'root/patrol/to B' && n.status === 'RUNNING')"
        f" && {INSPECT}.nodes.some(n => n.classes.includes('hit'))", timeout=WAIT_MS)
    graph = page.evaluate(INSPECT)
    nodes = {n["path"]: n for n in graph["nodes"] if n["path"]}
    assert set(nodes) == set(statuses)
    for path, status in statuses.items():  # the page shows what the engine says
        assert nodes[path]["status"] == status, (path, nodes[path]["status"], status)
    # Drawn as a tree: one edge per child, each child below its parent.
    by_id = {n["id"]: n for n in graph["nodes"]}
    assert len(graph["edges"]) == len(nodes) - 1
    for edge in graph["edges"]:
        assert by_id[edge["target"]]["center"]["y"] > by_id[edge["source"]]["center"]["y"]
    # Children left to right in their order (the order a sequence ticks them).
    xs = [nodes[f"root/patrol/{leaf}"]["center"]["x"] for leaf in ("to A", "look", "to B",
                                                                     "to C")]
    assert xs == sorted(xs), xs
    assert nodes["root/charge?"]["center"]["x"] < nodes["root/patrol"]["center"]["x"]
    png = save(page, "graph-tree.png")
    for path in ("root/patrol/to A", "root/patrol/to B"):
        want = STATUS["SUCCESS" if path.endswith("A") else "RUNNING"]
        assert share(png, nodes[path], want) > 0.25, (path, share(png, nodes[path], want))
    # Collapse the "patrol" sequence by clicking it: its four leaves disappear.
    patrol = nodes["root/patrol"]
    page.mouse.click(patrol["center"]["x"], patrol["center"]["y"])
    page.wait_for_function(f"!{INSPECT}.nodes.some(n => n.path && n.path.startsWith("
                           f"'root/patrol/'))", timeout=WAIT_MS)
    assert page.evaluate(f"{INSPECT}.nodes.find(n => n.path === 'root/charge?/dock').visible")
    after = page.evaluate(INSPECT)
    assert [n["label"] for n in after["nodes"] if n["path"] == "root/patrol"] == [
        "patrol (Sequence, memory) (+4)"]
    page.click("#breakpoints .bp-continue")
    assert wait_until(lambda: not robot.paused)


def test_zoom_with_the_wheel_and_pan_by_dragging(
        server: HttpServer, page: Any, robot: HighLevelBehaviorManager) -> None:
    robot.blackboard.set("battery/percentage", 80.0)  # no nested machine: one layout
    # Tall enough to show the graph without scrolling: cytoscape takes a wheel turn for
    # the page's while the page scrolls (and for 250 ms after).
    page.set_viewport_size({"width": 1280, "height": 1400})
    robot.switch("delivery")
    graph = open_graph(page, server, 1)
    canvas = graph["canvas"]
    x, y = canvas["x"] + canvas["width"] / 2, canvas["y"] + canvas["height"] / 2
    page.mouse.move(x, y)

    def zoomed_in() -> bool:  # a turn zooms by a few per cent: turn until it shows
        page.mouse.wheel(0, -400)
        return page.evaluate(INSPECT)["zoom"] > graph["zoom"] * 1.1

    assert wait_until(zoomed_in), "the wheel did not zoom the graph"
    tries: list[dict[str, Any]] = []

    def dragged() -> bool:
        """Drag from an empty spot (zoomed in, nodes and edges cover much of the canvas,
        and a press on an element does not pan): the whole graph moves with the pointer.
        A drag the page took for something else is tried again, as a user would; what
        each try saw is in the failure message."""
        # Settled: no wheel turn or drag still on its way changes the view under the drag.
        page.wait_for_timeout(300)
        before = page.evaluate(INSPECT)
        sx, sy, dx, dy = _empty_spot(before)
        page.mouse.move(sx, sy)
        page.mouse.down()
        for step in range(1, 6):
            page.mouse.move(sx + dx * step, sy + dy * step)
        page.mouse.up()
        # Input events are handled before the next frames are drawn: two frames later
        # the drag has had its effect.
        page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
        after = page.evaluate(INSPECT)
        tries.append({"from": (sx, sy), "step": (dx, dy), "pan": (before["pan"], after["pan"]),
                      "zoom": (before["zoom"], after["zoom"])})
        return abs(after["pan"]["x"] - before["pan"]["x"]) > 30

    assert any(dragged() for _ in range(5)), f"dragging did not pan the graph: {tries}"
    zoomed, panned = ({"pan": tries[-1]["pan"][i], "zoom": tries[-1]["zoom"][i]}
                      for i in (0, 1))
    dx, dy = tries[-1]["step"]
    assert panned["zoom"] == zoomed["zoom"], (panned["zoom"], zoomed["zoom"])
    # With the pointer (5 steps of dx, dy), less what a drag's start threshold keeps.
    moved_x = (panned["pan"]["x"] - zoomed["pan"]["x"]) * (1 if dx > 0 else -1)
    moved_y = (panned["pan"]["y"] - zoomed["pan"]["y"]) * (1 if dy > 0 else -1)
    assert 40 <= moved_x <= 62 and 25 <= moved_y <= 42, (panned["pan"], zoomed["pan"], dx, dy)
    page.click('.bh-graph-tools button[data-action="fit"]')
    page.wait_for_function(f"{INSPECT}.zoom < {panned['zoom']}", timeout=WAIT_MS)


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("view", ["delivery", "patrol"])
def test_screenshot_of_each_view_at_desktop_and_phone_size(
        server: HttpServer, browser: Any, robot: HighLevelBehaviorManager,
        view: str, size: str) -> None:
    """The graph is inside the screen's width and its nodes are drawn where the page
    says they are (status / active colours found at their centres, in the pixels)."""
    robot.blackboard.set("battery/percentage", 80.0)
    context = browser.new_context(viewport=SIZES[size], device_scale_factor=1,
                                  is_mobile=size == "phone", has_touch=size == "phone")
    try:
        page = context.new_page()
        page.goto(server.url)
        page.wait_for_selector("#breakpoints .bp-add", timeout=WAIT_MS)
        stop_at = {"delivery": ("state", "to_drop"), "patrol": ("node", "look")}[view]
        set_breakpoint(page, *stop_at)
        robot.switch(view)
        assert wait_until(lambda: robot.paused)
        page.wait_for_function(f"{INSPECT} && {INSPECT}.nodes.some(n => "
                               f"n.classes.includes('hit'))", timeout=WAIT_MS)
        page.locator("#graph-panel").scroll_into_view_if_needed()
        graph = page.evaluate(INSPECT)
        canvas = graph["canvas"]
        assert canvas["x"] >= 0 and canvas["x"] + canvas["width"] <= SIZES[size]["width"]
        assert page.evaluate("document.documentElement.scrollWidth") <= SIZES[size]["width"]
        png = page.screenshot()
        name = f"graph-{view}-{size}.png"
        OUT.mkdir(exist_ok=True)
        (OUT / name).write_bytes(png)
        if os.environ.get("BEEHAVE_DOCS_IMG") == "1" and size == "phone":
            page.locator("#graph-panel").screenshot(path=str(DOCS_IMG / name))
        lit = [n for n in graph["nodes"] if "active" in n["classes"]
               or n["status"] == "RUNNING"]
        assert lit
        found = 0
        for node in lit:
            want = ACTIVE if "active" in node["classes"] else STATUS["RUNNING"]
            found += share(png, node, want) > 0.25
        assert found == len(lit), [(n["id"], n["classes"]) for n in lit]
        page.click("#breakpoints .bp-remove")
        page.click("#breakpoints .bp-continue")
        assert wait_until(lambda: not robot.paused)
    finally:
        context.close()


def test_a_structure_the_server_does_not_have_is_asked_for_once_not_in_a_loop(
        server: HttpServer, page: Any) -> None:
    """An engine that ended before the page asked for its structure: the page asks once
    (a snapshot naming a structure_id that GET …/structure does not list)."""
    page.goto(server.url)
    page.wait_for_selector("#graphs", state="attached", timeout=WAIT_MS)
    asked: list[str] = []
    page.on("request", lambda r: asked.append(r.url) if "/structure" in r.url else None)
    with page.expect_response(lambda r: "/structure" in r.url, timeout=WAIT_MS):
        page.evaluate("""(() => {
            const box = document.createElement('div');
            box.style.width = '300px'; box.style.height = '200px';
            document.body.appendChild(box);
            beehaveGraph.render(box, {engines: [{path: 'gone', structure_id: 'ended-1',
                                                 kind: 'state_machine'}]},
                                {robot: 'emili1'}); })()""")
    page.wait_for_timeout(LOOP_WINDOW_MS)  # a loop would ask again within milliseconds
    assert asked == [f"{server.url}api/robots/emili1/structure"]
