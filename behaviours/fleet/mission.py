"""The mission controller: one state machine per transport order, with status reports.

Seed paper 000's mission controller tracks every transport order through its life and
reports it. Here each order is a :mod:`transitions` state machine driven by the contract
net's steps (the ``observer`` of :func:`beehave.agents.protocols.contract_net`)::

    created ──announce──▶ announced ──award──▶ awarded ──deliver──▶ delivered
                             │  ▲                 │
                        give_up └──── lose ───────┘   (awardee failed, died or fell
                             ▼                           silent: the next bid is tried)
                          failed

A step the machine does not allow (an award while the order is awarded: two robots on one
contract) is not taken; it is reported as a ``violation`` instead, and ``beehave fleet``
fails its check on it.

Every state change is published on ``/fleet/orders`` (std_msgs/String, reliable, depth
100), schema ``beehave.fleet.order/1``::

    {"schema": "beehave.fleet.order/1", "order": "press1-3", "machine": "press1",
     "depot": "depot", "state": "awarded", "atv": "atv2", "attempt": 1,
     "awards": ["atv2"], "reason": null, "violation": null, "stamp": 1795240691.6,
     "sim_s": 131.4, "placed_sim_s": 128.9, "due_sim_s": 328.9}

``stamp`` is wall time; ``sim_s`` the simulation's time of the change (the machine's latest
``/factory/state``), ``placed_sim_s`` when the order was placed and ``due_sim_s`` when the
machine would fall to its safety stock (20 % of its capacity) without it: an order
delivered after it, or still open past it, is **late**. The lead time of an order is
``sim_s`` of its ``delivered`` report minus ``placed_sim_s``.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from transitions import Machine, MachineError

log = logging.getLogger(__name__)

ORDERS_TOPIC = "/fleet/orders"
ORDERS_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
SCHEMA = "beehave.fleet.order/1"
STATES = ["created", "announced", "awarded", "delivered", "failed"]
TRANSITIONS: list[Any] = [
    {"trigger": "announce", "source": "created", "dest": "announced"},
    {"trigger": "award", "source": "announced", "dest": "awarded"},
    {"trigger": "lose", "source": "awarded", "dest": "announced"},
    {"trigger": "deliver", "source": "awarded", "dest": "delivered"},
    {"trigger": "give_up", "source": ["created", "announced", "awarded"], "dest": "failed"},
]


class Mission:
    """One transport order's state machine (see the module docstring)."""

    state: str
    trigger: Any  # added by transitions.Machine

    def __init__(self, order: str, machine: str, depot: str, publish: Any, *,
                 sim_s: Any = None, due_sim_s: float | None = None) -> None:
        self.order, self.machine, self.depot = order, machine, depot
        #: The simulation's time now (a callable; None: not known).
        self._sim_s = sim_s if sim_s is not None else (lambda: None)
        self.placed_sim_s: float | None = self._sim_s()
        self.due_sim_s = due_sim_s
        self.atv: str | None = None
        self.attempt = 0
        self.awards: list[str] = []
        self.reason: str | None = None
        self._publish = publish
        self._lock = threading.Lock()
        Machine(model=self, states=STATES, transitions=TRANSITIONS, initial="created",
                after_state_change="_report", auto_transitions=False)

    def as_dict(self, violation: str | None = None) -> dict[str, Any]:
        return {"schema": SCHEMA, "order": self.order, "machine": self.machine,
                "depot": self.depot, "state": self.state, "atv": self.atv,
                "attempt": self.attempt, "awards": list(self.awards), "reason": self.reason,
                "violation": violation, "stamp": time.time(), "sim_s": self._sim_s(),
                "placed_sim_s": self.placed_sim_s, "due_sim_s": self.due_sim_s}

    def _report(self) -> None:
        self._publish(self.as_dict())

    def step(self, step: str, detail: dict[str, Any]) -> None:
        """The contract net's ``observer``: drive the machine from its steps."""
        with self._lock:
            try:
                if step == "cfp":
                    self.trigger("announce")
                elif step == "awarded":
                    self.atv, self.attempt = detail["awardee"], detail["attempt"]
                    self.awards.append(self.atv)
                    self.reason = None
                    self.trigger("award")
                elif step == "failed":
                    self.reason = str(detail.get("reason"))
                    self.trigger("lose")
                elif step == "done":
                    self.trigger("deliver")
            except MachineError as exc:
                log.error("order %s: %s in state %s: %s", self.order, step, self.state, exc)
                self._publish(self.as_dict(violation=f"{step} in state {self.state}"))

    def fail(self, reason: str) -> None:
        with self._lock:
            self.reason = reason
            if self.state != "failed":
                self.trigger("give_up")


class MissionController:
    """Makes the :class:`Mission` of every order and publishes its reports with
    ``publisher`` (make it with the behaviour's ``self.ros.publisher(String, ORDERS_TOPIC,
    qos=ORDERS_QOS)``, so that it ends with the behaviour)."""

    def __init__(self, publisher: Any) -> None:
        self._pub = publisher
        self.missions: dict[str, Mission] = {}

    def _publish(self, report: dict[str, Any]) -> None:
        self._pub.publish(String(data=json.dumps(report)))

    def new(self, order: str, machine: str, depot: str, *, sim_s: Any = None,
            due_sim_s: float | None = None) -> Mission:
        """A new order's mission; ``sim_s()`` tells the simulation's time (for the reports'
        ``sim_s`` and ``placed_sim_s``), ``due_sim_s`` when the machine runs empty."""
        mission = Mission(order, machine, depot, self._publish, sim_s=sim_s,
                          due_sim_s=due_sim_s)
        self.missions[order] = mission
        mission._report()
        return mission
