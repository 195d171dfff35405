"""What the server accepts from where, checked before the application sees a request.

:class:`Guard` is an ASGI middleware in front of the FastAPI application:

- **Host** (DNS rebinding): while anything is served without a token (every server on
  loopback), a request must name the server by an address of this machine's loopback
  (``localhost``, ``127.0.0.1``, ``[::1]``), the bound address or a configured name;
  any other ``Host`` is refused with 403 before it reaches an endpoint.
- **Origin** (cross-site requests): a command (any method but GET/HEAD/OPTIONS) and a
  WebSocket upgrade are refused with 403 when the browser says they come from another
  site: an ``Origin`` other than the server's own (or ``null``), a ``Sec-Fetch-Site``
  other than ``same-origin``/``none``. A command must moreover carry
  ``Content-Type: application/json`` (415 otherwise): what no HTML form and no
  ``no-cors`` fetch can send without a CORS preflight, which this server never grants.
- **Body size**: a request body above ``max_body_bytes`` is refused with 413: at once
  when its ``Content-Length`` says so, else as soon as that many bytes of a chunked body
  have come (the rest is never read).
- **Connections**: while more than ``max_connections`` connections are open (HTTP ones,
  kept-alive or still sending their headers, and WebSocket streams, this one included),
  a request and a WebSocket upgrade are refused with 503 (``Retry-After``) and their
  connection closed: the server's memory and the robot's CPU stay bounded however many
  clients come; those already served are not disturbed.

:func:`header_timeout_protocol` closes connections that do not complete a request's
headers within ``header_timeout_s`` (half-open connections, slowloris).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from typing import Any

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

#: The largest request body accepted (bytes): a switch request with its parameters.
MAX_BODY_BYTES = 64 * 1024
#: The longest a connection may take to send a request's headers (seconds).
HEADER_TIMEOUT_S = 10.0
#: The most connections (HTTP and WebSocket) a server holds open at once.
MAX_CONNECTIONS = 100
#: Names of this machine every loopback server answers to.
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
_SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
_SAME_SITE = frozenset({"same-origin", "none"})

log = logging.getLogger(__name__)


def host_name(host: str) -> str:
    """The name in a ``Host`` header value or a URL's netloc, without the port, lowercase
    (``[::1]:8080`` → ``::1``)."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1:].partition("]")[0]
    name, sep, port = host.rpartition(":")
    return name if sep and port.isdigit() and ":" not in name else host


class Guard:
    """The checks of the module docstring in front of ``app``.

    ``check_host``: whether the Host rule applies (the server answers something without a
    token); ``hosts``: the names accepted besides the loopback names; ``origins``: origins
    (``scheme://host:port``) accepted besides the server's own; ``connections``: how many
    connections the server holds open now (None: not counted), ``max_connections`` the
    most it serves."""

    def __init__(self, app: ASGIApp, *, check_host: bool, hosts: Iterable[str] = (),
                 origins: Iterable[str] = (), max_body_bytes: int = MAX_BODY_BYTES,
                 connections: Callable[[], int] | None = None,
                 max_connections: int = MAX_CONNECTIONS) -> None:
        self.app = app
        self.connections = connections
        self.max_connections = max_connections
        self._warned = -float("inf")
        self.check_host = check_host
        self.hosts = LOOPBACK_NAMES | {host_name(h) for h in hosts if h}
        self.origins = frozenset(o.rstrip("/").lower() for o in origins)
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        if self.connections is not None:
            open_now = self.connections()  # this one included
            if open_now > self.max_connections:
                now = time.monotonic()
                if now - self._warned > 10.0:  # a flood is reported, not logged per request
                    self._warned = now
                    log.warning("HTTP interface: %d connections open, above its limit of %d:"
                                " refusing new requests with 503", open_now,
                                self.max_connections)
                await _refuse(scope, send, 503, "TooManyConnections",
                              f"this server holds {open_now} connections, more than its "
                              f"limit of {self.max_connections} (max_connections): try again "
                              f"later", retry_after_s=1)
                return
        headers = _headers(scope)
        refusal = self._refusal(scope, headers)
        if refusal is not None:
            await _refuse(scope, send, *refusal)
            return
        if kind == "http":
            length = headers.get("content-length", "")
            if length.isdigit() and int(length) > self.max_body_bytes:
                await _refuse(scope, send, *self._too_large(int(length)))
                return
            more, read = True, 0
            chunks: list[Message] = []
            while more:  # read the body here, bounded; the app gets it replayed
                message = await receive()
                if message["type"] != "http.request":
                    chunks.append(message)
                    break
                read += len(message.get("body", b""))
                if read > self.max_body_bytes:
                    await _refuse(scope, send, *self._too_large(None))
                    return
                chunks.append(message)
                more = message.get("more_body", False)
            replay = iter(chunks)

            async def replayed() -> Message:
                for message in replay:
                    return message
                return await receive()

            await self.app(scope, replayed, send)
            return
        await self.app(scope, receive, send)

    def _too_large(self, length: int | None) -> tuple[int, str, str]:
        size = "" if length is None else f" ({length} bytes)"
        return (413, "RequestTooLarge", f"the request body{size} is larger than the "
                f"{self.max_body_bytes} bytes this server accepts")

    def _refusal(self, scope: Scope, headers: dict[str, str]) -> tuple[int, str, str] | None:
        host = headers.get("host", "")
        if self.check_host and host_name(host) not in self.hosts:
            return (403, "ForbiddenHost",
                    f"Host {host[:100]!r} does not name this server: without a token it "
                    f"answers only to {', '.join(sorted(self.hosts))} (a foreign name is "
                    f"how DNS rebinding reaches a loopback server)")
        websocket = scope["type"] == "websocket"
        if not websocket and scope.get("method", "GET") in _SAFE_METHODS:
            return None
        what = "a WebSocket" if websocket else "a command"
        origin = headers.get("origin")
        if origin is not None:
            # The page's own origin names the host the request was sent to (its scheme
            # may differ behind a TLS proxy). A rebound name matches here too: that is
            # what the Host rule above is for.
            netloc = origin.partition("://")[2].rstrip("/").lower()
            if (not netloc or netloc != host.strip().lower()) \
                    and origin.rstrip("/").lower() not in self.origins:
                return (403, "CrossOrigin",
                        f"{what} from origin {origin[:100]!r} is refused: only this "
                        f"server's own page (an origin naming {host[:100]!r}) and API "
                        f"clients (which send no Origin) may send one")
        site = headers.get("sec-fetch-site")
        if site is not None and site not in _SAME_SITE and (
                origin is None or origin.rstrip("/").lower() not in self.origins):
            return (403, "CrossOrigin", f"{what} from another site (Sec-Fetch-Site: "
                                        f"{site[:40]}) is refused")
        if not websocket:
            media = headers.get("content-type", "").partition(";")[0].strip().lower()
            if media != "application/json":
                return (415, "UnsupportedMediaType",
                        f"a command must be sent with 'Content-Type: application/json' "
                        f"(a JSON body, '{{}}' when it has no fields), got "
                        f"{media[:60] or 'none'!r}")
        return None


def _headers(scope: Scope) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1")
            for k, v in scope.get("headers", ())}


async def _refuse(scope: Scope, send: Send, status: int, error: str, detail: str, *,
                  retry_after_s: int | None = None) -> None:
    body = json.dumps({"error": error, "detail": detail}).encode()
    headers = [(b"content-type", b"application/json"),
               (b"content-length", str(len(body)).encode()), (b"connection", b"close")]
    if retry_after_s is not None:
        headers.append((b"retry-after", str(retry_after_s).encode()))
    start = {"status": status, "headers": headers}
    if scope["type"] == "websocket":  # the denial response the browser sees
        if "websocket.http.response" in scope.get("extensions", {}):
            await send({"type": "websocket.http.response.start", **start})
            await send({"type": "websocket.http.response.body", "body": body})
        else:
            await send({"type": "websocket.close", "code": 4000 + status,
                        "reason": detail[:120]})
        return
    await send({"type": "http.response.start", **start})
    await send({"type": "http.response.body", "body": body})


def header_timeout_protocol(base: type[asyncio.Protocol], timeout_s: float
                            ) -> type[asyncio.Protocol]:
    """A subclass of uvicorn's HTTP protocol ``base`` that closes a connection whose next
    request's headers have not all come ``timeout_s`` after it was opened or after its
    previous response."""

    class HeaderTimeout(base):  # type: ignore[valid-type, misc]
        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            self._arm_header_timeout()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            self._arm_header_timeout()

        def _arm_header_timeout(self) -> None:
            cycle = self.cycle
            self.loop.call_later(timeout_s, self._header_timeout, cycle)

        def _header_timeout(self, cycle: Any) -> None:
            transport = self.transport
            if (self.cycle is cycle and not transport.is_closing()
                    and transport.get_protocol() is self):  # not upgraded to a WebSocket
                transport.close()

    HeaderTimeout.__name__ = HeaderTimeout.__qualname__ = f"HeaderTimeout{base.__name__}"
    return HeaderTimeout
