"""VDA 5050 2.1 over MQTT: a beehave robot as a standard AGV (``docs/vda5050.md``).

- :mod:`.agv` — :class:`Vda5050Interface`, the robot on the broker (topics, connection and
  last will, state, visualization, factsheet, instant actions);
- :mod:`.order` — :class:`AgvOrders`, the order state and the standard's rules for orders
  and order updates;
- :mod:`.validation` — every message checked against the official 2.1.0 JSON schemas
  (shipped in ``schemas/`` with their MIT licence).

The robot's YAML enables it with a ``vda5050:`` section; ``beehave run`` then connects.
"""

from beehave.errors import Vda5050Error, Vda5050ValidationError
from beehave.interfaces.vda5050.agv import MAJOR, QOS, VERSION, Topics, Vda5050Interface
from beehave.interfaces.vda5050.order import (
    INSTANT_ACTIONS,
    NODE_ACTIONS,
    ActionStatus,
    AgvOrders,
    OrderRejected,
)
from beehave.interfaces.vda5050.validation import Problem, check, problems

__all__ = ["INSTANT_ACTIONS", "MAJOR", "NODE_ACTIONS", "QOS", "VERSION", "ActionStatus",
           "AgvOrders", "OrderRejected", "Problem", "Topics", "Vda5050Error",
           "Vda5050Interface", "Vda5050ValidationError", "check", "problems"]
