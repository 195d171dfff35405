"""One robot: the two managers, their ROS 2 nodes and the bridges between them.

``beehave run ROBOT.yaml`` builds a :class:`Robot` from a configuration file. Both
managers run in one process by default; ``only="high"`` / ``only="low"`` runs one of them,
so the pair can be split across processes or machines — they only talk over ROS 2.
"""

from __future__ import annotations

import functools
import logging
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from beehave.behavior import Behavior
from beehave.clock import SimClock, WallClock
from beehave.config import RobotConfig, import_class
from beehave.errors import (
    BeehaveError,
    ConfigError,
    ConstructorFailed,
    InvalidParameters,
    SimClockNotStarted,
    UnknownNameError,
)
from beehave.hal import HAL
from beehave.highlevel import HighLevelBehaviorManager
from beehave.lifecycle import Running
from beehave.logic import Logic
from beehave.lowlevel import LowLevelBehaviorManager

if TYPE_CHECKING:
    from rclpy.node import Node

    from beehave.agents import Agent
    from beehave.agents.trust import Trust
    from beehave.interfaces import ControlPlane
    from beehave.interfaces.vda5050 import Vda5050Interface
    from beehave.ros.bridge import HighLevelBridge, LowLevelBridge
    from beehave.ros.context import RosContext
    from beehave.ros.execute import ExecuteBehaviorServer
    from beehave.simulation import RunningSimulation

log = logging.getLogger(__name__)

Only = Literal["high", "low"] | None

HIGH_NODE = "beehave_high_level"
LOW_NODE = "beehave_low_level"


class Robot(Running):
    """Builds, starts and stops a robot described by a :class:`RobotConfig`.

    Use it as a context manager. :meth:`shutdown` interrupts the actions (safe states
    applied), stops the logics and HALs, destroys the nodes and joins every thread.
    ``ros``: a :class:`~beehave.ros.context.RosContext` to share with other robots in the
    same process (one executor thread, one DDS participant); the robot then destroys only
    its own nodes.
    """

    def __init__(self, config: RobotConfig, *, only: Only = None,
                 ros: RosContext | None = None, clock: WallClock | None = None) -> None:
        if only not in (None, "high", "low"):
            raise ConfigError(f"only must be 'high', 'low' or None, got {only!r}")
        self.config = config
        self.only = only
        # A test's virtual clock (beehave.testing): both levels follow it and share one
        # blackboard, as they do in one process without ROS.
        self._clock = clock
        self.high: HighLevelBehaviorManager | None = None
        self.low: LowLevelBehaviorManager | None = None
        #: The VDA 5050 interface (``vda5050:`` in the configuration; needs the high level).
        self.vda5050: Vda5050Interface | None = None
        self._build()
        self._ros: RosContext | None = None
        self._shared_ros = ros
        self._bridges: list[HighLevelBridge | LowLevelBridge | ExecuteBehaviorServer] = []
        self._nodes: list[Node] = []
        self._started = False
        #: The simulator's object, when the configuration asks for a simulation (``sim:``).
        self.sim: Any = None
        self._simulation: RunningSimulation | None = None
        #: The robot's agent (``agent:`` in the configuration; needs the high level).
        self.agent: Agent | None = None
        #: The control-plane core every network interface of this robot uses (ROS 2,
        #: HTTP, VDA 5050); set by :meth:`start` when the high level runs here.
        self.plane: ControlPlane | None = None

    def _build(self) -> None:
        """Import and register everything the configuration names, so a bad name or bad
        parameters fail here, before anything starts. Every error names the file and the
        key path (``emili.yaml: behaviors.tour.params: …``)."""
        cfg = self.config
        src = cfg.source
        if self.only in (None, "high"):
            clock = self._clock
            if clock is None and cfg.use_sim_time:
                clock = SimClock()
            hl = HighLevelBehaviorManager(default=cfg.default_behavior,
                                          stop_timeout_s=cfg.stop_timeout_s, clock=clock)
            for name, spec in cfg.behaviors.items():
                cls = import_class(spec.class_, base=Behavior,
                                   where=f"{src}: behaviors.{name}.class")
                with _located(f"{src}: behaviors.{name}.params"):
                    hl.register(name, cls, **spec.params)
            if cfg.vda5050 is not None:  # registers the order behaviour: before start
                from beehave.interfaces.vda5050.agv import make_interface

                with _located(f"{src}: vda5050"):
                    self.vda5050 = make_interface(cfg.vda5050, high=hl,
                                                  import_class=import_class, source=src)
            self.high = hl
        if self.only in (None, "low"):
            ll = LowLevelBehaviorManager(
                default=cfg.default_logic, stop_timeout_s=cfg.stop_timeout_s, clock=self._clock,
                blackboard=self.high.blackboard if self._clock is not None and self.high
                else None)
            for name, spec in cfg.logics.items():
                logic_cls = import_class(spec.class_, base=Logic,
                                         where=f"{src}: logics.{name}.class")
                with _located(f"{src}: logics.{name}.params"):
                    ll.register(name, logic_cls, **spec.params)
            # Two entries of one name would silently replace each other: refuse them.
            seen: dict[str, int] = {}
            for i, hal in enumerate(cfg.hals):
                if isinstance(hal, str):
                    hal_name = hal
                    with _located(f"{src}: hals.{i}"):
                        ll.hals.resolve(hal)  # an unknown name fails now, listing the names
                else:
                    hal_cls = import_class(hal.class_, base=HAL, where=f"{src}: hals.{i}.class")
                    hal_name = hal.name or hal_cls.name
                    with _located(f"{src}: hals.{i}" if not hal_name else
                                  f"{src}: hals.{i}.params"):
                        ll.hals.register(hal_cls, name=hal.name, **hal.params)
                if hal_name in seen:
                    raise ConfigError(f"{src}: hals.{i}: HAL {hal_name!r} is already given by "
                                      f"hals.{seen[hal_name]}; list each HAL once")
                seen[hal_name] = i
            _register_arbiters(ll, cfg, seen)
            self.low = ll
        self._substitute()

    def _substitute(self) -> None:
        """The configuration's ``substitutes:`` (tests): scripted stand-ins by name."""
        subs = self.config.substitutes
        if not subs:
            return
        from beehave.testing.fakes import Scripted

        for pattern, spec in subs.items():
            stand_in = Scripted(duration_s=spec.duration_s, result=spec.result,
                                raises=None if spec.fail is None else RuntimeError(spec.fail))
            if self.high is not None:
                self.high.substitute(pattern, stand_in)
            if self.low is not None:
                self.low.substitute(pattern, stand_in)

    def start(self) -> None:
        from beehave.ros.bridge import HighLevelBridge, LowLevelBridge
        from beehave.ros.context import RosContext

        cfg = self.config
        ros = self._shared_ros or RosContext()
        self._ros = ros
        try:
            ros.start()
            if cfg.sim is not None and self.only != "high":
                self._start_sim(ros)
            high_node = None
            if self.high is not None:
                # Before the low level starts: a logic may set the high-level node's
                # parameters from its first moment, so they are declared first.
                high_node = ros.create_node(HIGH_NODE, namespace=cfg.namespace,
                                            use_sim_time=cfg.use_sim_time)
                self._nodes.append(high_node)
                for behavior_cls in self.high.registered_classes():
                    behavior_cls.prepare_node(high_node)
            if self.low is not None:
                # The low level runs on wall time (asyncio); only the high level follows
                # /clock, so each robot subscribes to it once, not once per node.
                node = ros.create_node(LOW_NODE, namespace=cfg.namespace)
                self._nodes.append(node)
                self.low.hals.node = node
                self.low.__enter__()
                self._bridges.append(LowLevelBridge(
                    self.low, node, blackboard_rate_hz=cfg.ros.blackboard_rate_hz,
                    snapshot_period_s=cfg.ros.snapshot_period_s))
            if self.high is not None:
                assert high_node is not None
                node = high_node
                from beehave.interfaces import ControlPlane

                self.plane = ControlPlane(self.high, low=self.low,
                                          name=cfg.namespace.replace("/", "_"))
                self._bridges.append(HighLevelBridge(
                    self.high, node, state_period_s=cfg.ros.state_period_s,
                    plane=self.plane))
                from beehave.ros.execute import ExecuteBehaviorServer, InterfacesMissing

                try:
                    self._bridges.append(ExecuteBehaviorServer(
                        self.plane, node, second_goal=cfg.ros.second_goal,
                        feedback_period_s=cfg.ros.state_period_s))
                except InterfacesMissing as exc:  # the robot runs; only the action is gone
                    log.warning("robot %r: no beehave/execute_behavior action: %s",
                                cfg.namespace, exc)
                if cfg.agent is not None:  # before the behaviours, which may use it
                    from beehave.agents import Agent

                    self.agent = Agent(cfg.agent.name, node=node, services=cfg.agent.services,
                                       lease_s=cfg.agent.lease_s, trust=_trust(cfg))
                    self.agent.attach(self.high)
                if isinstance(self.high.clock, SimClock):
                    self._wait_for_sim_clock(self.high.clock, node)
                # The default behaviour is constructed now: name its entry when it fails.
                default = cfg.default_behavior
                with _located(f"{cfg.source}: behaviors.{default}" if default != "idle"
                              else f"{cfg.source}: default_behavior",
                              only=(InvalidParameters, ConstructorFailed)):
                    self.high.start()
                if self.vda5050 is not None:  # connects in the background, retrying
                    self.vda5050.start(control=self.plane, node=node)
        except BaseException as exc:
            try:
                self.shutdown()
            except BeehaveError as late:  # the start error is the one to report
                exc.add_note(f"and while shutting down after it: {late}")
            raise
        self._started = True

    def _wait_for_sim_clock(self, clock: SimClock, node: Node) -> None:
        """On sim time, behaviours start once the simulation's time has reached the robot
        (its first ``/clock``): started before, they would run at a time of 0 that the
        simulation never had, then see time jump to where it already is -- a loop of
        sleeps would skip steps, and a recording would carry the false time."""
        cfg = self.config
        if clock.started:
            return
        log.info("robot %r: waiting for the simulation's time (/clock), up to %.0f s",
                 cfg.namespace, cfg.sim_clock_timeout_s)
        t0 = time.monotonic()
        if not clock.wait_started(cfg.sim_clock_timeout_s):
            try:  # discovery failed, or a publisher that sends nothing: say which
                publishers = [f"{i.node_namespace.rstrip('/')}/{i.node_name}"
                              for i in node.get_publishers_info_by_topic("/clock")]
                seen = (f"this robot sees {len(publishers)} publisher(s) of /clock"
                        + (f": {', '.join(publishers)}, which sent nothing it received "
                           f"(a simulation that is paused or stuck?)" if publishers else ""))
            except Exception as exc:  # the node went away meanwhile
                seen = f"its publishers could not be listed ({exc})"
            raise SimClockNotStarted(
                f"{cfg.source}: use_sim_time is true, but no /clock message arrived within "
                f"sim_clock_timeout_s={cfg.sim_clock_timeout_s:g} s ({seen}): start the "
                f"simulation (beehave sim, or a sim: section) on ROS_DOMAIN_ID="
                f"{os.environ.get('ROS_DOMAIN_ID', '0')}, raise sim_clock_timeout_s, or set "
                f"use_sim_time: false")
        log.info("robot %r: the simulation's time reached it after %.2f s (sim time %.3f s)",
                 cfg.namespace, time.monotonic() - t0, clock.now())

    def _start_sim(self, ros: RosContext) -> None:
        from beehave.simulation import load_simulator

        assert self.config.sim is not None
        opts = self.config.sim
        src = self.config.source
        with _located(f"{src}: sim.simulator"):
            simulator = load_simulator(opts.simulator)
        # A world that does not exist or does not load is the configuration's fault; a
        # simulation that fails while starting is not.
        with _located(f"{src}: sim.world", only=(ConfigError, UnknownNameError)):
            self._simulation = simulator.start(opts.world,
                                               real_time_factor=opts.real_time_factor, ros=ros)
        self.sim = self._simulation.sim

    def shutdown(self) -> None:
        """Stop everything, in the order that keeps the robot safe: actions first (their
        safe states may still publish), then the bridges, the logics and HALs, the
        simulation, the nodes.

        Every step runs even when an earlier one fails (a logic that blocked the event
        loop must not keep the ROS executor thread alive and the process from exiting);
        the first error is raised afterwards, the later ones are attached as notes."""
        errors: list[BaseException] = []

        def step(what: str, fn: Callable[[], object]) -> None:
            try:
                fn()
            except Exception as exc:
                log.error("robot %r: %s failed: %s", self.config.namespace, what, exc)
                errors.append(exc)

        if self.high is not None:
            step("high-level shutdown", self.high.shutdown)
        if self.vda5050 is not None:  # after the safe states: its last state shows them
            step("closing the VDA 5050 interface", self.vda5050.close)
        if self.agent is not None:
            step("closing the agent", self.agent.close)
            self.agent = None
        for bridge in reversed(self._bridges):
            step(f"destroying {type(bridge).__name__}", bridge.destroy)
        self._bridges.clear()
        if self.plane is not None:
            step("closing the control plane", self.plane.close)
            self.plane = None
        if self.low is not None:
            step("low-level shutdown", self.low.shutdown)
        if self._simulation is not None:
            step("closing the simulation", self._simulation.close)
            self._simulation = None
            self.sim = None
        if self._ros is not None:
            ros = self._ros
            if ros is not self._shared_ros:
                step("ROS shutdown", ros.shutdown)
            else:
                for node in self._nodes:
                    step(f"destroying node {node.get_name()!r}",
                         functools.partial(ros.destroy_node, node))
            self._nodes.clear()
            self._ros = None
        if errors:
            first = errors[0]
            for later in errors[1:]:
                first.add_note(f"also while shutting down: {type(later).__name__}: {later}")
            raise first



def _register_arbiters(ll: LowLevelBehaviorManager, cfg: RobotConfig,
                       hals: dict[str, int]) -> None:
    """The ``fusion:`` section: one arbiter HAL per actuator (``fusion_<actuator>``),
    built once now so that a bad value fails here, naming its key path."""
    from beehave.fusion import Arbiter, arbiter_name

    for actuator, spec in cfg.fusion.items():
        where = f"{cfg.source}: fusion.{actuator}"
        cls = import_class(spec.class_, base=Arbiter, where=f"{where}.class")
        name = arbiter_name(actuator)
        if name in hals:
            raise ConfigError(f"{where}: its arbiter HAL {name!r} is already given by "
                              f"hals.{hals[name]}; list it in one place")
        params = spec.arbiter_params(actuator)
        with _located(where):
            ll.hals.register(cls, name=name, **params)
            cls(**params)  # an Arbiter's constructor only checks and stores


@contextmanager
def _located(where: str, *, only: tuple[type[BaseException], ...] = (BeehaveError,)
             ) -> Iterator[None]:
    """Re-raise a beehave error (of the ``only`` types) as a :class:`ConfigError` that
    starts with ``where`` (file and key path), so the user knows which line to fix."""
    try:
        yield
    except only as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def _trust(cfg: RobotConfig) -> Trust | None:
    """The agent's keys and mode from the YAML (paths relative to the file); None leaves
    them to the environment (``BEEHAVE_AGENT_MODE``, ``BEEHAVE_AGENT_KEYS``)."""
    from beehave.agents.trust import Trust

    a = cfg.agent
    assert a is not None
    paths = {"keys_dir": a.keys, "fleet_public_key": a.fleet_public_key, "key": a.key,
             "certificate": a.certificate}
    if a.mode is None and not any(paths.values()):
        return None
    here = Path(cfg.source).parent if cfg.source != "<dict>" else Path.cwd()
    given = {k: here / v for k, v in paths.items() if v}
    mode = a.mode or "signed"
    with _located(f"{cfg.source}: agent", only=(ConfigError,)):
        if not given:
            return Trust(mode, name=a.name)
        return Trust.load(a.name, mode=mode, keys_dir=given.get("keys_dir"),
                          fleet_public_key=given.get("fleet_public_key"),
                          key=given.get("key"), certificate=given.get("certificate"))
