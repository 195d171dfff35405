"""Replay: a low level run again on its recording produces the same outputs; a changed
logic is caught at its first divergence; a recording without what a replay needs is
refused naming the missing channels. (The demo's replay: tests/test_replay_demo.py.)"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from replay_fixtures import recorded_low

from beehave.config import RobotConfig, parse_config
from beehave.errors import RecordingError
from beehave.recording import Recorder, read_recording
from beehave.recording.replay import Output, compare, replay
from beehave.testing import wait_until
from hal.debug import DebugRobot


def _config(threshold: float = 20.0) -> RobotConfig:
    return parse_config({
        "namespace": "bot",
        "stop_timeout_s": 0.5,
        "logics": {"leds": {"class": "behaviours.logics:LedLogic",
                            "params": {"threshold": threshold}},
                   "display": {"class": "behaviours.logics:DisplayLogic"}},
        "default_logic": "leds",
        "hals": ["debug"],
    }, source="bot.yaml")


def _record_live(path: Path) -> DebugRobot:
    """A low level (debug HAL, LED logic) recorded while its battery drains and its logic
    is switched once, as `beehave run --record` records it (without ROS)."""
    hardware = DebugRobot(battery_percentage=40.0)
    with recorded_low(path, _config(), hardware) as low:
        assert wait_until(lambda: "debug" in low.hals.loaded)
        # Each step waits for the logic's answer: a watcher coalesces changes it has
        # not taken yet, and this test is about replaying what happened, not a race.
        for pct, colour in ((35.0, "green"), (25.0, "green"), (15.0, "red"),
                            (10.0, "red"), (30.0, "green"), (12.0, "red")):
            hardware.set_battery(pct)
            assert wait_until(lambda c=colour: hardware.led_color == c)  # type: ignore[misc]
            time.sleep(0.01)
        low.switch("display")
        for pct, text in ((50.0, "50%"), (18.0, "battery-low"), (60.0, "60%")):
            hardware.set_battery(pct)
            assert wait_until(lambda t=text: hardware.display == t)  # type: ignore[misc]
            time.sleep(0.01)
    return hardware


def test_replay_reproduces_the_logic_outputs(tmp_path: Path) -> None:
    path = tmp_path / "bot.mcap"
    hardware = _record_live(path)
    assert list(hardware.led_history)[:4] == ["green", "red", "green", "red"]

    result = replay(path, _config(), speed=None)

    assert result.divergence is None, result.divergence
    keys = [o.key for o in result.outputs]
    assert keys.count("debug.set_leds") == 4  # green, red, green, red
    assert "debug.show" in keys and keys.count("logic") == 2  # the start, then display
    assert [o.value for o in result.outputs if o.key == "debug.set_leds"] == \
        [[["green"], {}], [["red"], {}], [["green"], {}], [["red"], {}]]
    assert result.fed > 10 and not result.warnings


def test_a_changed_logic_is_reported_at_its_first_divergence(tmp_path: Path) -> None:
    path = tmp_path / "bot.mcap"
    _record_live(path)
    # Same recording, a logic whose threshold moved to 33 %: at 30 % it stays red, where
    # the recorded one turned green again.
    result = replay(path, _config(threshold=33.0), speed=None)
    div = result.divergence
    assert div is not None
    assert (div.key, div.index, div.expected, div.got) == \
        ("debug.set_leds", 2, [["green"], {}], None)
    recorded = [o for o in result.expected if o.key == "debug.set_leds"]
    assert div.t_s == pytest.approx(recorded[2].t_s)
    assert "debug.set_leds" in str(div) and f"t={div.t_s:.3f} s" in str(div)


def test_the_replay_check_fixture_passes_the_same_logic_and_fails_a_changed_one(
        tmp_path: Path, replay_check: Any) -> None:
    """The test kit's regression check (docs/testing.md): a reference recording, the same
    configuration passes, a changed threshold fails naming the first divergence."""
    path = tmp_path / "bot.mcap"
    _record_live(path)
    result = replay_check(path, _config())
    assert result.divergence is None and result.fed > 10
    with pytest.raises(pytest.fail.Exception, match=r"diverged .*debug\.set_leds"):
        replay_check(path, _config(threshold=33.0))


def test_paced_replay_follows_the_recorded_times(tmp_path: Path) -> None:
    path = tmp_path / "bot.mcap"
    _record_live(path)
    result = replay(path, _config(), speed=1.0)
    assert result.divergence is None
    # Real-time pacing: the replay takes (at least) the recorded span.
    assert result.span_s > 0.05  # else the check below holds without any pacing
    assert result.wall_s >= result.span_s * 0.9


def test_replay_window_compares_only_inside_it(tmp_path: Path) -> None:
    path = tmp_path / "bot.mcap"
    _record_live(path)
    whole = replay(path, _config(), speed=None)
    leds = [o for o in whole.expected if o.key == "debug.set_leds"]
    start = (leds[1].t_s + leds[2].t_s) / 2  # after the first red, before green again
    part = replay(path, _config(), speed=None, from_s=start)
    assert part.divergence is None, part.divergence
    assert part.expected and all(o.t_s >= start for o in part.expected)
    assert [o.value for o in part.outputs if o.key == "debug.set_leds"][-1] == [["red"], {}]


def test_missing_channels_are_named(tmp_path: Path) -> None:
    from beehave.blackboard import Blackboard

    path = tmp_path / "partial.mcap"
    board = Blackboard()
    with Recorder(path) as recorder:
        recorder.attach_blackboard(board, prefix="bot")
        board.set("battery/percentage", 50.0, writer="hal:debug")
    with pytest.raises(RecordingError) as err:
        replay(path, _config(), speed=None)
    text = str(err.value)
    assert "/bot/beehave/events/low" in text and "/bot/beehave/outputs" in text
    assert "/bot/beehave/blackboard" in text.split("has:")[1]  # what it does have
    with pytest.raises(RecordingError, match="robots recorded: 'bot'"):
        replay(path, _config(), prefix="emili1", speed=None)


def test_compare_takes_the_earliest_stream_difference() -> None:
    def o(key: str, value: Any, t: float) -> Output:
        return Output(key, value, t)

    want = [o("a", 1, 0.0), o("b", 1, 1.0), o("a", 2, 2.0), o("b", 2, 3.0)]
    assert compare(want, list(want)) is None
    got = [o("a", 1, 0.0), o("b", 1, 1.0), o("a", 3, 2.5), o("b", 9, 2.9)]
    div = compare(want, got)
    assert div is not None and (div.key, div.index, div.t_s) == ("a", 1, 2.0)
    missing = compare(want, want[:3])
    assert missing is not None and missing.key == "b" and missing.got is None


def test_recording_reads_back_the_live_run(tmp_path: Path) -> None:
    path = tmp_path / "bot.mcap"
    _record_live(path)
    rec = read_recording(path)
    assert rec.prefixes == ["bot"] and not rec.truncated and rec.dropped() == 0
    commands = rec.of("/bot/beehave/outputs")
    assert [m.data["args"] for m in commands][:2] == [["green"], ["red"]]
