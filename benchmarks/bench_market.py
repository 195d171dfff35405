"""Market-based allocation (``python -m benchmarks market``).

- ``market_quality_single``: 20 single-robot tasks, 10 robots (seeded random instances,
  places in a 20 m × 20 m hall). A robot bids the round trip from its base to the task
  at 1 m/s and takes at most 2 tasks; the optimum is computed centrally by
  ``scipy.optimize.linear_sum_assignment`` (every robot as two slots). Figure: median of
  (sum of the auction's costs / optimum), sequential single-item auctions and batch
  mode; target ≤ 1.15.
- ``market_quality_coalition``: 10 two-role tasks (``fetch`` at a shelf, ``serve`` at a
  table) for 5 robots of at most 5 roles each; the optimum by exhaustive search
  (dynamic programming over the tasks and every robot's remaining capacity). Same figure.
- ``market_award``: one auction (cfp → accept-proposals) with 10 brokers, each in its
  own process, p50/p99 over repeated auctions; target p99 ≤ 30 ms.
- ``market_reaward``: a member killed (SIGKILL) while it works → the next award of its
  role, with the brokers' lease of 1 s (a dead process is noticed when its lease runs out).

The quality figures run the auctioneer's own decision code (:func:`~beehave.agents.
market.choose`, which every auction round calls on the bids it collected) on brokers'
bids computed in this process; the award figures run the whole protocol over DDS.
Children: ``tests/market_node.py`` (a scripted broker).
"""

from __future__ import annotations

import functools
import math
import os
import random
import sys
import threading
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(101, 200)))

TESTS = Path(__file__).resolve().parents[1] / "tests"
sys.path.insert(0, str(TESTS))  # the agent tests' process helper, shared with them

from agent_procs import AgentProc, stop_all  # noqa: E402

from beehave.agents import Agent, Role, Task, TaskState, auction  # noqa: E402
from beehave.agents.market import Bids, choose  # noqa: E402
from benchmarks._util import median, percentile, report  # noqa: E402

NODE = TESTS / "market_node.py"
SEEDS = int(os.environ.get("BENCH_MARKET_SEEDS", 50))
N_AUCTIONS = int(os.environ.get("BENCH_MARKET_N", 60))
N_KILLS = int(os.environ.get("BENCH_MARKET_KILLS", 3))
LEASE_S = 1.0

Point = tuple[float, float]


def _dist(a: Point, b: Point) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _place(rng: random.Random) -> Point:
    return (rng.uniform(0, 20), rng.uniform(0, 20))


# ---------------------------------------------------------------------- quality
def _auction_single(bases: list[Point], tasks: list[Point], cap: int, *,
                    batch: bool) -> float:
    """Sum of costs of the market's assignment (cost = round trip at 1 m/s)."""
    load = [0] * len(bases)
    waiting = list(range(len(tasks)))
    total = 0.0
    while waiting:
        batch_now = waiting if batch else waiting[:1]
        bids: Bids = {}
        for t in batch_now:  # brokers refuse once their queue is full
            bids[(str(t), "main", "go")] = {
                str(r): 2 * _dist(b, tasks[t]) for r, b in enumerate(bases) if load[r] < cap}
        chosen = choose({str(t): {"main": ["go"]} for t in batch_now}, bids, batch=batch)
        assert chosen, "capacity covers every task"
        for tid, c in chosen.items():
            r = int(c.members["go"])
            load[r] += 1
            total += c.cost
            waiting.remove(int(tid))
    return total


def _optimum_single(bases: list[Point], tasks: list[Point], cap: int) -> float:
    import numpy as np
    from scipy.optimize import linear_sum_assignment

    cost = np.array([[2 * _dist(b, t) for b in bases for _ in range(cap)] for t in tasks])
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].sum())


def _auction_pairs(bases: list[Point], tasks: list[tuple[Point, Point]], cap: int, *,
                   batch: bool) -> float:
    load = [0] * len(bases)
    waiting = list(range(len(tasks)))
    total = 0.0
    while waiting:
        batch_now = waiting if batch else waiting[:1]
        bids: Bids = {}
        for t in batch_now:
            for i, role in enumerate(("fetch", "serve")):
                bids[(str(t), "main", role)] = {
                    str(r): 2 * _dist(b, tasks[t][i])
                    for r, b in enumerate(bases) if load[r] < cap}
        chosen = choose({str(t): {"main": ["fetch", "serve"]} for t in batch_now}, bids,
                        batch=batch)
        assert chosen, "capacity covers every role"
        for tid, c in chosen.items():
            for broker in c.members.values():
                load[int(broker)] += 1
            total += c.cost
            waiting.remove(int(tid))
    return total


def _optimum_pairs(bases: list[Point], tasks: list[tuple[Point, Point]], cap: int) -> float:
    """Exhaustive: every task's (fetch, serve) on two distinct robots, every robot at
    most ``cap`` roles; dynamic programming over (task, remaining capacities)."""
    n = len(bases)
    pairs = [(a, b) for a in range(n) for b in range(n) if a != b]

    @functools.cache
    def best(i: int, left: tuple[int, ...]) -> float:
        if i == len(tasks):
            return 0.0
        out = math.inf
        for a, b in pairs:
            if left[a] and left[b]:
                nxt = list(left)
                nxt[a] -= 1
                nxt[b] -= 1
                cost = 2 * _dist(bases[a], tasks[i][0]) + 2 * _dist(bases[b], tasks[i][1])
                out = min(out, cost + best(i + 1, tuple(nxt)))
        return out

    return best(0, tuple([cap] * n))


def quality() -> list[dict[str, Any]]:
    rows = []
    single: dict[str, list[float]] = {"sequential": [], "batch": []}
    pairs: dict[str, list[float]] = {"sequential": [], "batch": []}
    for seed in range(SEEDS):
        rng = random.Random(seed)
        bases = [_place(rng) for _ in range(10)]
        tasks = [_place(rng) for _ in range(20)]
        opt = _optimum_single(bases, tasks, 2)
        for mode in single:
            single[mode].append(_auction_single(bases, tasks, 2, batch=mode == "batch") / opt)
        bases5 = [_place(rng) for _ in range(5)]
        duo = [(_place(rng), _place(rng)) for _ in range(10)]
        opt2 = _optimum_pairs(bases5, duo, 5)
        for mode in pairs:
            pairs[mode].append(_auction_pairs(bases5, duo, 5, batch=mode == "batch") / opt2)
    for name, table in (("market_quality_single", single),
                        ("market_quality_coalition", pairs)):
        for mode, ratios in table.items():
            m = median(ratios)
            rows.append(report(f"{name}_{mode}", m, "x optimum", "<= 1.15 median",
                               m <= 1.15, seeds=SEEDS, worst=round(max(ratios), 3)))
    return rows


# ---------------------------------------------------------------------- over DDS
def _Broker(name: str, caps: str, cost: float) -> AgentProc:  # noqa: N802 - reads as a class
    """A scripted broker process (``tests/market_node.py``)."""
    return AgentProc(name, [sys.executable, str(NODE), name, "--caps", caps,
                            "--cost", str(cost), "--lease-s", str(LEASE_S)], wait_s=60.0)


def _wait_brokers(agent: Agent, names: set[str]) -> None:
    deadline = time.monotonic() + 60
    while {i.name for i in agent.directory.search("broker")} < names:
        if time.monotonic() > deadline:
            raise RuntimeError(f"brokers {names} not seen")
        time.sleep(0.05)


def award_latency() -> list[dict[str, Any]]:
    tag = random.randint(0, 99999)
    procs = [_Broker(f"bm{tag}_{i}", "carry", 1.0 + i) for i in range(10)]
    rows = []
    try:
        for p in procs:
            p.wait_event("ready")
        with Agent(f"bm{tag}_boss", lease_s=LEASE_S) as boss:
            _wait_brokers(boss, {p.name for p in procs})
            samples = []
            for i in range(N_AUCTIONS + 3):
                task = Task.make("deliver", id=f"b{i}", roles=[Role("carry", "carry")])
                outcome = auction(boss, task, reply_by_s=2.0)
                if i >= 3:  # the first rounds open the DDS writers to every broker
                    samples.append(outcome.award_latency_s[0] * 1000)
            p50, p99 = median(samples), percentile(samples, 99)
            rows.append(report("market_award_10_brokers_p50", p50, "ms", None, None,
                               n=len(samples)))
            rows.append(report("market_award_10_brokers_p99", p99, "ms", "<= 30 ms",
                               p99 <= 30.0, n=len(samples)))
    finally:
        stop_all(procs)
    return rows


def _one_kill(boss: Agent, backup: AgentProc, name: str, task_id: str) -> float:
    """Seconds from killing the working member to the award of its role to the backup."""
    victim = _Broker(name, "carry", 1.0)
    try:
        victim.wait_event("ready")
        _wait_brokers(boss, {victim.name, backup.name})
        killed_at: list[float] = []
        awarded_at: list[float] = []

        def seen(step: str, detail: dict[str, Any]) -> None:
            if step == "awarded" and killed_at:
                awarded_at.append(time.monotonic())

        # Long enough that the kill lands mid-role (the backup then does it again).
        task = Task.make("deliver", id=task_id, roles=[Role(
            "carry", "carry", params={"script": ["sleep:2"]})])
        done: list[Any] = []
        thread = threading.Thread(target=lambda: done.append(
            auction(boss, task, reply_by_s=2.0, observer=seen)))
        thread.start()
        victim.wait_event("step", step="sleep:2")
        killed_at.append(time.monotonic())
        victim.kill()
        thread.join(60)
        if not done or done[0].state is not TaskState.COMPLETED:
            raise RuntimeError(f"the task was not completed after the kill: {done}")
        return awarded_at[0] - killed_at[0]
    finally:
        victim.kill()


def reaward() -> list[dict[str, Any]]:
    tag = random.randint(0, 99999)
    samples = []
    backup = _Broker(f"br{tag}_backup", "carry", 5.0)
    try:
        backup.wait_event("ready")
        with Agent(f"br{tag}_boss", lease_s=LEASE_S) as boss:
            for k in range(N_KILLS):
                samples.append(_one_kill(boss, backup, f"br{tag}_v{k}", f"r{k}"))
    finally:
        backup.stop()
    m = median(samples)
    return [report("market_reaward_after_kill", m, "s", f"<= lease {LEASE_S} s + 0.5 s",
                   m <= LEASE_S + 0.5, n=len(samples), worst=round(max(samples), 3),
                   lease_s=LEASE_S)]


def main() -> list[dict[str, Any]]:
    sys.setswitchinterval(0.001)
    return quality() + award_latency() + reaward()


if __name__ == "__main__":
    main()
