"""A pybullet simulation stepped in lockstep with a :class:`~beehave.clock.VirtualClock`.

The simulation's time *is* the clock's: a stepping thread, one of the managers' workers for
the clock, waits one physics step of virtual time, steps, and waits again. So the clock
never moves past a step the physics has not taken, and the physics never runs ahead of the
behaviours — ``clock.advance(10.0)`` is ten simulated seconds of physics with every
``sleep`` of every behaviour in between, however slow the machine.
"""

from __future__ import annotations

import threading
from types import TracebackType
from typing import Any, Self

from beehave.clock import VirtualClock
from beehave.errors import ConfigError


class Lockstep:
    """Step ``sim`` (a :class:`robots.Simulation`, not started) in ``clock``'s time.

    Use it as a context manager; leaving it stops the stepping thread (the simulation
    stays open: its owner closes it). ``clock.now()`` and ``sim.time_s`` agree on entry,
    so start both at 0.
    """

    def __init__(self, sim: Any, clock: VirtualClock) -> None:
        if not isinstance(clock, VirtualClock):
            raise ConfigError(f"Lockstep needs a VirtualClock, got {clock!r}")
        if abs(sim.time_s - clock.now()) > sim.step_s:
            raise ConfigError(f"Lockstep: the simulation is at {sim.time_s:.3f} s and the clock "
                              f"at {clock.now():.3f} s; start both at the same time")
        self.sim = sim
        self.clock = clock
        self._cond = threading.Condition(threading.Lock())
        self._stopping = False
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def __enter__(self) -> Self:
        # Counted as a worker from now on, before the thread exists: a clock moved right
        # after this returns still waits for the first step.
        job = self.clock.track_job(self._run)
        self._thread = threading.Thread(target=job, name="sim-lockstep", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join()
        if self.error is not None and exc is None:
            raise self.error

    def _run(self) -> None:
        sim, clock = self.sim, self.clock
        try:
            while True:
                step_end = (sim.steps + 1) * sim.step_s
                with self._cond:
                    clock.wait(self._cond, lambda: self._stopping,
                               max(0.0, step_end - clock.now()))
                    if self._stopping:
                        return
                sim.step()
        except BaseException as exc:  # raised again when the block is left
            self.error = exc
