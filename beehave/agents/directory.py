"""The directory (yellow pages, as JADE's DF): which agents are alive and what they offer.

There is no directory process. Every agent publishes its own entry on the topic
``/beehave/agents/directory`` (``std_msgs/String``, JSON, reliable, transient-local, so a
newcomer receives every live entry at once) every ``lease_s / 4`` seconds, and keeps the
entries it hears. An entry not renewed within its ``lease_s`` expires: an agent whose process
is killed vanishes from every other agent's view after at most its lease (plus one expiry
check, 0.1 s). An agent that closes says so and vanishes at once.

An entry (schema ``beehave.directory/1``)::

    {"schema": "beehave.directory/1",
     "agent": "atv_1",
     "incarnation": "8c0e…",          # new for every start of the agent
     "started_at": 1767225590.5,      # Unix time of that start
     "state": "alive",                # "joining" while it checks its name, "leaving"
     "lease_s": 2.0,
     "services": {"transport": {"payload_kg": 50, "zone": "north"}},
     "sent_at": 1767225599.5,         # Unix time of this announcement
     "auth": {"certificate": {…}, "signature": "…"}}   # signed agents (trust.py)
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from beehave.agents.message import NAME_PATTERN, is_agent_name

log = logging.getLogger(__name__)

DIRECTORY_TOPIC = "/beehave/agents/directory"
DIRECTORY_SCHEMA = "beehave.directory/1"

EXPIRY_CHECK_S = 0.1
"""How often entries are checked against their lease."""

STALL_S = 0.5
"""A check that comes this much later than :data:`EXPIRY_CHECK_S` means this process did
not run (a loaded host): the gap is not counted against anyone's lease, since the
announcements that arrived meanwhile may still wait in the queue behind the check."""


class EntryState(Enum):
    JOINING = "joining"
    """The agent checks that its name is free; it is not found by :meth:`Directory.search`."""
    ALIVE = "alive"
    LEAVING = "leaving"


class Announcement(BaseModel):
    """One directory entry on the wire (validated on receipt; invalid ones are logged)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_: str = Field(DIRECTORY_SCHEMA, alias="schema")
    agent: str = Field(pattern=NAME_PATTERN)
    incarnation: str = Field(min_length=1, max_length=100)
    started_at: float = Field(allow_inf_nan=False)
    state: EntryState
    lease_s: float = Field(gt=0, allow_inf_nan=False)
    services: dict[str, dict[str, Any]] = Field(default_factory=dict)
    sent_at: float | None = Field(None, allow_inf_nan=False)
    auth: dict[str, Any] | None = None

    @field_validator("schema_")
    @classmethod
    def _schema(cls, value: str) -> str:
        if value != DIRECTORY_SCHEMA:
            raise ValueError(f"unsupported schema {value!r}; expected {DIRECTORY_SCHEMA!r}")
        return value

    def older_than(self, other: Announcement) -> bool:
        """Who keeps a contested name: the earlier start (incarnation breaks a tie)."""
        return (self.started_at, self.incarnation) < (other.started_at, other.incarnation)


@dataclass(frozen=True)
class AgentInfo:
    """What the directory knows about one live agent."""

    name: str
    services: dict[str, dict[str, Any]]
    lease_s: float
    incarnation: str
    started_at: float

    def properties(self, service: str) -> dict[str, Any]:
        """The properties it registered ``service`` with (KeyError if it does not offer it)."""
        return self.services[service]


class Change(Enum):
    APPEARED = "appeared"
    """The agent offers the service now (it joined, or registered the service)."""
    CHANGED = "changed"
    """It still offers it, with other properties."""
    DISAPPEARED = "disappeared"
    """It no longer does (deregistered, closed, or its lease expired)."""


@dataclass(frozen=True)
class DirectoryEvent:
    """What a :meth:`Directory.subscribe` callback receives."""

    change: Change
    service: str
    agent: AgentInfo
    reason: str = ""


@dataclass
class _Entry:
    announcement: Announcement
    renewed_at: float  # time.monotonic()


@dataclass
class _Subscription:
    service: str
    callback: Callable[[DirectoryEvent], None]
    constraints: dict[str, Any] = field(default_factory=dict)
    closed: bool = False


def matches(properties: dict[str, Any], constraints: dict[str, Any]) -> bool:
    """Every constraint equals the property of its name (a missing property never does)."""
    return all(key in properties and properties[key] == value
               for key, value in constraints.items())


class Directory:
    """The entries this agent has heard (made and owned by :class:`~beehave.agents.Agent`;
    use it as ``agent.directory``). Thread-safe; callbacks run in the ROS executor thread
    and must be short."""

    def __init__(self, own_name: str) -> None:
        self._own = own_name
        self._lock = threading.Lock()
        self._entries: dict[str, _Entry] = {}
        self._checked_at: float | None = None  # the last _expire, time.monotonic()
        self._subscriptions: list[_Subscription] = []
        self._heard: set[str] = set()  # incarnations heard (probing counts them)
        self.conflict: Announcement | None = None  # who holds our name, if anyone
        self._own_announcement: Announcement | None = None
        #: When this agent last heard its own entry back (time.monotonic()): a measure of
        #: how far this process's reading of the topic lags (see :meth:`_receive_lag`).
        self._own_heard_at: float | None = None
        self._departure_listeners: list[Callable[[str, str], None]] = []
        self._name_lost: Callable[[Announcement], None] | None = None

    # ------------------------------------------------------------------ queries
    def search(self, service: str, **constraints: Any) -> list[AgentInfo]:
        """The live agents offering ``service`` whose properties equal every constraint
        (``search("transport", zone="north")``), sorted by name; this agent included when
        it offers the service itself."""
        with self._lock:
            found = [self._info(e.announcement) for e in self._entries.values()
                     if e.announcement.state is EntryState.ALIVE
                     and service in e.announcement.services
                     and matches(e.announcement.services[service], constraints)]
        return sorted(found, key=lambda info: info.name)

    def get(self, name: str) -> AgentInfo | None:
        """The live agent ``name``, or None."""
        with self._lock:
            entry = self._entries.get(name)
        if entry is None or entry.announcement.state is not EntryState.ALIVE:
            return None
        return self._info(entry.announcement)

    def agents(self) -> list[AgentInfo]:
        """Every live agent, sorted by name."""
        with self._lock:
            found = [self._info(e.announcement) for e in self._entries.values()
                     if e.announcement.state is EntryState.ALIVE]
        return sorted(found, key=lambda info: info.name)

    def alive(self, name: str) -> bool:
        return self.get(name) is not None

    @staticmethod
    def _info(a: Announcement) -> AgentInfo:
        return AgentInfo(name=a.agent, services=a.services, lease_s=a.lease_s,
                         incarnation=a.incarnation, started_at=a.started_at)

    # ------------------------------------------------------------------ subscriptions
    def subscribe(self, service: str, callback: Callable[[DirectoryEvent], None],
                  **constraints: Any) -> Callable[[], None]:
        """Call ``callback(event)`` whenever an agent offering ``service`` (with these
        constraints) appears, changes its properties or disappears; the agents offering it
        now are reported at once, as APPEARED. Returns the function that ends the
        subscription. Callbacks run in the ROS executor thread (or in this call, for the
        initial report); an exception there is logged with its traceback."""
        sub = _Subscription(service, callback, dict(constraints))
        with self._lock:
            self._subscriptions.append(sub)
        for info in self.search(service, **constraints):
            self._call(sub, DirectoryEvent(Change.APPEARED, service, info, "present"))

        def unsubscribe() -> None:
            with self._lock:
                sub.closed = True
                if sub in self._subscriptions:
                    self._subscriptions.remove(sub)

        return unsubscribe

    def _on_departure(self, listener: Callable[[str, str], None]) -> Callable[[], None]:
        """``listener(name, reason)`` when a live agent goes (for conversations)."""
        with self._lock:
            self._departure_listeners.append(listener)

        def remove() -> None:
            with self._lock:
                if listener in self._departure_listeners:
                    self._departure_listeners.remove(listener)

        return remove

    @staticmethod
    def _call(sub: _Subscription, event: DirectoryEvent) -> None:
        if sub.closed:
            return
        try:
            sub.callback(event)
        except Exception:
            log.exception("directory subscription callback for %r raised on %s of %r",
                          sub.service, event.change.value, event.agent.name)

    # ------------------------------------------------------------------ updates
    def _receive(self, text: str) -> None:
        """A directory message arrived (executor thread)."""
        data: Any = None
        try:
            data = json.loads(text)
            announcement = Announcement.model_validate(data)
        except (ValueError, ValidationError) as exc:
            who = data.get("agent") if isinstance(data, dict) else None
            log.warning("directory: ignored an invalid entry%s: %s",
                        f" from {who!r}" if is_agent_name(who) else "", exc)
            return
        own = self._own_announcement
        if announcement.agent == self._own:
            if own is not None and announcement.incarnation != own.incarnation:
                self._name_contested(announcement, own)
            elif own is not None:
                self._own_heard_at = time.monotonic()
            return
        with self._lock:
            self._heard.add(announcement.incarnation)
            old = self._entries.get(announcement.agent)
            if old is not None and old.announcement.incarnation != announcement.incarnation \
                    and announcement.state is not EntryState.LEAVING \
                    and old.announcement.state is EntryState.ALIVE \
                    and old.announcement.older_than(announcement):
                # Another process claims a live name: the older one keeps it (the newcomer
                # refuses itself when it sees the holder).
                return
            if old is not None and announcement.state is EntryState.LEAVING \
                    and old.announcement.incarnation != announcement.incarnation:
                return  # a late goodbye of an earlier incarnation
            if announcement.state is EntryState.LEAVING:
                self._entries.pop(announcement.agent, None)
            else:
                self._entries[announcement.agent] = _Entry(announcement, time.monotonic())
        before = old.announcement if old is not None else None
        after = announcement if announcement.state is not EntryState.LEAVING else None
        self._report(before, after, "left" if after is None else "announced")

    def _name_contested(self, other: Announcement, own: Announcement) -> None:
        if other.state is EntryState.LEAVING or not other.older_than(own):
            return  # a younger claimant refuses itself when it hears us
        if other.state is EntryState.ALIVE or own.state is EntryState.JOINING:
            first = self.conflict is None
            self.conflict = other
            if first and own.state is EntryState.ALIVE and self._name_lost is not None:
                self._name_lost(other)

    def _expire(self) -> None:
        """Drop the entries whose lease ran out (executor thread, every EXPIRY_CHECK_S)."""
        now = time.monotonic()
        with self._lock:
            stalled = 0.0 if self._checked_at is None else now - self._checked_at - EXPIRY_CHECK_S
            self._checked_at = now
            if stalled > STALL_S:
                # We were not running: an entry whose owner is silent only from our view
                # must not expire for it. (A dead owner expires one stall later.)
                log.info("directory: this process stalled %.2f s; not counted against the "
                         "leases", stalled)
                for entry in self._entries.values():
                    entry.renewed_at += stalled
            lag = self._receive_lag(now)
            gone = [e for name, e in self._entries.items()
                    if now - e.renewed_at - lag > e.announcement.lease_s]
            for entry in gone:
                del self._entries[entry.announcement.agent]
        for entry in gone:
            log.info("directory: agent %r expired (no announcement for %.2f s, lease %.2f s)",
                     entry.announcement.agent, now - entry.renewed_at,
                     entry.announcement.lease_s)
            self._report(entry.announcement, None, "lease expired")

    def _receive_lag(self, now: float) -> float:
        """How far behind this process reads the topic: the time its own entry, sent every
        ``lease_s / 4``, has not come back beyond that period. Not counted against anyone's
        lease: a peer's announcements wait in the same queue as our own (a process busy
        elsewhere, its executor behind, on a loaded host). 0 without an own live entry."""
        own = self._own_announcement
        if own is None or own.state is not EntryState.ALIVE or self._own_heard_at is None:
            return 0.0
        return max(0.0, now - self._own_heard_at - own.lease_s / 4)

    def _set_own(self, announcement: Announcement | None) -> None:
        """This agent's own entry, kept so that :meth:`search` finds it too."""
        self._own_announcement = announcement
        with self._lock:
            old = self._entries.get(self._own)
            if announcement is None or announcement.state is not EntryState.ALIVE:
                self._entries.pop(self._own, None)
            else:
                # Never expires: renewed here with every own announcement.
                self._entries[self._own] = _Entry(announcement, float("inf"))
        if announcement is not None and announcement.state is EntryState.JOINING:
            return
        before = old.announcement if old is not None else None
        after = (announcement if announcement is not None
                 and announcement.state is EntryState.ALIVE else None)
        self._report(before, after, "own entry")

    def _report(self, before: Announcement | None, after: Announcement | None,
                reason: str) -> None:
        was = before.services if before is not None and before.state is EntryState.ALIVE \
            else {}
        now = after.services if after is not None and after.state is EntryState.ALIVE else {}
        with self._lock:
            subs = list(self._subscriptions)
            listeners = list(self._departure_listeners)
        for sub in subs:
            old_ok = sub.service in was and matches(was[sub.service], sub.constraints)
            new_ok = sub.service in now and matches(now[sub.service], sub.constraints)
            if new_ok and not old_ok:
                assert after is not None
                self._call(sub, DirectoryEvent(Change.APPEARED, sub.service,
                                               self._info(after), reason))
            elif old_ok and not new_ok:
                assert before is not None
                self._call(sub, DirectoryEvent(Change.DISAPPEARED, sub.service,
                                               self._info(after or before), reason))
            elif old_ok and new_ok and was[sub.service] != now[sub.service]:
                assert after is not None
                self._call(sub, DirectoryEvent(Change.CHANGED, sub.service,
                                               self._info(after), reason))
        if before is not None and after is None and before.state is EntryState.ALIVE:
            for listener in listeners:
                try:
                    listener(before.agent, reason)
                except Exception:
                    log.exception("directory: departure listener raised")

    def _heard_count(self) -> int:
        with self._lock:
            return len(self._heard)
