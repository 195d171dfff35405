"""Shared fixtures: a high-level manager that must leave no thread behind."""

from __future__ import annotations

import importlib
import os
import random
from collections.abc import Iterator
from types import ModuleType
from typing import Any

import pytest

from beehave import Event, HighLevelBehaviorManager
from beehave.testing import no_thread_left

# ROS 2 isolation: only this machine, and a domain of our own for this test run and this
# pytest-xdist worker (child processes inherit both). The workers of one run share a seed
# (PYTEST_XDIST_TESTRUNUID), so they take consecutive domains and never the same one; the
# benchmarks use 101-200. BEEHAVE_TEST_DOMAINS=LO-HI moves a run into another range, so
# that two suites on one machine (e.g. `make test-stress` beside development) never meet.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
_SEED = os.environ.get("PYTEST_XDIST_TESTRUNUID", str(os.getpid()))
_LO, _HI = (int(n) for n in os.environ.get("BEEHAVE_TEST_DOMAINS", "1-100").split("-"))
_SPAN = min(16, _HI - _LO + 1)
_DOMAIN = str(random.Random(_SEED).randint(_LO, _HI - _SPAN + 1)
              + int(_WORKER.removeprefix("gw")) % _SPAN)
if "PYTEST_XDIST_WORKER" in os.environ:
    # A worker inherits the controller's environment: its own domain replaces that one.
    os.environ["ROS_DOMAIN_ID"] = _DOMAIN
else:
    os.environ.setdefault("ROS_DOMAIN_ID", _DOMAIN)

if os.environ.get("BEEHAVE_REQUIRE_EXTRAS") == "1":
    # `make test` installs every extra: a missing rclpy or pybullet there is a broken
    # set-up, and a skipped ROS or physics test would hide it. Outside it (a bare checkout
    # without extras), those tests are skipped as usual.
    def _require(modname: str, *args: Any, **kwargs: Any) -> ModuleType:
        try:
            return importlib.import_module(modname)
        except ImportError as exc:
            pytest.fail(f"{modname} is not importable although `make test` installs every "
                        f"extra (BEEHAVE_REQUIRE_EXTRAS=1): {exc}", pytrace=False)

    pytest.importorskip = _require  # type: ignore[assignment]


@pytest.fixture
def hl() -> Iterator[HighLevelBehaviorManager]:
    """A started manager with a short stop timeout; checks that nothing leaks."""
    with no_thread_left("shutdown"):
        manager = HighLevelBehaviorManager(stop_timeout_s=0.3)
        manager.start()
        try:
            yield manager
        finally:
            manager.shutdown()


@pytest.fixture
def events(hl: HighLevelBehaviorManager) -> list[Event]:
    received: list[Event] = []
    hl.subscribe(received.append)
    return received
