"""The factory HAL: what the simulated factory says about *this* robot, on the blackboard.

A factory world's sim node publishes ``/factory/state`` (:mod:`robots.factory`, schema
``beehave/factory/state/1``, latched, 5 Hz of sim time and at once after every load and
delivery). This HAL subscribes to it and keeps the entries of its own robot — the one
whose namespace is the low level's node namespace (``/atv3`` → ``atv3``) — current:

==================================  =========  ===========================================
key (writer ``hal:factory``)        type       meaning
==================================  =========  ===========================================
``factory/load``                    float      units carried; 0.0 when empty
``factory/loaded``                  bool       carries a load (a Kobuki carries one)
``factory/zone``                    str        the speed zone the robot is in; "" outside
``factory/zone_max_speed_mps``      float      that zone's limit; ``inf`` outside any zone
``factory/charging_at``             str        the charging station it stands in; ""
``factory/time_s``                  float      sim time of the state these came from
==================================  =========  ===========================================

All have a max age of 2 s (ten periods): when the simulation stops publishing they read
as stale rather than silently old. A logic asks for it like any HAL
(``await self.hal("factory")``); the loading happens in the physics (stand still in the
depot, then in a machine's delivery area — docs/simulation.md), so the HAL has no methods.

A state message with another schema is reported as a HAL error (naming the schema it
expects) and skipped. A state that does not list this robot (a wrong namespace, or a world
started with fewer robots) is reported once with a warning that names the namespace and
the robots the factory has; the entries then stay unset.
"""

from __future__ import annotations

import json
import logging
import math
from typing import Any

from std_msgs.msg import String

from beehave.errors import HALError
from beehave.ros.hal import RosHAL, TopicInput
from beehave.ros.io import LATCHED
from robots import topics
from robots.factory import STATE_SCHEMA

log = logging.getLogger(__name__)

__all__ = ["FACTORY_KEYS", "FactoryHAL", "factory_entries"]

FACTORY_KEYS = ("factory/load", "factory/loaded", "factory/zone",
                "factory/zone_max_speed_mps", "factory/charging_at", "factory/time_s")

STATE_QOS = LATCHED
"""As the sim node publishes it: a HAL loaded late still gets the last state at once."""


def factory_entries(data: dict[str, Any], namespace: str) -> dict[str, Any] | None:
    """One decoded ``/factory/state`` → the ``factory/*`` entries of robot ``namespace``;
    None when the state does not list that robot. Raises :class:`HALError` for another
    schema."""
    schema = data.get("schema")
    if schema != STATE_SCHEMA:
        raise HALError(f"HAL 'factory': {topics.FACTORY_STATE} carries schema {schema!r}; "
                       f"this HAL reads {STATE_SCHEMA!r}")
    robot = data.get("robots", {}).get(namespace)
    if robot is None:
        return None
    load = robot.get("load")
    limit = robot.get("zone_max_speed_mps")
    return {"factory/load": float(load or 0.0), "factory/loaded": load is not None,
            "factory/zone": robot.get("zone") or "",
            "factory/zone_max_speed_mps": math.inf if limit is None else float(limit),
            "factory/charging_at": robot.get("charging_at") or "",
            "factory/time_s": float(data.get("time_s", 0.0))}


class FactoryHAL(RosHAL):
    """This robot's load, speed zone and charging station from ``/factory/state``."""

    name = "factory"
    max_age_s = 2.0

    async def on_load(self) -> None:
        await super().on_load()  # the node check and the bookkeeping of RosHAL
        self.namespace = self.node.get_namespace().strip("/")
        self._warned_missing = False
        for key in FACTORY_KEYS:
            self.blackboard.declare(key, max_age_s=self.max_age_s)
        # Built here, not as a class-level TopicInput: the conversion needs the namespace.
        spec = TopicInput(topics.FACTORY_STATE, String, self._entries, qos=STATE_QOS)
        sub = self.node.create_subscription(String, spec.topic, self._input_callback(spec),
                                            spec.qos)
        self._entities.append(("subscription", sub))

    def _entries(self, msg: Any) -> dict[str, Any]:
        data = json.loads(msg.data)
        entries = factory_entries(data, self.namespace)
        if entries is None:
            if not self._warned_missing:
                self._warned_missing = True
                robots = sorted(data.get("robots", {}))
                log.warning("HAL 'factory': robot %r is not in the factory's state; its "
                            "robots: %s", self.namespace, ", ".join(robots) or "none")
            return {}
        return entries
