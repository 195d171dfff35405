"""Ready-made logics for the low level: LED colour and display symbol from the battery.

Both work with any HAL that offers the methods they call (the Debug HAL does), and read
``battery/percentage`` from the blackboard.
"""

from __future__ import annotations

from typing import Protocol, cast

from beehave.logic import Logic

__all__ = ["DisplayLogic", "LedLogic"]

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
