"""Shared fleet state: every agent publishes what others need to know about it — where it
is, how it moves, its battery, mode, current behaviour and mission — and keeps the latest
state of every peer, with its age.

::

    fleet = Fleet(agent, state=lambda: {"position": {...}, "battery_pct": 87.0})
    fleet.attach(hl)                          # behaviours: self.fleet
    fleet.attach(ll)                          # logics: self.fleet
    leader = fleet.get("rover1")              # PeerState or None
    if leader is not None and not leader.stale:
        north = leader.state["position"]["north_m"]

Transport. One topic for the whole fleet, ``/beehave/fleet/state`` (``std_msgs/String``
holding JSON, schema ``beehave.fleet/1``), BEST_EFFORT and VOLATILE: a state that is lost is
replaced by the next one within ``1 / rate_hz``, so nothing is retransmitted and a slow
reader never holds a fast writer back. (On sim time, the next one may be far off in wall
time — the simulation held; see below.) Each agent publishes at most ``rate_hz`` times a
second (the newest state; a state that did not change is still sent, as a heartbeat, so
that its peers can tell silence from standing still). Robot-agnostic: ``state`` is any
JSON object; :mod:`behaviours.droid` fills it for MAVLink vehicles.

Staleness. ``age_s`` of a peer's state is the time since it was received plus the time it
travelled (its sender's timestamp against this host's clock, at least 0: hosts need
synchronised clocks for that part, as for agent messages). It is stale past
``stale_after_s`` (default 1 s, ten periods at 10 Hz). Messages that fail the schema are
counted in :attr:`Fleet.rejected` and logged, never raised.

Sim time. An agent whose node follows ``/clock`` (``use_sim_time``) publishes at
``rate_hz`` of simulated time and stamps its states with the simulation's time
(``"clock": "sim"``); for a peer that does the same, ``age_s`` is the difference of the
two sim times — what the state's age means to a controller of a simulation that may run
faster or slower than real time. A state stamped on the other kind of clock is aged from
its receipt only. A wall-time timer backs the sim-time one up: every ``1 / rate_hz`` of
wall time it sends a new state if a period of sim time passed without one (rclpy's
sim-time timer may not fire after a jump of ``/clock`` that then stands still), else the
latest again (same ``seq``, same stamp) if none went out: while sim time stands still, a
lost state would otherwise never be replaced, and a lockstep controller that holds the
simulation may be waiting for exactly that state.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from beehave.attach import attach, attached, detach
from beehave.behavior import NO_FLEET
from beehave.errors import ConfigError
from beehave.hal import check_duration_s
from beehave.lifecycle import Closing

if TYPE_CHECKING:
    from beehave.agents.agent import Agent

log = logging.getLogger(__name__)

__all__ = ["FLEET_TOPIC", "SCHEMA", "Fleet", "PeerState", "fleet_of"]

FLEET_TOPIC = "/beehave/fleet/state"
SCHEMA = "beehave.fleet/1"
FLEET_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                       reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)

StateSource = Callable[[], dict[str, Any]]


@dataclass(frozen=True)
class PeerState:
    """The latest state of one peer."""

    name: str
    state: dict[str, Any]
    sent_at: float
    """The sender's wall time (Unix seconds) when it published; its sim time (s) when it
    stamps on sim time (``"clock": "sim"``)."""
    received: float
    """This host's monotonic time when it arrived."""
    seq: int
    stale_after_s: float
    sim_now: Callable[[], float] | None = None
    """This agent's sim time, when both it and the peer stamp on sim time."""
    comparable: bool = True
    """False when the peer stamps on the other kind of clock: aged from receipt only."""

    @property
    def age_s(self) -> float:
        """Seconds since the state was true at its sender (see the module doc)."""
        if self.sim_now is not None:
            return max(0.0, self.sim_now() - self.sent_at)
        since = time.monotonic() - self.received
        if not self.comparable:
            return since
        transit = max(0.0, (time.time() - self.sent_at) - since)
        return since + transit

    @property
    def stale(self) -> bool:
        return self.age_s > self.stale_after_s


def _uses_sim_time(node: Any) -> bool:
    return bool(node.has_parameter("use_sim_time")
                and node.get_parameter("use_sim_time").value)


class Fleet(Closing):
    """This agent's view of the fleet, and its own contribution (see the module doc).

    ``agent``: the :class:`~beehave.agents.Agent` whose node and name it uses. ``state``:
    called in the ROS executor thread ``rate_hz`` times a second for this agent's state
    (keep it short; it may read a blackboard); None publishes what :meth:`update` set.
    Close it (or ``with``) to stop publishing; peers then see this agent go stale."""

    def __init__(self, agent: Agent, *, state: StateSource | None = None,
                 rate_hz: float = 10.0, stale_after_s: float = 1.0) -> None:
        if not (isinstance(rate_hz, int | float) and 0 < rate_hz <= 100
                and math.isfinite(rate_hz)):
            raise ConfigError(f"fleet of agent {agent.name!r}: rate_hz must be in (0, 100], "
                              f"got {rate_hz!r}")
        self.agent = agent
        self.name = agent.name
        self.rate_hz = float(rate_hz)
        self.stale_after_s = check_duration_s(f"fleet of agent {agent.name!r}: stale_after_s",
                                              stale_after_s)
        #: Messages that were not taken, by reason.
        self.rejected: Counter[str] = Counter()
        self._source = state
        self._own: dict[str, Any] = {}
        self._peers: dict[str, PeerState] = {}
        self._lock = threading.Lock()
        self._seq = 0
        self._closed = False
        node = agent.node
        self._sim_clock = node.get_clock() if _uses_sim_time(node) else None
        self._pub = node.create_publisher(String, FLEET_TOPIC, FLEET_QOS)
        self._sub = node.create_subscription(String, FLEET_TOPIC, self._on_state, FLEET_QOS)
        self._timer = node.create_timer(1.0 / self.rate_hz, self._publish)
        self._last_text: str | None = None
        self._last_sent_s = -math.inf  # the sim time of the latest new state
        self._sent_since_resend = False
        self._resend_timer = None
        if self._sim_clock is not None:
            # Sim time may jump and then stand still while a lockstep controller holds
            # the simulation, perhaps waiting for this very state (a follower for its
            # leader's). rclpy's sim-time timer may then not fire (seen: no state for
            # 0.8 s of wall time with the clock 0.25 s past the timer's due time), and a
            # lost state is not replaced. A wall-time timer covers both (see _catch_up).
            self._resend_timer = node.create_timer(
                1.0 / self.rate_hz, self._catch_up,
                clock=Clock(clock_type=ClockType.STEADY_TIME))

    # ---- own state ---------------------------------------------------------------------

    def update(self, **fields: Any) -> None:
        """Merge ``fields`` into this agent's state; it goes out with the next period."""
        with self._lock:
            self._own.update(fields)

    @property
    def own(self) -> dict[str, Any]:
        """This agent's state as last published."""
        with self._lock:
            return dict(self._own)

    def _publish(self) -> None:
        if self._closed:
            return
        try:
            state = self._source() if self._source is not None else None
        except Exception:  # a broken state source must not end the fleet
            log.exception("fleet of agent %r: the state source raised", self.name)
            return
        with self._lock:
            if state is not None:
                self._own.update(state)
            self._seq += 1
            sent_at = time.time() if self._sim_clock is None else self._sim_s()
            payload = {"schema": SCHEMA, "agent": self.name, "seq": self._seq,
                       "sent_at": sent_at, "state": self._own}
            if self._sim_clock is not None:
                payload["clock"] = "sim"
            try:
                text = json.dumps(payload, allow_nan=False)
            except (TypeError, ValueError) as exc:
                self.rejected[f"own state not JSON: {exc}"] += 1
                log.error("fleet of agent %r: state is not JSON, not sent: %s", self.name, exc)
                return
            self._last_text, self._sent_since_resend = text, True
            self._last_sent_s = sent_at
        self._send(text)

    def _catch_up(self) -> None:
        """On sim time, every period of wall time: a new state when a period of sim time
        has passed without one (the sim-time timer did not fire), else the latest again
        (the same ``seq`` and stamp: a peer that has it drops it as a repeat) when none
        went out in this period."""
        if self._closed:
            return
        with self._lock:
            text, sent, last_s = self._last_text, self._sent_since_resend, self._last_sent_s
            self._sent_since_resend = False
        now_s = self._sim_s()
        if now_s == 0.0:
            return  # no /clock yet: nothing to stamp a state with
        if now_s - last_s >= 1.0 / self.rate_hz - 1e-9:
            self._publish()
        elif text is not None and not sent:
            self._send(text)

    def _send(self, text: str) -> None:
        try:
            self._pub.publish(String(data=text))
        except Exception:  # the node is being destroyed (shutdown race)
            if not self._closed:
                raise

    # ---- peers -------------------------------------------------------------------------

    def _on_state(self, msg: String) -> None:
        try:
            data = json.loads(msg.data)
            if not isinstance(data, dict) or data.get("schema") != SCHEMA:
                raise ValueError(f"schema is not {SCHEMA!r}")
            name, state = data["agent"], data["state"]
            sent_at, seq = float(data["sent_at"]), int(data["seq"])
            if not isinstance(name, str) or not isinstance(state, dict):
                raise ValueError("agent must be a string and state an object")
            on_sim = data.get("clock") == "sim"
        except (ValueError, KeyError, TypeError) as exc:
            self.rejected[str(exc)[:80]] += 1
            log.debug("fleet of agent %r: rejected a state: %s", self.name, exc)
            return
        if name == self.name:
            return
        with self._lock:
            old = self._peers.get(name)
            if old is not None and seq <= old.seq and old.sent_at >= sent_at:
                return  # reordered: an older state of a process we hear already
            self._peers[name] = PeerState(
                name, state, sent_at, time.monotonic(), seq, self.stale_after_s,
                sim_now=self._sim_s if on_sim and self._sim_clock is not None else None,
                comparable=on_sim == (self._sim_clock is not None))

    def _sim_s(self) -> float:
        assert self._sim_clock is not None
        return float(self._sim_clock.now().nanoseconds) / 1e9

    def get(self, name: str) -> PeerState | None:
        """The latest state of peer ``name`` (check ``.stale``), None if never heard."""
        with self._lock:
            return self._peers.get(name)

    def peers(self, *, include_stale: bool = True) -> dict[str, PeerState]:
        """Every peer heard, by name."""
        with self._lock:
            peers = dict(self._peers)
        return {n: p for n, p in peers.items() if include_stale or not p.stale}

    # ---- reach from behaviours and logics ---------------------------------------------------

    def attach(self, manager: object) -> None:
        """Make this ``self.fleet`` of the Behaviors and Actions of a
        HighLevelBehaviorManager, or of the Logics of a LowLevelBehaviorManager."""
        attach(_key(manager), "fleet", self)

    # ---- lifecycle ---------------------------------------------------------------------

    def close(self) -> None:
        """Stop publishing and listening; detach from every manager."""
        if self._closed:
            return
        self._closed = True
        detach(self, "fleet")
        node = self.agent.node
        timers = [t for t in (self._timer, self._resend_timer) if t is not None]
        for kind, entity in [*(("timer", t) for t in timers), ("subscription", self._sub),
                             ("publisher", self._pub)]:
            try:
                getattr(node, f"destroy_{kind}")(entity)
            except Exception:  # the node went first (its owner shut it down)
                log.debug("fleet of %r: destroying its %s failed", self.name, kind)


    def __repr__(self) -> str:
        return f"<Fleet of {self.name!r}: peers {sorted(self._peers)}>"




def _key(manager: object) -> object:
    # A logic reaches its blackboard, not its manager: a low level is keyed by its board.
    from beehave.lowlevel import LowLevelBehaviorManager

    if isinstance(manager, LowLevelBehaviorManager):
        return manager.blackboard
    return manager


def fleet_of(manager: object) -> Fleet:
    """The fleet attached to a manager (a HighLevelBehaviorManager, or a
    LowLevelBehaviorManager's blackboard)."""
    fleet: Fleet = attached(_key(manager), "fleet", missing=NO_FLEET)  # keyed as attach() does
    return fleet
