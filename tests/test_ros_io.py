"""RosIO's shared publishers: the topic every action of a kind commands stays matched."""

from __future__ import annotations

import os

import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import Twist  # noqa: E402
from ros_probe import Probe  # noqa: E402

from beehave.errors import BeehaveError  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.ros.io import RosIO  # noqa: E402

NS = f"shared_pub_{os.getpid()}"


def test_a_shared_publisher_outlives_its_owner_and_refuses_it_afterwards() -> None:
    """The robot hears a new owner's very first command (no new DDS writer to discover),
    and an owner that ended — an action gone STUCK — can no longer command the robot."""
    ros = RosContext()
    node = ros.create_node("beehave_high_level", namespace=NS)
    ros.start()
    probe = Probe()  # another participant: discovery takes real time, as for the robot
    try:
        seen = probe.record(Twist, f"/{NS}/cmd_vel")
        first = RosIO(node, owner="tour/Navigation")
        cmd = first.publisher(Twist, "cmd_vel", shared=True)
        assert probe.wait(lambda: cmd.get_subscription_count() == 1)
        cmd.publish(Twist())
        assert probe.wait(lambda: len(seen) == 1)
        first.destroy_all()
        with pytest.raises(BeehaveError, match=r"tour/Navigation: has ended; cannot publish "
                                               rf"on /{NS}/cmd_vel"):
            cmd.publish(Twist())

        second = RosIO(node, owner="tour/Navigation#2")
        again = second.publisher(Twist, "cmd_vel", shared=True)
        assert again.get_subscription_count() == 1  # still matched: nothing to discover
        go = Twist()
        go.linear.x = 0.5
        again.publish(go)  # at once, no wait: it must still arrive
        assert probe.wait(lambda: len(seen) == 2)
        assert seen[-1].linear.x == 0.5
        # Another QoS or type is another publisher; a private one is the owner's own.
        other = second.publisher(Twist, "cmd_vel", qos=1, shared=True)
        second.publisher(Twist, "cmd_vel")
        assert other._publisher is not again._publisher  # type: ignore[attr-defined]
        second.destroy_all()
        assert probe.wait(lambda: probe.publishers(f"/{NS}/cmd_vel") == 2)  # 2 kept by node
    finally:
        probe.close()
        ros.shutdown()
