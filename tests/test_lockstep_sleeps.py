"""``lockstep_sleeps``: a behaviour's timed steps held in lockstep with a simulation, as a
driving action's control periods are (the demo's chime: live under load it sounded late in
sim time, its replay on time, and the replay reported a divergence)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

pytest.importorskip("rclpy")

from std_msgs.msg import String  # noqa: E402

from beehave import Behavior, HighLevelBehaviorManager  # noqa: E402
from beehave.clock import SimClock  # noqa: E402
from beehave.testing import wait_until  # noqa: E402
from behaviours.actions import lockstep_sleeps  # noqa: E402
from robots import topics  # noqa: E402
from tests.ros_probe import Probe  # noqa: E402


class Ticker(Behavior):
    def run(self) -> int:
        steps = 0
        with lockstep_sleeps(self) as sleep:
            while steps < 3 and sleep(1.0):
                steps += 1
        return steps


@dataclass
class Rig:
    """A manager on a hand-moved sim clock (at 10 s) with a node, a probe on ``/lockstep``
    and the ``Ticker`` started."""

    clock: SimClock
    hl: HighLevelBehaviorManager
    heard: list[Any]
    ticker: Any

    def holds(self) -> list[Any]:
        return [json.loads(m.data)["until_s"] for m in list(self.heard)]


@pytest.fixture
def rig() -> Iterator[Rig]:
    probe = Probe()
    clock = SimClock()
    clock.set_time(10.0)
    hl = HighLevelBehaviorManager(node=probe.ros.create_node("ticker_robot"), clock=clock)
    try:
        heard = probe.record(String, topics.LOCKSTEP)
        hl.register("ticker", Ticker)
        hl.start()
        yield Rig(clock, hl, heard, hl.request_switch("ticker"))
    finally:
        hl.shutdown()
        probe.ros.shutdown()


def test_each_sleep_holds_the_simulation_where_it_ends_and_the_end_lets_it_go(
        rig: Rig) -> None:
    def announced(until_s: float | None) -> bool:
        holds = rig.holds()
        return bool(holds) and holds[-1] == until_s

    # The simulation may not run past a step before the behaviour has taken it.
    for step_s in (11.0, 12.0, 13.0):
        assert wait_until(lambda step_s=step_s: announced(step_s)), rig.holds()
        rig.clock.set_time(step_s)
    assert wait_until(lambda: announced(None)), rig.holds()  # done: let go
    assert wait_until(lambda: rig.ticker.status.finished) and rig.ticker.result == 3
    assert rig.holds() == [11.0, 12.0, 13.0, None], rig.holds()
    participants = {json.loads(m.data)["participant"] for m in list(rig.heard)}
    assert len(participants) == 1 and "ticker" in participants.pop()


def test_a_pause_lets_the_simulation_go_and_the_resume_holds_it_again(rig: Rig) -> None:
    """Paused, the behaviour's time stands still: the simulation (and every other robot in
    it) must not wait for it meanwhile."""
    def last() -> Any:
        holds = rig.holds()
        return holds[-1] if holds else "nothing"

    assert wait_until(lambda: last() == 11.0), last()
    rig.hl.pause()
    assert wait_until(lambda: last() is None), last()
    rig.clock.set_time(10.5)  # time runs on for the world, not for the paused behaviour
    rig.hl.resume()
    assert wait_until(lambda: last() == 11.5), last()  # the 0.5 s it had left
