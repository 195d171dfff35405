"""Blackboard change → high-level mirror over ROS 2: latency and sustained rate.

Targets (issue 4): cross-process p50 ≤ 300 µs and p99 ≤ 1 ms at 1 kHz of changes;
≥ 5,000 changes/s sustained without losing the latest value. Issue 9: cross-process p50 ≤
2× the bare rclpy floor measured in the same run. Two floors are measured: a String
between two contexts of this process (the figure issue 9 quotes) and a String from another
process at 1 kHz (what the cross-process mirror can at best approach: the same path
without beehave). Every change must arrive (``n``, ``missed_messages``).
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import threading
import time
from typing import Any

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(101, 200)))

from std_msgs.msg import String  # noqa: E402

from beehave.highlevel import HighLevelBehaviorManager  # noqa: E402
from beehave.lowlevel import LowLevelBehaviorManager  # noqa: E402
from beehave.ros.bridge import BLACKBOARD_QOS, HighLevelBridge, LowLevelBridge  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import wait_until  # noqa: E402
from benchmarks._util import median, percentile, report  # noqa: E402

N_PACED = 2000
N_BURST = 50_000


class Mirror:
    """A high level with its bridge; records when `bench/t` values arrive."""

    def __init__(self, namespace: str) -> None:
        self.ros = RosContext()
        self.node = self.ros.create_node("beehave_high_level", namespace=namespace)
        self.hl = HighLevelBehaviorManager()
        self.bridge = HighLevelBridge(self.hl, self.node)
        self.latencies: list[float] = []
        self.done = threading.Event()
        self.finished_at = 0.0
        self.hl.blackboard.subscribe("bench/t", self._on_t)
        self.hl.blackboard.subscribe("bench/done", self._on_done)
        self.ros.start()

    def wait_connected(self, timeout_s: float = 30.0) -> None:
        """Until the low level's first snapshot arrived: both sides discovered each other.
        (A fixed sleep was not enough on a busy machine: the first ~1,500 changes of a
        run were then lost before the match and the figures came from the rest.)"""
        if not wait_until(lambda: self.bridge.mirror_complete, timeout_s):
            raise TimeoutError("the mirror never received the low level's snapshot")
        time.sleep(0.2)  # let the late-joiner replay pass

    def _on_t(self, change: Any) -> None:
        self.latencies.append(time.monotonic() - change.value)

    def _on_done(self, change: Any) -> None:
        self.finished_at = time.monotonic()
        self.done.set()

    def close(self) -> None:
        self.bridge.destroy()
        self.hl.shutdown()
        self.ros.shutdown()


def floor_roundtrip(n: int) -> list[float]:
    """Bare rclpy: a String published in one process context, received in another."""
    a, b = RosContext(), RosContext()
    pub_node, sub_node = a.create_node("floor_pub"), b.create_node("floor_sub")
    got = threading.Event()
    stamps: list[float] = []

    def on_msg(msg: String) -> None:
        stamps.append(time.monotonic() - float(msg.data))
        got.set()

    sub_node.create_subscription(String, "floor", on_msg, 10)
    pub = pub_node.create_publisher(String, "floor", 10)
    a.start()
    b.start()
    while pub.get_subscription_count() == 0:
        time.sleep(0.01)
    time.sleep(0.2)
    for _ in range(n):
        got.clear()
        pub.publish(String(data=repr(time.monotonic())))
        got.wait(1.0)
        time.sleep(0.001)
    a.shutdown()
    b.shutdown()
    return stamps


def same_process(n: int) -> list[float]:
    mirror = Mirror("bench_same")
    low_ros = RosContext()
    node = low_ros.create_node("beehave_low_level", namespace="bench_same")
    low_ros.start()
    with LowLevelBehaviorManager() as ll:
        bridge = LowLevelBridge(ll, node)
        mirror.wait_connected()

        async def paced() -> None:
            import asyncio

            start = time.monotonic()
            for i in range(n):
                ll.blackboard.set("bench/t", time.monotonic())
                await asyncio.sleep(max(0.0, start + (i + 1) * 0.001 - time.monotonic()))

        ll.call(paced())
        time.sleep(0.3)
        bridge.destroy()
    low_ros.shutdown()
    mirror.close()
    return mirror.latencies


def floor_cross_process(n: int, rate_hz: float = 1000.0) -> list[float]:
    """Bare rclpy across processes, paced like the mirror benchmark."""
    ros = RosContext()
    node = ros.create_node("floor_sub")
    stamps: list[float] = []
    node.create_subscription(String, "floor",
                             lambda msg: stamps.append(time.monotonic() - float(msg.data)),
                             BLACKBOARD_QOS)
    ros.start()
    proc = subprocess.Popen([sys.executable, "-m", "benchmarks._ros_floor_pub", str(n),
                             str(rate_hz)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    time.sleep(0.5)  # the child saw our subscription; let discovery settle both ways
    assert proc.stdin is not None
    proc.stdin.write("go\n")
    proc.stdin.flush()
    deadline = time.monotonic() + n / rate_hz + 10
    while len(stamps) < n and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.stdin.write("stop\n")
    proc.stdin.flush()
    proc.wait(20)
    ros.shutdown()
    return stamps


def child(namespace: str, mode: str, n: int, rate_hz: float) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-m", "benchmarks._ros_low_level", namespace,
                             mode, str(n), str(rate_hz)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


def cross_process_paced(n: int) -> tuple[list[float], int]:
    mirror = Mirror("bench_cross")
    proc = child("bench_cross", "paced", n, 1000.0)
    mirror.wait_connected()
    assert proc.stdin is not None
    proc.stdin.write("go\n")
    proc.stdin.flush()
    deadline = time.monotonic() + n / 1000.0 + 10
    while len(mirror.latencies) < n and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.stdin.write("stop\n")
    proc.stdin.flush()
    proc.wait(20)
    missed = mirror.bridge.missed_messages
    mirror.close()
    return mirror.latencies, missed


def cross_process_burst(n: int) -> dict[str, Any]:
    mirror = Mirror("bench_burst")
    proc = child("bench_burst", "burst", n, 0.0)
    mirror.wait_connected()
    assert proc.stdin is not None
    proc.stdin.write("go\n")
    proc.stdin.flush()
    ok = mirror.done.wait(60)
    board = mirror.hl.blackboard
    done = board.get("bench/done") or {}
    finals = [board.get(f"bench/k{k}") for k in range(10)]
    expected = [n - 10 + ((k - n) % 10) for k in range(10)]
    proc.stdin.write("stop\n")
    proc.stdin.flush()
    proc.wait(20)
    mirror.close()
    return {"arrived": ok, "writer_elapsed_s": done.get("elapsed_s", float("nan")),
            "latest_values_kept": finals == expected}


def main() -> list[dict[str, Any]]:
    rows = []
    floor = floor_roundtrip(1000)
    rows.append(report("ros_string_floor_cross_context_p50", median(floor) * 1e6, "us", None,
                       None, p99_us=round(percentile(floor, 99) * 1e6, 1)))
    same = same_process(N_PACED)
    rows.append(report("mirror_same_process_p50", median(same) * 1e6, "us", None, None,
                       p99_us=round(percentile(same, 99) * 1e6, 1), n=len(same)))
    xfloor = floor_cross_process(N_PACED)
    rows.append(report("ros_string_floor_cross_process_1khz_p50", median(xfloor) * 1e6, "us",
                       None, None, p99_us=round(percentile(xfloor, 99) * 1e6, 1),
                       n=len(xfloor)))
    cross, missed = cross_process_paced(N_PACED)
    p50, p99 = median(cross), percentile(cross, 99)
    rows.append(report("mirror_cross_process_1khz_p50", p50 * 1e6, "us", "<= 300 us",
                       p50 <= 300e-6, n=len(cross), missed_messages=missed))
    rows.append(report("mirror_cross_process_1khz_p99", p99 * 1e6, "us", "<= 1000 us",
                       p99 <= 1e-3))
    ratio = p50 / median(floor)
    rows.append(report("mirror_cross_process_p50_over_context_floor", ratio, "x", "<= 2",
                       ratio <= 2.0))
    xratio = p50 / median(xfloor)
    rows.append(report("mirror_cross_process_p50_over_process_floor", xratio, "x", "<= 2",
                       xratio <= 2.0))
    burst = cross_process_burst(N_BURST)
    rate = N_BURST / burst["writer_elapsed_s"]
    rows.append(report("mirror_sustained_changes_per_s", rate, "changes/s", ">= 5000",
                       rate >= 5000 and burst["arrived"] and burst["latest_values_kept"],
                       arrived=burst["arrived"],
                       latest_values_kept=burst["latest_values_kept"]))
    return rows


if __name__ == "__main__":
    main()
