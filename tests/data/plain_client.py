"""A plain rclpy program (no beehave import): switch a beehave robot by its `behavior`
parameter and read its blackboard topic. Prints one JSON line."""

import json
import sys
import time

import rclpy
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

ns = sys.argv[1]
rclpy.init()
node = rclpy.create_node("plain_client")
client = node.create_client(SetParameters, f"{ns}/beehave_high_level/set_parameters")
assert client.wait_for_service(timeout_sec=20.0), "no parameter service"
value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value="patrol")
future = client.call_async(SetParameters.Request(
    parameters=[Parameter(name="behavior", value=value)]))
rclpy.spin_until_future_complete(node, future, timeout_sec=20.0)
ok = future.result().results[0].successful

latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
mode = {"value": None}


def on_board(msg: String) -> None:
    entry = json.loads(msg.data)["entries"].get("mode")
    if entry is not None:
        mode["value"] = entry["value"]


node.create_subscription(String, f"{ns}/beehave/blackboard", on_board, latched)
deadline = time.monotonic() + 20.0
while mode["value"] != "driving" and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
print(json.dumps({"set_behavior": ok, "mode": mode["value"]}))
node.destroy_node()
rclpy.shutdown()
