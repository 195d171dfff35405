"""Stress: many threads switching, starting, preempting and interrupting at random.

Invariants, checked on an instrumented timeline: never two actions of one type inside
``run`` or ``safe_state`` at once (a STUCK action's forced safe state included), never two
top-level behaviours running at once, ``safe_state`` exactly once per action that ended
without success (never after success), no thread left behind.
"""

from __future__ import annotations

import random
import threading
import time
from typing import Any

from beehave import ActionTypeBusy, BeehaveError, Behavior, HighLevelBehaviorManager, Status
from beehave.testing import ScriptedAction, Timeline, beehave_threads, wait_until, wall_timeout

TYPES = ["driving", "lifting", "sound", "leds"]
THREADS = 8
OPS_PER_THREAD = 260  # 8 × 260 = 2,080 operations


class World:
    def __init__(self, seed: int) -> None:
        self.timeline = Timeline()
        self.lock = threading.Lock()
        self.actions: list[ScriptedAction] = []
        self.top_active = 0
        self.top_max = 0
        self.rng = random.Random(seed)

    def action(self, rng: random.Random) -> ScriptedAction:
        roll = rng.random()
        ignore = 0.45 if roll < 0.004 else (0.01 if roll < 0.1 else 0.0)  # a few get STUCK
        raises = RuntimeError("scripted failure") if rng.random() < 0.05 else None
        # Some safe states take a while: the type stays locked until they have returned.
        safe_s = 0.02 if rng.random() < 0.05 else 0.0
        action = ScriptedAction(rng.choice(TYPES), duration_s=rng.uniform(0, 0.002),
                                ignore_interrupt_s=ignore, raises=raises,
                                timeline=self.timeline, safe_state_s=safe_s)
        with self.lock:
            self.actions.append(action)
        return action

    def top_enter(self) -> None:
        with self.lock:
            self.top_active += 1
            self.top_max = max(self.top_max, self.top_active)

    def top_exit(self) -> None:
        with self.lock:
            self.top_active -= 1


class Worker(Behavior):
    """A top-level behaviour that keeps starting random actions itself."""

    def __init__(self, world: World, seed: int) -> None:
        self.world = world
        self.rng = random.Random(seed)

    def run(self) -> None:
        self.world.top_enter()
        try:
            while not self.interrupted:
                try:
                    self.start_action(self.world.action(self.rng), preempt=self.rng.random() < 0.1)
                except (ActionTypeBusy, BeehaveError):
                    pass  # busy, or a child failure surfaced: both are expected here
                try:
                    self.sleep(self.rng.uniform(0, 0.002))
                except BeehaveError:
                    pass
        finally:
            self.world.top_exit()


def operate(hl: HighLevelBehaviorManager, world: World, seed: int,
            errors: list[BaseException]) -> None:
    rng = random.Random(seed)
    try:
        for _ in range(OPS_PER_THREAD):
            time.sleep(rng.uniform(0, 0.001))  # spread the operations over the run
            op = rng.random()
            top = hl.top
            try:
                if op < 0.15:
                    hl.switch(rng.choice(["w1", "w2", "w3", "idle"]), seed=rng.randrange(1 << 30)) \
                        if rng.random() < 0.9 else hl.switch("idle")
                elif op < 0.6 and top is not None:
                    top.start_action(world.action(rng), preempt=op < 0.35)
                elif top is not None:
                    running = [c for c in top.children if c.status is Status.RUNNING]
                    if running:
                        rng.choice(running).interrupt()
            except BeehaveError:
                pass  # superseded switches, busy types, interrupted tops: all legitimate
    except BaseException as exc:  # pragma: no cover - reported below
        errors.append(exc)


def test_random_operations_keep_every_invariant() -> None:
    before = set(beehave_threads())
    world = World(seed=2026)
    errors: list[BaseException] = []
    hl = HighLevelBehaviorManager(stop_timeout_s=0.3)
    for name in ("w1", "w2", "w3"):
        hl.register(name, Worker, world=world)
    hl.register("idle_plus", Worker, world=world, seed=0)
    with hl:
        threads = [threading.Thread(target=operate, args=(hl, world, i, errors))
                   for i in range(THREADS)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(wall_timeout(2.0))
        assert not any(t.is_alive() for t in threads)
        # Make sure the run contains a STUCK action whatever the interleaving was.
        top: Any = hl.switch("w1", seed=1)
        stubborn = ScriptedAction("docking", duration_s=30, ignore_interrupt_s=0.45,
                                  timeline=world.timeline, safe_state_s=0.2)
        world.actions.append(top.start_action(stubborn, preempt=True))
        final: Any = hl.switch("w2", seed=2)
        assert stubborn.status is Status.STUCK
        assert hl.current == "w2" and final.status is Status.RUNNING
    assert not errors, errors
    # STUCK actions end by themselves a little later; then nothing may be left.
    assert wait_until(lambda: not [t for t in beehave_threads() if t not in before])

    assert len(world.actions) > 800
    assert max(world.timeline.max_concurrent.values()) == 1, world.timeline.max_concurrent
    assert world.top_max == 1
    statuses = {s: 0 for s in Status}
    for action in world.actions:
        statuses[action.status] += 1
        if action.status is Status.PENDING:
            continue  # rejected before it started (busy type, interrupted parent)
        assert action.status.finished and not action.alive
        expected = 0 if action.status is Status.SUCCEEDED else 1
        assert action.safe_state_calls == expected, (action, action.safe_state_calls)
    assert statuses[Status.SUCCEEDED] and statuses[Status.INTERRUPTED] and statuses[Status.FAILED]
    assert statuses[Status.STUCK]
