"""The ``beehave`` command line, run for real: ``python -m beehave.cli`` in a subprocess
(this worktree's packages), checked by exit status and what it prints.

Exit status: 0 ok, 1 a failure while running, 2 bad arguments or configuration.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from beehave.testing import WALL_TIMEOUT_S

ROOT = Path(__file__).resolve().parent.parent
HERE = ROOT / "tests"
CONFIGS = HERE / "data" / "config"
# How long a user waits before pressing Ctrl-C again: part of the scenario, not a bound on
# an outcome (the test accepts either way out), so it stays short.
CTRL_C_AGAIN_S = 3.0


def beehave(*args: str, timeout_s: float = WALL_TIMEOUT_S) -> subprocess.CompletedProcess[str]:
    """``beehave ARGS`` in a subprocess, with tests/ on the path for the fixtures."""
    return subprocess.run([sys.executable, "-m", "beehave.cli", *args], cwd=ROOT,
                          env=_env(), capture_output=True, text=True, timeout=timeout_s)


def _env() -> dict[str, str]:
    path = os.pathsep.join(p for p in (str(HERE), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "PYTHONPATH": path}


# ---- global options before a command (-v sim, -v graph) ----------------------------------

def test_verbose_before_sim_reaches_the_sim_parser() -> None:
    done = beehave("-v", "sim", "-h")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: beehave sim"), done.stdout
    assert "Traceback" not in done.stderr, done.stderr


def test_verbose_before_graph_renders(tmp_path: Path) -> None:
    out = tmp_path / "sm.dot"
    done = beehave("-v", "graph", "tests/data/patrol_sm.yaml", "-o", str(out),
                   "--registry", "tests.test_yaml_behavior:REGISTRY")
    assert done.returncode == 0, done.stderr
    assert "digraph" in out.read_text()


def test_unknown_command_lists_the_commands() -> None:
    done = beehave("-v", "rn")
    assert done.returncode == 2
    assert "invalid choice: 'rn'" in done.stderr and "'run'" in done.stderr, done.stderr


# ---- non-finite numbers on the command line and in the configuration --------------------

@pytest.mark.parametrize("value", ["inf", "nan", "-1", "soon", "1e10"])
def test_run_duration_must_be_finite(value: str) -> None:
    done = beehave("run", str(CONFIGS / "waits.yaml"), "--duration-s", value)
    assert done.returncode == 2
    assert "argument --duration-s: expected a" in done.stderr, done.stderr
    assert repr(value) in done.stderr, done.stderr


@pytest.mark.parametrize("value", ["inf", "nan", "-1"])
def test_sim_duration_must_be_finite(value: str) -> None:
    done = beehave("sim", "--duration-s", value)
    assert done.returncode == 2
    assert "--duration-s must be a positive, finite number" in done.stderr, done.stderr


@pytest.mark.parametrize("value", ["inf", "nan", "0", "5000"])
def test_sim_clock_rate_must_be_sane(value: str) -> None:
    done = beehave("sim", "--clock-rate-hz", value)
    assert done.returncode == 2
    assert "--clock-rate-hz must be in [1, 1000]" in done.stderr, done.stderr


@pytest.mark.parametrize("value", ["inf", "nan", "0"])
def test_demo_real_time_factor_must_be_finite_and_positive(value: str) -> None:
    done = beehave("demo", "--real-time-factor", value)
    assert done.returncode == 2
    assert "argument --real-time-factor: expected a finite number > 0" in done.stderr, \
        done.stderr
    assert "--fast" in done.stderr  # the way to say "no pacing"


def test_infinite_stop_timeout_in_the_file_is_refused_before_start(tmp_path: Path) -> None:
    config = tmp_path / "r.yaml"
    config.write_text("namespace: r\nstop_timeout_s: .inf\n")
    done = beehave("run", str(config), "--duration-s", "0")
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.startswith(f"beehave run: {config}: stop_timeout_s: Input should be "
                                  "a finite number"), done.stderr
    assert "running" not in done.stdout


# ---- errors inside `with robot:` ---------------------------------------------------------

@pytest.mark.parametrize(("config", "expected"), [
    ("explodes.yaml",
     "explodes.yaml: behaviors.boom: behavior 'boom': Explodes.__init__ raised RuntimeError"),
    # The shipped worlds grow (droid, factory …): every one is listed, warehouse among them.
    ("unknown_world.yaml", "unknown_world.yaml: sim.world: unknown world 'atlantis'; "
                           "registered: "),
])
def test_errors_at_start_are_one_message_and_exit_2(config: str, expected: str) -> None:
    if config == "unknown_world.yaml":
        pytest.importorskip("pybullet")
    pytest.importorskip("rclpy")
    done = beehave("run", str(CONFIGS / config), "--duration-s", "5")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert f"beehave run: {CONFIGS / config}" in done.stderr, done.stderr
    assert expected in done.stderr, done.stderr
    assert "motor controller not found" in done.stderr or config != "explodes.yaml"
    assert "running" not in done.stdout  # it never claimed to run


def test_bad_parameters_exit_2_with_file_and_key() -> None:
    config = CONFIGS / "bad_params.yaml"
    done = beehave("run", str(config))
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.startswith(f"beehave run: {config}: behaviors.tour.params: "), \
        done.stderr
    assert "speed_mps" in done.stderr  # what it accepts


@pytest.mark.parametrize("where", ["high", "low"])
def test_an_error_while_leaving_the_robot_is_reported_and_everything_stops(
        where: str, monkeypatch: pytest.MonkeyPatch,
        capfd: pytest.CaptureFixture[str]) -> None:
    """A manager whose shutdown raises (as a low level whose loop was blocked does) gives
    a message and exit 1; the other manager, the bridges and the ROS executor still stop."""
    pytest.importorskip("rclpy")
    from beehave.cli import main
    from beehave.errors import BeehaveError
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.lowlevel import LowLevelBehaviorManager
    from beehave.testing import wait_until

    cls: Any = HighLevelBehaviorManager if where == "high" else LowLevelBehaviorManager
    real = cls.shutdown

    def failing_shutdown(self: Any) -> None:
        real(self)
        raise BeehaveError(f"{where}-level loop blocked for 9.9 s by logic 'x'")

    monkeypatch.setattr(cls, "shutdown", failing_shutdown)
    monkeypatch.syspath_prepend(str(HERE))
    before = set(threading.enumerate())
    handler = signal.getsignal(signal.SIGINT)
    code = main(["run", str(CONFIGS / "waits.yaml"), "--duration-s", "0.2"])
    err = capfd.readouterr().err
    assert code == 1, err
    assert f"beehave run: {where}-level loop blocked for 9.9 s by logic 'x'" in err, err
    assert "raised while shutting the robot down" in err, err
    # Everything the robot started has ended (ROS executor, low-level loop, workers).
    assert wait_until(lambda: not [t for t in threading.enumerate()
                                   if t not in before and t.is_alive()]), \
        [t.name for t in threading.enumerate() if t not in before]
    assert signal.getsignal(signal.SIGINT) is handler  # restored


def test_a_failed_start_leaves_nothing_running(monkeypatch: pytest.MonkeyPatch,
                                              capfd: pytest.CaptureFixture[str]) -> None:
    """The default behaviour's constructor fails after the nodes, the low level and the
    bridges are up: all of it is shut down again before the message."""
    pytest.importorskip("rclpy")
    from beehave.cli import main
    from beehave.testing import wait_until

    monkeypatch.syspath_prepend(str(HERE))
    before = set(threading.enumerate())
    assert main(["run", str(CONFIGS / "explodes.yaml")]) == 2
    assert ("behaviors.boom: behavior 'boom': Explodes.__init__ raised RuntimeError"
            in capfd.readouterr().err)
    assert wait_until(lambda: not [t for t in threading.enumerate()
                                   if t not in before and t.is_alive()]), \
        [t.name for t in threading.enumerate() if t not in before]


def test_a_blocked_event_loop_never_hangs_the_process() -> None:
    """A logic that blocks the event loop: Ctrl-C ends the process with a message and a
    non-zero status — at the first signal once shutdown is bounded, at the latest at the
    second one (the forced exit)."""
    pytest.importorskip("rclpy")
    proc = subprocess.Popen([sys.executable, "-m", "beehave.cli", "run",
                             str(CONFIGS / "blocks_loop.yaml")], cwd=ROOT, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        seen = []
        for line in proc.stdout:  # until the logic blocks the loop (or EOF if it died)
            seen.append(line)
            if "blocking the event loop now" in line:
                break
        assert any("running" in line for line in seen), seen
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=CTRL_C_AGAIN_S)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)  # the user presses Ctrl-C again
        out, err = proc.communicate(timeout=WALL_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode not in (0, None), (out, err)
    assert proc.returncode != -signal.SIGINT  # ended by beehave, not killed by the signal
    # The message is ours (second signal, or the LoopBlocked error of a bounded shutdown)
    # or the low level's watchdog's: either way the user is told why it did not stop cleanly.
    assert "blocked" in err or "beehave run:" in err, err


# ---- help that tells the truth ------------------------------------------------------------

def test_demo_out_is_a_folder() -> None:
    helped = beehave("demo", "-h")
    assert "--out FOLDER" in helped.stdout and "demo.png" in helped.stdout, helped.stdout
    done = beehave("demo", "--out", "picture.png")
    assert done.returncode == 2
    assert "--out is a folder" in done.stderr and "'picture.png'" in done.stderr, done.stderr


def test_top_level_help_lists_every_command_and_the_exit_status() -> None:
    done = beehave("-h")
    assert done.returncode == 0
    for command in ("demo", "run", "graph", "sim"):
        assert f"\n    {command} " in done.stdout, done.stdout
    assert "exit status: 0 ok, 1 a failure while running, 2 bad arguments" in done.stdout
    assert "``" not in done.stdout  # no reStructuredText markup in a terminal
