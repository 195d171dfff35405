"""The Debug HAL: the HAL contract, plus its in-memory robot."""

from __future__ import annotations

import asyncio
from typing import Any

from hal_contract import HALContract

from beehave.events import Event
from beehave.hal import HALManager
from hal.debug import DebugHAL, DebugRobot


class TestDebugHAL(HALContract):
    hal_cls = DebugHAL
    entry_point = "debug"
    expected_keys = ("battery/percentage", "battery/charging", "buttons/a", "buttons/b",
                     "leds/color", "leds/0", "display/symbol")


def test_poking_the_robot_updates_the_blackboard() -> None:
    robot = DebugRobot(battery_percentage=50)

    async def body(manager: HALManager, events: list[Event]) -> dict[str, Any]:
        hal = await manager.load("debug")
        assert isinstance(hal, DebugHAL)
        await HALContract.settle()
        robot.drain(30)
        robot.press("a")
        hal.set_leds("red")
        hal.show("battery-low")
        bb = manager.blackboard
        return {k: bb.get(k) for k in ("battery/percentage", "buttons/a", "leds/color",
                                       "leds/3", "display/symbol")}

    contract = TestDebugHAL()
    contract.hal_params = lambda: {"robot": robot}  # type: ignore[method-assign]
    got = contract.run_with_manager(body)
    assert got == {"battery/percentage": 20.0, "buttons/a": True, "leds/color": "red",
                   "leds/3": "red", "display/symbol": "battery-low"}
    assert list(robot.led_history)[-2:] == ["red", "off"]  # "off": safe state at unload
    assert robot.display == ""


def test_drain_rate_drains_the_battery_while_running() -> None:
    robot = DebugRobot(battery_percentage=100)

    async def body(manager: HALManager, events: list[Event]) -> float:
        await manager.load("debug")
        while robot.battery_percentage > 99:
            await asyncio.sleep(0.005)
        return float(manager.blackboard.get("battery/percentage"))

    contract = TestDebugHAL()
    contract.hal_params = lambda: {"robot": robot, "drain_pct_per_s": 100.0,  # type: ignore[method-assign]
                                   "tick_s": 0.005}
    assert contract.run_with_manager(body) <= 99


def test_robot_rejects_unknown_buttons_and_leds_naming_what_exists() -> None:
    robot = DebugRobot(n_leds=2)
    try:
        robot.press("z")
    except KeyError as err:
        assert "'z'" in str(err) and "['a', 'b']" in str(err)
    else:
        raise AssertionError("no KeyError")
    try:
        robot.set_led(5, "red")
    except IndexError as err:
        assert "0..1" in str(err)
    else:
        raise AssertionError("no IndexError")


def test_debug_hal_rejects_non_finite_durations_and_rates_naming_them() -> None:
    import pytest

    from beehave.errors import ConfigError

    for kwargs, name in (({"tick_s": float("inf")}, "tick_s"),
                         ({"tick_s": float("nan")}, "tick_s"),
                         ({"drain_pct_per_s": float("inf")}, "drain_pct_per_s"),
                         ({"battery_max_age_s": float("nan")}, "battery_max_age_s")):
        with pytest.raises(ConfigError, match=name):
            DebugHAL(**kwargs)
