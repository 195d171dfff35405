"""HighLevelBehaviorManager contract: switching, fallback, bad input, events, shutdown."""

from __future__ import annotations

import gc
import json
import threading
import time
import weakref
from typing import Any

import pytest

from beehave import (
    Action,
    Behavior,
    HighLevelBehaviorManager,
    InvalidParameters,
    ManagerShutdown,
    Status,
    SwitchSuperseded,
    UnknownBehavior,
)
from beehave.errors import ConfigError, NotASubclass
from beehave.events import Event, EventKind
from beehave.testing import (
    WALL_TIMEOUT_S,
    ScriptedAction,
    beehave_threads,
    wait_until,
    wall_timeout,
)


class Busy(Behavior):
    """Drives and beeps until interrupted."""

    def __init__(self, *, stubborn: bool = False, ready: threading.Event | None = None) -> None:
        self.stubborn = stubborn
        self.ready = ready
        self.actions: list[ScriptedAction] = []

    def run(self) -> None:
        ignore = float("inf") if self.stubborn else 0.0
        self.actions.append(self.start_action(
            ScriptedAction("driving", duration_s=30, ignore_interrupt_s=ignore)))
        self.actions.append(self.start_action(ScriptedAction("sound", duration_s=30)))
        if self.ready:
            self.ready.set()
        while self.sleep(10):
            pass


class Crashes(Behavior):
    def run(self) -> None:
        raise RuntimeError("planner exploded")


class Finishes(Behavior):
    def run(self) -> str:
        return "delivered"


class NeedsSpeed(Behavior):
    def __init__(self, speed_mps: float) -> None:
        if speed_mps <= 0:
            raise ValueError("speed_mps must be positive")
        self.speed_mps = speed_mps

    def run(self) -> None:
        while self.sleep(10):
            pass


def switch_ready(hl: HighLevelBehaviorManager, name: str, **params: Any) -> Busy:
    ready = threading.Event()
    top = hl.switch(name, ready=ready, **params)
    assert ready.wait(WALL_TIMEOUT_S)
    return top  # type: ignore[return-value]


def test_starts_in_idle(hl: HighLevelBehaviorManager) -> None:
    assert hl.current == "idle"
    assert hl.snapshot()["top"]["class"] == "Idle"


def test_switch_returns_after_old_ended_and_new_runs(hl: HighLevelBehaviorManager) -> None:
    hl.register("busy", Busy)
    old = switch_ready(hl, "busy")
    new = hl.switch("idle")
    assert old.status is Status.INTERRUPTED and not old.alive
    assert all(a.status is Status.INTERRUPTED and a.safe_state_calls == 1 for a in old.actions)
    assert new.status is Status.RUNNING and hl.current == "idle"
    assert hl.snapshot()["locks"] == {}


def test_a_switch_leaves_no_reference_cycles(hl: HighLevelBehaviorManager) -> None:
    """An ended behaviour and its actions are freed as soon as nobody holds them, without
    the garbage collector: cycles would wait for it, and its pauses land in later switches."""
    hl.register("busy", Busy)
    gc.collect()
    gc.disable()
    try:
        old = switch_ready(hl, "busy")
        refs = [weakref.ref(old)] + [weakref.ref(a) for a in old.actions]
        hl.switch("idle")
        assert wait_until(lambda: not any(item.alive for r in refs if (item := r()) is not None))
        del old
        assert wait_until(lambda: all(r() is None for r in refs)), \
            f"still alive: {[r() for r in refs if r() is not None]}"
    finally:
        gc.enable()


def test_a_manager_whose_breakpoints_nobody_closed_is_freed_once_dropped() -> None:
    """The registry of breakpoints per manager must not keep a manager alive: a script
    that forgets ``Breakpoints.close()`` would otherwise keep every manager it made."""
    from beehave.breakpoints import Breakpoints, of

    with HighLevelBehaviorManager() as hl:
        points = Breakpoints(hl)
        assert of(hl) is points
    ref = weakref.ref(hl)
    del hl, points
    gc.collect()
    assert ref() is None, "the manager outlived every reference to it"


class Drives(Action):
    """Counts its runs; drives (sleeps) until interrupted."""

    action_type = "breakpoint_driving"
    runs = 0

    def run(self) -> None:
        type(self).runs += 1
        self.sleep(30)


class StartsDrives(Behavior):
    def run(self) -> None:
        self.start_action(Drives()).wait()


def test_an_action_type_breakpoint_stops_the_action_before_its_run_begins(
        hl: HighLevelBehaviorManager, events: list[Event]) -> None:
    """The breakpoint's pause is carried out in a manager thread; with its threads warm
    (any robot after its first switch) the action's run() — the robot moving — began
    before that pause landed. It must wait for the resume instead."""
    from beehave.breakpoints import Breakpoints

    hl.stop_timeout_s = 2.0  # a loaded host must not give up on the pause
    hl.register("drives", StartsDrives)
    points = Breakpoints(hl)
    try:
        points.add("action_type", "breakpoint_driving")
        for round_ in range(3):  # the later rounds find the manager's threads warm
            Drives.runs = 0
            events.clear()
            top = hl.switch("drives")
            assert wait_until(lambda: any(e.kind is EventKind.PAUSED for e in events))
            assert Drives.runs == 0, f"round {round_}: run() began before the breakpoint"
            (action,) = top.children
            assert action.status is Status.RUNNING
            assert points.resume()
            assert wait_until(lambda: Drives.runs == 1)
            hl.switch("idle")
    finally:
        points.close()


def test_a_breakpoint_resumed_by_someone_else_is_not_blamed_for_a_later_pause(
        hl: HighLevelBehaviorManager, events: list[Event]) -> None:
    """``hit`` says where a breakpoint stopped the robot; once the pause button (not
    ``Breakpoints.resume``) ended that pause, a later pause of the button's is no hit."""
    from beehave.breakpoints import Breakpoints

    hl.stop_timeout_s = 2.0  # a loaded host must not give up on the pause
    hl.register("drives", StartsDrives)
    points = Breakpoints(hl)
    try:
        points.add("action_type", "breakpoint_driving")
        Drives.runs = 0
        hl.switch("drives")
        assert wait_until(lambda: any(e.kind is EventKind.PAUSED for e in events))
        hit = points.hit
        assert hit is not None and hit["target"] == "breakpoint_driving", hit
        points.clear()
        assert hl.resume()  # the pause button, not points.resume()
        assert wait_until(lambda: Drives.runs == 1)
        assert hl.pause()
        assert points.hit is None, points.hit
        assert points.state()["paused"] is True
    finally:
        points.close()


def test_switch_params_override_registered_ones(hl: HighLevelBehaviorManager) -> None:
    hl.register("speedy", NeedsSpeed, speed_mps=0.5)
    assert hl.switch("speedy").speed_mps == 0.5  # type: ignore[attr-defined]
    assert hl.switch("speedy", speed_mps=1.5).speed_mps == 1.5  # type: ignore[attr-defined]


def test_unknown_name_lists_registered_names(hl: HighLevelBehaviorManager) -> None:
    hl.register("busy", Busy)
    with pytest.raises(UnknownBehavior) as info:
        hl.switch("bussy")
    assert "'bussy'" in str(info.value) and "'busy', 'idle'" in str(info.value)
    assert info.value.choices == ["busy", "idle"]
    assert hl.current == "idle"


@pytest.mark.parametrize("params, match", [
    ({"sped_mps": 1.0}, "accepts: speed_mps"),     # misspelt: the signature rejects it
    ({}, "missing a required argument"),
    ({"speed_mps": -1.0}, "must be positive"),     # the constructor rejects it
])
def test_rejected_parameters_keep_the_old_behaviour_running(
        hl: HighLevelBehaviorManager, params: dict[str, Any], match: str) -> None:
    hl.register("busy", Busy)
    hl.register("speedy", NeedsSpeed)
    old = switch_ready(hl, "busy")
    with pytest.raises(InvalidParameters, match=match):
        hl.switch("speedy", **params)
    assert hl.current == "busy" and old.status is Status.RUNNING
    assert all(a.status is Status.RUNNING for a in old.actions)


def test_register_rejects_bad_input(hl: HighLevelBehaviorManager) -> None:
    with pytest.raises(NotASubclass, match="Behavior subclass"):
        hl.register("x", ScriptedAction)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="built in"):
        hl.register("idle", Busy)
    with pytest.raises(InvalidParameters, match="accepts: stubborn, ready"):
        hl.register("busy", Busy, speed=3)


def test_stuck_action_does_not_block_the_switch(hl: HighLevelBehaviorManager) -> None:
    hl.register("busy", Busy)
    old = switch_ready(hl, "busy", stubborn=True)
    stubborn, sound = old.actions
    t0 = time.monotonic()
    hl.switch("idle")
    elapsed = time.monotonic() - t0
    # It returned while the stubborn thread still runs (until its release below): the
    # switch waited stop_timeout_s for it, not for the thread. (The bound only catches a
    # switch that waited for something else; how fast it is goes in the benchmarks.)
    assert stubborn.alive
    assert elapsed < hl.stop_timeout_s + wall_timeout(0.05)
    assert stubborn.status is Status.STUCK and stubborn.safe_state_calls == 1
    assert sound.status is Status.INTERRUPTED and sound.safe_state_calls == 1
    snap = hl.snapshot()
    assert snap["stuck"] == ["busy/ScriptedAction"]
    assert snap["locks"]["driving"]["status"] == "STUCK"
    # The next behaviour cannot drive until the stuck thread is really gone: its
    # start_action raises ActionTypeBusy, it fails and the manager falls back to idle.
    blocked = hl.switch("busy")
    assert blocked.wait(WALL_TIMEOUT_S) and blocked.status is Status.FAILED
    assert "driving" in str(blocked.error) and "STUCK" in str(blocked.error)
    assert wait_until(lambda: hl.current == "idle")
    stubborn.release.set()
    assert wait_until(lambda: not stubborn.alive)
    assert stubborn.safe_state_calls == 1
    assert "driving" not in hl.snapshot()["locks"] and hl.snapshot()["stuck"] == []
    again = switch_ready(hl, "busy")
    assert again.actions[0].status is Status.RUNNING


def test_a_stuck_action_that_returns_late_ends_without_an_error(
        hl: HighLevelBehaviorManager, caplog: pytest.LogCaptureFixture) -> None:
    # Its forced safe state returned first, so its own thread ends its life when run()
    # returns: that thread used to go on to tell the (by then weakly held) parent a second
    # time and die with an AttributeError logged by the worker pool.
    hl.register("busy", Busy)
    old = switch_ready(hl, "busy", stubborn=True)
    stubborn = old.actions[0]
    hl.switch("idle")
    assert stubborn.status is Status.STUCK and stubborn.alive
    with caplog.at_level("ERROR"):
        stubborn.release.set()
        assert wait_until(lambda: not stubborn.alive)
        assert wait_until(lambda: "driving" not in hl.snapshot()["locks"])
        hl.switch("busy")  # the pool thread is reused: nothing raised in the one before
        hl.switch("idle")
    assert [r.getMessage() for r in caplog.records if r.levelname == "ERROR"] == []


def test_failing_top_level_behaviour_falls_back_to_idle(hl: HighLevelBehaviorManager,
                                                        events) -> None:  # type: ignore[no-untyped-def]
    hl.register("crashes", Crashes)
    top = hl.switch("crashes")
    assert top.wait(WALL_TIMEOUT_S)
    assert wait_until(lambda: hl.current == "idle")
    assert top.status is Status.FAILED and "planner exploded" in str(top.error)
    record = hl.history[-1]
    assert record["name"] == "crashes" and record["status"] == "FAILED"
    assert "planner exploded" in record["error"]
    fallback = [e for e in events if e.kind.value == "fallback"]
    assert fallback and fallback[0].subject == "crashes" and fallback[0].error is top.error


def test_finished_top_level_behaviour_leaves_idle_running(hl: HighLevelBehaviorManager) -> None:
    hl.register("finishes", Finishes)
    top = hl.switch("finishes")
    assert top.wait(WALL_TIMEOUT_S) and top.result == "delivered"
    assert wait_until(lambda: hl.current == "idle")


def test_concurrent_switches_latest_wins(hl: HighLevelBehaviorManager) -> None:
    for i in range(8):
        hl.register(f"b{i}", NeedsSpeed, speed_mps=1.0)
    outcomes: dict[int, Any] = {}
    barrier = threading.Barrier(8)

    def request(i: int) -> None:
        barrier.wait()
        try:
            outcomes[i] = hl.switch(f"b{i}")
        except SwitchSuperseded as exc:
            outcomes[i] = exc

    threads = [threading.Thread(target=request, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(5)
    assert len(outcomes) == 8
    winners = [i for i, o in outcomes.items() if not isinstance(o, SwitchSuperseded)]
    assert winners, "at least the last request succeeds"
    running = [o for o in outcomes.values()
               if isinstance(o, Behavior) and o.status is Status.RUNNING]
    assert len(running) == 1 and running[0].name == hl.current
    superseded = [o for o in outcomes.values() if isinstance(o, SwitchSuperseded)]
    assert all("superseded" in str(s) for s in superseded)


def test_switch_from_inside_a_behaviour_is_queued(hl: HighLevelBehaviorManager) -> None:
    class Handover(Behavior):
        def run(self) -> None:
            self.next = hl.switch("speedy")
            while self.sleep(10):
                pass

    hl.register("speedy", NeedsSpeed, speed_mps=1.0)
    hl.register("handover", Handover)
    first = hl.switch("handover")
    assert wait_until(lambda: hl.current == "speedy")
    assert first.status is Status.INTERRUPTED


def test_events_cover_the_lifecycle(hl: HighLevelBehaviorManager, events) -> None:  # type: ignore[no-untyped-def]
    hl.register("busy", Busy)
    switch_ready(hl, "busy")
    with pytest.raises(UnknownBehavior):
        hl.switch("nope")
    hl.switch("idle")
    kinds = [(e.kind.value, e.subject) for e in events]
    for expected in [("switch_requested", "busy"), ("started", "busy"),
                     ("started", "busy/ScriptedAction"), ("switch_completed", "busy"),
                     ("switch_rejected", "nope"), ("ended", "busy/ScriptedAction"),
                     ("ended", "busy"), ("switch_completed", "idle")]:
        assert expected in kinds, expected
    ended = [e for e in events if e.kind.value == "ended" and e.subject == "busy"]
    assert ended[0].status == "INTERRUPTED"
    json.dumps([e.as_dict() for e in events])


def test_a_raising_event_subscriber_breaks_nothing(hl: HighLevelBehaviorManager,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    def bad(_: Any) -> None:
        raise RuntimeError("observer bug")

    hl.subscribe(bad)
    hl.register("busy", Busy)
    switch_ready(hl, "busy")
    hl.switch("idle")
    assert hl.current == "idle"
    assert "observer bug" in caplog.text


def test_shutdown_leaves_no_thread_and_refuses_more() -> None:
    before = set(beehave_threads())
    with HighLevelBehaviorManager(stop_timeout_s=0.3) as hl:
        hl.register("busy", Busy)
        top = switch_ready(hl, "busy")
        assert len(beehave_threads()) > len(before)
    assert top.status is Status.INTERRUPTED
    assert [t for t in beehave_threads() if t not in before] == []
    with pytest.raises(ManagerShutdown):
        hl.switch("idle")
    with pytest.raises(ManagerShutdown):
        hl.start()


def test_unknown_default_is_reported_at_start() -> None:
    manager = HighLevelBehaviorManager(default="patrol")
    with pytest.raises(UnknownBehavior, match="'patrol'; registered: 'idle'"):
        manager.start()
    manager.shutdown()


def test_bad_stop_timeout() -> None:
    with pytest.raises(ConfigError, match="stop_timeout_s"):
        HighLevelBehaviorManager(stop_timeout_s=0)
