"""Behaviour contract: children never outlive it, interrupts go down first, failures go up."""

from __future__ import annotations

import threading
from typing import Any

from beehave import (
    Behavior,
    ChildFailed,
    HighLevelBehaviorManager,
    Interrupted,
    NotASubclass,
    Status,
)
from beehave.testing import WALL_TIMEOUT_S, ScriptedAction, Timeline


class Scripted(Behavior):
    """Calls ``body(self)`` as its run; lets tests script a behaviour inline."""

    def __init__(self, body: Any) -> None:
        self.body = body

    def run(self) -> Any:
        return self.body(self)


def run_top(hl: HighLevelBehaviorManager, body: Any) -> Behavior:
    hl.register("scripted", Scripted)
    return hl.switch("scripted", body=body)


def test_run_returning_interrupts_and_waits_for_running_children(
        hl: HighLevelBehaviorManager) -> None:
    timeline = Timeline()
    started: list[ScriptedAction] = []

    def body(b: Behavior) -> str:
        started.append(b.start_action(ScriptedAction("driving", duration_s=30, timeline=timeline)))
        started.append(b.start_action(ScriptedAction("sound", duration_s=30, timeline=timeline)))
        return "done"

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert top.status is Status.SUCCEEDED and top.result == "done"
    for action in started:
        assert action.status is Status.INTERRUPTED and not action.alive
        assert action.safe_state_calls == 1
        # The behaviour decided only after its children had ended.
        assert action.ended_at is not None and top.ended_at is not None
        assert action.ended_at <= top.ended_at


def test_interrupting_a_behaviour_interrupts_its_children_first(
        hl: HighLevelBehaviorManager) -> None:
    order: list[str] = []
    ready = threading.Event()

    class Child(Behavior):
        def run(self) -> None:
            self.start_action(ScriptedAction("x", duration_s=30))
            ready.set()
            while self.sleep(10):
                pass
            order.append("child saw interrupt")

    def body(b: Behavior) -> None:
        b.start_behavior(Child())
        while b.sleep(10):
            pass
        order.append("parent saw interrupt")
        # The child may still be winding down; the parent's end waits for it.

    top = run_top(hl, body)
    assert ready.wait(WALL_TIMEOUT_S)
    hl.switch("idle")
    assert top.status is Status.INTERRUPTED
    (child,) = top.children
    assert child.status is Status.INTERRUPTED
    assert set(order) == {"child saw interrupt", "parent saw interrupt"}
    assert all(not c.alive for c in child.children)  # type: ignore[attr-defined]


def test_child_failure_is_raised_at_the_next_framework_call(
        hl: HighLevelBehaviorManager) -> None:
    caught: list[BaseException] = []
    boom = ValueError("lift overload")

    def body(b: Behavior) -> str:
        failing = b.start_action(ScriptedAction("lifting", raises=boom))
        try:
            while b.sleep(10):
                pass
        except ChildFailed as exc:
            caught.append(exc)
            assert exc.child is failing
        return "recovered"

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert top.status is Status.SUCCEEDED
    (exc,) = caught
    assert exc.__cause__ is boom and "lift overload" in str(exc)


def test_waiting_for_a_child_observes_its_failure(hl: HighLevelBehaviorManager) -> None:
    def body(b: Behavior) -> Status:
        action = b.start_action(ScriptedAction("lifting", raises=ValueError("x")))
        action.wait()
        b.sleep(0.01)  # does not raise: the failure was seen through wait()
        return action.status

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert top.status is Status.SUCCEEDED and top.result is Status.FAILED


def test_uncaught_child_failure_fails_the_behaviour(hl: HighLevelBehaviorManager) -> None:
    def body(b: Behavior) -> None:
        b.start_action(ScriptedAction("lifting", raises=ValueError("x")))
        while b.sleep(10):
            pass

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert top.status is Status.FAILED and isinstance(top.error, ChildFailed)


def test_failure_after_run_returned_fails_the_behaviour(hl: HighLevelBehaviorManager) -> None:
    def body(b: Behavior) -> None:
        b.start_action(ScriptedAction("lifting", raises=ValueError("late")))
        threading.Event().wait(0.05)  # a plain wait: no framework call sees the failure

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert top.status is Status.FAILED
    assert isinstance(top.error, ChildFailed) and "late" in str(top.error)


def test_nested_sub_behaviours_end_with_their_parent(hl: HighLevelBehaviorManager) -> None:
    depth_reached = threading.Event()
    nodes: list[Behavior] = []

    class Nest(Behavior):
        def __init__(self, depth: int) -> None:
            self.depth = depth

        def run(self) -> None:
            nodes.append(self)
            if self.depth:
                self.start_behavior(Nest(self.depth - 1))
            else:
                self.start_action(ScriptedAction("driving", duration_s=30))
                depth_reached.set()
            while self.sleep(10):
                pass

    hl.register("nest", Nest, depth=4)
    hl.switch("nest")
    assert depth_reached.wait(WALL_TIMEOUT_S)
    assert nodes[-1].path == "nest/Nest/Nest/Nest/Nest"
    hl.switch("idle")
    assert all(n.status is Status.INTERRUPTED and not n.alive for n in nodes)


def test_start_after_interrupt_raises_interrupted(hl: HighLevelBehaviorManager) -> None:
    outcome: list[BaseException] = []

    def body(b: Behavior) -> None:
        while b.sleep(10):
            pass
        try:
            b.start_action(ScriptedAction("driving"))
        except Interrupted as exc:
            outcome.append(exc)
            raise

    top = run_top(hl, body)
    hl.switch("idle")
    assert top.status is Status.INTERRUPTED  # Interrupted propagating is not a failure
    assert outcome and "interrupted" in str(outcome[0])


def test_start_action_type_checks(hl: HighLevelBehaviorManager) -> None:
    errors: list[BaseException] = []

    def body(b: Behavior) -> None:
        for bad in (lambda: b.start_action(Scripted(lambda _: None)),  # type: ignore[arg-type]
                    lambda: b.start_behavior(ScriptedAction())):  # type: ignore[arg-type]
            try:
                bad()
            except NotASubclass as exc:
                errors.append(exc)

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert len(errors) == 2
    assert "start_behavior()" in str(errors[0]) and "start_action()" in str(errors[1])


def test_many_finished_actions_do_not_accumulate(hl: HighLevelBehaviorManager) -> None:
    def body(b: Behavior) -> int:
        for _ in range(200):
            b.start_action(ScriptedAction("beep")).wait()
        return len(b.children)

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert top.result is not None and top.result <= 2


def test_snapshot_shows_the_tree(hl: HighLevelBehaviorManager) -> None:
    import json

    ready = threading.Event()

    def body(b: Behavior) -> None:
        b.start_action(ScriptedAction("driving", duration_s=30, name="nav"))
        ready.set()
        while b.sleep(10):
            pass

    run_top(hl, body)
    assert ready.wait(WALL_TIMEOUT_S)
    snap = json.loads(json.dumps(hl.snapshot()))
    assert snap["current"] == "scripted"
    assert snap["top"]["status"] == "RUNNING"
    (child,) = snap["top"]["children"]
    assert child["path"] == "scripted/nav" and child["action_type"] == "driving"
    assert child["elapsed_s"] >= 0 and child["started_at"] > 0
    assert snap["locks"]["driving"]["holder"] == "scripted/nav"


def test_behaviours_and_actions_read_the_managers_blackboard(
        hl: HighLevelBehaviorManager) -> None:
    hl.blackboard.set("battery/percentage", 55.0)
    seen: list[object] = []

    class Reads(ScriptedAction):
        def run(self) -> object:
            seen.append(self.blackboard.get("battery/percentage"))
            return None

    def body(b: Behavior) -> None:
        seen.append(b.blackboard.get("battery/percentage"))
        b.start_action(Reads()).wait()

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert seen == [55.0, 55.0]


def test_behaviours_cannot_write_the_blackboard(hl: HighLevelBehaviorManager) -> None:
    from beehave.errors import BlackboardError

    errors: list[BaseException] = []

    def body(b: Behavior) -> None:
        try:
            b.blackboard.set("leds/color", "red")
        except BlackboardError as exc:
            errors.append(exc)

    top = run_top(hl, body)
    assert top.wait(WALL_TIMEOUT_S)
    assert errors and "'leds/color'" in str(errors[0]) and "actions" in str(errors[0])
    assert hl.blackboard.get("leds/color") is None
