"""YAML behaviours: files that run, and errors that name the file, key path and expectation."""

from __future__ import annotations

from pathlib import Path

import pytest

from beehave import HighLevelBehaviorManager, InvalidParameters, Status
from behaviours.behaviors import YamlBehavior, YamlBehaviorError
from behaviours.demos.console import Beep, Drive, PointRobot
from behaviours.yaml_schema import load_engine

DATA = Path(__file__).parent / "data"
REGISTRY = {"drive": Drive, "beep": Beep}


def test_a_state_machine_file_runs_its_actions(hl: HighLevelBehaviorManager) -> None:
    robot = PointRobot()
    hl.register("patrol", YamlBehavior, file=DATA / "patrol_sm.yaml", registry=REGISTRY,
                inject={"robot": robot})
    behavior = hl.switch("patrol")
    assert behavior.wait(10)
    assert behavior.status is Status.SUCCEEDED and behavior.result == "done"
    assert behavior.name == "patrol"
    assert robot.sounds == ["hi"] and abs(robot.x_m) < 0.03


def test_a_tree_file_runs_an_inline_state_machine_sub_behaviour(
        hl: HighLevelBehaviorManager) -> None:
    robot = PointRobot()
    hl.blackboard.set("battery/percentage", 80)
    hl.register("tree", YamlBehavior, file=DATA / "charge_tree.yaml", registry=REGISTRY,
                inject={"robot": robot})
    behavior = hl.switch("tree")
    assert behavior.wait(10)
    assert behavior.status is Status.SUCCEEDED, behavior.error
    assert 0.02 < robot.x_m < 0.08 and robot.lift_m == 0.0


@pytest.mark.parametrize(("file", "expected"), [
    ("bad_type.yaml", r"bad_type\.yaml: rate_hz: Input should be a valid number.*'fast'"),
    ("bad_action.yaml", r"bad_action\.yaml: states\[0\]\.start: unknown action 'drivee'; "
                        r"known: 'beep', 'drive'; or give an import path 'module:Class'"),
    ("bad_transition.yaml", r"bad_transition\.yaml: transitions\[0\]\.dest: unknown state "
                            r"'nowhere'; states: 'a'"),
    ("bad_params.yaml", r"bad_params\.yaml: states\[0\]\.start\.params: 'drive' rejects "
                        r"\['goal'\].*accepts: robot, goal_m, speed_mps"),
    ("bad_syntax.yaml", r"bad_syntax\.yaml: line 3, column 1: not valid YAML"),
    ("missing.yaml", r"missing\.yaml: cannot read"),
])
def test_errors_name_the_file_the_key_path_and_what_was_expected(file: str,
                                                                 expected: str) -> None:
    with pytest.raises(YamlBehaviorError, match=expected):
        load_engine(DATA / file, registry=REGISTRY, inject={"robot": PointRobot()})


def test_engine_specific_keys_are_checked() -> None:
    from behaviours.yaml_schema import build_engine

    with pytest.raises(YamlBehaviorError, match="engine 'tree' needs key"):
        build_engine({"engine": "tree"}, file="inline.yaml")
    with pytest.raises(YamlBehaviorError, match=r"engine: Input should be 'state_machine', "
                                                r"'tree' or 'neural'"):
        build_engine({"engine": "fsm"}, file="inline.yaml")


def test_a_broken_file_is_refused_at_switch_and_the_running_behaviour_stays(
        hl: HighLevelBehaviorManager) -> None:
    hl.register("broken", YamlBehavior, file=DATA / "bad_action.yaml", registry=REGISTRY)
    with pytest.raises(InvalidParameters, match=r"bad_action\.yaml: states\[0\]\.start"):
        hl.switch("broken")
    assert hl.current == "idle"


def test_a_neural_file_builds_a_network_engine() -> None:
    from behaviours.yaml_schema import build_engine

    engine = build_engine({"engine": "neural", "neural": {
        "features": ["battery/percentage", {"key": "dock/distance_m", "scale": 0.1}],
        "decisions": {"patrol": "drive", "charge": None}}}, registry=REGISTRY,
        inject={"robot": PointRobot(), "goal_m": 1.0})
    assert engine.kind == "neural"
    with pytest.raises(YamlBehaviorError, match=r"neural\.features: expected a non-empty list"):
        build_engine({"engine": "neural", "neural": {"features": [], "decisions": {}}})
