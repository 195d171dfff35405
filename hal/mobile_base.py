"""HALs every mobile robot shares, over ROS 2: odometry, battery, laser.

EMILI and the Kobuki both use them (:mod:`hal.emili` and :mod:`hal.kobuki` re-export
them); so can any robot that publishes the standard topics of :mod:`robots.topics`.

==================  ===================================================
HAL ``name``        blackboard keys (writer ``hal:<name>``)
==================  ===================================================
``odometry``        ``odom/x_m``, ``odom/y_m``, ``odom/yaw_rad``
                    (deadband 0.01 m / rad), ``odom/linear_mps``,
                    ``odom/angular_rps`` (deadband 0.01); max age 0.5 s
``battery``         ``battery/percentage`` (0–100), ``battery/charging``,
                    ``battery/voltage_v``; max age 2 s
``laser``           ``laser/front_m``, ``laser/left_m``, ``laser/back_m``,
                    ``laser/right_m``: nearest hit per sector, inf when
                    none; max age 1 s
==================  ===================================================

Laser sectors, in the robot frame (0 = straight ahead, counter-clockwise positive):
front |a| <= 45°, left 45° < a < 135°, back |a| >= 135°, right -135° < a < -45°. Beams
that hit nothing (inf), NaN and readings outside ``[range_min, range_max]`` are ignored.
"""

from __future__ import annotations

import itertools
import math
from functools import lru_cache
from typing import Any

from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import BatteryState, LaserScan

from beehave.ros.hal import RosHAL, TopicInput
from robots import topics

__all__ = ["BatteryHAL", "LaserHAL", "OdometryHAL", "laser_entries", "odometry_entries",
           "battery_entries", "sector_of", "yaw_from_quaternion"]

_QUARTER_RAD = math.pi / 4
_BOUNDARY_RAD = 1e-5
# LaserScan angles are float32: a beam meant to lie on a sector boundary (±45°, ±135°) is
# off by up to ~1e-6 rad after angle_min + i * angle_increment. Within this tolerance it
# counts as on the boundary, so the boundaries stay where the docstring says.


# ---- odometry ----------------------------------------------------------------------------

POSE_KEYS = ("odom/x_m", "odom/y_m", "odom/yaw_rad")
TWIST_KEYS = ("odom/linear_mps", "odom/angular_rps")


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The heading (rotation about z, radians in (-π, π]) of a quaternion."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def odometry_entries(msg: Any) -> dict[str, float]:
    """nav_msgs/Odometry → the ``odom/*`` keys (pose in the world frame, twist in the
    robot frame)."""
    pose = msg.pose.pose
    q = pose.orientation
    twist = msg.twist.twist
    return {"odom/x_m": pose.position.x, "odom/y_m": pose.position.y,
            "odom/yaw_rad": yaw_from_quaternion(q.x, q.y, q.z, q.w),
            "odom/linear_mps": twist.linear.x, "odom/angular_rps": twist.angular.z}


class OdometryHAL(RosHAL):
    """Where the robot is and how it moves, from ``odom``.

    The pose keys have a deadband of ``pose_deadband`` (0.01 m for x and y, 0.01 rad for
    the yaw) and the velocities one of ``twist_deadband``: a logic watching them wakes for
    relevant moves only, not for every one of the 50 messages a second. Within the
    deadband the entry keeps its last relevant value (so ``get()`` may lag the robot by
    up to 0.01 m) while staying fresh.
    """

    name = "odometry"
    pose_deadband = 0.01
    twist_deadband = 0.01
    max_age_s = 0.5
    #: Subscribed by on_load itself (not ``inputs``): raw when only some are read.
    odom_input = TopicInput(topics.ODOM, Odometry, odometry_entries)

    def __init__(self, *, every: int = 1) -> None:
        """``every``: read one message in ``every`` (1: all of them). The robot publishes
        at 50 Hz of its time (:data:`robots.topics.ODOM_RATE_HZ`), so ``every=5`` keeps
        the keys at 10 Hz of sim time, whatever the simulation's speed; the messages left
        out are never turned into Python objects (each costs the process's executor
        thread about as much as a whole blackboard write). For logics that need the
        pose at a lower rate than a controller would (a fleet's speed zones, bids): a
        driving action subscribes to ``odom`` itself."""
        if isinstance(every, bool) or not isinstance(every, int) or not 1 <= every <= 50:
            raise ValueError(f"HAL 'odometry': every must be an integer in [1, 50] "
                             f"(read one message in every), got {every!r}")
        self.every = every

    async def on_load(self) -> None:
        # Declared here, per key: one TopicInput's policy would apply to every key.
        for key in POSE_KEYS:
            self.blackboard.declare(key, max_age_s=self.max_age_s, deadband=self.pose_deadband)
        for key in TWIST_KEYS:
            self.blackboard.declare(key, max_age_s=self.max_age_s,
                                    deadband=self.twist_deadband)
        await super().on_load()
        spec = self.odom_input
        convert = self._input_callback(spec)
        if self.every == 1:
            sub = self.node.create_subscription(Odometry, spec.topic, convert, spec.qos)
        else:
            # Raw bytes: a message left out costs no Python message object.
            count = itertools.count()
            every = self.every

            def on_raw(data: bytes) -> None:  # in the ROS executor thread
                if next(count) % every == 0:
                    convert(deserialize_message(data, Odometry))

            sub = self.node.create_subscription(Odometry, spec.topic, on_raw, spec.qos,
                                                raw=True)
        self._entities.append(("subscription", sub))


# ---- battery -----------------------------------------------------------------------------

def battery_entries(msg: Any) -> dict[str, Any]:
    """sensor_msgs/BatteryState → ``battery/*`` (percentage 0–100, like the debug HAL)."""
    return {"battery/percentage": msg.percentage * 100.0,
            "battery/charging": msg.power_supply_status
            == BatteryState.POWER_SUPPLY_STATUS_CHARGING,
            "battery/voltage_v": msg.voltage}


class BatteryHAL(RosHAL):
    """State of charge, charging flag and voltage, from ``battery_state`` (5 Hz)."""

    name = "battery"
    inputs = [TopicInput(topics.BATTERY, BatteryState, battery_entries, max_age_s=2.0)]


# ---- laser -------------------------------------------------------------------------------

SECTORS = ("front", "left", "back", "right")


def sector_of(angle_rad: float) -> str:
    """The sector of a beam at ``angle_rad`` (robot frame; see the module docstring)."""
    a = math.remainder(angle_rad, 2 * math.pi)  # into [-π, π]
    if abs(a) <= _QUARTER_RAD + _BOUNDARY_RAD:
        return "front"
    if abs(a) >= 3 * _QUARTER_RAD - _BOUNDARY_RAD:
        return "back"
    return "left" if a > 0 else "right"


@lru_cache(maxsize=8)
def _beam_sectors(angle_min_rad: float, increment_rad: float, count: int) -> tuple[str, ...]:
    # A scanner's geometry never changes: classify its beams once.
    return tuple(sector_of(angle_min_rad + i * increment_rad) for i in range(count))


def laser_entries(msg: Any) -> dict[str, float]:
    """sensor_msgs/LaserScan → the nearest valid range per sector, ``inf`` for none."""
    nearest = dict.fromkeys(SECTORS, math.inf)
    ranges = msg.ranges
    lo, hi = msg.range_min, msg.range_max
    sectors = _beam_sectors(msg.angle_min, msg.angle_increment, len(ranges))
    for sector, r in zip(sectors, ranges, strict=True):
        if lo <= r <= hi and r < nearest[sector]:  # NaN and inf fail the comparison
            nearest[sector] = float(r)
    return {f"laser/{sector}_m": value for sector, value in nearest.items()}


class LaserHAL(RosHAL):
    """The nearest obstacle in front, left, behind and right, from ``scan`` (10 Hz)."""

    name = "laser"
    inputs = [TopicInput(topics.SCAN, LaserScan, laser_entries, max_age_s=1.0)]
