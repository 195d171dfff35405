"""Run the HTTP/WebSocket interface in a thread of the robot's (or fleet's) process."""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import os
import secrets
import socket
import threading
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from beehave.errors import BeehaveError, ConfigError
from beehave.interfaces.core import ControlPlane
from beehave.interfaces.http.app import Provider, create_app
from beehave.interfaces.http.guard import (
    HEADER_TIMEOUT_S,
    MAX_BODY_BYTES,
    MAX_CONNECTIONS,
    header_timeout_protocol,
)
from beehave.interfaces.http.remote import Address
from beehave.lifecycle import Running

if TYPE_CHECKING:
    from beehave.lowlevel import LowLevelBehaviorManager

log = logging.getLogger(__name__)

#: The HALs whose blackboard entries the web view's map draws (pose, battery). HALs load
#: on demand, when a logic asks: a robot whose logics never need odometry would show no
#: marker, so ``beehave run --http`` holds these (those the robot configures) while it
#: serves. See :func:`hold_hals`.
VIEW_HALS = ("odometry", "battery")

#: The environment variable a token is taken from when none is passed.
TOKEN_ENV = "BEEHAVE_HTTP_TOKEN"
DEFAULT_HOST = "127.0.0.1"


def is_loopback(host: str) -> bool:
    """Whether ``host`` is reachable from this machine only (127.0.0.0/8, ::1,
    ``localhost``)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def address_arg(text: str) -> tuple[str, int]:
    """An argparse ``type`` for ``[HOST:]PORT`` (127.0.0.1 unless a host is given)."""
    import argparse

    try:
        return parse_address(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def parse_address(text: str) -> tuple[str, int]:
    """``PORT``, ``HOST:PORT`` or ``[IPv6]:PORT`` → (host, port); the host defaults to
    127.0.0.1 and port 0 picks a free one. :class:`ConfigError` says what is wrong."""
    host, port_text = DEFAULT_HOST, text.strip()
    if port_text.startswith("["):
        inner, sep, rest = port_text[1:].partition("]")
        if not sep or not rest.startswith(":"):
            raise ConfigError(f"HTTP address {text!r}: write an IPv6 host as [::1]:PORT")
        host, port_text = inner, rest[1:]
    elif ":" in port_text:
        host, _, port_text = port_text.rpartition(":")
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ConfigError(f"HTTP address {text!r}: expected PORT or HOST:PORT with a port "
                          f"0–65535 (0 picks a free one), e.g. 8080 or 0.0.0.0:8080")
    if not host:
        raise ConfigError(f"HTTP address {text!r}: the host before ':' is empty")
    return host, int(port_text)


class HttpServer(Running):
    """The HTTP/WebSocket interface and web view of one or more robots, served by uvicorn
    in a thread of its own (with its own event loop) of this process.

    ``planes``: one :class:`~beehave.interfaces.ControlPlane`, or robot name → plane.
    ``host``: 127.0.0.1 by default (this machine only); any other address needs a token:
    ``token``, else the environment's ``BEEHAVE_HTTP_TOKEN``, else one is generated
    (:attr:`token`, logged as a warning and shown in :attr:`url`). A token set on loopback
    protects the commands (switch, stop). ``port`` 0 picks a free port (:attr:`port`).
    ``world`` / ``fleet``: what the web view draws (see
    :func:`~beehave.interfaces.http.create_app`). ``rate_hz``: WebSocket updates per robot
    and second at most. ``refresh_s``: the longest time between two updates of a robot
    that did not change (its blackboard's ages and staleness move on). ``remotes``: robots
    served by other processes, name → their server's address (with ``#token=…`` when it
    has one, as their :attr:`url` gives it) or a function returning it once known: a
    fleet process's page shows them in full (:mod:`beehave.interfaces.http.remote`).
    ``max_connections``: the most connections (HTTP and WebSocket) open at once; beyond,
    requests and upgrades get 503 (:class:`~beehave.interfaces.http.guard.Guard`).
    ``recording``: a :class:`~beehave.recording.timeline.RecordingTimeline` to serve
    read-only with the same page (``beehave view FILE.mcap``; ``planes`` then ``{}``).

    :meth:`start` returns once the server accepts connections; :meth:`stop` ends it and
    its thread (the robots keep running). Use it as a context manager.
    """

    def __init__(self, planes: ControlPlane | Mapping[str, ControlPlane], *,
                 host: str = DEFAULT_HOST, port: int = 0, token: str | None = None,
                 world: Provider = None, fleet: Provider = None, rate_hz: float = 20.0,
                 refresh_s: float = 1.0, hosts: Iterable[str] = (),
                 origins: Iterable[str] = (), max_body_bytes: int = MAX_BODY_BYTES,
                 header_timeout_s: float = HEADER_TIMEOUT_S,
                 max_connections: int = MAX_CONNECTIONS,
                 remotes: Mapping[str, Address] | None = None, recording: Any = None
                 ) -> None:
        if isinstance(planes, ControlPlane):
            planes = {planes.name: planes}
        if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
            raise ConfigError(f"HttpServer: port must be an int 0–65535, got {port!r}")
        if not (isinstance(rate_hz, (int, float)) and 0 < rate_hz <= 1000):
            raise ConfigError(f"HttpServer: rate_hz must be a number in (0, 1000], got "
                              f"{rate_hz!r}")
        if not (isinstance(refresh_s, (int, float)) and 0 < refresh_s <= 3600):
            raise ConfigError(f"HttpServer: refresh_s must be a number of seconds in "
                              f"(0, 3600], got {refresh_s!r}")
        if not (isinstance(max_body_bytes, int) and max_body_bytes > 0):
            raise ConfigError(f"HttpServer: max_body_bytes must be a positive int, got "
                              f"{max_body_bytes!r}")
        if not (isinstance(header_timeout_s, (int, float)) and 0 < header_timeout_s <= 3600):
            raise ConfigError(f"HttpServer: header_timeout_s must be a number of seconds in "
                              f"(0, 3600], got {header_timeout_s!r}")
        if not (isinstance(max_connections, int) and not isinstance(max_connections, bool)
                and max_connections > 0):
            raise ConfigError(f"HttpServer: max_connections must be a positive int, got "
                              f"{max_connections!r}")
        self.max_connections = max_connections
        self.header_timeout_s = float(header_timeout_s)
        self.max_body_bytes = max_body_bytes
        self.host = host
        self.loopback = is_loopback(host)
        #: Where the token came from: "given", "environment", "generated" or None.
        self.token_source: str | None = None
        from_env = os.environ.get(TOKEN_ENV) or None
        if token is not None:
            self.token_source = "given"
        elif from_env is not None:
            token, self.token_source = from_env, "environment"
        elif not self.loopback:
            token = secrets.token_urlsafe(24)
            self.token_source = "generated"
        if token is not None and (not token or any(c.isspace() for c in token)):
            raise ConfigError("HttpServer: a token must be a non-empty string without "
                              "whitespace")
        self.token = token
        self.planes = dict(planes)
        self._ready = threading.Event()
        self.app = create_app(self.planes, world=world, fleet=fleet, token=token,
                              loopback=self.loopback, rate_hz=rate_hz, refresh_s=refresh_s,
                              on_started=self._ready.set, hosts=[host, *hosts],
                              origins=origins, max_body_bytes=max_body_bytes,
                              remotes=remotes, connections=self._open_connections,
                              max_connections=max_connections, recording=recording)
        self._port = port
        self._sock: socket.socket | None = None
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @property
    def port(self) -> int:
        """The port it listens on (the free one picked for port 0, once started)."""
        return self._port

    @property
    def url(self) -> str:
        """The web view's address; with a token, it rides in the fragment (``#token=``),
        which the browser keeps to itself (never sent to a server or a log)."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        if ":" in host:
            host = f"[{host}]"
        base = f"http://{host}:{self._port}/"
        return f"{base}#token={self.token}" if self.token else base

    def _open_connections(self) -> int:
        """The connections uvicorn holds now (HTTP and WebSocket; in the server's loop)."""
        server = self._server
        return 0 if server is None else len(server.server_state.connections)

    @property
    def hub(self) -> Any:
        """The WebSocket fan-out (its ``stats()``: clients, updates, dropped snapshots)."""
        return self.app.state.hub

    def start(self, *, timeout_s: float = 30.0) -> None:
        """Bind, start the thread, return once requests are served. A port in use or an
        address this machine does not have raises :class:`ConfigError` at once."""
        import uvicorn

        if self._thread is not None:
            raise BeehaveError("HttpServer.start: already started; create a new server")
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        # IPPROTO_TCP named explicitly: asyncio sets TCP_NODELAY only on sockets whose
        # proto says TCP, and accepted sockets inherit it. Without it every response waited
        # for Nagle + the peer's delayed ACK: 40 ms per request.
        sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self._port))
        except OSError as exc:
            sock.close()
            raise ConfigError(f"HTTP interface: cannot listen on {self.host}:{self._port}: "
                              f"{exc.strerror or exc}") from exc
        sock.listen(128)
        self._sock = sock
        self._port = sock.getsockname()[1]
        # No permessage-deflate: every client's copy of every update would be compressed
        # separately, in the robot's process (0.3–0.5 ms per 11 KB update and client).
        base: type[asyncio.Protocol]
        try:  # what uvicorn's "auto" picks, with a timeout on a request's headers
            from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
            base = HttpToolsProtocol
        except ImportError:  # pragma: no cover - httptools is a uvicorn[standard] extra
            from uvicorn.protocols.http.h11_impl import H11Protocol
            base = H11Protocol
        config = uvicorn.Config(self.app, log_level="warning", lifespan="on",
                                http=header_timeout_protocol(base, self.header_timeout_s),
                                ws="websockets-sansio", ws_per_message_deflate=False,
                                # clients send nothing on the stream: a message beyond the
                                # body limit closes it (1009) instead of being buffered
                                ws_max_size=self.max_body_bytes,
                                timeout_graceful_shutdown=1, access_log=False)
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._main, name="beehave:http", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s) or self._error is not None:
            error = self._error
            self.stop()
            why = repr(error) if error is not None else f"not ready within {timeout_s:g} s"
            raise BeehaveError(f"HTTP interface on {self.host}:{self._port} did not start: "
                               f"{why}")
        if self.token_source == "generated":
            log.warning("HTTP interface on %s:%d: token %s (clients send 'Authorization: "
                        "Bearer TOKEN'; set %s to choose one)", self.host, self._port,
                        self.token, TOKEN_ENV)

    def _main(self) -> None:
        loop = asyncio.new_event_loop()
        try:
            # The socket is bound and listening already: a request that comes before
            # uvicorn serves it waits in the backlog. The app's startup sets _ready.
            loop.run_until_complete(self._server.serve(sockets=[self._sock]))
        except BaseException as exc:
            self._error = exc
            log.exception("HTTP interface stopped with an error")
        finally:
            self._ready.set()
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.run_until_complete(loop.shutdown_default_executor())  # to_thread's workers
            loop.close()
            # A forced exit (stop's timeout) or a failed start skips the lifespan's
            # shutdown: the hub's pump thread and robot subscriptions end here then.
            self.hub.close()

    def stop(self, *, timeout_s: float = 5.0) -> None:
        """Close every connection and end the thread (at most ``timeout_s``). Idempotent."""
        server, thread = self._server, self._thread
        if server is not None:
            server.should_exit = True
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
            if thread.is_alive():
                server.force_exit = True
                thread.join(1.0)
                if thread.is_alive():
                    log.warning("HTTP interface thread still running after %.1f s",
                                timeout_s + 1.0)
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    _stop_with = "stop"


def hold_hals(low: LowLevelBehaviorManager, names: Iterable[str], *,
              timeout_s: float = 5.0) -> Callable[[], None]:
    """Keep the HALs ``names`` loaded (one reference of their own, as a logic holds them)
    so that their blackboard entries stay current for a viewer; returns the function that
    gives the references back. A HAL that fails to load is reported (a warning naming it)
    and skipped: the view then lacks its entries, the robot runs on."""
    owner = object()  # the viewer's references, told apart from every logic's
    held: list[str] = []
    for name in names:
        try:
            low.call(low.hals.load(name, owner=owner), timeout_s=timeout_s)
        except (BeehaveError, TimeoutError) as exc:
            log.warning("web view: HAL %r not loaded (its entries stay off the view): %s",
                        name, exc)
        else:
            held.append(name)

    def release() -> None:
        for name in held:
            try:
                low.call(low.hals.release(name, owner=owner), timeout_s=timeout_s)
            except (BeehaveError, TimeoutError) as exc:
                log.warning("web view: releasing HAL %r failed: %s", name, exc)
        held.clear()

    return release


def serve(planes: ControlPlane | Mapping[str, ControlPlane], *, host: str = DEFAULT_HOST,
          port: int = 0, token: str | None = None, world: Provider = None,
          fleet: Provider = None, rate_hz: float = 20.0, refresh_s: float = 1.0,
          **options: Any) -> HttpServer:
    """Start an :class:`HttpServer` for ``planes`` and return it (call ``stop()`` on it).

    A fleet process serves all its robots with one server::

        server = serve({name: robot.plane for name, robot in robots.items()},
                       world=world.model_dump(mode="json"), fleet=fleet_view)

    ``options``: the rest of :class:`HttpServer`'s settings (``hosts``, ``origins``,
    ``max_body_bytes``, ``header_timeout_s``, ``max_connections``, ``remotes``).
    """
    server = HttpServer(planes, host=host, port=port, token=token, world=world, fleet=fleet,
                        rate_hz=rate_hz, refresh_s=refresh_s, **options)
    server.start()
    return server
