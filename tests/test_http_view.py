"""The web view on a phone (issue 22, item 12): a real chromium page at 390 px against a
real server in this process; nothing is wider than the screen, Switch and Stop are
reachable and work. The screenshot is written to out/webview-phone.png."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")
sync_api = pytest.importorskip("playwright.sync_api")
from config_fixtures import Drive  # noqa: E402

from beehave import HighLevelBehaviorManager  # noqa: E402
from beehave.interfaces import ControlPlane  # noqa: E402
from beehave.interfaces.http import TOKEN_ENV, HttpServer  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402
from tests.chromium import CHROMIUM, chromium  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_http_view")

OUT = Path(__file__).resolve().parent.parent / "out"
WAIT_MS = WALL_TIMEOUT_S * 1000
WORLD = {"name": "tiny", "floor": {"size_m": [6, 4]},
         "stations": [{"name": "dock", "kind": "charging", "center_m": [1, 1]}]}

if not Path(CHROMIUM).exists():  # pragma: no cover - `make setup` installs it
    pytest.skip(f"{CHROMIUM} is not installed", allow_module_level=True)


@pytest.fixture
def server(hl: HighLevelBehaviorManager, monkeypatch: pytest.MonkeyPatch
           ) -> Iterator[HttpServer]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    hl.register("drive", Drive, station="dock")
    hl.blackboard.set("odom/x_m", 1.0, writer="hal:odometry")
    hl.blackboard.set("odom/y_m", 1.0, writer="hal:odometry")
    hl.blackboard.set("some/very/long/key/that/a/phone/must/wrap/or/scroll", "x" * 300,
                      writer="test")
    plane = ControlPlane(hl, name="emili1")
    try:
        with HttpServer(plane, world=WORLD) as srv:
            yield srv
    finally:
        plane.close()


@pytest.fixture
def phone() -> Iterator[Any]:
    with chromium() as browser:
        yield browser.new_page(viewport={"width": 390, "height": 844},
                               device_scale_factor=2, is_mobile=True, has_touch=True)


def test_the_view_fits_a_phone_and_switch_and_stop_work_there(
        server: HttpServer, phone: Any, hl: HighLevelBehaviorManager) -> None:
    phone.goto(server.url)
    phone.wait_for_selector("#robot-emili1", state="attached", timeout=WAIT_MS)
    phone.wait_for_function("document.querySelectorAll('#behavior-choice option').length > 1",
                            timeout=WAIT_MS)
    width = phone.evaluate("document.documentElement.scrollWidth")
    assert width <= 390, f"the page is {width} px wide on a 390 px screen"
    for button in ("#switch-btn", "#stop-btn"):
        box = phone.locator(button).bounding_box()
        assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= 390, box
    OUT.mkdir(exist_ok=True)
    phone.screenshot(path=str(OUT / "webview-phone.png"), full_page=True)
    phone.select_option("#behavior-choice", "drive")
    phone.locator("#switch-btn").tap()
    assert wait_until(lambda: hl.current == "drive")
    phone.locator("#stop-btn").tap()
    assert wait_until(lambda: hl.current == "idle")


FACTORY = {**WORLD, "machines": [{"name": "press1", "center_m": [4.0, 3.0]}]}
FLEET = {"robots": [{"name": "atv1", "x_m": 2.0, "y_m": 1.5, "battery_pct": 80.0}],
         "machines": [{"machine": "press1", "level": 70.2, "capacity": 100}],
         "messages": [{"topic": "fleet/atv1/order", "payload": "{" + '"k": 1, ' * 200 + "}"}
                      for _ in range(3)]}


def test_a_fleet_view_shows_no_empty_robot_panels_and_its_tables_fit(
        monkeypatch: pytest.MonkeyPatch, phone: Any) -> None:
    """Issue 22, item 13 (in part): a fleet process without robots of its own shows the
    map with its machines labelled and the fleet's tables, not empty robot panels whose
    Switch answers 404."""
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    phone.set_viewport_size({"width": 1280, "height": 800})
    with HttpServer({}, world=FACTORY, fleet=lambda: FLEET) as srv:
        phone.goto(srv.url)
        phone.wait_for_selector("#fleet-panel table[data-section=messages]", timeout=WAIT_MS)
        phone.wait_for_selector('[data-fleet-robot="atv1"]', state="attached",
                                timeout=WAIT_MS)
        for panel in ("#behavior-panel", "#switch-btn", "#stop-btn", "#robot-select"):
            assert not phone.locator(panel).is_visible(), f"{panel} is shown"
        assert phone.locator(".robot-panel:visible").count() == 0
        width = phone.evaluate("document.documentElement.scrollWidth")
        assert width <= 1280, f"the page is {width} px wide in a 1280 px window"
        overflow = phone.evaluate("(() => { const p = document.querySelector('#fleet-panel');"
                                  " return p.scrollWidth - p.clientWidth; })()")
        assert overflow <= 0, f"the fleet panel overflows by {overflow} px"
        # The machines are drawn and labelled, with the level the fleet reports.
        label = phone.locator('[data-machine-label="press1"]')
        label.wait_for(state="attached", timeout=WAIT_MS)
        phone.wait_for_function("document.querySelector('[data-machine-label=\"press1\"]')"
                                ".textContent === 'press1 70/100'", timeout=WAIT_MS)


def test_a_fleet_view_shows_the_robot_picked_in_full_and_commands_it(
        server: HttpServer, phone: Any, hl: HighLevelBehaviorManager) -> None:
    """Issue 22, item 13: the fleet's page (a server of a fleet process, no robot of its
    own) is given the addresses of its robots' servers; the user picks a robot with the
    selector or on the map and sees its full view, and Switch and Stop act on it. The
    second robot's server has a token: it rides in its address."""
    phone.set_viewport_size({"width": 1280, "height": 800})
    other = HighLevelBehaviorManager(stop_timeout_s=0.3)
    other.start()
    other.register("drive", Drive, station="dock")
    other.blackboard.set("odom/x_m", 3.0, writer="hal:odometry")
    other.blackboard.set("odom/y_m", 2.0, writer="hal:odometry")
    other.blackboard.set("bumper/pressed", False, writer="hal:kobuki")
    plane = ControlPlane(other, name="kobuki1")
    fleet = {"robots": [{"name": "emili1", "x_m": 1.0, "y_m": 1.0},
                        {"name": "kobuki1", "x_m": 3.0, "y_m": 2.0}]}
    try:
        with HttpServer(plane, token="kobuki-secret") as robot2, \
                HttpServer({}, world=FACTORY, fleet=lambda: fleet,
                           remotes={"emili1": server.url, "kobuki1": robot2.url}) as srv:
            assert "#token=kobuki-secret" in robot2.url
            phone.goto(srv.url)
            # The first robot is shown at once: its behaviours, its blackboard, its marker.
            phone.wait_for_function("document.querySelectorAll('#behavior-choice option')"
                                    ".length > 1", timeout=WAIT_MS)
            assert phone.locator("#robot-select").input_value() == "emili1"
            phone.wait_for_selector('#blackboard tr[data-key="some/very/long/key/that/a/'
                                    'phone/must/wrap/or/scroll"]', timeout=WAIT_MS)
            phone.wait_for_selector("#robot-emili1", state="attached", timeout=WAIT_MS)
            assert phone.locator("#current-behavior").inner_text() == "idle"
            phone.select_option("#behavior-choice", "drive")
            phone.fill('#params input[data-param="station"]', "dock")
            phone.locator("#switch-btn").click()
            assert wait_until(lambda: hl.current == "drive")
            phone.wait_for_function("document.querySelector('#current-behavior')"
                                    ".textContent === 'drive'", timeout=WAIT_MS)
            phone.wait_for_selector('#tree [data-status="RUNNING"]', timeout=WAIT_MS)
            phone.wait_for_selector('#events li[data-kind="switch_completed"]',
                                    timeout=WAIT_MS)
            # Pick the other one on the map: its own view replaces the first one's.
            phone.locator('[data-fleet-robot="kobuki1"] .body').click()
            phone.wait_for_selector('#blackboard tr[data-key="bumper/pressed"]',
                                    timeout=WAIT_MS)
            assert phone.locator("#robot-select").input_value() == "kobuki1"
            assert phone.locator('#blackboard tr[data-key^="some/very"]').count() == 0
            phone.wait_for_function("document.querySelectorAll('#behavior-choice option')"
                                    ".length > 1", timeout=WAIT_MS)
            phone.select_option("#behavior-choice", "drive")
            phone.locator("#switch-btn").click()
            assert wait_until(lambda: other.current == "drive")
            phone.locator("#stop-btn").click()
            assert wait_until(lambda: other.current == "idle")
            assert hl.current == "drive", "a command for kobuki1 reached emili1"
            # And back with the selector.
            phone.select_option("#robot-select", "emili1")
            phone.locator("#stop-btn").click()
            assert wait_until(lambda: hl.current == "idle")
            assert phone.locator("#control-msg.error").count() == 0, \
                phone.locator("#control-msg").inner_text()
    finally:
        plane.close()
        other.shutdown()
