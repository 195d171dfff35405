"""``beehave graph``: render a YAML behaviour or a module:attr engine without a robot."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from beehave.engines import EngineBehavior, State, StateMachineEngine, Transition
from beehave.engines.graph import graph_main, load_spec
from beehave.testing import ScriptedAction

DATA = Path(__file__).parent / "data"
needs_dot = pytest.mark.skipif(shutil.which("dot") is None, reason="graphviz 'dot' missing")


def example_machine() -> StateMachineEngine:
    return StateMachineEngine([State("work", start=ScriptedAction), State("done", final=True)],
                              [Transition("work", "done", on="succeeded")], initial="work")


def example_behavior(label: str = "x") -> EngineBehavior:
    return EngineBehavior(example_machine(), name=label)


@needs_dot
def test_renders_a_yaml_state_machine_to_png(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "patrol.png"
    code = graph_main([str(DATA / "patrol_sm.yaml"), "-o", str(out),
                       "--registry", "tests.test_yaml_behavior:REGISTRY"])
    assert code == 0, capsys.readouterr().err
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().out.strip() == str(out)


def test_renders_a_yaml_tree_to_dot_source(tmp_path: Path) -> None:
    out = tmp_path / "tree.dot"
    assert graph_main([str(DATA / "charge_tree.yaml"), "-o", str(out),
                       "--registry", "tests.test_yaml_behavior:REGISTRY"]) == 0
    source = out.read_text()
    assert "? root" in source and "battery/percentage < 20" in source


def test_module_attr_specs_build_the_engine_with_params() -> None:
    engine = load_spec("tests.test_graph:example_behavior", {"label": "y"})
    assert isinstance(engine, StateMachineEngine)
    assert isinstance(load_spec("tests.test_graph:example_machine"), StateMachineEngine)


def test_bad_specs_fail_with_a_message(capsys: pytest.CaptureFixture[str]) -> None:
    assert graph_main(["tests.test_graph:DATA"]) == 2
    assert "not a DecisionEngine" in capsys.readouterr().err
    assert graph_main(["no_such_module:thing"]) == 2
    assert "cannot import 'no_such_module'" in capsys.readouterr().err
    assert graph_main([str(DATA / "bad_action.yaml")]) == 2
    assert "unknown action 'drivee'" in capsys.readouterr().err


def test_beehave_cli_routes_graph(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from beehave.cli import main

    out = tmp_path / "sm.dot"
    assert main(["graph", "tests/data/patrol_sm.yaml", "-o", str(out),
                 "--registry", "tests.test_yaml_behavior:REGISTRY"]) == 0
    assert "digraph" in out.read_text()


def needs_a_robot(robot: object, speed_mps: float = 1.0) -> StateMachineEngine:
    assert robot is None or isinstance(robot, dict)
    return example_machine()


def test_a_function_missing_its_arguments_says_to_pass_them_with_p(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "robot.dot"
    assert graph_main(["tests.test_graph:needs_a_robot", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "missing a required argument: 'robot'" in err
    assert "-p KEY=VALUE" in err and "-p robot=null" in err
    assert "it takes: robot, speed_mps=1.0" in err
    assert graph_main(["tests.test_graph:needs_a_robot", "-p", "robot=null", "-o",
                       str(out)]) == 0
    assert "digraph" in out.read_text()


def test_a_yaml_file_without_its_registry_says_to_pass_registry(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert graph_main([str(DATA / "patrol_sm.yaml"), "-o", "unused.dot"]) == 2
    err = capsys.readouterr().err
    assert "unknown action 'drive'" in err and "hint: name the file's actions with " \
        "--registry MODULE:ATTR" in err
    assert graph_main([str(DATA / "patrol_sm.yaml"), "--registry", "tests.test_graph:nothing"]
                      ) == 2
    assert "--registry 'tests.test_graph:nothing': 'tests.test_graph' has no mapping " \
        "'nothing'" in capsys.readouterr().err


def test_verbose_graph_logs_load_warnings(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                          caplog: pytest.LogCaptureFixture) -> None:
    spec = tmp_path / "unreachable_graph_v.yaml"
    spec.write_text("engine: state_machine\ninitial: a\nstates:\n  - {name: a}\n"
                    "  - {name: lonely_v}\n")
    out = tmp_path / "u.dot"
    assert graph_main(["-v", str(spec), "-o", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    assert "lonely_v" in out.read_text()
    assert any(r.levelname == "WARNING" and "lonely_v" in r.getMessage()
               for r in caplog.records), caplog.text
