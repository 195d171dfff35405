"""Clocks: how long ``sleep`` and timeouts last — wall time, or the simulation's time.

Behaviours and actions never call ``time.sleep``; ``self.sleep(s)`` and the waits of the
ROS helpers ask their manager's clock. :class:`WallClock` is the default; with
``use_sim_time`` the ROS bridge installs a :class:`SimClock` fed from ``/clock``, so a
``sleep(1.0)`` lasts one simulated second however fast the simulation runs.
``stop_timeout_s`` always stays wall time: a paused simulation must not stop a switch from
ending.

Lockstep. A simulator that runs faster than real time must not outrun the controllers that
follow its clock, or a 20 Hz control loop sees its robot jump 0.5 m between two looks.
:meth:`SimClock.announcing` tells a controller the exact sim time its next wait ends at,
so that it can ask the simulator to hold there until it has answered (see
``docs/simulation.md``, "Lockstep").
"""

from __future__ import annotations

import asyncio
import functools
import heapq
import itertools
import math
import selectors
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import Any

from beehave.errors import ClockNotSettled

Job = Callable[[], None]


class WallClock:
    """Monotonic wall time."""

    def now(self) -> float:
        return time.monotonic()

    def wait(self, cond: threading.Condition, predicate: Callable[[], bool],
             timeout_s: float | None) -> bool:
        """With ``cond`` held: wait until ``predicate()`` or ``timeout_s`` passed (whoever
        changes what the predicate reads notifies ``cond``). Returns ``predicate()``."""
        return cond.wait_for(predicate, timeout_s)

    # The managers tell their clock what their workers do; only a virtual clock listens
    # (it jumps when none of them can run). Here they cost nothing.
    def track_job(self, job: Job) -> Job:
        """A pool is about to run ``job`` in a worker thread: the returned callable runs it
        as one of the managers' workers."""
        return job

    def busy(self) -> AbstractContextManager[None]:
        """Inside the block the calling thread does the managers' work (a switch)."""
        return nullcontext()

    def blocked(self, predicate: Callable[[], bool]) -> AbstractContextManager[None]:
        """Inside the block the calling thread waits for something the managers deliver;
        ``predicate()`` turns true when it may go on (an event set, a child ended)."""
        return nullcontext()

    def free_running(self) -> AbstractContextManager[None]:
        """Inside the block time runs by itself (a virtual clock jumps): for shutdowns."""
        return nullcontext()



class SimClock(WallClock):
    """Time from a simulation: :meth:`set_time` moves it (the ROS bridge calls it for every
    ``/clock`` message) and wakes the waits whose deadline passed.

    Before the first ``set_time`` the clock has not *started*: it reads 0, which is no
    time of the simulation. Nothing should run on it then -- a behaviour started at 0 sees
    time jump to wherever the simulation already is, and a recording would carry a false
    time. :attr:`started` tells, :meth:`wait_started` waits for it (the robot does, before
    it starts its behaviours)."""

    SLACK_S = 1e-6
    """A deadline this close counts as reached: ``/clock`` carries integer nanoseconds, so
    a deadline computed from one stamp never exactly equals a later stamp."""

    def __init__(self) -> None:
        self._now = 0.0
        self._lock = threading.Lock()
        self._waiters: list[tuple[float, int, threading.Condition]] = []
        self._ids = itertools.count()
        self._local = threading.local()
        self._started = threading.Event()
        self._listeners: tuple[Callable[[float], None], ...] = ()

    def now(self) -> float:
        return self._now

    def on_set(self, callback: Callable[[float], None]) -> Callable[[], None]:
        """Call ``callback(now_s)`` after every :meth:`set_time`, in the thread that moved
        the clock (keep it short); returns the function that removes it. The recorder
        samples the clock with it (see :meth:`~beehave.recording.Recorder.attach_clock`)."""
        with self._lock:
            self._listeners = (*self._listeners, callback)

        def remove() -> None:
            with self._lock:
                self._listeners = tuple(c for c in self._listeners if c is not callback)
        return remove

    @property
    def started(self) -> bool:
        """Whether the simulation's time has reached this clock (a first ``set_time``)."""
        return self._started.is_set()

    def wait_started(self, timeout_s: float) -> bool:
        """Wait (wall time) up to ``timeout_s`` for the first ``set_time``; whether it came."""
        return self._started.wait(timeout_s)

    def _due_until(self) -> float:
        """Deadlines up to this time are reached (the replay's clock may hold some back)."""
        return self._now

    def set_time(self, t_s: float) -> None:
        with self._lock:
            self._now = max(self._now, t_s)
            self._started.set()
            due: list[threading.Condition] = []
            until = self._due_until() + self.SLACK_S
            while self._waiters and self._waiters[0][0] <= until:
                due.append(heapq.heappop(self._waiters)[2])
            now, listeners = self._now, self._listeners
        for cond in due:
            with cond:
                cond.notify_all()
        for listener in listeners:
            listener(now)

    @contextmanager
    def announcing(self, callback: Callable[[float], None]) -> Iterator[None]:
        """Within the block, every timed wait of *this thread* first calls
        ``callback(deadline_s)`` with the sim time it will wake at — computed once, so the
        simulator can be asked to hold exactly there (lockstep). ::

            with clock.announcing(lambda t: hold_sim_at(t)):
                self.sleep(0.05)
        """
        previous = getattr(self._local, "announce", None)
        self._local.announce = callback
        try:
            yield
        finally:
            self._local.announce = previous

    def wait(self, cond: threading.Condition, predicate: Callable[[], bool],
             timeout_s: float | None) -> bool:
        if timeout_s is None:
            return cond.wait_for(predicate)
        deadline = self._now + timeout_s
        entry = (deadline, next(self._ids), cond)
        with self._lock:
            heapq.heappush(self._waiters, entry)
        announce = getattr(self._local, "announce", None)
        try:
            if announce is not None and not predicate():
                # After registering: a /clock that reaches the deadline from now on wakes us.
                announce(deadline)
            while not predicate():
                if self._now + self.SLACK_S >= deadline:
                    return predicate()
                cond.wait()  # woken by set_time() past the deadline, or by the notifier
            return True
        finally:
            with self._lock:
                if entry in self._waiters:
                    self._waiters.remove(entry)
                    heapq.heapify(self._waiters)


class PausableClock(WallClock):
    """The clock behaviours and actions follow: the manager's clock with its pauses cut out.

    While :meth:`freeze` holds (``hl.pause()``), time stands still for them: :meth:`now`
    stays where it was, and every :meth:`wait` — a ``sleep``, an engine's tick, a ROS
    helper's timeout — blocks whatever its predicate says, and goes on with the time it
    had left after :meth:`thaw`. Safe states and the pause hooks run :meth:`unfrozen`
    (the hardware must get safe while paused). Everything else (``busy``, ``blocked``,
    ``announcing``, ``set_time`` …) is the manager's clock's own.
    """

    def __init__(self, base: WallClock) -> None:
        self.base = base
        self._lock = threading.Lock()
        self._since: float | None = None  # base time of the freeze, while frozen
        self._cut = 0.0  # base seconds spent frozen so far
        # Counts freezes: a waiter that did not run between a freeze and its thaw (a
        # starved thread, a short pause) still sees that one came and went.
        self._freezes = 0
        self._waiting: dict[threading.Condition, int] = {}
        self._local = threading.local()

    def __getattr__(self, name: str) -> Any:  # announcing, set_time, started …
        return getattr(self.base, name)

    # What the managers tell their clock goes to the manager's clock.
    def track_job(self, job: Job) -> Job:
        return self.base.track_job(job)

    def busy(self) -> AbstractContextManager[None]:
        return self.base.busy()

    def blocked(self, predicate: Callable[[], bool]) -> AbstractContextManager[None]:
        return self.base.blocked(predicate)

    def free_running(self) -> AbstractContextManager[None]:
        return self.base.free_running()

    @property
    def frozen(self) -> bool:
        return self._since is not None

    def now(self) -> float:
        with self._lock:
            since, cut = self._since, self._cut
        return (self.base.now() if since is None else since) - cut

    def freeze(self) -> None:
        with self._lock:
            if self._since is not None:
                return
            self._since = self.base.now()
            self._freezes += 1
            conds = list(self._waiting)
        _notify(conds)

    def frozen_for(self) -> float:
        """How long the current freeze has lasted (the base clock's seconds; 0 when not
        frozen)."""
        since = self._since
        return 0.0 if since is None else max(0.0, self.base.now() - since)

    def thaw(self) -> float:
        """End the freeze; returns how long it lasted (the base clock's seconds)."""
        with self._lock:
            if self._since is None:
                return 0.0
            lasted = max(0.0, self.base.now() - self._since)
            self._cut += lasted
            self._since = None
            conds = list(self._waiting)
        _notify(conds)
        return lasted

    @contextmanager
    def unfrozen(self) -> Iterator[None]:
        """Inside the block, the calling thread's waits run on the base clock, frozen or
        not (a safe state, an ``on_pause`` hook)."""
        self._local.depth = getattr(self._local, "depth", 0) + 1
        try:
            yield
        finally:
            self._local.depth -= 1

    def _woken(self, freezes: int, predicate: Callable[[], bool]) -> bool:
        """A running wait ends on a freeze after the ``freezes``-th, or on its predicate."""
        return self._freezes != freezes or predicate()

    def _running(self) -> bool:
        return self._since is None

    def wait(self, cond: threading.Condition, predicate: Callable[[], bool],
             timeout_s: float | None, *,
             frozen_escape: Callable[[], bool] | None = None) -> bool:
        """Like the base clock's ``wait``, in this clock's time. While frozen, time stands
        still: the wait ends only when ``frozen_escape()`` turns true (default: the
        predicate — an event still wakes a frozen sleep, only its time does not run; an
        engine passes "interrupted" alone, so that it decides nothing while paused)."""
        if getattr(self._local, "depth", 0):
            return self.base.wait(cond, predicate, timeout_s)
        escape = predicate if frozen_escape is None else frozen_escape
        deadline = None if timeout_s is None else self.now() + timeout_s
        remaining = timeout_s  # unchanged unless a freeze interrupts the wait (exact times)
        with self._lock:
            self._waiting[cond] = self._waiting.get(cond, 0) + 1
        try:
            while True:
                if self._since is not None:
                    if escape():
                        return predicate()
                    self.base.wait(cond, lambda: self._since is None or escape(), None)
                    if self._since is None and deadline is not None:
                        remaining = max(0.0, deadline - self.now())
                    continue
                if predicate():
                    return True
                if remaining is not None and remaining <= 0:
                    return False
                freezes = self._freezes
                self.base.wait(cond, functools.partial(self._woken, freezes, predicate),
                               remaining)
                if self._since is not None:
                    continue
                if predicate():
                    return True
                if self._freezes == freezes:
                    return False  # its time is up, no freeze meanwhile
                # A freeze came (and went, perhaps before this thread ran again): wait on
                # for the time left, from a new base deadline (announced again).
                if deadline is not None:
                    remaining = max(0.0, deadline - self.now())
        finally:
            with self._lock:
                left = self._waiting[cond] - 1
                if left:
                    self._waiting[cond] = left
                else:
                    del self._waiting[cond]


def _notify(conds: list[threading.Condition]) -> None:
    for cond in conds:
        with cond:
            cond.notify_all()


class _Worker:
    """What a virtual clock knows of one thread of the managers."""

    __slots__ = ("busy", "ready", "name")

    def __init__(self, name: str) -> None:
        self.busy = 0
        #: While the thread waits: a callable that tells whether it may go on (it is then
        #: runnable, about to wake). None while it runs.
        self.ready: Callable[[], bool] | None = None
        self.name = name


def _to_ns(seconds: float) -> int:
    return round(seconds * 1e9)


def _check_span(what: str, seconds: float) -> None:
    if isinstance(seconds, bool) or not isinstance(seconds, int | float) \
            or not (0 <= seconds < math.inf):
        raise ValueError(f"{what} takes a finite number of seconds >= 0, got {seconds!r}")


class VirtualClock(WallClock):
    """Time that moves only when a test moves it: the test kit's clock.

    Give it to the managers (``HighLevelBehaviorManager(clock=…)``,
    ``LowLevelBehaviorManager(clock=…)``); every ``sleep``, timeout, rate and deadline of
    behaviours, actions, engines, logics and HALs then follows it. Two ways to move it:

    * **by hand**: :meth:`advance` (``clock.advance(5.0)``) steps from one deadline to the
      next up to the target, and before each step waits until every worker of the managers
      is at rest (waiting): a loop that sleeps 1 s runs 600 times in ``advance(600)``, the
      same on an idle or a loaded machine. :meth:`run_until` steps until a condition holds.
    * **autojump** (``VirtualClock(autojump=True)``): whenever every worker is at rest, a
      thread of the clock jumps to the earliest deadline, so a 10-minute mission runs in
      milliseconds while the test simply waits for its outcome.

    At rest means: every thread the managers run (the worker pool's, a switch in progress,
    the low level's event loop) waits on this clock or on another worker, and none of those
    waits is already satisfied. What the managers wait for from outside (a ROS message from
    another process) is not known to the clock: for those, drive a simulation in lockstep
    with :class:`SimClock` instead. ``stop_timeout_s`` stays wall time, as everywhere.
    """

    #: Time and deadlines are whole nanoseconds here, exactly (as ``/clock`` is), so that
    #: ``sleep(0.01)`` two hundred times ends at 2.0 s, not at 2.0000000000000013 s.
    SLACK_S = 0.0
    #: How long (wall time) :meth:`advance` waits for the workers to come to rest before it
    #: raises :class:`ClockNotSettled`.
    SETTLE_TIMEOUT_S = 10.0

    def __init__(self, start_s: float = 0.0, *, autojump: bool = False) -> None:
        self._ns = _to_ns(start_s)
        self._now = self._ns / 1e9
        self._changed = threading.Condition(threading.Lock())
        self._timed: list[tuple[int, int, threading.Condition]] = []  # (deadline ns, …)
        self._ids = itertools.count()
        self._workers: dict[int, _Worker] = {}
        self._queued = 0  # jobs handed to a pool whose thread has not yet taken them
        self._loops: list[_VirtualLoop] = []
        self._jumper: threading.Thread | None = None
        self._autojump = False
        self._free_running = 0
        #: How many deadlines the clock has stepped to (by hand or by autojump).
        self.jumps = 0
        if autojump:
            self.autojump = True

    # -------------------------------------------------------------------- reading
    def now(self) -> float:
        return self._now

    def __call__(self) -> float:
        """The clock as a plain time function (``Blackboard(clock=virtual_clock)``)."""
        return self._now

    def __repr__(self) -> str:
        return (f"<VirtualClock t={self._now:.6f} s{' autojump' if self._autojump else ''} "
                f"workers={len(self._workers)}>")

    # -------------------------------------------------------------------- waiting
    def wait(self, cond: threading.Condition, predicate: Callable[[], bool],
             timeout_s: float | None) -> bool:
        deadline: int | None = None
        if timeout_s is not None:
            # A positive wait lasts at least a nanosecond: one of 1e-17 s (the float rest of
            # a tick) would otherwise end at once, and its caller wait again at that instant.
            deadline = self._ns + max(_to_ns(timeout_s), 1 if timeout_s > 0 else 0)
        entry = None if deadline is None else (deadline, next(self._ids), cond)

        def ready() -> bool:
            return predicate() or (deadline is not None and self._ns >= deadline)

        with self._changed:
            if entry is not None:
                heapq.heappush(self._timed, entry)
            worker = self._workers.get(threading.get_ident())
            previous = None
            if worker is not None:
                previous, worker.ready = worker.ready, ready
            self._changed.notify_all()
        try:
            while not predicate():
                if deadline is not None and self._ns >= deadline:
                    return predicate()
                cond.wait()  # woken by _set past the deadline, or by whoever notifies cond
            return True
        finally:
            with self._changed:
                if entry is not None and entry in self._timed:
                    self._timed.remove(entry)
                    heapq.heapify(self._timed)
                if worker is not None:
                    worker.ready = previous
                self._changed.notify_all()

    def sleep(self, seconds: float) -> None:
        """Block the calling thread for ``seconds`` of virtual time (a test thread: with
        autojump, the clock moves there by itself; by hand, another thread must advance)."""
        _check_span("sleep(seconds)", seconds)
        cond = threading.Condition()
        with cond:
            self.wait(cond, lambda: False, seconds)

    # -------------------------------------------------------------------- who runs
    def track_job(self, job: Job) -> Job:
        with self._changed:
            self._queued += 1

        def tracked() -> None:
            me = threading.get_ident()
            with self._changed:
                self._queued -= 1
                worker = self._workers.setdefault(me, _Worker(threading.current_thread().name))
                worker.busy += 1
            try:
                job()
            finally:
                self._leave(me)
        return tracked

    @contextmanager
    def busy(self) -> Iterator[None]:
        me = threading.get_ident()
        with self._changed:
            worker = self._workers.setdefault(me, _Worker(threading.current_thread().name))
            worker.busy += 1
        try:
            yield
        finally:
            self._leave(me)

    def _leave(self, ident: int) -> None:
        with self._changed:
            worker = self._workers[ident]
            worker.busy -= 1
            if worker.busy == 0:
                del self._workers[ident]
            self._changed.notify_all()

    @contextmanager
    def blocked(self, predicate: Callable[[], bool]) -> Iterator[None]:
        with self._changed:
            worker = self._workers.get(threading.get_ident())
            previous = None
            if worker is not None:
                previous, worker.ready = worker.ready, predicate
                self._changed.notify_all()
        try:
            yield
        finally:
            if worker is not None:
                with self._changed:
                    worker.ready = previous
                    self._changed.notify_all()

    def _running_locked(self) -> list[str]:
        """The workers that can run now (empty: at rest). Called with ``_changed`` held."""
        running = [f"{self._queued} job(s) not yet taken by a worker"] if self._queued else []
        for worker in self._workers.values():
            ready = worker.ready
            try:
                if ready is None or ready():
                    running.append(worker.name)
            except Exception:  # a predicate that cannot be read yet: assume it may run
                running.append(worker.name)
        for loop in self._loops:
            if not loop._at_rest(self._ns):
                running.append(f"event loop {loop.name}")
        return running

    def _next_deadline_locked(self) -> int | None:
        """The earliest deadline after now (ns)."""
        now = self._ns
        deadlines = [d for d, _, _ in self._timed if d > now]
        deadlines += [d for loop in self._loops
                      if (d := loop._deadline) is not None and d > now]
        return min(deadlines, default=None)

    @property
    def at_rest(self) -> bool:
        """True when no worker of the managers can run until time moves."""
        with self._changed:
            return not self._running_locked()

    @property
    def next_deadline(self) -> float | None:
        """The earliest time something waits for (None: nothing waits for time)."""
        with self._changed:
            step = self._next_deadline_locked()
        return None if step is None else step / 1e9

    # -------------------------------------------------------------------- moving time
    def _set(self, t_ns: int) -> None:
        with self._changed:
            if t_ns <= self._ns:
                return
            self._ns = t_ns
            self._now = t_ns / 1e9
            self.jumps += 1
            due: list[threading.Condition] = []
            while self._timed and self._timed[0][0] <= t_ns:
                due.append(heapq.heappop(self._timed)[2])
            loops = [loop for loop in self._loops
                     if loop._deadline is not None and loop._deadline <= t_ns]
            self._changed.notify_all()
        for cond in due:
            with cond:
                cond.notify_all()
        for loop in loops:
            loop._wake()

    def settle(self, *, timeout_s: float | None = None) -> None:
        """Wait (wall time) until every worker is at rest; :class:`ClockNotSettled` naming
        the ones still running after ``timeout_s`` (default :attr:`SETTLE_TIMEOUT_S`)."""
        limit = self.SETTLE_TIMEOUT_S if timeout_s is None else timeout_s
        give_up = time.monotonic() + limit
        with self._changed:
            while running := self._running_locked():
                remaining = give_up - time.monotonic()
                if remaining <= 0:
                    raise ClockNotSettled(
                        f"virtual clock at t={self._now:.3f} s: after {limit:.1f} s (wall) "
                        f"these still run instead of waiting: {', '.join(running)} — a loop "
                        f"that never sleeps, or a wait that does not go through the clock")
                # Predicates change without telling the clock (an interrupt flag, an event
                # set by another worker): look again soon.
                self._changed.wait(min(remaining, 0.0005))

    def advance(self, seconds: float) -> float:
        """Move time ``seconds`` forward, deadline by deadline, letting every worker run
        until it waits again before each step; returns the new time. With autojump on,
        the calling thread sleeps ``seconds`` of virtual time instead."""
        _check_span("advance(seconds)", seconds)
        if self._autojump:
            self.sleep(seconds)
            return self._now
        target = self._ns + _to_ns(seconds)
        while True:
            self.settle()
            with self._changed:
                step = self._next_deadline_locked()
            if step is None or step > target:
                break
            self._set(step)
        self._set(target)
        self.settle()
        return self._now

    def run_until(self, predicate: Callable[[], bool], *, timeout_s: float) -> bool:
        """Move time deadline by deadline until ``predicate()`` holds (checked whenever the
        workers are at rest) or ``timeout_s`` of virtual time passed; returns
        ``predicate()``. The deterministic way to wait for an outcome::

            assert clock.run_until(lambda: hl.current == "idle", timeout_s=600)
        """
        _check_span("run_until(timeout_s=…)", timeout_s)
        end = self._ns + _to_ns(timeout_s)
        if self._autojump:
            give_up = time.monotonic() + self.SETTLE_TIMEOUT_S
            cond = threading.Condition()
            with cond:
                # Registered as a timed waiter at `end`, polled for the predicate.
                entry = (end, next(self._ids), cond)
                with self._changed:
                    heapq.heappush(self._timed, entry)
                try:
                    while not predicate() and self._ns < end:
                        last = self.jumps
                        cond.wait(0.001)
                        if self.jumps != last:
                            give_up = time.monotonic() + self.SETTLE_TIMEOUT_S
                        elif time.monotonic() > give_up:
                            self.settle(timeout_s=0.0)  # names who keeps time from moving
                finally:
                    with self._changed:
                        if entry in self._timed:
                            self._timed.remove(entry)
                            heapq.heapify(self._timed)
            return predicate()
        while True:
            self.settle()
            if predicate():
                return True
            with self._changed:
                step = self._next_deadline_locked()
            if step is None or step > end:
                self._set(end)
                self.settle()
                return predicate()
            self._set(step)

    # -------------------------------------------------------------------- autojump
    @property
    def autojump(self) -> bool:
        """Jump to the next deadline by itself whenever every worker is at rest."""
        return self._autojump

    @autojump.setter
    def autojump(self, on: bool) -> None:
        with self._changed:
            self._autojump = bool(on)
        self._run_jumper()

    def _run_jumper(self) -> None:
        """Start the jumping thread when someone wants jumps, join it when nobody does."""
        with self._changed:
            wanted = self._autojump or self._free_running > 0
            jumper = self._jumper
            if wanted and jumper is None:
                jumper = self._jumper = threading.Thread(
                    target=self._jump_loop, daemon=True, name="beehave-clock-autojump")
                jumper.start()
                return
            if not wanted:
                self._jumper = None
            self._changed.notify_all()
        if not wanted and jumper is not None and jumper is not threading.current_thread():
            jumper.join()

    @contextmanager
    def free_running(self) -> Iterator[None]:
        """Autojump inside the block, whatever :attr:`autojump` says. The managers'
        ``shutdown`` uses it: safe states and unloads that sleep or time out on this clock
        must end, even when the test moves time by hand."""
        with self._changed:
            self._free_running += 1
        self._run_jumper()
        try:
            yield
        finally:
            with self._changed:
                self._free_running -= 1
            self._run_jumper()

    def close(self) -> None:
        """Stop autojumping (joins the clock's thread)."""
        self.autojump = False

    def _jump_loop(self) -> None:
        while True:
            with self._changed:
                if self._jumper is not threading.current_thread():
                    return
                step = None if self._running_locked() else self._next_deadline_locked()
                if step is None:
                    self._changed.wait(0.0005)
                    continue
            self._set(step)

    # -------------------------------------------------------------------- asyncio
    def new_event_loop(self) -> asyncio.AbstractEventLoop:
        """An asyncio loop whose time is this clock: ``asyncio.sleep``, ``wait_for`` and
        ``call_later`` follow it, and the clock knows when the loop is at rest."""
        return _VirtualLoop(self)

    def _add_loop(self, loop: _VirtualLoop) -> None:
        with self._changed:
            self._loops.append(loop)
            self._changed.notify_all()

    def _remove_loop(self, loop: _VirtualLoop) -> None:
        with self._changed:
            if loop in self._loops:
                self._loops.remove(loop)
            self._changed.notify_all()

    def _loop_state(self, loop: _VirtualLoop, idle: bool, deadline_s: float | None) -> None:
        with self._changed:
            loop._idle = idle
            # asyncio's timers are floats: the step lands on the nearest nanosecond, within
            # the loop's clock resolution (1 ns), so the timer is due there.
            loop._deadline = None if deadline_s is None or not idle else _to_ns(deadline_s)
            self._changed.notify_all()


_FileObject = int | Any  # what selectors accept: a file descriptor or an object with fileno()


class _ClockedSelector(selectors.BaseSelector):
    """The loop's selector, telling the clock when the loop waits and for which deadline."""

    def __init__(self, clock: VirtualClock) -> None:
        self._inner = selectors.DefaultSelector()
        self._clock = clock
        self.loop: _VirtualLoop | None = None

    def register(self, fileobj: _FileObject, events: int,
                 data: object = None) -> selectors.SelectorKey:
        return self._inner.register(fileobj, events, data)

    def unregister(self, fileobj: _FileObject) -> selectors.SelectorKey:
        return self._inner.unregister(fileobj)

    def modify(self, fileobj: _FileObject, events: int,
               data: object = None) -> selectors.SelectorKey:
        return self._inner.modify(fileobj, events, data)

    def get_map(self) -> Mapping[_FileObject, selectors.SelectorKey]:
        return self._inner.get_map()

    def close(self) -> None:
        self._inner.close()

    def select(self, timeout: float | None = None
               ) -> list[tuple[selectors.SelectorKey, int]]:
        loop = self.loop
        if loop is None or (timeout is not None and timeout <= 0):
            return self._inner.select(timeout)
        # asyncio asks to sleep until its earliest timer (virtual seconds from now): it is
        # at rest until that deadline or an I/O event; the clock wakes it past the deadline.
        deadline = None if timeout is None else self._clock.now() + timeout
        self._clock._loop_state(loop, True, deadline)
        due = loop._deadline
        try:
            while True:
                events = self._inner.select(0.25)
                if events or (due is not None and self._clock._ns >= due):
                    return events
                if loop._ready:  # type: ignore[attr-defined]
                    return events
        finally:
            self._clock._loop_state(loop, False, None)


class _VirtualLoop(asyncio.SelectorEventLoop):
    """asyncio's loop with a virtual time (uvloop keeps its own time in C)."""

    def __init__(self, clock: VirtualClock) -> None:
        selector = _ClockedSelector(clock)
        super().__init__(selector)
        selector.loop = self
        self._clock = clock
        self._idle = False
        self._deadline: int | None = None  # ns, while idle
        self.name = f"loop@{id(self):x}"
        clock._add_loop(self)

    def time(self) -> float:
        return self._clock.now()

    def _at_rest(self, now: int) -> bool:
        return (self._idle and not self._ready  # type: ignore[attr-defined]
                and (self._deadline is None or self._deadline > now))

    def _wake(self) -> None:
        try:
            self.call_soon_threadsafe(lambda: None)
        except RuntimeError:  # closed
            pass

    def close(self) -> None:
        self._clock._remove_loop(self)
        super().close()
