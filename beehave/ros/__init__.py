"""ROS 2 for beehave: the managers as nodes, robot I/O for behaviours and actions, the
blackboard and high-level state between the managers, and ROS-backed HALs.

Importing this package imports rclpy (the ``ros`` extra); ``import beehave`` does not.
"""

from beehave.errors import GoalFailed
from beehave.ros.actions import RosActionGoal, ServiceCall
from beehave.ros.context import RosContext
from beehave.ros.io import LATCHED, Goal, Latest, RosIO, WaitTimeout

__all__ = ["LATCHED", "Goal", "GoalFailed", "Latest", "RosActionGoal", "RosContext", "RosIO",
           "ServiceCall", "WaitTimeout"]
