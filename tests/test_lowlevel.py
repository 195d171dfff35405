"""LowLevelBehaviorManager and Logic contract: switching, structured concurrency, fallback."""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from beehave.errors import (
    AlreadyStarted,
    BeehaveError,
    ChildFailed,
    ConfigError,
    InvalidParameters,
    ManagerShutdown,
    UnknownLogic,
)
from beehave.events import Event, EventKind, describe
from beehave.logic import Logic
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.status import Status
from beehave.testing import WALL_TIMEOUT_S
from beehave.testing import wait_until as _wait_until

# The suite's one bound (beehave.testing): a safety net only; nothing here waits that long
# when it works.
WAIT_S = WALL_TIMEOUT_S


class Forever(Logic):
    """Runs until cancelled; records that its cleanup ran."""

    def __init__(self, label: str = "") -> None:
        self.label = label
        self.cleaned_up = threading.Event()
        self.started = threading.Event()

    async def run(self) -> None:
        self.started.set()
        try:
            await asyncio.Event().wait()
        finally:
            self.cleaned_up.set()


class Crashing(Logic):
    async def run(self) -> None:
        await asyncio.sleep(0)
        raise RuntimeError("logic bug")


class Parent(Logic):
    """Starts two sub-logics (one of them with a grandchild) and waits."""

    def __init__(self) -> None:
        self.kids: list[Logic] = []

    async def run(self) -> None:
        self.kids.append(self.start_logic(Forever("a"), name="a"))
        b = self.start_logic(Nested(), name="b")
        self.kids.append(b)
        await asyncio.Event().wait()


class Nested(Logic):
    def __init__(self) -> None:
        self.grandchild: Forever | None = None

    async def run(self) -> None:
        self.grandchild = self.start_logic(Forever("g"), name="g")
        await asyncio.Event().wait()


class FailingChildParent(Logic):
    async def run(self) -> None:
        self.start_logic(Crashing(), name="bad")
        await asyncio.Event().wait()


class Stubborn(Logic):
    """Ignores its first cancellation (a bug the manager must survive)."""

    async def run(self) -> None:
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            await asyncio.sleep(0.3)


@pytest.fixture
def ll() -> Iterator[LowLevelBehaviorManager]:
    before = set(threading.enumerate())
    manager = LowLevelBehaviorManager(default="idle", stop_timeout_s=0.1)
    manager.register("idle", Forever, label="idle")
    manager.register("forever", Forever)
    manager.register("crashing", Crashing)
    manager.register("parent", Parent)
    manager.register("failing_child", FailingChildParent)
    manager.register("stubborn", Stubborn)
    yield manager
    manager.shutdown()
    assert set(threading.enumerate()) <= before, "thread left behind"


def events_of(ll: LowLevelBehaviorManager) -> list[Event]:
    got: list[Event] = []
    ll.subscribe(got.append)
    return got


def wait_until(predicate: Any, timeout_s: float = WAIT_S) -> bool:
    return _wait_until(predicate, timeout_s)


# -- registry and errors ---------------------------------------------------------------------

def test_logic_subclass_needs_no_super_init_and_has_a_handle() -> None:
    logic = Forever("x")
    assert (logic.status, logic.error, logic.name) == (Status.PENDING, None, "Forever")
    with pytest.raises(BeehaveError, match="not running"):
        _ = logic.blackboard


def test_register_rejects_parameters_the_constructor_does_not_take() -> None:
    manager = LowLevelBehaviorManager()
    with pytest.raises(InvalidParameters, match="'x'.*colour"):
        manager.register("x", Forever, colour="red")
    with pytest.raises(InvalidParameters, match="takes no parameters"):
        manager.register("y", Crashing, speed=1)


def test_unknown_logic_lists_registered_names_and_stops_nothing(
        ll: LowLevelBehaviorManager) -> None:
    events = events_of(ll)
    with ll:
        ll.switch("forever")
        running = ll.logic
        with pytest.raises(UnknownLogic) as info:
            ll.switch("nope")
        assert "'nope'" in str(info.value)
        for name in ("crashing", "forever", "idle", "parent"):
            assert repr(name) in str(info.value)
        assert ll.logic is running and ll.current == "forever"
    assert any(e.kind is EventKind.SWITCH_REJECTED and e.subject == "nope" for e in events)


# -- switching ---------------------------------------------------------------------------------

def test_default_runs_when_nothing_is_selected(ll: LowLevelBehaviorManager) -> None:
    with ll:
        assert ll.current == "idle"


def test_switch_before_start_selects_the_first_logic(ll: LowLevelBehaviorManager) -> None:
    assert ll.switch("forever") is None
    with ll:
        assert ll.current == "forever"


def test_switch_from_another_thread_returns_once_old_ended_and_new_runs(
        ll: LowLevelBehaviorManager) -> None:
    with ll:
        old = ll.logic
        assert isinstance(old, Forever)
        new = ll.switch("forever", label="second")
        assert isinstance(new, Forever) and new.label == "second"
        assert old.status is Status.INTERRUPTED and old.cleaned_up.is_set()
        assert new.status is Status.RUNNING and ll.current == "forever"
        assert new.started.wait(WAIT_S)


def test_switch_cancels_sub_logics_recursively_and_runs_their_cleanup(
        ll: LowLevelBehaviorManager) -> None:
    with ll:
        parent = ll.switch("parent")
        assert isinstance(parent, Parent)
        assert wait_until(lambda: len(parent.kids) == 2 and parent.kids[1].children)
        a, b = parent.kids
        assert isinstance(b, Nested) and b.grandchild is not None
        grandchild = b.grandchild
        assert grandchild.path == "parent/b/g"
        ll.switch("forever")
        for logic in (parent, a, b, grandchild):
            assert logic.status is Status.INTERRUPTED, logic
        assert isinstance(a, Forever) and a.cleaned_up.is_set() and grandchild.cleaned_up.is_set()
        assert parent.children == () and b.children == ()


def test_switch_inside_the_loop_raises_and_switch_async_works(
        ll: LowLevelBehaviorManager) -> None:
    async def inside() -> tuple[str, str | None]:
        try:
            ll.switch("forever")
        except BeehaveError as err:
            message = str(err)
        else:
            message = ""
        await ll.switch_async("forever")
        return message, ll.current

    with ll:
        message, current = ll.call(inside(), timeout_s=WAIT_S)
    assert "switch_async" in message and current == "forever"


def test_switch_events_are_requested_then_completed(ll: LowLevelBehaviorManager) -> None:
    events = events_of(ll)
    with ll:
        ll.switch("forever")
    kinds = [(e.kind, e.subject) for e in events if e.kind.name.startswith("SWITCH")]
    assert kinds == [(EventKind.SWITCH_REQUESTED, "idle"),  # the default started
                     (EventKind.SWITCH_COMPLETED, "idle"),
                     (EventKind.SWITCH_REQUESTED, "forever"),
                     (EventKind.SWITCH_COMPLETED, "forever")]


def test_crashing_top_level_logic_is_recorded_reported_and_replaced_by_default(
        ll: LowLevelBehaviorManager) -> None:
    events = events_of(ll)
    with ll:
        crashing = ll.switch("crashing")
        assert crashing is not None
        assert wait_until(lambda: ll.current == "idle")
        assert crashing.status is Status.FAILED
        assert isinstance(crashing.error, RuntimeError)
        assert ll.last_failed is crashing
    fallback = [e for e in events if e.kind is EventKind.FALLBACK]
    assert len(fallback) == 1 and fallback[0].subject == "crashing"
    assert isinstance(fallback[0].error, RuntimeError) and fallback[0].detail["next"] == "idle"


def test_failing_sub_logic_fails_its_parent_with_child_failed(
        ll: LowLevelBehaviorManager) -> None:
    with ll:
        parent = ll.switch("failing_child")
        assert parent is not None
        assert wait_until(lambda: ll.current == "idle")
        assert parent.status is Status.FAILED
        assert isinstance(parent.error, ChildFailed)
        assert isinstance(parent.error.__cause__, RuntimeError)
        assert parent.error.child.path == "failing_child/bad"


def test_logic_ignoring_cancellation_is_reported_stuck_and_the_switch_goes_on(
        ll: LowLevelBehaviorManager) -> None:
    events = events_of(ll)
    with ll:
        stubborn = ll.switch("stubborn")
        new = ll.switch("forever")
        assert new is not None and new.status is Status.RUNNING
        assert stubborn is not None and stubborn.status is Status.STUCK
    assert any(e.kind is EventKind.STUCK and e.subject == "stubborn" for e in events)
    assert stubborn.status.finished and stubborn.task is not None and stubborn.task.done()


def test_snapshot_is_json_serialisable_and_shows_the_running_tree(
        ll: LowLevelBehaviorManager) -> None:
    with ll:
        parent = ll.switch("parent")
        assert isinstance(parent, Parent)
        assert wait_until(lambda: len(parent.kids) == 2)
        snap = json.loads(json.dumps(ll.snapshot()))
    assert snap["current"] == "parent"
    assert snap["logic"]["status"] == "RUNNING"
    assert sorted(c["name"] for c in snap["logic"]["children"]) == ["a", "b"]
    assert snap["registered"] == ll.registered


# -- lifecycle ---------------------------------------------------------------------------------

def test_context_manager_leaves_no_thread_and_no_task(ll: LowLevelBehaviorManager) -> None:
    before = set(threading.enumerate())
    with ll:
        loop = ll.loop
        assert loop is not None
        ll.switch("parent")
        assert len(threading.enumerate()) == len(before) + 2  # the loop and its watchdog
    assert set(threading.enumerate()) == before
    assert loop.is_closed()
    assert not asyncio.all_tasks(loop)
    with pytest.raises(ManagerShutdown):
        ll.switch("forever")


def test_manager_runs_in_the_callers_loop_until_shutdown() -> None:
    class Stopper(Logic):
        async def run(self) -> None:
            await asyncio.sleep(0)
            manager.shutdown()  # inside the loop: only asks
            await asyncio.Event().wait()

    manager = LowLevelBehaviorManager(default="stopper")
    manager.register("stopper", Stopper)

    async def main() -> tuple[set[asyncio.Task[Any]], Logic | None]:
        await asyncio.wait_for(manager.run(), WAIT_S)
        return asyncio.all_tasks() - {asyncio.current_task()}, manager.history[-1]

    leftover, stopped = asyncio.run(main())
    assert leftover == set()
    assert stopped is not None and stopped.status is Status.INTERRUPTED
    with pytest.raises(AlreadyStarted):
        asyncio.run(manager.run())


def test_cancelling_run_stops_logics_and_leaves_no_task() -> None:
    manager = LowLevelBehaviorManager(default="forever")
    manager.register("forever", Forever)

    async def main() -> tuple[set[asyncio.Task[Any]], Logic | None]:
        task = asyncio.create_task(manager.run())
        while manager.current != "forever":
            await asyncio.sleep(0)
        logic = manager.logic
        task.cancel()
        await asyncio.wait({task})
        return asyncio.all_tasks() - {asyncio.current_task()}, logic

    leftover, logic = asyncio.run(main())
    assert leftover == set()
    assert isinstance(logic, Forever) and logic.status is Status.INTERRUPTED
    assert logic.cleaned_up.is_set()


def test_unknown_default_fails_the_start_with_unknown_logic() -> None:
    manager = LowLevelBehaviorManager(default="missing")
    with pytest.raises(UnknownLogic, match="'missing'"):
        manager.__enter__()
    assert not any(t.name == "beehave-lowlevel" for t in threading.enumerate())


def test_a_failing_blackboard_callback_is_reported_as_an_event() -> None:
    manager = LowLevelBehaviorManager()
    events = events_of(manager)

    def bad(change: Any) -> None:
        raise ValueError("subscriber bug")

    with manager:
        sub = manager.blackboard.subscribe("a", bad)
        manager.blackboard.set("a", 1)
        assert wait_until(lambda: sub.closed)
    failed = [e for e in events if e.subject == "blackboard:a"]
    assert len(failed) == 1 and isinstance(failed[0].error, ValueError)
    assert failed[0].status == "FAILED"


def test_logic_subscriptions_and_watchers_are_closed_when_it_ends(
        ll: LowLevelBehaviorManager) -> None:
    class Watching(Logic):
        async def run(self) -> None:
            self.blackboard.subscribe("x", lambda c: None)
            async for _ in self.blackboard.watch("y"):
                pass

    ll.register("watching", Watching)
    with ll:
        ll.switch("watching")
        assert wait_until(lambda: len(ll.blackboard.subscriptions) == 2)
        ll.switch("forever")
        assert ll.blackboard.subscriptions == ()


def test_logic_writes_as_logic_path() -> None:
    class Writer(Logic):
        async def run(self) -> None:
            self.blackboard.set("wanted/color", "blue")
            await asyncio.Event().wait()

    manager = LowLevelBehaviorManager(default="writer")
    manager.register("writer", Writer)
    with manager:
        assert wait_until(lambda: manager.blackboard.get("wanted/color") == "blue")
        entry = manager.blackboard.entry("wanted/color")
    assert entry is not None and entry.writer == "logic:writer"


def test_already_started_logic_cannot_be_started_again() -> None:
    class Twice(Logic):
        async def run(self) -> str:
            child = self.start_logic(Forever())
            try:
                self.start_logic(child)
            except AlreadyStarted as err:
                return str(err)
            return ""

    manager = LowLevelBehaviorManager(default="twice")
    manager.register("twice", Twice)
    with manager:
        assert wait_until(lambda: manager.history)
        result = manager.history[-1].result
    assert "already started" in result


# -- every change of the running logic is announced (issue 9, item 14) -------------------------

def test_a_fallback_announces_the_default_as_a_completed_switch_and_current_agrees(
        ll: LowLevelBehaviorManager) -> None:
    seen: list[tuple[EventKind, str, str | None]] = []

    def record(event: Event) -> None:
        if event.kind in (EventKind.SWITCH_COMPLETED, EventKind.FALLBACK):
            # what a ROS bridge would read when it follows the events
            seen.append((event.kind, event.subject, ll.current))

    ll.subscribe(record)
    with ll:
        ll.switch("crashing")
        assert wait_until(lambda: (EventKind.SWITCH_COMPLETED, "idle", "idle") in seen[2:])
    completed = [s for s in seen if s[0] is EventKind.SWITCH_COMPLETED]
    # the start of the default, the switch, the fallback: each names what runs now
    assert [s[1] for s in completed] == ["idle", "crashing", "idle"]
    assert all(subject == current for _, subject, current in completed)
    assert seen[-2][:2] == (EventKind.FALLBACK, "crashing")


def test_a_fallback_switch_event_says_from_where_and_why(ll: LowLevelBehaviorManager) -> None:
    events = events_of(ll)
    with ll:
        ll.switch("crashing")
        assert wait_until(lambda: any(e.kind is EventKind.SWITCH_COMPLETED
                                      and e.detail.get("from") == "crashing" for e in events))
    last = [e for e in events if e.kind is EventKind.SWITCH_COMPLETED][-1]
    assert last.subject == "idle" and last.detail["fallback"] is True


# -- non-finite numbers (issue 9, item 4) ------------------------------------------------------

@pytest.mark.parametrize("option", ["stop_timeout_s", "hal_backoff_initial_s",
                                    "hal_backoff_max_s", "loop_lag_warn_s", "hal_handover_s"])
@pytest.mark.parametrize("value", [float("inf"), float("nan"), -1.0])
def test_durations_must_be_finite_and_positive(option: str, value: float) -> None:
    with pytest.raises(ConfigError, match=rf"{option}.*{value!r}"):
        LowLevelBehaviorManager(**{option: value})


def test_a_call_timeout_must_be_finite(ll: LowLevelBehaviorManager) -> None:
    with ll:
        with pytest.raises(ConfigError, match="timeout_s"):
            ll.call(asyncio.sleep(0), timeout_s=float("nan"))


def test_a_switch_whose_caller_stops_waiting_still_completes(
        ll: LowLevelBehaviorManager) -> None:
    async def impatient() -> bool:
        task = asyncio.ensure_future(ll.switch_async("forever"))
        await asyncio.sleep(0.02)   # the switch now waits for "stubborn" to end
        task.cancel()
        await asyncio.wait({task})
        return task.cancelled()

    with ll:
        ll.switch("stubborn")
        assert ll.call(impatient(), timeout_s=WAIT_S) is True
        # the old logic is gone either way; the robot is not left without one
        assert ll.current == "forever"


def test_every_switch_event_says_whether_it_is_a_fallback_and_fallback_names_the_next(
        ll: LowLevelBehaviorManager) -> None:
    """docs/lowlevel.md promises "fallback" on every change; FALLBACK names the next logic
    under "to", as the high level does, so one log line (events.describe) reads both."""
    events = events_of(ll)
    with ll:
        ll.switch("forever")
        ll.switch("crashing")
        assert wait_until(lambda: any(e.kind is EventKind.FALLBACK for e in events))
        assert wait_until(lambda: ll.current == "idle")
    switches = [e for e in events if e.kind in (EventKind.SWITCH_REQUESTED,
                                                EventKind.SWITCH_COMPLETED)]
    assert all(isinstance(e.detail.get("fallback"), bool) for e in switches)
    assert [e.detail["fallback"] for e in switches if e.subject == "forever"] == [False, False]
    fallback = next(e for e in events if e.kind is EventKind.FALLBACK)
    assert fallback.detail["to"] == "idle"
    assert "starting 'idle'" in describe(fallback)


def test_concurrent_switches_report_where_each_one_really_came_from(
        ll: LowLevelBehaviorManager) -> None:
    """Each SWITCH_COMPLETED names the logic it replaced: read under the switch lock, so
    the completed switches form one chain idle → … → the last one."""
    events = events_of(ll)
    with ll:
        names = ["forever", "parent", "stubborn", "forever", "parent"] * 2
        threads = [threading.Thread(target=ll.switch, args=(n,)) for n in names]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(WAIT_S)
    completed = [e for e in events if e.kind is EventKind.SWITCH_COMPLETED]
    assert completed[0].subject == "idle" and completed[0].detail["from"] is None
    for before, after in zip(completed, completed[1:], strict=False):
        assert after.detail["from"] == before.subject, (before, after)
