"""Neural network engine: the engine contract, online learning, training thread, weights."""

from __future__ import annotations

import random
import threading
from pathlib import Path

import pytest

from beehave import HighLevelBehaviorManager
from beehave.engines import (
    DecisionEngine,
    EngineConfigError,
    MissingExtra,
    State,
    StateMachineEngine,
    Transition,
)
from beehave.engines.engine import StartLike
from beehave.engines.neural import NeuralEngine, NeuralPolicy
from beehave.testing import WALL_TIMEOUT_S, beehave_threads, wait_until
from tests.engine_contract import EngineContract, Recorder, run


def fixed_policy(feature: str) -> NeuralPolicy:
    """A fixed network: decision 0 when the feature is above 0.5, else decision 1. (torch
    is imported here, not at collection: importing it costs every pytest-xdist worker 2 s
    of CPU, and only the one that runs these tests needs it.)"""
    import torch

    class Threshold(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return torch.cat([x - 0.5, 0.5 - x], dim=1)

    return NeuralPolicy([feature], ["yes", "no"], model=Threshold())


class TestNeuralContract(EngineContract):
    description_kind = "neural_network"

    def check_description_while_running(self, described: dict[str, object]) -> None:
        assert described["last_decision"] == "no" and described["running"] == "long"
        assert described["decisions"] == ["yes", "no"] and described["training"] is False

    def single(self, start: StartLike) -> DecisionEngine:
        # The missing key reads as 0.0 → "no", which is mapped to the action.
        return NeuralEngine(fixed_policy("unset/key"), {"no": start}, on_success="return",
                            rate_hz=200)

    def choice(self, key: str, if_true: StartLike, if_false: StartLike) -> DecisionEngine:
        return NeuralEngine(fixed_policy(key), {"yes": if_true, "no": if_false},
                            on_success="return", rate_hz=200)


def toy_point(rng: random.Random) -> tuple[list[float], str]:
    """A separable toy problem: charge when battery < 0.2 + 0.5 · distance."""
    battery, distance = rng.random(), rng.random()
    return [battery, distance], "charge" if battery < 0.2 + 0.5 * distance else "patrol"


def test_reaches_95_percent_agreement_within_bounded_online_steps() -> None:
    rng = random.Random(1)
    policy = NeuralPolicy(["battery", "distance"], ["patrol", "charge"], hidden=(16,),
                          learning_rate=0.02, seed=1)
    window: list[bool] = []
    reached_at = None
    for step in range(3000):
        features, label = toy_point(rng)
        window.append(policy.decide_features(features) == label)  # predict, then learn
        window = window[-200:]
        policy.add_example(features, label)
        policy.train_step()
        if len(window) == 200 and sum(window) / 200 >= 0.95:
            reached_at = step
            break
    assert reached_at is not None, f"agreement stuck at {sum(window) / len(window):.2%}"
    held_out = [toy_point(rng) for _ in range(500)]
    agreement = sum(policy.decide_features(f) == y for f, y in held_out) / len(held_out)
    assert agreement >= 0.95


def test_background_training_learns_and_its_thread_is_joined() -> None:
    rng = random.Random(2)
    policy = NeuralPolicy(["battery", "distance"], ["patrol", "charge"], learning_rate=0.02,
                          steps_per_example=2)
    trainer = policy.start_training(name="beehave:nn-train:test")
    try:
        for _ in range(1500):
            policy.add_example(*toy_point(rng))
        assert wait_until(lambda: policy.steps >= 1000)
    finally:
        trainer.stop()
    assert not trainer.thread.is_alive()
    assert not [t for t in beehave_threads() if t.name.startswith("beehave:nn-train")]
    held_out = [toy_point(rng) for _ in range(300)]
    assert sum(policy.decide_features(f) == y for f, y in held_out) / 300 >= 0.9


def test_a_decision_never_waits_for_training() -> None:
    policy = NeuralPolicy(["x"], ["a", "b"])
    decided = threading.Event()
    with policy._train_lock:  # a training step in progress
        def decide() -> None:
            policy.decide_features([0.3])
            decided.set()

        worker = threading.Thread(target=decide)
        worker.start()
        assert decided.wait(WALL_TIMEOUT_S)
    worker.join()


def test_rewards_shift_the_decision() -> None:
    policy = NeuralPolicy(["x"], ["left", "right"], learning_rate=0.05)
    for _ in range(200):
        policy.add_reward([1.0], "left", -1.0)
        policy.add_reward([1.0], "right", +1.0)
        policy.train_step()
    assert policy.decide_features([1.0]) == "right"


def test_weights_round_trip_and_mismatches_are_refused(tmp_path: Path) -> None:
    rng = random.Random(3)
    trained = NeuralPolicy(["battery", "distance"], ["patrol", "charge"], seed=3)
    for _ in range(300):
        trained.add_example(*toy_point(rng))
        trained.train_step()
    path = tmp_path / "charging.pt"
    trained.save(path)
    loaded = NeuralPolicy(["battery", "distance"], ["patrol", "charge"], seed=99, weights=path)
    probes = [toy_point(rng)[0] for _ in range(50)]
    assert [loaded.decide_features(p) for p in probes] == [
        trained.decide_features(p) for p in probes]
    with pytest.raises(EngineConfigError, match=r"charging\.pt: weights are for features"):
        NeuralPolicy(["battery"], ["patrol", "charge"], weights=path)


def test_engine_owns_its_training_thread_and_learns_from_a_teacher(
        hl: HighLevelBehaviorManager) -> None:
    policy = NeuralPolicy(["go"], ["wait", "work"])
    hl.blackboard.set("go", 1.0)
    engine = NeuralEngine(policy, {"work": Recorder("w", duration_s=30), "wait": None},
                          rate_hz=200, teacher=lambda bb: "work" if bb.get("go") else "wait")
    run(hl, engine)
    assert wait_until(lambda: policy.steps >= 20)
    assert any(t.name.startswith("beehave:nn-train:") for t in beehave_threads())
    hl.switch("idle")
    assert not [t for t in beehave_threads() if t.name.startswith("beehave:nn-train")]


def test_a_network_decision_guards_a_state_machine(hl: HighLevelBehaviorManager) -> None:
    policy = fixed_policy("battery/low")
    hl.blackboard.set("battery/low", 1.0)
    machine = StateMachineEngine(
        [State("patrol"), State("charge", final=True)],
        [Transition("patrol", "charge", when=policy.condition("yes"))], initial="patrol")
    behavior = run(hl, machine)
    assert behavior.wait(WALL_TIMEOUT_S) and behavior.result == "charge"


def test_unknown_decisions_are_named() -> None:
    policy = fixed_policy("x")
    with pytest.raises(EngineConfigError, match="unknown decision.*'maybe'.*'yes', 'no'"):
        policy.condition("maybe")
    with pytest.raises(EngineConfigError, match=r"unknown decision\(s\) \['fly'\]"):
        NeuralEngine(policy, {"fly": Recorder("f")})


def test_missing_torch_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib

    from beehave.engines import neural

    real = importlib.import_module

    def no_torch(name: str, package: str | None = None) -> object:
        if name == "torch":
            raise ImportError("No module named 'torch'")
        return real(name, package)

    monkeypatch.setattr(importlib, "import_module", no_torch)
    with pytest.raises(MissingExtra, match=r"pip install 'beehave-robotics\[nn\]'"):
        neural.NeuralPolicy(["x"], ["a", "b"])


def test_importing_beehave_imports_no_engine_dependency() -> None:
    import subprocess
    import sys

    code = ("import beehave, beehave.engines, sys; "
            "print([m for m in ('torch', 'py_trees', 'transitions') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"


def test_network_decisions_as_guards_are_exclusive_in_the_cycle_check() -> None:
    policy = fixed_policy("battery")
    states = [State("patrol"), State("charge")]
    exclusive = StateMachineEngine(states, [
        Transition("patrol", "charge", when=policy.condition("no")),
        Transition("charge", "patrol", when=policy.condition("yes"))], initial="patrol")
    assert exclusive.warnings == []
    same = StateMachineEngine(states, [
        Transition("patrol", "charge", when=policy.condition("no")),
        Transition("charge", "patrol", when=policy.condition("no"))], initial="patrol")
    (warning,) = same.warnings
    assert "may loop" in warning and "nn: no" in warning
