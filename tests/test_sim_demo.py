"""The main demo checks its goals in the physics; run it as ``beehave demo --fast`` does
(as fast as possible), which the README advertises. Lockstep keeps fast mode correct: the
controllers hold the physics at each of their steps, so a reaction time measured in sim time
does not grow with the speed-up."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

pytest.importorskip("pybullet")
pytest.importorskip("rclpy")

from rich.console import Console  # noqa: E402

from beehave.testing import beehave_threads, wait_until  # noqa: E402
from behaviours.demos.warehouse import run_sim_demo  # noqa: E402


def test_fast_sim_demo_reaches_every_goal(tmp_path: Path) -> None:
    before = set(beehave_threads())
    out = io.StringIO()
    problems = run_sim_demo(Console(file=out, width=120), real_time_factor=None,
                            out_dir=tmp_path, live_display=False)
    assert problems == [], out.getvalue()
    picture = tmp_path / "demo.png"
    assert picture.exists() and picture.stat().st_size > 5000
    assert wait_until(lambda: not [t for t in beehave_threads() if t not in before], 5)
