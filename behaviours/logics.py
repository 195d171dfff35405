"""Ready-made logics for the low level: LED colour and display symbol from the battery.

Both work with any HAL that offers the methods they call (the Debug HAL does), and read
``battery/percentage`` from the blackboard.
"""

from __future__ import annotations

from typing import Protocol, cast

from beehave.logic import Logic

__all__ = ["DisplayLogic", "EmiliDisplayLogic", "EmiliLedLogic", "EmiliLogic", "KobukiLedLogic",
           "LedLogic"]

BATTERY_KEY = "battery/percentage"


class _Leds(Protocol):
    def set_leds(self, color: str) -> None: ...


class _Display(Protocol):
    def show(self, symbol: str) -> None: ...


class LedLogic(Logic):
    """LEDs ``low`` (red) while the battery is below ``threshold`` percent, else ``normal``
    (green); ``unknown`` (yellow) while the battery reading is stale (HAL down)."""

    def __init__(self, threshold: float = 20.0, *, hal: str = "debug", normal: str = "green",
                 low: str = "red", unknown: str = "yellow") -> None:
        self.threshold = threshold
        self.hal_name = hal
        self.colors = {"normal": normal, "low": low, "unknown": unknown}

    def color_for(self, percentage: float | None, stale: bool) -> str:
        if stale or percentage is None:
            return self.colors["unknown"]
        return self.colors["low"] if percentage < self.threshold else self.colors["normal"]

    async def run(self) -> None:
        leds = cast(_Leds, await self.hal(self.hal_name))
        shown: str | None = None
        async for change in self.blackboard.watch(BATTERY_KEY):
            color = self.color_for(change.value, change.stale)
            if color != shown:  # only relevant changes reach the hardware
                leds.set_leds(color)
                shown = color


class DisplayLogic(Logic):
    """The display shows ``symbol`` (``"battery-low"``) while the battery is below
    ``threshold`` percent, else the charge (``"57%"``)."""

    def __init__(self, threshold: float = 20.0, *, hal: str = "debug",
                 symbol: str = "battery-low") -> None:
        self.threshold = threshold
        self.hal_name = hal
        self.symbol = symbol

    async def run(self) -> None:
        display = cast(_Display, await self.hal(self.hal_name))
        shown: str | None = None
        async for change in self.blackboard.watch(BATTERY_KEY):
            if change.stale:
                text = "?"
            elif change.value < self.threshold:
                text = self.symbol
            else:
                text = f"{change.value:.0f}%"
            if text != shown:
                display.show(text)
                shown = text


# --------------------------------------------------------------------------- EMILI, Kobuki
# The paper's low-level evaluation: the LEDs and the display follow the battery and what
# the high level does (``high_level/running``, written by the ROS bridge).

LIGHT_BLUE = (0.35, 0.75, 1.0)
RED = (1.0, 0.0, 0.0)
YELLOW = (1.0, 0.85, 0.0)
ORANGE = (1.0, 0.45, 0.0)
PURPLE = (0.6, 0.0, 0.8)
DIM_WHITE = (0.3, 0.3, 0.3)
OFF = (0.0, 0.0, 0.0)


def running_classes(running: object) -> set[str]:
    """The classes of the running actions in ``high_level/running``."""
    if not isinstance(running, list):
        return set()
    return {str(item.get("class")) for item in running
            if isinstance(item, dict) and item.get("kind") == "action"}


class _RgbLeds(Protocol):
    def set_color(self, r: float, g: float, b: float) -> None: ...


class EmiliLedLogic(Logic):
    """EMILI's LED strip: red while the battery is below ``threshold`` %; else light blue
    while laser-based free navigation runs, blinking yellow while lane following, orange
    while the lift moves, purple in ``maintenance``; dim white otherwise."""

    def __init__(self, threshold: float = 20.0, *, blink_s: float = 0.5,
                 maintenance: bool = False) -> None:
        self.threshold, self.blink_s, self.maintenance = threshold, blink_s, maintenance

    def pattern(self, battery: float | None, running: set[str]) -> str:
        if battery is not None and battery < self.threshold:
            return "battery_low"
        if self.maintenance:
            return "maintenance"
        if "Navigation" in running:
            return "navigation"
        if "LaneFollowing" in running:
            return "lane_following"
        if "Lift" in running:
            return "lifting"
        return "idle"

    async def run(self) -> None:

        leds = cast(_RgbLeds, await self.hal("emili_leds"))
        await self.hal("battery")
        colours = {"battery_low": RED, "maintenance": PURPLE, "navigation": LIGHT_BLUE,
                   "lifting": ORANGE, "idle": DIM_WHITE}
        watcher = self.blackboard.watch("**")
        shown: tuple[float, float, float] | None = None
        shown_mode: str | None = None
        blink_on = True
        while True:
            if await watcher.next(self.blink_s) is None:
                blink_on = not blink_on
            battery = self.blackboard.get(BATTERY_KEY, fresh=True)
            mode = self.pattern(battery, running_classes(self.blackboard.get("high_level/running")))
            if mode != shown_mode:  # only changes: this logic watches what it writes
                self.blackboard.set("leds/pattern", mode)
                shown_mode = mode
            colour = (YELLOW if blink_on else OFF) if mode == "lane_following" else colours[mode]
            if colour != shown:
                leds.set_color(*colour)
                shown = colour


class _TextDisplay(Protocol):
    def show(self, text: str) -> None: ...


class EmiliDisplayLogic(Logic):
    """EMILI's display: the battery-low symbol below ``threshold`` %, else the current task
    (``behaviour: action``), ``MAINTENANCE`` in maintenance."""

    BATTERY_LOW = "[!] BATTERY LOW"

    def __init__(self, threshold: float = 20.0, *, maintenance: bool = False) -> None:
        self.threshold, self.maintenance = threshold, maintenance

    def text(self, battery: float | None, behavior: object, running: object) -> str:
        if battery is not None and battery < self.threshold:
            return self.BATTERY_LOW
        if self.maintenance:
            return "MAINTENANCE"
        actions = sorted(running_classes(running))
        task = str(behavior or "idle")
        return f"{task}: {', '.join(actions)}" if actions else task

    async def run(self) -> None:
        display = cast(_TextDisplay, await self.hal("display"))
        await self.hal("battery")
        shown: str | None = None
        async for change in self.blackboard.watch("**"):
            if not (change.key.startswith("battery/") or change.key.startswith("high_level/")):
                continue
            text = self.text(self.blackboard.get(BATTERY_KEY, fresh=True),
                             self.blackboard.get("high_level/behavior"),
                             self.blackboard.get("high_level/running"))
            if text != shown:
                display.show(text)
                shown = text


class EmiliLogic(Logic):
    """EMILI's top-level logic: LEDs and display as sub-logics."""

    def __init__(self, threshold: float = 20.0, *, maintenance: bool = False) -> None:
        self.threshold, self.maintenance = threshold, maintenance

    async def run(self) -> None:
        import asyncio

        self.start_logic(EmiliLedLogic(self.threshold, maintenance=self.maintenance),
                         name="leds")
        self.start_logic(EmiliDisplayLogic(self.threshold, maintenance=self.maintenance),
                         name="display")
        await asyncio.Event().wait()  # the sub-logics do the work until we are cancelled


class _KobukiLeds(Protocol):
    def set(self, led1: str, led2: str) -> None: ...


class KobukiLedLogic(Logic):
    """Kobuki's two LEDs: LED1 the battery (green > 50 %, orange > ``threshold``, red);
    LED2 red while a bumper is pressed, green while driving, off otherwise."""

    def __init__(self, threshold: float = 20.0) -> None:
        self.threshold = threshold

    def colours(self, battery: float | None, bumped: bool, driving: bool) -> tuple[str, str]:
        if battery is None:
            led1 = "off"
        elif battery > 50:
            led1 = "green"
        elif battery > self.threshold:
            led1 = "orange"
        else:
            led1 = "red"
        led2 = "red" if bumped else ("green" if driving else "off")
        return led1, led2

    async def run(self) -> None:
        leds = cast(_KobukiLeds, await self.hal("kobuki_leds"))
        await self.hal("battery")
        await self.hal("kobuki_bumpers")
        shown: tuple[str, str] | None = None
        async for change in self.blackboard.watch("**"):
            if not change.key.startswith(("battery/", "bumper/", "high_level/")):
                continue
            bumped = any(bool(self.blackboard.get(f"bumper/{s}"))
                         for s in ("left", "center", "right"))
            locks = self.blackboard.get("high_level/locks") or {}
            pair = self.colours(self.blackboard.get(BATTERY_KEY, fresh=True), bumped,
                                isinstance(locks, dict) and "driving" in locks)
            if pair != shown:
                leds.set(*pair)
                shown = pair
