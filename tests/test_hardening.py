"""Contract edges found in review: races around wait(), hooks that raise, clean-ups that
hang, interrupts from outside a switch, retries after a refused start."""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import pytest

from beehave import (
    Action,
    ActionTypeBusy,
    Behavior,
    Event,
    EventKind,
    HighLevelBehaviorManager,
    Status,
)
from beehave.testing import WALL_TIMEOUT_S, ScriptedAction, wait_until, wall_timeout


class Body(Behavior):
    def __init__(self, body: Any) -> None:
        self.body = body

    def run(self) -> Any:
        return self.body(self)


def run_top(hl: HighLevelBehaviorManager, body: Any) -> Behavior:
    hl.register("body", Body)
    return hl.switch("body", body=body)


def test_waiting_for_a_failed_child_never_raises_it_later(hl: HighLevelBehaviorManager) -> None:
    def slow_observer(event: Event) -> None:
        if event.kind is EventKind.ENDED and event.status == "FAILED":
            time.sleep(0.02)  # widens the gap between the outcome and the bookkeeping

    hl.subscribe(slow_observer)

    def body(b: Behavior) -> str:
        for _ in range(5):
            failing = b.start_action(ScriptedAction("x", raises=ValueError("boom")))
            failing.wait()
            b.sleep(0.03)  # must not raise ChildFailed: we saw the outcome
        return "ok"

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert top.status is Status.SUCCEEDED, top.error


@pytest.mark.parametrize("hook_s", [0.0, 0.2])
def test_a_raising_on_interrupt_does_not_break_the_switch(hl: HighLevelBehaviorManager,
                                                          events: list[Event],
                                                          hook_s: float) -> None:
    """The hook's error decides the status, however long the hook takes before it raises:
    the behaviour's own thread is woken after it (woken first, it ended INTERRUPTED while a
    loaded machine's hook had not yet raised; a stress run)."""
    class Fragile(Behavior):
        def on_interrupt(self) -> None:
            time.sleep(hook_s)  # within conftest's 0.3 s stop timeout
            raise RuntimeError("hook bug")

        def run(self) -> None:
            while self.sleep(10):
                pass

    hl.register("fragile", Fragile)
    fragile = hl.switch("fragile")
    assert hl.switch("idle").status is Status.RUNNING
    assert hl.current == "idle"
    assert fragile.status is Status.FAILED and "hook bug" in str(fragile.error)
    assert any(e.kind is EventKind.HOOK_FAILED and e.detail["hook"] == "on_interrupt"
               for e in events)


def test_a_raising_on_child_ended_is_surfaced_in_the_behaviour(
        hl: HighLevelBehaviorManager) -> None:
    class Picky(Behavior):
        def on_child_ended(self, child: Any) -> None:
            raise KeyError("hook bug")

        def run(self) -> None:
            self.start_action(ScriptedAction("x")).wait()
            while self.sleep(10):
                pass

    hl.register("picky", Picky)
    picky = hl.switch("picky")
    assert picky.wait(WALL_TIMEOUT_S)
    assert picky.status is Status.FAILED and isinstance(picky.error, KeyError)
    assert hl.snapshot()["stuck"] == []


def test_a_top_level_behaviour_interrupted_from_outside_falls_back_to_idle(
        hl: HighLevelBehaviorManager) -> None:
    class Patrol(Behavior):
        def run(self) -> None:
            while self.sleep(10):
                pass

    hl.register("patrol", Patrol)
    patrol = hl.switch("patrol")
    patrol.interrupt()  # not a switch: somebody stopped it directly
    assert wait_until(lambda: hl.current == "idle")
    assert patrol.status is Status.INTERRUPTED


def test_a_hanging_safe_state_becomes_stuck_and_does_not_block_the_switch(
        hl: HighLevelBehaviorManager) -> None:
    release = threading.Event()
    calls: list[str] = []

    class Hangs(Action):
        action_type = "driving"

        def run(self) -> None:
            while self.sleep(10):
                pass

        def safe_state(self) -> None:
            calls.append("safe")
            release.wait(WALL_TIMEOUT_S)  # e.g. a service call to a dead driver

    holder: list[Action] = []

    def body(b: Behavior) -> None:
        holder.append(b.start_action(Hangs()))
        while b.sleep(10):
            pass

    run_top(hl, body)
    assert wait_until(lambda: bool(holder))
    t0 = time.monotonic()
    hl.switch("idle")
    assert time.monotonic() - t0 < hl.stop_timeout_s + wall_timeout(0.05)  # not for ever
    action = holder[0]
    assert action.status is Status.STUCK and calls == ["safe"]
    assert hl.snapshot()["locks"]["driving"]["status"] == "STUCK"
    release.set()
    assert wait_until(lambda: not action.alive)
    assert calls == ["safe"]  # exactly once
    assert "driving" not in hl.snapshot()["locks"] and hl.snapshot()["stuck"] == []


def test_an_action_refused_for_a_busy_type_can_be_started_again(
        hl: HighLevelBehaviorManager) -> None:
    def body(b: Behavior) -> Status:
        first = b.start_action(ScriptedAction("lift", duration_s=WALL_TIMEOUT_S))
        again = ScriptedAction("lift")
        with pytest.raises(ActionTypeBusy):
            b.start_action(again)
        first.interrupt()  # (the lock was held for sure while `again` was refused)
        first.wait()
        b.start_action(again).wait()  # the same object, now that the type is free
        return again.status

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S) and top.result is Status.SUCCEEDED


def test_a_free_type_promised_to_an_earlier_preemptor_is_refused_cleanly(
        hl: HighLevelBehaviorManager) -> None:
    ahead = ScriptedAction("docking", name="ahead")
    late = ScriptedAction("docking", name="late")
    locks = hl._locks
    locks._queues["docking"] = deque([ahead])  # a preemptor was woken but has not run yet
    with pytest.raises(ActionTypeBusy, match="waiting to preempt"):
        locks.acquire(late, preempt=True, timeout_s=0.02, cancelled=lambda: False)
    assert list(locks._queues["docking"]) == [ahead]
