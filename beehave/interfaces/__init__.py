"""Network interfaces of a robot: one control-plane core, thin adapters.

:class:`ControlPlane` (:mod:`beehave.interfaces.core`) holds the operations — switch,
stop, status, snapshot, blackboard, events — and their validation; the ROS 2 bridge
(:mod:`beehave.ros.bridge`), VDA 5050 over MQTT and HTTP/WebSocket
(:mod:`beehave.interfaces.http`, needs FastAPI and uvicorn) call it and only translate
their wire format and its errors.
"""

from beehave.interfaces.core import SNAPSHOT_SCHEMA, STATE_SCHEMA, ControlPlane

__all__ = ["SNAPSHOT_SCHEMA", "STATE_SCHEMA", "ControlPlane"]
