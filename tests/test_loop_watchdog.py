"""The event-loop watchdog: a logic or HAL that blocks the loop is named, calls from other
threads and shutdown stay bounded, and the HALs still get their safe states (issue 9,
item 11)."""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from beehave.errors import ConfigError, LoopBlocked, ManagerShutdown
from beehave.events import Event, EventKind
from beehave.hal import HAL
from beehave.logic import Logic
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.testing import WALL_TIMEOUT_S, beehave_threads, wait_until
from hal.debug import DebugHAL, DebugRobot

WAIT_S = WALL_TIMEOUT_S  # the suite's one bound (beehave.testing): a safety net only


class Blocker(Logic):
    """Takes the debug HAL, then blocks the loop (a blocking call instead of an await)
    until the test lets go."""

    def __init__(self, gate: threading.Event, blocking: threading.Event,
                 use_hal: bool = False) -> None:
        self.gate = gate
        self.blocking = blocking
        self.use_hal = use_hal

    async def run(self) -> None:
        if self.use_hal:
            await self.hal("debug")
        self.blocking.set()
        self.gate.wait(WAIT_S * 4)  # the bug: blocks the whole loop
        await asyncio.Event().wait()


class Forever(Logic):
    async def run(self) -> None:
        await asyncio.Event().wait()


class Sleeper(Logic):
    """Blocks the loop, again until ``enough`` is set: one block may come while the whole
    process is starved, and then it is rightly blamed on nobody."""

    enough = threading.Event()

    async def run(self) -> None:
        while not Sleeper.enough.is_set():
            time.sleep(0.3)  # the classic mistake
            await asyncio.sleep(0.2)
        await asyncio.Event().wait()


@pytest.fixture
def gate() -> Iterator[threading.Event]:
    """Opened at the end of every test, so a blocked loop always ends."""
    event = threading.Event()
    before = set(beehave_threads())
    yield event
    event.set()
    assert wait_until(lambda: set(beehave_threads()) <= before, WAIT_S), \
        f"threads left: {set(beehave_threads()) - before}"


def blocked_manager(gate: threading.Event, blocking: threading.Event,
                    robot: DebugRobot | None = None) -> LowLevelBehaviorManager:
    """A manager whose default logic blocks the loop until ``gate`` opens (taking the
    debug HAL of ``robot`` first, if one is given); declared blocked after 0.2 s."""
    ll = LowLevelBehaviorManager(default="blocker", stop_timeout_s=0.2, loop_lag_warn_s=0.05)
    ll.register("blocker", Blocker, gate=gate, blocking=blocking, use_hal=robot is not None)
    if robot is not None:
        ll.hals.register(DebugHAL, robot=robot)
    return ll


def events_of(ll: LowLevelBehaviorManager) -> list[Event]:
    got: list[Event] = []
    ll.subscribe(got.append)
    return got


def test_a_logic_that_blocks_the_loop_is_named_in_a_warning_and_an_event(
        caplog: pytest.LogCaptureFixture) -> None:
    ll = LowLevelBehaviorManager(default="sleeper", loop_lag_warn_s=0.05)
    ll.register("sleeper", Sleeper)
    events = events_of(ll)

    def blamed() -> list[Event]:
        # (A loaded machine may report a starved process, which blames nobody, or the loop
        # held in beehave's own code, which says so: seen beside busy loops.)
        return [e for e in events if e.kind is EventKind.LOOP_BLOCKED
                and not e.detail["starved"] and not e.detail.get("internal")]

    Sleeper.enough.clear()
    with caplog.at_level(logging.WARNING, logger="beehave.watchdog"), ll:
        assert wait_until(lambda: any(e.detail["ended"] for e in blamed()), WAIT_S)
        Sleeper.enough.set()
    blocked = blamed()
    assert [e.detail["ended"] for e in blocked[:2]] == [False, True]
    assert {e.subject for e in blocked} == {"logic:sleeper"}
    assert all(e.detail["culprit"] == "logic 'sleeper'" for e in blocked)
    where = blocked[0].detail["where"]
    assert "test_loop_watchdog.py" in where and where.endswith("in run")
    assert {e.subject for e in events if e.kind is EventKind.LOOP_BLOCKED} <= \
        {"logic:sleeper", "process"}  # nobody else is ever blamed
    warning = next(r.getMessage() for r in caplog.records
                   if "blocked" in r.getMessage() and "logic 'sleeper'" in r.getMessage())
    assert "logic 'sleeper'" in warning and "await asyncio.sleep" in warning
    assert "asyncio.to_thread" in warning


def test_a_hal_that_blocks_the_loop_is_named() -> None:
    class Sleepy(HAL):
        name = "sleepy"

        async def run(self) -> None:
            while True:
                time.sleep(0.3)  # a blocking driver read
                await asyncio.sleep(0.05)

    class UsesSleepy(Logic):
        async def run(self) -> None:
            await self.hal("sleepy")
            await asyncio.Event().wait()

    ll = LowLevelBehaviorManager(default="uses", loop_lag_warn_s=0.05)
    ll.register("uses", UsesSleepy)
    ll.hals.register(Sleepy)
    events = events_of(ll)

    def blocked() -> list[Any]:
        return [e for e in events if e.kind is EventKind.LOOP_BLOCKED]

    # On a loaded machine the watchdog itself may wake late during one block, and then
    # rightly blames no one (the process was starved); a driver that keeps blocking is
    # named at a block where it woke on time. Nobody else is ever blamed.
    with ll:
        assert wait_until(lambda: any(e.subject == "hal:sleepy" for e in blocked()))
    named = next(e for e in blocked() if e.subject == "hal:sleepy")
    assert named.detail["culprit"] == "HAL 'sleepy'"
    assert {e.subject for e in blocked()} <= {"hal:sleepy", "process"}, blocked()


def test_a_blocking_blackboard_callback_is_found_by_its_line() -> None:
    ll = LowLevelBehaviorManager(loop_lag_warn_s=0.05)
    events = events_of(ll)

    def slow_callback(change: Any) -> None:
        time.sleep(0.3)

    def blamed() -> list[Any]:  # starvation and beehave's own steps blame no user code
        return [e for e in events if e.kind is EventKind.LOOP_BLOCKED
                and not e.detail["starved"] and not e.detail.get("internal")]

    with ll:
        ll.blackboard.subscribe("button", slow_callback)
        ll.blackboard.set("button", True)
        assert wait_until(lambda: bool(blamed()))
    # (A loaded machine may first report a starved process, or the loop held mid-step in
    # beehave's own code, which says so and blames nobody's line: seen beside busy loops.)
    first = blamed()[0]
    assert first.subject == "callback", first
    assert first.detail["where"].endswith("in slow_callback")


def test_switch_from_another_thread_fails_with_loop_blocked_instead_of_hanging(
        gate: threading.Event) -> None:
    blocking = threading.Event()
    ll = blocked_manager(gate, blocking)
    ll.register("forever", Forever)
    with ll:
        assert blocking.wait(WAIT_S)
        with pytest.raises(LoopBlocked) as info:
            ll.switch("forever")
        assert info.value.culprit == "logic 'blocker'"
        assert "test_loop_watchdog.py" in info.value.where
        assert info.value.blocked_s >= 0.2                 # it waited stop_timeout_s first
        assert "logic 'blocker'" in str(info.value) and "asyncio.to_thread" in str(info.value)
        with pytest.raises(LoopBlocked):                   # still blocked: fails too
            ll.call(asyncio.sleep(0))
        snap = ll.snapshot()                               # introspection still works
        assert snap["loop_blocked"]["culprit"] == "logic 'blocker'"
        gate.set()
        assert wait_until(lambda: ll.snapshot()["loop_blocked"] is None)
        # the loop runs again: the failed switch was withdrawn, the blocker still runs
        assert ll.call(asyncio.sleep(0, "alive"), timeout_s=WAIT_S) == "alive"
        assert ll.current == "blocker"
        assert ll.snapshot()["loop_blocked"] is None
        assert ll.switch("forever") is not None and ll.current == "forever"


def test_leaving_the_with_block_while_the_loop_is_blocked_forces_safe_states_and_raises(
        gate: threading.Event) -> None:
    blocking = threading.Event()
    robot = DebugRobot()
    ll = blocked_manager(gate, blocking, robot)
    with pytest.raises(LoopBlocked) as info:
        with ll:
            assert blocking.wait(WAIT_S)
            hal = ll.hals.loaded["debug"]
            assert isinstance(hal, DebugHAL)
            hal.set_leds("green")
    message = str(info.value)
    assert "logic 'blocker'" in message and "'debug'" in message
    assert "safe states" in message.lower()
    # a defined end: stopped, the safe state ran (from the shutdown thread), nothing accepted
    assert robot.led_color == "off" and hal.safe_states == 1
    assert not ll.running and ll.snapshot()["phase"] == "stopped"
    with pytest.raises(ManagerShutdown):
        ll.switch("blocker")
    ll.shutdown()  # said once; a second shutdown does not raise again
    # Should the loop ever run again, its own teardown finishes without a second safe state.
    gate.set()
    assert wait_until(lambda: ll.hals.loaded == {} and ll._thread is not None
                      and not ll._thread.is_alive(), WAIT_S)
    assert hal.safe_states == 1 and robot.led_color == "off"


@pytest.mark.parametrize("reentry", ["snapshot", "switch", "call", "shutdown"])
def test_a_loop_blocked_subscriber_that_calls_back_into_the_manager_keeps_calls_bounded(
        gate: threading.Event, reentry: str) -> None:
    """The LOOP_BLOCKED callback is where a user asks "what runs?" or gives up: calling back
    into the manager from there must neither hang itself nor the watchdog, which is what
    bounds every other thread's calls."""
    blocking = threading.Event()
    ll = blocked_manager(gate, blocking)
    ll.register("forever", Forever)
    in_callback: list[str] = []
    callback_done = threading.Event()

    def on_event(event: Event) -> None:
        if event.kind is not EventKind.LOOP_BLOCKED or event.detail["ended"] or in_callback:
            return
        in_callback.append(threading.current_thread().name)
        try:
            if reentry == "snapshot":
                ll.snapshot()
            elif reentry == "switch":
                ll.switch("forever")
            elif reentry == "call":
                ll.call(asyncio.sleep(0))
            else:
                ll.shutdown()
        except (LoopBlocked, ManagerShutdown):
            pass
        finally:
            callback_done.set()

    ll.subscribe(on_event)
    outcome: list[BaseException | None] = []

    def main() -> None:
        try:
            with ll:
                assert blocking.wait(WAIT_S)
                assert callback_done.wait(WAIT_S)
                try:
                    ll.switch("forever")
                except (LoopBlocked, ManagerShutdown) as exc:
                    outcome.append(exc)
        except LoopBlocked as exc:
            outcome.append(exc)

    thread = threading.Thread(target=main, daemon=True)
    thread.start()
    # switch and shutdown are each bounded by about stop_timeout_s; a hang is the bug.
    thread.join(WAIT_S)
    hung = thread.is_alive()
    gate.set()
    thread.join(WAIT_S)
    assert not hung, f"a LOOP_BLOCKED callback calling {reentry}() hangs the manager"
    assert in_callback and in_callback[0] != "beehave-lowlevel-watchdog"
    assert outcome and all(isinstance(o, (LoopBlocked, ManagerShutdown)) for o in outcome)


def test_durations_beyond_a_day_are_refused_with_the_name_and_the_cap() -> None:
    for key in ("loop_lag_warn_s", "stop_timeout_s", "hal_handover_s"):
        with pytest.raises(ConfigError) as info:
            LowLevelBehaviorManager(**{key: 1e10})
        assert key in str(info.value) and "86400" in str(info.value)
    # the cap itself is allowed
    LowLevelBehaviorManager(loop_lag_warn_s=86400.0).shutdown()


def test_two_shutdowns_of_a_blocked_loop_both_report_the_forced_safe_states(
        gate: threading.Event) -> None:
    blocking = threading.Event()
    robot = DebugRobot()
    ll = blocked_manager(gate, blocking, robot)
    ll.__enter__()
    assert blocking.wait(WAIT_S)
    errors: list[BaseException] = []

    def stop() -> None:
        try:
            ll.shutdown()
        except LoopBlocked as exc:
            errors.append(exc)

    threads = [threading.Thread(target=stop) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(WAIT_S)
    assert len(errors) == 2 and str(errors[0]) == str(errors[1])
    assert "'debug'" in str(errors[0]) and "none loaded" not in str(errors[0])
    hal = ll.hals.loaded["debug"]
    assert isinstance(hal, DebugHAL) and hal.safe_states == 1


def test_a_hal_whose_unload_blocks_the_loop_still_gets_its_forced_safe_state(
        gate: threading.Event) -> None:
    """The unload itself is what blocks (a blocking driver close on cancellation): the HAL
    is no longer "loaded", but its safe state is still owed and forced."""
    calls: list[str] = []

    class Motor(HAL):
        name = "motor"

        async def run(self) -> None:
            try:
                await asyncio.Event().wait()
            finally:
                gate.wait(WAIT_S * 4)  # the bug: a blocking close in the loop

        def safe_state(self) -> None:
            calls.append(threading.current_thread().name)

    class UsesMotor(Logic):
        async def run(self) -> None:
            await self.hal("motor")
            await asyncio.Event().wait()

    ll = LowLevelBehaviorManager(default="m", stop_timeout_s=0.2, loop_lag_warn_s=0.05)
    ll.register("m", UsesMotor)
    ll.hals.register(Motor)
    stuck: list[str] = []
    ll.subscribe(lambda e: e.kind is EventKind.STUCK and stuck.append(e.subject))
    with pytest.raises(LoopBlocked) as info:
        with ll:
            assert wait_until(lambda: "motor" in ll.hals.loaded, WAIT_S)
    assert "'motor'" in str(info.value) and "none loaded" not in str(info.value)
    assert calls == ["beehave-lowlevel-safe-states"]
    gate.set()
    assert wait_until(lambda: ll._thread is not None and not ll._thread.is_alive(), WAIT_S)
    assert len(calls) == 1                # the loop's own unload does not repeat it
    assert "m" not in stuck               # the logic obeyed at once; the HAL blocked


def test_a_loop_that_runs_again_during_the_escalation_unloads_after_the_forced_safe_state(
        gate: threading.Event) -> None:
    """The escalation forces safe_state from a helper thread; should the loop run again
    meanwhile, its own unload must not call on_unload (closing the device) while that
    safe_state still uses it."""
    marks: list[str] = []
    blocking = threading.Event()
    finish_safe_state = threading.Event()

    class Device(HAL):
        name = "device"

        def safe_state(self) -> None:
            marks.append("safe_state begins")
            # Longer than the escalation waits for it (stop_timeout_s): until the test saw
            # that the escalation gave up.
            finish_safe_state.wait(WAIT_S)
            marks.append("safe_state ends")

        def on_unload(self) -> None:
            marks.append("on_unload")

    class BlocksWithDevice(Logic):
        async def run(self) -> None:
            await self.hal("device")
            blocking.set()
            gate.wait(WAIT_S * 4)
            await asyncio.Event().wait()

    ll = LowLevelBehaviorManager(default="b", stop_timeout_s=0.2, loop_lag_warn_s=0.05)
    ll.register("b", BlocksWithDevice)
    ll.hals.register(Device)
    with pytest.raises(LoopBlocked):
        with ll:
            assert blocking.wait(WAIT_S)
    assert marks == ["safe_state begins"]  # the escalation gave up waiting for it
    gate.set()                              # the loop runs again and tears down
    finish_safe_state.set()
    assert wait_until(lambda: ll._thread is not None and not ll._thread.is_alive(), WAIT_S)
    assert wait_until(lambda: len(marks) == 3, WAIT_S)
    assert marks == ["safe_state begins", "safe_state ends", "on_unload"]


@pytest.mark.parametrize("answered", [True, False])
def test_a_block_declared_after_the_loop_answered_fails_nobody(answered: bool) -> None:
    """A watchdog thread starved between its last wait and its declaration came after the
    loop had answered: it failed, with the old block's LoopBlocked, a call that began once
    the loop ran again (seen beside busy loops). A declaration now looks first."""
    import concurrent.futures

    from beehave.events import EventBus
    from beehave.watchdog import Culprit, LoopWatchdog

    loop = asyncio.new_event_loop()
    try:
        dog = LoopWatchdog(loop, threading.get_ident(), EventBus(), warn_s=0.05, block_s=0.1)
        if answered:
            dog._answered.set()  # the loop answered: the block is over
        call: concurrent.futures.Future[None] = concurrent.futures.Future()
        dog.watch(call)  # a caller that began after that
        dog._declare_blocked(Culprit("logic:hog", "logic 'hog'", "x.py:1 in run"), 0.4)
        if answered:
            assert dog.blocked() is None and not call.done()
        else:  # still blocked: declared, and the caller fails with it
            assert isinstance(dog.blocked(), LoopBlocked)
            assert isinstance(call.exception(0), LoopBlocked)
    finally:
        loop.close()
