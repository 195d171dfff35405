"""The contract every decision engine keeps; each engine's test module inherits it.

A subclass says how to build two small structures with its engine; the tests here check
that the engine starts what it decided, decides from the blackboard, stops cleanly when
interrupted mid-action (safe state applied once), surfaces failures as errors with the
action's error as cause, can be driven again, and can run a sub-behaviour that another
engine drives.
"""

from __future__ import annotations

import abc
import json
import time
from typing import Any

from beehave import Behavior, HighLevelBehaviorManager, Status
from beehave.engines import (
    DecisionEngine,
    EngineBehavior,
    EngineError,
    State,
    StateMachineEngine,
    Transition,
)
from beehave.engines.engine import StartLike
from beehave.runnable import Runnable
from beehave.testing import WALL_TIMEOUT_S, ScriptedAction, Timeline, wait_until

# A negative check (a paused engine takes no step) runs to its end: short on purpose; a loaded
# machine can only make it see fewer steps, never fail a right engine.
FROZEN_S = 0.5


class Recorder:
    """A factory of ScriptedActions that remembers every action it built."""

    def __init__(self, label: str, action_type: str = "scripted", **kwargs: Any) -> None:
        self.label, self.action_type, self.kwargs = label, action_type, kwargs
        self.built: list[ScriptedAction] = []
        self.__name__ = label

    def __call__(self) -> ScriptedAction:
        action = ScriptedAction(self.action_type, name=self.label, **self.kwargs)
        self.built.append(action)
        return action


def run(hl: HighLevelBehaviorManager, engine: DecisionEngine) -> EngineBehavior:
    hl.register("engine", EngineBehavior, engine=engine)
    behavior = hl.switch("engine")
    assert isinstance(behavior, EngineBehavior)
    return behavior


class EngineContract(abc.ABC):
    """Inherit it in ``tests/test_<engine>.py``, write the two builders and name the
    ``kind`` the engine's :meth:`~DecisionEngine.describe` reports."""

    #: ``describe()["kind"]``: "state_machine", "behaviour_tree", "neural_network" …
    description_kind: str

    @abc.abstractmethod
    def single(self, start: StartLike) -> DecisionEngine:
        """An engine that starts ``start`` once and ends successfully when it succeeded
        (fails when it failed)."""

    @abc.abstractmethod
    def choice(self, key: str, if_true: StartLike, if_false: StartLike) -> DecisionEngine:
        """An engine that starts ``if_true`` when blackboard ``key`` is true, else
        ``if_false``, and ends successfully when that succeeded."""

    # ---------------------------------------------------------------------------- tests
    def test_starts_the_action_and_succeeds_when_it_did(
            self, hl: HighLevelBehaviorManager) -> None:
        act = Recorder("act", duration_s=0.01, result=42)
        behavior = run(hl, self.single(act))
        assert behavior.wait(WALL_TIMEOUT_S)
        assert behavior.status is Status.SUCCEEDED, behavior.error
        (action,) = act.built
        assert action.status is Status.SUCCEEDED and action.parent is behavior

    def test_decides_from_the_blackboard(self, hl: HighLevelBehaviorManager) -> None:
        for flag in (True, False):
            yes, no = Recorder("yes", duration_s=0.01), Recorder("no", duration_s=0.01)
            hl.blackboard.set("go", flag)
            behavior = run(hl, self.choice("go", yes, no))
            assert behavior.wait(WALL_TIMEOUT_S)
            assert behavior.status is Status.SUCCEEDED, behavior.error
            assert (len(yes.built), len(no.built)) == ((1, 0) if flag else (0, 1))

    def test_interrupt_mid_action_interrupts_it_and_applies_its_safe_state(
            self, hl: HighLevelBehaviorManager) -> None:
        act = Recorder("long", duration_s=30)
        behavior = run(hl, self.single(act))
        assert wait_until(lambda: bool(act.built) and act.built[0].status is Status.RUNNING)
        hl.switch("idle")
        (action,) = act.built
        assert behavior.status is Status.INTERRUPTED
        assert action.status is Status.INTERRUPTED and not action.alive
        assert action.safe_state_calls == 1

    def test_a_pause_keeps_the_engine_where_it_is_and_resume_goes_on(
            self, hl: HighLevelBehaviorManager) -> None:
        # Generous bounds: on a loaded host the pause must not find the action already
        # done, nor declare it STUCK (the fixture's 0.3 s is for switches).
        hl.stop_timeout_s = 2.0
        timeline = Timeline()
        act = Recorder("act", duration_s=1.0, result=7, timeline=timeline)
        engine = self.single(act)
        behavior = run(hl, engine)
        # Inside run(): paused before it, an action only waits for the resume (it has
        # moved nothing, so it needs no safe state).
        assert wait_until(lambda: bool(act.built)
                          and bool(timeline.times("run", act.built[0].path)))
        hl.pause()
        (action,) = act.built
        # The action is in its safe state, paused (still RUNNING, its type held); the
        # engine decides nothing while paused, although the action's 1 s passed.
        assert action.safe_state_calls == 1 and action.status is Status.RUNNING, (
            action.safe_state_calls, action.status, action.error, hl.snapshot())

        def described() -> str:
            return json.dumps(engine.describe(), sort_keys=True, default=str)

        def settled() -> bool:
            # A step under way when the pause came may finish; then nothing moves.
            before = described()
            time.sleep(0.1)
            return described() == before

        assert wait_until(settled)
        frozen = described()
        time.sleep(FROZEN_S)
        assert described() == frozen
        assert behavior.status is Status.RUNNING and len(act.built) == 1
        hl.resume()
        assert behavior.wait(WALL_TIMEOUT_S)
        assert behavior.status is Status.SUCCEEDED, behavior.error
        # The same action ran again to its end: not rebuilt, its safe state not repeated.
        assert len(act.built) == 1 and action.status is Status.SUCCEEDED
        assert action.result == 7 and action.safe_state_calls == 1

    def test_a_switch_while_paused_stops_the_engine_and_its_action_once(
            self, hl: HighLevelBehaviorManager) -> None:
        hl.stop_timeout_s = 2.0  # a loaded host must not make the pause STUCK
        act = Recorder("long", duration_s=30)
        behavior = run(hl, self.single(act))
        assert wait_until(lambda: bool(act.built) and act.built[0].status is Status.RUNNING)
        hl.pause()
        hl.switch("idle")
        (action,) = act.built
        assert not hl.paused and behavior.status is Status.INTERRUPTED
        assert action.status is Status.INTERRUPTED and action.safe_state_calls == 1

    def test_the_snapshot_shows_where_the_running_engine_is(
            self, hl: HighLevelBehaviorManager) -> None:
        act = Recorder("long", duration_s=30)
        engine = self.single(act)
        behavior = run(hl, engine)
        assert wait_until(lambda: bool(act.built) and act.built[0].status is Status.RUNNING)
        snap = hl.snapshot()
        described = snap["top"]["engine"]
        assert described["kind"] == self.description_kind
        assert set(described) == set(engine.describe())  # values move on as it runs
        json.dumps(snap)  # the ROS 2 state topic publishes it as JSON

        def shows_it() -> bool:
            # The engine records what it started just after the action's thread began.
            try:
                self.check_description_while_running(hl.snapshot()["top"]["engine"])
            except AssertionError:
                return False
            return True

        if not wait_until(shows_it):
            self.check_description_while_running(hl.snapshot()["top"]["engine"])
        hl.switch("idle")
        assert behavior.status is Status.INTERRUPTED

    def test_a_plain_behaviour_driving_the_engine_shows_it_too(
            self, hl: HighLevelBehaviorManager) -> None:
        act = Recorder("long", duration_s=30)
        engine = self.single(act)

        class Plain(Behavior):
            def run(self) -> Any:
                return engine.drive(self)

        hl.register("plain", Plain)
        hl.switch("plain")
        assert wait_until(lambda: bool(act.built) and act.built[0].status is Status.RUNNING)
        assert hl.snapshot()["top"]["engine"]["kind"] == self.description_kind
        hl.switch("idle")
        assert "engine" not in hl.snapshot()["top"]

    def check_description_while_running(self, described: dict[str, Any]) -> None:
        """Engine-specific checks of ``describe()`` while ``single``'s action runs."""

    def test_a_failed_action_fails_the_behaviour_with_its_error_as_cause(
            self, hl: HighLevelBehaviorManager) -> None:
        boom = RuntimeError("lift overload")
        act = Recorder("lift", raises=boom)
        behavior = run(hl, self.single(act))
        assert behavior.wait(WALL_TIMEOUT_S)
        assert behavior.status is Status.FAILED
        assert isinstance(behavior.error, EngineError), behavior.error
        assert behavior.error.__cause__ is boom
        assert act.built[0].safe_state_calls == 1

    def test_the_engine_can_be_driven_again_after_it_ended(
            self, hl: HighLevelBehaviorManager) -> None:
        act = Recorder("again", duration_s=0.01)
        engine = self.single(act)
        for _ in range(2):
            behavior = run(hl, engine)
            assert behavior.wait(WALL_TIMEOUT_S)
            assert behavior.status is Status.SUCCEEDED, behavior.error
        assert len(act.built) == 2

    def test_runs_a_sub_behaviour_that_a_state_machine_drives(
            self, hl: HighLevelBehaviorManager) -> None:
        inner = Recorder("inner", duration_s=0.01)
        subs: list[Runnable] = []

        def sub_behavior() -> EngineBehavior:
            machine = StateMachineEngine(
                [State("work", start=inner), State("done", final=True)],
                [Transition("work", "done", on="succeeded")], initial="work")
            behavior = EngineBehavior(machine, name="sub")
            subs.append(behavior)
            return behavior

        behavior = run(hl, self.single(sub_behavior))
        assert behavior.wait(WALL_TIMEOUT_S)
        assert behavior.status is Status.SUCCEEDED, behavior.error
        (sub,) = subs
        assert sub.status is Status.SUCCEEDED and sub.result == "done"
        assert inner.built[0].status is Status.SUCCEEDED and inner.built[0].parent is sub
