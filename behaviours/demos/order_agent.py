"""Another agent that orders a beehave robot around: publishes one order on
``<ns>/orders`` and prints the robot's progress until the order is reached, failed or
rejected. A plain rclpy program; it imports nothing of beehave's framework.

    python -m behaviours.demos.order_agent emili1 --station emili_charging
    python -m behaviours.demos.order_agent emili1 --goal 12.0 3.5 --id o7
    python -m behaviours.demos.order_agent emili1 --switch commanded --station emili_pickup

``--switch NAME`` first sets the robot's ``behavior`` parameter (on
``/<ns>/beehave_high_level``) to ``NAME`` — what ``ros2 param set`` would do, for machines
without the ros2 command line — and waits until the robot accepted it.

Exit status 0 when the order was reached, 1 otherwise (2 when the switch was refused).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import rclpy
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from std_msgs.msg import String


def switch_behavior(node: Node, namespace: str, behavior: str, *, timeout_s: float) -> str:
    """Set ``behavior`` on the robot's high-level node; returns "" or why it was refused."""
    client: Any = node.create_client(SetParameters,
                                     f"/{namespace}/beehave_high_level/set_parameters")
    deadline = time.monotonic() + timeout_s
    try:
        while not client.wait_for_service(timeout_sec=0.5):
            if time.monotonic() >= deadline:
                return f"/{namespace}/beehave_high_level is not running"
        # Fast DDS drops an answer sent before the server matched our response reader.
        time.sleep(0.3)
        value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=behavior)
        request = SetParameters.Request(parameters=[Parameter(name="behavior", value=value)])
        future = client.call_async(request)
        rclpy.spin_until_future_complete(node, future,
                                         timeout_sec=max(0.1, deadline - time.monotonic()))
        response = future.result() if future.done() else None
        if response is None:
            return "the robot did not answer"
        result = response.results[0]
        return "" if result.successful else (result.reason or "refused")
    finally:
        node.destroy_client(client)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="order_agent", description=__doc__)
    parser.add_argument("namespace")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--station")
    where.add_argument("--goal", nargs=2, type=float, metavar=("X_M", "Y_M"))
    parser.add_argument("--id", default="order-1")
    parser.add_argument("--timeout-s", type=float, default=300.0)
    parser.add_argument("--switch", metavar="BEHAVIOR",
                        help="first switch the robot to this top-level behaviour "
                             "(its behavior parameter), e.g. commanded")
    args = parser.parse_args(argv)
    order = {"id": args.id, **({"station": args.station} if args.station
                               else {"goal": args.goal})}
    rclpy.init()
    node = rclpy.create_node("order_agent")
    outcome: dict[str, str] = {}
    if args.switch:
        refused = switch_behavior(node, args.namespace, args.switch,
                                  timeout_s=min(60.0, args.timeout_s))
        if refused:
            print(f"order_agent: cannot switch {args.namespace} to {args.switch!r}: {refused}",
                  file=sys.stderr, flush=True)
            node.destroy_node()
            rclpy.shutdown()
            return 2
        print(json.dumps({"switched": args.switch}), flush=True)

    def on_progress(msg: String) -> None:
        try:
            report = json.loads(msg.data)
        except ValueError as exc:  # reported, not fatal: the next report may be fine
            print(f"order_agent: malformed progress report {msg.data!r:.80}: {exc}",
                  file=sys.stderr, flush=True)
            return
        if not isinstance(report, dict) or report.get("id") != args.id:
            return
        print(json.dumps(report), flush=True)
        if report["status"] in ("reached", "failed", "rejected"):
            outcome["status"] = report["status"]

    node.create_subscription(String, f"/{args.namespace}/orders/progress", on_progress, 10)
    pub = node.create_publisher(String, f"/{args.namespace}/orders", 10)
    deadline = time.monotonic() + args.timeout_s
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)  # wait until the robot listens
    time.sleep(0.3)  # let its progress publisher be discovered too
    pub.publish(String(data=json.dumps(order)))
    print(json.dumps({"sent": order}), flush=True)
    while "status" not in outcome and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.shutdown()
    return 0 if outcome.get("status") == "reached" else 1


if __name__ == "__main__":
    sys.exit(main())
