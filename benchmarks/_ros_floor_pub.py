"""Child process of bench_ros: the bare rclpy floor across processes.

argv: n rate_hz — publishes n std_msgs/String carrying ``time.monotonic()`` on ``floor``
(the blackboard topic's QoS) at rate_hz, once the parent says go; nothing of beehave but
its RosContext (one EventsExecutor thread, as every beehave process has).
"""

from __future__ import annotations

import sys
import time

from std_msgs.msg import String

from beehave.ros.bridge import BLACKBOARD_QOS
from beehave.ros.context import RosContext


def main() -> None:
    n, rate_hz = int(sys.argv[1]), float(sys.argv[2])
    ros = RosContext()
    node = ros.create_node("floor_pub")
    ros.start()
    pub = node.create_publisher(String, "floor", BLACKBOARD_QOS)
    while pub.get_subscription_count() == 0:  # the parent's subscription is discovered
        time.sleep(0.01)
    print("ready", flush=True)
    sys.stdin.readline()
    start = time.monotonic()
    for i in range(n):
        pub.publish(String(data=repr(time.monotonic())))
        time.sleep(max(0.0, start + (i + 1) / rate_hz - time.monotonic()))
    sys.stdin.readline()  # the parent says stop
    ros.shutdown()


if __name__ == "__main__":
    main()
