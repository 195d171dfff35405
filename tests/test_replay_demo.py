"""Replay determinism on the main demo: record `beehave demo --fast --record`, replay each
robot's logics on the recording at `--speed max`, and get the same LED colours, display
texts and logic switches as live. Also checks what `beehave inspect` and `beehave plot`
make of the recording."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

pytest.importorskip("pybullet")
pytest.importorskip("rclpy")

from rich.console import Console  # noqa: E402

from beehave.cli import main  # noqa: E402
from beehave.recording import read_recording  # noqa: E402
from behaviours.demos.warehouse import CONFIG_DIR, run_sim_demo  # noqa: E402
from behaviours.logics import LIGHT_BLUE  # noqa: E402


def test_demo_recording_replays_to_the_same_decisions(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    path = tmp_path / "demo.mcap"
    out = io.StringIO()
    with capsys.disabled():  # rclpy's executor wants the real stdout
        problems = run_sim_demo(Console(file=out, width=120), real_time_factor=None,
                                out_dir=tmp_path, live_display=False, record=path)
    assert problems == [], out.getvalue()
    assert f"into {path}" in out.getvalue()

    rec = read_recording(path)
    assert rec.prefixes == ["emili1", "kobuki1"] and rec.dropped() == 0
    for robot in ("emili1", "kobuki1"):
        for channel in ("beehave/blackboard", "beehave/events/high", "beehave/events/low",
                        "beehave/outputs", "beehave/clock", "odom", "scan", "cmd_vel",
                        "battery_state"):
            assert rec.channels[f"/{robot}/{channel}"].count > 0, (robot, channel)
    commands = [m.data for m in rec.of("/emili1/beehave/outputs")]
    assert {"hal": "emili_leds", "method": "set_color", "args": list(LIGHT_BLUE)}.items() \
        <= next(c for c in commands if c["args"] == list(LIGHT_BLUE)).items()
    switches = [m.data["subject"] for m in rec.of("/emili1/beehave/events/high")
                if m.data["kind"] == "switch_completed"]
    assert switches == ["idle", "tour", "commanded", "maintenance"]

    capsys.readouterr()
    for config in ("emili.yaml", "kobuki.yaml"):
        code = main(["replay", str(path), "--robot", str(CONFIG_DIR / config),
                     "--speed", "max"])
        printed = capsys.readouterr().out
        assert code == 0, printed
        assert "deterministic" in printed and "(sim time)" in printed

    assert main(["inspect", str(path), "--limit", "500"]) == 0
    shown = capsys.readouterr().out
    assert "/emili1/odom" in shown and "switch_completed  maintenance" in shown

    picture = tmp_path / "timeline.png"
    assert main(["plot", str(path), "-o", str(picture)]) == 0
    assert picture.stat().st_size > 20_000
