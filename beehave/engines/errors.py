"""Errors of the decision engines; all derive from :class:`beehave.errors.BeehaveError`.

Messages name the engine, the state or tree node, and for a bad name what exists.
"""

from __future__ import annotations

from collections.abc import Iterable

from beehave.errors import BeehaveError, ConfigError, UnknownNameError


class EngineError(BeehaveError):
    """Root of the decision-engine errors."""


class MissingExtra(EngineError, ImportError):
    """An optional dependency of an engine is not installed; the message names the extra."""


class EngineBusy(EngineError):
    """One engine object drives one behaviour at a time; build a second engine instead."""


class EngineConfigError(EngineError, ConfigError):
    """A state machine, tree or network definition that is not valid (unknown state,
    missing initial state, bad condition …). The message names the key path or state."""


class UnknownEvent(EngineError, UnknownNameError):
    """``machine.post(name)`` with a name that no transition of the machine uses, or a
    built-in outcome (the engine fires those itself). ``.choices`` lists the events the
    machine declares."""

    kind = "event"

    def __init__(self, name: str, choices: Iterable[str], *, message: str) -> None:
        super().__init__(name, choices)
        self.args = (message,)


class UnhandledOutcome(EngineError):
    """What a state started failed (or got stuck) and no transition handles that outcome.

    ``.state`` is the state, ``.outcome`` the trigger (``"failed"``, ``"stuck"``); the
    failed handle's error is the ``__cause__``.
    """

    def __init__(self, message: str, *, state: str, outcome: str) -> None:
        super().__init__(message)
        self.state = state
        self.outcome = outcome


class TreeFailed(EngineError):
    """The behaviour tree's root returned FAILURE. ``.node`` names the failing leaf, the
    failed action's error (if one failed) is the ``__cause__``."""

    def __init__(self, message: str, *, node: str) -> None:
        super().__init__(message)
        self.node = node


class DecisionFailed(EngineError):
    """What a network decision started failed. ``.decision`` names it."""

    def __init__(self, message: str, *, decision: str) -> None:
        super().__init__(message)
        self.decision = decision


class NotRenderable(EngineError):
    """``beehave graph`` was given something that has no state machine or tree to draw."""
