"""The Debug HAL: an in-memory robot that tests and demos can poke.

:class:`DebugRobot` is the "hardware": a battery that can be drained or set, a strip of LEDs,
a display and buttons. It is thread-safe and outlives HAL loads, like a real robot outlives
its driver. :class:`DebugHAL` (name ``"debug"``) is the driver: it mirrors the robot onto
the blackboard and offers the methods logics call.

Blackboard keys (writer ``hal:debug``):

=======================  ========================================================
``battery/percentage``   float, 0–100
``battery/charging``     bool
``buttons/<name>``       bool, True while pressed (``a``, ``b`` by default)
``leds/color``           str, the colour of the whole strip (``"mixed"`` if not uniform)
``leds/<i>``             str, the colour of LED *i*
``display/symbol``       str, what the display shows (``""`` when blank)
=======================  ========================================================

Give several loads one robot by registering the HAL with it:
``ll.hals.register(DebugHAL, robot=robot)``; otherwise each instance makes its own.
"""

from __future__ import annotations

import asyncio
import math
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from beehave.errors import ConfigError
from beehave.hal import HAL, check_duration_s

__all__ = ["DebugHAL", "DebugRobot"]

RobotCallback = Callable[[str, Any], None]


class DebugRobot:
    """An in-memory robot; every setter notifies the subscribers with ``(key, value)``."""

    def __init__(self, *, battery_percentage: float = 100.0, n_leds: int = 4,
                 buttons: tuple[str, ...] = ("a", "b")) -> None:
        # Re-entrant, and held while notifying, so subscribers see changes in the order
        # they happened (a subscriber may poke the robot in turn).
        self._lock = threading.RLock()
        self._battery = float(battery_percentage)
        self._charging = False
        self._leds = ["off"] * n_leds
        self._display = ""
        self._buttons = dict.fromkeys(buttons, False)
        self._subscribers: tuple[RobotCallback, ...] = ()
        self.led_history: deque[str] = deque(maxlen=256)
        """Every colour the whole strip was set to, oldest first."""
        self.display_history: deque[str] = deque(maxlen=256)
        """Every symbol the display showed, oldest first."""

    # -- reading -------------------------------------------------------------------------

    @property
    def battery_percentage(self) -> float:
        return self._battery

    @property
    def charging(self) -> bool:
        return self._charging

    @property
    def leds(self) -> tuple[str, ...]:
        return tuple(self._leds)

    @property
    def led_color(self) -> str:
        """The strip's colour, or ``"mixed"``."""
        colors = set(self._leds)
        return colors.pop() if len(colors) == 1 else "mixed"

    @property
    def display(self) -> str:
        return self._display

    @property
    def buttons(self) -> dict[str, bool]:
        return dict(self._buttons)

    def state(self) -> dict[str, Any]:
        """Every blackboard key the HAL publishes, with its current value."""
        with self._lock:
            out: dict[str, Any] = {"battery/percentage": self._battery,
                                   "battery/charging": self._charging,
                                   "display/symbol": self._display,
                                   "leds/color": self.led_color}
            out.update({f"leds/{i}": c for i, c in enumerate(self._leds)})
            out.update({f"buttons/{b}": p for b, p in self._buttons.items()})
        return out

    # -- poking --------------------------------------------------------------------------

    def subscribe(self, callback: RobotCallback) -> Callable[[], None]:
        """Call ``callback(key, value)`` on every change; returns the unsubscribe function."""
        with self._lock:
            self._subscribers = (*self._subscribers, callback)

        def unsubscribe() -> None:
            with self._lock:
                self._subscribers = tuple(s for s in self._subscribers if s is not callback)

        return unsubscribe

    def _emit(self, items: dict[str, Any]) -> None:
        for callback in self._subscribers:
            for key, value in items.items():
                callback(key, value)

    def set_battery(self, percentage: float) -> None:
        with self._lock:
            self._battery = min(100.0, max(0.0, float(percentage)))
            value = self._battery
            self._emit({"battery/percentage": value})

    def drain(self, percentage: float) -> float:
        """Take ``percentage`` points off the battery; returns the new level."""
        with self._lock:
            self._battery = max(0.0, self._battery - float(percentage))
            value = self._battery
            self._emit({"battery/percentage": value})
        return value

    def set_charging(self, charging: bool) -> None:
        with self._lock:
            self._charging = bool(charging)
            self._emit({"battery/charging": bool(charging)})

    def press(self, button: str) -> None:
        self._set_button(button, True)

    def release(self, button: str) -> None:
        self._set_button(button, False)

    def _set_button(self, button: str, pressed: bool) -> None:
        with self._lock:
            if button not in self._buttons:
                raise KeyError(f"debug robot has no button {button!r}; buttons: "
                               f"{sorted(self._buttons)}")
            self._buttons[button] = pressed
            self._emit({f"buttons/{button}": pressed})

    def set_leds(self, color: str) -> None:
        with self._lock:
            self._leds = [color] * len(self._leds)
            self.led_history.append(color)
            items: dict[str, Any] = {f"leds/{i}": color for i in range(len(self._leds))}
            items["leds/color"] = color
            self._emit(items)

    def set_led(self, index: int, color: str) -> None:
        with self._lock:
            if not 0 <= index < len(self._leds):
                raise IndexError(f"debug robot has LEDs 0..{len(self._leds) - 1}, not {index}")
            self._leds[index] = color
            strip = self.led_color
            self._emit({f"leds/{index}": color, "leds/color": strip})

    def show(self, symbol: str) -> None:
        with self._lock:
            self._display = symbol
            self.display_history.append(symbol)
            self._emit({"display/symbol": symbol})


class DebugHAL(HAL):
    """Driver of a :class:`DebugRobot`.

    ``drain_pct_per_s`` drains the battery while the HAL runs (for demos), in steps every
    ``tick_s``. ``battery_max_age_s`` declares how fresh ``battery/percentage`` must be.
    Tests can break it: :meth:`crash` makes the running ``run()`` raise, ``fail_runs = n``
    makes the next *n* starts of ``run()`` raise at once.
    """

    name = "debug"

    def __init__(self, *, robot: DebugRobot | None = None, drain_pct_per_s: float = 0.0,
                 tick_s: float = 0.05, battery_max_age_s: float | None = None) -> None:
        self.robot = robot if robot is not None else DebugRobot()
        self.drain_pct_per_s = check_rate("drain_pct_per_s", drain_pct_per_s)
        self.tick_s = check_duration_s("tick_s", tick_s)
        self.battery_max_age_s = (None if battery_max_age_s is None
                                  else check_duration_s("battery_max_age_s", battery_max_age_s))
        self.fail_runs = 0
        self.runs = 0
        """How many times ``run()`` was started."""
        self.safe_states = 0
        """How many times ``safe_state()`` ran."""
        self._crash: BaseException | None = None
        self._wake: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._crash_lock = threading.Lock()

    # -- lifecycle -----------------------------------------------------------------------

    async def on_load(self) -> None:
        if self.battery_max_age_s is not None:
            self.blackboard.declare("battery/percentage", max_age_s=self.battery_max_age_s)
        self._publish_all()

    def _publish_all(self) -> None:
        for key, value in self.robot.state().items():
            self.blackboard.set(key, value)

    async def run(self) -> None:
        self.runs += 1
        if self.fail_runs > 0:
            self.fail_runs -= 1
            raise RuntimeError(f"debug HAL: injected failure of run() #{self.runs}")
        self._loop = asyncio.get_running_loop()
        with self._crash_lock:
            self._wake = asyncio.Event()
            self._crash = None
        unsubscribe = self.robot.subscribe(self.blackboard.set)
        try:
            self._publish_all()  # fresh again after a restart
            while True:
                timeout = self.tick_s if self.drain_pct_per_s > 0 else None
                try:
                    # asyncio.timeout, not wait_for: on Python 3.11 wait_for can swallow a
                    # cancellation that arrives as the inner wait completes.
                    async with asyncio.timeout(timeout):
                        await self._wake.wait()
                except TimeoutError:
                    self.robot.drain(self.drain_pct_per_s * self.tick_s)
                    continue
                with self._crash_lock:
                    crash, self._crash = self._crash, None
                    self._wake.clear()
                if crash is not None:
                    raise crash
        finally:
            unsubscribe()

    def safe_state(self) -> None:
        """LEDs off, display blank."""
        self.safe_states += 1
        self.robot.set_leds("off")
        self.robot.show("")

    # -- what logics call ----------------------------------------------------------------

    def set_leds(self, color: str) -> None:
        """Set the whole LED strip to ``color``."""
        self.robot.set_leds(color)

    def set_led(self, index: int, color: str) -> None:
        self.robot.set_led(index, color)

    def show(self, symbol: str) -> None:
        """Show ``symbol`` on the display (``""`` blanks it)."""
        self.robot.show(symbol)

    # -- what tests call -----------------------------------------------------------------

    def crash(self, error: BaseException | None = None) -> None:
        """Make the running ``run()`` raise ``error`` (default RuntimeError); any thread."""
        with self._crash_lock:
            self._crash = error or RuntimeError("debug HAL: injected crash")
            wake, loop = self._wake, self._loop
        if wake is None or loop is None:
            raise RuntimeError("debug HAL is not running; nothing to crash")
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            wake.set()
        else:
            loop.call_soon_threadsafe(wake.set)


def check_rate(name: str, value: float) -> float:
    """A finite rate ≥ 0 (``drain_pct_per_s``); else :class:`ConfigError` naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value < 0:
        raise ConfigError(f"{name} must be a finite number ≥ 0, got {value!r}")
    return float(value)
