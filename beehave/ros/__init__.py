"""ROS 2 for beehave: the managers as nodes, robot I/O for behaviours and actions, the
blackboard and high-level state between the managers, and ROS-backed HALs.

Importing this package imports rclpy (the ``ros`` extra); ``import beehave`` does not.
"""

from beehave.ros.context import RosContext
from beehave.ros.io import Latest, RosIO

__all__ = ["Latest", "RosContext", "RosIO"]
