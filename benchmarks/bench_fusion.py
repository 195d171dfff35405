"""Priority fusion: the arbiter's overhead per cycle with 10 proposers.

One :meth:`~beehave.fusion.Arbiter.cycle` (select the winner among 10 sources, forward it,
publish ``fusion/cmd_vel/winner``) on a blackboard, the forward itself a no-op so that only
the arbitration is timed. Two cases: the highest source is fresh (the first look wins), and
only the lowest one is (every source is looked at: the worst case, which the target is
for). The floor measured in the same run: a bare cycle that reads one proposal from the
blackboard and forwards it, with no arbitration at all.
"""

from __future__ import annotations

import asyncio
import gc
import time
from typing import Any

from beehave.blackboard import Blackboard
from beehave.events import EventBus
from beehave.fusion import Arbiter, FusionInput, check_twist, proposal_key
from benchmarks._util import percentile, report

CYCLES = 20_000
SOURCES = 10
TARGET_US = 20.0
NS = 1e-3  # ns → µs


class _Clock:
    t = 0.0

    def __call__(self) -> float:
        return self.t


class _NullArbiter(Arbiter):
    default_safe_value = (0.0, 0.0)

    def check(self, value: Any) -> tuple[float, float]:
        return check_twist(value)

    def forward(self, value: Any) -> None:
        pass


def _arbiter(board: Blackboard) -> _NullArbiter:
    inputs = {f"s{i}": FusionInput(priority=i, max_age_s=0.5, safety=i == SOURCES - 1)
              for i in range(SOURCES)}
    arb = _NullArbiter(actuator="cmd_vel", inputs=inputs, rate_hz=50.0)
    arb.blackboard = board.client("hal:fusion_cmd_vel")
    arb.events = EventBus()
    asyncio.run(arb.on_load())  # declares the keys, subscribes; the board stays unbound
    return arb


def _time_cycles(arb: _NullArbiter) -> list[float]:
    samples: list[float] = []
    cycle = arb.cycle
    clock = time.perf_counter_ns
    for _ in range(CYCLES):
        t0 = clock()
        cycle()
        samples.append((clock() - t0) * NS)
    return samples


def _time_floor(board: Blackboard) -> list[float]:
    samples: list[float] = []
    key = proposal_key("cmd_vel", "s0")
    sink: list[Any] = []
    forward = sink.append
    clock = time.perf_counter_ns
    for _ in range(CYCLES):
        t0 = clock()
        forward(board.get(key))
        samples.append((clock() - t0) * NS)
        sink.clear()
    return samples


def main() -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    gc.disable()
    try:
        clock = _Clock()
        board = Blackboard(clock=clock)
        arb = _arbiter(board)
        for i in range(SOURCES):
            arb.propose(f"s{i}", (0.1 * i, 0.0))
        best = _time_cycles(arb)
        assert arb.winner == f"s{SOURCES - 1}"
        # Only the lowest source stays fresh: every other one is looked at and refused.
        clock.t = 0.4
        arb.propose("s0", (0.05, 0.0))
        clock.t = 0.6
        worst = _time_cycles(arb)
        assert arb.winner == "s0"
        floor = _time_floor(board)
    finally:
        gc.enable()
    p50 = percentile(worst, 50)
    rows.append(report("fusion cycle, 10 proposers, only the lowest fresh (p50)", p50, "µs",
                       f"<= {TARGET_US:g} µs", p50 <= TARGET_US))
    rows.append(report("fusion cycle, 10 proposers, only the lowest fresh (p99)",
                       percentile(worst, 99), "µs"))
    rows.append(report("fusion cycle, 10 proposers, the highest fresh (p50)",
                       percentile(best, 50), "µs"))
    rows.append(report("floor: read one proposal and forward it, no arbitration (p50)",
                       percentile(floor, 50), "µs"))
    return rows


if __name__ == "__main__":
    main()
