"""Decision engines: state machine, behaviour tree and neural network behind one interface.

Importing this package imports none of transitions, py_trees or torch; import the engine
module you use (``beehave.engines.state_machine``, ``.tree``, ``.neural``), or take the
names from here, which imports the module on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from beehave.engines.engine import (
    BlackboardCondition,
    Condition,
    DecisionEngine,
    EngineBehavior,
    EngineContext,
    Starter,
    as_starter,
    parse_condition,
)
from beehave.engines.errors import (
    DecisionFailed,
    EngineBusy,
    EngineConfigError,
    EngineError,
    MissingExtra,
    NotRenderable,
    TreeFailed,
    UnhandledOutcome,
    UnknownEvent,
)

if TYPE_CHECKING:
    from beehave.engines.neural import DecisionCondition, Feature, NeuralEngine, NeuralPolicy
    from beehave.engines.state_machine import State, StateMachineEngine, Transition
    from beehave.engines.tree import BlackboardCheck, StartLeaf, TreeEngine

_LAZY = {
    "State": "state_machine", "Transition": "state_machine",
    "StateMachineEngine": "state_machine",
    "TreeEngine": "tree", "StartLeaf": "tree", "BlackboardCheck": "tree",
    "NeuralEngine": "neural", "NeuralPolicy": "neural", "Feature": "neural",
    "DecisionCondition": "neural",
}

__all__ = [
    "BlackboardCheck", "BlackboardCondition", "Condition", "DecisionCondition",
    "DecisionEngine", "DecisionFailed", "EngineBehavior", "EngineBusy", "EngineConfigError",
    "EngineContext", "EngineError", "Feature", "MissingExtra", "NeuralEngine", "NeuralPolicy",
    "NotRenderable", "StartLeaf", "Starter", "State", "StateMachineEngine", "Transition",
    "TreeEngine", "TreeFailed", "UnhandledOutcome", "UnknownEvent", "as_starter",
    "parse_condition",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'beehave.engines' has no attribute {name!r}")
    return getattr(importlib.import_module(f"beehave.engines.{module}"), name)
