"""Clocks: sleep follows simulated time when the manager has a SimClock."""

from __future__ import annotations

import threading

from beehave import Behavior, HighLevelBehaviorManager, Status
from beehave.clock import SimClock
from beehave.testing import WALL_TIMEOUT_S, wait_until

# A negative check (still asleep) runs to its end: short on purpose; a loaded machine can only
# make it miss a wrong wake-up, never fail a right clock.
ASLEEP_S = 0.05


def test_sleep_follows_sim_time() -> None:
    clock = SimClock()
    woke = threading.Event()
    entered = threading.Event()

    class Nap(Behavior):
        def run(self) -> bool:
            entered.set()
            ok = self.sleep(10.0)  # ten simulated seconds
            woke.set()
            return ok

    with HighLevelBehaviorManager(clock=clock, stop_timeout_s=0.5) as hl:
        hl.register("nap", Nap)
        nap = hl.switch("nap")
        assert entered.wait(WALL_TIMEOUT_S)
        clock.set_time(5.0)
        assert not woke.wait(ASLEEP_S)  # half-way in sim time: still asleep
        clock.set_time(10.5)
        assert woke.wait(WALL_TIMEOUT_S)
        assert nap.wait(WALL_TIMEOUT_S) and nap.result is True and nap.status is Status.SUCCEEDED


def test_interrupt_wakes_a_sim_time_sleep_when_the_clock_stands_still() -> None:
    clock = SimClock()  # never advanced: a paused simulation
    entered = threading.Event()

    class Nap(Behavior):
        def run(self) -> None:
            entered.set()
            self.sleep(10.0)

    with HighLevelBehaviorManager(clock=clock, stop_timeout_s=0.5) as hl:
        hl.register("nap", Nap)
        nap = hl.switch("nap")
        assert entered.wait(WALL_TIMEOUT_S)
        hl.switch("idle")  # stop_timeout_s is wall time: a paused sim cannot block it
        # Woken within stop_timeout_s (else it would be STUCK), in wall time.
        assert nap.status is Status.INTERRUPTED


def test_a_pause_its_sleeper_never_saw_still_counts_and_is_announced_again() -> None:
    """A starved thread may not run between a freeze and its thaw (a short pause on a
    loaded machine): its sleep must still go on for the time it had left, from a new
    deadline that a lockstep simulator hears about (seen on CI: the simulation held at the
    old deadline, the behaviour woke 0.5 s early in its own time)."""
    from beehave.clock import PausableClock

    base = SimClock()
    base.set_time(10.0)
    clock = PausableClock(base)
    cond = threading.Condition()
    announced: list[float] = []
    result: list[bool] = []

    def sleeper() -> None:
        with base.announcing(announced.append), cond:
            result.append(clock.wait(cond, lambda: False, 1.0))

    thread = threading.Thread(target=sleeper, daemon=True)
    thread.start()
    assert wait_until(lambda: announced == [11.0]), announced
    with cond:  # the sleeper cannot run until the pause is over
        clock.freeze()
        base.set_time(10.5)
        clock.thaw()
    assert wait_until(lambda: announced != [11.0])
    assert announced == [11.0, 11.5]
    base.set_time(11.2)
    thread.join(0.05)
    assert thread.is_alive() and clock.now() == 10.7  # 0.3 s left of its own time
    base.set_time(11.5)
    thread.join(WALL_TIMEOUT_S)
    assert result == [False] and clock.now() == 11.0
