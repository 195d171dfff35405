"""The WebSocket fan-out: one coalescing pump per server, one bounded mailbox per client.

The pump sleeps until a robot changes (an event, a blackboard write: the first change
after a turn wakes it) or ``refresh_s`` passes (ages and staleness move on), and takes at
most ``rate_hz`` turns a second: a change to a quiet robot goes out at once, a burst is
coalesced into one update per ``1/rate_hz`` (while the pump sleeps out a period, changes
only set a flag: no wakeup at all). In a turn, for every robot that changed it builds the
update once (snapshot + blackboard; the blackboard's entries re-encoded only when they
changed; the snapshot and the event log read again only after one of the robot's events,
the snapshot also when it is ``TREE_MAX_AGE_S`` old), serialises the whole message once,
and *offers* that one string to each client watching that robot. A client's mailbox
holds one update per robot: an offer that finds the previous one still unsent replaces
it and counts it as dropped. A client that keeps up is sent the shared string as it
is — no per-client work; only a client that dropped something gets a message of its own
(the events of the replaced updates, its counts).
Nothing the robot does waits for a client: the managers only set a flag, the pump never
awaits a socket, and a client whose socket is full simply receives fewer, newer updates.
Events are never dropped with a snapshot: they accumulate in the mailbox (bounded by
``events_kept``; past that the oldest go and are counted).
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

#: The oldest a robot's running tree (its snapshot) may be in an update when none of its
#: events came since it was read: what moves without an event — durations, a decision
#: engine's state or a tree's tick statuses — is shown at least this often. An event
#: (a start, an end, a switch …) has it read again at the next turn.
TREE_MAX_AGE_S = 0.25


@dataclass(frozen=True)
class Update:
    """One robot's update of one turn, serialised once for every client."""

    robot: str
    #: ``"seq":…,"stamp":…,"snapshot":…,"blackboard":…`` (the fields, without braces).
    body: bytes
    #: The events that came with this turn.
    events: list[dict[str, Any]]
    #: The whole message, as every client that keeps up receives it.
    text: str


def _message(robot: str, body: bytes, events: list[dict[str, Any]],
             counts: tuple[int, int] | None = None) -> str:
    parts = [b'{"type":"update","robot":', to_json(robot)]
    if counts is not None:
        parts += [b',"dropped":', str(counts[0]).encode(),
                  b',"events_dropped":', str(counts[1]).encode()]
    parts += [b',"events":', to_json(events)]
    if body:
        parts += [b",", body]
    parts.append(b"}")
    return b"".join(parts).decode()


@dataclass
class _Pending:
    update: Update | None = None
    #: Whether the update's own events go out with it (not when a new client has them
    #: in its backlog already: then those it lacks are in ``events``).
    own: bool = True
    #: Events the update does not carry: those of replaced updates, a new client's backlog.
    events: list[dict[str, Any]] = field(default_factory=list)


class Client:
    """One WebSocket client: which robots it watches, what waits to be sent, what was
    dropped. The hub offers (in the server's loop); the client's sender task sends."""

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
        self._told: tuple[int, int] | None = None  # the counts last sent to the client
        #: robot → the last event seq of the backlog it was given: not to be sent twice.
        self._since: dict[str, int] = {}
        self._wake = asyncio.Event()

    def offer(self, update: Update) -> None:
        """Queue ``update`` in place of an unsent one of its robot (in the server loop)."""
        robot, own, extra = update.robot, True, None
        since = self._since.get(robot)
        if since is not None and update.events:
            if update.events[0]["seq"] > since:
                del self._since[robot]  # past the backlog: events go as they come
            else:
                own, extra = False, [e for e in update.events if e["seq"] > since]
        pending = self._pending.get(robot)
        if pending is None:
            pending = self._pending[robot] = _Pending()
        elif pending.update is not None:
            self.dropped += 1
            if pending.own:
                self._keep(pending, pending.update.events)
        pending.update, pending.own = update, own
        if extra:
            self._keep(pending, extra)
        self._wake.set()

    def offer_events(self, robot: str, events: list[dict[str, Any]], *, upto: int) -> None:
        """Queue a new client's backlog: the events up to seq ``upto``; later updates
        bring the events after it."""
        self._since[robot] = upto
        if events:
            self._keep(self._pending.setdefault(robot, _Pending()), events)
            self._wake.set()

    def _keep(self, pending: _Pending, events: list[dict[str, Any]]) -> None:
        pending.events.extend(events)
        excess = len(pending.events) - self._events_kept
        if excess > 0:
            del pending.events[:excess]
            self.events_dropped += excess

    async def next_messages(self) -> list[str]:
        """Wait until something is queued; return the messages to send now."""
        await self._wake.wait()
        self._wake.clear()
        pending, self._pending = self._pending, {}
        out = []
        for robot, item in pending.items():
            update = item.update
            counts = (self.dropped, self.events_dropped)
            if update is not None and item.own and not item.events and counts == self._told:
                out.append(update.text)  # the shared message: nothing of this client's own
                continue
            events = item.events
            if update is not None and item.own:
                self._keep(item, update.events)
                counts = (self.dropped, self.events_dropped)
            self._told = counts
            out.append(_message(robot, b"" if update is None else update.body, events,
                                counts))
        return out

    def stats(self) -> dict[str, Any]:
        return {"robots": self.robots, "sent": self.sent, "dropped": self.dropped,
                "events_dropped": self.events_dropped, "connected_at": self.connected_at}


class _BoardCache:
    """One robot's blackboard as JSON, each entry re-encoded only when it changed.

    Every build reads each entry (:meth:`~beehave.Blackboard.entry`: the same object while
    the entry is unchanged and fresh) and re-encodes only those that are new objects: a
    write, a refresh of the same value, staleness by age. Which keys exist comes from the
    hub's subscription (a new key) and, every ``resync_s``, from a full snapshot (keys
    declared but never written)."""

    def __init__(self, board: Any, *, resync_s: float) -> None:
        self.board = board
        self.resync_s = resync_s
        self._lock = threading.Lock()
        self._new: set[str] = set()
        #: key → (the entry encoded, ``"key":{"value":…,"stamp":…,"stale":…,"writer":…,
        #: "age_s":``, and when it was written; None: declared, never written)
        self._entries: dict[str, tuple[Any, bytes, float | None]] = {}
        self._order: list[str] = []
        self._synced = -math.inf

    def written(self, key: str) -> None:
        """A write to ``key`` (in the writer's thread): note it when the key is new."""
        if key not in self._entries:
            with self._lock:
                self._new.add(key)

    @staticmethod
    def _fragment(key: str, entry: dict[str, Any]) -> bytes:
        fields = {k: v for k, v in entry.items() if k != "age_s"}
        return b"".join([to_json(key), b":", to_json(fields)[:-1], b',"age_s":'])

    def encode(self) -> bytes:
        """The board as ``{key: {value, stamp, stale, writer, age_s}}`` (what
        :meth:`~beehave.Blackboard.snapshot` gives), serialised."""
        now = time.monotonic()
        entries, board = self._entries, self.board
        with self._lock:
            new, self._new = self._new, set()
        if now - self._synced >= self.resync_s:
            self._synced = now
            entries.clear()
            for key, value in board.snapshot().items():
                entries[key] = (None, self._fragment(key, value), None)
            self._order = sorted(entries.keys() | new)
        elif new:
            self._order = sorted(entries.keys() | new)
        parts = []
        for key in self._order:
            change = board.entry(key)
            cached = entries.get(key)
            if change is None:
                if cached is None:
                    continue
                fragment, written = cached[1], cached[2]
                if cached[0] is not None:  # it had a value: gone now (cannot happen today)
                    del entries[key]
                    continue
            elif cached is not None and cached[0] is change:
                fragment, written = cached[1], cached[2]
            else:
                fragment, written = self._fragment(key, change.as_dict()), change.monotonic
                entries[key] = (change, fragment, written)
            age = b"null" if written is None else b"%.6f" % max(0.0, now - written)
            parts.append(fragment + age + b"}")
        return b"{" + b",".join(parts) + b"}"


class Hub:
    """The pump and the clients of one server (see the module docstring).

    The pump is a thread of its own: it sleeps out each period on its own timer, builds
    the updates (a snapshot reads the managers, and the low level's part crosses into its
    loop: the server's loop never waits for a robot), and hands them to the server's loop
    in one call, which offers them to the clients."""

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
        self._boards = {name: _BoardCache(plane.board, resync_s=refresh_s)
                        for name, plane in self.planes.items()}
        self._dirty = {name: threading.Event() for name in self.planes}
        #: Set by each of the robot's events (in its threads): the pump reads the event log
        #: and the running tree again only then (or when the tree is TREE_MAX_AGE_S old):
        #: a robot whose blackboard alone changes costs a turn the blackboard's changes.
        self._happened = {name: threading.Event() for name in self.planes}
        self._tree_happened = {name: threading.Event() for name in self.planes}
        #: robot → (when, its snapshot serialised) for the turns between two reads.
        self._trees: dict[str, tuple[float, bytes]] = {}
        self._last_seq = dict.fromkeys(self.planes, 0)
        self._last_built = dict.fromkeys(self.planes, -math.inf)
        #: The robots some client watches (replaced, never changed in place: the pump
        #: thread reads it).
        self._watched: frozenset[str] = frozenset()
        self._seq = 0
        self._build_lock = threading.Lock()
        #: Whether a change must wake the pump (it waits) or only set its robot's flag
        #: (the pump sleeps out a period and looks at the flags anyway).
        self._armed = True
        self._kick = threading.Event()
        self._stopping = False
        self._unsubscribe: list[Callable[[], None]] = []
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        #: "server" (the server's loop) and "pump" → their OS thread ids, for ``stats()``.
        self._threads: dict[str, int] = {}

    def start(self) -> None:
        """Subscribe to the robots and start the pump (in the server's running loop)."""
        self._loop = asyncio.get_running_loop()
        self._threads["server"] = threading.get_native_id()
        kick = self._kick
        for name, plane in self.planes.items():
            flag, board = self._dirty[name], self._boards[name]

            def mark(_: object, flag: threading.Event = flag) -> None:
                # Called in the robot's threads: set a flag and, on the first change since
                # the last turn only and only when the pump waits for one, wake it: the
                # rest costs the robot a flag test each.
                if flag.is_set():
                    return
                flag.set()
                if self._armed:
                    kick.set()

            def written(change: Any, board: _BoardCache = board,
                        mark: Callable[[object], None] = mark) -> None:
                board.written(change.key)
                mark(change)

            def happened(event: object, mark: Callable[[object], None] = mark,
                         flags: tuple[threading.Event, ...] = (
                             self._happened[name], self._tree_happened[name])) -> None:
                for flag in flags:
                    flag.set()
                mark(event)

            self._unsubscribe.append(plane.subscribe(happened))
            sub = plane.board.subscribe("**", written)
            self._unsubscribe.append(sub.close)
        self._thread = threading.Thread(target=self._pump, name="beehave:http-pump",
                                        daemon=True)
        self._thread.start()

    async def stop(self) -> None:
        """Unsubscribe and end the pump (in the server's loop)."""
        thread = self._release()
        if thread is not None:
            await asyncio.to_thread(thread.join, 5.0)  # at most a build and a period
            self._check_ended(thread)

    def close(self) -> None:
        """:meth:`stop` for any thread, once the server's loop has gone (a forced exit
        skips the lifespan's shutdown). Idempotent: nothing left to do after a stop."""
        thread = self._release()
        if thread is not None and thread is not threading.current_thread():
            thread.join(5.0)
            self._check_ended(thread)

    def _release(self) -> threading.Thread | None:
        """Unsubscribe and tell the pump to end; the thread to join (None: none runs)."""
        for fn in self._unsubscribe:
            with contextlib.suppress(Exception):
                fn()
        self._unsubscribe.clear()
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stopping = True
            self._kick.set()
        return thread

    @staticmethod
    def _check_ended(thread: threading.Thread) -> None:
        if thread.is_alive():
            log.warning("web view: the update pump did not end within 5 s")

    def add(self, robots: list[str]) -> Client:
        """A new client (in the server loop): it gets the events kept so far, then the
        current picture at the pump's next turn."""
        client = Client(robots, events_kept=self.events_kept)
        self.clients.add(client)
        self._watched = self._watched | set(robots)
        for name in robots:
            # The events up to what the pump took last: the later ones come with updates.
            upto = self._last_seq[name]
            kept = self.planes[name].events(limit=self.events_kept)
            client.offer_events(name, [e for e in kept if e["seq"] <= upto], upto=upto)
            self._dirty[name].set()
        self._kick.set()
        return client

    def remove(self, client: Client) -> None:
        self.clients.discard(client)
        self._watched = frozenset(name for c in self.clients for name in c.robots)
        self.dropped_total += client.dropped

    def build(self, name: str, *, reuse_tree: bool = False) -> bytes:
        """One robot's update (``{"seq", "stamp", "snapshot", "blackboard"}``), serialised
        once for every client (any thread). ``reuse_tree``: take the snapshot built last
        unless one of the robot's events came since or it is :data:`TREE_MAX_AGE_S` old
        (the pump's turns; the blackboard is read every time)."""
        with self._build_lock:
            started = time.perf_counter()
            now = time.monotonic()
            tree = self._trees.get(name) if reuse_tree else None
            happened = self._tree_happened[name]
            if tree is None or happened.is_set() or now - tree[0] >= TREE_MAX_AGE_S:
                happened.clear()  # before reading: an event during the read sets it again
                tree = self._trees[name] = (now, to_json(self.planes[name].snapshot()))
            self._seq += 1
            out = b"".join([b'{"seq":%d,"stamp":' % self._seq, to_json(time.time()),
                            b',"snapshot":', tree[1], b',"blackboard":',
                            self._boards[name].encode(), b"}"])
            self.build_s += time.perf_counter() - started
            self.updates_built += 1
            return out

    def _due(self, now: float) -> bool:
        """Whether a watched robot changed or waits for its refresh."""
        return any(self._dirty[name].is_set() or now - self._last_built[name] >= self.refresh_s
                   for name in self._watched)

    def _pump(self) -> None:
        self._threads["pump"] = threading.get_native_id()
        last_turn = -math.inf
        while not self._stopping:
            # The coalescing: at most one turn every period_s. While it sleeps out the
            # period, a change only sets its robot's flag; only the latest state is sent.
            self._armed = False
            delay_s = last_turn + self.period_s - time.monotonic()
            if delay_s > 0:
                time.sleep(delay_s)
            while not self._stopping and not self._due(time.monotonic()):
                # Nothing to send: wait for a change (the leading edge: a quiet robot's
                # change is on its way within a build) or the next refresh (ages move on).
                self._kick.clear()
                self._armed = True
                if self._due(time.monotonic()):  # a change came before it was armed
                    break
                self._kick.wait(self.refresh_s if self._watched else None)
            self._armed = False
            if self._stopping:
                return
            last_turn = time.monotonic()
            try:
                self._turn()
            except Exception:  # a robot's snapshot failed: report, keep serving
                log.exception("web view: building an update failed")

    def _turn(self) -> None:
        now = time.monotonic()
        updates = []
        for name in self._watched:
            due = now - self._last_built[name] >= self.refresh_s
            if not (self._dirty[name].is_set() or due):
                continue
            self._dirty[name].clear()
            self._last_built[name] = now
            body = self.build(name, reuse_tree=True)[1:-1]
            events: list[dict[str, Any]] = []
            if self._happened[name].is_set():  # the log is read only when it grew
                self._happened[name].clear()
                events = self.planes[name].events(after_seq=self._last_seq[name],
                                                  limit=self.events_kept)
            if events:
                self._last_seq[name] = events[-1]["seq"]
            updates.append(Update(name, body, events, _message(name, body, events)))
        if updates and self._loop is not None:
            try:
                self._loop.call_soon_threadsafe(self._deliver, updates)
            except RuntimeError:  # the server's loop has closed: nobody to send to
                self._stopping = True

    def _deliver(self, updates: list[Update]) -> None:
        """Offer this turn's updates to the clients watching their robots (server loop)."""
        for update in updates:
            for client in self.clients:
                if update.robot in client.robots:
                    client.offer(update)

    def stats(self) -> dict[str, Any]:
        clients = [c.stats() for c in self.clients]
        return {"clients": clients, "updates_built": self.updates_built,
                "build_ms_mean": round(1000 * self.build_s / self.updates_built, 3)
                if self.updates_built else None,
                "dropped_snapshots": self.dropped_total + sum(c["dropped"] for c in clients),
                "rate_hz": round(1.0 / self.period_s, 3),
                "cpu_s": {name: _thread_cpu_s(tid) for name, tid in self._threads.items()}}


def _thread_cpu_s(tid: int) -> float | None:
    """The CPU time a thread of this process has used (Linux; None elsewhere): what serving
    costs, told apart from the robot's own threads (``GET /api/stats``, the benchmark)."""
    try:
        with open(f"/proc/self/task/{tid}/schedstat") as stat:
            return int(stat.read().split()[0]) / 1e9
    except (OSError, ValueError, IndexError):
        return None
