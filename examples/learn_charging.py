"""A network learns online to imitate a state machine's decision of when to go charging.

The teacher is a beehave state machine: it patrols, and goes charging when the battery is
below a threshold that grows with the distance to the dock (``battery < 20 % + 5 %/m``).
The world jumps to a random battery level and dock distance each step; the state machine
decides (its blackboard conditions wake it), and the network — which sees the same two
blackboard keys — first predicts the decision, then learns from it in its background
training thread. Agreement over the last 200 decisions is printed as it goes.

Run: ``python examples/learn_charging.py`` (about ten seconds, no robot needed).
"""

from __future__ import annotations

import random
import sys
import threading
import time
from collections import deque
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from beehave import Action, HighLevelBehaviorManager  # noqa: E402
from beehave.engines import EngineBehavior, State, StateMachineEngine, Transition  # noqa: E402
from beehave.engines.engine import Readable  # noqa: E402
from beehave.engines.neural import Feature, NeuralPolicy  # noqa: E402

STEPS = 3000
WINDOW = 200


guard_tick = [-1]  # the world tick the teacher's guard last saw


def needs_charge(board: Readable) -> bool:
    """The teacher's rule, as a state-machine guard."""
    # The world writes the tick after both features: reading it first means the features
    # read next belong to that tick (or it is not labelled yet).
    guard_tick[0] = board.get("world/tick", -1)
    return bool(board.get("battery/percentage", 100.0)
                < 20.0 + 5.0 * board.get("dock/distance_m", 0.0))


class Hold(Action):
    """Stands in for patrolling or charging: runs until interrupted."""

    action_type = "driving"

    def run(self) -> None:
        while self.sleep(60):
            pass


def main() -> int:
    labelled = threading.Condition()
    seen: dict[str, object] = {"tick": -1, "state": None}

    def on_step(machine: StateMachineEngine) -> None:
        # Called in the state machine's thread after each decision step.
        with labelled:
            seen["tick"] = guard_tick[0]
            seen["state"] = machine.state
            labelled.notify_all()

    teacher = StateMachineEngine(
        [State("patrol", start=Hold), State("charge", start=Hold)],
        [Transition("patrol", "charge", when=needs_charge),
         Transition("charge", "patrol", unless=needs_charge)],
        initial="patrol", on_step=on_step)
    student = NeuralPolicy([Feature("battery/percentage", scale=0.01),
                            Feature("dock/distance_m", scale=0.1)],
                           ["patrol", "charge"], hidden=(16,), learning_rate=0.02,
                           steps_per_example=2, seed=0)
    rng = random.Random(0)
    window: deque[bool] = deque(maxlen=WINDOW)
    report: list[tuple[int, float]] = []
    t0 = time.monotonic()
    with HighLevelBehaviorManager(stop_timeout_s=1.0) as hl:
        board = hl.blackboard
        hl.register("teacher", EngineBehavior, engine=teacher)
        hl.switch("teacher")
        trainer = student.start_training(name="beehave:nn-train:example")
        try:
            for tick in range(STEPS):
                board.set("battery/percentage", rng.uniform(0.0, 100.0))
                board.set("dock/distance_m", rng.uniform(0.0, 10.0))
                board.set("world/tick", tick)  # last: the machine has seen both features
                with labelled:
                    if not labelled.wait_for(lambda t=tick: seen["tick"] == t,  # type: ignore[misc]
                                             timeout=5.0):
                        print("the state machine did not decide in time")
                        return 1
                    decision = str(seen["state"])
                features = student.featurize(board)
                window.append(student.decide_features(features) == decision)
                student.add_example(features, decision)
                if (tick + 1) % WINDOW == 0:
                    agreement = sum(window) / len(window)
                    report.append((tick + 1, agreement))
                    print(f"step {tick + 1:5d}  agreement over the last {WINDOW}: "
                          f"{agreement:6.1%}  (training steps: {student.steps})", flush=True)
        finally:
            trainer.stop()
    final = report[-1][1]
    print(f"done in {time.monotonic() - t0:.1f} s; final agreement {final:.1%}")
    return 0 if final >= 0.95 else 1


if __name__ == "__main__":
    raise SystemExit(main())
