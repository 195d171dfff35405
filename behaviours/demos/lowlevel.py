"""Low-level demo: the LED logic reacts to a draining Debug HAL battery, then the top-level
logic is switched to the display logic and back. Called by ``beehave demo``."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from rich.console import Console

from beehave.events import Event, EventKind
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.testing import wait_until
from behaviours.logics import DisplayLogic, LedLogic
from hal.debug import DebugHAL, DebugRobot

THRESHOLD = 20.0
STEP_S = 0.12


def _wait(predicate: Callable[[], bool]) -> bool:
    """Wait for a state reached through the loop (a safety net, never a pacing sleep)."""
    return wait_until(predicate, timeout_s=2.0)


def run_lowlevel_demo(console: Console) -> bool:
    """Show the low level at work; True when everything shown really happened."""
    robot = DebugRobot(battery_percentage=30.0)
    ll = LowLevelBehaviorManager(default="leds")
    ll.register("leds", LedLogic, threshold=THRESHOLD)
    ll.register("display", DisplayLogic, threshold=THRESHOLD)
    ll.hals.register(DebugHAL, robot=robot)
    checks: dict[str, bool] = {}
    notes: list[str] = []
    lock = threading.Lock()

    def on_event(event: Event) -> None:
        if event.kind in (EventKind.SWITCH_COMPLETED, EventKind.STARTED, EventKind.ENDED):
            with lock:
                notes.append(f"{event.kind.value} {event.subject}"
                             f"{' ' + event.status if event.status else ''}")

    def flush_notes() -> None:
        with lock:
            lines, notes[:] = list(notes), []
        for line in lines:
            console.print(f"    [dim]event: {line}[/dim]")

    ll.subscribe(on_event)
    console.rule("[bold]low level: logics, blackboard, HALs")
    started = time.monotonic()
    with ll:
        bb = ll.blackboard
        checks["led logic runs by default"] = ll.current == "leds"
        checks["LEDs green at 30 %"] = _wait(lambda: robot.led_color == "green")
        flush_notes()
        console.print(f"  top-level logic [cyan]{ll.current}[/cyan]; LEDs turn red below "
                      f"{THRESHOLD:.0f} %; draining the Debug HAL battery:")
        turned_red_at: float | None = None
        while robot.battery_percentage > 14:
            level = robot.drain(2.0)
            wanted = "red" if level < THRESHOLD else "green"
            def arrived(lv: float = level, w: str = wanted) -> bool:
                return bool(bb.get("battery/percentage") == lv and robot.led_color == w)

            ok = _wait(arrived)
            color = robot.led_color
            style = "red" if color == "red" else "green"
            console.print(f"    battery [bold]{level:5.1f} %[/bold]  →  LEDs "
                          f"[{style}]{color}[/{style}]" + ("" if ok else "  [red](late)[/red]"))
            if color == "red" and turned_red_at is None:
                turned_red_at = level
            time.sleep(STEP_S)  # pace for the reader
        checks["LEDs red below threshold"] = (turned_red_at is not None
                                              and turned_red_at < THRESHOLD
                                              and bb.get("leds/color") == "red")
        entry = bb.entry("leds/color")
        checks["HAL wrote the LED state"] = entry is not None and entry.writer == "hal:debug"

        console.print("  [bold]switch[/bold] leds → display (cancels the LED logic; the "
                      "HAL both logics use stays loaded)")
        hal_before = ll.hals.loaded.get("debug")
        t0 = time.perf_counter()
        ll.switch("display")
        took_ms = (time.perf_counter() - t0) * 1000
        checks["display logic runs"] = ll.current == "display"
        checks["display shows battery-low"] = _wait(lambda: robot.display == "battery-low")
        checks["HAL kept across the switch"] = (hal_before is not None
                                                and ll.hals.loaded.get("debug") is hal_before)
        flush_notes()
        console.print(f"    switched in {took_ms:.1f} ms; display shows "
                      f"[bold]{robot.display!r}[/bold], LEDs [dim]{robot.led_color}[/dim]")

        robot.set_battery(80.0)
        checks["display follows the charge"] = _wait(lambda: robot.display == "80%")
        console.print(f"    battery charged to 80 % → display [bold]{robot.display!r}[/bold]")
        ll.switch("leds")
        checks["back to LEDs: green at 80 %"] = _wait(lambda: robot.led_color == "green")
        flush_notes()
        console.print(f"  [bold]switch[/bold] display → leds: LEDs "
                      f"[green]{robot.led_color}[/green]")
        checks["one shared HAL instance"] = len(ll.hals.loaded) == 1
    checks["HAL unloaded at shutdown"] = ll.hals.loaded == {} and robot.led_color == "off"
    for name, ok in checks.items():
        mark = "[green]✓[/green]" if ok else "[red]✗[/red]"
        console.print(f"  {mark} {name}")
    console.print(f"  low-level demo took {time.monotonic() - started:.1f} s")
    return all(checks.values())
