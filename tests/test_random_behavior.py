"""RandomBehavior: seeded, reproducible random decisions for soak tests."""

from __future__ import annotations

import random

from beehave import HighLevelBehaviorManager, Status
from beehave.testing import WALL_TIMEOUT_S, ScriptedAction, Timeline, wait_until
from behaviours.behaviors import RandomBehavior

TIMELINE = Timeline()


def drive(rng: random.Random) -> ScriptedAction:
    return ScriptedAction("driving", duration_s=rng.uniform(0.0, 0.02), timeline=TIMELINE)


def beep(rng: random.Random) -> ScriptedAction:
    return ScriptedAction("sound", duration_s=0.005)


def broken(rng: random.Random) -> ScriptedAction:
    return ScriptedAction("lifting", raises=ValueError("jammed"))


def test_the_same_seed_makes_the_same_decisions(hl: HighLevelBehaviorManager) -> None:
    choices = {"drive": drive, "beep": beep}
    histories = []
    for _ in range(2):
        hl.register("random", RandomBehavior, choices=choices, seed=7, steps=12,
                    hold_s=(0.0, 0.01))
        behavior = hl.switch("random")
        assert behavior.wait(WALL_TIMEOUT_S) and behavior.status is Status.SUCCEEDED
        assert isinstance(behavior, RandomBehavior)
        histories.append([step.choice for step in behavior.history])
    assert histories[0] == histories[1] == RandomBehavior(choices, seed=7).plan(12)
    assert RandomBehavior(choices, seed=8).plan(12) != histories[0]


def test_failures_are_recorded_not_raised(hl: HighLevelBehaviorManager) -> None:
    hl.register("random", RandomBehavior, choices={"broken": broken, "beep": beep}, seed=1,
                steps=10, hold_s=(1.0, 2.0))
    behavior = hl.switch("random")
    assert behavior.wait(WALL_TIMEOUT_S) and behavior.status is Status.SUCCEEDED
    assert isinstance(behavior, RandomBehavior)
    statuses = {step.choice: step.status for step in behavior.history}
    assert statuses == {"broken": "FAILED", "beep": "SUCCEEDED"}
    assert behavior.result == {"FAILED": sum(s.choice == "broken" for s in behavior.history),
                               "SUCCEEDED": sum(s.choice == "beep" for s in behavior.history)}


def test_an_endless_soak_stops_cleanly_on_switch(hl: HighLevelBehaviorManager) -> None:
    long = {"drive": lambda rng: ScriptedAction("driving", duration_s=30)}
    hl.register("soak", RandomBehavior, choices=long, seed=3, hold_s=(10.0, 20.0))
    behavior = hl.switch("soak")
    assert wait_until(lambda: bool(behavior.children))
    (action,) = behavior.children
    hl.switch("idle")
    assert behavior.status is Status.INTERRUPTED
    assert action.status is Status.INTERRUPTED
