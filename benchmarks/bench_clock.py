"""The test kit's virtual clock: how fast a mission of minutes runs in a test.

- ``clock_mission_wall_ms``: a ten-minute mission (a behaviour that sleeps 1 s 600 times
  beside an action that sleeps 0.5 s 1200 times: 1,800 deadlines), moved by
  ``clock.advance(600)``; median wall time of 5 runs. Target: at most 1 s (a test of a
  ten-minute mission takes under a second).
- ``clock_autojump_wall_ms``: the same mission with autojump, waited for by the test.
- ``clock_speedup``: virtual seconds per wall second for the manual run (the ratio against
  real time, the baseline a test on the wall clock would have).
- ``clock_vs_wall_ratio``: a 2-second mission of 0.01 s sleeps (200 deadlines) run once on
  the wall clock (the baseline, in the same process) and on the virtual clock by hand: the
  wall time of the virtual run over the baseline's (target: at most 0.1).
- ``clock_low_level_wall_ms``: the low level: a logic that sleeps 0.1 s 6,000 times
  (``asyncio.sleep`` on the virtual loop), ``advance(600)``. Target: at most 2 s.

Run: ``python -m benchmarks clock``.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from beehave import Action, Behavior, HighLevelBehaviorManager, Logic, LowLevelBehaviorManager
from beehave.clock import VirtualClock
from benchmarks._util import median, report

MISSION_S = 600.0
RUNS = 5


class _Blink(Action):
    action_type = "lights"

    def run(self) -> int:
        n = 0
        while self.sleep(0.5):
            n += 1
        return n


class _Mission(Behavior):
    def run(self) -> int:
        self.start_action(_Blink())
        n = 0
        while n < int(MISSION_S) and self.sleep(1.0):
            n += 1
        return n


def _mission(autojump: bool) -> float:
    clock = VirtualClock(autojump=autojump)
    try:
        with HighLevelBehaviorManager(clock=clock, stop_timeout_s=1.0) as hl:
            hl.register("mission", _Mission)
            start = time.perf_counter()
            mission = hl.switch("mission")
            if autojump:
                if not mission.wait(60.0):
                    raise RuntimeError("the autojump mission did not end within 60 s")
            else:
                clock.advance(MISSION_S)
            wall = time.perf_counter() - start
            if mission.result != int(MISSION_S):
                raise RuntimeError(f"mission result {mission.result}, expected {MISSION_S}")
            return wall
    finally:
        clock.close()


class _Short(Behavior):
    def run(self) -> int:
        n = 0
        while n < 200 and self.sleep(0.01):
            n += 1
        return n


def _short(clock: Any) -> float:
    with HighLevelBehaviorManager(clock=clock, stop_timeout_s=1.0) as hl:
        hl.register("short", _Short)
        start = time.perf_counter()
        short = hl.switch("short")
        if isinstance(clock, VirtualClock):
            clock.advance(2.0)
        if not short.wait(30.0) or short.result != 200:
            raise RuntimeError(f"short mission: {short.status} {short.result}")
        return time.perf_counter() - start


def _low_level() -> float:
    clock = VirtualClock()
    ticks = [0]

    class Tick(Logic):
        async def run(self) -> None:
            while True:
                await asyncio.sleep(0.1)
                ticks[0] += 1

    with LowLevelBehaviorManager(clock=clock) as ll:
        ll.register("tick", Tick)
        ll.switch("tick")
        start = time.perf_counter()
        clock.advance(MISSION_S)
        wall = time.perf_counter() - start
    if ticks[0] != 6000:
        raise RuntimeError(f"{ticks[0]} ticks, expected 6000")
    return wall


def main() -> list[dict[str, Any]]:
    manual = median([_mission(False) for _ in range(RUNS)])
    jumping = median([_mission(True) for _ in range(RUNS)])
    low = median([_low_level() for _ in range(RUNS)])
    from beehave.clock import WallClock

    wall_baseline = _short(WallClock())
    virtual = median([_short(VirtualClock()) for _ in range(RUNS)])
    return [
        report("clock_mission_wall_ms", manual * 1e3, "ms", "<= 1000 ms",
               manual <= 1.0, deadlines=1800, runs=RUNS),
        report("clock_autojump_wall_ms", jumping * 1e3, "ms", "<= 1000 ms",
               jumping <= 1.0, deadlines=1800, runs=RUNS),
        report("clock_speedup", MISSION_S / manual, "x real time", None, None,
               baseline="the same mission on the wall clock: 600 s"),
        report("clock_vs_wall_ratio", virtual / wall_baseline, "ratio", "<= 0.1",
               virtual / wall_baseline <= 0.1, virtual_ms=round(virtual * 1e3, 1),
               wall_baseline_ms=round(wall_baseline * 1e3, 1)),
        report("clock_low_level_wall_ms", low * 1e3, "ms", "<= 2000 ms", low <= 2.0,
               deadlines=6000, runs=RUNS),
    ]
