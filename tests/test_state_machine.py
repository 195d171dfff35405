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
    UnknownEvent,
)
from beehave.engines.engine import Starter, StartLike, as_starter
from beehave.testing import WALL_TIMEOUT_S, ScriptedAction, wait_until
from tests.engine_contract import EngineContract, Recorder, run


class TestStateMachineContract(EngineContract):
    description_kind = "state_machine"

    def check_description_while_running(self, described: dict[str, object]) -> None:
        assert described["state"] == "work" and described["states"] == ["work", "done"]
        assert described["last_transition"] is None

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
    assert behavior.wait(WALL_TIMEOUT_S)
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
    # Built is not yet started (PENDING for a moment, seen beside busy loops): wait for RUNNING.
    assert wait_until(lambda: machine.state == "charge" and bool(charge.built)
                      and charge.built[0].status is Status.RUNNING), charge.built
    # Same action type: the old state's action was stopped before the new one started.
    assert patrol.built[0].status is Status.INTERRUPTED
    assert patrol.built[0].safe_state_calls == 1
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
    assert behavior.wait(WALL_TIMEOUT_S)
    assert behavior.result == "stopped"


def test_unhandled_failure_names_the_state_and_outcome(hl: HighLevelBehaviorManager) -> None:
    machine = StateMachineEngine(
        [State("lift", start=Recorder("lift", raises=OSError("motor"))),
         State("done", final=True)],
        [Transition("lift", "done", on="succeeded")], initial="lift")
    behavior = run(hl, machine)
    assert behavior.wait(WALL_TIMEOUT_S)
    error = behavior.error
    assert isinstance(error, UnhandledOutcome)
    assert (error.state, error.outcome) == ("lift", "failed")
    assert "'lift'" in str(error) and "motor" in str(error)


def test_a_loop_the_load_check_cannot_decide_is_stopped_while_running(
        hl: HighLevelBehaviorManager) -> None:
    # Two different callables: loading cannot know they hold together, so it warns…
    machine = StateMachineEngine(
        [State("a"), State("b")],
        [Transition("a", "b", when=lambda bb: bool(bb.get("x"))),
         Transition("b", "a", when=lambda bb: bb.get("x") is True)], initial="a")
    assert any("may loop" in w and "'a' → 'b' → 'a'" in w for w in machine.warnings)
    hl.blackboard.set("x", True)
    # …and the running machine reports the loop.
    behavior = run(hl, machine)
    assert behavior.wait(WALL_TIMEOUT_S)
    assert isinstance(behavior.error, EngineConfigError) and "loop" in str(behavior.error)


def test_a_wildcard_never_re_enters_its_destination(hl: HighLevelBehaviorManager) -> None:
    charge = Recorder("charge", action_type="driving", duration_s=30)
    steps: list[str | None] = []
    stepped = threading.Condition()

    def on_step(m: StateMachineEngine) -> None:
        with stepped:
            steps.append(m.state)
            stepped.notify_all()

    hl.blackboard.set("battery/percentage", 80)
    machine = StateMachineEngine(
        [State("patrol", start=Recorder("patrol", action_type="driving", duration_s=30)),
         State("charge", start=charge)],
        [Transition("*", "charge", when="battery/percentage < 20")], initial="patrol",
        on_step=on_step)
    behavior = run(hl, machine)
    hl.blackboard.set("battery/percentage", 10)
    assert wait_until(lambda: machine.state == "charge")
    for level in (9, 8, 7):  # each change wakes the machine for another decision step
        with stepped:
            seen = len(steps)
            hl.blackboard.set("battery/percentage", level)
            assert stepped.wait_for(lambda n=seen: len(steps) > n, timeout=WALL_TIMEOUT_S)
    assert len(charge.built) == 1, "the wildcard re-entered its own destination"
    assert charge.built[0].status is Status.RUNNING and charge.built[0].safe_state_calls == 0
    assert behavior.status is Status.RUNNING


def test_a_wildcard_covers_every_state_but_its_destination_and_final_states() -> None:
    machine = StateMachineEngine(
        [State("a"), State("b"), State("c"), State("end", final=True)],
        [Transition("*", "b", on="go"), Transition("a", "end", on="stop")], initial="a")
    assert machine._compiled[0][3] == ["a", "c"]
    source = machine.to_graph().source
    assert "b -> b" not in source and "end -> b" not in source and "c -> b" in source


@pytest.mark.parametrize(("transitions", "cycle", "witness"), [
    # The case: two wildcards on one condition chase each other.
    ([Transition("*", "a", when="low"), Transition("*", "b", when="low")],
     "'a' → 'b' → 'a'", "low = True"),
    # A state that restarts itself while a condition holds.
    ([Transition("b", "b", when="battery/percentage < 20")], "'b' → 'b'",
     "battery/percentage = 19"),
    # Overlapping ranges: both hold for 4 < x < 6.
    ([Transition("a", "b", when="x > 4"), Transition("b", "a", when="x < 6")],
     "'a' → 'b' → 'a'", "x = 5.0"),
    # Three states, mixed when/unless.
    ([Transition("a", "b", when="mode == 'auto'"), Transition("b", "c", unless="docked"),
      Transition("c", "a", when="mode != 'manual'")], "'a' → 'b' → 'c' → 'a'",
     "mode = 'auto', docked = None"),
])
def test_condition_cycles_that_can_hold_together_are_rejected_at_load(
        transitions: list[Transition], cycle: str, witness: str) -> None:
    with pytest.raises(EngineConfigError, match="condition cycle") as info:
        StateMachineEngine([State("a"), State("b"), State("c")], transitions, initial="a")
    assert cycle in str(info.value) and f"holds when {witness}" in str(info.value)


@pytest.mark.parametrize("transitions", [
    # Hysteresis: down below 20, back above 90.
    [Transition("a", "b", when="battery/percentage < 20"),
     Transition("b", "a", when="battery/percentage > 90")],
    # A cycle that an outcome closes.
    [Transition("a", "b", when=lambda bb: bool(bb.get("x"))),
     Transition("b", "a", on="succeeded")],
    # A wildcard to a state that leaves on an outcome.
    [Transition("*", "b", when="low"), Transition("b", "a", on="succeeded")],
    [Transition("a", "b", when="x == 1"), Transition("b", "a", when="x == 2")],
    [Transition("a", "b", when="x"), Transition("b", "a", unless="x")],
])
def test_exclusive_or_event_broken_cycles_load_without_warning(
        transitions: list[Transition]) -> None:
    machine = StateMachineEngine([State("a"), State("b")], transitions, initial="a")
    assert machine.warnings == []


def test_the_same_callable_as_when_and_unless_is_exclusive() -> None:
    def needs_charge(bb: object) -> bool:
        return False

    machine = StateMachineEngine(
        [State("patrol"), State("charge")],
        [Transition("patrol", "charge", when=needs_charge),
         Transition("charge", "patrol", unless=needs_charge)], initial="patrol")
    assert machine.warnings == []


def test_unreachable_states_are_warned_about(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level("WARNING", logger="beehave.engines.state_machine"):
        machine = StateMachineEngine(
            [State("start"), State("orphan_7f3"), State("end", final=True)],
            [Transition("start", "end", on="succeeded")], initial="start")
    (text,) = machine.warnings
    assert "state 'orphan_7f3' is unreachable" in text and "'start'" in text
    assert text in caplog.messages


def test_events_posted_while_not_running_are_dropped(hl: HighLevelBehaviorManager) -> None:
    machine = StateMachineEngine(
        [State("wait", start=Recorder("w", duration_s=30)), State("stopped", final=True)],
        [Transition("*", "stopped", on="shutdown")], initial="wait")
    assert machine.post("shutdown") is False  # nobody runs it: dropped, not kept
    behavior = run(hl, machine)
    assert wait_until(lambda: machine.state == "wait")
    assert behavior.status is Status.RUNNING  # the stale event did not fire at start
    hl.switch("idle")
    assert machine.post("shutdown") is False
    behavior = run(hl, machine)
    assert wait_until(lambda: machine.state == "wait")
    assert behavior.status is Status.RUNNING
    assert machine.post("shutdown") is True
    assert behavior.wait(WALL_TIMEOUT_S) and behavior.result == "stopped"


def test_posting_an_unknown_event_or_an_outcome_raises() -> None:
    machine = StateMachineEngine(
        [State("a"), State("b")], [Transition("a", "b", on="shutdown")], initial="a")
    with pytest.raises(UnknownEvent, match=r"cannot post 'shutdwon'.*events: 'shutdown'"):
        machine.post("shutdwon")
    with pytest.raises(UnknownEvent, match=r"'succeeded': it is an outcome"):
        machine.post("succeeded")


def test_a_misspelt_outcome_is_rejected() -> None:
    with pytest.raises(EngineConfigError, match=r"transitions\[0\]\.on: unknown event "
                                                r"'succeded': did you mean the outcome "
                                                r"'succeeded'"):
        StateMachineEngine([State("a"), State("b")], [Transition("a", "b", on="succeded")],
                           initial="a")
    with pytest.raises(EngineConfigError, match=r"unknown event 'dock_now'.*declared events: "
                                                r"'shutdown'"):
        StateMachineEngine([State("a"), State("b")], [Transition("a", "b", on="dock_now")],
                           initial="a", events=["shutdown"])
    with pytest.raises(EngineConfigError, match=r"events\[0\]: 'failed' is built in"):
        StateMachineEngine([State("a")], [], initial="a", events=["failed"])


def test_the_engine_description_names_the_state_and_the_last_transition(
        hl: HighLevelBehaviorManager) -> None:
    machine = StateMachineEngine(
        [State("wait", start=Recorder("w", duration_s=30)), State("go"),
         State("end", final=True)],
        [Transition("wait", "go", on="next"), Transition("go", "end", on="finish")],
        initial="wait")
    behavior = run(hl, machine)
    assert wait_until(lambda: machine.state == "wait")
    assert hl.snapshot()["top"]["engine"] == {
        "kind": "state_machine", "state": "wait", "states": ["wait", "go", "end"],
        "last_transition": None, "structure_id": machine.structure_id()}
    machine.post("next")
    assert wait_until(lambda: machine.state == "go")
    engine = hl.snapshot()["top"]["engine"]
    assert engine["state"] == "go"
    assert {k: engine["last_transition"][k] for k in ("source", "dest", "trigger")} == {
        "source": "wait", "dest": "go", "trigger": "next"}
    assert behavior.status is Status.RUNNING


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
    assert behavior.wait(WALL_TIMEOUT_S) and behavior.result == "end"
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


class CountedDrive(ScriptedAction):
    """Counts the runs begun (the robot moving) across objects."""

    runs = 0

    def run(self) -> object:
        type(self).runs += 1
        return super().run()


def test_a_state_breakpoint_stops_the_machine_before_the_state_starts_its_action(
        hl: HighLevelBehaviorManager) -> None:
    """The breakpoint's pause is carried out in a manager thread; the machine waits for it
    before it starts the state's actions, which then wait for the resume. Without that
    wait, with the manager's threads warm (any robot after its first switch), the action
    began (the robot moved) before the pause landed."""
    from beehave.breakpoints import Breakpoints
    from beehave.engines import EngineBehavior
    from beehave.events import EventKind

    hl.stop_timeout_s = 2.0  # a loaded host must not give up on the pause
    machine = StateMachineEngine(
        [State("go", start=lambda: CountedDrive("state_bp_driving", duration_s=30)),
         State("done", final=True)],
        [Transition("go", "done", on="succeeded")], initial="go")
    hl.register("m", EngineBehavior, engine=machine)
    paused: list[object] = []
    hl.subscribe(lambda e: paused.append(e) if e.kind is EventKind.PAUSED else None)
    points = Breakpoints(hl)
    try:
        points.add("state", "go")
        for round_ in range(30):  # the race was lost in 1 of ~5 rounds with warm threads
            CountedDrive.runs = 0
            paused.clear()
            hl.switch("m")
            assert wait_until(lambda: bool(paused))
            assert machine.state == "go"
            assert CountedDrive.runs == 0, f"round {round_}: the action began before the pause"
            assert points.resume()
            assert wait_until(lambda: CountedDrive.runs == 1)
            hl.switch("idle")
    finally:
        points.close()
