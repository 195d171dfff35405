"""High-level manager: switch and start_action latency beside the thread floor.

Targets (issue 2): switch p99 ≤ 2 ms and ≤ 10× the floor (bare thread start+join p50),
with 10 cooperative actions running; start_action p99 ≤ 300 µs. Beside the latencies, the
process's CPU time during a switch (all threads): what a switch costs, whatever else runs.
Pause (issue 27), with 10 actions commanding motion: from ``pause()`` to the last of them
commanding zero (its safe state), p99 ≤ 1.5 × the switch's stop p99 of the same run (a
pause does what a stop does to the actions, and keeps them); from ``resume()`` to the
first command again, p99 ≤ 2 ms. A further floor: ten threads woken at once and joined,
the least a switch that ends ten threads could cost without the worker pool. Also shows
how much a CPU-bound thread delays a wake with Python's default switch interval and with
the one the manager sets (``gil_switch_interval_s``).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Any

from beehave import Action, Behavior, HighLevelBehaviorManager
from benchmarks._util import median, percentile, report


class Wait(Action):
    def run(self) -> None:
        while self.sleep(60):
            pass


class Ten(Behavior):
    """Starts 10 cooperative actions (10 types) and waits."""

    def __init__(self, ready: threading.Event | None = None) -> None:
        self.ready = ready

    def run(self) -> None:
        for i in range(10):
            action = Wait()
            action.action_type = f"type{i}"  # type: ignore[misc]
            self.start_action(action)
        if self.ready:
            self.ready.set()
        while self.sleep(60):
            pass


class Bus:
    """The "motor controller": when every motor was last commanded zero, and when the
    first non-zero command came after a mark."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.last: dict[int, float] = {}
        self.all_zero_at: float | None = None
        self.first_motion_at: float | None = None
        self.moving = threading.Event()

    def command(self, who: Action, value: float) -> None:
        now = time.perf_counter()
        with self.lock:
            self.last[id(who)] = value
            if value == 0.0 and all(v == 0.0 for v in self.last.values()):
                self.all_zero_at = now
            if value != 0.0:
                if self.first_motion_at is None:
                    self.first_motion_at = now
                if len(self.last) == 10 and all(v != 0.0 for v in self.last.values()):
                    self.moving.set()

    def mark(self) -> None:
        with self.lock:
            self.all_zero_at = self.first_motion_at = None
            self.moving.clear()


class Motor(Action):
    """Commands a velocity every 5 ms; zero in its safe state."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    def run(self) -> None:
        while not self.interrupted:
            self.bus.command(self, 1.0)
            self.sleep(0.005)

    def safe_state(self) -> None:
        self.bus.command(self, 0.0)


class Motors(Behavior):
    """Ten motors of ten types."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    def run(self) -> None:
        for i in range(10):
            motor = Motor(self.bus)
            motor.action_type = f"motor{i}"  # type: ignore[misc]
            self.start_action(motor)
        while self.sleep(60):
            pass


def pause_resume(hl: HighLevelBehaviorManager, n: int) -> tuple[list[float], list[float]]:
    """(pause() → every motor zero, resume() → the first command again), n times each."""
    bus = Bus()
    hl.register("motors", Motors, bus=bus)
    hl.switch("motors")
    to_zero, to_motion = [], []
    for _ in range(n):
        bus.moving.wait(10)
        bus.mark()
        t0 = time.perf_counter()
        hl.pause()
        assert bus.all_zero_at is not None, "pause() returned before every motor was zero"
        to_zero.append(bus.all_zero_at - t0)
        bus.mark()
        t0 = time.perf_counter()
        hl.resume()
        while bus.first_motion_at is None:
            time.sleep(0)
        to_motion.append(bus.first_motion_at - t0)
    hl.switch("idle")
    return to_zero, to_motion


class Quick(Action):
    def run(self) -> None:
        return None


class StartMany(Behavior):
    def __init__(self, n: int, out: list[float]) -> None:
        self.n, self.out = n, out

    def run(self) -> None:
        for _ in range(self.n):
            action = Quick()
            t0 = time.perf_counter()
            self.start_action(action)
            self.out.append(time.perf_counter() - t0)
            action.wait()


def thread_floor(n: int) -> list[float]:
    samples = []
    for _ in range(n):
        t0 = time.perf_counter()
        t = threading.Thread(target=lambda: None)
        t.start()
        t.join()
        samples.append(time.perf_counter() - t0)
    return samples


def ten_threads(n: int) -> list[float]:
    samples = []
    for _ in range(n):
        events = [threading.Event() for _ in range(10)]
        threads = [threading.Thread(target=e.wait) for e in events]
        for t in threads:
            t.start()
        time.sleep(0.0005)
        t0 = time.perf_counter()
        for e in events:
            e.set()
        for t in threads:
            t.join()
        samples.append(time.perf_counter() - t0)
    return samples


def event_wake(n: int, *, busy: bool = False) -> list[float]:
    """Latency from Event.set() in this thread to the waiter running, optionally with a
    CPU-bound thread competing for the GIL."""
    samples: list[float] = []
    stop = threading.Event()

    def spin() -> None:
        x = 0
        while not stop.is_set():
            x += 1

    spinner = threading.Thread(target=spin) if busy else None
    if spinner:
        spinner.start()
    for _ in range(n):
        ev, woke = threading.Event(), threading.Event()
        stamp: list[float] = []

        def waiter(ev: threading.Event = ev, stamp: list[float] = stamp,
                   woke: threading.Event = woke) -> None:
            ev.wait()
            stamp.append(time.perf_counter())
            woke.set()

        t = threading.Thread(target=waiter)
        t.start()
        time.sleep(0.0005)
        t0 = time.perf_counter()
        ev.set()
        woke.wait()
        t.join()
        samples.append(stamp[0] - t0)
    stop.set()
    if spinner:
        spinner.join()
    return samples


def main() -> list[dict[str, Any]]:
    rows = []
    floor = thread_floor(2000)
    floor_p50 = median(floor)
    rows.append(report("thread_start_join_p50", floor_p50 * 1e6, "us", None, None))
    rows.append(report("ten_threads_wake_and_exit_p50", median(ten_threads(300)) * 1e6, "us",
                       None, None))
    wake = event_wake(500)
    rows.append(report("event_wake_p50", median(wake) * 1e6, "us", None, None))

    with HighLevelBehaviorManager() as hl:
        hl.register("ten", Ten)
        stop10, both10, stop10_cpu = [], [], []
        for _ in range(300):
            ready = threading.Event()
            t0 = time.perf_counter()
            hl.switch("ten", ready=ready)  # from idle, or from another "ten"
            both10.append(time.perf_counter() - t0)
            ready.wait()
            ready = threading.Event()
            t0 = time.perf_counter()
            hl.switch("ten", ready=ready)  # stops 10 running actions, starts 10 new ones
            both10.append(time.perf_counter() - t0)
            ready.wait()
            c0, t0 = time.process_time(), time.perf_counter()
            hl.switch("idle")  # stops 10 running actions
            stop10.append(time.perf_counter() - t0)
            stop10_cpu.append(time.process_time() - c0)
        p50, p99 = median(stop10), percentile(stop10, 99)
        rows.append(report("switch_stopping_10_actions_p50", p50 * 1e6, "us", None, None))
        rows.append(report("switch_stopping_10_actions_p99", p99 * 1e6, "us", "<= 2000 us",
                           p99 <= 2e-3))
        rows.append(report("switch_p99_over_thread_floor", p99 / floor_p50, "x", "<= 10 x",
                           p99 / floor_p50 <= 10))
        # CPU of the whole process (every thread) during those switches: what they cost,
        # robust to other load on the machine (a latency on a shared host is not).
        rows.append(report("switch_stopping_10_actions_cpu_p50", median(stop10_cpu) * 1e6, "us",
                           None, None, note="process CPU time during the switch, all threads"))
        rows.append(report("switch_10_to_10_actions_p50", median(both10) * 1e6, "us", None,
                           None, p99_us=round(percentile(both10, 99) * 1e6, 1),
                           note="the caller also competes for the GIL with the new "
                                "behaviour starting its 10 actions"))

        to_zero, to_motion = pause_resume(hl, 300)
        zero_p99, stop_p99 = percentile(to_zero, 99), p99
        rows.append(report("pause_10_motors_to_zero_p50", median(to_zero) * 1e6, "us",
                           None, None))
        rows.append(report("pause_10_motors_to_zero_p99", zero_p99 * 1e6, "us",
                           "<= 1.5 x switch stop p99", zero_p99 <= 1.5 * stop_p99,
                           ratio_to_switch_stop_p99=round(zero_p99 / stop_p99, 2)))
        motion_p99 = percentile(to_motion, 99)
        rows.append(report("resume_to_first_command_p50", median(to_motion) * 1e6, "us",
                           None, None))
        rows.append(report("resume_to_first_command_p99", motion_p99 * 1e6, "us",
                           "<= 2000 us", motion_p99 <= 2e-3))

        out: list[float] = []
        hl.register("starter", StartMany, n=2000, out=out)
        top = hl.switch("starter")
        top.wait(60)
        rows.append(report("start_action_p50", median(out) * 1e6, "us", None, None))
        p99 = percentile(out, 99)
        rows.append(report("start_action_p99", p99 * 1e6, "us", "<= 300 us", p99 <= 300e-6))

    default_interval = 0.005
    saved = sys.getswitchinterval()
    try:
        for interval in (default_interval, 0.001):
            sys.setswitchinterval(interval)
            busy = event_wake(100, busy=True)
            rows.append(report(f"wake_with_cpu_bound_thread_interval_{interval * 1e3:g}ms_p50",
                               median(busy) * 1e6, "us", None, None,
                               p99_us=round(percentile(busy, 99) * 1e6, 1)))
    finally:
        sys.setswitchinterval(saved)
    return rows


if __name__ == "__main__":
    main()
