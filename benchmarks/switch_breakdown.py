"""Where a switch spends its time: ``python -m benchmarks.switch_breakdown``.

Switches from ``Ten`` (10 sleeping actions, the ``highlevel`` benchmark's behaviour) to
``idle`` and stamps each step with ``time.perf_counter()`` from the ``switch()`` call: the
request queued, the top-level behaviour and its actions interrupted, each action back from
``run``, at its ``safe_state()`` and done, the behaviour's clean-up, and the return. The
stamps come from wrappers around the framework's internal steps (a diagnostic, not a
figure to track: they add about a microsecond each), printed as p50 / p99 per step and,
for a few switches, the whole sequence. Not part of ``python -m benchmarks``.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from typing import Any

from beehave import HighLevelBehaviorManager
from beehave.behavior import Behavior
from beehave.highlevel import HighLevelBehaviorManager as _Manager
from beehave.runnable import Runnable
from benchmarks._util import median, percentile
from benchmarks.bench_highlevel import Ten, Wait, thread_floor

_stamps: list[tuple[str, float]] = []


def _mark(label: str) -> None:
    _stamps.append((label, time.perf_counter()))


def _wrap(owner: type, attr: str, before: str | None = None,
          after: Callable[[Any], str | None] | None = None) -> None:
    original = getattr(owner, attr)

    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        if before:
            _mark(before)
        result = original(self, *args, **kwargs)
        label = after(self) if after else None
        if label:
            _mark(label)
        return result

    setattr(owner, attr, wrapper)


def _instrument() -> None:
    _wrap(_Manager, "_enqueue", after=lambda _: "request queued")
    _wrap(Runnable, "_interrupt",
          after=lambda node: "all interrupted" if node.parent is None else None)
    _wrap(Wait, "run", after=lambda _: "action: run() returned")
    _wrap(Wait, "safe_state", before="action: safe_state()")
    _wrap(Runnable, "_finish", after=lambda node: ("action: done" if isinstance(node, Wait)
                                                    else "behaviour: done"))
    _wrap(Behavior, "_after_run", before="behaviour: run() returned",
          after=lambda _: "behaviour: children collected")


def main(n: int = 400, show: int = 2) -> None:
    _instrument()
    floor = median(thread_floor(1000))
    rows: dict[str, list[float]] = {}
    with HighLevelBehaviorManager() as hl:
        hl.register("ten", Ten)
        for i in range(n):
            ready = threading.Event()
            hl.switch("ten", ready=ready)
            ready.wait()
            time.sleep(0.0005)  # every action asleep in its sleep()
            _stamps.clear()
            t0 = time.perf_counter()
            hl.switch("idle")
            t1 = time.perf_counter()
            stamps = [(label, (t - t0) * 1e6) for label, t in _stamps]
            stamps.append(("switch() returned", (t1 - t0) * 1e6))
            for label, us in stamps:
                rows.setdefault(label, []).append(us)
            if i >= n - show:
                print("one switch (µs):", ", ".join(f"{label} {us:.0f}"
                                                    for label, us in stamps))
    print(f"thread start+join floor p50 {floor * 1e6:.0f} µs; load {os.getloadavg()[0]:.1f}")
    print(f"{'step (µs from the switch() call)':34s} {'per switch':>10s} {'p50':>7s} {'p99':>7s}")
    for label in sorted(rows, key=lambda k: median(rows[k])):
        values = rows[label]
        print(f"{label:34s} {len(values) / n:10.0f} {median(values):7.0f} "
              f"{percentile(values, 99):7.0f}")


if __name__ == "__main__":
    main()
