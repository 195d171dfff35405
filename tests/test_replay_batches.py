"""Replay groups the recorded writes as the logics saw them, not by wall-clock gaps.

A logic runs between two loop callbacks, so what it saw together is what the loop
delivered between two of its steps. The recorder stamps each blackboard change with that
*batch*; the replay feeds one batch per loop turn. Here both ways a wall-clock rule goes
wrong are made to happen on purpose, with the display logic (the charge, or
``battery-low`` below 20 %):

- *seen apart, stamped close*: in the loop, a write of 15 %, the logic's step
  (``battery-low``), a write of 30 % (``30%``) -- microseconds apart;
- *seen together, stamped far apart*: while the loop is busy, another thread writes 12 %,
  waits 5 ms (ten times the old 0.5 ms rule), writes 35 %; the loop then delivers only
  35 %, and the display goes from ``30%`` to ``35%`` without ``battery-low`` between.

A replay by wall time shows ``30%`` before ``battery-low``: the first divergence.
"""

from __future__ import annotations

import asyncio
import functools
import threading
import time
from pathlib import Path
from typing import Any, cast

import pytest
from replay_fixtures import recorded_low

from beehave.config import RobotConfig, parse_config
from beehave.logic import Logic
from beehave.recording import read_recording
from beehave.recording import recorder as recorder_module
from beehave.recording import writer as writer_module
from beehave.recording.replay import replay
from beehave.testing import WALL_TIMEOUT_S, wait_until
from hal.debug import DebugHAL, DebugRobot

KEY = "battery/percentage"


def _config() -> RobotConfig:
    return parse_config({
        "namespace": "bot",
        "stop_timeout_s": 0.5,
        "logics": {"display": {"class": "behaviours.logics:DisplayLogic"}},
        "default_logic": "display",
        "hals": ["debug"],
    }, source="bot.yaml")


def _record(path: Path) -> DebugRobot:
    hardware = DebugRobot(battery_percentage=40.0)
    with recorded_low(path, _config(), hardware) as low:
        assert wait_until(lambda: hardware.display == "40%")
        board = low.blackboard

        async def apart() -> None:  # seen apart, stamped close
            board.set(KEY, 15.0, writer="hal:debug")
            for _ in range(5):  # the logic's step: battery-low
                await asyncio.sleep(0)
            board.set(KEY, 30.0, writer="hal:debug")
            for _ in range(5):
                await asyncio.sleep(0)

        low.call(apart())
        assert list(hardware.display_history) == ["40%", "battery-low", "30%"]

        # Seen together, stamped far apart: the loop is held in a callback meanwhile.
        entered, release = threading.Event(), threading.Event()

        def busy() -> None:
            entered.set()
            release.wait(WALL_TIMEOUT_S)

        loop = low.loop
        assert loop is not None
        loop.call_soon_threadsafe(busy)
        assert entered.wait(WALL_TIMEOUT_S)
        hardware.set_battery(12.0)
        time.sleep(0.005)
        hardware.set_battery(35.0)
        release.set()

        async def settled() -> None:
            for _ in range(10):
                await asyncio.sleep(0)

        low.call(settled())
        assert list(hardware.display_history) == ["40%", "battery-low", "30%", "35%"]
    return hardware


def _battery_writes(path: Path) -> list[dict[str, object]]:
    rec = read_recording(path)
    return [m.data for m in rec.of("/bot/beehave/blackboard")
            if m.data["key"] == KEY and m.data["writer"] == "hal:debug"
            and not m.data["stale"]]


def test_the_recording_says_which_writes_the_logic_saw_together(tmp_path: Path) -> None:
    path = tmp_path / "bot.mcap"
    _record(path)
    writes = _battery_writes(path)
    assert [w["value"] for w in writes] == [40.0, 15.0, 30.0, 12.0, 35.0]
    first, apart_15, apart_30, together_12, together_35 = (w["batch"] for w in writes)
    assert isinstance(apart_15, int) and isinstance(apart_30, int)
    assert isinstance(together_12, int)
    assert apart_15 < apart_30  # the logic ran between them
    assert together_12 == together_35  # the loop delivered them in one callback
    assert apart_30 < together_12  # batches follow the order the logics saw them in
    assert first is not None


def test_replay_follows_the_batches_under_any_timing(tmp_path: Path) -> None:
    path = tmp_path / "bot.mcap"
    _record(path)
    result = replay(path, _config(), speed=None)
    assert result.divergence is None, result.divergence
    assert [o.value[0][0] for o in result.outputs if o.key == "debug.show"] == \
        ["40%", "battery-low", "30%", "35%"]


def test_a_recording_without_batches_replays_by_wall_time(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    """Recordings made before batch ids still replay, with the 0.5 ms rule (which gets
    both cases above wrong, so this run waits for the logic after each write)."""
    encode = recorder_module._encode_change

    def old_format(item: Any) -> tuple[int, bytes]:
        return encode((item[0], item[1], None))

    monkeypatch.setattr(recorder_module, "_encode_change", old_format)
    monkeypatch.setattr(recorder_module, "_encode_changes",
                        functools.partial(writer_module._encode_each, old_format))
    path = tmp_path / "old.mcap"
    hardware = DebugRobot(battery_percentage=40.0)
    with recorded_low(path, _config(), hardware):
        for pct, text in ((40.0, "40%"), (15.0, "battery-low"), (30.0, "30%")):
            hardware.set_battery(pct)
            assert wait_until(lambda t=text: hardware.display == t)  # type: ignore[misc]
            time.sleep(0.01)
    assert all("batch" not in w for w in _battery_writes(path))
    result = replay(path, _config(), speed=None)
    assert result.divergence is None, result.divergence
    assert [o.value[0][0] for o in result.outputs if o.key == "debug.show"] == \
        ["40%", "battery-low", "30%"]


class PairLogic(Logic):
    """Shows ``x/y`` each time ``in/x`` changes, reading both with ``get()`` -- as EMILI's
    display reads the battery and the high level's state."""

    async def run(self) -> None:
        display = cast(DebugHAL, await self.hal("debug"))
        shown: str | None = None
        async for _ in self.blackboard.watch("in/x"):
            text = f"{self.blackboard.get('in/x')}/{self.blackboard.get('in/y')}"
            if text != shown:
                display.show(text)
                shown = text


def _pair_config() -> RobotConfig:
    return parse_config({
        "namespace": "bot",
        "stop_timeout_s": 0.5,
        "logics": {"pair": {"class": f"{__name__}:PairLogic"}},
        "default_logic": "pair",
        "hals": ["debug"],
    }, source="bot.yaml")


def test_a_write_stored_before_the_step_counts_in_its_batch(tmp_path: Path) -> None:
    """A write from another thread that is stored after a logic was woken but before its
    step runs is read by that step (``get()`` sees it at once, delivered or not): it
    belongs to the batch the step saw, although the loop delivers it only later."""
    path = tmp_path / "bot.mcap"
    hardware = DebugRobot()
    with recorded_low(path, _pair_config(), hardware) as low:
        assert wait_until(lambda: "debug" in low.hals.loaded)

        async def settled() -> None:
            for _ in range(10):
                await asyncio.sleep(0)

        low.call(settled())  # the logic waits on its watcher
        board = low.blackboard

        def woken_then_written() -> None:  # one loop callback
            board.set("in/x", 1, writer="hal:debug")  # wakes the logic
            other = threading.Thread(target=board.set, args=("in/y", 1),
                                     kwargs={"writer": "hal:debug"})
            other.start()
            other.join()

        loop = low.loop
        assert loop is not None
        loop.call_soon_threadsafe(woken_then_written)
        assert wait_until(lambda: hardware.display == "1/1")
    writes = {m.data["key"]: m.data["batch"] for m in read_recording(path).of(
        "/bot/beehave/blackboard") if m.data["key"].startswith("in/")}
    assert writes["in/x"] == writes["in/y"]
    result = replay(path, _pair_config(), speed=None)
    assert result.divergence is None, result.divergence
    assert [o.value[0][0] for o in result.outputs if o.key == "debug.show"] == ["1/1"]
