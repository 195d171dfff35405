"""Blackboard: set → woken-logic latency, cross-thread latency, set throughput.

Runs inside a real :class:`~beehave.lowlevel.LowLevelBehaviorManager` (uvloop when
installed), beside the floor measured in the same run: a bare ``asyncio.Event`` wake.
KogMo-RTDB figures (C, real-time kernel, under load) are printed as informational rows.
"""

from __future__ import annotations

import asyncio
import gc
import threading
import time
from typing import Any

from beehave.blackboard import Blackboard
from beehave.lowlevel import LowLevelBehaviorManager
from benchmarks._util import percentile, report

ROUNDS = 3000
THREAD_ROUNDS = 3000
SETS = 300_000
NS = 1e-3  # ns → µs


async def _event_floor(rounds: int) -> list[float]:
    """Latency of waking one task with a bare asyncio.Event, in µs."""
    event = asyncio.Event()
    woken = asyncio.Event()
    sent = 0
    samples: list[float] = []

    async def waiter() -> None:
        for _ in range(rounds):
            await event.wait()
            samples.append((time.perf_counter_ns() - sent) * NS)
            event.clear()
            woken.set()

    task = asyncio.create_task(waiter())
    await asyncio.sleep(0)
    for _ in range(rounds):
        woken.clear()
        sent = time.perf_counter_ns()
        event.set()
        await woken.wait()
    await task
    return samples


async def _watch_latency(bb: Blackboard, n_watchers: int, rounds: int
                         ) -> tuple[list[float], list[float]]:
    """Per-watcher and all-woken latency of an in-loop set, in µs."""
    key = f"bench/w{n_watchers}"
    per_watcher: list[float] = []
    all_woken: list[float] = []
    done = asyncio.Event()
    remaining = n_watchers
    last = 0

    async def watcher() -> None:
        nonlocal remaining, last
        async with bb.watch(key, initial=False) as changes:
            async for change in changes:
                if change.value is None:
                    return
                now = time.perf_counter_ns()
                per_watcher.append((now - change.value) * NS)
                last = max(last, now)
                remaining -= 1
                if remaining == 0:
                    done.set()

    tasks = [asyncio.create_task(watcher()) for _ in range(n_watchers)]
    await asyncio.sleep(0)
    for _ in range(rounds):
        remaining, last = n_watchers, 0
        done.clear()
        sent = time.perf_counter_ns()
        bb.set(key, sent)
        await done.wait()
        all_woken.append((last - sent) * NS)
    bb.set(key, None)
    await asyncio.gather(*tasks)
    return per_watcher, all_woken


def _cross_thread(ll: LowLevelBehaviorManager, rounds: int) -> tuple[list[float], list[float]]:
    """Latency of a set made in another thread until the watcher in the loop wakes (µs),
    and the floor: loop.call_soon_threadsafe(event.set) to a waiting task."""
    bb = ll.blackboard
    loop = ll.loop
    assert loop is not None
    woken = threading.Event()
    samples: list[float] = []
    floor: list[float] = []
    ready = threading.Event()

    async def watcher() -> None:
        async with bb.watch("bench/thread", initial=False) as changes:
            ready.set()
            async for change in changes:
                if change.value is None:
                    return
                samples.append((time.perf_counter_ns() - change.value) * NS)
                woken.set()

    async def floor_waiter(event: asyncio.Event) -> None:
        ready.set()
        for _ in range(rounds):
            await event.wait()
            floor.append((time.perf_counter_ns() - sent) * NS)
            event.clear()
            woken.set()

    future = asyncio.run_coroutine_threadsafe(watcher(), loop)
    ready.wait()
    for _ in range(rounds):
        woken.clear()
        bb.set("bench/thread", time.perf_counter_ns())
        woken.wait()
    bb.set("bench/thread", None)
    future.result()

    async def make_event() -> asyncio.Event:
        return asyncio.Event()

    event = asyncio.run_coroutine_threadsafe(make_event(), loop).result()
    ready.clear()
    sent = 0
    future = asyncio.run_coroutine_threadsafe(floor_waiter(event), loop)
    ready.wait()
    for _ in range(rounds):
        woken.clear()
        sent = time.perf_counter_ns()
        loop.call_soon_threadsafe(event.set)
        woken.wait()
    future.result()
    return samples, floor


async def _throughput(bb: Blackboard, n: int) -> float:
    keys = [f"bench/tp/{i}" for i in range(8)]
    for k in keys:
        bb.set(k, 0)
    t0 = time.perf_counter()
    for i in range(n // 8):
        for k in keys:
            bb.set(k, i)
    return (n // 8 * 8) / (time.perf_counter() - t0)


async def _get_ns(bb: Blackboard, n: int) -> float:
    bb.set("bench/get", 1)
    t0 = time.perf_counter_ns()
    for _ in range(n):
        bb.get("bench/get")
    return (time.perf_counter_ns() - t0) / n


def main() -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    gc.collect()
    # The throughput rounds hold the loop on purpose (tight set loops): no lag warnings.
    with LowLevelBehaviorManager(loop_lag_warn_s=5.0) as ll:
        loop = ll.loop
        assert loop is not None
        impl = type(loop).__module__.split(".")[0]

        def run(coro: Any) -> Any:
            return asyncio.run_coroutine_threadsafe(coro, loop).result()

        run(_event_floor(500))  # warm-up
        floor = run(_event_floor(ROUNDS))
        rows.append(report("floor_asyncio_event_wake_p50", percentile(floor, 50), "us",
                           loop=impl))
        rows.append(report("floor_asyncio_event_wake_p99", percentile(floor, 99), "us",
                           loop=impl))

        bb = ll.blackboard
        run(_watch_latency(bb, 1, 300))  # warm-up
        targets = {1: ("<= 10 us", 10.0, "<= 30 us", 30.0),
                   10: (None, None, "<= 60 us (all woken)", 60.0),
                   100: (None, None, None, None)}
        for n in (1, 10, 100):
            rounds = ROUNDS if n < 100 else ROUNDS // 3
            per, all_woken = run(_watch_latency(bb, n, rounds))
            t50, v50, t99, v99 = targets[n]
            p50 = percentile(per, 50)
            rows.append(report(f"set_to_woken_inloop_{n}w_p50", p50, "us", t50,
                               None if v50 is None else p50 <= v50, loop=impl))
            if n == 1:
                p99 = percentile(per, 99)
                rows.append(report("set_to_woken_inloop_1w_p99", p99, "us", t99, p99 <= 30.0,
                                   loop=impl))
            else:
                p99 = percentile(all_woken, 99)
                rows.append(report(f"set_to_all_woken_inloop_{n}w_p99", p99, "us", t99,
                                   None if v99 is None else p99 <= v99, loop=impl))
                rows.append(report(f"set_to_all_woken_inloop_{n}w_p50",
                                   percentile(all_woken, 50), "us", loop=impl))

        _cross_thread(ll, 300)  # warm-up
        cross, cross_floor = _cross_thread(ll, THREAD_ROUNDS)
        rows.append(report("set_to_woken_cross_thread_1w_p50", percentile(cross, 50), "us",
                           loop=impl))
        p99 = percentile(cross, 99)
        rows.append(report("set_to_woken_cross_thread_1w_p99", p99, "us", "<= 100 us",
                           p99 <= 100.0, loop=impl))
        rows.append(report("floor_call_soon_threadsafe_wake_p50", percentile(cross_floor, 50),
                           "us", loop=impl))
        rows.append(report("floor_call_soon_threadsafe_wake_p99", percentile(cross_floor, 99),
                           "us", loop=impl))

        rate = max(run(_throughput(bb, SETS)) for _ in range(3))
        rows.append(report("set_throughput_no_watcher_inloop", rate, "sets/s",
                           ">= 300000 sets/s", rate >= 300_000, loop=impl))
        rows.append(report("get_latency_mean", run(_get_ns(bb, 200_000)) / 1000, "us"))

    unbound = Blackboard()
    rate = max(_sync_throughput(unbound, SETS) for _ in range(3))
    rows.append(report("set_throughput_no_watcher_unbound", rate, "sets/s"))

    for name, value in (("write_avg", 25.6), ("write_worst", 134.0), ("read_avg", 16.8),
                        ("read_worst", 62.0), ("notify_avg", 66.5), ("notify_worst", 208.0)):
        rows.append(report(f"reference_kogmo_rtdb_{name}", value, "us",
                           source="KogMo-RTDB, C, real-time kernel, under load"))
    return rows


def _sync_throughput(bb: Blackboard, n: int) -> float:
    t0 = time.perf_counter()
    for i in range(n):
        bb.set("bench/sync", i)
    return n / (time.perf_counter() - t0)


if __name__ == "__main__":
    main()
