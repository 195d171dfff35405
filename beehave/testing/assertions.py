"""Assertions that read like the docs: switched to, lock held by, safe state ran, and the
timeline of events — each failing with a message that shows what did happen.

::

    events = EventLog(hl, clock=clock)
    hl.switch("tour")
    clock.advance(60)
    events.assert_switched_to("tour")
    assert_lock_held_by(hl, "driving", "tour/Navigate")
    events.assert_in_order("started tour/Navigate", "ended tour/Navigate SUCCEEDED")
"""

from __future__ import annotations

import fnmatch
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from beehave.events import Event, EventKind


@dataclass(frozen=True)
class Entry:
    """One event on the timeline: ``t`` is the manager's clock time when it happened
    (virtual time under the test kit's clock)."""

    t: float
    kind: str
    subject: str
    status: str | None
    event: Event

    def __str__(self) -> str:
        status = f" {self.status}" if self.status else ""
        return f"{self.t:10.3f}  {self.kind} {self.subject}{status}"

    def matches(self, pattern: str) -> bool:
        """``"KIND SUBJECT [STATUS]"`` with ``fnmatch`` wildcards in each word:
        ``"ended tour/* INTERRUPTED"``, ``"switch_completed tour"``."""
        words = pattern.split()
        if not 1 <= len(words) <= 3:
            raise ValueError(f"timeline pattern {pattern!r}: expected 'KIND [SUBJECT [STATUS]]' "
                             f"(kinds: {', '.join(k.value for k in EventKind)})")
        mine = [self.kind, self.subject, self.status or ""]
        return all(fnmatch.fnmatchcase(have, want) for have, want in zip(mine, words,
                                                                          strict=False))


class EventLog:
    """Records every event of one or more managers (high and low level) with the clock
    time it happened at. Thread-safe; unsubscribes on :meth:`close`."""

    def __init__(self, *managers: Any, clock: Callable[[], float] | Any = None) -> None:
        if not managers:
            raise ValueError("EventLog(manager, …): give at least one manager to record")
        now = getattr(clock, "now", clock)
        if now is None:
            now = getattr(getattr(managers[0], "clock", None), "now", None)
        if now is None:
            import time
            now = time.monotonic
        self._now: Callable[[], float] = now
        self._lock = threading.Lock()
        self.entries: list[Entry] = []
        self._unsubscribe = [m.subscribe(self._on_event) for m in managers]

    def _on_event(self, event: Event) -> None:
        entry = Entry(self._now(), event.kind.value, event.subject, event.status, event)
        with self._lock:
            self.entries.append(entry)

    def close(self) -> None:
        for unsubscribe in self._unsubscribe:
            unsubscribe()
        self._unsubscribe = []

    def timeline(self, pattern: str | None = None) -> list[Entry]:
        """The entries so far (those that match ``pattern``, if given), oldest first."""
        with self._lock:
            entries = list(self.entries)
        return entries if pattern is None else [e for e in entries if e.matches(pattern)]

    def __str__(self) -> str:
        return "\n".join(str(e) for e in self.timeline()) or "(no events)"

    def find(self, pattern: str) -> Entry | None:
        """The first entry that matches ``pattern``, or None."""
        found = self.timeline(pattern)
        return found[0] if found else None

    # -------------------------------------------------------------------- assertions
    def assert_in_order(self, *patterns: str) -> list[Entry]:
        """Each pattern matches an entry, in this order (others may come between);
        returns the matched entries."""
        entries = self.timeline()
        matched: list[Entry] = []
        i = 0
        for pattern in patterns:
            while i < len(entries) and not entries[i].matches(pattern):
                i += 1
            if i == len(entries):
                done = "".join(f"\n  ✓ {p}" for p in patterns[:len(matched)])
                raise AssertionError(
                    f"timeline: no {pattern!r} after the earlier matches{done}\n"
                    f"  ✗ {pattern}\nthe timeline:\n{self}")
            matched.append(entries[i])
            i += 1
        return matched

    def assert_not_happened(self, pattern: str) -> None:
        found = self.timeline(pattern)
        if found:
            raise AssertionError(f"timeline: {pattern!r} happened: {found[0]}\nthe timeline:\n"
                                 f"{self}")

    def assert_switched_to(self, name: str) -> Entry:
        """A switch to ``name`` completed (the behaviour started as the top level)."""
        entry = self.find(f"switch_completed {name}") or self.find(f"started {name}")
        if entry is None:
            switches = [str(e) for e in self.timeline("switch_*")] or ["(none)"]
            raise AssertionError(f"no switch to {name!r} completed; the switches:\n  "
                                 + "\n  ".join(switches))
        return entry


def assert_lock_held_by(manager: Any, action_type: str, holder: str) -> None:
    """The type lock ``action_type`` of the high-level ``manager`` is held now by an action
    whose path, name or class matches ``holder`` (``fnmatch``)."""
    locks = manager.snapshot()["locks"]
    hold = locks.get(action_type)
    if hold is None:
        held = ", ".join(f"{k} by {v['holder']}" for k, v in locks.items()) or "none"
        raise AssertionError(f"type lock {action_type!r} is not held (held now: {held})")
    names = (hold["holder"], hold["holder"].rsplit("/", 1)[-1], hold["class"])
    if not any(fnmatch.fnmatchcase(n, holder) for n in names):
        raise AssertionError(f"type lock {action_type!r} is held by {hold['holder']!r} "
                             f"({hold['class']}, {hold['status']}), not {holder!r}")


def assert_safe_state_ran(action: Any) -> None:
    """``action``'s ``safe_state()`` was called and has returned."""
    done = getattr(action, "_safe_done", None)
    if done is None:
        raise AssertionError(f"{action!r}: its safe_state() never ran (status "
                             f"{action.status.name}; it runs when an action ends without "
                             f"success)")
    if not done.is_set():
        raise AssertionError(f"{action!r}: its safe_state() is still running")
