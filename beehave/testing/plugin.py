"""beehave's pytest plugin (entry point ``pytest11: beehave``): loaded by pytest whenever
beehave is installed. Fixtures:

=================  =========================================================================
``clock``          a :class:`~beehave.clock.VirtualClock` at 0, moved by hand
                   (``@pytest.mark.beehave_clock(autojump=True)``: by itself)
``blackboard``     a :class:`~beehave.Blackboard` whose ages follow ``clock``
``high_level``     a started :class:`~beehave.HighLevelBehaviorManager` on ``clock`` and
                   ``blackboard``; shut down after the test, which fails if a thread is left
``low_level``      a running :class:`~beehave.LowLevelBehaviorManager` (its loop in its own
                   thread) on ``clock`` and ``blackboard``
``debug_robot``    both levels, with the Debug HAL on an in-memory
                   :class:`~hal.debug.DebugRobot` (``debug_robot.hardware``)
``robot_factory``  ``robot_factory("robot.yaml", substitutes={...})``: the behaviours, logics
                   and HALs of a robot YAML on ``clock``, without ROS
``sim``            ``sim("warehouse")``: a pybullet world stepped in lockstep with ``clock``
``event_log``      an :class:`~beehave.testing.EventLog` of ``high_level`` and ``low_level``
``replay_check``   ``replay_check("run.mcap", "robot.yaml")``: replays a reference recording
                   and fails on the first divergence
=================  =========================================================================

Marker ``beehave_clock(autojump=False, start_s=0.0)`` configures ``clock``; marker
``beehave_stop_timeout(seconds)`` the managers' ``stop_timeout_s`` (default 1.0, wall time).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from beehave.blackboard import Blackboard
from beehave.clock import VirtualClock
from beehave.highlevel import HighLevelBehaviorManager
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.testing.assertions import EventLog
from beehave.testing.fakes import no_thread_left


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "beehave_clock(autojump=False, start_s=0.0): how the `clock` fixture moves")
    config.addinivalue_line(
        "markers", "beehave_stop_timeout(seconds): stop_timeout_s of the fixtures' managers")


def _stop_timeout_s(request: pytest.FixtureRequest) -> float:
    marker = request.node.get_closest_marker("beehave_stop_timeout")
    return float(marker.args[0]) if marker is not None else 1.0


@pytest.fixture
def clock(request: pytest.FixtureRequest) -> Iterator[VirtualClock]:
    """Virtual time for the managers of this test: ``clock.advance(600)`` runs ten minutes
    of behaviours in milliseconds, the same on a loaded machine."""
    marker = request.node.get_closest_marker("beehave_clock")
    options = dict(marker.kwargs) if marker is not None else {}
    virtual = VirtualClock(options.pop("start_s", 0.0), autojump=options.pop("autojump", False))
    if options:
        raise pytest.UsageError(f"beehave_clock: unknown option(s) {sorted(options)}; "
                                f"valid: autojump, start_s")
    try:
        yield virtual
    finally:
        virtual.close()


@pytest.fixture
def blackboard(clock: VirtualClock) -> Blackboard:
    return Blackboard(clock=clock.now)


@pytest.fixture
def high_level(request: pytest.FixtureRequest, clock: VirtualClock,
               blackboard: Blackboard) -> Iterator[HighLevelBehaviorManager]:
    with no_thread_left("the high level's shutdown"):
        manager = HighLevelBehaviorManager(clock=clock, blackboard=blackboard,
                                           stop_timeout_s=_stop_timeout_s(request))
        manager.start()
        try:
            yield manager
        finally:
            manager.shutdown()


@pytest.fixture
def low_level(request: pytest.FixtureRequest, clock: VirtualClock,
              blackboard: Blackboard) -> Iterator[LowLevelBehaviorManager]:
    with LowLevelBehaviorManager(clock=clock, blackboard=blackboard,
                                 stop_timeout_s=_stop_timeout_s(request)) as manager:
        yield manager


@pytest.fixture
def event_log(high_level: HighLevelBehaviorManager,
           low_level: LowLevelBehaviorManager, clock: VirtualClock) -> Iterator[EventLog]:
    log = EventLog(high_level, low_level, clock=clock)
    try:
        yield log
    finally:
        log.close()


@dataclass
class DebugRobotFixture:
    """What ``debug_robot`` gives: both managers, their blackboard and clock, and the
    in-memory hardware the Debug HAL drives (``hardware.set_battery(15.0)``)."""

    high: HighLevelBehaviorManager
    low: LowLevelBehaviorManager
    blackboard: Blackboard
    clock: VirtualClock
    hardware: Any


@pytest.fixture
def debug_robot(high_level: HighLevelBehaviorManager, low_level: LowLevelBehaviorManager,
                blackboard: Blackboard, clock: VirtualClock) -> DebugRobotFixture:
    from hal.debug import DebugHAL, DebugRobot

    hardware = DebugRobot()
    low_level.hals.register(DebugHAL, robot=hardware)
    return DebugRobotFixture(high_level, low_level, blackboard, clock, hardware)


@dataclass
class BuiltRobot:
    """A robot YAML's managers on the test's clock, without ROS (``robot_factory``)."""

    high: HighLevelBehaviorManager
    low: LowLevelBehaviorManager
    blackboard: Blackboard
    clock: VirtualClock
    config: Any


@pytest.fixture
def robot_factory(request: pytest.FixtureRequest, clock: VirtualClock
                  ) -> Iterator[Callable[..., BuiltRobot]]:
    """``robot_factory(path_or_config, substitutes=None, hals=None)``: the behaviours,
    logics and HALs of a robot YAML on the test's clock, both levels sharing one
    blackboard, started (the default behaviour and logic run), without ROS.

    ``substitutes`` adds substitution rules to the YAML's (``{"tour/Navigate": Scripted(…)}``);
    ``hals`` registers stand-ins by name (``{"lift": ScriptedHAL}`` or
    ``{"lift": (ScriptedHAL, {"values": {...}})}``)."""
    from beehave.robot import Robot

    started: list[BuiltRobot] = []

    def build(config: Any, *, substitutes: dict[str, Any] | None = None,
              hals: dict[str, Any] | None = None) -> BuiltRobot:
        from beehave.config import RobotConfig, load_config

        cfg = config if isinstance(config, RobotConfig) else load_config(Path(config))
        robot = Robot(cfg, clock=clock)
        high, low = robot.high, robot.low
        assert high is not None and low is not None
        for name, spec in (hals or {}).items():
            cls, params = spec if isinstance(spec, tuple) else (spec, {})
            low.hals.register(cls, name=name, **params)
        for pattern, substitute in (substitutes or {}).items():
            high.substitute(pattern, substitute)
            low.substitute(pattern, substitute)
        low.__enter__()
        try:
            high.start()
        except BaseException:
            low.shutdown()
            raise
        built = BuiltRobot(high, low, low.blackboard, clock, cfg)
        started.append(built)
        return built

    try:
        yield build
    finally:
        for built in reversed(started):
            try:
                built.high.shutdown()
            finally:
                built.low.shutdown()


@pytest.fixture
def sim(clock: VirtualClock) -> Iterator[Callable[..., Any]]:
    """``sim(world="warehouse", **options)``: a :class:`robots.Simulation` (real pybullet
    physics) stepped in lockstep with ``clock``: ``clock.advance(5.0)`` is five simulated
    seconds of physics and of every behaviour's sleeps in between."""
    from beehave.testing.lockstep import Lockstep

    opened: list[tuple[Any, Lockstep]] = []

    def make(world: Any = "warehouse", **options: Any) -> Any:
        from robots import Simulation

        simulation = Simulation(world, real_time_factor=None, **options)
        lockstep = Lockstep(simulation, clock)
        lockstep.__enter__()
        opened.append((simulation, lockstep))
        return simulation

    try:
        yield make
    finally:
        for simulation, lockstep in reversed(opened):
            try:
                lockstep.__exit__(None, None, None)
            finally:
                simulation.close()


@pytest.fixture
def replay_check() -> Callable[..., Any]:
    """``replay_check(recording, config, **replay_options)``: run the configuration on a
    reference recording (``beehave replay``) and fail with the first divergence; returns
    the :class:`~beehave.recording.replay.ReplayResult`."""

    def check(recording: str | Path, config: Any, **options: Any) -> Any:
        from beehave.config import RobotConfig, load_config
        from beehave.recording.replay import replay

        cfg = config if isinstance(config, RobotConfig) else load_config(Path(config))
        options.setdefault("speed", None)
        result = replay(recording, cfg, **options)
        if result.divergence is not None:
            pytest.fail(f"replay of {recording} diverged from the reference: "
                        f"{result.divergence}", pytrace=False)
        if result.damaged:  # a reference that is not whole proves nothing past the damage
            pytest.fail(f"the reference {recording} is damaged: "
                        + "; ".join(result.damaged), pytrace=False)
        return result

    return check
