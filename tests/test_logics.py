"""The ready-made low-level logics, through the demo that shows them."""

from __future__ import annotations

import io

from rich.console import Console

from behaviours.demos.lowlevel import run_lowlevel_demo
from behaviours.logics import LedLogic


def test_led_logic_colour_table() -> None:
    logic = LedLogic(threshold=20)
    assert [logic.color_for(p, stale) for p, stale in
            ((50.0, False), (20.0, False), (19.9, False), (50.0, True), (None, False))] \
        == ["green", "green", "red", "yellow", "yellow"]


def test_lowlevel_demo_shows_leds_reacting_and_a_switch_and_says_so() -> None:
    out = io.StringIO()
    assert run_lowlevel_demo(Console(file=out, width=100)) is True
    text = out.getvalue()
    assert "LEDs red" in text and "battery-low" in text and "✗" not in text
