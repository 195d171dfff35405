"""Type locks: one action per type across all behaviours; reject and preempt policies."""

from __future__ import annotations

import threading
import time

import pytest

from beehave import Action, ActionTypeBusy, Behavior, HighLevelBehaviorManager, Status
from beehave.testing import WALL_TIMEOUT_S, ScriptedAction, Timeline, wait_until, wall_timeout


class Parallel(Behavior):
    """Runs two sub-behaviours that each hold on until interrupted."""

    def __init__(self, ready: threading.Event) -> None:
        self.ready = ready

    def run(self) -> None:
        self.left = self.start_behavior(Holder())
        self.right = self.start_behavior(Holder())
        self.ready.set()
        while self.sleep(10):
            pass


class Holder(Behavior):
    def run(self) -> None:
        while self.sleep(10):
            pass


@pytest.fixture
def two(hl: HighLevelBehaviorManager) -> Parallel:
    ready = threading.Event()
    hl.register("parallel", Parallel)
    top = hl.switch("parallel", ready=ready)
    assert ready.wait(WALL_TIMEOUT_S)
    return top  # type: ignore[return-value]


def test_busy_type_is_rejected_across_behaviours(two: Parallel) -> None:
    drive = two.left.start_action(ScriptedAction("driving", duration_s=30, name="nav"))
    with pytest.raises(ActionTypeBusy) as info:
        two.right.start_action(ScriptedAction("driving", name="lane"))
    err = info.value
    assert err.action_type == "driving" and err.holder is drive
    text = str(err)
    assert "'driving'" in text and "ScriptedAction" in text and "'nav'" in text
    assert "behavior 'Holder'" in text and " s" in text  # holder, owner and since when
    # Another type runs beside it.
    sound = two.right.start_action(ScriptedAction("sound", duration_s=30))
    assert sound.status is Status.RUNNING and drive.status is Status.RUNNING


def test_lock_is_free_after_the_holder_ends(two: Parallel) -> None:
    first = two.left.start_action(ScriptedAction("lifting"))
    assert first.wait(WALL_TIMEOUT_S)
    second = two.right.start_action(ScriptedAction("lifting", duration_s=30))
    assert second.status is Status.RUNNING


def test_preempt_waits_for_the_holders_safe_state(two: Parallel) -> None:
    timeline = Timeline()
    old = two.left.start_action(ScriptedAction("driving", duration_s=30, timeline=timeline,
                                               name="old"))
    new = two.right.start_action(ScriptedAction("driving", duration_s=30, timeline=timeline,
                                                name="new"), preempt=True)
    assert old.status is Status.INTERRUPTED and old.safe_state_calls == 1
    assert new.status is Status.RUNNING
    (safe_done,) = timeline.times("safe", old.path)
    assert wait_until(lambda: timeline.times("run", new.path))
    (new_run,) = timeline.times("run", new.path)
    assert safe_done <= new_run
    assert timeline.max_concurrent["driving"] == 1


def test_no_third_action_slips_in_while_preempting(
        two: Parallel, hl: HighLevelBehaviorManager) -> None:
    """The holder takes a while to stop; meanwhile a plain start must be rejected."""
    # The holder's 0.15 s must end within the stop timeout, also when its thread runs late.
    hl.stop_timeout_s = wall_timeout(0.05)
    slow = two.left.start_action(ScriptedAction("driving", duration_s=30,
                                                ignore_interrupt_s=0.15))
    result: list[Action] = []
    preempter = threading.Thread(target=lambda: result.append(
        two.right.start_action(ScriptedAction("driving", duration_s=30), preempt=True)))
    preempter.start()
    assert wait_until(lambda: slow.interrupted)
    with pytest.raises(ActionTypeBusy):
        two.left.start_action(ScriptedAction("driving"))
    preempter.join(WALL_TIMEOUT_S)
    assert result and result[0].status is Status.RUNNING
    assert slow.status is Status.INTERRUPTED


def test_preempting_a_holder_that_ignores_its_interrupt(two: Parallel, hl) -> None:  # type: ignore[no-untyped-def]
    stubborn = two.left.start_action(ScriptedAction("driving", duration_s=30,
                                                    ignore_interrupt_s=float("inf")))
    t0 = time.monotonic()
    with pytest.raises(ActionTypeBusy, match="STUCK"):
        two.right.start_action(ScriptedAction("driving"), preempt=True)
    assert time.monotonic() - t0 < hl.stop_timeout_s + wall_timeout(0.05)  # not for ever
    assert stubborn.status is Status.STUCK and stubborn.safe_state_calls == 1
    # The STUCK action keeps its type until its thread really ends …
    with pytest.raises(ActionTypeBusy, match="STUCK"):
        two.right.start_action(ScriptedAction("driving"), preempt=True)
    assert hl.snapshot()["locks"]["driving"]["status"] == "STUCK"
    stubborn.release.set()
    assert stubborn._join(2)
    # … then it is free, and the safe state was not called a second time.
    two.right.start_action(ScriptedAction("driving"))
    assert stubborn.safe_state_calls == 1 and stubborn.status is Status.STUCK


def test_lock_events(two: Parallel, events) -> None:  # type: ignore[no-untyped-def]
    two.left.start_action(ScriptedAction("sound", duration_s=30))
    with pytest.raises(ActionTypeBusy):
        two.right.start_action(ScriptedAction("sound"))
    two.right.start_action(ScriptedAction("sound"), preempt=True)
    kinds = [e.kind.value for e in events]
    assert "lock_rejected" in kinds and "lock_preempted" in kinds
