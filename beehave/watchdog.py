"""The event-loop watchdog: notices when something holds the low level's loop, and says who.

Every logic, HAL and blackboard callback of the low level shares one asyncio loop. A
callback that does not ``await`` -- ``time.sleep`` in a logic, a blocking read in a HAL --
holds that loop: no other logic runs, no switch happens, shutdown cannot proceed. The
loop itself cannot notice (it is the one that is stuck), so a thread does::

    watchdog thread                       the loop's thread
    ── ping (call_soon_threadsafe) ──►    answers when it gets to it
    no answer after loop_lag_warn_s  →    warning + LOOP_BLOCKED event naming the culprit
    no answer after block_s          →    pending cross-thread calls fail with LoopBlocked

``block_s`` is ``max(stop_timeout_s, loop_lag_warn_s)``: a loop is never declared blocked
before it has been warned about.

LOOP_BLOCKED events are delivered from a notifier thread of their own
(``beehave-lowlevel-loop-events``), never from the thread that measures: a subscriber that
calls back into the manager (``ll.snapshot()``, ``ll.switch()``, ``ll.shutdown()``) waits for
the loop, and only the measuring thread can fail that wait with ``LoopBlocked``.

The culprit is read from the loop while it is stuck: the task it is stepping
(``asyncio.current_task(loop)``, whose name says ``logic:<path>`` or ``hal:<name>``) and the
innermost frame of its thread outside the standard library (the line that blocks).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
import queue
import sys
import sysconfig
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import FrameType
from typing import Any

from beehave.errors import LoopBlocked, ManagerShutdown
from beehave.events import Event, EventBus, EventKind

log = logging.getLogger(__name__)

__all__ = ["Culprit", "LoopWatchdog"]

_STDLIB = tuple(os.path.normcase(p) + os.sep for p in {
    sysconfig.get_paths()["stdlib"], sysconfig.get_paths()["platstdlib"]})
_RULE = ("never block the loop: use `await asyncio.sleep(...)`, not time.sleep, and "
         "`await asyncio.to_thread(...)` for blocking I/O")


@dataclass(frozen=True)
class Culprit:
    """What holds the loop: ``subject`` (``logic:<path>``, ``hal:<name>``, ``task:<name>``
    or ``callback``), a readable ``who`` and ``where`` it is (``file.py:42 in run``)."""

    subject: str
    who: str
    where: str


def find_culprit(loop: asyncio.AbstractEventLoop, thread_id: int) -> Culprit:
    """Name whatever the (blocked) ``loop`` in thread ``thread_id`` is running right now."""
    # Both reads are made from another thread while the loop is stuck: the task dict and
    # the frame do not change under us for as long as it stays stuck.
    task = asyncio.current_task(loop)
    where = _where(sys._current_frames().get(thread_id))
    if task is None:
        return Culprit("callback", "a callback outside any task", where)
    name = task.get_name()
    kind, _, rest = name.partition(":")
    if kind == "logic":
        return Culprit(name, f"logic {rest!r}", where)
    if kind == "hal":
        hal, _, phase = rest.partition(":")
        what = {"load": " (on_load)", "unload": " (safe_state/on_unload)"}.get(phase, "")
        return Culprit(f"hal:{hal}", f"HAL {hal!r}{what}", where)
    return Culprit(f"task:{name}", f"task {name!r}", where)


def _where(frame: FrameType | None) -> str:
    """The innermost frame outside the standard library: the user's line that blocks."""
    innermost = frame
    while frame is not None:
        filename = os.path.normcase(os.path.abspath(frame.f_code.co_filename))
        if not filename.startswith(_STDLIB) or "site-packages" in filename:
            return f"{frame.f_code.co_filename}:{frame.f_lineno} in {frame.f_code.co_name}"
        frame = frame.f_back
    if innermost is None:
        return "unknown"
    return f"{innermost.f_code.co_filename}:{innermost.f_lineno} in {innermost.f_code.co_name}"


class LoopWatchdog:
    """Pings ``loop`` from a thread of its own; warns after ``warn_s`` without an answer
    and declares the loop blocked after ``block_s``.

    While blocked, :meth:`blocked` returns the :class:`~beehave.errors.LoopBlocked` error
    that callers should raise, and every future registered with :meth:`watch` fails with
    it, so nobody waits for ever on a loop that does not run. Started and stopped by the
    :class:`~beehave.lowlevel.LowLevelBehaviorManager` that owns the loop.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, thread_id: int, events: EventBus, *,
                 warn_s: float, block_s: float, name: str = "low-level") -> None:
        self.loop = loop
        self.thread_id = thread_id
        self.events = events
        self.warn_s = warn_s
        self.block_s = max(block_s, warn_s)
        self.name = name
        self._period_s = warn_s / 2
        self._answered = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._watched: set[concurrent.futures.Future[Any]] = set()
        self._blocked: LoopBlocked | None = None
        self._warned: Culprit | None = None  # who held the loop when it was last warned about
        self._thread = threading.Thread(target=self._main, name="beehave-lowlevel-watchdog",
                                        daemon=True)
        # Subscribers run here, not in _thread: see the module docstring.
        self._outbox: queue.SimpleQueue[Event | None] = queue.SimpleQueue()
        self._notifier = threading.Thread(target=self._notify, name="beehave-lowlevel-loop-events",
                                          daemon=True)
        self._notifier_started = False
        self.warnings = 0
        """How many times the loop was found held longer than ``warn_s``."""

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        self._thread.start()

    def _post(self, event: Event) -> None:
        """Queue ``event`` for the notifier, started on the first one (most runs never need
        it)."""
        with self._lock:
            if not self._notifier_started and not self._stop.is_set():
                self._notifier.start()
                self._notifier_started = True
            queued = self._notifier_started
        if queued:
            self._outbox.put(event)
        else:  # stopping, and no notifier ever ran: deliver it here rather than drop it
            self.events.emit(event)

    def stop(self, *, notify_timeout_s: float = 1.0) -> None:
        """Stop and join the measuring thread (it never blocks for long: it only waits on
        events); fail the calls still waiting with :class:`ManagerShutdown`, since nobody
        would fail them any more; let the notifier deliver what is queued (joined at most
        ``notify_timeout_s``: a subscriber may itself be slow)."""
        self._stop.set()
        self._answered.set()
        me = threading.current_thread()
        if self._thread.is_alive() and self._thread is not me:
            self._thread.join()
        with self._lock:
            watched, self._watched = self._watched, set()
        for future in watched:
            _fail(future, ManagerShutdown(f"the {self.name} manager stopped"))
        with self._lock:  # after this, _post starts no notifier any more
            started = self._notifier_started
        self._outbox.put(None)
        if started and self._notifier is not me:
            self._notifier.join(notify_timeout_s)

    # -- what callers use ----------------------------------------------------------------

    def blocked(self) -> LoopBlocked | None:
        """The error to raise while the loop is blocked past ``block_s`` (else None)."""
        return self._blocked

    def watch(self, future: concurrent.futures.Future[Any]) -> Callable[[], None]:
        """Fail ``future`` with :class:`LoopBlocked` if the loop is (or gets) blocked past
        ``block_s`` before it is done; returns the function that stops watching it."""
        with self._lock:
            if self._stop.is_set():
                _fail(future, ManagerShutdown(f"the {self.name} manager stopped"))
            else:
                self._watched.add(future)

        def unwatch() -> None:
            with self._lock:
                self._watched.discard(future)

        return unwatch

    # -- the thread ----------------------------------------------------------------------

    def _main(self) -> None:
        while not self._stop.is_set():
            self._answered.clear()
            sent = time.monotonic()
            try:
                self.loop.call_soon_threadsafe(self._answer, sent)
            except RuntimeError:  # the loop closed
                return
            if self._answered.wait(self.warn_s):
                self._stop.wait(self._period_s)
                continue
            if self._stop.is_set():
                return
            try:
                self._held(sent)
            except Exception:  # the watchdog must outlive its own bugs: log, keep watching
                log.exception("%s event loop watchdog failed while the loop was held",
                              self.name)

    def _notify(self) -> None:
        while (event := self._outbox.get()) is not None:
            self.events.emit(event)  # EventBus.emit logs a failing subscriber, never raises

    def _held(self, sent: float) -> None:
        culprit = find_culprit(self.loop, self.thread_id)
        lag = time.monotonic() - sent
        self.warnings += 1
        self._warned = culprit
        log.warning("%s event loop blocked for %.3f s by %s at %s; %s", self.name, lag,
                    culprit.who, culprit.where, _RULE)
        self._post(Event(EventKind.LOOP_BLOCKED, culprit.subject, detail={
            "culprit": culprit.who, "where": culprit.where, "blocked_s": round(lag, 3),
            "ended": False}))
        declared = False
        while not self._answered.wait(self._period_s if declared
                                      else max(0.0, sent + self.block_s - time.monotonic())):
            if self._stop.is_set():
                return
            if not declared:
                # Read again: the first look may have caught the loop between two steps.
                culprit = find_culprit(self.loop, self.thread_id)
                log.error("%s", self._error(culprit, time.monotonic() - sent))
                declared = True
            # Every period while it lasts: callers that started waiting meanwhile fail too
            # (at most one period late, so a loop that just recovered is not misjudged).
            self._declare_blocked(culprit, time.monotonic() - sent)

    def _error(self, culprit: Culprit, lag: float) -> LoopBlocked:
        return LoopBlocked(
            f"the {self.name} event loop has been blocked for {lag:.3f} s (more than "
            f"{self.block_s} s) by {culprit.who} at {culprit.where}; {_RULE}",
            culprit=culprit.who, where=culprit.where, blocked_s=lag)

    def _declare_blocked(self, culprit: Culprit, lag: float) -> None:
        error = self._error(culprit, lag)
        with self._lock:
            self._blocked = error
            watched, self._watched = self._watched, set()
        for future in watched:
            _fail(future, error)

    def _answer(self, sent: float) -> None:
        # In the loop's thread: it runs again.
        culprit = self._warned
        self._warned = None
        self._blocked = None
        self._answered.set()
        if culprit is not None:
            held = time.monotonic() - sent
            log.warning("%s event loop answers again after %.3f s (held by %s at %s)",
                        self.name, held, culprit.who, culprit.where)
            # Through the notifier too: after the "blocked" event, never before it.
            self._post(Event(EventKind.LOOP_BLOCKED, culprit.subject, detail={
                "culprit": culprit.who, "where": culprit.where, "blocked_s": round(held, 3),
                "ended": True}))


def _fail(future: concurrent.futures.Future[Any], error: BaseException) -> None:
    try:
        future.set_exception(error)
    except concurrent.futures.InvalidStateError:
        pass  # it finished meanwhile
