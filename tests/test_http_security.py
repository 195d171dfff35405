"""Issue 22, probed as an attacker would: a real uvicorn server on a free port, plain
httpx / raw sockets / ``websockets``, and a real chromium page served from another origin
for the cross-site fetch and form probes. Every refusal also checks that the robot kept
running its behaviour (the same instance, no switch requested)."""

from __future__ import annotations

import contextlib
import http.server
import json
import socket
import threading
import time
from collections.abc import Iterator
from typing import Annotated, Any

import pytest
from annotated_types import Gt

pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")
from config_fixtures import Drive  # noqa: E402
from websockets.exceptions import InvalidStatus  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from beehave import Behavior, HighLevelBehaviorManager  # noqa: E402
from beehave.errors import ConfigError, InvalidParameters  # noqa: E402
from beehave.interfaces import ControlPlane  # noqa: E402
from beehave.interfaces.http import TOKEN_ENV, HttpServer  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402
from tests.chromium import chromium  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_http_security")



@pytest.fixture
def plane(hl: HighLevelBehaviorManager) -> Iterator[ControlPlane]:
    hl.register("drive", Drive, station="dock")
    core = ControlPlane(hl, name="emili1")
    yield core
    core.close()


@pytest.fixture
def server(plane: ControlPlane, monkeypatch: pytest.MonkeyPatch) -> Iterator[HttpServer]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with HttpServer(plane, header_timeout_s=1.0) as srv:
        yield srv


@pytest.fixture
def driving(hl: HighLevelBehaviorManager) -> Any:
    """The robot runs ``drive``; returns the running instance."""
    hl.switch("drive")
    assert wait_until(lambda: hl.current == "drive" and hl.top is not None)
    return hl.top


def kept_driving(hl: HighLevelBehaviorManager, top: Any) -> None:
    assert hl.requested is None, f"a switch was requested: {hl.requested}"
    assert hl.current == "drive" and hl.top is top, "the running behaviour was interrupted"


def base(srv: HttpServer) -> str:
    return f"http://127.0.0.1:{srv.port}"


# ---- 1: commands need proof they come from the page itself or an API client ------------------

@pytest.mark.parametrize("headers", [
    {"Origin": "https://evil.example"},
    {"Origin": "null"},
    {"Origin": "http://127.0.0.1:1"},  # another port of this machine: another origin
    {"Sec-Fetch-Site": "cross-site"},
    {"Sec-Fetch-Site": "same-site"},
    {"Origin": "https://evil.example", "Sec-Fetch-Site": "cross-site",
     "Content-Type": "application/json"},
])
def test_a_command_from_another_origin_is_refused(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any,
        headers: dict[str, str]) -> None:
    for path, body in (("stop", {}), ("switch", {"behavior": "idle"})):
        answer = httpx.post(f"{base(server)}/api/robots/emili1/{path}", json=body,
                            headers=headers)
        assert answer.status_code == 403, answer.text
        assert answer.json()["error"] == "CrossOrigin"
    kept_driving(hl, driving)


@pytest.mark.parametrize("content_type", [None, "text/plain",
                                          "application/x-www-form-urlencoded",
                                          "multipart/form-data; boundary=x"])
def test_a_command_without_a_json_content_type_is_refused(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any,
        content_type: str | None) -> None:
    headers = {} if content_type is None else {"Content-Type": content_type}
    for path, body in (("stop", b""), ("switch", b'{"behavior": "idle"}')):
        answer = httpx.post(f"{base(server)}/api/robots/emili1/{path}", content=body,
                            headers=headers)
        assert answer.status_code == 415, answer.text
        assert "Content-Type: application/json" in answer.json()["detail"]
    kept_driving(hl, driving)


def test_api_clients_with_json_still_switch_and_stop(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any) -> None:
    api = f"{base(server)}/api/robots/emili1"
    assert httpx.post(f"{api}/stop", json={}).status_code == 202
    assert wait_until(lambda: hl.current == "idle")
    # A same-origin request as the page sends it (Origin and Sec-Fetch-Site its own).
    assert httpx.post(f"{api}/switch", json={"behavior": "drive"},
                      headers={"Origin": base(server), "Sec-Fetch-Site": "same-origin"}
                      ).status_code == 202
    assert wait_until(lambda: hl.current == "drive")


def test_the_page_behind_a_tls_proxy_may_command_with_its_token(
        plane: ControlPlane, hl: HighLevelBehaviorManager, driving: Any,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with HttpServer(plane, host="0.0.0.0", token="t0ken") as srv:
        api = f"http://127.0.0.1:{srv.port}/api/robots/emili1"
        page = {"Host": "robot.example", "Origin": "https://robot.example",
                "Sec-Fetch-Site": "same-origin", "Authorization": "Bearer t0ken"}
        foreign = dict(page, Origin="https://evil.example", **{"Sec-Fetch-Site": "cross-site"})
        assert httpx.post(f"{api}/stop", json={}, headers=foreign).status_code == 403
        kept_driving(hl, driving)
        assert httpx.post(f"{api}/stop", json={}, headers=page).status_code == 202
        assert wait_until(lambda: hl.current == "idle")


# ---- 2: DNS rebinding ----------------------------------------------------------------------

@pytest.mark.parametrize("method,path", [("post", "switch"), ("post", "stop"),
                                         ("get", "status")])
def test_a_foreign_host_name_is_refused(server: HttpServer, hl: HighLevelBehaviorManager,
                                        driving: Any, method: str, path: str) -> None:
    kwargs: dict[str, Any] = {"json": {"behavior": "idle"}} if method == "post" else {}
    answer = httpx.request(method, f"{base(server)}/api/robots/emili1/{path}",
                           headers={"Host": f"rebind.attacker.example:{server.port}"},
                           **kwargs)
    assert answer.status_code == 403, answer.text
    assert answer.json()["error"] == "ForbiddenHost"
    kept_driving(hl, driving)
    for host in ("localhost", "127.0.0.1", f"127.0.0.1:{server.port}"):
        assert httpx.get(f"{base(server)}/api/robots/emili1/status",
                         headers={"Host": host}).status_code == 200


# ---- 3: the WebSocket checks Origin on the upgrade ------------------------------------------

def test_a_websocket_from_a_foreign_origin_is_refused(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any) -> None:
    url = f"ws://127.0.0.1:{server.port}/api/ws"
    with pytest.raises(InvalidStatus) as refused:
        connect(url, origin="https://evil.example", open_timeout=WALL_TIMEOUT_S)
    assert refused.value.response.status_code == 403
    with pytest.raises(InvalidStatus) as rebound:
        connect(url, additional_headers={"Host": "rebind.attacker.example"},
                open_timeout=WALL_TIMEOUT_S)
    assert rebound.value.response.status_code == 403
    kept_driving(hl, driving)
    # The page's own origin and a plain client (no Origin) are served.
    for origin in (base(server), None):
        with connect(url, origin=origin, open_timeout=WALL_TIMEOUT_S) as ws:  # type: ignore[arg-type]
            assert json.loads(ws.recv(WALL_TIMEOUT_S))["type"] == "update"


# ---- 4: no third-party script, the schema behind the token -----------------------------------

def test_no_swagger_ui_and_the_schema_needs_the_token_off_loopback(
        plane: ControlPlane, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with HttpServer(plane, host="0.0.0.0", token="t0ken") as srv:
        url = f"http://127.0.0.1:{srv.port}"
        assert httpx.get(f"{url}/docs").status_code in (401, 404)
        assert httpx.get(f"{url}/redoc").status_code in (401, 404)
        assert httpx.get(f"{url}/openapi.json").status_code == 401
        spec = httpx.get(f"{url}/openapi.json", headers={"Authorization": "Bearer t0ken"})
        assert spec.status_code == 200 and "/api/robots/{robot}/switch" in spec.json()["paths"]
        assert "cdn" not in httpx.get(f"{url}/").text.lower()


# ---- 5: bounded request bodies ---------------------------------------------------------------

def _raw(port: int, head: bytes) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=WALL_TIMEOUT_S)
    sock.sendall(head)
    return sock


def _status_line(sock: socket.socket) -> bytes:
    data = b""
    while b"\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    return data.split(b"\r\n", 1)[0]


def test_an_oversized_body_is_refused_before_it_is_read(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any) -> None:
    head = (f"POST /api/robots/emili1/switch HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {100 * 2**20}\r\n\r\n")
    with _raw(server.port, head.encode()) as sock:
        assert b" 413 " in _status_line(sock)  # no byte of the body was sent
    # Chunked: the server answers 413 while the client is still sending.
    head = (f"POST /api/robots/emili1/switch HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n"
            f"Content-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n")
    sent = 0
    with _raw(server.port, head.encode()) as sock:
        chunk = b"10000\r\n" + b"x" * 0x10000 + b"\r\n"
        answered = threading.Event()
        status: list[bytes] = []

        def read() -> None:
            status.append(_status_line(sock))
            answered.set()

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        try:
            while not answered.is_set() and sent < 100 * 2**20:
                sock.sendall(chunk)
                sent += len(chunk)
        except OSError:
            pass  # the server closed the connection: what it should do
        reader.join(WALL_TIMEOUT_S)
    assert status and b" 413 " in status[0], status
    assert sent < 100 * 2**20, "the whole 100 MB body was taken"
    kept_driving(hl, driving)
    assert httpx.get(f"{base(server)}/api/robots/emili1/status").status_code == 200


def test_an_oversized_websocket_message_closes_that_stream_only(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any) -> None:
    from websockets.exceptions import ConnectionClosed

    url = f"ws://127.0.0.1:{server.port}/api/ws"
    with connect(url, open_timeout=WALL_TIMEOUT_S, max_size=2**22) as ws:
        ws.send("x" * 2**20)
        deadline = time.monotonic() + WALL_TIMEOUT_S
        with pytest.raises(ConnectionClosed) as closed:
            while time.monotonic() < deadline:  # updates come until the server closes
                ws.recv(WALL_TIMEOUT_S)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009
    kept_driving(hl, driving)
    with connect(url, open_timeout=WALL_TIMEOUT_S) as ws:
        assert json.loads(ws.recv(WALL_TIMEOUT_S))["type"] == "update"


# ---- 6: what a refused switch leaves in the event log and echoes is bounded -------------------

def test_huge_refused_parameters_are_cut_in_the_answer_the_event_log_and_the_stream(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any) -> None:
    api = f"{base(server)}/api/robots/emili1"
    huge = {"payload": "x" * 40_000, "many": list(range(2_000))}
    for _ in range(20):
        answer = httpx.post(f"{api}/switch", json={"behavior": "drive", "params": huge})
        assert answer.status_code == 422, answer.text[:300]
        assert len(answer.content) < 4_000 and "cut" in answer.json()["detail"]
    kept_driving(hl, driving)
    events = httpx.get(f"{api}/events", params={"limit": 10_000})
    rejected = [e for e in events.json() if e["kind"] == "switch_rejected"]
    assert len(rejected) == 20
    assert len(events.content) < 20 * 4_000, len(events.content)
    # A new WebSocket client receives the backlog: bounded as well.
    with connect(f"ws://127.0.0.1:{server.port}/api/ws", open_timeout=WALL_TIMEOUT_S,
                 max_size=2**20) as ws:
        received: list[dict[str, Any]] = []
        while sum(1 for m in received for e in m["events"]
                  if e["kind"] == "switch_rejected") < 20:
            received.append(json.loads(ws.recv(WALL_TIMEOUT_S)))


# ---- 7: blackboard patterns cost linear time; too long or malformed ones get 400 -------------

def test_pathological_blackboard_patterns_answer_at_once_or_get_400(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any) -> None:
    for key in ("battery/percentage", "odom/x_m", "a/b/c/d/e/f"):
        hl.blackboard.set(key, 1.0, writer="test")
    url = f"{base(server)}/api/robots/emili1/blackboard"
    # 166 "**" segments (500 characters): exponential before, a moment now.
    pattern = "/".join(["**"] * 166) + "/x_m"
    answer = httpx.get(url, params={"pattern": pattern}, timeout=WALL_TIMEOUT_S)
    assert answer.status_code == 200, answer.text[:300]
    assert list(answer.json()) == ["odom/x_m"]
    answer = httpx.get(url, params={"pattern": "/".join(["**", "f"] * 100)},
                       timeout=WALL_TIMEOUT_S)
    assert answer.status_code == 200
    for bad, why in (("/".join(["**"] * 2000), "at most"), ("a/b*c", "segment"),
                     ("a//b", "segment")):
        answer = httpx.get(url, params={"pattern": bad}, timeout=WALL_TIMEOUT_S)
        assert answer.status_code == 400, answer.text[:200]
        assert why in answer.json()["detail"] and len(answer.content) < 2_000
    kept_driving(hl, driving)


# ---- 8: half-open connections are closed -----------------------------------------------------

def test_half_open_connections_are_closed_after_the_header_timeout(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any) -> None:
    socks = [_raw(server.port, b"GET /api/robots HTTP/1.1\r\nHost: 127.0.0.1\r\n")
             for _ in range(50)]
    try:
        # Meanwhile the server answers others.
        assert httpx.get(f"{base(server)}/api/robots/emili1/status").status_code == 200
        for sock in socks:  # every one is closed by the server (recv returns b"")
            sock.settimeout(WALL_TIMEOUT_S)
            assert sock.recv(4096) == b""
    finally:
        for sock in socks:
            sock.close()
    kept_driving(hl, driving)


# ---- a cap on connections ---------------------------------------------------------------------

def test_connections_above_the_cap_are_refused_with_503_and_the_served_ones_go_on(
        plane: ControlPlane, hl: HighLevelBehaviorManager, driving: Any,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Clients beyond ``max_connections`` (HTTP, WebSocket) get 503 with Retry-After (a
    WebSocket's handshake too) and their connection closed; the streams already open keep
    receiving, the robot keeps driving, and a slot that frees is served again."""
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with HttpServer(plane, max_connections=4, refresh_s=0.2) as srv, \
            contextlib.ExitStack() as opened:
        url = f"ws://127.0.0.1:{srv.port}/api/ws"
        streams = [opened.enter_context(connect(url)) for _ in range(3)]
        keep_alive = _raw(srv.port, b"GET /api/robots/emili1/status HTTP/1.1\r\n"
                                    b"Host: 127.0.0.1\r\n\r\n")
        try:
            assert _status_line(keep_alive).startswith(b"HTTP/1.1 200")
            # Four open: three streams and one kept-alive connection. A fifth:
            refused = httpx.get(f"{base(srv)}/api/robots/emili1/status")
            assert refused.status_code == 503, refused.text
            assert refused.json()["error"] == "TooManyConnections"
            assert "max_connections" in refused.json()["detail"]
            assert refused.headers["retry-after"] == "1"
            assert refused.headers["connection"] == "close"
            with pytest.raises(InvalidStatus) as ws_refused:
                connect(url)
            assert ws_refused.value.response.status_code == 503
            for stream in streams:  # the served ones are not disturbed
                assert json.loads(stream.recv(timeout=WALL_TIMEOUT_S))["robot"] == "emili1"
            kept_driving(hl, driving)
        finally:
            keep_alive.close()
        # A slot frees: served again.
        assert wait_until(lambda: httpx.get(
            f"{base(srv)}/api/robots/emili1/status").status_code == 200)
    kept_driving(hl, driving)


def test_max_connections_must_be_a_positive_int(plane: ControlPlane) -> None:
    for bad in (0, -1, 2.5, True, "100"):
        with pytest.raises(ConfigError, match="max_connections must be a positive int"):
            HttpServer(plane, max_connections=bad)  # type: ignore[arg-type]


# ---- chromium on another origin: no-cors fetch and form posts --------------------------------

ATTACK = """<!doctype html><html><body>
<form id="plain" method="POST" enctype="text/plain" action="{robot}/api/robots/emili1/switch">
<input name='{{"behavior":"idle","x":"' value='"}}'></form>
<form id="urlenc" method="POST" action="{robot}/api/robots/emili1/stop">
<input name="a" value="b"></form>
</body></html>"""


class _Attacker(http.server.BaseHTTPRequestHandler):
    page = b""

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(self.page)))
        self.end_headers()
        self.wfile.write(self.page)

    def log_message(self, *args: Any) -> None:
        pass


@pytest.fixture
def attacker(server: HttpServer) -> Iterator[str]:
    """A page on another origin (localhost, another port: another site than 127.0.0.1)."""
    handler = type("Attacker", (_Attacker,), {
        "page": ATTACK.format(robot=base(server)).encode()})
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://localhost:{httpd.server_address[1]}/"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(5)


@pytest.fixture
def browser() -> Iterator[Any]:
    with chromium() as launched:
        yield launched


def test_a_page_of_another_origin_cannot_command_the_robot(
        server: HttpServer, attacker: str, browser: Any, hl: HighLevelBehaviorManager,
        driving: Any) -> None:
    page = browser.new_page()
    try:
        page.goto(attacker)
        robot = base(server)
        # no-cors fetches: the response is opaque, but they reach the server.
        for path, init in (
                ("stop", '{method: "POST", mode: "no-cors"}'),
                ("stop", '{method: "POST", mode: "no-cors", body: "{}", '
                         'headers: {"Content-Type": "text/plain"}}'),
                ("switch", '{method: "POST", mode: "no-cors", '
                           'body: JSON.stringify({behavior: "idle"})}')):
            page.evaluate(f'async () => {{ await fetch("{robot}/api/robots/emili1/{path}", '
                          f'{init}); }}')
        # A CORS fetch with JSON needs a preflight, which is never granted.
        refused = page.evaluate(
            f'async () => {{ try {{ await fetch("{robot}/api/robots/emili1/stop", '
            f'{{method: "POST", headers: {{"Content-Type": "application/json"}}, '
            f'body: "{{}}"}}); return false; }} catch (e) {{ return true; }} }}')
        assert refused
        # A WebSocket opened by the foreign page is refused too.
        opened = page.evaluate(
            f'() => new Promise(done => {{ const ws = new WebSocket("ws://127.0.0.1:'
            f'{server.port}/api/ws"); ws.onmessage = () => done(true); '
            f'ws.onerror = () => done(false); }})')
        assert opened is False
        # Form posts (top-level navigations): the answer is the refusal.
        for form in ("plain", "urlenc"):
            page.goto(attacker)
            with page.expect_navigation(timeout=WALL_TIMEOUT_S * 1000):
                page.evaluate(f'() => document.getElementById("{form}").submit()')
            assert "CrossOrigin" in page.content() or "UnsupportedMediaType" in page.content()
        kept_driving(hl, driving)
        # The robot's own page may command it.
        page.goto(robot + "/")
        status = page.evaluate(
            'async () => (await fetch("/api/robots/emili1/stop", {method: "POST", '
            'headers: {"Content-Type": "application/json"}, body: "{}"})).status')
        assert status == 202
        assert wait_until(lambda: hl.current == "idle")
    finally:
        page.close()



# ---- 9: parameters are checked against the constructor's annotations before anything stops --

class Rounds(Behavior):
    def __init__(self, rounds: int, speed_mps: Annotated[float, Gt(0)] = 0.5,
                 stations: tuple[str, ...] = ()) -> None:
        self.rounds, self.speed_mps, self.stations = rounds, speed_mps, stations

    def run(self) -> None:
        while self.sleep(0.01):
            pass


@pytest.mark.parametrize("params,named,expected", [
    ({"rounds": "many"}, "'rounds'", "int"),
    ({"rounds": 2, "speed_mps": -5}, "'speed_mps'", "float"),
    ({"rounds": 2, "stations": "dock"}, "'stations'", "tuple"),
    ({"rounds": 2.5}, "'rounds'", "int"),
])
def test_a_parameter_of_the_wrong_type_is_refused_and_stops_nothing(
        server: HttpServer, hl: HighLevelBehaviorManager, plane: ControlPlane,
        driving: Any, params: dict[str, Any], named: str, expected: str) -> None:
    hl.register("rounds", Rounds)
    answer = httpx.post(f"{base(server)}/api/robots/emili1/switch",
                        json={"behavior": "rounds", "params": params})
    assert answer.status_code == 422, answer.text
    detail = answer.json()["detail"]
    value = next(v for k, v in params.items() if f"'{k}'" == named)
    assert named in detail and expected in detail and repr(value) in detail, detail
    kept_driving(hl, driving)
    # The same refusal for every interface: they all switch through the control plane.
    with pytest.raises(InvalidParameters, match=named):
        plane.switch("rounds", params)
    kept_driving(hl, driving)


def test_parameters_of_the_right_type_switch_and_are_converted(
        server: HttpServer, hl: HighLevelBehaviorManager, driving: Any) -> None:
    hl.register("rounds", Rounds)
    answer = httpx.post(f"{base(server)}/api/robots/emili1/switch", json={
        "behavior": "rounds", "params": {"rounds": 3, "speed_mps": 1, "stations": ["a"]}})
    assert answer.status_code == 202, answer.text
    assert wait_until(lambda: hl.current == "rounds")
    top = hl.top
    assert (top.rounds, top.speed_mps, top.stations) == (3, 1.0, ("a",))


# ---- 10: an undocumented behaviour is described with nothing, not the base class's text ------

def test_an_undocumented_behaviour_has_no_description(server: HttpServer,
                                                      hl: HighLevelBehaviorManager) -> None:
    hl.register("rounds", Rounds)
    listed = httpx.get(f"{base(server)}/api/robots/emili1/behaviors").json()
    rounds = next(b for b in listed if b["name"] == "rounds")
    assert rounds["doc"] == ""
    drive = next(b for b in listed if b["name"] == "drive")
    assert drive["doc"].startswith("Drives to a station")
    types = {p["name"]: p["type"] for p in rounds["parameters"]}
    assert types["rounds"] == "int" and types["speed_mps"].startswith("float")
