"""YAML behaviours: files that run, and errors that name the file, key path and expectation."""

from __future__ import annotations

from pathlib import Path

import pytest

from beehave import HighLevelBehaviorManager, InvalidParameters, Status
from beehave.testing import WALL_TIMEOUT_S, wait_until
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
    assert behavior.wait(WALL_TIMEOUT_S)
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
    assert behavior.wait(WALL_TIMEOUT_S)
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
    ("bad_event.yaml", r"bad_event\.yaml: transitions\[0\]\.on: unknown event 'succeded': "
                       r"did you mean the outcome 'succeeded'\? outcomes: succeeded, failed, "
                       r"stuck, interrupted, done; declared events: 'shutdown'"),
    ("bad_use.yaml", r"bad_use\.yaml: states\[0\]\.start: import path "
                     r"'collections:OrderedDict' is the class collections\.OrderedDict, which "
                     r"is not an Action or Behavior subclass"),
    ("bad_cycle.yaml", r"bad_cycle\.yaml: condition cycle 'charge' → 'alarm' → 'charge' "
                       r"\(transitions\[1\], transitions\[0\]\): every guard holds when "
                       r"battery/percentage = 9"),
    ("self_include.yaml", r"self_include\.yaml: states\[0\]\.start\.behavior: behaviour "
                          r"files start each other in a cycle: \S*self_include\.yaml → "
                          r"\S*self_include\.yaml"),
    ("include_a.yaml", r"include_a\.yaml: states\[0\]\.start\.behavior: \S*include_b\.yaml: "
                       r"tree\.sequence\.children\[0\]\.behavior\.behavior: behaviour files "
                       r"start each other in a cycle: \S*include_a\.yaml → \S*include_b\.yaml "
                       r"→ \S*include_a\.yaml"),
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


def test_use_of_something_that_is_not_an_action_class_is_refused() -> None:
    from behaviours.yaml_schema import build_engine

    def doc(use: str) -> dict[str, object]:
        return {"engine": "state_machine", "initial": "a",
                "states": [{"name": "a", "start": {"use": use}}]}

    with pytest.raises(YamlBehaviorError, match=r"x\.yaml: states\[0\]\.start: 'os\.path:join' "
                                                r"is a function, not an Action or Behavior "
                                                r"class"):
        build_engine(doc("os.path:join"), file="x.yaml")
    with pytest.raises(YamlBehaviorError, match=r"registry entry 'cfg' is 42: not an Action"):
        build_engine(doc("cfg"), file="x.yaml", registry={"cfg": 42})  # type: ignore[dict-item]
    with pytest.raises(YamlBehaviorError, match=r"registry entry 'd' is the class "
                                                r"builtins\.dict, which is not an Action"):
        build_engine(doc("d"), file="x.yaml", registry={"d": dict})  # type: ignore[dict-item]


def test_an_inline_behaviour_that_contains_itself_through_an_alias_is_refused(
        tmp_path: Path) -> None:
    file = tmp_path / "alias.yaml"
    file.write_text("engine: tree\n"
                    "tree: &root\n"
                    "  sequence:\n"
                    "    children:\n"
                    "      - behavior: {behavior: {engine: tree, tree: *root}}\n")
    with pytest.raises(YamlBehaviorError, match=r"alias\.yaml: .*behavior\.behavior: this "
                                                r"inline behaviour contains itself"):
        load_engine(file, registry=REGISTRY)


def test_events_are_declared_and_unreachable_states_warned_with_the_file(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    file = tmp_path / "warn_unreachable.yaml"
    file.write_text("""engine: state_machine
events: [dock_now]
initial: patrol
states:
  - {name: patrol}
  - {name: dock}
  - {name: forgotten}
transitions:
  - {source: patrol, dest: dock, on: dock_now}
""")
    with caplog.at_level("WARNING"):
        engine = load_engine(file, registry=REGISTRY)
    assert engine.events == {"dock_now"}  # type: ignore[attr-defined]
    (warning,) = engine.warnings  # type: ignore[attr-defined]
    assert warning.startswith(f"{file}: state 'forgotten' is unreachable")
    assert warning in caplog.messages
    with pytest.raises(YamlBehaviorError, match=r"key\(s\) events do not belong to engine "
                                                r"'tree'"):
        from behaviours.yaml_schema import build_engine
        build_engine({"engine": "tree", "events": ["dock_now"],
                      "tree": {"action": "drive"}}, registry=REGISTRY)


def test_the_documented_wildcard_example_charges_once(hl: HighLevelBehaviorManager,
                                                      tmp_path: Path) -> None:
    robot = PointRobot()
    built: list[Drive] = []

    def drive(**params: object) -> Drive:
        built.append(Drive(**params))  # type: ignore[arg-type]
        return built[-1]

    file = tmp_path / "wildcard.yaml"
    file.write_text("""engine: state_machine
initial: out
states:
  - {name: out, start: {use: drive, params: {goal_m: 50.0, speed_mps: 0.1}}}
  - {name: home, start: {use: drive, params: {goal_m: -50.0, speed_mps: 0.1}}}
transitions:
  - {source: "*", dest: home, when: "battery/percentage < 20"}
""")
    hl.blackboard.set("battery/percentage", 50)
    hl.register("w", YamlBehavior, file=file, registry={"drive": drive},
                inject={"robot": robot})
    behavior = hl.switch("w")
    assert wait_until(lambda: len(built) == 1)
    hl.blackboard.set("battery/percentage", 10)
    assert wait_until(lambda: hl.snapshot()["top"]["engine"]["state"] == "home")
    for level in (9, 8, 7):  # more decision steps while the condition holds
        hl.blackboard.set("battery/percentage", level)
    assert wait_until(lambda: hl.snapshot()["top"]["engine"]["last_transition"]["dest"]
                      == "home")
    assert len(built) == 2, "the wildcard re-entered its own destination"
    assert [d.status for d in built] == [Status.INTERRUPTED, Status.RUNNING]
    assert behavior.status is Status.RUNNING
    assert hl.snapshot()["top"]["file"] == str(file)


def test_the_example_in_the_docs_loads_without_warnings(tmp_path: Path) -> None:
    docs = Path(__file__).parents[1] / "docs" / "yaml_behaviors.md"
    example = docs.read_text().split("```yaml\n", 1)[1].split("```", 1)[0]
    (tmp_path / "patrol.yaml").write_text(example)
    (tmp_path / "docking.yaml").write_text(
        "engine: tree\ntree: {action: {use: drive, params: {goal_m: 0.0}}}\n")
    engine = load_engine(tmp_path / "patrol.yaml", registry=REGISTRY,
                         inject={"robot": PointRobot()})
    assert engine.warnings == []  # type: ignore[attr-defined]
    assert engine.events == {"dock_now"}  # type: ignore[attr-defined]
