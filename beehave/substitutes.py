"""Substitution rules: run a scripted stand-in instead of an action, behaviour or logic, by
name, without changing the code that starts it (BehaviorTree.CPP's substitution rules).

A rule is an ``fnmatch`` pattern and a *substitute*: a callable that the manager calls with
the object just before it starts. The substitute replaces what runs — typically the object's
``run`` (and an action's ``safe_state``) — and keeps the object itself, so the behaviour
that started it gets the same handle back, with its own attributes. The ready-made
substitute is :class:`beehave.testing.Scripted`; the managers' entry points are
``HighLevelBehaviorManager.substitute`` and ``LowLevelBehaviorManager.substitute``, and a
robot YAML may list rules under ``substitutes:``.

A pattern matches an object when it matches its path (``tour/Navigate``), its name
(``Navigate``) or its class name; the first rule that matches wins.
"""

from __future__ import annotations

import fnmatch
import threading
from collections.abc import Callable
from typing import Any

from beehave.errors import ConfigError

Substitute = Callable[[Any], None]


class Substitutions:
    """The rules of one manager (thread-safe; empty costs one attribute read per start)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._rules: tuple[tuple[str, Substitute], ...] = ()

    def add(self, pattern: str, substitute: Substitute) -> Callable[[], None]:
        """Add a rule; returns a function that removes it again."""
        if not isinstance(pattern, str) or not pattern:
            raise ConfigError(f"a substitution pattern must be a non-empty str, got {pattern!r}")
        if not callable(substitute):
            raise ConfigError(f"substitute for {pattern!r} must be callable with the object "
                              f"to replace (e.g. beehave.testing.Scripted(...)), got "
                              f"{substitute!r}")
        rule = (pattern, substitute)
        with self._lock:
            self._rules = (*self._rules, rule)

        def remove() -> None:
            with self._lock:
                self._rules = tuple(r for r in self._rules if r is not rule)
        return remove

    @property
    def patterns(self) -> list[str]:
        return [p for p, _ in self._rules]

    def apply(self, obj: Any, *, path: str) -> bool:
        """Let the first matching rule replace ``obj``'s work; True when one did."""
        rules = self._rules
        if not rules:
            return False
        names = (path, getattr(obj, "name", ""), type(obj).__name__)
        for pattern, substitute in rules:
            if any(fnmatch.fnmatchcase(n, pattern) for n in names if n):
                substitute(obj)
                return True
        return False
