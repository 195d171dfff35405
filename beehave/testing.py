"""Fakes for testing behaviours without a robot: scripted actions and a timeline recorder.

Use them in your own tests::

    timeline = Timeline()
    drive = ScriptedAction("driving", duration_s=0.2, timeline=timeline)
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from beehave.action import Action


@dataclass(frozen=True)
class Mark:
    t: float
    what: str  # "run", "end", "safe_begin", "safe"
    path: str
    action_type: str


class Timeline:
    """Thread-safe record of run start/end and safe_state calls, with live invariants:
    ``max_concurrent[type]`` is the most actions of one type ever active at once — inside
    ``run`` or inside ``safe_state`` (a safe state still commands the hardware, so the type
    lock covers it too)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.marks: list[Mark] = []
        self.active: Counter[str] = Counter()
        self.max_concurrent: Counter[str] = Counter()
        self.safe_calls: Counter[int] = Counter()
        self._inside: dict[str, Counter[int]] = {}

    def record(self, what: str, action: Action) -> None:
        with self._lock:
            kind = action.action_type
            # An action is active while inside run or safe_state (a STUCK action's forced
            # safe state may run beside its run): count actions, not calls.
            inside = self._inside.setdefault(kind, Counter())
            if what in ("run", "safe_begin"):
                inside[id(action)] += 1
            elif what in ("end", "safe"):
                inside[id(action)] -= 1
                if inside[id(action)] <= 0:
                    del inside[id(action)]
            if what == "safe":
                self.safe_calls[id(action)] += 1
            self.active[kind] = len(inside)
            self.max_concurrent[kind] = max(self.max_concurrent[kind], self.active[kind])
            self.marks.append(Mark(time.monotonic(), what, action.path, kind))

    def times(self, what: str, path: str) -> list[float]:
        with self._lock:
            return [m.t for m in self.marks if m.what == what and m.path == path]


class ScriptedAction(Action):
    """An action that does what it is told: run ``duration_s`` (interruptibly), then
    return ``result`` or raise ``raises``; ``ignore_interrupt_s`` keeps it running that
    long after an interrupt (``float('inf')`` until ``release`` is set) to provoke STUCK;
    ``safe_state_s`` makes its ``safe_state`` take that long (``float('inf')`` until
    ``safe_release`` is set)."""

    def __init__(self, action_type: str = "scripted", *, duration_s: float = 0.0,
                 result: Any = None, raises: BaseException | None = None,
                 ignore_interrupt_s: float = 0.0, timeline: Timeline | None = None,
                 name: str | None = None, safe_state_s: float = 0.0) -> None:
        # action_type is per instance here; real actions set it on the class.
        self.action_type = action_type  # type: ignore[misc]
        self.duration_s = duration_s
        self.scripted_result = result
        self.raises = raises
        self.ignore_interrupt_s = ignore_interrupt_s
        self.timeline = timeline
        self.release = threading.Event()
        self.safe_state_s = safe_state_s
        self.safe_release = threading.Event()
        self.safe_state_calls = 0
        if name:
            self.name = name

    def run(self) -> Any:
        if self.timeline:
            self.timeline.record("run", self)
        try:
            completed = self.sleep(self.duration_s)
            if not completed and self.ignore_interrupt_s > 0:
                forever = self.ignore_interrupt_s == float("inf")
                self.release.wait(None if forever else self.ignore_interrupt_s)
            if self.raises is not None:
                raise self.raises
            return self.scripted_result
        finally:
            if self.timeline:
                self.timeline.record("end", self)

    def safe_state(self) -> None:
        if self.timeline:
            self.timeline.record("safe_begin", self)
        try:
            if self.safe_state_s > 0:
                forever = self.safe_state_s == float("inf")
                self.safe_release.wait(None if forever else self.safe_state_s)
        finally:
            self.safe_state_calls += 1
            if self.timeline:
                self.timeline.record("safe", self)


def beehave_threads() -> list[threading.Thread]:
    """The threads beehave runs (their names start with ``beehave``): for leak checks."""
    return [t for t in threading.enumerate() if t.name.startswith("beehave")]


def wait_until(predicate: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    """Poll ``predicate`` until true or ``timeout_s`` passed; for conditions that have no
    event to wait on (a thread ending). A safety net in tests, not a timing."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return bool(predicate())
