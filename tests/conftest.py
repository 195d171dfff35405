"""Shared fixtures: a high-level manager that must leave no thread behind."""

from __future__ import annotations

import os
import random
from collections.abc import Iterator

import pytest

from beehave import Event, HighLevelBehaviorManager
from beehave.testing import beehave_threads

# ROS 2 isolation: only this machine, and a domain of our own for this test run (child
# processes inherit both).
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(1, 100)))


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
