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

import heapq
import itertools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager


class WallClock:
    """Monotonic wall time."""

    def now(self) -> float:
        return time.monotonic()

    def wait(self, cond: threading.Condition, predicate: Callable[[], bool],
             timeout_s: float | None) -> bool:
        """With ``cond`` held: wait until ``predicate()`` or ``timeout_s`` passed (whoever
        changes what the predicate reads notifies ``cond``). Returns ``predicate()``."""
        return cond.wait_for(predicate, timeout_s)



class SimClock(WallClock):
    """Time from a simulation: :meth:`set_time` moves it (the ROS bridge calls it for every
    ``/clock`` message) and wakes the waits whose deadline passed. Before the first
    ``set_time`` it reads 0."""

    SLACK_S = 1e-6
    """A deadline this close counts as reached: ``/clock`` carries integer nanoseconds, so
    a deadline computed from one stamp never exactly equals a later stamp."""

    def __init__(self) -> None:
        self._now = 0.0
        self._lock = threading.Lock()
        self._waiters: list[tuple[float, int, threading.Condition]] = []
        self._ids = itertools.count()
        self._local = threading.local()

    def now(self) -> float:
        return self._now

    def set_time(self, t_s: float) -> None:
        with self._lock:
            self._now = max(self._now, t_s)
            due: list[threading.Condition] = []
            while self._waiters and self._waiters[0][0] <= self._now + self.SLACK_S:
                due.append(heapq.heappop(self._waiters)[2])
        for cond in due:
            with cond:
                cond.notify_all()

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
