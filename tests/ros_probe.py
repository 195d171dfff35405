"""A plain-rclpy observer for the ROS 2 tests: what any ROS 2 tool would see."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from typing import Any

from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from std_msgs.msg import String
from std_srvs.srv import Trigger

from beehave.ros.bridge import LATCHED
from beehave.ros.context import RosContext


class Probe:
    def __init__(self) -> None:
        self.ros = RosContext()
        self.node = self.ros.create_node("probe")
        self.ros.start()
        self._lock = threading.Lock()
        self.messages: dict[str, list[Any]] = {}

    def record(self, msg_type: type, topic: str, *, latched: bool = False) -> list[Any]:
        """Collect every message on ``topic`` (returns the live list)."""
        box: list[Any] = []
        with self._lock:
            self.messages[topic] = box
        self.node.create_subscription(msg_type, topic, box.append, LATCHED if latched else 10)
        return box

    def wait(self, predicate: Callable[[], bool], timeout_s: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.01)
        return predicate()

    def _call(self, srv_type: type, name: str, request: Any, timeout_s: float = 10.0) -> Any:
        client = self.node.create_client(srv_type, name)
        try:
            assert client.wait_for_service(timeout_sec=timeout_s), f"no service {name}"
            future = client.call_async(request)
            done = threading.Event()
            future.add_done_callback(lambda _: done.set())
            assert done.wait(timeout_s), f"{name} did not answer"
            return future.result()
        finally:
            self.node.destroy_client(client)

    def set_param(self, node: str, name: str, value: Any) -> Any:
        """SetParameters on ``node`` (fully qualified); returns the SetParametersResult."""
        pv = ParameterValue()
        if isinstance(value, str):
            pv.type, pv.string_value = ParameterType.PARAMETER_STRING, value
        elif isinstance(value, bool):
            pv.type, pv.bool_value = ParameterType.PARAMETER_BOOL, value
        elif isinstance(value, int):
            pv.type, pv.integer_value = ParameterType.PARAMETER_INTEGER, value
        else:
            raise TypeError(value)
        request = SetParameters.Request(parameters=[ParameterMsg(name=name, value=pv)])
        return self._call(SetParameters, f"{node}/set_parameters", request).results[0]

    def get_param(self, node: str, name: str) -> Any:
        response = self._call(GetParameters, f"{node}/get_parameters",
                              GetParameters.Request(names=[name]))
        return response.values[0].string_value

    def trigger(self, name: str) -> Any:
        return self._call(Trigger, name, Trigger.Request())

    def publishers(self, topic: str) -> int:
        return self.node.count_publishers(topic)

    def close(self) -> None:
        self.ros.shutdown()


def last_json(box: list[String]) -> dict[str, Any] | None:
    return json.loads(box[-1].data) if box else None
