"""Shared fixtures: a high-level manager that must leave no thread behind."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from beehave import Event, HighLevelBehaviorManager
from beehave.testing import beehave_threads


@pytest.fixture
def hl() -> Iterator[HighLevelBehaviorManager]:
    """A started manager with a short stop timeout; checks that nothing leaks."""
    before = set(beehave_threads())
    manager = HighLevelBehaviorManager(stop_timeout_s=0.3)
    manager.start()
    try:
        yield manager
    finally:
        manager.shutdown()
    leaked = [t for t in beehave_threads() if t not in before]
    assert not leaked, f"threads left after shutdown: {leaked}"


@pytest.fixture
def events(hl: HighLevelBehaviorManager) -> list[Event]:
    received: list[Event] = []
    hl.subscribe(received.append)
    return received
