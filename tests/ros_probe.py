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
from rclpy.qos import QoSProfile
from std_msgs.msg import String
from std_srvs.srv import Trigger

from beehave.ros.bridge import LATCHED
from beehave.ros.context import RosContext
from beehave.testing import WALL_TIMEOUT_S


class Probe:
    def __init__(self) -> None:
        self.ros = RosContext()
        self.node = self.ros.create_node("probe")
        self.ros.start()
        self._lock = threading.Lock()
        self.messages: dict[str, list[Any]] = {}

    def record(self, msg_type: type, topic: str, *, latched: bool = False) -> list[Any]:
        """Collect every message on ``topic`` (returns the live list). ``latched``: also
        the last one sent before this subscribed; the reader keeps 100, not LATCHED's 1,
        so that a message followed closely by the next one is not overwritten before the
        executor takes it (a factory's pick-up state was, on a loaded machine)."""
        box: list[Any] = []
        with self._lock:
            self.messages[topic] = box
        qos = QoSProfile(depth=100, history=LATCHED.history, reliability=LATCHED.reliability,
                         durability=LATCHED.durability) if latched else 10
        self.node.create_subscription(msg_type, topic, box.append, qos)
        return box

    def wait(self, predicate: Callable[[], bool], timeout_s: float = WALL_TIMEOUT_S) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.01)
        return predicate()

    def _call(self, srv_type: type, name: str, request: Any,
              timeout_s: float = WALL_TIMEOUT_S) -> Any:
        # One client per service, kept: with Fast DDS a server that answers before it has
        # matched a new client's response reader drops the answer ("failed to send
        # response"), which a loaded machine makes likely for a client made per call.
        clients: dict[tuple[type, str], Any] = self.__dict__.setdefault("_clients", {})
        client = clients.get((srv_type, name))
        if client is None:
            client = self.node.create_client(srv_type, name)
            assert client.wait_for_service(timeout_sec=timeout_s), f"no service {name}"
            time.sleep(0.3)  # let the server match our response reader too
            clients[(srv_type, name)] = client
        assert client.wait_for_service(timeout_sec=timeout_s), f"no service {name}"
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        assert done.wait(timeout_s), f"{name} did not answer"
        return future.result()

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


class FibonacciServer:
    """A plain rclpy action server (test_msgs/Fibonacci) in a context of its own, spun by a
    MultiThreadedExecutor so that cancel requests arrive while a goal executes.

    ``order`` chooses the script: < 0 rejected; 99 aborted; otherwise one feedback per step
    every ``step_s``, then SUCCEEDED. ``cancelled`` lists the orders of the goals that
    ended cancelled on request, ``succeeded`` those that ran to their end. A busy server:
    ``accept_delay_s`` before it answers a goal; a slow one to stop: ``stop_delay_s``
    between a cancel request and the goal's end.
    """

    def __init__(self, name: str, *, step_s: float = 0.01) -> None:
        import rclpy
        from rclpy.action import ActionServer, CancelResponse
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor
        from test_msgs.action import Fibonacci

        self._fib = Fibonacci
        self.step_s = step_s
        self.accept_delay_s = 0.0
        self.stop_delay_s = 0.0
        self.cancelled: list[int] = []
        self.succeeded: list[int] = []
        self.requested = threading.Event()  # a goal request came
        self.executing = threading.Event()
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("fibonacci_server", context=self.context)
        self.server = ActionServer(
            self.node, Fibonacci, name, execute_callback=self._execute,
            goal_callback=self._on_goal,
            cancel_callback=lambda _handle: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        self.executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, name="fibonacci-server",
                                        daemon=True)
        self._thread.start()

    def _on_goal(self, goal: Any) -> Any:
        from rclpy.action import GoalResponse

        self.requested.set()
        time.sleep(self.accept_delay_s)
        return GoalResponse.REJECT if goal.order < 0 else GoalResponse.ACCEPT

    def _execute(self, handle: Any) -> Any:
        fib = self._fib
        order = handle.request.order
        sequence = [0, 1]
        self.executing.set()
        cancel_seen: float | None = None
        for _ in range(max(order, 1)):
            if handle.is_cancel_requested and cancel_seen is None:
                cancel_seen = time.monotonic()
            if cancel_seen is not None and time.monotonic() - cancel_seen >= self.stop_delay_s:
                handle.canceled()
                self.cancelled.append(order)
                return fib.Result(sequence=sequence)
            if order == 99:
                handle.abort()
                return fib.Result(sequence=[-1])
            sequence.append((sequence[-1] + sequence[-2]) % 2**31)  # int32 on the wire
            handle.publish_feedback(fib.Feedback(sequence=sequence))
            time.sleep(self.step_s)
        handle.succeed()
        self.succeeded.append(order)
        return fib.Result(sequence=sequence)

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self._thread.join(WALL_TIMEOUT_S)
        self.server.destroy()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
