"""Action contract: result, failure, interrupts, safe_state exactly once, type defaults."""

from __future__ import annotations

import threading
import time

import pytest

from beehave import Action, AlreadyStarted, Behavior, HighLevelBehaviorManager, Status
from beehave.testing import WALL_TIMEOUT_S, ScriptedAction, wall_timeout


class Host(Behavior):
    """A top-level behaviour that starts what the test gives it, then waits."""

    def __init__(self, todo: list[Action], started: threading.Event) -> None:
        self.todo = todo
        self.started = started

    def run(self) -> None:
        for action in self.todo:
            self.start_action(action)
        self.started.set()
        while self.sleep(10):
            pass


def host(hl: HighLevelBehaviorManager, *actions: Action) -> Behavior:
    started = threading.Event()
    hl.register("host", Host)
    top = hl.switch("host", todo=list(actions), started=started)
    assert started.wait(WALL_TIMEOUT_S)
    return top


def test_success_sets_result_and_skips_safe_state(hl: HighLevelBehaviorManager) -> None:
    action = ScriptedAction(result=42)
    host(hl, action)
    assert action.wait(WALL_TIMEOUT_S)
    assert action.status is Status.SUCCEEDED
    assert action.result == 42 and action.error is None
    assert action.safe_state_calls == 0


def test_exception_fails_with_error_and_traceback(hl: HighLevelBehaviorManager) -> None:
    boom = RuntimeError("motor driver offline")
    action = ScriptedAction(raises=boom)
    top = host(hl, action)
    assert action.wait(WALL_TIMEOUT_S)
    assert action.status is Status.FAILED
    assert action.error is boom and boom.__traceback__ is not None
    assert "motor driver offline" in action._traceback
    assert action.safe_state_calls == 1
    top.interrupt()


def test_interrupt_wakes_sleep_at_once_and_calls_safe_state_once(
        hl: HighLevelBehaviorManager) -> None:
    action = ScriptedAction(duration_s=30)
    host(hl, action)
    t0 = time.monotonic()
    action.interrupt()
    action.interrupt()  # idempotent
    assert action.wait(WALL_TIMEOUT_S)
    assert time.monotonic() - t0 < wall_timeout(0.25)  # below the 30 s sleep: woken
    assert action.status is Status.INTERRUPTED
    assert action.safe_state_calls == 1


def test_sleep_returns_true_when_not_interrupted(hl: HighLevelBehaviorManager) -> None:
    seen: list[bool] = []

    class Nap(Action):
        def run(self) -> None:
            seen.append(self.sleep(0.01))

    action = Nap()
    host(hl, action)
    assert action.wait(WALL_TIMEOUT_S)
    assert seen == [True]


def test_action_type_defaults_to_class_name_and_is_inherited() -> None:
    class Beep(Action):
        def run(self) -> None: ...

    class LoudBeep(Beep):
        pass

    class Drive(Action):
        action_type = "driving"

        def run(self) -> None: ...

    class FastDrive(Drive):
        pass

    assert Beep.action_type == "Beep"
    assert LoudBeep.action_type == "Beep"
    assert FastDrive.action_type == "driving"


def test_non_string_action_type_is_rejected() -> None:
    with pytest.raises(TypeError, match="action_type must be a str"):
        class Bad(Action):
            action_type = 3  # type: ignore[assignment]

            def run(self) -> None: ...


def test_run_is_the_one_abstract_method() -> None:
    class NoRun(Action):
        pass

    with pytest.raises(TypeError, match="run"):
        NoRun()  # type: ignore[abstract]


def test_subclass_need_not_call_super_init(hl: HighLevelBehaviorManager) -> None:
    class Lift(Action):
        action_type = "lifting"

        def __init__(self, height_m: float) -> None:
            self.height_m = height_m  # no super().__init__()

        def run(self) -> float:
            return self.height_m

    action = Lift(0.2)
    host(hl, action)
    assert action.wait(WALL_TIMEOUT_S)
    assert action.result == 0.2 and action.status is Status.SUCCEEDED


def test_an_action_object_runs_once(hl: HighLevelBehaviorManager) -> None:
    action = ScriptedAction()
    top = host(hl, action)
    assert action.wait(WALL_TIMEOUT_S)
    with pytest.raises(AlreadyStarted, match="create a new object"):
        top.start_action(action)


def test_safe_state_error_is_recorded_not_dropped(hl: HighLevelBehaviorManager, events) -> None:  # type: ignore[no-untyped-def]
    class Clumsy(ScriptedAction):
        def safe_state(self) -> None:
            raise OSError("brake relay stuck")

    action = Clumsy(duration_s=30)
    host(hl, action)
    action.interrupt()
    assert action.wait(WALL_TIMEOUT_S)
    assert isinstance(action.safe_state_error, OSError)
    assert any(e.kind.value == "safe_state_failed" and e.error is action.safe_state_error
               for e in events)


def test_a_safe_state_that_ran_is_an_event_and_success_has_none(
        hl: HighLevelBehaviorManager, events) -> None:  # type: ignore[no-untyped-def]
    done = ScriptedAction("first", result=1)
    stopped = ScriptedAction("other", duration_s=30)
    failed = ScriptedAction("third", raises=RuntimeError("wheel"))
    host(hl, done, stopped, failed)
    assert done.wait(WALL_TIMEOUT_S) and failed.wait(WALL_TIMEOUT_S)
    stopped.interrupt()
    assert stopped.wait(WALL_TIMEOUT_S)
    ran = [e for e in list(events) if e.kind.value == "safe_state_ran"]
    assert sorted((e.subject, e.status) for e in ran) == sorted(
        [(stopped.path, "INTERRUPTED"), (failed.path, "FAILED")])
    assert all(e.detail["took_s"] >= 0 and "action_type" in e.detail for e in ran)
    # Before the action's end, in the order it happened: the safe state, then "ended".
    kinds = [e.kind.value for e in list(events) if e.subject == stopped.path]
    assert kinds.index("safe_state_ran") < kinds.index("ended"), kinds
