"""The main demo checks its goals in the physics; run it (as fast as possible)."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

pytest.importorskip("pybullet")
pytest.importorskip("rclpy")

from rich.console import Console  # noqa: E402

from beehave.testing import beehave_threads, wait_until  # noqa: E402
from behaviours.demos.warehouse import run_sim_demo  # noqa: E402


def test_sim_demo_reaches_every_goal(tmp_path: Path) -> None:
    before = set(beehave_threads())
    out = io.StringIO()
    # A bounded speed-up: the demo checks a reaction time in sim time (wheels stopped
    # within 0.2 s of the switch), which wall-time delays would inflate at full speed.
    problems = run_sim_demo(Console(file=out, width=120), real_time_factor=2.0,
                            out_dir=tmp_path, live_display=False)
    assert problems == [], out.getvalue()
    picture = tmp_path / "demo.png"
    assert picture.exists() and picture.stat().st_size > 5000
    assert wait_until(lambda: not [t for t in beehave_threads() if t not in before], 5)
