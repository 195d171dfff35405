"""Child process of bench_ros: a low level on ROS 2 that writes benchmark changes.

argv: namespace mode n rate_hz — mode "paced" writes `bench/t` = time.monotonic() at
rate_hz; mode "burst" writes n changes over 10 keys as fast as it can, then `bench/done`.
CLOCK_MONOTONIC is system-wide on Linux, so the parent can subtract it.
"""

from __future__ import annotations

import asyncio
import sys
import time

from beehave.lowlevel import LowLevelBehaviorManager
from beehave.ros.bridge import LowLevelBridge
from beehave.ros.context import RosContext


async def paced(ll: LowLevelBehaviorManager, n: int, rate_hz: float) -> None:
    period = 1.0 / rate_hz
    start = time.monotonic()
    for i in range(n):
        ll.blackboard.set("bench/t", time.monotonic())
        await asyncio.sleep(max(0.0, start + (i + 1) * period - time.monotonic()))


async def burst(ll: LowLevelBehaviorManager, n: int) -> None:
    t0 = time.monotonic()
    for i in range(n):
        ll.blackboard.set(f"bench/k{i % 10}", i)
        if i % 200 == 0:
            await asyncio.sleep(0)  # let the bridge publish, as a real loop would
    ll.blackboard.set("bench/done", {"n": n, "elapsed_s": time.monotonic() - t0})


def main() -> None:
    namespace, mode, n, rate_hz = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    ros = RosContext()
    node = ros.create_node("beehave_low_level", namespace=namespace)
    ros.start()
    with LowLevelBehaviorManager() as ll:
        bridge = LowLevelBridge(ll, node)
        print("ready", flush=True)
        sys.stdin.readline()  # the parent says go once its mirror is connected
        coro = paced(ll, n, rate_hz) if mode == "paced" else burst(ll, n)
        ll.call(coro)
        sys.stdin.readline()  # the parent says stop
        bridge.destroy()
    ros.shutdown()


if __name__ == "__main__":
    main()
