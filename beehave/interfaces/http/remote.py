"""Robots served by another process: a fleet server forwards their API and stream.

A fleet process whose robots run in processes of their own (``beehave fleet``) has no
:class:`~beehave.interfaces.ControlPlane` of theirs. Each robot serves its own API
(``beehave run ROBOT.yaml --http …``); the fleet's server is given their addresses
(``remotes={"atv1": "http://127.0.0.1:8101/"}``, or a function returning the address once
it is known: a robot that binds a free port tells it when it has started) and forwards,
as an API client of each:

- ``GET`` and ``POST /api/robots/{robot}/…`` to that robot's server, answered with the
  robot's own status and body (its errors, validation and limits are the robot's);
- ``WS /api/ws?robots={robot}``: one upstream stream per browser stream, its messages
  relayed as they come (the robot's own coalescing and mailbox apply: a slow browser
  makes this relay read slower, and the robot drops snapshots for it).

So the page served by the fleet shows any robot of the fleet in full, and Switch and Stop
act on it. Whatever a browser sends passes this server's own checks first (Host, Origin,
content type, body size, token); the robot then sees a plain API client (no ``Origin``)
that carries the robot's token when its address has one (``http://…/#token=TOKEN``, as
:attr:`~beehave.interfaces.http.HttpServer.url` gives it).
"""

from __future__ import annotations

import re
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeAlias
from urllib.parse import quote, urlsplit

from beehave.errors import ConfigError

#: Names a remote robot may have: they become literal path segments of the routes.
NAME = re.compile(r"[A-Za-z0-9_.~-]+")
#: The largest message relayed from a robot's stream (a new client's backlog of events
#: is the largest: 500 bounded events).
MAX_MESSAGE_BYTES = 16 * 1024 * 1024

#: A robot server's address, or a function returning it (None: not known yet).
Address: TypeAlias = str | Callable[[], str | None]


@dataclass(frozen=True)
class Remote:
    """One robot served by another process: its name there, its server, its token."""

    name: str
    #: ``http://host:port`` (no path, no token).
    base: str
    token: str | None = None

    @classmethod
    def parse(cls, name: str, url: str) -> Remote:
        """``url``: the robot server's address, optionally with its token in the fragment
        (``http://127.0.0.1:8101/#token=…``). :class:`ConfigError` names what is wrong."""
        check_name(name)
        if not isinstance(url, str):
            raise ConfigError(f"remote robot {name!r}: its address must be a URL string, "
                              f"got {url!r}")
        parts = urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.netloc:
            raise ConfigError(f"remote robot {name!r}: {url!r} is not an http:// or https:// "
                              f"address of a beehave server (e.g. http://127.0.0.1:8101/)")
        if parts.path.strip("/") or parts.query:
            raise ConfigError(f"remote robot {name!r}: give the server's address without a "
                              f"path or query, got {url!r}")
        match = re.search(r"(?:^|&)token=([^&]+)", parts.fragment)
        return cls(name, f"{parts.scheme}://{parts.netloc}", match.group(1) if match else None)

    @property
    def stream_url(self) -> str:
        scheme = "wss" if self.base.startswith("https:") else "ws"
        return f"{scheme}{self.base[self.base.index(':'):]}/api/ws?robots={quote(self.name)}"

    def headers(self) -> dict[str, str]:
        headers = {"accept": "application/json"}
        if self.token:
            headers["authorization"] = f"Bearer {self.token}"
        return headers


def check_name(name: object) -> None:
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise ConfigError(f"remote robot name {name!r}: use letters, digits and "
                          f"'_.~-' (the name its own server serves it under)")


class RemoteError(Exception):
    """A robot's server could not answer (502): unknown yet, unreachable, or it refused
    this server."""

    def __init__(self, name: str, base: str | None, why: str) -> None:
        where = f" (served at {base})" if base else ""
        super().__init__(f"robot {name!r}{where}: {why}")
        self.name = name


class Remotes:
    """The robots of other processes one server forwards to (see the module docstring).

    :meth:`start` and :meth:`stop` run in the server's loop (its lifespan)."""

    def __init__(self, urls: Mapping[str, Address], *, timeout_s: float = 10.0) -> None:
        for name, url in urls.items():
            check_name(name)
            if not callable(url):
                Remote.parse(name, url)  # a bad address is refused at once
        self.robots = dict(urls)
        self.timeout_s = timeout_s
        self._client: Any = None
        self._parsed: dict[tuple[str, str], Remote] = {}

    def find(self, name: str) -> Remote | None:
        """Robot ``name``'s server (None: its address is not known yet)."""
        given = self.robots[name]
        url = given() if callable(given) else given
        if url is None:
            return None
        remote = self._parsed.get((name, url))
        if remote is None:
            remote = self._parsed[name, url] = Remote.parse(name, url)
        return remote

    def _get(self, name: str) -> Remote:
        try:
            remote = self.find(name)
        except ConfigError as exc:
            raise RemoteError(name, None, str(exc)) from exc
        if remote is None:
            raise RemoteError(name, None, "its server has not told its address yet (still "
                                          "starting?)")
        return remote

    def __contains__(self, name: object) -> bool:
        return name in self.robots

    def __bool__(self) -> bool:
        return bool(self.robots)

    async def start(self) -> None:
        if self.robots:
            import httpx

            # trust_env=False: a proxy from the environment must not see the robots' tokens
            self._client = httpx.AsyncClient(timeout=self.timeout_s, trust_env=False)

    async def stop(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            await client.aclose()

    async def forward(self, name: str, method: str, path: str, query: bytes,
                      body: bytes) -> tuple[int, bytes, str]:
        """Ask robot ``name``'s server ``method path?query`` (the same path: it serves the
        robot under the same name); its (status, body, content type)."""
        import httpx

        remote = self._get(name)
        headers = remote.headers()
        if method != "GET":
            headers["content-type"] = "application/json"
        url = remote.base + path + ("?" + query.decode("latin-1") if query else "")
        if self._client is None:
            raise RemoteError(name, remote.base, "the server is not running")
        try:
            response = await self._client.request(method, url, headers=headers,
                                                  content=body if method != "GET" else None)
        except httpx.HTTPError as exc:
            raise RemoteError(name, remote.base, f"not reachable ({type(exc).__name__}: "
                                      f"{str(exc)[:200] or 'no answer'})") from exc
        if response.status_code in (401, 403):
            raise RemoteError(name, remote.base,
                              f"refused this fleet server ({response.status_code}: "
                              f"{response.text[:300]}); give its address with its token, "
                              f"http://…/#token=TOKEN")
        kind = response.headers.get("content-type", "application/json")
        return response.status_code, response.content, kind

    async def relay(self, name: str, send: Callable[[str], Awaitable[None]]) -> None:
        """Open robot ``name``'s stream and pass each of its messages to ``send`` until
        either side ends it; :class:`RemoteError` when it cannot be opened."""
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

        remote = self._get(name)
        protocols: list[Any] = ["beehave"]
        if remote.token:
            protocols.append(f"bearer.{remote.token}")
        try:
            upstream = await connect(remote.stream_url, subprotocols=protocols,
                                     compression=None, max_size=MAX_MESSAGE_BYTES,
                                     open_timeout=self.timeout_s, proxy=None)
        except (OSError, TimeoutError, InvalidHandshake, InvalidURI) as exc:
            raise RemoteError(name, remote.base, f"its stream did not open ({type(exc).__name__}: "
                                      f"{str(exc)[:200]})") from exc
        async with upstream:
            try:
                async for message in upstream:
                    if isinstance(message, str):
                        await send(message)
            except ConnectionClosed as exc:
                raise RemoteError(name, remote.base, f"its stream closed ({exc})") from exc


__all__ = ["Address", "Remote", "RemoteError", "Remotes"]
