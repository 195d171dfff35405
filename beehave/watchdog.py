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
innermost frame of its thread outside the standard library and beehave itself (the line
that blocks).

A late answer is not always a blocking callback. When the whole process gets no CPU (a
machine at load 27, a stopped process, another thread holding the GIL), the loop is late
with nothing holding it. The watchdog tells the two apart before blaming anyone:

- the loop's thread was *idle* — waiting in its poll for work (``selectors`` for asyncio's
  loop; uvloop's C loop under the frame that started it) — so nothing held it;
- or the watchdog thread itself woke more than ``warn_s`` (and :data:`STARVED_LATE_S`)
  late: then no thread of the process was getting CPU, and what the loop happened to be
  running when it was stopped is not to blame;
- or the loop answered late, but before the watchdog thread woke to notice (the process
  resumed, and the loop's thread got the interpreter first): reported when the watchdog
  wakes, as a starvation that has already ended.

Either way the warning says "the process was starved of CPU for X s" (with the process's
CPU time over that wall time) and names no line. A loop held inside beehave's own code
(no frame of anyone else's) is reported as such, never as a line for the user to fix.
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

__all__ = ["Culprit", "LoopWatchdog", "loop_is_idle"]

_STDLIB = tuple(os.path.normcase(p) + os.sep for p in {
    sysconfig.get_paths()["stdlib"], sysconfig.get_paths()["platstdlib"]})
#: beehave's own package: a frame there is never the line a user is told to fix.
_BEEHAVE = os.path.normcase(os.path.dirname(os.path.abspath(__file__))) + os.sep
_RULE = ("never block the loop: use `await asyncio.sleep(...)`, not time.sleep, and "
         "`await asyncio.to_thread(...)` for blocking I/O")
#: The stdlib frames in which an idle loop waits: the calls under which uvloop's loop (C,
#: no frame of its own) waits; asyncio's selector poll is checked with its caller.
_IDLE_FRAMES = {("base_events.py", "run_forever"), ("base_events.py", "run_until_complete"),
                ("runners.py", "run")}
#: The watchdog itself must wake at least this late (and more than ``warn_s``) before a
#: loop found running someone's code is put down to starvation: a loaded machine delays
#: every thread a little, and a callback that really blocks must still be named.
STARVED_LATE_S = 0.25


@dataclass(frozen=True)
class Culprit:
    """What holds the loop: ``subject`` (``logic:<path>``, ``hal:<name>``, ``task:<name>``,
    ``callback``, or ``process`` when nothing held it and the process was starved of CPU),
    a readable ``who`` and ``where`` it is (``file.py:42 in run``).

    ``starved``: the process got no CPU (``why`` gives the figures) — nobody's line is to
    blame. ``internal``: the loop was busy in beehave's own code (``where`` is there)."""

    subject: str
    who: str
    where: str
    starved: bool = False
    internal: bool = False
    why: str = ""

    def describe(self, lag_s: float) -> str:
        """``lag_s`` of it in words, ending with what to do about it."""
        if self.starved:
            return (f"did not run for {lag_s:.3f} s: the process was starved of CPU for "
                    f"{lag_s:.3f} s ({self.why}); a loaded machine or a stopped process, "
                    f"not a blocking callback: nothing in your logics or HALs to fix")
        if self.internal:
            return (f"was held for {lag_s:.3f} s by {self.who} inside beehave itself at "
                    f"{self.where}, not by your code; if it repeats on an idle machine, "
                    f"report it with this line")
        return f"blocked for {lag_s:.3f} s by {self.who} at {self.where}; {_RULE}"


def find_culprit(loop: asyncio.AbstractEventLoop, thread_id: int) -> Culprit:
    """Name whatever the (blocked) ``loop`` in thread ``thread_id`` is running right now."""
    # Both reads are made from another thread while the loop is stuck: the task dict and
    # the frame do not change under us for as long as it stays stuck.
    task = asyncio.current_task(loop)
    frame = sys._current_frames().get(thread_id)
    where = _where(frame)
    if where is None:  # only the standard library and beehave on the stack
        inner = _where(frame, skip_beehave=False) or "unknown"
        who = ("a callback outside any task" if task is None
               else f"task {task.get_name()!r}")
        return Culprit(task.get_name() if task is not None else "callback", who, inner,
                       internal=True)
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


def _where(frame: FrameType | None, *, skip_beehave: bool = True) -> str | None:
    """The innermost frame outside the standard library (and beehave's own package): the
    user's line that blocks; None when there is none (the loop is in beehave's code, or
    idle). A library's frame (site-packages) counts: the user called it."""
    while frame is not None:
        filename = os.path.normcase(os.path.abspath(frame.f_code.co_filename))
        if (not filename.startswith(_STDLIB) or "site-packages" in filename) and not (
                skip_beehave and filename.startswith(_BEEHAVE)):
            return f"{frame.f_code.co_filename}:{frame.f_lineno} in {frame.f_code.co_name}"
        frame = frame.f_back
    return None


def loop_is_idle(frame: FrameType | None) -> bool:
    """Whether the loop's thread, whose innermost frame is ``frame``, waits for work in its
    poll — then nothing holds the loop, and a late answer means it got no CPU."""
    if frame is None:
        return False
    code = frame.f_code
    filename = os.path.normcase(os.path.abspath(code.co_filename))
    if filename.startswith(_STDLIB) and "site-packages" not in filename:
        base = os.path.basename(filename)
        if base == "selectors.py":  # asyncio's loop polls in select(), called by _run_once
            caller = frame.f_back
            return caller is not None and caller.f_code.co_name == "_run_once" and \
                os.path.basename(caller.f_code.co_filename) == "base_events.py"
        return (base, code.co_name) in _IDLE_FRAMES
    # uvloop under the low level's own thread: its C loop runs under _thread_main.
    return filename.startswith(_BEEHAVE) and code.co_name == "_thread_main"


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
        # Orders _warned against the loop's answer (the loop thread and this one).
        self._answer_lock = threading.Lock()
        self._answered_at = 0.0  # when the loop last answered (monotonic; under _answer_lock)
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
            cpu = time.process_time()
            try:
                self.loop.call_soon_threadsafe(self._answer, sent)
            except RuntimeError:  # the loop closed
                return
            if self._answered.wait(self.warn_s):
                self._late_answer(sent, cpu)
                self._stop.wait(self._period_s)
                continue
            woke = time.monotonic()
            if self._stop.is_set():
                return
            try:
                self._held(sent, woke, cpu)
            except Exception:  # the watchdog must outlive its own bugs: log, keep watching
                log.exception("%s event loop watchdog failed while the loop was held",
                              self.name)

    def diagnose(self, sent: float, woke: float, cpu: float, *,
                 waited_s: float | None = None) -> Culprit:
        """Who held the loop since ``sent`` (monotonic), seen by a watchdog that woke at
        ``woke`` from a wait of ``waited_s`` (default ``warn_s``) begun at ``sent``;
        ``cpu``: ``time.process_time()`` at ``sent``."""
        # Not the loop thread's own CPU clock or scheduler state: a callback descheduled
        # mid-step and one asleep in time.sleep both show little CPU, and while this
        # thread reads them it holds the GIL, which a running loop thread then waits for.
        frame = sys._current_frames().get(self.thread_id)
        late_s = woke - (sent + (self.warn_s if waited_s is None else waited_s))
        idle = loop_is_idle(frame)
        if idle or late_s > max(self.warn_s, STARVED_LATE_S):
            return _starvation(sent, cpu, "the loop was idle, waiting for work" if idle
                               else f"the watchdog itself woke {late_s:.3f} s late")
        return find_culprit(self.loop, self.thread_id)

    def _late_answer(self, sent: float, cpu: float) -> None:
        """The loop answered ``sent``'s ping more than ``warn_s`` late, yet before this
        thread woke to notice: the whole process was stopped or starved of CPU (SIGSTOP, a
        machine at load 27), and when it ran again the loop's thread got the interpreter
        first. Reported as a starvation that has ended (both events at once), not dropped.
        A late answer while this thread woke on time is a block that ended as it looked:
        nobody can be named any more, and the next one is reported as usual."""
        woke = time.monotonic()
        with self._answer_lock:
            held = self._answered_at - sent
        if held <= self.warn_s or woke - (sent + self.warn_s) <= max(self.warn_s,
                                                                      STARVED_LATE_S):
            return
        culprit = _starvation(sent, cpu, f"the watchdog itself woke "
                                         f"{woke - sent - self.warn_s:.3f} s late")
        self.warnings += 1
        log.warning("%s event loop %s", self.name, culprit.describe(held))
        self._post(Event(EventKind.LOOP_BLOCKED, culprit.subject,
                         detail=_detail(culprit, held, ended=False)))
        self._report_answer(culprit, held)

    def _notify(self) -> None:
        while (event := self._outbox.get()) is not None:
            self.events.emit(event)  # EventBus.emit logs a failing subscriber, never raises

    def _held(self, sent: float, woke: float, cpu: float) -> None:
        culprit = self.diagnose(sent, woke, cpu)
        lag = time.monotonic() - sent
        self.warnings += 1
        log.warning("%s event loop %s", self.name, culprit.describe(lag))
        self._post(Event(EventKind.LOOP_BLOCKED, culprit.subject,
                         detail=_detail(culprit, lag, ended=False)))
        with self._answer_lock:
            # Set after the "blocked" event, so the loop's "ended" one follows it; an
            # answer that came while we looked found nothing to report: report it here.
            answered = self._answered.is_set()
            if not answered:
                self._warned = culprit
        if answered:
            self._report_answer(culprit, lag)
            return
        declared = False
        while True:
            waited = (self._period_s if declared
                      else max(0.0, sent + self.block_s - time.monotonic()))
            began, began_cpu = time.monotonic(), time.process_time()
            if self._answered.wait(waited):
                break
            if self._stop.is_set():
                return
            if not declared or culprit.starved:
                # Read again: the first look may have caught the loop between two steps
                # (and a process that was starved may since have run into a real block).
                culprit = self.diagnose(began, time.monotonic(), began_cpu, waited_s=waited)
                with self._answer_lock:
                    if not self._answered.is_set():  # else the answer reported the old one
                        self._warned = culprit
                if not declared:
                    log.error("%s", self._error(culprit, time.monotonic() - sent))
                declared = True
            # Every period while it lasts: callers that started waiting meanwhile fail too
            # (at most one period late, so a loop that just recovered is not misjudged).
            self._declare_blocked(culprit, time.monotonic() - sent)

    def _error(self, culprit: Culprit, lag: float) -> LoopBlocked:
        what = culprit.describe(lag)
        if not culprit.starved and not culprit.internal:
            what = (f"has been blocked for {lag:.3f} s (more than {self.block_s} s) by "
                    f"{culprit.who} at {culprit.where}; {_RULE}")
        return LoopBlocked(f"the {self.name} event loop {what}", culprit=culprit.who,
                           where=culprit.where, blocked_s=lag)

    def _declare_blocked(self, culprit: Culprit, lag: float) -> None:
        error = self._error(culprit, lag)
        with self._answer_lock:
            # A watchdog starved between its wait and here may come after the loop answered:
            # declaring then would fail a caller that began once the loop ran again (seen
            # beside busy loops: a call right after the block ended got its LoopBlocked).
            if self._answered.is_set():
                return
            with self._lock:
                self._blocked = error
                watched, self._watched = self._watched, set()
        for future in watched:
            _fail(future, error)

    def _answer(self, sent: float) -> None:
        # In the loop's thread: it runs again.
        with self._answer_lock:
            self._answered_at = time.monotonic()
            culprit = self._warned
            self._warned = None
            self._blocked = None
            self._answered.set()
        if culprit is not None:
            self._report_answer(culprit, time.monotonic() - sent)

    def _report_answer(self, culprit: Culprit, held: float) -> None:
        """The loop runs again after ``held`` seconds: say so, after the "blocked" event."""
        if culprit.starved:
            log.warning("%s event loop runs again after %.3f s (the process was starved of "
                        "CPU)", self.name, held)
        else:
            log.warning("%s event loop answers again after %.3f s (held by %s at %s)",
                        self.name, held, culprit.who, culprit.where)
        # Through the notifier too: after the "blocked" event, never before it.
        self._post(Event(EventKind.LOOP_BLOCKED, culprit.subject,
                         detail=_detail(culprit, held, ended=True)))


def _starvation(sent: float, cpu: float, how: str) -> Culprit:
    """The process, starved of CPU since ``sent`` (monotonic; ``cpu``: its
    ``time.process_time()`` then); ``how`` it was told apart from a blocking callback."""
    wall_s = time.monotonic() - sent
    cpu_s = time.process_time() - cpu
    return Culprit("process", "CPU starvation of the process", "", starved=True,
                   why=f"it used {cpu_s:.3f} s of CPU in {wall_s:.3f} s; {how}")


def _detail(culprit: Culprit, lag: float, *, ended: bool) -> dict[str, Any]:
    """A LOOP_BLOCKED event's detail: who, where, how long, whether it ended, and whether
    the process was starved of CPU (then ``why`` has the figures and nobody is blamed)."""
    detail: dict[str, Any] = {"culprit": culprit.who, "where": culprit.where,
                              "blocked_s": round(lag, 3), "ended": ended,
                              "starved": culprit.starved}
    if culprit.why:
        detail["why"] = culprit.why
    if culprit.internal:
        detail["internal"] = True
    return detail


def _fail(future: concurrent.futures.Future[Any], error: BaseException) -> None:
    try:
        future.set_exception(error)
    except concurrent.futures.InvalidStateError:
        pass  # it finished meanwhile
