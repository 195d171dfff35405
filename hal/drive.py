"""The fused drive: one :class:`~beehave.fusion.Arbiter` for ``cmd_vel`` over ROS 2.

==================  ===================================================  ======================
HAL ``name``        blackboard keys                                      methods
==================  ===================================================  ======================
``fusion_cmd_vel``  ``fusion/cmd_vel/<source>`` (proposals),             ``propose(source,
                    ``fusion/cmd_vel/winner``, ``fusion/cmd_vel/         (linear_mps,
                    rejected``, ``fusion/cmd_vel/locks/<lock>``          angular_rps))``,
                    (True: engaged), ``fusion/cmd_vel/locked``           ``withdraw(source)``,
                                                                         ``set_lock(lock,
                                                                         engaged)``
==================  ===================================================  ======================

A proposal is ``(linear_mps, angular_rps)``; the winner is published on ``cmd_vel``
(geometry_msgs/Twist, ``linear.x`` and ``angular.z``) at ``rate_hz``; the safe value is
``(0.0, 0.0)``. Register it from the robot file's ``fusion:`` section (docs/fusion.md).
"""

from __future__ import annotations

from typing import Any

from geometry_msgs.msg import Twist

from beehave.fusion import Arbiter, check_twist
from beehave.ros.hal import RosHAL, TopicOutput
from robots import topics

__all__ = ["CmdVelArbiter"]


class CmdVelArbiter(Arbiter, RosHAL):
    """Fuses ``cmd_vel`` proposals and publishes the winner as a Twist."""

    name = "fusion_cmd_vel"
    default_safe_value = (0.0, 0.0)
    expected = "(linear_mps, angular_rps): two finite numbers"
    outputs = {"cmd_vel": TopicOutput(topics.CMD_VEL, Twist)}

    def check(self, value: Any) -> tuple[float, float]:
        return check_twist(value)

    def forward(self, value: tuple[float, float]) -> None:
        msg = Twist()
        msg.linear.x, msg.angular.z = value
        self.publish("cmd_vel", msg)
