"""Blackboard contract: keys, patterns, threads, slow watchers, freshness, deadband."""

from __future__ import annotations

import asyncio
import gc
import json
import threading
from typing import Any

import pytest

from beehave.blackboard import Blackboard, Change, Subscription, matches
from beehave.errors import BlackboardError
from beehave.testing import WALL_TIMEOUT_S, wait_until


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


# -- keys and patterns ----------------------------------------------------------------------

def test_set_then_get_returns_the_value_and_default_for_missing_keys() -> None:
    bb = Blackboard()
    bb.set("battery/percentage", 42.0)
    assert bb.get("battery/percentage") == 42.0
    assert bb.get("battery/voltage") is None
    assert bb.get("battery/voltage", 7) == 7
    assert "battery/percentage" in bb and "battery/voltage" not in bb
    assert bb.keys() == ["battery/percentage"]


@pytest.mark.parametrize("key", ["", "/a", "a/", "a//b", "a b", "a/*", "led*", 5])
def test_invalid_keys_raise_blackboard_error_naming_the_key(key: Any) -> None:
    bb = Blackboard()
    with pytest.raises(BlackboardError, match="invalid blackboard key") as info:
        bb.set(key, 1)
    assert repr(key) in str(info.value)


@pytest.mark.parametrize("pattern", ["", "a//b", "led*/x", "a/b c"])
def test_invalid_patterns_raise_blackboard_error_naming_the_pattern(pattern: str) -> None:
    with pytest.raises(BlackboardError, match="invalid blackboard pattern") as info:
        Blackboard().subscribe(pattern, lambda c: None)
    assert repr(pattern) in str(info.value)


@pytest.mark.parametrize("pattern, key, expected", [
    ("battery/percentage", "battery/percentage", True),
    ("battery/percentage", "battery/voltage", False),
    ("leds/*", "leds/front", True),
    ("leds/*", "leds/front/left", False),
    ("leds/*", "leds", False),
    ("*/percentage", "battery/percentage", True),
    ("*", "battery", True),
    ("*", "battery/percentage", False),
    ("battery/**", "battery", True),
    ("battery/**", "battery/percentage", True),
    ("battery/**", "battery/cells/3", True),
    ("battery/**", "batteryx/a", False),
    ("**", "anything/at/all", True),
    ("**/x", "a/b/x", True),
    ("**/x", "x", True),
    ("a/**/z", "a/b/c/z", True),
    ("a/**/z", "a/z", True),
    ("a/**/z", "a/b/c", False),
])
def test_pattern_matching_table(pattern: str, key: str, expected: bool) -> None:
    assert matches(pattern, key) is expected
    bb = Blackboard()
    seen: list[str] = []
    bb.subscribe(pattern, lambda c: seen.append(c.key))
    bb.set(key, 1)
    assert seen == ([key] if expected else [])


# -- synchronous use (no loop) ----------------------------------------------------------------

def test_without_a_loop_callbacks_run_synchronously_in_the_writer_thread() -> None:
    bb = Blackboard()
    seen: list[tuple[str, Any, int]] = []
    bb.subscribe("leds/*", lambda c: seen.append((c.key, c.value, threading.get_ident())))
    bb.set("leds/front", "red")
    assert seen == [("leds/front", "red", threading.get_ident())]


def test_change_carries_key_value_stamp_and_the_entry_remembers_its_writer() -> None:
    bb = Blackboard()
    changes: list[Change] = []
    bb.subscribe("**", changes.append)
    bb.client("hal:debug").set("battery/percentage", 50.0)
    (change,) = changes
    assert (change.key, change.value, change.writer) == ("battery/percentage", 50.0, "hal:debug")
    assert change.stamp > 0 and change.stale is False
    entry = bb.entry("battery/percentage")
    assert entry is not None and entry.writer == "hal:debug"


def test_closed_subscription_receives_nothing_more() -> None:
    bb = Blackboard()
    seen: list[Any] = []
    sub = bb.subscribe("a", lambda c: seen.append(c.value))
    bb.set("a", 1)
    sub.close()
    bb.set("a", 2)
    assert seen == [1] and sub.closed and sub not in bb.subscriptions


def test_subscription_made_after_a_key_exists_receives_its_changes() -> None:
    bb = Blackboard()
    bb.set("pose/x", 1.0)  # the key's subscriber index is built here
    seen: list[float] = []
    bb.subscribe("pose/*", lambda c: seen.append(c.value))
    bb.set("pose/x", 2.0)
    assert seen == [2.0]


def test_a_raising_callback_is_recorded_closed_and_reported_while_the_writer_goes_on() -> None:
    reported: list[tuple[Subscription, BaseException]] = []
    bb = Blackboard(on_error=lambda sub, exc: reported.append((sub, exc)))
    good: list[int] = []

    def bad(change: Change) -> None:
        raise ValueError("observer bug")

    sub = bb.subscribe("a", bad)
    bb.subscribe("a", lambda c: good.append(c.value))
    bb.set("a", 1)
    bb.set("a", 2)
    assert isinstance(sub.error, ValueError) and sub.closed
    assert reported == [(sub, sub.error)]
    assert good == [1, 2] and bb.get("a") == 2


# -- watchers and the loop ---------------------------------------------------------------------

def test_watch_yields_current_entries_first_then_changes() -> None:
    async def main() -> list[tuple[str, Any]]:
        bb = Blackboard()
        bb.set("battery/percentage", 80.0)
        got: list[tuple[str, Any]] = []
        async with bb.watch("battery/*") as watcher:
            bb.set("battery/charging", True)
            async for change in watcher:
                got.append((change.key, change.value))
                if len(got) == 2:
                    break
        return got

    assert asyncio.run(main()) == [("battery/percentage", 80.0), ("battery/charging", True)]


def test_watch_with_initial_false_yields_only_later_changes() -> None:
    async def main() -> Change:
        bb = Blackboard()
        bb.set("a", 1)
        watcher = bb.watch("a", initial=False)
        bb.set("a", 2)
        return await anext(watcher)

    assert asyncio.run(main()).value == 2


def test_slow_watcher_coalesces_to_the_latest_value_per_key_and_never_blocks_writers() -> None:
    async def main() -> tuple[list[tuple[str, Any]], int, int]:
        bb = Blackboard()
        watcher = bb.watch("k/*")
        for i in range(10_000):  # the watcher does not get to run meanwhile
            bb.set("k/a", i)
            bb.set("k/b", -i)
        pending = watcher.pending
        got = [(c.key, c.value) for c in (await anext(watcher), await anext(watcher))]
        return got, pending, watcher.coalesced

    got, pending, coalesced = asyncio.run(main())
    assert pending == 2  # bounded by the number of keys, not of writes
    assert got == [("k/a", 9_999), ("k/b", -9_999)]
    assert coalesced == 2 * 10_000 - 2


def test_closing_a_watcher_ends_its_iteration() -> None:
    async def main() -> list[Any]:
        bb = Blackboard()
        watcher = bb.watch("a")
        got: list[Any] = []

        async def consume() -> None:
            async for change in watcher:
                got.append(change.value)

        task = asyncio.create_task(consume())
        bb.set("a", 1)
        await asyncio.sleep(0)
        watcher.close()
        await asyncio.wait_for(task, WALL_TIMEOUT_S)
        return got

    assert asyncio.run(main()) == [1]


def test_watch_outside_a_loop_raises_blackboard_error() -> None:
    with pytest.raises(BlackboardError, match="running asyncio loop"):
        Blackboard().watch("a")


def test_set_from_another_thread_is_visible_at_once_and_delivered_in_the_loop_thread() -> None:
    async def main() -> tuple[Any, int, int]:
        bb = Blackboard()
        bb.bind()
        loop_thread = threading.get_ident()
        delivered = asyncio.Event()
        callback_threads: list[int] = []

        def on_change(change: Change) -> None:
            callback_threads.append(threading.get_ident())
            delivered.set()

        bb.subscribe("a", on_change)
        seen_by_writer: list[Any] = []

        def writer() -> None:
            bb.set("a", 7)
            seen_by_writer.append(bb.get("a"))  # read-your-writes in the writer's thread

        thread = threading.Thread(target=writer)
        thread.start()
        thread.join()
        await asyncio.wait_for(delivered.wait(), 2)
        bb.unbind()
        return seen_by_writer[0], callback_threads[0], loop_thread

    seen, callback_thread, loop_thread = asyncio.run(main())
    assert seen == 7
    assert callback_thread == loop_thread


# -- freshness, staleness, deadband ------------------------------------------------------------

def test_entry_older_than_max_age_reads_as_stale() -> None:
    clock = FakeClock()
    bb = Blackboard(clock=clock)
    bb.declare("battery/percentage", max_age_s=1.0)
    assert bb.is_stale("battery/percentage")  # never written
    bb.set("battery/percentage", 50.0)
    clock.now += 0.5
    assert not bb.is_stale("battery/percentage")
    assert bb.get("battery/percentage", fresh=True) == 50.0
    clock.now += 1.0
    assert bb.is_stale("battery/percentage")
    entry = bb.entry("battery/percentage")
    assert entry is not None and entry.stale and entry.value == 50.0
    assert bb.get("battery/percentage", "unknown", fresh=True) == "unknown"
    assert bb.get("battery/percentage") == 50.0
    bb.set("battery/percentage", 49.0)
    assert not bb.is_stale("battery/percentage")


def test_bound_blackboard_tells_watchers_when_an_entry_goes_stale() -> None:
    async def main() -> list[tuple[Any, bool]]:
        bb = Blackboard()
        bb.bind()
        bb.declare("sensor/range", max_age_s=0.03)
        got: list[tuple[Any, bool]] = []
        async with bb.watch("sensor/range", initial=False) as watcher:
            bb.set("sensor/range", 1.5)
            async for change in watcher:
                got.append((change.value, change.stale))
                if change.stale:
                    break
        bb.unbind()
        return got

    assert asyncio.run(asyncio.wait_for(main(), 5)) == [(1.5, False), (1.5, True)]


def test_mark_stale_by_writer_flags_only_that_writers_entries_until_rewritten() -> None:
    bb = Blackboard()
    seen: list[tuple[str, bool]] = []
    bb.subscribe("**", lambda c: seen.append((c.key, c.stale)))
    bb.client("hal:debug").set("battery/percentage", 50.0)
    bb.client("logic:led").set("leds/wanted", "red")
    assert bb.mark_stale(writer="hal:debug") == ["battery/percentage"]
    assert bb.is_stale("battery/percentage") and not bb.is_stale("leds/wanted")
    assert seen[-1] == ("battery/percentage", True)
    bb.client("hal:debug").set("battery/percentage", 49.0)
    assert not bb.is_stale("battery/percentage")


def test_deadband_publishes_only_relevant_changes_but_keeps_the_entry_fresh() -> None:
    clock = FakeClock()
    bb = Blackboard(clock=clock)
    bb.declare("pose/x", deadband=0.01, max_age_s=1.0)
    seen: list[float] = []
    bb.subscribe("pose/x", lambda c: seen.append(c.value))
    for x in (0.0, 0.004, 0.009, 0.012, 0.015, 0.0221, 0.5):
        clock.now += 0.6
        bb.set("pose/x", x)
    # compared with the last *published* value, so slow drift is published eventually
    assert seen == [0.0, 0.012, 0.0221, 0.5]
    clock.now += 0.6
    bb.set("pose/x", 0.501)  # irrelevant, but the sensor is alive
    clock.now += 0.6
    assert not bb.is_stale("pose/x") and bb.get("pose/x") == 0.5


def test_deadband_on_number_sequences_uses_euclidean_distance() -> None:
    bb = Blackboard()
    bb.declare("pose/xy", deadband=0.01)
    seen: list[Any] = []
    bb.subscribe("pose/xy", lambda c: seen.append(c.value))
    for pose in ((0.0, 0.0), (0.006, 0.006), (0.008, 0.008), ("n/a",), (0.0, 0.0)):
        bb.set("pose/xy", pose)
    assert seen == [(0.0, 0.0), (0.008, 0.008), ("n/a",), (0.0, 0.0)]


def test_declare_rejects_negative_limits_naming_the_key() -> None:
    with pytest.raises(BlackboardError, match="'pose/x'"):
        Blackboard().declare("pose/x", deadband=-1)


def test_snapshot_is_json_serialisable_with_values_stamps_and_stale_flags() -> None:
    bb = Blackboard()
    bb.declare("sensor/never", max_age_s=1.0)
    bb.client("hal:debug").set("battery/percentage", 50.0)
    bb.set("odd/value", object())
    bb.set("odd/nan", float("nan"))
    bb.set("nested/dict", {"a": (1, 2)})
    bb.mark_stale(writer="hal:debug")
    snap = json.loads(json.dumps(bb.snapshot()))
    assert snap["battery/percentage"]["value"] == 50.0
    assert snap["battery/percentage"]["stale"] is True
    assert snap["battery/percentage"]["writer"] == "hal:debug"
    assert isinstance(snap["battery/percentage"]["stamp"], float)
    assert snap["sensor/never"] == {"value": None, "stamp": None, "stale": True,
                                    "writer": None, "age_s": None}
    assert snap["odd/value"]["value"].startswith("<object")
    assert snap["nested/dict"]["value"] == {"a": [1, 2]}
    assert list(bb.snapshot("battery/**")) == ["battery/percentage"]


# -- stress ----------------------------------------------------------------------------------

def test_stress_4_threads_x_10000_sets_with_50_watchers_lose_no_final_value() -> None:
    n_threads, n_sets, n_watchers = 4, 10_000, 50
    keys = [f"stress/t{i}" for i in range(n_threads)]

    async def main() -> tuple[list[dict[str, Any]], int, int]:
        bb = Blackboard()
        bb.bind()
        loop = asyncio.get_running_loop()
        finals = {k: n_sets - 1 for k in keys}
        max_pending = 0
        max_board_pending = 0

        async def watcher(index: int) -> dict[str, Any]:
            nonlocal max_pending, max_board_pending
            last: dict[str, Any] = {}
            async with bb.watch("stress/*") as changes:
                async for change in changes:
                    last[change.key] = change.value
                    max_pending = max(max_pending, changes.pending)
                    max_board_pending = max(max_board_pending, len(bb._pending))
                    if last == finals:
                        return last
                    if index % 5 == 0:  # some watchers are slow
                        await asyncio.sleep(0.0005)
            return last

        tasks = [asyncio.create_task(watcher(i)) for i in range(n_watchers)]
        await asyncio.sleep(0)

        def writer(key: str) -> None:
            for i in range(n_sets):
                bb.set(key, i)

        threads = [threading.Thread(target=writer, args=(k,)) for k in keys]
        gc.collect()
        for t in threads:
            t.start()
        await loop.run_in_executor(None, lambda: [t.join() for t in threads])
        results = await asyncio.wait_for(asyncio.gather(*tasks), 20)
        bb.unbind()
        return results, max_pending, max_board_pending

    results, max_pending, max_board_pending = asyncio.run(main())
    assert all(r == {k: n_sets - 1 for k in keys} for r in results)
    assert max_pending <= n_threads          # one pending change per key per watcher
    assert max_board_pending <= n_threads    # one pending hand-over per key


def test_watcher_next_times_out_and_is_cancellation_safe() -> None:
    """Cancelling a logic while it waits with a timeout must end it, even when a change
    arrives at the same moment (asyncio.wait_for on 3.11 can swallow that cancellation)."""
    import asyncio

    from beehave.blackboard import Blackboard

    async def main() -> None:
        bb = Blackboard()
        bb.bind(asyncio.get_running_loop())
        watcher = bb.watch("**", initial=False)
        assert await watcher.next(0.01) is None
        bb.set("a", 1)
        change = await watcher.next(1.0)
        assert change is not None and change.value == 1

        async def logic() -> None:
            while True:
                await watcher.next(0.001)

        loop = asyncio.get_running_loop()
        for i in range(300):
            task = loop.create_task(logic())
            await asyncio.sleep(0)
            # The change and the cancellation reach the logic in the same loop iteration.
            bb.set("a", i)
            task.cancel()
            done, _ = await asyncio.wait({task}, timeout=WALL_TIMEOUT_S)
            assert task in done, "the cancelled logic kept running"

    asyncio.run(main())


def test_a_logic_that_writes_what_it_watches_does_not_starve_the_loop() -> None:
    import asyncio

    from beehave.blackboard import Blackboard

    async def main() -> None:
        bb = Blackboard()
        bb.bind(asyncio.get_running_loop())
        watcher = bb.watch("**", initial=False)

        async def echo() -> None:
            bb.set("x", 0)
            async for change in watcher:
                bb.set("x", change.value + 1)  # feeds its own watcher, forever

        other_ran = asyncio.Event()
        task = asyncio.get_running_loop().create_task(echo())

        async def other() -> None:
            other_ran.set()

        asyncio.get_running_loop().create_task(other())
        async with asyncio.timeout(5):
            await other_ran.wait()
        task.cancel()
        async with asyncio.timeout(5):
            await asyncio.wait({task})
        assert task.cancelled()

    asyncio.run(main())


# -- callbacks run outside the blackboard's lock (issue 9, item 7) -----------------------------

def test_a_slow_callback_blocks_no_other_thread_subscribing_closing_or_writing() -> None:
    """Without a loop a callback runs in the writer's thread; while it works, every other
    thread must still be able to subscribe, close and write (the high-level mirror's
    "battery low → switch" callback waits for a behaviour that closes its subscription)."""
    bb = Blackboard()
    entered, release = threading.Event(), threading.Event()

    def slow(change: Change) -> None:
        entered.set()
        release.wait(WALL_TIMEOUT_S)

    bb.subscribe("battery/low", slow)
    writer = threading.Thread(target=bb.set, args=("battery/low", True))
    writer.start()
    try:
        assert entered.wait(WALL_TIMEOUT_S)
        done = threading.Event()
        others: list[Any] = []

        def other_thread() -> None:
            sub = bb.subscribe("pose/x", lambda c: others.append(c.value))
            bb.set("pose/x", 1.0)
            sub.close()
            done.set()

        threading.Thread(target=other_thread, daemon=True).start()
        # A deadlock detector, not a speed check: the other thread must finish while the
        # slow callback still holds on.
        assert done.wait(WALL_TIMEOUT_S), "another thread blocked behind a running callback"
        assert not release.is_set()
    finally:
        release.set()
        writer.join(WALL_TIMEOUT_S)
    assert bb.get("pose/x") == 1.0 and others == [1.0]


def test_without_a_loop_notifications_keep_the_order_of_writes_per_key() -> None:
    bb = Blackboard()
    seen: dict[str, list[int]] = {"order/a": [], "order/b": []}
    bb.subscribe("order/*", lambda c: seen[c.key].append(c.value))
    n = 2000

    def writer(key: str, base: int) -> None:
        for i in range(n):
            bb.set(key, base + i)

    threads = [threading.Thread(target=writer, args=(key, base))
               for key in ("order/a", "order/b") for base in (0, 10 * n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for key, values in seen.items():
        assert len(values) == len(set(values)) >= 2 * n - 1  # equal writes wake nobody
        for base in (0, 10 * n):
            mine = [v for v in values if base <= v < base + n]
            assert mine == sorted(mine), f"{key}: one writer's changes out of order"
        assert values[-1] == bb.get(key), f"{key}: the last notification is not the value"


def test_a_callback_that_writes_its_own_key_sees_that_change_after_it_returns() -> None:
    bb = Blackboard()
    log: list[str] = []

    def count_to_3(change: Change) -> None:
        log.append(f"{change.value} begins")
        if change.value < 3:
            bb.set("counter", change.value + 1)
        log.append(f"{change.value} ends")

    bb.subscribe("counter", count_to_3)
    bb.set("counter", 1)
    assert log == ["1 begins", "1 ends", "2 begins", "2 ends", "3 begins", "3 ends"]


def test_battery_low_callback_that_switches_leaves_no_behaviour_stuck(hl: Any,
                                                                      events: list[Any]) -> None:
    """The high level's mirror is written by the ROS executor thread; a behaviour's
    subscription whose callback switches (blocking) must not make that behaviour STUCK."""
    from beehave import Behavior

    class Charge(Behavior):
        def run(self) -> None:
            while self.sleep(1.0):
                pass

    class Work(Behavior):
        def run(self) -> None:
            with self.blackboard.subscribe("battery/low", self.on_low):
                while self.sleep(1.0):
                    pass

        def on_low(self, change: Change) -> None:
            if change.value:
                hl.switch("charge")

    hl.register("charge", Charge)
    hl.register("work", Work)
    work = hl.switch("work")
    assert wait_until(lambda: len(hl.blackboard.subscriptions) == 1)
    mirror = threading.Thread(target=hl.blackboard.set, args=("battery/low", True),
                              name="mirror-writer")
    mirror.start()
    mirror.join(WALL_TIMEOUT_S)
    assert not mirror.is_alive()
    assert hl.current == "charge"
    assert work.status.name == "INTERRUPTED", work.status
    assert not [e for e in events if e.kind.name == "STUCK"]


# -- non-finite numbers in JSON (issue 9, item 19) ---------------------------------------------

def test_non_finite_floats_round_trip_through_strict_json() -> None:
    from beehave.blackboard import from_json, to_json

    value = {"front_m": float("inf"), "back_m": float("-inf"), "ranges": [1.0, float("nan")],
             "pair": (2.5, float("inf")), "label": "inf", "n": 3}
    text = json.dumps(to_json(value), allow_nan=False)  # strict JSON, for any ROS 2 tool
    back = from_json(json.loads(text))
    assert back["front_m"] == float("inf") and back["back_m"] == float("-inf")
    assert back["ranges"][0] == 1.0 and back["ranges"][1] != back["ranges"][1]  # NaN
    assert back["pair"] == [2.5, float("inf")]
    assert back["label"] == "inf" and back["n"] == 3  # strings stay strings


def test_snapshot_encodes_non_finite_floats_as_tagged_numbers() -> None:
    bb = Blackboard()
    bb.set("laser/front_m", float("inf"))
    snap = json.loads(json.dumps(bb.snapshot(), allow_nan=False))
    assert snap["laser/front_m"]["value"] == {"$float": "inf"}


# -- review of issue 9 -----------------------------------------------------------------------

def test_a_subscription_closed_during_a_delivery_is_not_called_after_close_returns() -> None:
    """Callbacks run outside the lock, so close() cannot wait for a delivery under way;
    it must still keep the closed subscription from being called afterwards."""
    bb = Blackboard()
    entered, release = threading.Event(), threading.Event()
    after_close: list[Any] = []
    closed = threading.Event()

    def slow_first(change: Change) -> None:
        entered.set()
        release.wait(WALL_TIMEOUT_S)

    bb.subscribe("battery/low", slow_first)
    sub = bb.subscribe("battery/low",
                       lambda c: after_close.append(c.value) if closed.is_set() else None)
    writer = threading.Thread(target=bb.set, args=("battery/low", True))
    writer.start()
    assert entered.wait(WALL_TIMEOUT_S)
    sub.close()  # while slow_first runs: sub is next in line for this change
    closed.set()
    release.set()
    writer.join(WALL_TIMEOUT_S)
    assert not writer.is_alive()
    assert after_close == []


@pytest.mark.parametrize("make", [lambda: float("nan"), lambda: [1.0, float("nan")],
                                  lambda: {"x": float("nan")}, lambda: (float("nan"),)],
                         ids=["float", "list", "dict", "tuple"])
def test_rewriting_nan_is_no_change(make: Any) -> None:
    """nan != nan, yet a sensor that keeps reporting "no reading" has not changed (the
    mirror got it again at every snapshot). Each write is a new NaN object."""
    bb = Blackboard()
    seen: list[Change] = []
    bb.subscribe("laser/front_m", seen.append)
    bb.set("laser/front_m", make())
    bb.set("laser/front_m", make())
    assert len(seen) == 1
    bb.set("laser/front_m", 1.0)
    assert len(seen) == 2


def test_setting_a_value_already_stale_notifies_once_and_never_fresh() -> None:
    """A mirror copies a stale entry: one stale change, none when repeated, and nothing
    that reads as fresh in between."""
    bb = Blackboard()
    seen: list[tuple[Any, bool]] = []
    bb.set("battery/percentage", 54.0, writer="hal:battery")
    bb.subscribe("battery/percentage", lambda c: seen.append((c.value, c.stale)))
    for _ in range(3):
        bb.set("battery/percentage", 54.0, writer="hal:battery", stale=True)
    assert seen == [(54.0, True)]
    assert bb.is_stale("battery/percentage")
    bb.set("battery/percentage", 54.0, writer="hal:battery")  # the sensor is back
    assert seen == [(54.0, True), (54.0, False)]
    assert not bb.is_stale("battery/percentage")


def test_changes_queued_when_an_on_error_hook_raised_keep_their_order() -> None:
    """A raising on_error hook ends the delivery that called it; the changes other threads
    queued meanwhile must still reach subscribers before any newer one."""
    def hook(_sub: Subscription, exc: BaseException) -> None:
        raise RuntimeError("the hook itself is broken") from exc

    bb = Blackboard(on_error=hook)
    seen: list[int] = []
    entered, queued = threading.Event(), threading.Event()

    def breaks_on_first(change: Change) -> None:
        if change.value == 1:
            entered.set()
            assert queued.wait(WALL_TIMEOUT_S)
            raise ValueError("subscriber bug")

    bb.subscribe("k", lambda c: seen.append(c.value))
    bb.subscribe("k", breaks_on_first)
    failed: list[BaseException] = []

    def first_writer() -> None:
        try:
            bb.set("k", 1)
        except RuntimeError as exc:
            failed.append(exc)

    writer = threading.Thread(target=first_writer)
    writer.start()
    assert entered.wait(WALL_TIMEOUT_S)
    bb.set("k", 2)  # delivery of k is under way in the writer: queued behind it
    queued.set()
    writer.join(WALL_TIMEOUT_S)
    assert failed, "the hook's exception reaches the writer that ran it"
    bb.set("k", 3)
    assert seen == [1, 2, 3]
    assert bb.get("k") == 3
