"""The web view's timeline, plots, recordings and fleet sequence diagram (issue 28 items 2,
3, 5) in a real chromium page.

- Live: the page keeps the robot's history; the slider shows a past moment (behaviour,
  running actions, type locks, blackboard, map as they were) and Live returns to now;
  blackboard values are plotted.
- ``beehave view FILE.mcap``: the same page plays a recording; what it shows at t is what
  ``beehave inspect --at t`` prints (and, for the blackboard, what the MCAP file holds, read
  with the plain ``mcap`` reader); commands are refused (405).
- A fleet: its robots and agents are listed and open a robot's full view; its messages are
  drawn as a sequence diagram, filtered by conversation.

Every view is shot at desktop (1280x800) and phone (390x844) size into out/ and checked
by its pixels (the plot's line colour, the arrows of the diagram) and its width.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")
pytest.importorskip("playwright.sync_api")
httpx = pytest.importorskip("httpx")
Image = pytest.importorskip("PIL.Image")
from mcap.reader import make_reader  # noqa: E402
from timeline_fixtures import Patrol, make_recording  # noqa: E402

from beehave import Action, HighLevelBehaviorManager  # noqa: E402
from beehave.engines import (  # noqa: E402
    EngineBehavior,
    StartLeaf,
    State,
    StateMachineEngine,
    Transition,
    TreeEngine,
)
from beehave.interfaces.http import TOKEN_ENV, HttpServer  # noqa: E402
from beehave.recording import Recorder  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402
from tests.chromium import CHROMIUM, chromium  # noqa: E402
from tests.http_fixtures import served  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_http_timeline")

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "out"
WAIT_MS = WALL_TIMEOUT_S * 1000
DESKTOP = {"width": 1280, "height": 800}
PHONE = {"width": 390, "height": 844}
BLUE = (0x2F, 0x7D, 0xE1)  # the first plotted series, the diagram's arrows

if not Path(CHROMIUM).exists():  # pragma: no cover - `make setup` installs it
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as launched:
        yield launched


def open_page(browser: Any, url: str, size: dict[str, int]) -> tuple[Any, list[str]]:
    phone = size["width"] < 500
    page = browser.new_page(viewport=size, device_scale_factor=1, is_mobile=phone,
                            has_touch=phone)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(url)
    return page, errors


def pixels_near(png: bytes, colour: tuple[int, int, int], *, tolerance: int = 40) -> int:
    """How many pixels of the picture are within ``tolerance`` of ``colour``."""
    image = Image.open(io.BytesIO(png)).convert("RGB")
    data = image.tobytes()
    return sum(1 for i in range(0, len(data), 3)
               if all(abs(data[i + c] - colour[c]) <= tolerance for c in range(3)))


_WIDER = """(width) => [...document.querySelectorAll('body *')]
  .filter((e) => e.getBoundingClientRect().right > width + 0.5)
  .filter((e) => ![...e.children].some((c) => c.getBoundingClientRect().right > width + 0.5))
  .slice(0, 8)
  .map((e) => `${e.tagName.toLowerCase()}${e.id ? '#' + e.id : ''}` +
              `${e.className && typeof e.className === 'string' ? '.' + e.className : ''}` +
              ` right=${Math.round(e.getBoundingClientRect().right)}` +
              ` "${(e.textContent || '').trim().slice(0, 60)}"`)"""


def fits(page: Any, width: int) -> None:
    scroll = page.evaluate("document.documentElement.scrollWidth")
    # When it does not fit, name the innermost elements that stick out (what overflows
    # depends on what the page shows at that moment).
    assert scroll <= width, (f"the page is {scroll} px wide on a {width} px screen: "
                             f"{page.evaluate(_WIDER, width)}")


def click_until(page: Any, selector: str, shown: str) -> None:
    """Click ``selector`` until the JavaScript expression ``shown`` is true. The live page
    may move the target between playwright's aim and its click (a panel above it grows
    with an update): beside two busy loops a click on a fleet member landed on the one
    above it. Clicking again is what a user does."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    for _ in range(5):
        page.click(selector)
        try:
            page.wait_for_function(shown, timeout=WAIT_MS / 5)
            return
        except PlaywrightTimeout:
            continue
    raise AssertionError(f"clicking {selector} 5 times never showed {shown}")


def shoot(page: Any, view: str, size: dict[str, int]) -> None:
    """Save the page as ``out/webview-{view}-{desktop|phone}.png``; it fits the screen."""
    OUT.mkdir(exist_ok=True)
    name = "desktop" if size is DESKTOP else "phone"
    page.screenshot(path=str(OUT / f"webview-{view}-{name}.png"))
    fits(page, size["width"])


def plot(page: Any, key: str, *, points_over: int) -> None:
    """Plot ``key``; it shows more than ``points_over`` points in the first series' blue."""
    page.fill("#plot-key", key)
    page.click("#plot-add")
    page.wait_for_function("Number(document.querySelector('#plot').dataset.points) > "
                           f"{points_over}", timeout=WAIT_MS)
    page.locator("#plot").scroll_into_view_if_needed()
    assert pixels_near(page.locator("#plot canvas").screenshot(), BLUE) > 200


def table(page: Any, selector: str) -> list[list[str]]:
    return page.evaluate(f"""[...document.querySelectorAll('{selector} tbody tr')]
        .map((r) => [...r.children].map((c) => c.textContent.trim()))""")


# ---- item 2: the live timeline and plots -------------------------------------------------

@pytest.fixture
def live(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[HttpServer, HighLevelBehaviorManager]]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        hl.register("patrol", Patrol)
        hl.blackboard.set("odom/x_m", 4.5, writer="hal:odometry")
        hl.blackboard.set("odom/y_m", 2.0, writer="hal:odometry")
        hl.blackboard.set("mission", "start", writer="test")
        with served(hl) as server:
            yield server, hl


@pytest.mark.parametrize("size", [DESKTOP, PHONE], ids=["desktop", "phone"])
def test_the_slider_shows_the_robot_as_it_was_and_live_returns_to_now(
        live: tuple[HttpServer, HighLevelBehaviorManager], browser: Any,
        size: dict[str, int]) -> None:
    server, hl = live
    page, errors = open_page(browser, server.url, size)
    page.wait_for_selector("#conn.up", timeout=WAIT_MS)
    # The socket is up before its first update has reached the timeline, which then writes
    # the bar for the first time (stress runs: the robot's history read undefined, and
    # that first write counted as a rewrite).
    page.wait_for_function("window.beehaveTimeline.robots.emili1 !== undefined"
                           " && document.querySelector('#timeline').dataset.at === 'live'",
                           timeout=WAIT_MS)
    # Live, the bar's clock, Live button and moment stay as they are: count rewrites.
    page.evaluate("""(() => {
        window.barWrites = [];
        const seen = new MutationObserver((ms) => window.barWrites.push(...ms.map(
            (m) => `${m.target.id || m.target.parentNode.id}:${m.attributeName || m.type}`)));
        seen.observe(document.querySelector('#tl-live'), {attributes: true});
        seen.observe(document.querySelector('#tl-time'),
                     {childList: true, characterData: true, subtree: true});
        seen.observe(document.querySelector('#timeline'),
                     {attributes: true, attributeFilter: ['data-at']}); })()""")
    updates = page.evaluate("window.beehaveTimeline.robots.emili1.snaps.length")
    hl.switch("patrol", laps=1.0)
    # The page saw the lap (its locks) and then the robot idle again.
    page.wait_for_selector('#locks tr[data-lock="driving"]', timeout=WAIT_MS)
    assert wait_until(lambda: hl.blackboard.get("patrol/done") is True)
    hl.switch("idle")
    hl.blackboard.set("mission", "done", writer="test")
    page.wait_for_function("document.querySelector('#current-behavior').textContent === 'idle'"
                           " && [...document.querySelectorAll('#blackboard tr[data-key=mission]"
                           " td')].some((c) => c.textContent === 'done')", timeout=WAIT_MS)
    assert page.evaluate("window.beehaveTimeline.robots.emili1.snaps.length") > updates + 10
    assert page.evaluate("window.barWrites") == []
    # The slider's moment where the lap ran: half-way between the first and the last
    # picture of it the page kept.
    offset = page.evaluate("""(() => {
        const snaps = window.beehaveTimeline.robots.emili1.snaps;
        const lap = snaps.filter(([, s]) => s.lock_details && s.lock_details.driving);
        const first = snaps[0][0];
        return (lap[0][0] + lap[lap.length - 1][0]) / 2 - first; })()""")
    slider = page.locator("#tl-slider")
    slider.evaluate("(s, v) => { s.value = v; s.dispatchEvent(new Event('input')); }",
                    f"{offset:.2f}")
    page.wait_for_function("document.querySelector('#tl-live').getAttribute('aria-pressed')"
                           " === 'false'", timeout=WAIT_MS)
    assert page.inner_text("#current-behavior") == "patrol"
    locks = {row[0]: row[1] for row in table(page, "#locks")}
    assert locks == {"driving": "patrol/Roll", "sound": "patrol/Beep"}
    running = page.eval_on_selector_all("#tree li", "ls => ls.map((l) => l.dataset.path)")
    assert running == ["patrol", "patrol/Beep", "patrol/Roll"]
    board = {row[0]: row[1] for row in table(page, "#blackboard")}
    assert board["mission"] == "start"
    x, y = float(board["odom/x_m"]), float(board["odom/y_m"])
    # A pose of the lap (a circle of 1.5 m about (3, 2)), and the marker is drawn there.
    assert math.hypot(x - 3.0, y - 2.0) == pytest.approx(1.5, abs=0.01)
    marker = page.locator("#robot-emili1")
    assert float(marker.get_attribute("data-x")) == pytest.approx(x, abs=0.002)
    assert float(marker.get_attribute("data-y")) == pytest.approx(y, abs=0.002)

    # Plots: the speed over the kept history, the moment marked.
    plot(page, "odom/x_m", points_over=20)
    shoot(page, "timeline", size)

    page.click("#tl-live")
    page.wait_for_function("document.querySelector('#current-behavior').textContent === "
                           "'idle'", timeout=WAIT_MS)
    board = {row[0]: row[1] for row in table(page, "#blackboard")}
    assert board["mission"] == "done"
    assert table(page, "#locks") == []
    page.close()
    assert not errors, errors


def test_the_kept_history_is_bounded_in_time_and_count(
        live: tuple[HttpServer, HighLevelBehaviorManager], browser: Any) -> None:
    """Eleven minutes of updates at 20 Hz (fed to the page's history as the stream would):
    the page keeps the last ten minutes, one picture per 0.1 s, 2000 changes per key."""
    server, _ = live
    page, errors = open_page(browser, server.url, DESKTOP)
    page.wait_for_selector("#conn.up", timeout=WAIT_MS)
    kept = page.evaluate("""(() => {
        const view = window.beehave, t0 = 1e9, state = {blackboard: {}};
        for (let i = 0; i < 11 * 60 * 20; i++) {
            const t = t0 + i / 20;
            const board = {"speed_mps": {value: i, stamp: t, stale: false, age_s: 0}};
            state.blackboard = board;
            view.onUpdate({type: "update", robot: "ghost", stamp: t, blackboard: board,
                           snapshot: {behavior: "drive"}, events: []}, state);
        }
        const h = window.beehaveTimeline.robots.ghost;
        return {first: h.snaps[0][0] - t0, last: h.snaps[h.snaps.length - 1][0] - t0,
                snaps: h.snaps.length, changes: h.keys.speed_mps.length,
                limits: window.beehaveTimeline.limits}; })()""")
    assert kept["limits"]["HISTORY_S"] == 600 and kept["limits"]["SNAPS_MAX"] == 6000
    assert kept["last"] == pytest.approx(11 * 60 - 0.05)
    assert kept["last"] - kept["first"] <= 600
    assert kept["snaps"] <= 6000 and kept["changes"] == 2000
    page.close()
    assert not errors, errors


# ---- item 3: a recording in the same page ------------------------------------------------

class ViewProcess:
    """``beehave view FILE.mcap --port 0`` in a process of its own."""

    def __init__(self, recording: Path) -> None:
        env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "beehave.cli", "view", str(recording), "--port", "0"],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.url = ""
        self._found = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            match = re.search(r" at (http://\S+)", line)
            if match:
                self.url = match.group(1)
                self._found.set()
        self._found.set()

    def stop(self) -> str:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:  # pragma: no cover - reported by the assert
            self.proc.kill()
            self.proc.wait(5)
        return "".join(self.lines)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_recording(tmp_path_factory.mktemp("timeline") / "patrol.mcap")


@contextlib.contextmanager
def viewing(recording: Path) -> Iterator[ViewProcess]:
    """``beehave view recording`` serving; on the way out it ends, and must end cleanly."""
    process = ViewProcess(recording)
    try:
        process._found.wait(WALL_TIMEOUT_S)
        assert process.url, "beehave view printed no URL:\n" + "".join(process.lines)
        yield process
    finally:
        output = process.stop()
    assert process.proc.returncode == 0, output


@pytest.fixture(scope="module")
def viewer(recording: Path) -> Iterator[ViewProcess]:
    with viewing(recording) as process:
        yield process


def inspect_at(recording: Path, t_s: float) -> dict[str, dict[str, Any]]:
    """``beehave inspect --at t``'s lines, parsed: robot → what it says of it."""
    done = subprocess.run([sys.executable, "-m", "beehave.cli", "inspect", str(recording),
                           "--at", f"{t_s}"], cwd=ROOT, capture_output=True, text=True,
                          timeout=WALL_TIMEOUT_S, check=True)
    robots: dict[str, dict[str, Any]] = {}
    for line in done.stdout.splitlines()[1:]:
        robot, _, fact = line.partition(" ")
        said = robots.setdefault(robot, {"running": [], "locks": {}, "blackboard": {}})
        what, _, rest = fact.partition(": ")
        if what == "behaviour":
            said["behavior"] = rest
        elif what == "running":
            said["running"].append(rest.split(" ")[0])
        elif what == "lock":
            kind, _, holder = rest.partition(" held by ")
            said["locks"][kind] = holder
        elif what == "blackboard":
            key, _, value = rest.partition(" = ")
            said["blackboard"][key] = value.rsplit(" (writer", 1)[0]
        elif what == "engine":  # "<path> (state_machine) state <name> (from …)"
            path, _, tail = rest.partition(" (")
            kind, _, facts = tail.partition(") ")
            said.setdefault("engines", {})[path] = (
                kind, facts.split(" ")[1] if facts.startswith("state ") else None)
        elif what == "node":  # "<engine path> <node path> <status>"
            engine, _, tail = rest.partition(" ")
            node, _, status = tail.rpartition(" ")
            said.setdefault("nodes", {})[(engine, node)] = status
    return robots


def inspect_timeline(recording: Path) -> list[tuple[float, str, str, str]]:
    """``beehave inspect``'s event timeline: (t, robot, kind, subject) per line."""
    done = subprocess.run([sys.executable, "-m", "beehave.cli", "inspect", str(recording),
                           "--limit", "1000"], cwd=ROOT, capture_output=True, text=True,
                          timeout=WALL_TIMEOUT_S, check=True)
    lines = done.stdout.split("event timeline", 1)[1].splitlines()[1:]
    return [(float(t), robot, kind, subject) for t, robot, _, kind, subject, *_ in
            (line.split() for line in lines if line.strip())]


def mcap_board(recording: Path, robot: str, t_s: float) -> dict[str, Any]:
    """The blackboard at ``t_s`` straight from the file (the plain MCAP reader)."""
    with open(recording, "rb") as f:
        messages = [(m.log_time, ch.topic, m.data) for _, ch, m in
                    make_reader(f).iter_messages(log_time_order=True)]
    start = messages[0][0]
    board = {}
    for t, topic, data in messages:
        if topic == f"/{robot}/beehave/blackboard" and t <= start + t_s * 1e9:
            change = json.loads(data)
            board[change["key"]] = change["value"]
    return board


def seek(page: Any, t_s: float) -> None:
    page.locator("#tl-slider").evaluate(
        "(s, v) => { s.value = v; s.dispatchEvent(new Event('input')); }", f"{t_s:.2f}")
    page.wait_for_function(f"document.querySelector('#timeline').dataset.shown === "
                           f"'{t_s:.2f}'.replace(/\\.?0+$/, '')", timeout=WAIT_MS)


@pytest.mark.parametrize("size", [DESKTOP, PHONE], ids=["desktop", "phone"])
def test_the_recorded_page_at_t_says_what_beehave_inspect_says_at_t(
        viewer: ViewProcess, recording: Path, browser: Any, size: dict[str, int]) -> None:
    page, errors = open_page(browser, viewer.url, size)
    page.wait_for_selector("body.recording", timeout=WAIT_MS)
    assert page.locator("#switch-btn").is_hidden()
    assert page.eval_on_selector_all("#robot-select option", "os => os.map((o) => o.value)") \
        == ["emili1", "kobuki1"]
    behaviours = set()
    timeline = inspect_timeline(recording)
    # The moments to look at come from the recording: its stamps are wall time, so a loaded
    # machine stretches the laps (kobuki1's half lap took 3.65 s beside two busy loops).
    # Two inside kobuki1's patrol, one between its switch to idle and emili1's.
    idle_at = {who: when for when, who, kind, subject in timeline
               if kind == "switch_completed" and subject == "idle"}
    assert set(idle_at) == {"emili1", "kobuki1"}, timeline
    moments = (round(idle_at["kobuki1"] / 4, 2), round(idle_at["kobuki1"] * 3 / 4, 2),
               round((idle_at["kobuki1"] + idle_at["emili1"]) / 2, 2))
    for robot in ("emili1", "kobuki1"):
        page.select_option("#robot-select", robot)
        for t_s in moments:
            seek(page, t_s)
            said = inspect_at(recording, t_s)[robot]
            behaviours.add((robot, t_s, said["behavior"]))
            assert page.inner_text("#current-behavior") == said["behavior"]
            running = page.eval_on_selector_all("#tree li",
                                                "ls => ls.map((l) => l.dataset.path)")
            assert running == said["running"]
            assert {row[0]: row[1] for row in table(page, "#locks")} == said["locks"]
            shown = {row[0]: row[1] for row in table(page, "#blackboard")}
            raw = mcap_board(recording, robot, t_s)
            assert set(shown) == set(said["blackboard"]) == set(raw)
            for key, text in said["blackboard"].items():
                value = json.loads(text)
                if isinstance(value, float):
                    assert float(shown[key]) == pytest.approx(value, abs=1e-3), key
                    assert raw[key] == pytest.approx(value, abs=1e-9), key
                else:  # a string as it is, anything else as JSON
                    assert shown[key] == (value if isinstance(value, str) else text), key
                    assert raw[key] == value, key
            # The events up to t: every line of inspect's timeline is in the list.
            listed = page.eval_on_selector_all(
                "#events li", "ls => ls.map((l) => l.textContent.split(' ').slice(-3))")
            for when, who, kind, subject in timeline:
                if who == robot and when <= t_s - 0.002:
                    assert any(kind in item and subject in item for item in listed), \
                        (when, kind, subject, listed)
            # The robot's marker stands where its recorded pose was.
            marker = page.locator(f"#robot-{robot}")
            assert float(marker.get_attribute("data-x")) == pytest.approx(
                raw["odom/x_m"], abs=0.002)
    # The two robots did different things: kobuki1's half lap was over, emili1's lap not.
    assert ("emili1", moments[2], "patrol") in behaviours
    assert ("kobuki1", moments[2], "idle") in behaviours
    page.select_option("#robot-select", "emili1")
    # Play at ×5: the moment moves on by itself; pause holds it.
    seek(page, 0.0)
    page.select_option("#tl-speed", "5")
    page.click("#tl-play")
    try:
        page.wait_for_function(
            "Number(document.querySelector('#timeline').dataset.shown) > 1", timeout=WAIT_MS)
    except Exception as exc:  # what the player shows, and whether its server still lives
        state = page.evaluate("""() => ({
            shown: document.querySelector('#timeline').dataset.shown,
            at: document.querySelector('#timeline').dataset.at,
            time: document.querySelector('#tl-time').textContent,
            play: document.querySelector('#tl-play').textContent,
            speed: document.querySelector('#tl-speed').value,
            visibility: document.visibilityState})""")
        raise AssertionError(f"playing at x5 did not move the moment past 1 s: {state}; "
                             f"viewer alive: {viewer.proc.poll() is None}; its output:\n"
                             f"{''.join(viewer.lines[-20:])}") from exc
    page.click("#tl-play")
    plot(page, "speed_mps", points_over=50)
    shoot(page, "recording", size)
    page.close()
    assert not errors, errors


# ---- item 3: the same graphs in a recording -----------------------------------------------

class Hold(Action):
    """Holds its state for ``HOLD_S``."""

    action_type = "driving"

    def run(self) -> None:
        self.sleep(HOLD_S)


class Look(Hold):
    action_type = "camera"


HOLD_S = 1.2


def mission() -> StateMachineEngine:
    """go (an action) → check (a behaviour driven by a tree: look, then hold) → done."""
    import py_trees

    def check() -> EngineBehavior:
        root = py_trees.composites.Sequence("check", memory=True, children=[
            StartLeaf("look", Look), StartLeaf("hold", Hold)])
        return EngineBehavior(TreeEngine(root, rate_hz=20.0), name="check")

    return StateMachineEngine(
        [State("go", start=Hold), State("check", start=check), State("done", final=True)],
        [Transition("go", "check", on="succeeded"),
         Transition("check", "done", on="succeeded")], initial="go")


@pytest.fixture(scope="module")
def machine_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A robot whose behaviour runs a state machine (one state drives a tree), recorded
    as ``beehave run --record`` records it (events, blackboard, engines)."""
    path = tmp_path_factory.mktemp("machine") / "mission.mcap"
    with HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        hl.register("mission", EngineBehavior, engine=mission())
        with Recorder(path, flush_period_s=0.05) as recorder:
            recorder.attach_events(hl.events, prefix="emili1", level="high")
            recorder.attach_blackboard(hl.blackboard, prefix="emili1")
            recorder.attach_engines(hl, prefix="emili1")
            hl.blackboard.set("mission", "start", writer="test")
            ended = threading.Event()
            hl.events.subscribe(lambda e: ended.set() if e.kind.value == "ended"
                                and e.subject == "mission" else None)
            hl.switch("mission")
            assert wait_until(ended.is_set)
            hl.switch("idle")
    return path


@pytest.fixture(scope="module")
def machine_viewer(machine_recording: Path) -> Iterator[ViewProcess]:
    with viewing(machine_recording) as process:
        yield process


def mcap_engines(recording: Path) -> list[tuple[float, str, dict[str, Any] | None]]:
    """The engine states straight from the file: (t_s, behaviour path, state or None)."""
    with open(recording, "rb") as f:
        messages = [(m.log_time, ch.topic, m.data) for _, ch, m in
                    make_reader(f).iter_messages(log_time_order=True)]
    start = messages[0][0]
    return [((t - start) / 1e9, data["path"], data["engine"]) for t, topic, raw in messages
            if topic == "/emili1/beehave/engines/state" and (data := json.loads(raw))]


def graph_at(page: Any) -> dict[str, Any]:
    return page.evaluate("window.beehaveGraph.inspect(document.querySelector('#graphs'))")


@pytest.mark.parametrize("size", [DESKTOP, PHONE], ids=["desktop", "phone"])
def test_the_recorded_page_draws_the_engines_graphs_as_beehave_inspect_says_at_t(
        machine_viewer: ViewProcess, machine_recording: Path, browser: Any,
        size: dict[str, int]) -> None:
    """At two moments with different states, the graph highlights the state that
    ``beehave inspect --at t`` names (and the file holds); the tree drawn inside the
    second state colours its nodes as ``inspect`` says."""
    machine = [(t, engine) for t, path, engine in mcap_engines(machine_recording)
               if path == "mission"]
    spans: dict[str, tuple[float, float]] = {}  # state → its longest stay (from, to)
    for (t, engine), (t_next, _) in zip(machine, machine[1:], strict=False):
        if engine is not None and engine["state"] is not None:
            was = spans.get(engine["state"], (0.0, 0.0))
            if t_next - t > was[1] - was[0]:
                spans[engine["state"]] = (t, t_next)
    assert {"go", "check"} <= set(spans), spans
    page, errors = open_page(browser, machine_viewer.url, size)
    page.wait_for_selector("body.recording", timeout=WAIT_MS)
    for state in ("go", "check"):
        t_s = round(sum(spans[state]) / 2, 2)  # well inside the stay (HOLD_S long)
        seek(page, t_s)
        said = inspect_at(machine_recording, t_s)["emili1"]
        assert said["engines"]["mission"] == ("state_machine", state)
        # The graph is drawn for the moment shown: its active state is the one named.
        page.wait_for_function(
            "(() => { const g = window.beehaveGraph.inspect(document.querySelector("
            "'#graphs')); return g && g.nodes.some((n) => n.classes.includes('active')) && "
            f"document.querySelector('#graphs').dataset.engines === '{len(said['engines'])}'"
            "; })()", timeout=WAIT_MS)
        graph = graph_at(page)
        active = [(n["engine"], n["state"]) for n in graph["nodes"]
                  if "active" in n["classes"]]
        assert active == [("mission", state)]
        assert {n["state"] for n in graph["nodes"] if n["engine"] == "mission"} >= \
            {"go", "check", "done"}
        if state == "check":  # the tree of the state, each node as inspect says
            assert said["engines"]["mission/check"] == ("behaviour_tree", None)
            nodes = {(n["engine"], n["path"]): n["status"] for n in graph["nodes"]
                     if n["engine"] == "mission/check" and n["path"]}
            assert nodes == said["nodes"]
            assert nodes[("mission/check", "check/look")] in ("RUNNING", "SUCCESS")
        page.locator("#graphs").scroll_into_view_if_needed()
        shoot(page, f"recording-graph-{state}", size)  # it fits in every state
    page.close()
    assert not errors, errors


def test_a_recording_opens_as_one_when_the_timeline_script_comes_late(
        viewer: ViewProcess, browser: Any) -> None:
    """The page's scripts hook into each other: the timeline's script, held back by a
    slow connection (here 1.5 s, after the robots' list has come), still opens the file
    as a recording (on a loaded host the page once stayed a live page without robot)."""
    page = browser.new_page(viewport=DESKTOP)
    try:
        def late(route: Any) -> None:
            time.sleep(1.5)
            route.continue_()

        page.route("**/static/timeline.js", late)
        page.goto(viewer.url)
        page.wait_for_selector("body.recording", timeout=WAIT_MS)
        assert page.locator("#tl-play").is_visible()
    finally:
        page.close()


def test_playing_to_the_end_while_the_server_is_slow_shows_the_end(
        viewer: ViewProcess, browser: Any) -> None:
    """Each moment takes the server 0.4 s (a loaded host): playing at x30 reaches the end
    while a moment is still asked, and the end is asked next and shown (the page once
    stopped at 0.92 s of 4.1 with its clock saying the end)."""
    page = browser.new_page(viewport=DESKTOP)
    try:
        page.goto(viewer.url)
        page.wait_for_selector("body.recording", timeout=WAIT_MS)
        seek(page, 0.0)

        def slow(route: Any) -> None:
            time.sleep(0.4)
            route.continue_()

        page.route("**/api/recording/at*", slow)
        page.select_option("#tl-speed", "30")
        page.click("#tl-play")
        page.wait_for_function("document.querySelector('#tl-play').textContent === '▶'",
                               timeout=WAIT_MS)
        end = float(page.get_attribute("#timeline", "data-at"))
        page.wait_for_function(
            f"Math.abs(Number(document.querySelector('#timeline').dataset.shown) - {end}) "
            f"< 1e-6", timeout=WAIT_MS)
    finally:
        page.close()


def test_a_recording_without_engines_serves_no_structure_and_refuses_breakpoints(
        viewer: ViewProcess) -> None:
    """An older recording (no engine channels) still opens: no graphs, no error."""
    answer = httpx.get(f"{viewer.url}api/robots/emili1/structure", timeout=WALL_TIMEOUT_S)
    assert answer.status_code == 200 and answer.json() == {"engines": []}
    answer = httpx.get(f"{viewer.url}api/robots/emili1/breakpoints", timeout=WALL_TIMEOUT_S)
    assert answer.status_code == 200 and answer.json()["breakpoints"] == {}
    for verb in ("breakpoints", "breakpoints/remove", "continue"):
        answer = httpx.post(f"{viewer.url}api/robots/emili1/{verb}",
                            json={"kind": "state", "target": "go"}, timeout=WALL_TIMEOUT_S)
        assert answer.status_code == 405, answer.text


def test_a_recording_refuses_commands_and_bad_times_with_the_reason(
        viewer: ViewProcess) -> None:
    for verb in ("switch", "stop", "pause", "resume"):
        answer = httpx.post(f"{viewer.url}api/robots/emili1/{verb}", json={},
                            timeout=WALL_TIMEOUT_S)
        assert answer.status_code == 405, answer.text
        assert "recording" in answer.json()["detail"]
    answer = httpx.get(f"{viewer.url}api/recording/at", params={"t": 1e6}, timeout=WALL_TIMEOUT_S)
    assert answer.status_code == 422 and "outside the recording" in answer.json()["detail"]
    answer = httpx.get(f"{viewer.url}api/robots/kobuki9/snapshot", timeout=WALL_TIMEOUT_S)
    assert answer.status_code == 404 and "emili1" in answer.json()["detail"]
    answer = httpx.get(f"{viewer.url}api/robots/emili1/series", params={"keys": "nope"},
                       timeout=WALL_TIMEOUT_S)
    assert answer.status_code == 422 and "odom/x_m" in answer.json()["detail"]


@pytest.mark.parametrize("content, said", [
    (b"", "not an MCAP file"), (b"garbage, not MCAP\n", "not an MCAP file"),
    ("head", "holds no message")], ids=["empty", "garbage", "truncated"])
def test_beehave_view_of_a_file_that_is_no_recording_exits_2_saying_why(
        recording: Path, tmp_path: Path, content: bytes | str, said: str) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(recording.read_bytes()[:3000] if content == "head" else content)
    done = subprocess.run([sys.executable, "-m", "beehave.cli", "view", str(path), "--port",
                           "0"], cwd=ROOT, capture_output=True, text=True,
                          timeout=WALL_TIMEOUT_S)
    assert done.returncode == 2, done.stdout + done.stderr
    assert said in done.stderr and str(path) in done.stderr and "Traceback" not in done.stderr


def test_a_recording_refuses_hostile_queries_naming_the_problem(viewer: ViewProcess) -> None:
    """What a plain client may send: times that are no finite seconds inside the
    recording, too many series keys, commands for a robot not recorded."""
    with httpx.Client(base_url=viewer.url, timeout=WALL_TIMEOUT_S) as client:
        for path in ("api/recording/at", "api/robots/emili1/snapshot",
                     "api/robots/emili1/structure"):
            for t in ("nan", "inf", "-inf", "1e400"):
                answer = client.get(path, params={"t": t})
                assert answer.status_code == 422, (path, t, answer.text)
                assert "finite number of seconds" in answer.json()["detail"], (path, t)
            answer = client.get(path, params={"t": -1})
            assert answer.status_code == 422, (path, answer.text)
            assert "outside the recording: 0 to" in answer.json()["detail"]
            answer = client.get(path, params={"t": "soon"})
            assert answer.status_code == 422 and "query.t" in answer.json()["detail"]
        series = "api/robots/emili1/series"
        answer = client.get(series, params={"keys": ",".join(["odom/x_m"] * 3000)})
        assert answer.status_code == 200, answer.text  # each key read once
        assert list(answer.json()["series"]) == ["odom/x_m"]
        answer = client.get(series, params={"keys": ",".join(f"k{i}" for i in range(101))})
        assert answer.status_code == 422 and "at most 100" in answer.json()["detail"]
        answer = client.get("api/recording", headers={"Host": "evil.example"})
        assert answer.status_code == 403 and "evil.example" in answer.json()["detail"]
        answer = client.post("api/robots/emili1/continue", json={},
                             headers={"Origin": "http://evil.example"})
        assert answer.status_code == 403 and "evil.example" in answer.json()["detail"]
        answer = client.post("api/robots/kobuki9/continue", json={})
        assert answer.status_code == 404, answer.text
        assert "'kobuki9'" in answer.json()["detail"] and "'emili1'" in answer.json()["detail"]


# ---- item 5: the fleet: members and the sequence diagram ---------------------------------

FLEET = {
    "robots": [{"atv": "emili1", "x_m": 1.0, "y_m": 1.0, "battery_pct": 80.0}],
    "agents": [{"agent": "emili1", "state": "idle"}, {"agent": "press1", "state": "ok"},
               {"agent": "orders", "state": "ok"}],
    # newest first, as a fleet process serves them
    "messages": [
        {"sent": "10:00:05", "performative": "inform", "from": "emili1", "to": "orders",
         "protocol": "fipa-contract-net", "conversation": "c1", "content": "{}"},
        {"sent": "10:00:04", "performative": "accept-proposal", "from": "orders",
         "to": "emili1", "protocol": "fipa-contract-net", "conversation": "c1", "content": "{}"},
        {"sent": "10:00:03", "performative": "request", "from": "press1", "to": "orders",
         "protocol": "fipa-request", "conversation": "c2", "content": "{}"},
        {"sent": "10:00:02", "performative": "propose", "from": "emili1", "to": "orders",
         "protocol": "fipa-contract-net", "conversation": "c1", "content": "{}"},
        {"sent": "10:00:01", "performative": "cfp", "from": "orders", "to": "emili1, press1",
         "protocol": "fipa-contract-net", "conversation": "c1", "content": "{}"}]}


@pytest.mark.parametrize("size", [DESKTOP, PHONE], ids=["desktop", "phone"])
def test_the_fleet_lists_its_members_and_draws_a_conversation_as_a_sequence_diagram(
        browser: Any, size: dict[str, int], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        hl.register("patrol", Patrol)
        with served(hl, fleet=FLEET) as server:
            page, errors = open_page(browser, server.url, size)
            page.wait_for_selector('#fleet-members [data-member="press1"]',
                                   timeout=WAIT_MS)
            members = page.eval_on_selector_all(
                "#fleet-members li", "ls => ls.map((l) => [l.dataset.member, l.className])")
            assert members == [["emili1", "robot"], ["orders", "agent"],
                               ["press1", "agent"]]
            page.select_option("#seq-conversation", "c1")
            arrows = page.eval_on_selector_all(
                "#sequence-svg .seq-msg",
                "gs => gs.map((g) => [g.dataset.from, g.dataset.to, g.dataset.performative])")
            # oldest first, one arrow per receiver, c2's request left out
            assert arrows == [["orders", "emili1", "cfp"], ["orders", "press1", "cfp"],
                              ["emili1", "orders", "propose"],
                              ["orders", "emili1", "accept-proposal"],
                              ["emili1", "orders", "inform"]]
            # Each arrow runs from its sender's lifeline to its receiver's, downwards.
            geometry = page.evaluate("""(() => {
                const lane = {};
                for (const t of document.querySelectorAll('#sequence-svg .seq-name'))
                    lane[t.dataset.lane] = Number(t.getAttribute('x'));
                return [...document.querySelectorAll('#sequence-svg .seq-msg')].map((g) => {
                    const l = g.querySelector('line');
                    return [lane[g.dataset.from], Number(l.getAttribute('x1')),
                            lane[g.dataset.to], Number(l.getAttribute('x2')),
                            Number(l.getAttribute('y1'))]; }); })()""")
            ys = [g[4] for g in geometry]
            assert ys == sorted(ys) and len(set(ys)) == len(ys)
            for from_x, x1, to_x, x2, _ in geometry:
                assert x1 == from_x and abs(x2 - to_x) <= 2
            diagram = page.locator("#sequence")
            diagram.scroll_into_view_if_needed()
            assert pixels_near(diagram.screenshot(), BLUE) > 100
            shoot(page, "fleet", size)
            # An agent's button filters its messages; a robot's opens its full view.
            click_until(page, '#fleet-members [data-member="press1"] button',
                        "document.querySelectorAll('#sequence-svg .seq-msg').length === 1")
            assert page.locator("#sequence-svg .seq-msg").count() == 1  # c1 + press1
            page.select_option("#seq-conversation", "")
            assert page.locator("#sequence-svg .seq-msg").count() == 2
            click_until(page, '#fleet-members [data-member="emili1"] button',
                        "document.querySelector('#robot-select').value === 'emili1'")
            page.wait_for_function("document.querySelectorAll('#behavior-choice option')"
                                   ".length > 1", timeout=WAIT_MS)
            page.close()
            assert not errors, errors
