"""The core's promises under faults (issue 9, high level).

One behaviour always runs; at most one action of a type, its safe state included; a switch
or shutdown returns within ``stop_timeout_s`` (plus a short, documented grace); bad input
gets an error that names the culprit. Each test here failed before its fix.
"""

from __future__ import annotations

import logging
import math
import random
import threading
import time
from typing import Any

import pytest

from beehave import (
    Action,
    ActionTypeBusy,
    Behavior,
    ConfigError,
    ConstructorFailed,
    Event,
    EventKind,
    HighLevelBehaviorManager,
    InvalidParameters,
    NotASubclass,
    ReservedAttribute,
    Status,
    SwitchSuperseded,
)
from beehave.events import describe
from beehave.testing import (
    WALL_TIMEOUT_S,
    ScriptedAction,
    Timeline,
    beehave_threads,
    wait_until,
    wall_timeout,
)


class Forever(Behavior):
    def run(self) -> None:
        while self.sleep(1.0):
            pass


class ShortLived(Behavior):
    """Ends on its own when ``done`` is set (or after ``life_s``)."""

    def __init__(self, life_s: float = math.inf) -> None:
        self.done = threading.Event()
        self.life_s = life_s

    def run(self) -> None:
        self.done.wait(None if math.isinf(self.life_s) else self.life_s)


def settled(hl: HighLevelBehaviorManager, timeout_s: float = 2.0) -> bool:
    """Every queued switch (fallbacks included) has been executed."""
    return wait_until(lambda: not hl._processing and not hl._pending, timeout_s)


# ---- 1. one behaviour always runs --------------------------------------------------------

def test_a_behaviour_ending_during_a_switch_does_not_leave_the_manager_empty(
        hl: HighLevelBehaviorManager) -> None:
    """The race of item 1, made deterministic: the top-level behaviour ends on its own after
    the switch took the request but before it stops the behaviour (the idle fallback is
    queued then). The user's request must win, and something must run."""
    hl.register("short", ShortLived)
    hl.register("long", Forever)
    short: Any = hl.switch("short")
    original = hl._stop_top

    def stop_top_after_the_top_ended() -> None:  # fault injection: widen the window
        short.done.set()
        assert short._join(2.0)  # ended, and its fallback is queued
        original()

    hl._stop_top = stop_top_after_the_top_ended  # type: ignore[method-assign]
    try:
        hl.switch("long")  # before the fix: SwitchSuperseded, and nothing ran at all
    finally:
        hl._stop_top = original  # type: ignore[method-assign]
    assert settled(hl)
    assert hl.current == "long"
    assert hl.top is not None and hl.top.status is Status.RUNNING


def test_storm_of_switches_and_behaviours_ending_on_their_own(
        hl: HighLevelBehaviorManager) -> None:
    """After every switch settles exactly one top-level behaviour runs: the last one
    requested, or idle when that one ended on its own."""
    hl.register("short", ShortLived)
    hl.register("long", Forever)
    rng = random.Random(9)
    for _ in range(300):
        hl.switch("short", life_s=rng.uniform(0, 0.0005))
        time.sleep(rng.uniform(0, 0.0005))
        hl.switch("long")  # nobody else asks: it is never superseded
        assert settled(hl)
        assert hl.current == "long", hl.history[-3:]
        assert hl.top is not None and hl.top.status is Status.RUNNING


def test_concurrent_storm_leaves_exactly_one_behaviour_running() -> None:
    active = 0
    most = 0
    lock = threading.Lock()

    class Counted(Behavior):
        def __init__(self, life_s: float) -> None:
            self.life_s = life_s

        def run(self) -> None:
            nonlocal active, most
            with lock:
                active += 1
                most = max(most, active)
            try:
                self.sleep(self.life_s)
            finally:
                with lock:
                    active -= 1

    before = set(beehave_threads())
    hl = HighLevelBehaviorManager(stop_timeout_s=0.3)
    hl.register("counted", Counted, life_s=0.001)
    with hl:
        def storm(seed: int) -> None:
            rng = random.Random(seed)
            for _ in range(150):
                life = rng.choice([0.0, 0.0005, 0.002, math.inf])
                try:
                    if rng.random() < 0.5:
                        hl.switch("counted", life_s=life)
                    else:
                        hl.request_switch("counted", life_s=life)
                except SwitchSuperseded:
                    pass

        threads = [threading.Thread(target=storm, args=(i,)) for i in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert settled(hl, 5.0)
        assert hl.top is not None and hl.top.status is Status.RUNNING
        assert hl.current in ("counted", "idle")
        assert most == 1  # never two top-level behaviours at once
    assert wait_until(lambda: not [t for t in beehave_threads() if t not in before])


# ---- 2. the type lock covers the forced safe state --------------------------------------

def test_stuck_action_keeps_its_type_until_its_forced_safe_state_returned() -> None:
    timeline = Timeline()
    stubborn = ScriptedAction("driving", duration_s=30, ignore_interrupt_s=math.inf,
                              safe_state_s=math.inf, timeline=timeline)
    busy_seen: list[ActionTypeBusy] = []
    preempt_failed = threading.Event()
    started_after: list[ScriptedAction] = []

    class Driver(Behavior):
        def run(self) -> None:
            self.start_action(stubborn)
            try:
                self.start_action(ScriptedAction("driving", timeline=timeline), preempt=True)
            except ActionTypeBusy:
                preempt_failed.set()  # it ignored the interrupt: STUCK, safe state forced
            while not self.interrupted:
                try:
                    started_after.append(self.start_action(
                        ScriptedAction("driving", duration_s=0.05, timeline=timeline)))
                    return
                except ActionTypeBusy as exc:
                    busy_seen.append(exc)
                    self.sleep(0.01)

    hl = HighLevelBehaviorManager(stop_timeout_s=0.2)
    hl.register("driver", Driver)
    try:
        with hl:
            hl.switch("driver")
            # Before the fix the forced safe state ran in the preempting thread: blocked.
            assert preempt_failed.wait(WALL_TIMEOUT_S)
            assert stubborn.status is Status.STUCK and stubborn.safe_state_pending
            stubborn.release.set()  # run() returns; the safe state still runs
            assert wait_until(lambda: len(busy_seen) >= 3)
            assert not started_after
            assert "safe_state() has not returned" in str(busy_seen[-1])
            assert hl.snapshot()["locks"]["driving"]["safe_state_pending"] is True
            stubborn.safe_release.set()
            assert wait_until(lambda: bool(started_after))
    finally:
        stubborn.release.set()
        stubborn.safe_release.set()
    assert timeline.max_concurrent["driving"] == 1, timeline.marks
    assert stubborn.safe_state_calls == 1


# ---- 3. switch and shutdown are bounded -------------------------------------------------

class Waits(Behavior):
    """The common pattern: start an action and wait for it."""

    def __init__(self, action: ScriptedAction) -> None:
        self.action = action

    def run(self) -> None:
        self.start_action(self.action).wait()


def _timed(fn: Any) -> tuple[bool, float]:
    thread = threading.Thread(target=fn, daemon=True)
    t0 = time.monotonic()
    thread.start()
    thread.join(5.0)  # a safety net: the bound is checked below, loosely (noisy machine)
    return not thread.is_alive(), time.monotonic() - t0


def test_switch_returns_although_a_stuck_safe_state_hangs() -> None:
    stop_timeout_s = 0.3
    blocked = ScriptedAction("driving", duration_s=30, ignore_interrupt_s=math.inf,
                             safe_state_s=math.inf)
    events: list[Event] = []
    hl = HighLevelBehaviorManager(stop_timeout_s=stop_timeout_s)
    hl.register("waits", Waits, action=blocked)
    hl.subscribe(events.append)
    try:
        with hl:
            hl.switch("waits")
            assert wait_until(lambda: blocked.status is Status.RUNNING)
            returned, took = _timed(lambda: hl.switch("idle"))
            assert returned, "switch() never returned (forced safe state in its thread)"
            assert took < stop_timeout_s + wall_timeout(0.05), took
            assert hl.current == "idle"
            assert blocked.status is Status.STUCK and blocked.safe_state_pending
            overdue = [e for e in events if e.kind is EventKind.SAFE_STATE_OVERDUE]
            assert [e.subject for e in overdue] == [blocked.path]
            returned, took = _timed(hl.shutdown)
            assert returned and took < stop_timeout_s + wall_timeout(0.05), took
    finally:
        blocked.release.set()
        blocked.safe_release.set()
    assert wait_until(lambda: blocked.safe_state_calls == 1 and not blocked.alive)


def test_a_quick_forced_safe_state_has_run_when_switch_returns(
        hl: HighLevelBehaviorManager) -> None:
    stubborn = ScriptedAction("driving", duration_s=30, ignore_interrupt_s=math.inf,
                              safe_state_s=0.02)
    hl.register("waits", Waits, action=stubborn)
    try:
        hl.switch("waits")
        assert wait_until(lambda: stubborn.status is Status.RUNNING)
        hl.switch("idle")
        assert stubborn.status is Status.STUCK
        assert stubborn.safe_state_calls == 1  # the README's promise: safe when it returns
    finally:
        stubborn.release.set()
    assert wait_until(lambda: not stubborn.alive)


# ---- 4. non-finite numbers ---------------------------------------------------------------

@pytest.mark.parametrize("bad", [math.inf, math.nan, -1.0, 0, True, "2"])
def test_stop_timeout_must_be_positive_and_finite(bad: Any) -> None:
    with pytest.raises(ConfigError, match="stop_timeout_s"):
        HighLevelBehaviorManager(stop_timeout_s=bad)


def test_sleep_takes_inf_for_until_interrupted_and_rejects_nan(
        hl: HighLevelBehaviorManager) -> None:
    outcome: list[Any] = []

    class Sleeper(Behavior):
        def run(self) -> None:
            try:
                self.sleep(math.nan)
            except ConfigError as exc:
                outcome.append(exc)
            outcome.append(self.sleep(math.inf))

    hl.register("sleeper", Sleeper)
    hl.switch("sleeper")
    assert wait_until(lambda: len(outcome) == 1)
    assert "sleep(seconds)" in str(outcome[0])
    hl.switch("idle")
    assert outcome[1] is False  # woke by the interrupt


# ---- 5. one switch processor, a bounded queue --------------------------------------------

def test_many_request_switches_use_one_thread_and_the_latest_wins(
        hl: HighLevelBehaviorManager) -> None:
    hl.register("a", Forever)
    hl.register("b", Forever)
    events: list[Event] = []
    hl.subscribe(events.append)
    before = len(beehave_threads())
    most = 0
    for i in range(500):
        hl.request_switch("a" if i % 2 else "b")
        most = max(most, len(beehave_threads()))
    hl.request_switch("a")
    assert hl.requested in ("a", None)  # None once the processor took it
    assert settled(hl, 10.0)
    assert hl.requested is None
    # One processor thread (plus the behaviours' own) however many requests arrive.
    assert most - before <= 3, (before, most)
    assert hl.current == "a"
    completed = [e for e in events if e.kind is EventKind.SWITCH_COMPLETED]
    superseded = [e for e in events if e.kind is EventKind.SWITCH_SUPERSEDED]
    assert len(completed) + len(superseded) == 501


# ---- 8. behaviours' blackboard subscriptions end with them -------------------------------

def test_blackboard_subscriptions_are_closed_when_the_behaviour_ends(
        hl: HighLevelBehaviorManager) -> None:
    calls: list[Any] = []
    subscriptions: list[Any] = []

    class Watcher(Behavior):
        def run(self) -> None:
            subscriptions.append(self.blackboard.subscribe("battery/*", calls.append))

    hl.register("watcher", Watcher)
    for _ in range(50):
        hl.switch("watcher")
        assert wait_until(lambda: hl.current == "idle")
    assert len(subscriptions) == 50
    assert all(s.closed for s in subscriptions)
    hl.blackboard.set("battery/percentage", 20.0)
    assert calls == []


# ---- 9. shutdown from inside ------------------------------------------------------------

def test_shutdown_from_inside_a_behaviour_is_deferred(hl: HighLevelBehaviorManager) -> None:
    outcome: list[Any] = []

    class Quitter(Behavior):
        def run(self) -> None:
            try:
                self.manager.shutdown()
                outcome.append("returned")
            except BaseException as exc:  # before the fix: cannot join current thread
                outcome.append(exc)
            self.sleep(5.0)  # interrupted by the deferred shutdown

    hl.register("quitter", Quitter)
    hl.switch("quitter")
    assert wait_until(lambda: hl.snapshot()["state"] == "stopped"), hl.snapshot()["state"]
    assert outcome == ["returned"]
    hl.shutdown()  # waits for the deferred one; the fixture checks no thread is left


# ---- 10. errors say who is at fault ------------------------------------------------------

def test_a_constructor_that_raises_is_reported_as_its_own_fault(
        hl: HighLevelBehaviorManager) -> None:
    class Broken(Behavior):
        def __init__(self, speed_mps: float = 1.0) -> None:
            self.table: dict[str, float] = {}
            self.limit = self.table["speed"]  # a bug, not a bad parameter

        def run(self) -> None:
            pass

    hl.register("broken", Broken)
    with pytest.raises(ConstructorFailed, match=r"Broken.__init__ raised KeyError") as info:
        hl.switch("broken", speed_mps=2.0)
    assert not isinstance(info.value, InvalidParameters)
    assert hl.current == "idle"


def test_a_behaviour_without_run_is_refused_at_register(hl: HighLevelBehaviorManager) -> None:
    class NoRun(Behavior):
        def tick(self) -> None:
            pass

    with pytest.raises(NotASubclass, match=r"does not implement run\(\)"):
        hl.register("norun", NoRun)  # type: ignore[type-abstract]


def test_the_py_trees_habit_of_naming_through_super_init_works(
        hl: HighLevelBehaviorManager) -> None:
    class Lift(Action):
        def __init__(self, height_m: float) -> None:
            super().__init__(name="front_lift")
            self.height_m = height_m

        def run(self) -> float:
            return self.height_m

    started: list[Action] = []

    class User(Behavior):
        def run(self) -> None:
            started.append(self.start_action(Lift(0.2)))
            started[0].wait(2.0)

    hl.register("user", User)
    hl.switch("user")
    assert wait_until(lambda: bool(started) and started[0].status is Status.SUCCEEDED)
    assert started[0].path == "user/front_lift"


@pytest.mark.parametrize("attr", ["status", "result", "path", "parent", "interrupted"])
def test_assigning_a_reserved_attribute_names_it(hl: HighLevelBehaviorManager,
                                                 attr: str) -> None:
    class Clash(Action):
        def __init__(self) -> None:
            setattr(self, attr, "mine")

        def run(self) -> None:
            pass

    with pytest.raises(ReservedAttribute, match=rf"Clash\.{attr} is beehave's"):
        Clash()

    class ClashingBehavior(Behavior):
        def __init__(self) -> None:
            setattr(self, attr, "mine")

        def run(self) -> None:
            pass

    hl.register("clash", ClashingBehavior)
    with pytest.raises(ConstructorFailed, match=rf"ClashingBehavior\.{attr} is beehave's"):
        hl.switch("clash")


@pytest.mark.parametrize("attr", ["result", "status", "children", "safe_state_error"])
def test_defining_a_reserved_name_in_a_class_body_is_refused_at_once(attr: str) -> None:
    # A class attribute of that name would hide beehave's value from every reader (a
    # `result = None` in the body: the handle's result then reads None forever).
    with pytest.raises(ReservedAttribute, match=rf"Shadows\.{attr} is beehave's"):
        type("Shadows", (Action,), {attr: None, "run": lambda self: None})
    with pytest.raises(ReservedAttribute, match=rf"Shadows\.{attr} is beehave's"):
        type("Shadows", (Behavior,), {attr: None, "run": lambda self: None})


def test_reserved_names_read_as_before_and_stay_read_only(hl: HighLevelBehaviorManager) -> None:
    action = ScriptedAction(result="there")
    assert action.result is None and action.error is None and action.started_at is None
    assert not hasattr(action, "children")
    with pytest.raises(ReservedAttribute, match=r"ScriptedAction\.children is beehave's"):
        action.children = []  # type: ignore[misc]

    class Starts(Behavior):
        def run(self) -> None:
            self.start_action(action).wait(WALL_TIMEOUT_S)

    hl.register("starts", Starts)
    top = hl.switch("starts")
    assert top.wait(WALL_TIMEOUT_S)
    assert action.status is Status.SUCCEEDED and action.result == "there"
    assert action.started_at is not None and action.ended_at is not None
    assert action.ended_at >= action.started_at and action.elapsed_s is not None
    with pytest.raises(ReservedAttribute, match=r"Starts\.ended_at is beehave's"):
        top.ended_at = 0.0  # type: ignore[misc]
    renamed = top.path
    top.name = "renamed"
    assert top.path == "renamed" and renamed == "starts"


def test_a_behaviour_and_an_action_may_keep_a_lock_and_a_result_of_their_own(
        hl: HighLevelBehaviorManager) -> None:
    # `self._lock`, `self._result`, `self._error` are common names in user classes:
    # beehave's own state must not live under them (the market's auctioneer keeps a lock).
    class Guarded(Action):
        def __init__(self) -> None:
            self._lock = threading.Lock()
            self._result = "mine"
            self._error = "mine too"

        def run(self) -> str:
            with self._lock:
                self.sleep(0.01)
            return "beehave's"

    class Sleeper(Action):
        def __init__(self) -> None:
            self._lock = threading.Lock()

        def run(self) -> None:
            with self._lock:
                self.sleep(math.inf)

    class Keeper(Behavior):
        def __init__(self) -> None:
            self._lock = threading.Lock()
            self.started: list[Action] = []

        def run(self) -> None:
            with self._lock:
                guarded = self.start_action(Guarded())
                guarded.wait(WALL_TIMEOUT_S)
                self.started += [guarded, self.start_action(Sleeper())]
            while self.sleep(math.inf):
                pass

    hl.register("keeper", Keeper)
    top = hl.switch("keeper")
    assert wait_until(lambda: len(top.started) == 2 and top.started[1].status is Status.RUNNING)
    guarded, sleeper = top.started
    assert guarded.status is Status.SUCCEEDED and guarded.result == "beehave's"
    assert guarded.error is None and guarded._result == "mine" and guarded._error == "mine too"
    hl.switch("idle")
    assert top.status is Status.INTERRUPTED and sleeper.status is Status.INTERRUPTED


def test_two_actions_of_one_class_have_distinct_paths(hl: HighLevelBehaviorManager) -> None:
    paths: list[str] = []

    class Drive(Action):
        action_type = "driving"

        def run(self) -> None:
            pass

    class Twice(Behavior):
        def run(self) -> None:
            for _ in range(3):
                action = self.start_action(Drive())
                action.wait(2.0)
                paths.append(action.path)

    hl.register("twice", Twice)
    hl.switch("twice")
    assert wait_until(lambda: len(paths) == 3)
    assert paths == ["twice/Drive", "twice/Drive#2", "twice/Drive#3"]


def test_run_returning_with_actions_still_running_is_logged(
        hl: HighLevelBehaviorManager, caplog: pytest.LogCaptureFixture) -> None:
    class Forgetful(Behavior):
        def run(self) -> None:
            self.start_action(ScriptedAction("sound", duration_s=10.0, name="Beep"))

    hl.register("forgetful", Forgetful)
    with caplog.at_level(logging.INFO, logger="beehave.behavior"):
        hl.switch("forgetful")
        assert wait_until(lambda: hl.current == "idle")
    assert any("forgetful/Beep" in r.getMessage() and "run() returned" in r.getMessage()
               for r in caplog.records), caplog.text


def test_stuck_report_says_what_was_ignored_for_how_long_and_where(
        hl: HighLevelBehaviorManager) -> None:
    events: list[Event] = []
    hl.subscribe(events.append)
    stubborn = ScriptedAction("driving", duration_s=30, ignore_interrupt_s=math.inf)
    gate = threading.Event()

    class Top(Behavior):
        def run(self) -> None:
            self.start_action(stubborn)
            gate.wait(30)  # ignores its own interrupt too: the top is STUCK

    hl.register("top", Top)
    try:
        hl.switch("top")
        assert wait_until(lambda: stubborn.status is Status.RUNNING)
        hl.switch("idle")
        stuck = {e.subject: e for e in events if e.kind is EventKind.STUCK}
        assert set(stuck) == {"top", stubborn.path}
        detail = stuck[stubborn.path].detail
        assert detail["ignored"] == "its interrupt"
        assert detail["for_s"] >= 0.3 * 0.9 and detail["stop_timeout_s"] == 0.3
        assert "fakes.py" in detail["at"], detail  # blocked in ScriptedAction.run
        assert "test_core_promises.py" in stuck["top"].detail["at"]
        assert "its interrupt" in describe(stuck[stubborn.path])
        assert [h["status"] for h in hl.history if h["name"] == "top"] == ["STUCK"]
    finally:
        stubborn.release.set()
        gate.set()


def test_a_behaviour_that_succeeds_is_not_logged_as_a_failure() -> None:
    event = Event(EventKind.FALLBACK, "tour", Status.SUCCEEDED.name, detail={"to": "idle"})
    assert describe(event) == "tour ended SUCCEEDED on its own; starting 'idle'"


# ---- found in review -----------------------------------------------------------------------

def test_switch_from_a_switch_requested_subscriber_does_not_deadlock(
        hl: HighLevelBehaviorManager) -> None:
    """A supervisor redirects every request for ``patrol`` to ``charge`` from an event
    callback: the nested request wins, nothing hangs."""
    hl.register("patrol", Forever)
    hl.register("charge", Forever)

    def redirect(event: Event) -> None:
        if event.kind is EventKind.SWITCH_REQUESTED and event.subject == "patrol":
            hl.switch("charge")

    hl.subscribe(redirect)
    outcome: list[Any] = []

    def ask() -> None:
        try:
            hl.switch("patrol")
            outcome.append("switched")
        except SwitchSuperseded as exc:
            outcome.append(exc)

    thread = threading.Thread(target=ask, daemon=True)
    thread.start()
    thread.join(5.0)
    assert not thread.is_alive(), "switch() from inside a SWITCH_REQUESTED callback hung"
    assert isinstance(outcome[0], SwitchSuperseded)
    assert settled(hl)
    assert hl.current == "charge"


def test_history_keeps_every_ended_behaviour() -> None:
    """Ended behaviours are freed and their ids reused: history must not mistake a new one
    for an old one."""
    hl = HighLevelBehaviorManager(stop_timeout_s=0.3, history_len=500)
    hl.register("a", Forever)
    hl.register("b", Forever)
    with hl:
        for i in range(200):
            hl.switch("a" if i % 2 else "b")
        hl.switch("idle")
        names = [h["name"] for h in hl.history if h["name"] in ("a", "b")]
    assert len(names) == 200


def test_stuck_items_are_forgotten_once_their_threads_end() -> None:
    """Safe states that end right at the stop deadline race the owner declaring them
    STUCK: whatever the interleaving, nothing stays listed as stuck once it ended."""
    rng = random.Random(1)

    class Edge(Action):
        action_type = "driving"

        def __init__(self, eps_s: float) -> None:
            self.eps_s = eps_s

        def run(self) -> None:
            while self.sleep(1.0):
                pass

        def safe_state(self) -> None:
            deadline = self.stop_deadline
            assert deadline is not None
            while time.monotonic() < deadline - self.eps_s:
                time.sleep(0.0002)

    class Top(Behavior):
        def __init__(self, eps_s: float) -> None:
            self.eps_s = eps_s

        def run(self) -> None:
            self.start_action(Edge(self.eps_s))
            while self.sleep(1.0):
                pass

    hl = HighLevelBehaviorManager(stop_timeout_s=0.02)
    hl.register("top", Top, eps_s=0.0)
    with hl:
        for _ in range(120):
            hl.switch("top", eps_s=rng.uniform(-0.0002, 0.0012))
            time.sleep(0.003)
            hl.switch("idle")
        assert wait_until(lambda: not hl.snapshot()["stuck"]), hl.snapshot()["stuck"]


def test_huge_timeouts_are_refused_or_mean_forever(hl: HighLevelBehaviorManager) -> None:
    with pytest.raises(ConfigError, match="at most"):
        HighLevelBehaviorManager(stop_timeout_s=1e10)
    woke: list[bool] = []

    class Sleeper(Behavior):
        def run(self) -> None:
            woke.append(self.sleep(1e10))  # longer than threading can wait: until interrupted

    hl.register("sleeper", Sleeper)
    hl.switch("sleeper")
    hl.switch("idle")
    assert woke == [False]
    assert hl.current == "idle"


def test_a_hanging_safe_state_after_an_obeyed_interrupt_is_reported_where_it_hangs() -> None:
    """run() obeyed its interrupt but safe_state() hangs (in run's thread): STUCK, the type
    stays locked and says why, and SAFE_STATE_OVERDUE points at the safe_state line."""
    gate = threading.Event()

    class Drive(Action):
        action_type = "driving"

        def run(self) -> None:
            while self.sleep(1.0):
                pass

        def safe_state(self) -> None:
            gate.wait(30)  # the line SAFE_STATE_OVERDUE must name

    class Top(Behavior):
        def run(self) -> None:
            self.start_action(Drive())
            while self.sleep(1.0):
                pass

    events: list[Event] = []
    hl = HighLevelBehaviorManager(stop_timeout_s=0.2)
    hl.register("top", Top)
    hl.subscribe(events.append)
    try:
        with hl:
            hl.switch("top")
            assert wait_until(lambda: bool(hl.snapshot()["locks"]))
            hl.switch("idle")
            lock = hl.snapshot()["locks"]["driving"]
            assert lock["status"] == "STUCK" and lock["safe_state_pending"] is True
            overdue = [e for e in events if e.kind is EventKind.SAFE_STATE_OVERDUE]
            assert len(overdue) == 1
            assert "in safe_state" in overdue[0].detail["at"], overdue[0].detail
            # (The behaviour waiting for it may be declared STUCK too, and first.)
            stuck = next(e for e in events
                         if e.kind is EventKind.STUCK and e.subject == "top/Drive")
            assert "safe_state() has not returned" in stuck.detail["ignored"]
            gate.set()
            assert wait_until(lambda: not hl.snapshot()["locks"])
    finally:
        gate.set()


def test_a_fallback_to_nothing_says_so() -> None:
    event = Event(EventKind.FALLBACK, "leds", "FAILED", detail={"to": None})
    assert describe(event) == "leds ended FAILED on its own; nothing to fall back to"
