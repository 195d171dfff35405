"""The WebSocket fan-out: one coalescing pump per server, one bounded mailbox per client.

The pump sleeps until a robot changes (an event, a blackboard write: the first change
after a turn wakes it) or ``refresh_s`` passes (ages and staleness move on), and takes at
most ``rate_hz`` turns a second: a change to a quiet robot goes out at once, a burst is
coalesced into one update per ``1/rate_hz``. In a turn, for every robot that changed it
builds the update once (snapshot + blackboard), serialises it once, and *offers* it to
each client watching that robot. A client's mailbox holds one
update per robot: an offer that finds the previous one still unsent replaces it and counts
it as dropped. Nothing the robot does waits for a client: the managers only set a flag,
the pump never awaits a socket, and a client whose socket is full simply receives fewer,
newer updates. Events are never dropped with a snapshot: they accumulate in the mailbox
(bounded by ``events_kept``; past that the oldest go and are counted).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from pydantic_core import to_json

from beehave.interfaces.core import ControlPlane

log = logging.getLogger(__name__)


@dataclass
class _Pending:
    update: bytes | None = None
    events: list[dict[str, Any]] = field(default_factory=list)


class Client:
    """One WebSocket client: which robots it watches, what waits to be sent, what was
    dropped. The pump (in the server's loop) offers; the client's sender task sends."""

    def __init__(self, robots: list[str], *, events_kept: int) -> None:
        self.robots = robots
        self.sent = 0
        #: Snapshots replaced before they could be sent (the client was slow).
        self.dropped = 0
        #: Events dropped because more than ``events_kept`` waited (a very slow client).
        self.events_dropped = 0
        self.connected_at = time.time()
        self._events_kept = events_kept
        self._pending: dict[str, _Pending] = {}
        self._wake = asyncio.Event()

    def offer(self, robot: str, update: bytes | None, events: list[dict[str, Any]]) -> None:
        """Queue ``update`` for ``robot`` in place of an unsent one (in the server loop)."""
        pending = self._pending.setdefault(robot, _Pending())
        if update is not None:
            if pending.update is not None:
                self.dropped += 1
            pending.update = update
        if events:
            pending.events.extend(events)
            excess = len(pending.events) - self._events_kept
            if excess > 0:
                del pending.events[:excess]
                self.events_dropped += excess
        self._wake.set()

    async def next_messages(self) -> list[bytes]:
        """Wait until something is queued; return the messages to send now."""
        await self._wake.wait()
        self._wake.clear()
        pending, self._pending = self._pending, {}
        out = []
        for robot, item in pending.items():
            parts = [b'{"type":"update","robot":', to_json(robot),
                     b',"dropped":', str(self.dropped).encode(),
                     b',"events_dropped":', str(self.events_dropped).encode(),
                     b',"events":', to_json(item.events)]
            if item.update is not None:
                parts += [b",", item.update[1:-1]]  # the update's own fields
            parts.append(b"}")
            out.append(b"".join(parts))
        return out

    def stats(self) -> dict[str, Any]:
        return {"robots": self.robots, "sent": self.sent, "dropped": self.dropped,
                "events_dropped": self.events_dropped, "connected_at": self.connected_at}


class Hub:
    """The pump and the clients of one server (see the module docstring)."""

    def __init__(self, planes: Mapping[str, ControlPlane], *, rate_hz: float = 20.0,
                 refresh_s: float = 1.0, events_kept: int = 500) -> None:
        self.planes = dict(planes)
        self.period_s = 1.0 / rate_hz
        self.refresh_s = refresh_s
        self.events_kept = events_kept
        self.clients: set[Client] = set()
        #: How many updates the pump built and how long that took in total (serialising
        #: included): the robot-side cost of the web view.
        self.updates_built = 0
        self.build_s = 0.0
        self.dropped_total = 0
        self._dirty = {name: threading.Event() for name in self.planes}
        self._last_seq = dict.fromkeys(self.planes, 0)
        self._last_built = dict.fromkeys(self.planes, 0.0)
        self._seq = 0
        self._unsubscribe: list[Callable[[], None]] = []
        self._task: asyncio.Task[None] | None = None
        self._wake: asyncio.Event | None = None

    def start(self) -> None:
        """Subscribe to the robots and start the pump (in the server's running loop)."""
        loop = asyncio.get_running_loop()
        self._wake = wake = asyncio.Event()
        for name, plane in self.planes.items():
            flag = self._dirty[name]

            def mark(_: object, flag: threading.Event = flag) -> None:
                # Called in the robot's threads: set a flag and, on the first change since
                # the last turn only, wake the pump (one non-blocking write to the loop's
                # self-pipe): the rest of a burst costs the robot a flag test each.
                if flag.is_set():
                    return
                flag.set()
                try:
                    loop.call_soon_threadsafe(wake.set)
                except RuntimeError:  # the server's loop is closed: nobody to tell
                    pass

            self._unsubscribe.append(plane.subscribe(mark))
            sub = plane.board.subscribe("**", mark)
            self._unsubscribe.append(sub.close)
        self._task = loop.create_task(self._pump(), name="beehave:http-pump")

    async def stop(self) -> None:
        for fn in self._unsubscribe:
            with contextlib.suppress(Exception):
                fn()
        self._unsubscribe.clear()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    def add(self, robots: list[str]) -> Client:
        """A new client (in the server loop): it gets the events kept so far, then the
        current picture at the pump's next turn."""
        client = Client(robots, events_kept=self.events_kept)
        self.clients.add(client)
        for name in robots:
            upto = self._last_seq[name]
            kept = self.planes[name].events(limit=self.events_kept)
            client.offer(name, None, [e for e in kept if e["seq"] <= upto])
            self._dirty[name].set()
        if self._wake is not None:
            self._wake.set()
        return client

    def remove(self, client: Client) -> None:
        self.clients.discard(client)
        self.dropped_total += client.dropped

    def build(self, name: str) -> bytes:
        """One robot's update, serialised once for every client (any thread)."""
        started = time.perf_counter()
        plane = self.planes[name]
        self._seq += 1
        data = {"seq": self._seq, "stamp": time.time(), "snapshot": plane.snapshot(),
                "blackboard": plane.blackboard()}
        out = to_json(data)
        self.build_s += time.perf_counter() - started
        self.updates_built += 1
        return out

    async def _pump(self) -> None:
        assert self._wake is not None
        last_turn = -math.inf
        while True:
            if not self.clients:
                await self._wake.wait()  # nobody watches: build nothing
            else:
                # A change wakes the pump at once (the leading edge: a quiet robot's change
                # is on its way within a build); the refresh moves ages on.
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), self.refresh_s)
            self._wake.clear()
            # The coalescing: at most one turn every period_s; whatever changes meanwhile
            # waits for it, and only the latest state is sent.
            delay_s = last_turn + self.period_s - time.monotonic()
            if delay_s > 0:
                await asyncio.sleep(delay_s)
            last_turn = time.monotonic()
            try:
                await self._turn()
            except Exception:  # a robot's snapshot failed: report, keep serving
                log.exception("web view: building an update failed")

    async def _turn(self) -> None:
        if not self.clients:
            return
        now = time.monotonic()
        for name, plane in self.planes.items():
            watchers = [c for c in self.clients if name in c.robots]
            if not watchers:
                continue
            due = now - self._last_built[name] >= self.refresh_s
            if not (self._dirty[name].is_set() or due):
                continue
            self._dirty[name].clear()
            self._last_built[name] = now
            # Built off the loop: a snapshot reads the managers (the low level's call
            # crosses into its loop) and must not stall the other clients' sends.
            update = await asyncio.to_thread(self.build, name)
            events = plane.events(after_seq=self._last_seq[name], limit=self.events_kept)
            if events:
                self._last_seq[name] = events[-1]["seq"]
            for client in watchers:
                if client in self.clients:
                    client.offer(name, update, events)

    def stats(self) -> dict[str, Any]:
        clients = [c.stats() for c in self.clients]
        return {"clients": clients, "updates_built": self.updates_built,
                "build_ms_mean": round(1000 * self.build_s / self.updates_built, 3)
                if self.updates_built else None,
                "dropped_snapshots": self.dropped_total + sum(c["dropped"] for c in clients),
                "rate_hz": round(1.0 / self.period_s, 3)}
