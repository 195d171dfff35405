"""Engines to look at in the web view's graphs (and to measure it with): a delivery state
machine with a nested charging sub-machine, a patrol tree, and large ones (a 60-state
machine, a 300-node tree) for ``python -m benchmarks http``.

Nothing here moves a robot: the actions wait (``Wait``, action type ``waiting``) or
"drive" by waiting (``FakeDrive``, action type ``driving``)::

    hl.register("delivery", EngineBehavior, engine=delivery_machine())
    hl.register("patrol_tree", EngineBehavior, engine=patrol_tree())
"""

from __future__ import annotations

import py_trees

from beehave import Action
from beehave.engines import (
    BlackboardCheck,
    EngineBehavior,
    StartLeaf,
    State,
    StateMachineEngine,
    Transition,
    TreeEngine,
)

__all__ = ["FakeDrive", "Wait", "big_machine", "big_tree", "delivery_machine", "patrol_tree"]


class Wait(Action):
    """Waits ``seconds`` (default 0.5) and succeeds."""

    action_type = "waiting"
    seconds = 0.5

    def run(self) -> None:
        self.sleep(self.seconds)


class FakeDrive(Action):
    """Stands for a drive: waits ``seconds`` and succeeds."""

    action_type = "driving"
    seconds = 0.8

    def run(self) -> None:
        self.sleep(self.seconds)


def _charging() -> EngineBehavior:
    machine = StateMachineEngine(
        states=[State("dock", start=FakeDrive), State("charge", start=Wait),
                State("undock", start=FakeDrive), State("charged", final=True)],
        transitions=[Transition("dock", "charge", on="succeeded"),
                     Transition("charge", "undock", on="succeeded"),
                     Transition("undock", "charged", on="succeeded")],
        initial="dock")
    return EngineBehavior(machine, name="charging")


def delivery_machine() -> StateMachineEngine:
    """pick → drop → (battery low? charge, a nested machine) → pick …; ``abort`` ends it."""
    return StateMachineEngine(
        states=[State("to_pick", start=FakeDrive), State("pick", start=Wait),
                State("to_drop", start=FakeDrive), State("drop", start=Wait),
                State("charge", start=_charging), State("done", final=True)],
        transitions=[
            Transition("to_pick", "pick", on="succeeded"),
            Transition("pick", "to_drop", on="succeeded"),
            Transition("to_drop", "drop", on="succeeded"),
            Transition("drop", "charge", on="succeeded", when="battery/percentage < 20"),
            Transition("drop", "to_pick", on="succeeded"),
            Transition("charge", "to_pick", on="succeeded"),
            Transition("*", "done", on="abort")],
        initial="to_pick", events=["abort"])


def patrol_tree() -> TreeEngine:
    """A selector: charge when the battery is low, else patrol three waypoints."""
    root = py_trees.composites.Selector("root", memory=False, children=[
        py_trees.composites.Sequence("charge?", memory=True, children=[
            BlackboardCheck("battery low", "battery/percentage < 20"),
            StartLeaf("dock", FakeDrive)]),
        py_trees.composites.Sequence("patrol", memory=True, children=[
            StartLeaf("to A", FakeDrive), StartLeaf("look", Wait),
            StartLeaf("to B", FakeDrive), StartLeaf("to C", FakeDrive)]),
    ])
    return TreeEngine(root, rate_hz=20)


def big_tree(nodes: int = 300, *, fanout: int = 4) -> TreeEngine:
    """A tree of ``nodes`` nodes (sequences of ``fanout`` children, Wait leaves) that runs
    for ever: the root is a Parallel whose leaves keep restarting."""
    count = 1
    leaves: list[py_trees.behaviour.Behaviour] = []

    def grow(depth: int) -> py_trees.behaviour.Behaviour:
        nonlocal count
        children: list[py_trees.behaviour.Behaviour] = []
        for _ in range(fanout):
            if count >= nodes:
                break
            count += 1
            if depth >= 3 or count >= nodes - fanout:
                leaf = StartLeaf(f"wait {count}", Wait)
                leaves.append(leaf)
                children.append(leaf)
            else:
                children.append(grow(depth + 1))
        return py_trees.composites.Sequence(f"seq {count}", memory=False,
                                            children=children)

    tops = []
    while count < nodes:
        tops.append(grow(1))
    root = py_trees.composites.Parallel(
        "root", policy=py_trees.common.ParallelPolicy.SuccessOnAll(synchronise=False),
        children=[py_trees.decorators.Repeat(f"repeat {i}", child=t, num_success=-1)
                  for i, t in enumerate(tops)])
    return TreeEngine(root, rate_hz=20)


def big_machine(states: int = 60) -> StateMachineEngine:
    """A ring of ``states`` states, each waiting a short while, with a condition shortcut
    every fifth state and an ``abort`` event: it runs for ever."""
    names = [f"s{i:02d}" for i in range(states)]
    transitions = [Transition(names[i], names[(i + 1) % states], on="succeeded")
                   for i in range(states)]
    transitions += [Transition(names[i], names[(i + 7) % states],
                               when=f"shortcut/{i} == true") for i in range(0, states, 5)]
    transitions.append(Transition("*", "stop", on="abort"))

    class Quick(Wait):
        seconds = 0.05

    return StateMachineEngine(
        states=[State(n, start=Quick) for n in names] + [State("stop", final=True)],
        transitions=transitions, initial=names[0], events=["abort"])
