"""Behaviour tree engine: the engine contract, plus leaves, preemption, mixing, YAML form."""

from __future__ import annotations

import py_trees
import pytest

from beehave import HighLevelBehaviorManager, Status
from beehave.engines import (
    DecisionEngine,
    EngineConfigError,
    EngineError,
    State,
    StateMachineEngine,
    Transition,
    TreeFailed,
)
from beehave.engines.engine import Starter, StartLike, as_starter
from beehave.engines.tree import BlackboardCheck, StartLeaf, TreeEngine
from beehave.testing import WALL_TIMEOUT_S, wait_until
from tests.engine_contract import EngineContract, Recorder, run

Sequence = py_trees.composites.Sequence
Selector = py_trees.composites.Selector


class TestTreeContract(EngineContract):
    description_kind = "behaviour_tree"

    def check_description_while_running(self, described: dict[str, object]) -> None:
        assert described["nodes"] == [{"name": "work", "path": "work", "status": "RUNNING"}]

    def single(self, start: StartLike) -> DecisionEngine:
        return TreeEngine(StartLeaf("work", start), rate_hz=200)

    def choice(self, key: str, if_true: StartLike, if_false: StartLike) -> DecisionEngine:
        root = Selector("root", memory=True, children=[
            Sequence("yes?", memory=True, children=[BlackboardCheck("flag", key),
                                                    StartLeaf("yes", if_true)]),
            StartLeaf("no", if_false)])
        return TreeEngine(root, rate_hz=200)


def test_a_higher_priority_branch_interrupts_the_running_leaf(
        hl: HighLevelBehaviorManager) -> None:
    patrol = Recorder("patrol", action_type="driving", duration_s=30)
    charge = Recorder("charge", action_type="driving", duration_s=30)
    hl.blackboard.set("battery/percentage", 80)
    root = Selector("root", memory=False, children=[
        Sequence("charge?", memory=True, children=[
            BlackboardCheck("low", "battery/percentage < 20"), StartLeaf("charge", charge)]),
        StartLeaf("patrol", patrol)])
    run(hl, TreeEngine(root, rate_hz=200))
    assert wait_until(lambda: bool(patrol.built) and patrol.built[0].status is Status.RUNNING)
    hl.blackboard.set("battery/percentage", 10)
    assert wait_until(lambda: bool(charge.built) and charge.built[-1].status is Status.RUNNING)
    assert patrol.built[0].status is Status.INTERRUPTED
    assert patrol.built[0].safe_state_calls == 1


def test_leaf_maps_statuses_tick_by_tick(hl: HighLevelBehaviorManager) -> None:
    act = Recorder("act", duration_s=30)
    leaf = StartLeaf("act", act)
    engine = TreeEngine(leaf, rate_hz=500)
    run(hl, engine)
    assert wait_until(lambda: bool(act.built))
    # The action is built inside the tick; the leaf's status is set when the tick returns.
    assert wait_until(lambda: leaf.status == py_trees.common.Status.RUNNING)
    act.built[0].interrupt()  # someone else stops it: not a success
    hl_status = wait_until(lambda: engine.root.status == py_trees.common.Status.FAILURE
                           or act.built[0].status is Status.INTERRUPTED)
    assert hl_status


def test_a_busy_action_type_can_fail_the_leaf(hl: HighLevelBehaviorManager) -> None:
    first = Recorder("first", action_type="driving", duration_s=30)
    second = Recorder("second", action_type="driving", duration_s=0.01)
    root = py_trees.composites.Parallel(
        "both", policy=py_trees.common.ParallelPolicy.SuccessOnAll(), children=[
            StartLeaf("first", first), StartLeaf("second", second, on_busy="failure")])
    behavior = run(hl, TreeEngine(root, rate_hz=200))
    assert behavior.wait(WALL_TIMEOUT_S)
    assert isinstance(behavior.error, TreeFailed)
    assert behavior.error.node == "second" and "'driving'" in str(behavior.error)


def test_failure_names_the_leaf_and_keeps_the_cause(hl: HighLevelBehaviorManager) -> None:
    boom = ValueError("no dock")
    root = Sequence("dock", memory=True, children=[
        StartLeaf("approach", Recorder("approach", duration_s=0.01)),
        StartLeaf("latch", Recorder("latch", raises=boom))])
    behavior = run(hl, TreeEngine(root, rate_hz=200))
    assert behavior.wait(WALL_TIMEOUT_S)
    assert isinstance(behavior.error, TreeFailed)
    assert "'latch'" in str(behavior.error) and behavior.error.__cause__ is boom


def test_a_state_machine_can_run_a_tree_driven_sub_behaviour(
        hl: HighLevelBehaviorManager) -> None:
    from beehave.engines import EngineBehavior

    leaf_act = Recorder("leaf", duration_s=0.01)
    machine = StateMachineEngine(
        [State("tree", start=lambda: EngineBehavior(TreeEngine(StartLeaf("leaf", leaf_act),
                                                               rate_hz=200))),
         State("done", final=True)],
        [Transition("tree", "done", on="succeeded")], initial="tree")
    behavior = run(hl, machine)
    assert behavior.wait(WALL_TIMEOUT_S) and behavior.result == "done"
    assert leaf_act.built[0].status is Status.SUCCEEDED


def test_from_dict_builds_a_tree_and_reports_key_paths(hl: HighLevelBehaviorManager) -> None:
    beep = Recorder("beep", duration_s=0.01, result="beeped")

    def resolve(entry: object, where: str) -> Starter:
        return as_starter(beep, label=str(entry))

    engine = TreeEngine.from_dict(
        {"sequence": {"children": [{"condition": "ready == true"}, {"action": "beep"}]}},
        resolve_start=resolve, rate_hz=200)
    hl.blackboard.set("ready", True)
    behavior = run(hl, engine)
    assert behavior.wait(WALL_TIMEOUT_S) and behavior.result == "beeped"
    with pytest.raises(EngineConfigError, match=r"tree\.selector\.children\[1\]: unknown node "
                                                r"kind 'sequense'"):
        TreeEngine.from_dict({"selector": {"children": [{"action": "a"}, {"sequense": {}}]}},
                             resolve_start=resolve)
    with pytest.raises(EngineConfigError, match=r"tree\.sequence\.children: expected a "
                                                r"non-empty list"):
        TreeEngine.from_dict({"sequence": {"children": []}}, resolve_start=resolve)


def test_tree_errors_are_engine_errors() -> None:
    with pytest.raises(EngineError, match="rate_hz must be positive"):
        TreeEngine(StartLeaf("x", Recorder("x")), rate_hz=0)


def test_graph_draws_composites_and_leaves() -> None:
    root = Selector("root", memory=False, children=[
        BlackboardCheck("low", "battery/percentage < 20"), StartLeaf("patrol", Recorder("p"))])
    source = TreeEngine(root).to_graph().source
    assert "? root" in source and "battery/percentage < 20" in source and "patrol" in source


def test_the_description_lists_every_node_with_its_status_in_pre_order(
        hl: HighLevelBehaviorManager) -> None:
    patrol = Recorder("patrol", duration_s=30)
    hl.blackboard.set("battery/percentage", 80)
    root = Selector("root", memory=False, children=[
        Sequence("charge?", memory=True, children=[
            BlackboardCheck("low", "battery/percentage < 20"),
            StartLeaf("charge", Recorder("charge", duration_s=30))]),
        StartLeaf("patrol", patrol), StartLeaf("patrol", Recorder("spare"))])
    engine = TreeEngine(root, rate_hz=200)
    run(hl, engine)
    assert wait_until(lambda: bool(patrol.built) and patrol.built[0].status is Status.RUNNING)
    expected = [
        ("root", "RUNNING"),
        ("root/charge?", "FAILURE"),
        ("root/charge?/low", "FAILURE"),
        ("root/charge?/charge", "INVALID"),
        ("root/patrol[1]", "RUNNING"),
        ("root/patrol[2]", "INVALID"),
    ]

    def seen() -> list[tuple[str, str]]:
        return [(n["path"], n["status"]) for n in hl.snapshot()["top"]["engine"]["nodes"]]

    assert wait_until(lambda: seen() == expected), seen()
    described = hl.snapshot()["top"]["engine"]
    assert described["kind"] == "behaviour_tree" and described["tick"] >= 1
    assert [n["name"] for n in described["nodes"]][-2:] == ["patrol", "patrol"]
