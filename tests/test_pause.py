"""The pause contract: ``hl.pause()`` / ``hl.resume()`` (docs/concepts.md, "Pause and resume").

A pause brings every running action to a safe stop within ``stop_timeout_s`` (STUCK if it
ignores it), keeps the top-level behaviour, its sub-behaviours, their type locks and their
progress, and stops time for them; resume goes on where each left off. A switch or the
shutdown while paused ends the pause and restarts nothing.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from beehave import (
    Action,
    ActionTypeBusy,
    BeehaveError,
    Behavior,
    Event,
    EventKind,
    HighLevelBehaviorManager,
    ManagerShutdown,
    Status,
)
from beehave.clock import VirtualClock
from beehave.testing import WALL_TIMEOUT_S, beehave_threads, no_thread_left, wait_until


class Motion:
    """What the "hardware" saw: every command with its time, and who is inside run()."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.commands: list[tuple[float, str]] = []
        self.inside: dict[str, int] = {}
        self.most_inside: dict[str, int] = {}

    def command(self, who: str) -> None:
        with self.lock:
            self.commands.append((time.monotonic(), who))

    def enter(self, kind: str) -> None:
        with self.lock:
            self.inside[kind] = self.inside.get(kind, 0) + 1
            self.most_inside[kind] = max(self.most_inside.get(kind, 0), self.inside[kind])

    def leave(self, kind: str) -> None:
        with self.lock:
            self.inside[kind] -= 1

    def between(self, t0: float, t1: float) -> list[tuple[float, str]]:
        with self.lock:
            return [c for c in self.commands if t0 < c[0] < t1]


class Drive(Action):
    """Commands a velocity every 10 ms until it has sent ``steps`` of them."""

    action_type = "driving"

    def __init__(self, motion: Motion, steps: int = 10_000, period_s: float = 0.01) -> None:
        self.motion, self.steps, self.period_s = motion, steps, period_s
        self.runs = 0
        self.sent = 0
        self.safe_calls = 0

    def run(self) -> int:
        self.runs += 1
        self.motion.enter(self.action_type)
        try:
            while self.sent < self.steps and not self.interrupted:
                self.motion.command(self.path)
                self.sent += 1
                self.sleep(self.period_s)
            return self.sent
        finally:
            self.motion.leave(self.action_type)

    def safe_state(self) -> None:
        self.safe_calls += 1


class HookedDrive(Drive):
    """Pauses itself: stops commanding and keeps its thread."""

    def __init__(self, motion: Motion, **kwargs: Any) -> None:
        super().__init__(motion, **kwargs)
        self.hold = False
        self.hooks: list[str] = []

    def run(self) -> int:
        self.runs += 1
        while self.sent < self.steps and not self.interrupted:
            if not self.hold:
                self.motion.command(self.path)
                self.sent += 1
            self.sleep(self.period_s)
        return self.sent

    def on_pause(self) -> None:
        self.hold = True
        self.hooks.append("pause")

    def on_resume(self) -> None:
        self.hooks.append("resume")
        self.hold = False


class Mission(Behavior):
    """Starts one action, then sleeps ``sleep_s`` and notes the time it saw."""

    def __init__(self, make: Any, sleep_s: float = 30.0) -> None:
        self.make, self.sleep_s = make, sleep_s
        self.action: Any = None
        self.slept: tuple[float, float] | None = None

    def run(self) -> None:
        self.action = self.start_action(self.make())
        t0 = self.manager.run_clock.now()
        self.sleep(self.sleep_s)
        self.slept = (t0, self.manager.run_clock.now())
        self.action.wait()


@pytest.fixture
def manager() -> Iterator[tuple[HighLevelBehaviorManager, list[Event]]]:
    with no_thread_left("shutdown"):
        # A generous bound: a pause that a loaded host makes late must not turn STUCK here
        # (the STUCK test waits for it, once).
        hl = HighLevelBehaviorManager(stop_timeout_s=2.0)
        events: list[Event] = []
        hl.subscribe(events.append)
        hl.start()
        try:
            yield hl, events
        finally:
            hl.shutdown()


def kinds(events: list[Event], kind: EventKind) -> list[Event]:
    return [e for e in list(events) if e.kind is kind]


def start(hl: HighLevelBehaviorManager, make: Any, sleep_s: float = 30.0) -> Mission:
    hl.register("mission", Mission, make=make, sleep_s=sleep_s)
    mission = hl.switch("mission")
    assert isinstance(mission, Mission)
    assert wait_until(lambda: mission.action is not None and mission.action.sent >= 2)
    return mission


def test_a_pause_stops_every_command_keeps_the_behaviour_and_resume_drives_on(manager) -> None:
    hl, events = manager
    motion = Motion()
    mission = start(hl, lambda: Drive(motion))
    drive = mission.action

    assert hl.pause() is True
    paused_at = time.monotonic()
    # Once pause() returned: the action is in its safe state, still RUNNING (paused) and
    # still holds its type; the behaviour runs on; the manager says paused.
    assert drive.safe_calls == 1 and drive.status is Status.RUNNING
    assert hl.paused and hl.snapshot()["paused"] is True
    assert mission.status is Status.RUNNING and hl.current == "mission"
    assert hl.snapshot()["locks"]["driving"]["holder"] == drive.path
    time.sleep(0.3)
    assert motion.between(paused_at, time.monotonic()) == []
    (paused,) = kinds(events, EventKind.PAUSED)
    assert paused.detail["actions"] == [drive.path] and paused.detail["stuck"] == []

    sent = drive.sent
    assert hl.resume() is True
    assert not hl.paused
    assert wait_until(lambda: drive.sent > sent + 2)
    assert drive.runs == 2  # no hooks: run() again from the start, same object
    (resumed,) = kinds(events, EventKind.RESUMED)
    assert resumed.detail["by"] == "resume" and resumed.detail["paused_s"] >= 0.3


def test_pause_and_resume_are_idempotent_and_refused_after_shutdown() -> None:
    hl = HighLevelBehaviorManager(stop_timeout_s=0.3)
    with hl:
        assert hl.resume() is False
        assert hl.pause() is True and hl.pause() is False
        assert hl.resume() is True and hl.resume() is False
    with pytest.raises(ManagerShutdown, match="cannot pause"):
        hl.pause()


def test_time_stands_still_for_behaviours_while_paused() -> None:
    clock = VirtualClock()
    with no_thread_left("shutdown"):
        hl = HighLevelBehaviorManager(stop_timeout_s=0.3, clock=clock)
        with hl:
            motion = Motion()
            hl.register("mission", Mission, make=lambda: Drive(motion, period_s=0.5),
                        sleep_s=10.0)
            mission: Any = hl.switch("mission")
            clock.advance(4.0)
            hl.pause()
            clock.advance(100.0)  # paused: none of this counts for the behaviour
            assert mission.slept is None and hl.run_clock.now() == pytest.approx(4.0)
            assert mission.action.sent == 9  # 0, 0.5 … 4.0 s: nothing while paused
            hl.resume()
            clock.advance(5.9)
            assert mission.slept is None
            clock.advance(0.1)
            assert wait_until(lambda: mission.slept is not None)
            assert mission.slept == pytest.approx((0.0, 10.0))
            assert clock.now() == pytest.approx(110.0)


def test_an_action_with_hooks_keeps_its_thread_and_goes_on(manager) -> None:
    hl, events = manager
    motion = Motion()
    mission = start(hl, lambda: HookedDrive(motion))
    drive = mission.action
    hl.pause()
    paused_at = time.monotonic()
    assert drive.hooks == ["pause"] and drive.safe_calls == 0
    time.sleep(0.2)
    assert motion.between(paused_at, time.monotonic()) == []
    hl.resume()
    sent = drive.sent
    assert wait_until(lambda: drive.sent > sent + 2)
    assert drive.hooks == ["pause", "resume"] and drive.runs == 1


def test_an_action_that_ignores_the_pause_becomes_stuck_in_bounded_time(manager) -> None:
    hl, events = manager

    class Deaf(Action):
        action_type = "driving"

        def __init__(self) -> None:
            self.release = threading.Event()
            self.sent = 0
            self.safe = 0

        def run(self) -> None:
            while not self.release.is_set():
                self.sent += 1
                time.sleep(0.005)  # never looks at interrupted: a bug, not a pause

        def safe_state(self) -> None:
            self.safe += 1

    mission = start(hl, Deaf)
    deaf = mission.action
    began = time.monotonic()
    hl.pause()
    took = time.monotonic() - began
    assert deaf.status is Status.STUCK and deaf.safe == 1
    assert took < hl.stop_timeout_s + WALL_TIMEOUT_S  # bounded (the figure: benchmarks)
    (paused,) = kinds(events, EventKind.PAUSED)
    assert paused.detail["stuck"] == [deaf.path]
    deaf.release.set()
    assert wait_until(lambda: not deaf.alive)


def test_a_failing_on_pause_hook_falls_back_to_the_safe_state(manager) -> None:
    hl, events = manager
    motion = Motion()

    class Broken(HookedDrive):
        def on_pause(self) -> None:
            raise RuntimeError("hook broke")

    mission = start(hl, lambda: Broken(motion))
    hl.pause()
    assert mission.action.safe_calls == 1 and mission.action.status is Status.RUNNING
    (failed,) = kinds(events, EventKind.HOOK_FAILED)
    assert failed.detail == {"hook": "on_pause"} and "hook broke" in repr(failed.error)
    hl.resume()
    assert wait_until(lambda: mission.action.runs == 2)


def test_an_action_started_while_paused_waits_for_the_resume(manager) -> None:
    hl, _ = manager
    motion = Motion()
    mission = start(hl, lambda: Drive(motion))
    hl.pause()
    lifting = Drive(motion)
    lifting.action_type = "lifting"  # type: ignore[misc]
    mission.start_action(lifting)
    time.sleep(0.2)
    assert lifting.runs == 0 and lifting.status is Status.RUNNING
    # Its type is held all the same: nobody else can take it while paused.
    other = Drive(motion)
    other.action_type = "lifting"  # type: ignore[misc]
    with pytest.raises(ActionTypeBusy):
        mission.start_action(other)
    hl.resume()
    assert wait_until(lambda: lifting.sent > 2)
    assert lifting.safe_calls == 0


def test_a_switch_while_paused_ends_the_pause_and_restarts_nothing(manager) -> None:
    hl, events = manager
    motion = Motion()
    mission = start(hl, lambda: Drive(motion))
    drive = mission.action
    hl.pause()
    hl.switch("idle")
    assert not hl.paused and hl.current == "idle"
    assert drive.status is Status.INTERRUPTED and mission.status is Status.INTERRUPTED
    assert drive.safe_calls == 1 and drive.runs == 1  # safe once: the pause made it so
    (resumed,) = kinds(events, EventKind.RESUMED)
    assert resumed.detail["by"] == "switch"


def test_shutdown_while_paused_leaves_no_thread() -> None:
    motion = Motion()
    with no_thread_left("shutdown"):
        hl = HighLevelBehaviorManager(stop_timeout_s=0.3)
        hl.start()
        mission = start(hl, lambda: HookedDrive(motion))
        hl.pause()
        hl.shutdown()
    assert mission.action.status is Status.INTERRUPTED
    assert mission.status is Status.INTERRUPTED


def test_a_behaviour_may_pause_its_own_manager(manager) -> None:
    hl, events = manager
    motion = Motion()

    class SelfPausing(Behavior):
        def run(self) -> None:
            self.drive = self.start_action(Drive(motion))
            self.sleep(0.05)
            self.manager.pause()
            self.sleep(math_inf)

    math_inf = float("inf")
    hl.register("selfpausing", SelfPausing)
    behaviour: Any = hl.switch("selfpausing")
    assert wait_until(lambda: kinds(events, EventKind.PAUSED))
    assert behaviour.drive.safe_calls == 1 and hl.paused
    hl.resume()
    assert wait_until(lambda: behaviour.drive.runs == 2)


# ----------------------------------------------------------------------------- stress
class Storm(Behavior):
    """Keeps starting drives of random types; counts what its sleeps saw."""

    def __init__(self, motion: Motion, seed: int) -> None:
        self.motion, self.rng = motion, random.Random(seed)
        self.started: list[Drive] = []

    def run(self) -> None:
        while not self.interrupted:
            drive = Drive(self.motion, steps=self.rng.randint(1, 20), period_s=0.002)
            drive.action_type = self.rng.choice(["driving", "lifting", "sound"])  # type: ignore[misc]
            try:
                self.started.append(self.start_action(drive, preempt=self.rng.random() < 0.3))
            except (ActionTypeBusy, BeehaveError):
                pass
            try:
                self.sleep(self.rng.uniform(0, 0.003))
            except BeehaveError:
                pass


def test_storms_of_pause_resume_and_switch_keep_every_invariant() -> None:
    before = set(beehave_threads())
    motion = Motion()
    hl = HighLevelBehaviorManager(stop_timeout_s=0.3)
    marks: list[tuple[float, str, bool]] = []  # (when, paused/resumed, clean pause)

    def on_event(event: Event) -> None:
        if event.kind is EventKind.PAUSED:
            marks.append((time.monotonic(), "paused", not event.detail["stuck"]))
        elif event.kind is EventKind.RESUMED:
            marks.append((time.monotonic(), "resumed", True))

    hl.subscribe(on_event)
    for name in ("s1", "s2"):
        hl.register(name, Storm, motion=motion, seed=0)
    errors: list[BaseException] = []

    def operate(seed: int) -> None:
        rng = random.Random(seed)
        try:
            for _ in range(120):
                time.sleep(rng.uniform(0, 0.004))
                op = rng.random()
                try:
                    if op < 0.35:
                        hl.pause()
                    elif op < 0.7:
                        hl.resume()
                    else:
                        hl.switch(rng.choice(["s1", "s2", "idle"]), seed=rng.randrange(1000))
                except BeehaveError:
                    pass  # superseded switches
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    with hl:
        threads = [threading.Thread(target=operate, args=(i,)) for i in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        assert not any(t.is_alive() for t in threads)
        hl.resume()
        assert hl.current in ("s1", "s2", "idle") and not hl.paused
    assert not errors, errors
    assert wait_until(lambda: not [t for t in beehave_threads() if t not in before])
    # Never two of one type inside run() at once, pause or no pause.
    assert max(motion.most_inside.values()) == 1, motion.most_inside
    # No command between a pause that took effect (every action safe, none STUCK) and
    # the end of that pause (a resume, a switch or the shutdown).
    pauses = [(t, clean) for t, what, clean in marks if what == "paused"]
    ends = sorted(t for t, what, _ in marks if what == "resumed")
    assert len(pauses) > 10 and ends
    for began, clean in pauses:
        closing = next((t for t in ends if t > began), time.monotonic())
        if clean:
            assert motion.between(began, closing) == [], (began, closing)
