"""The FastAPI application: REST endpoints, the WebSocket stream and the web view.

Every endpoint calls the robot's :class:`~beehave.interfaces.ControlPlane` and maps its
typed errors to HTTP (see :data:`STATUS_OF`); none validates a name or a parameter itself.
"""


import asyncio
import contextlib
import logging
import secrets
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field

from beehave.errors import (
    BadRequest,
    BeehaveError,
    BlackboardError,
    ConfigError,
    ConstructorFailed,
    InvalidParameters,
    ManagerShutdown,
    UnknownKey,
    UnknownNameError,
)
from beehave.interfaces.core import ControlPlane, shorten
from beehave.interfaces.http.guard import MAX_BODY_BYTES, MAX_CONNECTIONS, Guard
from beehave.interfaces.http.hub import Client, Hub
from beehave.interfaces.http.remote import Address, RemoteError, Remotes

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).parent / "static"

#: A world map or a fleet view: a JSON-able mapping, or a function returning one (called
#: on every request, so it may change), or None.
Provider = Mapping[str, Any] | Callable[[], Mapping[str, Any] | None] | None

#: HTTP status per error type (the first match in this order wins).
STATUS_OF: list[tuple[type[BaseException], int]] = [
    (UnknownKey, 404), (UnknownNameError, 404), (InvalidParameters, 422),
    (BadRequest, 400), (BlackboardError, 400), (ConfigError, 400),
    (ConstructorFailed, 500), (ManagerShutdown, 503), (BeehaveError, 400)]

#: The subprotocol the web view offers; a token travels as a second one, ``bearer.TOKEN``.
SUBPROTOCOL = "beehave"
BEARER_PREFIX = "bearer."


class Auth:
    """The token rules. Without a token everything is open (only allowed on loopback:
    :class:`~beehave.interfaces.http.HttpServer` enforces that). With one, commands
    (switch, stop) always need it; reads need it too unless the server listens on loopback
    only."""

    def __init__(self, token: str | None, *, loopback: bool) -> None:
        self.token = token
        self.loopback = loopback

    def allows(self, presented: str | None, *, command: bool) -> bool:
        if self.token is None or (self.loopback and not command):
            return True
        return presented is not None and secrets.compare_digest(
            presented.encode(), self.token.encode())

    def describe(self) -> dict[str, Any]:
        return {"token_required_for_reads": self.token is not None and not self.loopback,
                "token_required_for_commands": self.token is not None}


class SwitchRequest(BaseModel):
    """``POST /api/robots/{robot}/switch``."""

    model_config = ConfigDict(extra="forbid")
    behavior: str = Field(description="a registered top-level behaviour (GET .../behaviors)")
    params: dict[str, Any] = Field(default_factory=dict,
                                   description="constructor parameters, JSON values")


class BreakpointRequest(BaseModel):
    """``POST /api/robots/{robot}/breakpoints`` (and ``…/breakpoints/remove``)."""

    model_config = ConfigDict(extra="forbid")
    kind: str = Field(description="'state', 'node' or 'action_type'")
    target: str = Field(description="a state name, a tree node's path or name, an action "
                                    "type (GET …/breakpoints lists the choices)")


class HttpError(Exception):
    def __init__(self, status: int, error: str, detail: str) -> None:
        super().__init__(detail)
        self.status, self.error, self.detail = status, error, detail


def _bearer(request: Request) -> str | None:
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    return request.query_params.get("token")


def create_app(planes: Mapping[str, ControlPlane], *, world: Provider = None,
               fleet: Provider = None, token: str | None = None, loopback: bool = True,
               rate_hz: float = 20.0, refresh_s: float = 1.0,
               on_started: Callable[[], None] | None = None, hosts: Iterable[str] = (),
               origins: Iterable[str] = (), max_body_bytes: int = MAX_BODY_BYTES,
               remotes: Mapping[str, Address] | None = None,
               connections: Callable[[], int] | None = None,
               max_connections: int = MAX_CONNECTIONS, recording: Any = None) -> FastAPI:
    """The application serving ``planes`` (robot name → its control plane).

    ``world``: the map the web view draws (the world YAML as JSON: floor, walls, shelves,
    obstacles, lanes, stations); ``fleet``: what ``GET /api/fleet`` returns (agents,
    contracts, messages); ``token`` and ``loopback``: see :class:`Auth`; ``rate_hz``:
    the most WebSocket updates per robot and second; ``refresh_s``: the longest time
    between two updates of a robot that did not change (ages move on); ``on_started``:
    called once the server has started (its lifespan began). ``hosts``, ``origins``,
    ``max_body_bytes``: what :class:`~beehave.interfaces.http.guard.Guard` accepts besides
    the loopback names and the server's own origin, and the largest request body.
    ``remotes``: robots served by other processes, name → their server's address
    (``http://127.0.0.1:8101/``, with ``#token=…`` when it has one), or a function returning
    it once known (None before); ``connections`` (how many the server holds open now) and
    ``max_connections``: the connection limit. Their API and stream
    are forwarded (:mod:`beehave.interfaces.http.remote`), so the page shows them too.
    ``recording``: a :class:`~beehave.recording.timeline.RecordingTimeline` served
    read-only instead of live robots (``beehave view``,
    :mod:`beehave.interfaces.http.recorded`).
    """
    forwarded = Remotes(remotes or {})
    both = sorted(set(planes) & set(forwarded.robots))
    if both:
        raise ConfigError(f"robot(s) {both} are given both as a ControlPlane and as a remote "
                          f"address: serve each robot one way")
    if not planes and fleet is None and not forwarded and recording is None:
        raise ConfigError("the HTTP interface needs at least one robot's ControlPlane, or a "
                          "fleet view (a fleet process whose robots run elsewhere)")
    for name in planes:
        if not isinstance(name, str) or not name or "/" in name:
            raise ConfigError(f"robot names served over HTTP must be non-empty strings "
                              f"without '/', got {name!r}")
    auth = Auth(token, loopback=loopback)
    hub = Hub(planes, rate_hz=rate_hz, refresh_s=refresh_s)

    @contextlib.asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        try:  # the hub stops even when its start or on_started fails halfway
            hub.start()
            await forwarded.start()
            if on_started is not None:
                on_started()
            yield
        finally:
            await forwarded.stop()
            await hub.stop()

    # No /docs: Swagger UI would load its script from a CDN into the robot's origin (and
    # stay blank offline). The schema is served below, behind the read rule.
    app = FastAPI(
        title="beehave robot API", lifespan=lifespan, docs_url=None, redoc_url=None,
        openapi_url=None,
        description="Switch behaviours, read what runs, the blackboard and the events of "
                    "beehave robots; `WS /api/ws` streams coalesced updates. The web view "
                    "is at `/`. With a token: `Authorization: Bearer TOKEN`.")
    app.state.hub = hub
    app.state.remotes = forwarded
    app.state.auth = auth
    # Host (DNS rebinding) is checked whenever something is answered without a token.
    app.add_middleware(Guard, check_host=token is None or loopback, hosts=hosts,
                       origins=origins, max_body_bytes=max_body_bytes,
                       connections=connections, max_connections=max_connections)

    @app.exception_handler(BeehaveError)
    async def beehave_error(_: Request, exc: BeehaveError) -> JSONResponse:
        status = next(code for kind, code in STATUS_OF if isinstance(exc, kind))
        if status >= 500:
            log.warning("HTTP %d: %s", status, exc)
        # Bounded: an error naming a huge value must not echo it (issue 22).
        return JSONResponse({"error": type(exc).__name__, "detail": shorten(str(exc))},
                            status)

    @app.exception_handler(RemoteError)
    async def remote_error(_: Request, exc: RemoteError) -> JSONResponse:
        return JSONResponse({"error": "RemoteRobotUnavailable", "detail": shorten(str(exc))},
                            502)

    @app.exception_handler(HttpError)
    async def http_error(_: Request, exc: HttpError) -> JSONResponse:
        return JSONResponse({"error": exc.error, "detail": exc.detail}, exc.status)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_: Request, exc: RequestValidationError) -> JSONResponse:
        # One readable sentence per problem, naming where it is (body.behavior, query.limit).
        problems = ["{}: {}".format(".".join(str(p) for p in err.get("loc", ())),
                                    err.get("msg", "invalid")) for err in exc.errors()]
        return JSONResponse({"error": "BadRequest", "detail": shorten("; ".join(problems))},
                            422)

    @app.exception_handler(Exception)
    async def unexpected(_: Request, exc: Exception) -> JSONResponse:
        log.exception("HTTP request failed")
        return JSONResponse({"error": type(exc).__name__, "detail": shorten(str(exc))}, 500)

    def read_access(request: Request) -> None:
        if not auth.allows(_bearer(request), command=False):
            raise HttpError(401, "Unauthorized", "missing or wrong token: send "
                            "'Authorization: Bearer TOKEN' (printed when the server started, "
                            "or BEEHAVE_HTTP_TOKEN)")

    def command_access(request: Request) -> None:
        if not auth.allows(_bearer(request), command=True):
            raise HttpError(401, "Unauthorized", "switching needs the token: send "
                            "'Authorization: Bearer TOKEN' (printed when the server started, "
                            "or BEEHAVE_HTTP_TOKEN)")

    def plane_of(robot: str) -> ControlPlane:
        plane = planes.get(robot)
        if plane is None:
            raise HttpError(404, "UnknownRobot", f"unknown robot {robot!r}; serving: "
                            f"{', '.join(repr(n) for n in served)}")
        return plane

    served = sorted([*planes, *forwarded.robots])
    Read = Annotated[None, Depends(read_access)]
    Command = Annotated[None, Depends(command_access)]
    Plane = Annotated[ControlPlane, Depends(plane_of)]

    def provided(provider: Provider, what: str) -> Mapping[str, Any]:
        value = provider() if callable(provider) else provider
        if value is None:
            raise HttpError(404, "NotServed", f"this server has no {what}")
        return value

    def forwarder(name: str) -> Callable[..., Awaitable[Response]]:
        async def forward(request: Request, rest: str, _: Read) -> Response:
            if request.method != "GET":
                command_access(request)
            status, content, kind = await forwarded.forward(
                name, request.method, request.scope["raw_path"].decode("latin-1"),
                request.scope.get("query_string", b""), await request.body())
            return Response(content, status, media_type=kind)
        return forward

    if recording is not None:  # `beehave view`: its routes answer before the live ones
        from beehave.interfaces.http.recorded import add_recording_routes

        add_recording_routes(app, recording, Read, HttpError)

    for name in forwarded.robots:
        # One literal route per remote robot, ahead of the local routes (the first route
        # that matches answers).
        app.add_api_route(f"/api/robots/{name}/{{rest:path}}", forwarder(name),
                          methods=["GET", "POST"], include_in_schema=False)

    @app.get("/api/robots", summary="The robots served, with what each runs")
    def robots(_: Read) -> dict[str, Any]:
        local = [{"name": name, "behavior": plane.high.current,
                  "logic": None if plane.low is None else plane.low.current}
                 for name, plane in sorted(planes.items())]
        # A remote robot's state is its own server's to tell (its /status, its stream).
        remote = []
        for name in sorted(forwarded.robots):
            found = None
            with contextlib.suppress(BeehaveError):  # not told yet / a bad one: null
                found = forwarded.find(name)
            remote.append({"name": name, "remote": found.base if found else None})
        return {"robots": local + remote,
                "auth": auth.describe(), "world": world is not None,
                "fleet": fleet is not None}

    @app.get("/api/world", summary="The world map (floor, walls, shelves, lanes, stations)")
    def get_world(_: Read) -> Mapping[str, Any]:
        return provided(world, "world map (start it with world=…)")

    @app.get("/api/fleet", summary="The fleet: agents, contracts, auctions, messages")
    def get_fleet(_: Read) -> Mapping[str, Any]:
        return provided(fleet, "fleet view (only a fleet process serves one)")

    @app.get("/api/robots/{robot}/status", summary="What runs: behaviour, actions, locks, "
                                                   "STUCK items, decision engines")
    def status(_: Read, plane: Plane) -> dict[str, Any]:
        return plane.status()

    @app.get("/api/robots/{robot}/snapshot",
             summary="status + the behaviour tree with statuses + the low level")
    def snapshot(_: Read, plane: Plane) -> dict[str, Any]:
        return plane.snapshot()

    @app.get("/api/robots/{robot}/behaviors",
             summary="Registered top-level behaviours with their parameters")
    def behaviors(_: Read, plane: Plane) -> list[dict[str, Any]]:
        return plane.behaviors()

    @app.get("/api/robots/{robot}/logics",
             summary="Registered top-level logics with their parameters")
    def logics(_: Read, plane: Plane) -> list[dict[str, Any]]:
        return plane.logics()

    @app.post("/api/robots/{robot}/switch", status_code=202,
              summary="Switch the top-level behaviour (validated before anything stops)")
    def switch(_: Command, plane: Plane, body: SwitchRequest) -> dict[str, Any]:
        return plane.switch(body.behavior, body.params)

    @app.post("/api/robots/{robot}/stop", status_code=202,
              summary="Switch to idle: every action ends in its safe state")
    def stop(_: Command, plane: Plane) -> dict[str, Any]:
        return plane.stop()

    @app.post("/api/robots/{robot}/pause", status_code=202,
              summary="Pause in place: every action to a safe stop, the behaviour kept")
    def pause(_: Command, plane: Plane) -> dict[str, Any]:
        return plane.pause()

    @app.post("/api/robots/{robot}/resume", status_code=200,
              summary="End the pause: the behaviour goes on where it was")
    def resume(_: Command, plane: Plane) -> dict[str, Any]:
        return plane.resume()

    @app.get("/api/robots/{robot}/structure",
             summary="The structure of each running decision engine (states and labelled "
                     "transitions, tree nodes): fetched when an update names a new "
                     "structure_id")
    def structure(_: Read, plane: Plane) -> dict[str, Any]:
        return {"engines": plane.structures()}

    @app.get("/api/robots/{robot}/breakpoints",
             summary="Breakpoints set, the one that holds the robot (hit), valid targets")
    def get_breakpoints(_: Read, plane: Plane) -> dict[str, Any]:
        return plane.breakpoints()

    @app.post("/api/robots/{robot}/breakpoints", status_code=201,
              summary="Pause the robot when a state, a tree node or an action type is "
                      "entered")
    def set_breakpoint(_: Command, plane: Plane, body: BreakpointRequest) -> dict[str, Any]:
        return plane.set_breakpoint(body.kind, body.target)

    @app.post("/api/robots/{robot}/breakpoints/remove", status_code=200,
              summary="Remove a breakpoint")
    def clear_breakpoint(_: Command, plane: Plane, body: BreakpointRequest
                         ) -> dict[str, Any]:
        return plane.clear_breakpoint(body.kind, body.target)

    @app.post("/api/robots/{robot}/continue", status_code=200,
              summary="Continue after a breakpoint (ends the pause)")
    def continue_(_: Command, plane: Plane) -> dict[str, Any]:
        return plane.continue_()

    @app.get("/api/robots/{robot}/blackboard",
             summary="Blackboard entries by key or pattern, with age and staleness")
    def blackboard(_: Read, plane: Plane,
                   key: Annotated[str | None, Query(description="one key")] = None,
                   pattern: Annotated[str, Query(description="'*' one segment, '**' any"
                                                 )] = "**") -> dict[str, Any]:
        return plane.blackboard(key=key, pattern=pattern)

    @app.get("/api/robots/{robot}/events", summary="Recent events (after_seq to read on)")
    def events(_: Read, plane: Plane,
               after_seq: Annotated[int, Query(ge=0)] = 0,
               limit: Annotated[int, Query(ge=0, le=10_000)] = 200) -> list[dict[str, Any]]:
        return plane.events(after_seq=after_seq, limit=limit)

    @app.get("/api/stats", summary="WebSocket clients, updates built, snapshots dropped")
    def stats(_: Read) -> dict[str, Any]:
        return hub.stats()

    @app.websocket("/api/ws")
    async def stream(websocket: WebSocket, robots: str | None = None,
                     token: str | None = None) -> None:
        """Updates of the robots (comma-separated names, default: this process's robots;
        a robot of another process is relayed from its own server): one JSON message
        per robot and turn, ``{"type": "update", "robot", "seq", "stamp", "snapshot",
        "blackboard", "events"}`` (``snapshot`` and ``blackboard`` may be missing from a
        message that only carries events), plus this connection's ``dropped`` and
        ``events_dropped`` counts in its first message and whenever they change."""
        offered = list(websocket.scope.get("subprotocols", []))
        presented = token or next((p[len(BEARER_PREFIX):] for p in offered
                                   if p.startswith(BEARER_PREFIX)), None)
        if not auth.allows(presented, command=False):
            await _deny(websocket, 401, "missing or wrong token: offer the subprotocol "
                                        "'bearer.TOKEN' or add ?token=TOKEN")
            return
        # Default: this process's robots. A robot of another process is streamed when
        # named (the page asks for the one it shows).
        names = sorted(planes) if not robots else [n.strip() for n in robots.split(",")
                                                    if n.strip()]
        unknown = [n for n in names if n not in planes and n not in forwarded]
        if unknown or not names:
            await _deny(websocket, 404, f"unknown robot(s) {unknown}; serving: "
                                        f"{', '.join(served)}")
            return
        await websocket.accept(subprotocol=SUBPROTOCOL if SUBPROTOCOL in offered else None)
        local = [n for n in names if n in planes]
        remote = [n for n in names if n in forwarded]
        lock = asyncio.Lock()

        async def send_locked(text: str) -> None:
            async with lock:
                await websocket.send_text(text)

        # Several writers (the hub's client, relays) send one frame at a time.
        send = send_locked if len(remote) + bool(local) > 1 else websocket.send_text
        loop = asyncio.get_running_loop()
        client = hub.add(local) if local else None
        senders = [loop.create_task(_send_loop(send, client))] if client is not None else []
        senders += [loop.create_task(forwarded.relay(name, send)) for name in remote]
        receiver = loop.create_task(_until_disconnect(websocket))
        gone = False
        try:
            await asyncio.wait([receiver, *senders], return_when=asyncio.FIRST_COMPLETED)
            gone = receiver.done()
        finally:
            if client is not None:
                hub.remove(client)
            for task in (receiver, *senders):
                task.cancel()
            await asyncio.wait([receiver, *senders])  # never raises
            ended = [t for t in senders if not t.cancelled()]
            for task in ended:
                error = task.exception()
                if error is not None and not isinstance(error, _CLIENT_GONE):
                    log.warning("web view: the stream to a WebSocket client failed: %r",
                                error, exc_info=not isinstance(error, RemoteError))
        if ended and not gone:
            # A robot's stream ended (its process stopped): the page reconnects.
            with contextlib.suppress(*_CLIENT_GONE):
                await websocket.close(code=1011, reason="a robot's stream ended")

    @app.get("/openapi.json", include_in_schema=False)
    def openapi(_: Read) -> dict[str, Any]:
        return app.openapi()

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    return app


_CLIENT_GONE = (WebSocketDisconnect, RuntimeError, OSError)
"""What a send raises when the client has just gone (starlette: RuntimeError after the
close; uvicorn: ClientDisconnected, an OSError): not worth a warning. Anything else is."""


async def _until_disconnect(websocket: WebSocket) -> None:
    """Wait until the client goes (it sends nothing else on the stream)."""
    with contextlib.suppress(WebSocketDisconnect):
        while (await websocket.receive())["type"] != "websocket.disconnect":
            pass


async def _send_loop(send: Callable[[str], Awaitable[None]], client: Client) -> None:
    while True:
        for message in await client.next_messages():
            # Awaits the socket's flow control: only this client waits, and the pump
            # meanwhile replaces what it has not sent yet. Text frames: what a browser's
            # JSON.parse takes without a Blob round trip.
            await send(message)
            client.sent += 1


async def _deny(websocket: WebSocket, status: int, detail: str) -> None:
    """Refuse the handshake with an HTTP status (401, 404) the browser can see."""
    response = JSONResponse({"error": "Unauthorized" if status == 401 else "UnknownRobot",
                             "detail": detail}, status)
    try:
        await websocket.send_denial_response(response)
    except RuntimeError:  # a server without the denial extension: close before accept
        await websocket.close(code=4000 + status, reason=detail[:120])


__all__ = ["STATUS_OF", "Auth", "Provider", "SwitchRequest", "create_app"]
