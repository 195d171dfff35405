"""State machine engine: the engine contract, plus outcomes, conditions, events, errors."""

from __future__ import annotations

import threading

import pytest

from beehave import HighLevelBehaviorManager, Status
from beehave.engines import (
    DecisionEngine,
    EngineConfigError,
    State,
    StateMachineEngine,
    Transition,
    UnhandledOutcome,
)
from beehave.engines.engine import Starter, StartLike, as_starter
from beehave.testing import ScriptedAction, wait_until
from tests.engine_contract import EngineContract, Recorder, run


class TestStateMachineContract(EngineContract):
    def single(self, start: StartLike) -> DecisionEngine:
        return StateMachineEngine(
            [State("work", start=start), State("done", final=True)],
            [Transition("work", "done", on="succeeded")], initial="work")

    def choice(self, key: str, if_true: StartLike, if_false: StartLike) -> DecisionEngine:
        return StateMachineEngine(
            [State("decide"), State("yes", start=if_true), State("no", start=if_false),
             State("done", final=True)],
            [Transition("decide", "yes", when=f"{key} == true"),
             Transition("decide", "no", unless=lambda bb: bool(bb.get(key))),
             Transition(["yes", "no"], "done", on="succeeded")], initial="decide")


def test_outcomes_drive_the_machine_through_its_states(hl: HighLevelBehaviorManager) -> None:
    seen: list[str | None] = []
    a, b = Recorder("a", duration_s=0.01), Recorder("b", raises=ValueError("bump"))
    machine = StateMachineEngine(
        [State("first", start=a), State("second", start=b), State("recover"),
         State("end", final=True)],
        [Transition("first", "second", on="succeeded"),
         Transition("second", "recover", on="failed"),
         Transition("recover", "end", when="ok")],
        initial="first",
        on_step=lambda m: seen.append(m.state) if m.state not in seen else None)
    hl.blackboard.set("ok", True)
    behavior = run(hl, machine)
    assert behavior.wait(5)
    assert behavior.status is Status.SUCCEEDED and behavior.result == "end"
    assert seen == ["second", "recover", "end"] or seen == ["first", "second", "recover", "end"]
    assert b.built[0].status is Status.FAILED  # handled by the 'failed' transition


def test_a_blackboard_change_fires_a_condition_transition_and_stops_the_old_state(
        hl: HighLevelBehaviorManager) -> None:
    patrol = Recorder("patrol", action_type="driving", duration_s=30)
    charge = Recorder("charge", action_type="driving", duration_s=30)
    hl.blackboard.set("battery/percentage", 80)
    machine = StateMachineEngine(
        [State("patrol", start=patrol), State("charge", start=charge)],
        [Transition("patrol", "charge", when="battery/percentage < 20")], initial="patrol")
    behavior = run(hl, machine)
    assert wait_until(lambda: bool(patrol.built) and patrol.built[0].status is Status.RUNNING)
    hl.blackboard.set("battery/percentage", 15)
    assert wait_until(lambda: machine.state == "charge" and bool(charge.built))
    # Same action type: the old state's action was stopped before the new one started.
    assert patrol.built[0].status is Status.INTERRUPTED
    assert patrol.built[0].safe_state_calls == 1
    assert charge.built[0].status is Status.RUNNING
    assert behavior.status is Status.RUNNING


def test_posted_events_fire_from_any_thread(hl: HighLevelBehaviorManager) -> None:
    machine = StateMachineEngine(
        [State("wait", start=Recorder("w", duration_s=30)), State("stopped", final=True)],
        [Transition("*", "stopped", on="shutdown")], initial="wait")
    behavior = run(hl, machine)
    assert wait_until(lambda: machine.state == "wait")
    poster = threading.Thread(target=machine.post, args=("shutdown",))
    poster.start()
    poster.join()
    assert behavior.wait(5)
    assert behavior.result == "stopped"


def test_unhandled_failure_names_the_state_and_outcome(hl: HighLevelBehaviorManager) -> None:
    machine = StateMachineEngine(
        [State("lift", start=Recorder("lift", raises=OSError("motor"))),
         State("done", final=True)],
        [Transition("lift", "done", on="succeeded")], initial="lift")
    behavior = run(hl, machine)
    assert behavior.wait(5)
    error = behavior.error
    assert isinstance(error, UnhandledOutcome)
    assert (error.state, error.outcome) == ("lift", "failed")
    assert "'lift'" in str(error) and "motor" in str(error)


def test_condition_loops_are_reported(hl: HighLevelBehaviorManager) -> None:
    machine = StateMachineEngine(
        [State("a"), State("b")],
        [Transition("a", "b", when="x"), Transition("b", "a", when="x")], initial="a")
    hl.blackboard.set("x", True)
    behavior = run(hl, machine)
    assert behavior.wait(5)
    assert isinstance(behavior.error, EngineConfigError) and "loop" in str(behavior.error)


@pytest.mark.parametrize(("states", "transitions", "initial", "expected"), [
    (["a"], [], "zz", "initial state 'zz' is not a state; states: 'a'"),
    (["a"], [Transition("a", "nowhere", on="done")], "a",
     "transitions[0].dest: unknown state 'nowhere'; states: 'a'"),
    (["a", "b"], [Transition("a", "b")], "a", "transitions[0]: a transition needs 'on'"),
    (["a", "b"], [Transition("a", "b", when="battery <> 3")], "a",
     "transitions[0].when[0]: cannot read condition 'battery <> 3'"),
])
def test_definition_errors_name_what_is_wrong(states: list[str], transitions: list[Transition],
                                              initial: str, expected: str) -> None:
    with pytest.raises(EngineConfigError, match=expected.replace("[", r"\[").replace(
            "]", r"\]")):
        StateMachineEngine([State(s) for s in states], transitions, initial=initial)


def test_from_dict_builds_the_same_machine(hl: HighLevelBehaviorManager) -> None:
    beep = Recorder("beep", duration_s=0.01)

    def resolve(entry: object, where: str) -> Starter:
        assert entry == "beep"
        return as_starter(beep)

    machine = StateMachineEngine.from_dict(
        {"initial": "go", "states": [{"name": "go", "start": "beep"},
                                     {"name": "end", "final": True}],
         "transitions": [{"source": "go", "dest": "end", "on": "succeeded"}]},
        resolve_start=resolve)
    behavior = run(hl, machine)
    assert behavior.wait(5) and behavior.result == "end"
    assert beep.built[0].status is Status.SUCCEEDED


def test_from_dict_errors_give_the_key_path() -> None:
    with pytest.raises(EngineConfigError, match=r"states\[0\]\.final: Input should be a valid "
                                                r"boolean"):
        StateMachineEngine.from_dict({"initial": "a", "states": [{"name": "a", "final": "x"}]},
                                     resolve_start=lambda e, w: as_starter(ScriptedAction))


def test_graph_shows_states_and_guards() -> None:
    machine = StateMachineEngine(
        [State("patrol", start=Recorder("drive")), State("charge")],
        [Transition("patrol", "charge", when="battery/percentage < 20")], initial="patrol")
    source = machine.to_graph().source
    assert "patrol" in source and "charge" in source
    assert "[battery/percentage < 20]" in source
