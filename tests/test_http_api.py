"""The HTTP/WebSocket interface against a real uvicorn server in this process: every
endpoint, the errors malformed requests get, the token rules, and a slow WebSocket client
that must not slow anything else."""

from __future__ import annotations

import base64
import json
import os
import socket
import threading
from collections.abc import Iterator
from typing import Any

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")
from config_fixtures import Drive, Explodes  # noqa: E402
from websockets.exceptions import InvalidStatus  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from beehave import Behavior, HighLevelBehaviorManager  # noqa: E402
from beehave.errors import ConfigError  # noqa: E402
from beehave.interfaces import ControlPlane  # noqa: E402
from beehave.interfaces.http import TOKEN_ENV, HttpServer, parse_address, serve  # noqa: E402
from beehave.testing import ScriptedAction, wait_until  # noqa: E402

WORLD = {"name": "tiny", "floor": {"size_m": [6, 4]},
         "stations": [{"name": "dock", "kind": "charging", "center_m": [1, 1]}]}


@pytest.fixture
def plane(hl: HighLevelBehaviorManager) -> Iterator[ControlPlane]:
    hl.register("drive", Drive, station="dock")
    hl.register("broken", Explodes)
    hl.blackboard.set("battery/percentage", 54.0, writer="hal:debug")
    hl.blackboard.set("scan/front_m", float("inf"), writer="hal:laser")
    core = ControlPlane(hl, name="emili1")
    yield core
    core.close()


@pytest.fixture
def server(plane: ControlPlane, monkeypatch: pytest.MonkeyPatch) -> Iterator[HttpServer]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with HttpServer(plane, world=WORLD, rate_hz=50.0) as srv:
        yield srv


def base(srv: HttpServer) -> str:
    return srv.url.split("#")[0].rstrip("/")


def test_binds_loopback_on_a_free_port_and_serves_the_page_and_openapi(
        server: HttpServer) -> None:
    assert server.host == "127.0.0.1" and server.port > 0 and server.token is None
    assert server.url == f"http://127.0.0.1:{server.port}/"
    page = httpx.get(server.url)
    assert page.status_code == 200 and "beehave" in page.text and "/static/app.js" in page.text
    assert "cdn" not in page.text.lower()  # everything is served from the package
    script = httpx.get(f"{base(server)}/static/app.js")
    assert script.status_code == 200 and "new WebSocket" in script.text
    spec = httpx.get(f"{base(server)}/openapi.json").json()
    for path in ("/api/robots/{robot}/switch", "/api/robots/{robot}/blackboard",
                 "/api/robots/{robot}/events", "/api/world"):
        assert path in spec["paths"]
    # No Swagger UI: it would load a CDN's script into the robot's origin (issue 22).
    assert httpx.get(f"{base(server)}/docs").status_code == 404


def test_read_endpoints(server: HttpServer, hl: HighLevelBehaviorManager) -> None:
    api = f"{base(server)}/api"
    robots = httpx.get(f"{api}/robots").json()
    assert robots["robots"] == [{"name": "emili1", "behavior": "idle", "logic": None}]
    assert robots["world"] is True and robots["fleet"] is False
    assert httpx.get(f"{api}/world").json() == WORLD
    fleet = httpx.get(f"{api}/fleet")
    assert fleet.status_code == 404 and "no fleet view" in fleet.json()["detail"]
    status = httpx.get(f"{api}/robots/emili1/status").json()
    assert status["behavior"] == "idle" and status["schema"] == "beehave/high_level/state/2"
    snapshot = httpx.get(f"{api}/robots/emili1/snapshot").json()
    assert snapshot["tree"]["name"] == "idle" and snapshot["robot"] == "emili1"
    names = [b["name"] for b in httpx.get(f"{api}/robots/emili1/behaviors").json()]
    assert names == ["broken", "drive", "idle"]
    assert httpx.get(f"{api}/robots/emili1/logics").json() == []
    board = httpx.get(f"{api}/robots/emili1/blackboard").json()
    assert board["scan/front_m"]["value"] == {"$float": "inf"}
    one = httpx.get(f"{api}/robots/emili1/blackboard", params={"key": "battery/percentage"})
    assert one.json()["battery/percentage"]["value"] == 54.0
    assert "age_s" in one.json()["battery/percentage"]
    some = httpx.get(f"{api}/robots/emili1/blackboard", params={"pattern": "scan/*"}).json()
    assert list(some) == ["scan/front_m"]
    events = httpx.get(f"{api}/robots/emili1/events").json()
    assert events == [] or all("seq" in e for e in events)


def test_switch_and_stop_reach_the_manager(server: HttpServer,
                                          hl: HighLevelBehaviorManager) -> None:
    api = f"{base(server)}/api/robots/emili1"
    answer = httpx.post(f"{api}/switch", json={"behavior": "drive",
                                               "params": {"station": "shelf"}})
    assert answer.status_code == 202, answer.text
    assert answer.json() == {"requested": "drive", "params": {"station": "shelf"}}
    assert wait_until(lambda: hl.current == "drive")
    assert getattr(hl.top, "station", None) == "shelf"
    events = httpx.get(f"{api}/events", params={"limit": 1000}).json()
    assert any(e["kind"] == "switch_completed" and e["subject"] == "drive" for e in events)
    last = events[-1]["seq"]
    assert httpx.get(f"{api}/events", params={"after_seq": last}).json() == []
    assert httpx.post(f"{api}/stop", json={}).status_code == 202
    assert wait_until(lambda: hl.current == "idle")


class Stubborn(Behavior):
    """Raises the lift with an action that ignores its interrupt for a while."""

    def run(self) -> None:
        self.start_action(ScriptedAction("lift", duration_s=60.0, ignore_interrupt_s=1.5,
                                         name="raise"))
        while self.sleep(0.05):
            pass


def test_status_shows_type_locks_and_stuck_actions_and_behaviours_list_their_parameters(
        server: HttpServer, hl: HighLevelBehaviorManager) -> None:
    hl.register("stubborn", Stubborn)
    api = f"{base(server)}/api"
    assert httpx.post(f"{api}/robots/emili1/switch",
                      json={"behavior": "stubborn"}).status_code == 202
    assert wait_until(lambda: "lift" in httpx.get(f"{api}/robots/emili1/status"
                                                  ).json()["locks"])
    status = httpx.get(f"{api}/robots/emili1/status").json()
    assert status["locks"] == {"lift": "stubborn/raise"} and status["stuck"] == []
    assert {"path": "stubborn/raise", "kind": "action", "class": "ScriptedAction",
            "status": "RUNNING", "action_type": "lift"} in status["running"]
    # Stop: the action ignores its interrupt past stop_timeout_s, so it is STUCK, and its
    # type lock stays held until its thread really ends.
    assert httpx.post(f"{api}/robots/emili1/stop", json={}).status_code == 202
    seen: list[dict[str, Any]] = []  # the status that showed it (it ends by itself)

    def stuck() -> bool:
        now = httpx.get(f"{api}/robots/emili1/status").json()
        seen.append(now)
        return bool(now["stuck"]) and now["behavior"] == "idle"  # the switch is over

    assert wait_until(stuck)
    status = seen[-1]
    assert status["behavior"] == "idle" and "stubborn/raise" in str(status["stuck"])
    assert status["locks"] == {"lift": "stubborn/raise"}
    assert wait_until(lambda: not httpx.get(f"{api}/robots/emili1/status").json()["stuck"])
    drive = next(b for b in httpx.get(f"{api}/robots/emili1/behaviors").json()
                 if b["name"] == "drive")
    assert [(p["name"], p["default"], p["required"]) for p in drive["parameters"]] == [
        ("station", "dock", False), ("speed_mps", 0.5, False)]
    stats = httpx.get(f"{api}/stats").json()
    assert stats["rate_hz"] == 50.0 and stats["clients"] == []
    # What serving costs, apart from the robot's threads (Linux).
    assert set(stats["cpu_s"]) == {"server", "pump"}
    assert all(isinstance(v, float) and v > 0 for v in stats["cpu_s"].values())


def test_the_blackboard_endpoint_marks_stale_entries(server: HttpServer,
                                                     hl: HighLevelBehaviorManager) -> None:
    hl.blackboard.set("odom/x_m", 1.5, writer="hal:odometry", stale=True)
    entry = httpx.get(f"{base(server)}/api/robots/emili1/blackboard",
                      params={"key": "odom/x_m"}).json()["odom/x_m"]
    assert entry["stale"] is True and entry["value"] == 1.5 and entry["age_s"] >= 0
    assert httpx.get(f"{base(server)}/api/robots/emili1/blackboard",
                     params={"key": "battery/percentage"}).json()[
        "battery/percentage"]["stale"] is False


@pytest.mark.parametrize(("method", "path", "body", "status", "message"), [
    ("post", "/api/robots/emili1/switch", {"behavior": "patrol"}, 404,
     "unknown behavior 'patrol'; registered: 'broken', 'drive', 'idle'"),
    ("post", "/api/robots/emili1/switch", {"behavior": "drive", "params": {"colour": 1}},
     422, "it accepts: station, speed_mps"),
    ("post", "/api/robots/emili1/switch", {"behavior": "broken"}, 500,
     "motor controller not found"),
    ("post", "/api/robots/emili1/switch", {"behavior": 7}, 422,
     "body.behavior: Input should be a valid string"),
    ("post", "/api/robots/emili1/switch", {"name": "drive"}, 422, "body.behavior: Field required"),
    ("post", "/api/robots/emili1/switch", b"{not json", 422, "JSON decode error"),
    ("post", "/api/robots/emili1/switch", ["drive"], 422, "body: Input should be a valid"),
    ("post", "/api/robots/emili9/switch", {"behavior": "drive"}, 404,
     "unknown robot 'emili9'; serving: 'emili1'"),
    ("get", "/api/robots/emili1/blackboard?key=battery/percent", None, 404,
     "did you mean 'battery/percentage'?"),
    ("get", "/api/robots/emili1/blackboard?key=bad%20key", None, 400, "bad key"),
    ("get", "/api/robots/emili1/blackboard?pattern=a//b", None, 400, "a//b"),
    ("get", "/api/robots/emili1/events?limit=-1", None, 422, "query.limit"),
    ("get", "/api/robots/emili1/events?after_seq=x", None, 422, "query.after_seq"),
])
def test_malformed_requests_get_a_4xx_naming_the_problem_and_change_nothing(
        server: HttpServer, hl: HighLevelBehaviorManager, method: str, path: str, body: Any,
        status: int, message: str) -> None:
    url = base(server) + path
    if method == "get":
        response = httpx.get(url)
    elif isinstance(body, bytes):
        response = httpx.post(url, content=body, headers={"content-type": "application/json"})
    else:
        response = httpx.post(url, json=body)
    assert response.status_code == status, response.text
    assert message in response.json()["detail"], response.json()
    assert hl.current == "idle" and hl.requested is None
    assert httpx.get(f"{base(server)}/api/robots/emili1/status").status_code == 200


def _read_updates(ws: Any, n: int) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    while len(out) < n:
        message = json.loads(ws.recv(timeout=10))
        if "snapshot" in message:
            out.append(message)
    return out


def test_websocket_streams_snapshots_blackboard_and_events(
        server: HttpServer, hl: HighLevelBehaviorManager) -> None:
    url = f"ws://127.0.0.1:{server.port}/api/ws"
    with connect(url, subprotocols=["beehave"]) as ws:  # type: ignore[list-item]
        assert ws.subprotocol == "beehave"
        first = _read_updates(ws, 1)[0]
        assert first["robot"] == "emili1" and first["snapshot"]["behavior"] == "idle"
        assert first["blackboard"]["battery/percentage"]["value"] == 54.0
        hl.blackboard.set("battery/percentage", 42.0)
        httpx.post(f"{base(server)}/api/robots/emili1/switch", json={"behavior": "drive"})
        seen: list[dict[str, Any]] = []
        while not any(e["kind"] == "switch_completed" and e["subject"] == "drive"
                      for e in seen):
            seen += json.loads(ws.recv(timeout=10))["events"]
        later = _read_updates(ws, 1)[0]
        assert later["blackboard"]["battery/percentage"]["value"] == 42.0
        assert later["seq"] > first["seq"]
    with pytest.raises(InvalidStatus) as refused:
        connect(f"{url}?robots=emili9")
    assert refused.value.response.status_code == 404


def test_a_burst_of_writes_is_coalesced_into_few_updates_with_the_last_value(
        server: HttpServer, hl: HighLevelBehaviorManager) -> None:
    with connect(f"ws://127.0.0.1:{server.port}/api/ws") as ws:
        _read_updates(ws, 1)
        for i in range(1, 501):  # a few milliseconds of writes: a handful of 50 Hz turns
            hl.blackboard.set("odom/x_m", float(i), writer="hal:odometry")
        updates = [_read_updates(ws, 1)[0]]
        while updates[-1]["blackboard"]["odom/x_m"]["value"] != 500.0:
            updates += _read_updates(ws, 1)
    assert len(updates) < 50  # not one per write: the intermediate values were skipped


def test_serve_passes_the_refresh_on(plane: ControlPlane, hl: HighLevelBehaviorManager,
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    server = serve(plane, rate_hz=50.0, refresh_s=0.05)
    try:
        assert server.hub.refresh_s == 0.05
        with connect(f"ws://127.0.0.1:{server.port}/api/ws") as ws:
            # The robot does not change, yet updates keep coming: ages move on.
            ages = [u["blackboard"]["battery/percentage"]["age_s"]
                    for u in _read_updates(ws, 3)]
        assert ages == sorted(ages) and ages[-1] > ages[0]
    finally:
        server.stop()
    with pytest.raises(ConfigError, match="refresh_s"):
        HttpServer(plane, refresh_s=0)


class StalledClient:
    """A WebSocket client that completes the handshake, then never reads: its receive
    window is tiny, so the server's socket fills at once (a browser on a dead link)."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
        self.sock.connect(("127.0.0.1", port))
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /api/ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                           f"Upgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
                           ).encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)  # byte by byte: nothing past the headers is read
        assert head.startswith(b"HTTP/1.1 101"), head

    def close(self) -> None:
        self.sock.close()


def test_a_stalled_websocket_client_loses_snapshots_and_slows_nobody(
        server: HttpServer, hl: HighLevelBehaviorManager) -> None:
    # Big updates fill the stalled client's socket after a few messages.
    hl.blackboard.set("map/blob", "x" * 200_000)
    stalled = StalledClient(server.port)
    stop = threading.Event()

    def robot_writes() -> None:  # the robot keeps changing its blackboard
        value = 0
        while not stop.is_set():
            value += 1
            hl.blackboard.set("odom/x_m", float(value))
            stop.wait(0.005)

    writer = threading.Thread(target=robot_writes)
    writer.start()
    try:
        # The first snapshot must carry the value (a stress run: the writer thread had not
        # run yet when the fast client connected).
        assert wait_until(lambda: hl.blackboard.get("odom/x_m") is not None)
        with connect(f"ws://127.0.0.1:{server.port}/api/ws",
                     max_size=None) as fast:
            updates = _read_updates(fast, 30)
            # The fast client kept getting new updates while the other one was stuck …
            assert [u["seq"] for u in updates] == sorted({u["seq"] for u in updates})
            assert updates[-1]["blackboard"]["odom/x_m"]["value"] > \
                updates[0]["blackboard"]["odom/x_m"]["value"]
            # … the stalled client's unsent snapshots were replaced, and counted …
            assert wait_until(lambda: any(c["dropped"] >= 5
                                          for c in server.hub.stats()["clients"]))
            # … and the robot still switches at once through the API.
            assert httpx.post(f"{base(server)}/api/robots/emili1/switch",
                              json={"behavior": "drive"}).status_code == 202
            assert wait_until(lambda: hl.current == "drive")
    finally:
        stop.set()
        writer.join()
        stalled.close()
    assert wait_until(lambda: len(server.hub.stats()["clients"]) == 0)
    assert server.hub.stats()["dropped_snapshots"] >= 5


@pytest.mark.parametrize(("text", "expected"), [
    ("8080", ("127.0.0.1", 8080)), ("0", ("127.0.0.1", 0)),
    ("0.0.0.0:9000", ("0.0.0.0", 9000)), ("[::1]:81", ("::1", 81)),
    ("localhost:1", ("localhost", 1))])
def test_addresses(text: str, expected: tuple[str, int]) -> None:
    assert parse_address(text) == expected


@pytest.mark.parametrize("text", ["", "http", "70000", ":80", "[::1]80", "host:-1"])
def test_bad_addresses_say_what_is_expected(text: str) -> None:
    with pytest.raises(ConfigError, match="HTTP address"):
        parse_address(text)


def test_a_port_in_use_is_a_clear_error(server: HttpServer, plane: ControlPlane) -> None:
    with pytest.raises(ConfigError, match=f"cannot listen on 127.0.0.1:{server.port}"):
        HttpServer(plane, port=server.port).start()


# ---- tokens -----------------------------------------------------------------------------------

def test_any_other_address_generates_a_token_and_requires_it_for_everything(
        plane: ControlPlane, hl: HighLevelBehaviorManager,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    # 0.0.0.0 listens on every interface; the test talks to it over loopback only.
    with HttpServer(plane, host="0.0.0.0") as srv:
        assert srv.token_source == "generated" and srv.token and len(srv.token) >= 24
        assert srv.url.endswith(f"/#token={srv.token}")
        api = f"http://127.0.0.1:{srv.port}/api"
        for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": srv.token}):
            refused = httpx.get(f"{api}/robots/emili1/status", headers=headers)
            assert refused.status_code == 401 and "token" in refused.json()["detail"]
            assert httpx.post(f"{api}/robots/emili1/switch", json={"behavior": "drive"},
                              headers=headers).status_code == 401
        assert hl.current == "idle"
        good = {"Authorization": f"Bearer {srv.token}"}
        assert httpx.get(f"{api}/robots/emili1/status", headers=good).status_code == 200
        assert httpx.get(f"{api}/robots/emili1/status",
                         params={"token": srv.token}).status_code == 200
        assert httpx.post(f"{api}/robots/emili1/switch", json={"behavior": "drive"},
                          headers=good).status_code == 202
        assert wait_until(lambda: hl.current == "drive")
        # The page itself holds no data: it loads, then asks for the token.
        assert httpx.get(f"http://127.0.0.1:{srv.port}/").status_code == 200
        ws_url = f"ws://127.0.0.1:{srv.port}/api/ws"
        for attempt in ({"subprotocols": ["beehave"]},
                        {"subprotocols": ["beehave", "bearer.wrong"]}):
            with pytest.raises(InvalidStatus) as refused_ws:
                connect(ws_url, **attempt)  # type: ignore[arg-type]
            assert refused_ws.value.response.status_code == 401
        with connect(ws_url, subprotocols=["beehave", f"bearer.{srv.token}"]  # type: ignore[list-item]
                     ) as ws:
            assert json.loads(ws.recv(timeout=10))["robot"] == "emili1"
        with connect(f"{ws_url}?token={srv.token}") as ws:
            assert json.loads(ws.recv(timeout=10))["robot"] == "emili1"


def test_a_token_on_loopback_protects_commands_and_comes_from_the_environment(
        plane: ControlPlane, hl: HighLevelBehaviorManager,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(TOKEN_ENV, "s3cret-token")
    with HttpServer(plane) as srv:
        assert srv.token == "s3cret-token" and srv.token_source == "environment"
        api = f"http://127.0.0.1:{srv.port}/api/robots/emili1"
        assert httpx.get(f"{api}/status").status_code == 200  # reads stay open on loopback
        assert httpx.post(f"{api}/switch", json={"behavior": "drive"}).status_code == 401
        assert httpx.post(f"{api}/stop", json={}).status_code == 401
        assert hl.requested is None and hl.current == "idle"
        assert httpx.post(f"{api}/switch", json={"behavior": "drive"},
                          headers={"Authorization": "Bearer s3cret-token"}).status_code == 202
        assert wait_until(lambda: hl.current == "drive")


def test_server_stops_with_clients_connected_and_leaves_no_thread(
        plane: ControlPlane, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    srv = HttpServer(plane)
    srv.start()
    with connect(f"ws://127.0.0.1:{srv.port}/api/ws") as ws:
        ws.recv(timeout=10)
        srv.stop()
        assert not any(t.name == "beehave:http" for t in threading.enumerate())
    with pytest.raises(httpx.ConnectError):
        httpx.get(srv.url, timeout=1)


def test_one_server_serves_several_robots_and_a_client_picks_its_own(
        hl: HighLevelBehaviorManager, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    other = HighLevelBehaviorManager(stop_timeout_s=0.3)
    other.register("drive", Drive, station="dock")
    other.start()
    planes = {"emili1": ControlPlane(hl, name="emili1"),
              "kobuki1": ControlPlane(other, name="kobuki1")}
    fleet = {"agents": [{"name": "emili1"}, {"name": "kobuki1"}]}
    try:
        with HttpServer(planes, fleet=lambda: fleet) as srv:
            api = f"http://127.0.0.1:{srv.port}/api"
            listed = httpx.get(f"{api}/robots").json()["robots"]
            assert [r["name"] for r in listed] == ["emili1", "kobuki1"]
            assert httpx.get(f"{api}/fleet").json() == fleet
            assert httpx.post(f"{api}/robots/kobuki1/switch",
                              json={"behavior": "drive"}).status_code == 202
            assert wait_until(lambda: other.current == "drive")
            assert hl.current == "idle"  # only the robot asked
            with connect(f"ws://127.0.0.1:{srv.port}/api/ws?robots=kobuki1") as ws:
                robots = {json.loads(ws.recv(timeout=10))["robot"] for _ in range(3)}
            assert robots == {"kobuki1"}
    finally:
        for plane in planes.values():
            plane.close()
        other.shutdown()


def test_a_fleet_server_forwards_its_remote_robots_api_errors_and_stream(
        server: HttpServer, hl: HighLevelBehaviorManager) -> None:
    """Issue 22, item 13: a fleet process's server given a robot server's address answers
    for that robot with the robot's own answers (its errors too), after its own checks;
    a robot whose server is gone is a 502 naming it, and nothing else is affected."""
    with socket.socket() as closed:  # a port nobody listens on
        closed.bind(("127.0.0.1", 0))
        gone = f"http://127.0.0.1:{closed.getsockname()[1]}/"
    told: list[str] = []  # a robot that tells its address once it serves
    with HttpServer({}, fleet=lambda: {"robots": []},
                    remotes={"emili1": server.url, "atv9": gone,
                             "late": lambda: told[0] if told else None}) as srv:
        api = f"{base(srv)}/api"
        listed = httpx.get(f"{api}/robots").json()["robots"]
        assert [(r["name"], r["remote"]) for r in listed] == [
            ("atv9", gone.rstrip("/")), ("emili1", base(server)), ("late", None)]
        early = httpx.get(f"{api}/robots/late/status")
        assert early.status_code == 502 and "not told its address yet" in early.text
        told.append(server.url)
        assert httpx.get(f"{api}/robots/late/status").status_code == 404  # emili1's server
        status = httpx.get(f"{api}/robots/emili1/status")
        assert status.status_code == 200 and status.json()["behavior"] == "idle"
        board = httpx.get(f"{api}/robots/emili1/blackboard", params={"key": "scan/front_m"})
        assert board.json()["scan/front_m"]["value"] == {"$float": "inf"}
        unknown = httpx.post(f"{api}/robots/emili1/switch", json={"behavior": "fly"})
        assert unknown.status_code == 404 and "drive" in unknown.json()["detail"]
        wrong = httpx.post(f"{api}/robots/emili1/switch",
                           json={"behavior": "drive", "params": {"speed_mps": "fast"}})
        assert wrong.status_code == 422 and "speed_mps" in wrong.json()["detail"]
        # This server's own checks come first: a foreign page's command never goes on.
        foreign = httpx.post(f"{api}/robots/emili1/switch", json={"behavior": "drive"},
                             headers={"Origin": "http://evil.example"})
        assert foreign.status_code == 403 and hl.current == "idle"
        assert httpx.post(f"{api}/robots/emili1/switch",
                          json={"behavior": "drive"}).status_code == 202
        assert wait_until(lambda: hl.current == "drive")
        down = httpx.get(f"{api}/robots/atv9/status")
        assert down.status_code == 502 and "'atv9'" in down.json()["detail"]
        with connect(f"ws://127.0.0.1:{srv.port}/api/ws?robots=emili1",
                     subprotocols=["beehave"]) as ws:  # type: ignore[list-item]
            first = _read_updates(ws, 1)[0]
            assert first["robot"] == "emili1" and first["snapshot"]["behavior"] == "drive"
        assert httpx.post(f"{api}/robots/emili1/stop", content=b"{}",
                          headers={"content-type": "application/json"}).status_code == 202
        assert wait_until(lambda: hl.current == "idle")
