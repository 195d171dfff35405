"""HALManager contract: discovery, sharing, reference counting, crash and restart."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest

from beehave.blackboard import Blackboard
from beehave.clock import VirtualClock
from beehave.errors import HALError, InvalidParameters, UnknownHAL
from beehave.events import Event, EventBus, EventKind
from beehave.hal import HAL, HALManager
from beehave.logic import Logic
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.status import Status
from beehave.testing import WALL_TIMEOUT_S, wall_timeout
from beehave.testing import wait_until as _wait_until
from hal.debug import DebugHAL, DebugRobot

WAIT_S = WALL_TIMEOUT_S  # the suite's one bound (beehave.testing): a safety net only
# When a HAL that ignores cancellation is let go at last, for code that would wait for it for
# ever: well after a loaded machine's unload, well before WAIT_S ends the test.
LET_GO_S = wall_timeout(0.5)


def manager_with_events(**kwargs: Any) -> tuple[HALManager, list[Event]]:
    events: list[Event] = []
    bus = EventBus()
    bus.subscribe(events.append)
    return HALManager(Blackboard(), events=bus, **kwargs), events


def wait_until(predicate: Any, timeout_s: float = WAIT_S) -> bool:
    return _wait_until(predicate, timeout_s)


# -- registry and discovery -------------------------------------------------------------------

def test_unknown_hal_lists_registered_and_entry_point_names() -> None:
    class Lidar(HAL):
        name = "lidar"

    manager = HALManager()
    manager.register(Lidar)

    async def main() -> None:
        await manager.load("nope")

    with pytest.raises(UnknownHAL) as info:
        asyncio.run(main())
    assert "'nope'" in str(info.value)
    # the registered one and every entry point of the installed packages
    assert {"debug", "lidar", "odometry", "kobuki_bumpers"} <= set(info.value.choices)
    assert info.value.choices == sorted(info.value.choices)


def test_debug_hal_is_found_through_the_entry_point_group_without_registering() -> None:
    cls, params = HALManager().resolve("debug")
    assert cls is DebugHAL and params == {}


def test_register_rejects_non_hals_nameless_hals_and_bad_parameters() -> None:
    class Nameless(HAL):
        pass

    manager = HALManager()
    with pytest.raises(HALError, match="not a HAL subclass"):
        manager.register(dict)  # type: ignore[arg-type]
    with pytest.raises(HALError, match="Nameless has no name"):
        manager.register(Nameless)
    with pytest.raises(InvalidParameters, match="'debug'.*wheels"):
        manager.register(DebugHAL, wheels=3)


def test_hal_whose_on_load_raises_fails_the_load_with_hal_error_and_stays_unloaded() -> None:
    class Broken(HAL):
        name = "broken"

        async def on_load(self) -> None:
            raise OSError("no such device")

    manager, events = manager_with_events()
    manager.register(Broken)

    async def main() -> None:
        await manager.load("broken")

    with pytest.raises(HALError, match="'broken' failed to load.*no such device"):
        asyncio.run(main())
    assert manager.loaded == {}
    # Its safe state ran (the load had begun: the device may be half set up), then it ended.
    assert [(e.kind, e.status) for e in events] == [(EventKind.SAFE_STATE_RAN, "FAILED"),
                                                    (EventKind.ENDED, "FAILED")]


def test_concurrent_loads_create_one_instance() -> None:
    manager = HALManager()
    created: list[HAL] = []

    class Counted(HAL):
        name = "counted"

        def __init__(self) -> None:
            created.append(self)

        async def on_load(self) -> None:
            await asyncio.sleep(0.01)

    manager.register(Counted)

    async def main() -> tuple[HAL, HAL]:
        a, b = await asyncio.gather(manager.load("counted", owner=1),
                                    manager.load("counted", owner=2))
        refs = manager.refs("counted")
        await manager.close()
        assert refs == 2
        return a, b

    a, b = asyncio.run(main())
    assert a is b and created == [a]


# -- crash and restart ------------------------------------------------------------------------

def test_crashed_hal_is_restarted_its_entries_stale_meanwhile_and_events_say_so() -> None:
    manager, events = manager_with_events(backoff_initial_s=0.05, backoff_max_s=1.0)
    robot = DebugRobot()
    manager.register(DebugHAL, robot=robot)

    async def main() -> dict[str, Any]:
        hal = await manager.load("debug")
        assert isinstance(hal, DebugHAL)
        bb = manager.blackboard
        await asyncio.sleep(0)
        assert not bb.is_stale("battery/percentage")
        hal.crash(RuntimeError("bus error"))
        while hal.status is not Status.FAILED:
            await asyncio.sleep(0.001)
        during = {"stale": bb.is_stale("battery/percentage"), "status": hal.status}
        robot.set_battery(42)  # the robot changes while its driver is down
        during["value"] = bb.get("battery/percentage")
        while hal.restarts == 0 or bb.is_stale("battery/percentage"):
            await asyncio.sleep(0.001)
        after = {"stale": bb.is_stale("battery/percentage"), "value":
                 bb.get("battery/percentage"), "status": hal.status, "runs": hal.runs,
                 "same": manager.loaded["debug"] is hal, "error": hal.error}
        await manager.close()
        return {"during": during, "after": after}

    got = asyncio.run(asyncio.wait_for(main(), WAIT_S))
    assert got["during"] == {"stale": True, "status": Status.FAILED, "value": 100.0}
    after = got["after"]
    assert after["stale"] is False and after["value"] == 42.0
    assert after["status"] is Status.RUNNING and after["runs"] == 2 and after["same"]
    assert isinstance(after["error"], RuntimeError)
    kinds = [(e.kind, e.status) for e in events if e.subject == "hal:debug"]
    assert kinds[:3] == [(EventKind.STARTED, "RUNNING"), (EventKind.ENDED, "FAILED"),
                         (EventKind.RESTARTED, "RUNNING")]
    failed = next(e for e in events if e.kind is EventKind.ENDED and e.status == "FAILED")
    assert "battery/percentage" in failed.detail["stale_keys"]
    assert str(failed.error) == "bus error"


def test_restart_backoff_doubles_and_is_bounded() -> None:
    manager, events = manager_with_events(backoff_initial_s=0.005, backoff_max_s=0.02)
    manager.register(DebugHAL)

    async def main() -> int:
        hal = await manager.load("debug")
        assert isinstance(hal, DebugHAL)
        hal.fail_runs = 5
        hal.crash()
        while hal.restarts < 6:
            await asyncio.sleep(0.002)
        await manager.close()
        return hal.restarts

    assert asyncio.run(asyncio.wait_for(main(), WAIT_S)) == 6
    delays = [e.detail["after_s"] for e in events if e.kind is EventKind.RESTARTED]
    assert delays == [0.005, 0.01, 0.02, 0.02, 0.02, 0.02]


# -- logics sharing HALs across switches -------------------------------------------------------

class UsesDebug(Logic):
    """Holds the debug HAL and starts a sub-logic that holds it too."""

    def __init__(self, color: str = "green") -> None:
        self.color = color
        self.hal_seen: list[HAL] = []
        self.ready = threading.Event()

    async def run(self) -> None:
        hal = await self.hal("debug", DebugHAL)
        self.hal_seen.append(hal)
        hal.set_leds(self.color)
        child = self.start_logic(ChildUsesDebug(self.hal_seen), name="child")
        await child.ready.wait()
        self.ready.set()
        await asyncio.Event().wait()


class ChildUsesDebug(Logic):
    def __init__(self, seen: list[HAL]) -> None:
        self.seen = seen
        self.ready = asyncio.Event()

    async def run(self) -> None:
        self.seen.append(await self.hal("debug"))
        self.ready.set()
        await asyncio.Event().wait()


def test_switching_logics_while_hals_are_shared() -> None:
    robot = DebugRobot()
    ll = LowLevelBehaviorManager(stop_timeout_s=0.5)
    ll.register("green", UsesDebug, color="green")
    ll.register("blue", UsesDebug, color="blue")
    ll.hals.register(DebugHAL, robot=robot)
    with ll:
        first = ll.switch("green")
        assert isinstance(first, UsesDebug) and first.ready.wait(WAIT_S)
        hal = first.hal_seen[0]
        assert first.hal_seen == [hal, hal]              # parent and child share it
        assert ll.hals.refs("debug") == 2
        assert robot.led_color == "green"
        for _ in range(5):                              # switch back and forth
            for name in ("blue", "green"):
                logic = ll.switch(name)
                assert isinstance(logic, UsesDebug) and logic.ready.wait(WAIT_S)
                assert logic.hal_seen == [hal, hal]      # the one HAL, kept loaded
                assert robot.led_color == name
        assert isinstance(hal, DebugHAL) and hal.safe_states == 0 and hal.runs == 1
        assert ll.hals.loaded == {"debug": hal} and hal.status is Status.RUNNING
        assert wait_until(lambda: ll.hals.refs("debug") == 2)  # the handover was given back
    assert ll.hals.loaded == {}
    assert robot.led_color == "off"                     # safe state at shutdown
    assert hal.safe_states == 1 and list(robot.led_history).count("off") == 1


# -- HALs kept across a switch (issue 9, item 13) ----------------------------------------------

class CountsLoads(HAL):
    name = "counted"
    loads = 0
    safe = 0

    async def on_load(self) -> None:
        type(self).loads += 1

    def safe_state(self) -> None:
        type(self).safe += 1


class UsesCounted(Logic):
    def __init__(self, also_debug: bool = False) -> None:
        self.also_debug = also_debug
        self.ready = threading.Event()

    async def run(self) -> None:
        await self.hal("counted")
        if self.also_debug:
            await self.hal("debug")
        self.ready.set()
        await asyncio.Event().wait()


def test_a_hal_both_logics_use_stays_loaded_across_the_switch_and_the_rest_unloads() -> None:
    CountsLoads.loads = CountsLoads.safe = 0
    robot = DebugRobot()
    ll = LowLevelBehaviorManager(stop_timeout_s=0.5, hal_handover_s=0.05)
    ll.register("a", UsesCounted, also_debug=True)
    ll.register("b", UsesCounted)
    ll.hals.register(CountsLoads)
    ll.hals.register(DebugHAL, robot=robot)
    with ll:
        first = ll.switch("a")
        assert isinstance(first, UsesCounted) and first.ready.wait(WAIT_S)
        counted = ll.hals.loaded["counted"]
        second = ll.switch("b")
        assert isinstance(second, UsesCounted) and second.ready.wait(WAIT_S)
        # "debug" only "a" used: unloaded (safe state) once the handover time is over
        assert wait_until(lambda: "debug" not in ll.hals.loaded)
        assert robot.led_color == "off"
        assert ll.hals.loaded == {"counted": counted} and ll.hals.refs("counted") == 1
        assert (CountsLoads.loads, CountsLoads.safe) == (1, 0)
        third = ll.switch("a")                          # and back: "counted" still the same
        assert isinstance(third, UsesCounted) and third.ready.wait(WAIT_S)
        assert ll.hals.loaded["counted"] is counted
    assert (CountsLoads.loads, CountsLoads.safe) == (1, 1)


def test_a_fallback_hands_the_hals_over_to_the_default_too(clock: VirtualClock) -> None:
    """On the virtual clock: the 0.2 s handover is not eaten by a loaded machine."""
    class Brief(Logic):
        async def run(self) -> None:
            await self.hal("counted")

    CountsLoads.loads = CountsLoads.safe = 0
    ll = LowLevelBehaviorManager(default="b", stop_timeout_s=0.5, hal_handover_s=0.2,
                                 clock=clock)
    ll.register("b", UsesCounted)
    ll.register("brief", Brief)
    ll.hals.register(CountsLoads)
    with ll:
        assert clock.run_until(lambda: ll.hals.refs("counted") == 1, timeout_s=1.0)
        ll.switch("brief")                              # ends on its own: "b" comes back
        assert clock.run_until(lambda: ll.current == "b" and isinstance(ll.logic, UsesCounted)
                               and ll.logic.ready.is_set(), timeout_s=0.1)
        assert clock.run_until(lambda: ll.hals.refs("counted") == 1, timeout_s=1.0)
        assert CountsLoads.loads == 1
def test_wrong_hal_kind_raises_hal_error_naming_both_classes() -> None:
    class WantsOther(Logic):
        async def run(self) -> None:
            await self.hal("debug", UsesDebugHAL)

    class UsesDebugHAL(HAL):
        name = "other"

    ll = LowLevelBehaviorManager(default="wants")
    ll.register("wants", WantsOther)
    with ll:
        assert wait_until(lambda: ll.last_failed is not None)
        error = ll.last_failed.error if ll.last_failed else None
        assert wait_until(lambda: ll.hals.loaded == {})  # its reference was given back
    assert isinstance(error, HALError)
    assert "DebugHAL" in str(error) and "UsesDebugHAL" in str(error)


# -- bounded unload, safe_state exactly once (issue 9, item 12) --------------------------------

class Deaf(HAL):
    """run() and (optionally) on_load() ignore cancellation until ``let_go`` is set."""

    name = "deaf"

    def __init__(self, *, deaf_on_load: bool = False) -> None:
        self.deaf_on_load = deaf_on_load
        self.let_go = False
        self.safe = 0

    async def _deaf(self) -> None:
        while not self.let_go:
            try:
                await asyncio.sleep(0.005)
            except asyncio.CancelledError:
                continue  # the bug under test: cancellation swallowed

    async def on_load(self) -> None:
        if self.deaf_on_load:
            await self._deaf()

    async def run(self) -> None:
        await self._deaf()

    def safe_state(self) -> None:
        self.safe += 1


def test_unloading_a_hal_whose_run_ignores_cancellation_is_bounded_and_reported_stuck() -> None:
    manager, events = manager_with_events()
    manager.stop_timeout_s = 0.1
    manager.register(Deaf)

    async def main() -> dict[str, Any]:
        hal = await manager.load("deaf")
        assert isinstance(hal, Deaf)
        await asyncio.sleep(0.01)
        # a safety net for the unfixed code, which would wait for ever
        asyncio.get_running_loop().call_later(LET_GO_S, setattr, hal, "let_go", True)
        await manager.release("deaf")
        got = {"run_still_going": not hal.let_go, "status": hal.status, "safe": hal.safe,
               "loaded": dict(manager.loaded)}
        hal.let_go = True
        await manager.close()
        got["status_after"] = hal.status
        got["leftover"] = {t for t in asyncio.all_tasks() if t.get_name().startswith("hal:")}
        return got

    got = asyncio.run(asyncio.wait_for(main(), WAIT_S))
    assert got["run_still_going"] and got["status"] is Status.STUCK
    assert got["safe"] == 1 and got["loaded"] == {}      # unloaded anyway, safe state ran
    assert got["status_after"] is Status.INTERRUPTED and not got["leftover"]
    stuck = [e for e in events if e.kind is EventKind.STUCK]
    assert [(e.subject, e.detail["phase"]) for e in stuck] == [("hal:deaf", "run")]


def test_safe_state_runs_although_the_releasing_owner_is_cancelled_during_the_unload() -> None:
    class Slow(HAL):
        name = "slow"
        safe = 0

        async def run(self) -> None:
            try:
                await asyncio.Event().wait()
            finally:
                await asyncio.sleep(0.05)  # a slow but honest stop

        def safe_state(self) -> None:
            type(self).safe += 1

    manager, _ = manager_with_events()
    manager.register(Slow)

    async def main() -> set[asyncio.Task[Any]]:
        owner = object()
        await manager.load("slow", owner=owner)
        await asyncio.sleep(0)
        releaser = asyncio.create_task(manager.release("slow", owner=owner))
        await asyncio.sleep(0.01)  # the release now waits for run() to end
        releaser.cancel()          # its owner is stopped a second time
        await asyncio.wait({releaser})
        await manager.close()
        return {t for t in asyncio.all_tasks() if t.get_name().startswith("hal:")}

    leftover = asyncio.run(asyncio.wait_for(main(), WAIT_S))
    assert Slow.safe == 1 and not leftover


class HangsOnLoad(HAL):
    name = "hangs"
    safe = 0

    async def on_load(self) -> None:
        await asyncio.Event().wait()  # a device that never answers

    def safe_state(self) -> None:
        type(self).safe += 1


class AsksForHanging(Logic):
    async def run(self) -> None:
        await self.hal("hangs")


def test_a_hal_whose_on_load_hangs_does_not_hang_the_shutdown_and_gets_its_safe_state() -> None:
    ll = LowLevelBehaviorManager(default="asks", stop_timeout_s=0.1)
    ll.register("asks", AsksForHanging)
    ll.hals.register(HangsOnLoad)
    events: list[Event] = []
    ll.subscribe(events.append)

    def run() -> None:
        with ll:
            assert wait_until(lambda: ll.hals.refs("hangs") == 1)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(WAIT_S)
    assert not thread.is_alive(), "shutdown hangs on a HAL whose on_load never ends"
    assert HangsOnLoad.safe == 1
    ended = [e for e in events if e.subject == "hal:hangs" and e.kind is EventKind.ENDED]
    assert [(e.status, e.detail.get("phase")) for e in ended] == [("INTERRUPTED", "on_load")]


def test_an_on_load_that_ignores_cancellation_is_reported_stuck_at_shutdown() -> None:
    manager, events = manager_with_events()
    manager.stop_timeout_s = 0.1
    manager.register(Deaf, deaf_on_load=True)

    async def main() -> tuple[int, set[asyncio.Task[Any]]]:
        loading = asyncio.create_task(manager.load("deaf"))
        deadline = asyncio.get_running_loop().time() + WAIT_S
        while "deaf" not in manager._loaded and asyncio.get_running_loop().time() < deadline:
            await asyncio.sleep(0.01)
        hal = manager._loaded["deaf"].hal
        assert isinstance(hal, Deaf)
        asyncio.get_running_loop().call_later(LET_GO_S, setattr, hal, "let_go", True)  # safety net
        await manager.close()
        safe = hal.safe
        hal.let_go = True
        await asyncio.wait({loading})
        await asyncio.sleep(0.02)
        return safe, {t for t in asyncio.all_tasks() if t.get_name().startswith("hal:")}

    safe, leftover = asyncio.run(asyncio.wait_for(main(), WAIT_S))
    assert safe == 1 and not leftover
    assert [(e.kind, e.detail.get("phase")) for e in events if e.kind is EventKind.STUCK] \
        == [(EventKind.STUCK, "on_load")]


def test_a_hal_cancelled_in_on_load_gets_its_whole_async_safe_state_and_is_not_stuck() -> None:
    """on_load obeys its cancellation (with an orderly close) and safe_state is async: the
    two together may take longer than stop_timeout_s, each within it. That is not STUCK,
    and the safe state must not be cut short."""
    marks: list[str] = []

    class Cam(HAL):
        name = "cam"

        async def on_load(self) -> None:
            try:
                await asyncio.Event().wait()  # the device does not answer yet
            except asyncio.CancelledError:
                await asyncio.sleep(0.9)      # orderly close of the half-open device
                raise

        async def safe_state(self) -> None:
            marks.append("safe_state begins")
            await asyncio.sleep(0.9)
            marks.append("safe_state ends")

        def on_unload(self) -> None:
            marks.append("on_unload")

    # Each 0.9 s within 1.5 s, the two 1.8 s together: 0.6 s to spare for a loaded machine
    # (with 0.12 s each in 0.2 s, a stress run's safe state was cut short).
    manager, events = manager_with_events(stop_timeout_s=1.5)
    manager.register(Cam)

    async def main() -> set[asyncio.Task[Any]]:
        loading = asyncio.create_task(manager.load("cam"))
        await asyncio.sleep(0.02)
        await manager.close()
        await asyncio.wait({loading})
        return {t for t in asyncio.all_tasks() if t.get_name().startswith("hal:")}

    leftover = asyncio.run(asyncio.wait_for(main(), WAIT_S))
    assert marks == ["safe_state begins", "safe_state ends", "on_unload"]
    assert not [e for e in events if e.kind is EventKind.STUCK] and not leftover


def test_shutdown_with_many_hals_that_ignore_cancellation_is_bounded_once_not_per_hal() -> None:
    """Ten HALs whose run() swallows cancellation: they are unloaded together, so shutdown
    takes about stop_timeout_s (twice: once to unload, once to cancel them again), not ten
    times that; the logic that held them obeyed at once and is not STUCK."""
    names = [f"deaf{i}" for i in range(10)]
    hals: list[Deaf] = []

    class UsesAll(Logic):
        async def run(self) -> None:
            for n in names:
                hal = await self.hal(n)
                assert isinstance(hal, Deaf)
                hals.append(hal)
            await asyncio.Event().wait()

    ll = LowLevelBehaviorManager(default="u", stop_timeout_s=0.5)
    ll.register("u", UsesAll)
    for n in names:
        ll.hals.register(Deaf, name=n)
    stuck: list[str] = []
    ll.subscribe(lambda e: e.kind is EventKind.STUCK and stuck.append(e.subject))
    ll.__enter__()
    assert wait_until(lambda: len(hals) == len(names))
    thread = threading.Thread(target=ll.shutdown, daemon=True)
    thread.start()
    # Ten sequential unloads would take 10 × 0.5 s at least; together, twice 0.5 s, and 2 s
    # to spare for a loaded machine.
    thread.join(2 * 0.5 + 2.0)
    returned = not thread.is_alive()
    for hal in hals:
        hal.let_go = True
    thread.join(WAIT_S)
    assert returned, "shutdown time grows with the number of stuck HALs"
    assert "u" not in stuck and sorted(stuck) == sorted(f"hal:{n}" for n in names)
    assert all(hal.safe == 1 for hal in hals)


def test_a_sub_logic_that_ends_late_does_not_leak_its_hal_reference_to_the_handover() -> None:
    """It hands its reference over after the grace period of its switch has run out: that
    reference gets a grace period of its own and is then released (the HAL unloads)."""
    safe: list[int] = []

    class Lamp(HAL):
        name = "lamp"

        def safe_state(self) -> None:
            safe.append(1)

    class Slow(Logic):
        async def run(self) -> None:
            await self.hal("lamp")
            try:
                await asyncio.Event().wait()
            except asyncio.CancelledError:
                await asyncio.sleep(0.4)  # a slow cleanup, longer than stop_timeout_s
                raise

    class Parent(Logic):
        async def run(self) -> None:
            self.start_logic(Slow())
            await asyncio.Event().wait()

    class Idle(Logic):
        async def run(self) -> None:
            await asyncio.Event().wait()

    ll = LowLevelBehaviorManager(default="parent", stop_timeout_s=0.1, hal_handover_s=0.05)
    ll.register("parent", Parent)
    ll.register("idle", Idle)
    ll.hals.register(Lamp)
    with ll:
        assert wait_until(lambda: ll.hals.refs("lamp") == 1)
        ll.switch("idle")  # idle does not use the lamp
        assert wait_until(lambda: "lamp" not in ll.hals.loaded), \
            "the late sub-logic's lamp reference is never given back"
        # Unloaded first, then its safe state runs (in the loop): wait for it.
        assert wait_until(lambda: safe == [1])
    assert safe == [1]


def test_a_second_switch_keeps_the_grace_period_of_the_hals_it_hands_over(
        clock: VirtualClock) -> None:
    """a → b → c: the first handover is still being released (another HAL's slow safe
    state) when b hands over "y"; c asks for "y" well within hal_handover_s of its switch,
    so "y" is never unloaded and loaded again. On the test kit's virtual clock: the
    periods below are exact, on a loaded machine too."""
    loads: list[str] = []

    class X(HAL):
        name = "x"

        async def safe_state(self) -> None:
            await asyncio.sleep(0.5)

    class Y(HAL):
        name = "y"

        async def on_load(self) -> None:
            loads.append("y")

    class A(Logic):
        async def run(self) -> None:
            await self.hal("x")
            await self.hal("y")
            await asyncio.Event().wait()

    class B(Logic):
        async def run(self) -> None:
            await self.hal("y")
            await asyncio.Event().wait()

    class C(Logic):
        async def run(self) -> None:
            # After the old code released b's handover of y (0.5 s: x's safe state), well
            # within c's own grace period (1.5 s).
            await asyncio.sleep(0.9)
            await self.hal("y")
            await asyncio.Event().wait()

    ll = LowLevelBehaviorManager(default="a", hal_handover_s=1.5, stop_timeout_s=1.0,
                                 clock=clock)
    for name, cls in (("a", A), ("b", B), ("c", C)):
        ll.register(name, cls)
    ll.hals.register(X)
    ll.hals.register(Y)
    with ll:
        assert clock.run_until(lambda: ll.hals.refs("y") == 1, timeout_s=1.0)
        ll.switch("b")
        # a's grace is over at 1.5 s: x unloads (its safe state takes 0.5 s more).
        assert clock.run_until(lambda: "x" not in ll.hals.loaded, timeout_s=10.0)
        assert clock.now() == 1.5
        ll.switch("c")
        assert clock.run_until(lambda: ll.hals.refs("y") == 1 and ll.hals.holds("y", ll.logic),
                               timeout_s=10.0)
        # c took y at 2.4 s (0.9 s after its switch); b's handover let go of it at 3.0 s.
        assert clock.now() == 3.0
        assert loads == ["y"], "y was unloaded and loaded again within its grace period"
