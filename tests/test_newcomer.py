"""What a new user tripped over (issue 27, item 7), checked as that user works: the
``beehave`` command from another directory, the documented Python as written."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from beehave.testing import WALL_TIMEOUT_S, wall_timeout

ROOT = Path(__file__).resolve().parent.parent
CONFIG = str(ROOT / "tests" / "data" / "config" / "waits.yaml")


def beehave(*args: str, cwd: Path | str = ROOT, timeout_s: float = 120
            ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "beehave.cli", *args], cwd=cwd,
                          env=_env(), capture_output=True, text=True, timeout=timeout_s)


def _env() -> dict[str, str]:
    """This checkout's beehave wherever the command runs (the tests' own helper modules,
    such as config_fixtures, are not on the path: a user's robot has none of them)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    return env


def test_class_paths_resolve_from_the_config_directory_from_any_cwd(tmp_path: Path) -> None:
    """``class: mybots.behaviors:Wander`` beside robot.yaml works when ``beehave run`` is
    started in another directory (it said "No module named 'mybots'")."""
    pytest.importorskip("rclpy")
    project = tmp_path / "project"
    (project / "mybots").mkdir(parents=True)
    (project / "mybots" / "__init__.py").write_text("")
    (project / "mybots" / "behaviors.py").write_text(textwrap.dedent("""
        from beehave import Behavior

        class Wander(Behavior):
            def run(self) -> None:
                while self.sleep(0.1):
                    pass
    """))
    (project / "robot.yaml").write_text(textwrap.dedent("""
        namespace: newcomer
        stop_timeout_s: 0.5
        behaviors:
          wander: {class: "mybots.behaviors:Wander"}
        default_behavior: wander
        hals: [debug]
    """))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    done = beehave("run", str(project / "robot.yaml"), "--duration-s", "0.5", cwd=elsewhere)
    assert done.returncode == 0, done.stderr
    assert "stopped cleanly" in done.stdout, done.stdout

    # A module that is nowhere: the error says where import paths are looked up.
    (project / "bad.yaml").write_text(textwrap.dedent("""
        namespace: newcomer
        behaviors:
          wander: {class: "yourbots.behaviors:Wander"}
    """))
    done = beehave("run", str(project / "bad.yaml"), cwd=elsewhere)
    assert done.returncode == 2, done
    assert "behaviors.wander.class: cannot import module 'yourbots.behaviors'" in done.stderr
    assert "configuration file's directory" in done.stderr, done.stderr


def test_run_world_takes_the_world_names_sim_takes() -> None:
    """``beehave run --http 0 --world warehouse`` serves the shipped warehouse as the map;
    an unknown name is refused before anything starts, naming the shipped worlds."""
    pytest.importorskip("fastapi")
    pytest.importorskip("pybullet")
    import httpx

    done = beehave("run", CONFIG, "--http", "0", "--world", "warehous")
    assert done.returncode == 2, done
    assert "--world warehous: unknown world 'warehous'" in done.stderr, done.stderr
    assert "'warehouse'" in done.stderr, done.stderr
    assert "running" not in done.stdout

    env = _env()
    env["PYTHONPATH"] += os.pathsep + str(ROOT / "tests")  # waits.yaml's config_fixtures
    proc = subprocess.Popen(
        [sys.executable, "-m", "beehave.cli", "run", CONFIG, "--http", "127.0.0.1:0",
         "--world", "warehouse", "--duration-s", "120"], cwd=ROOT, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        lines, match = [], None
        for line in proc.stdout:
            lines.append(line)
            match = re.search(r"web view and API at (http://127\.0\.0\.1:\d+/)", line)
            if match:
                break
        assert match, "".join(lines)
        world = httpx.get(match.group(1) + "api/world", timeout=WALL_TIMEOUT_S).json()
        assert world["walls"] and world["floor"]
        shipped = (ROOT / "robots" / "worlds" / "warehouse.yaml").read_text()
        for station in world["stations"]:
            assert station["name"] in shipped
        proc.send_signal(signal.SIGINT)
        rest = proc.communicate(timeout=wall_timeout(2.0))[0]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WALL_TIMEOUT_S)
    assert proc.returncode == 0, "".join(lines) + rest


def test_the_tutorial_shows_writing_the_blackboard_from_plain_python(tmp_path: Path) -> None:
    text = (ROOT / "docs" / "tutorial.md").read_text()
    section = text[text.index("## 3."):text.index("## 4.")]
    assert "hl.blackboard.set(" in section
    program = tmp_path / "blackboard.py"
    program.write_text("\n\n".join(re.findall(r"```python\n(.*?)```", section, re.S)))
    done = subprocess.run([sys.executable, str(program)], capture_output=True, text=True,
                          timeout=WALL_TIMEOUT_S, cwd=tmp_path, env=_env())
    assert done.returncode == 0, done.stderr
    assert "SUCCEEDED heading for dock" in done.stdout, done.stdout


def test_the_docs_give_the_colour_format_of_set_leds() -> None:
    """docs/lowlevel.md says what set_leds takes, and it is what the HALs accept."""
    from hal.debug import DebugHAL
    from hal.kobuki import LED_COLORS

    text = (ROOT / "docs" / "lowlevel.md").read_text()
    section = text[text.index("**LED colours.**"):]
    section = section[:section.index("\n\n")]
    assert "`set_leds(color)`" in section and "colour *name*" in section
    assert "set_color(r, g, b)" in section and "0–1" in section
    for color in LED_COLORS:
        assert f"`{color}`" in section
    assert "set_leds" in vars(DebugHAL)
