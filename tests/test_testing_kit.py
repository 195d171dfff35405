"""The test kit (beehave.testing): the virtual clock's contract, the fixtures, substitutes,
ScriptedHAL, the assertions, and the simulation in lockstep — each checked against what
it promises in docs/testing.md, on the plugin's own fixtures."""

from __future__ import annotations

import asyncio
import math
import random
import threading
import time
from pathlib import Path

import pytest

from beehave import Action, Behavior, HighLevelBehaviorManager, Logic, Status
from beehave.clock import VirtualClock
from beehave.errors import ClockNotSettled, ConfigError
from beehave.testing import (
    WALL_TIMEOUT_S,
    EventLog,
    Scripted,
    ScriptedHAL,
    Timeline,
    assert_lock_held_by,
    assert_safe_state_ran,
)

# ------------------------------------------------------------------ the clock's contract


def test_advance_runs_a_sleeping_loop_once_per_second(high_level: HighLevelBehaviorManager,
                                                      clock: VirtualClock) -> None:
    stamps: list[float] = []

    class Patrol(Behavior):
        def run(self) -> None:
            while self.sleep(1.0):
                stamps.append(clock.now())

    high_level.register("patrol", Patrol)
    high_level.switch("patrol")
    clock.advance(600.0)
    assert stamps == [float(i) for i in range(1, 601)]
    assert clock.now() == 600.0


def test_decimal_periods_add_up_exactly(high_level: HighLevelBehaviorManager,
                                        clock: VirtualClock) -> None:
    """Time is whole nanoseconds: two hundred sleeps of 0.01 s end at 2.0 s, not at
    2.0000000000000013 s (a float sum), so ``advance(2.0)`` sees the last one."""
    done: list[float] = []

    class Fine(Behavior):
        def run(self) -> None:
            for _ in range(200):
                self.sleep(0.01)
            done.append(clock.now())

    high_level.register("fine", Fine)
    high_level.switch("fine")
    clock.advance(2.0)
    assert done == [2.0]


def test_time_stands_still_until_advanced(high_level: HighLevelBehaviorManager,
                                          clock: VirtualClock) -> None:
    woke = threading.Event()

    class Nap(Behavior):
        def run(self) -> None:
            self.sleep(5.0)
            woke.set()

    high_level.register("nap", Nap)
    high_level.switch("nap")
    time.sleep(0.05)  # wall time passes; virtual time does not
    assert not woke.is_set() and clock.now() == 0.0
    clock.advance(4.999)
    assert not woke.is_set()
    clock.advance(0.001)
    assert woke.is_set()


def test_no_step_while_a_worker_still_computes(high_level: HighLevelBehaviorManager,
                                               clock: VirtualClock) -> None:
    """A worker that computes (wall time) between its sleeps is waited for: the clock
    never steps past a deadline while someone can still act before it."""
    seen: list[tuple[str, float]] = []

    class Slow(Action):
        action_type = "slow"

        def run(self) -> None:
            for _ in range(5):
                end = time.monotonic() + 0.01
                while time.monotonic() < end:  # busy: 10 ms of wall time, no sleep
                    pass
                seen.append(("slow", clock.now()))
                self.sleep(1.0)

    class Fast(Action):
        action_type = "fast"

        def run(self) -> None:
            for _ in range(10):
                seen.append(("fast", clock.now()))
                self.sleep(0.5)

    class Both(Behavior):
        def run(self) -> None:
            a, b = self.start_action(Slow()), self.start_action(Fast())
            a.wait()
            b.wait()

    high_level.register("both", Both)
    both = high_level.switch("both")
    assert clock.run_until(lambda: both.status.finished, timeout_s=60.0)
    assert both.status is Status.SUCCEEDED
    assert sorted(t for who, t in seen if who == "slow") == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert sorted(t for who, t in seen if who == "fast") == [i * 0.5 for i in range(10)]
    assert clock.now() == 5.0


def test_run_until_gives_up_at_its_virtual_timeout(high_level: HighLevelBehaviorManager,
                                                   clock: VirtualClock) -> None:
    assert clock.run_until(lambda: False, timeout_s=30.0) is False
    assert clock.now() == 30.0


def test_a_wait_the_clock_cannot_see_is_named(high_level: HighLevelBehaviorManager,
                                              clock: VirtualClock,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    release = threading.Event()

    class Blind(Behavior):
        def run(self) -> None:
            release.wait()  # not through the clock: it cannot tell this thread waits

    monkeypatch.setattr(VirtualClock, "SETTLE_TIMEOUT_S", 0.2)
    high_level.register("blind", Blind)
    high_level.switch("blind")
    with pytest.raises(ClockNotSettled, match=r"beehave:blind"):
        clock.advance(1.0)
    release.set()


def test_advance_run_until_and_sleep_refuse_nonsense() -> None:
    clock = VirtualClock()
    for bad in (-1.0, math.inf, math.nan, "1"):
        with pytest.raises(ValueError, match="finite number"):
            clock.advance(bad)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="finite number"):
            clock.run_until(lambda: False, timeout_s=bad)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="finite number"):
            clock.sleep(bad)  # type: ignore[arg-type]


def test_autojump_reproduces_the_same_interleaving_every_time() -> None:
    """Three workers with co-prime periods: the order of their wake-ups is a function of
    virtual time alone, on an idle or a loaded machine."""

    def one_run() -> list[tuple[float, str]]:
        clock = VirtualClock(autojump=True)
        order: list[tuple[float, str]] = []
        lock = threading.Lock()

        def ticker(period_s: float) -> type[Action]:
            class Tick(Action):
                action_type = f"tick{period_s}"

                def run(self) -> None:
                    for _ in range(int(6.0 / period_s)):
                        if not self.sleep(period_s):
                            return
                        with lock:
                            order.append((clock.now(), self.action_type))
            return Tick

        class Three(Behavior):
            def run(self) -> None:
                for handle in [self.start_action(ticker(p)()) for p in (0.7, 1.1, 1.3)]:
                    handle.wait()

        try:
            with HighLevelBehaviorManager(clock=clock, stop_timeout_s=1.0) as hl:
                hl.register("three", Three)
                three = hl.switch("three")
                assert three.wait(WALL_TIMEOUT_S) and three.status is Status.SUCCEEDED
        finally:
            clock.close()
        return sorted(order)

    first = one_run()
    assert len(first) == 8 + 5 + 4
    assert all(abs(t - round(t / p) * p) < 1e-9 for t, who in first
               for p in [float(who[4:])])
    assert one_run() == first
    # The same beside a CPU hog in this very process (it competes for the GIL too).
    stop = threading.Event()

    def hog() -> None:
        while not stop.is_set():
            sum(range(1000))

    hogs = [threading.Thread(target=hog, daemon=True) for _ in range(2)]
    for thread in hogs:
        thread.start()
    try:
        assert one_run() == first
    finally:
        stop.set()
        for thread in hogs:
            thread.join()


@pytest.mark.beehave_clock(autojump=True)
def test_autojump_moves_only_while_everyone_rests(high_level: HighLevelBehaviorManager,
                                                  clock: VirtualClock) -> None:
    class Long(Behavior):
        def run(self) -> float:
            self.sleep(3600.0)
            return clock.now()

    high_level.register("long", Long)
    long = high_level.switch("long")
    assert long.wait(WALL_TIMEOUT_S)  # wall: an hour of virtual time is one jump
    assert long.result == 3600.0


def test_stress_switches_on_virtual_time_keep_the_type_locks(
        high_level: HighLevelBehaviorManager, clock: VirtualClock) -> None:
    """Many switches, while actions of one type preempt each other on virtual time: never
    two actions of a type at once, every interrupted action's safe state ran, no thread
    left (the fixture checks)."""
    timeline = Timeline()
    rng = random.Random(7)
    started: list[Action] = []

    class Drive(Action):
        action_type = "driving"

        def run(self) -> None:
            timeline.record("run", self)
            try:
                self.sleep(rng.choice([0.1, 0.5, 2.0]))
            finally:
                timeline.record("end", self)

        def safe_state(self) -> None:
            timeline.record("safe_begin", self)
            timeline.record("safe", self)

    class Busy(Behavior):
        def run(self) -> None:
            while not self.interrupted:
                started.append(self.start_action(Drive(), preempt=True))
                self.sleep(rng.choice([0.05, 0.3, 1.0]))

    for name in ("a", "b", "c"):
        high_level.register(name, Busy)
    for i in range(60):
        high_level.switch(rng.choice("abc"))
        clock.advance(rng.choice([0.0, 0.2, 1.5]))
        if i % 10 == 0:
            assert timeline.max_concurrent["driving"] <= 1
    high_level.switch("idle")
    assert timeline.max_concurrent["driving"] == 1
    ended = [a for a in started if a.status is not Status.SUCCEEDED]
    assert ended and all(timeline.safe_calls[id(a)] == 1 for a in ended)


# ------------------------------------------------------------------ the low level


def test_the_low_levels_asyncio_time_is_the_clock(low_level, clock: VirtualClock) -> None:
    seen: list[float] = []

    class Blink(Logic):
        async def run(self) -> None:
            loop = asyncio.get_running_loop()
            while True:
                await asyncio.sleep(0.25)
                seen.append(loop.time())

    low_level.register("blink", Blink)
    low_level.switch("blink")
    clock.advance(10.0)
    assert seen == [0.25 * i for i in range(1, 41)]


def test_a_timeout_in_a_logic_follows_the_clock(low_level, clock: VirtualClock) -> None:
    outcome: list[str] = []

    class Waits(Logic):
        async def run(self) -> None:
            try:
                await asyncio.wait_for(asyncio.Event().wait(), timeout=30.0)
            except TimeoutError:
                outcome.append(f"timed out at {asyncio.get_running_loop().time()}")

    low_level.register("waits", Waits)
    low_level.switch("waits")
    clock.advance(29.0)
    assert outcome == []
    clock.advance(1.0)
    assert outcome == ["timed out at 30.0"]


def test_blackboard_staleness_follows_the_clock(low_level, clock: VirtualClock) -> None:
    board = low_level.blackboard
    stale: list[float] = []
    board.declare("scan/range_m", max_age_s=5.0)
    board.subscribe("scan/range_m", lambda change: change.stale and stale.append(clock.now()))
    board.set("scan/range_m", 2.5)
    clock.advance(4.9)
    assert not board.is_stale("scan/range_m") and stale == []
    clock.advance(0.2)
    assert board.is_stale("scan/range_m") and stale == [5.0]


def test_a_tree_ticks_at_its_rate_in_virtual_time(high_level: HighLevelBehaviorManager,
                                                  clock: VirtualClock) -> None:
    import py_trees

    from beehave.engines import EngineBehavior
    from beehave.engines.tree import TreeEngine

    root = py_trees.behaviours.Running(name="forever")
    engine = TreeEngine(root, rate_hz=10.0)

    class Ticking(EngineBehavior):
        def __init__(self) -> None:
            super().__init__(engine)

    high_level.register("ticking", Ticking)
    high_level.switch("ticking")
    clock.advance(60.05)  # the tree's own float sum of 0.1 s steps ends 1 ns past 60.0
    assert engine.ticks == 601  # at 0, 0.1, …, 60.0 s


def test_debug_robot_battery_alarm(debug_robot) -> None:
    class Alarm(Logic):
        async def run(self) -> None:
            await self.hal("debug")
            async for change in self.blackboard.watch("battery/percentage"):
                self.blackboard.set("alarm", change.value < 20.0)

    debug_robot.low.register("alarm", Alarm)
    debug_robot.low.switch("alarm")
    debug_robot.clock.advance(1.0)
    assert debug_robot.blackboard.get("alarm") is False
    debug_robot.hardware.set_battery(12.0)
    debug_robot.clock.advance(1.0)
    assert debug_robot.blackboard.get("alarm") is True


# ------------------------------------------------------------------ substitutes


class Navigate(Action):
    action_type = "driving"

    def __init__(self, goal: str) -> None:
        self.goal = goal

    def run(self) -> None:
        raise AssertionError("the real Navigate ran although it was substituted")


class Lift(Action):
    action_type = "lifting"

    def run(self) -> None:
        raise AssertionError("the real Lift ran although it was substituted")


class Delivery(Behavior):
    def run(self) -> list[str]:
        done = []
        for step in (Navigate("pickup"), Lift(), Navigate("drop")):
            self.start_action(step).wait()
            done.append(f"{step.name}:{step.status.name}")
        return done


def test_substitution_by_path_name_or_class_and_first_rule_wins(
        high_level: HighLevelBehaviorManager, clock: VirtualClock) -> None:
    first = Scripted(duration_s=10.0, result="at pickup")
    second = Scripted(duration_s=20.0, result="elsewhere")
    lift = Scripted(duration_s=3.0, raises=RuntimeError("lift jammed"))
    high_level.substitute("delivery/Navigate", first)   # the path of the first one only
    high_level.substitute("Navigate*", second)          # every other
    remove = high_level.substitute("Lift", lift)        # by class name
    high_level.register("delivery", Delivery)
    delivery = high_level.switch("delivery")
    assert clock.run_until(lambda: delivery.status.finished, timeout_s=100.0)
    assert clock.now() == 33.0
    assert delivery.result == ["Navigate:SUCCEEDED", "Lift:FAILED", "Navigate:SUCCEEDED"]
    assert [n.goal for n in first.replaced] == ["pickup"]
    assert [n.goal for n in second.replaced] == ["drop"]
    assert first.replaced[0].result == "at pickup"
    assert str(lift.replaced[0].error) == "lift jammed"
    assert lift.safe_states == ["delivery/Lift"]
    remove()
    assert high_level.substitutes.patterns == ["delivery/Navigate", "Navigate*"]


def test_a_refused_action_was_stood_in_for_by_nobody(high_level, clock) -> None:
    from beehave.errors import ActionTypeBusy

    stand_in = Scripted(duration_s=math.inf)
    high_level.substitute("Navigate", stand_in)
    refused: list[str] = []

    class Twice(Behavior):
        def run(self) -> None:
            self.start_action(Navigate("a"))
            try:
                self.start_action(Navigate("b"))  # the type is taken: refused
            except ActionTypeBusy:
                refused.append("b")
            self.sleep(math.inf)

    high_level.register("twice", Twice)
    high_level.switch("twice")
    clock.advance(1.0)
    assert refused == ["b"]
    assert [n.goal for n in stand_in.replaced] == ["a"]


def test_bad_substitutes_are_refused_with_the_reason(high_level) -> None:
    with pytest.raises(ConfigError, match="callable"):
        high_level.substitute("Navigate", "not a substitute")
    with pytest.raises(ConfigError, match="non-empty str"):
        high_level.substitute("", Scripted())
    with pytest.raises(ConfigError, match="duration_s"):
        Scripted(duration_s=-1.0)
    with pytest.raises(ConfigError, match="raises"):
        Scripted(raises="boom")  # type: ignore[arg-type]


def test_an_interrupted_stand_in_runs_its_safe_state(high_level: HighLevelBehaviorManager,
                                                     clock: VirtualClock, event_log) -> None:
    drive = Scripted(duration_s=math.inf)
    high_level.substitute("Navigate", drive)
    high_level.register("delivery", Delivery)
    high_level.switch("delivery")
    clock.advance(5.0)
    assert_lock_held_by(high_level, "driving", "delivery/Navigate")
    with pytest.raises(AssertionError, match="not held"):
        assert_lock_held_by(high_level, "lifting", "Lift")
    high_level.switch("idle")
    nav = drive.replaced[0]
    assert nav.status is Status.INTERRUPTED
    assert_safe_state_ran(nav)
    event_log.assert_switched_to("idle")
    event_log.assert_in_order("started delivery/Navigate", "ended delivery/Navigate INTERRUPTED",
                           "ended delivery INTERRUPTED", "switch_completed idle")
    event_log.assert_not_happened("started delivery/Lift")
    with pytest.raises(AssertionError, match="no 'started delivery/Lift'"):
        event_log.assert_in_order("started delivery/Navigate", "started delivery/Lift")


def test_a_logic_is_substituted_by_name(low_level, clock: VirtualClock) -> None:
    class Lights(Logic):
        async def run(self) -> None:
            raise AssertionError("the real logic ran although it was substituted")

    stand_in = Scripted(duration_s=2.0, result="lit")
    low_level.substitute("lights", stand_in)
    low_level.register("lights", Lights)
    low_level.switch("lights")
    clock.advance(3.0)
    logic = stand_in.replaced[0]
    assert logic.status is Status.SUCCEEDED and logic.result == "lit"


def test_scripted_hal_records_calls_and_writes_its_values(low_level, clock) -> None:
    calls: list[tuple[str, tuple[object, ...], dict[str, object]]] = []

    class Raise(Logic):
        async def run(self) -> None:
            lift = await self.hal("lift")
            lift.set_height(0.2)
            self.blackboard.set("answer", lift.height())

    low_level.hals.register(ScriptedHAL, name="lift", values={"lift/height_m": 0.0},
                            returns={"height": 0.2}, calls=calls)
    low_level.register("raise", Raise)
    low_level.switch("raise")
    clock.advance(1.0)
    assert low_level.blackboard.get("lift/height_m") == 0.0
    assert low_level.blackboard.get("answer") == 0.2
    assert calls[:2] == [("set_height", (0.2,), {}), ("height", (), {})]


def test_substitutes_from_the_robot_yaml(tmp_path: Path, robot_factory, clock) -> None:
    (tmp_path / "robot.yaml").write_text(f"""
namespace: testbot
behaviors:
  delivery: {{class: "{__name__}:Delivery"}}
default_behavior: delivery
substitutes:
  "delivery/Navigate*": {{duration_s: 30.0, result: true}}
  "Lift": {{duration_s: 2.0, fail: "lift jammed"}}
""")
    robot = robot_factory(tmp_path / "robot.yaml")
    delivery = robot.high.top
    assert clock.run_until(lambda: delivery.status.finished, timeout_s=600.0)
    assert delivery.result == ["Navigate:SUCCEEDED", "Lift:FAILED", "Navigate:SUCCEEDED"]
    assert clock.now() == 62.0


def test_a_bad_substitute_in_yaml_names_the_key(tmp_path: Path) -> None:
    from beehave.config import load_config

    (tmp_path / "robot.yaml").write_text(
        'namespace: testbot\nsubstitutes:\n  "Lift": {duration_s: -2, fial: x}\n')
    with pytest.raises(ConfigError) as caught:
        load_config(tmp_path / "robot.yaml")
    assert "substitutes.Lift.duration_s" in str(caught.value)
    assert "substitutes.Lift.fial" in str(caught.value)


def test_event_log_needs_a_manager() -> None:
    with pytest.raises(ValueError, match="at least one manager"):
        EventLog()


# ------------------------------------------------------------------ the simulation


def test_the_simulation_steps_in_lockstep_with_the_clock(sim, clock, high_level) -> None:
    """Real pybullet physics on virtual time: EMILI driven at 0.3 m/s for 3 s covers about
    0.9 m, and the simulation's time is the clock's to the step."""
    world = sim("warehouse")
    emili = world.emili("emili1")
    start = emili.pose()

    class Drive(Action):
        action_type = "driving"

        def run(self) -> None:
            while not self.interrupted:
                emili.set_cmd_vel(0.3, 0.0)
                self.sleep(0.05)

        def safe_state(self) -> None:
            emili.set_cmd_vel(0.0, 0.0)

    class Go(Behavior):
        def run(self) -> None:
            self.start_action(Drive()).wait()

    high_level.register("go", Go)
    high_level.switch("go")
    clock.advance(3.0)
    high_level.switch("idle")
    clock.advance(1.0)
    end = emili.pose()
    moved = math.hypot(end.x_m - start.x_m, end.y_m - start.y_m)
    print(f"\n| sim time | clock | moved (m) |\n| {world.time_s:.3f} | {clock.now():.3f} | "
          f"{moved:.3f} |")
    assert abs(world.time_s - clock.now()) <= world.step_s
    assert 0.75 < moved < 1.0


# ------------------------------------------------------------------ found in review


def test_an_interrupt_reaches_an_engine_driven_from_a_plain_behaviour(
        high_level: HighLevelBehaviorManager, clock: VirtualClock) -> None:
    """``return engine.drive(self)`` in a plain behaviour: the engine's waits sleep on the
    behaviour's own condition, which the interrupt notifies; the virtual clock stands still
    during the switch, so a poll would never come."""
    from beehave.engines.engine import DecisionEngine

    class Waiter(DecisionEngine):
        def run(self, context: object) -> str:
            while context.wait():  # type: ignore[attr-defined]
                pass
            return "stopped"

    class Custom(Behavior):
        def run(self) -> object:
            return Waiter().drive(self)

    high_level.register("custom", Custom)
    custom = high_level.switch("custom")
    clock.advance(1.0)
    high_level.switch("idle")
    assert custom.status is Status.INTERRUPTED


def test_native_stacks_reads_a_child_s_c_stacks_with_gdb_or_says_nothing() -> None:
    import shutil
    import subprocess
    import sys

    from beehave.testing import native_stacks

    child = subprocess.Popen([sys.executable, "-c",
                              "import time; print('asleep', flush=True); time.sleep(60)"],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None and child.stdout.readline() == "asleep\n"
        stacks = native_stacks(child.pid)
        if shutil.which("gdb") is None:
            assert stacks == ""
        else:
            assert stacks.startswith("Thread 1 ") and "sleep" in stacks, stacks[:500]
        assert child.poll() is None  # read, not ended
    finally:
        child.kill()
        child.wait()
