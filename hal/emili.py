"""HALs for EMILI over ROS 2 — and the ones every robot shares (odometry, battery, laser).

Each HAL is one function of the robot, built on :class:`~beehave.ros.hal.RosHAL`: it
subscribes to the robot's topics (:mod:`robots.topics`, relative to the low level's
namespace) when a logic first asks for it, keeps its blackboard keys current, and offers
the methods that drive the hardware. They work the same against the simulation
(``beehave sim``) and a real robot that speaks the same topics.

==================  ===================================================  ======================
HAL ``name``        blackboard keys (writer ``hal:<name>``)              methods
==================  ===================================================  ======================
``odometry``        ``odom/x_m``, ``odom/y_m``, ``odom/yaw_rad``
                    (deadband 0.01 m / rad), ``odom/linear_mps``,
                    ``odom/angular_rps`` (deadband 0.01); max age 0.5 s
``battery``         ``battery/percentage`` (0–100), ``battery/charging``,
                    ``battery/voltage_v``; max age 2 s
``laser``           ``laser/front_m``, ``laser/left_m``, ``laser/back_m``,
                    ``laser/right_m``: nearest hit per sector, inf when
                    none; max age 1 s
``line_sensor``     ``line/offset_m`` (m, + = tape to the left; None
                    when no tape), ``line/visible``; max age 0.5 s
``lift``            ``lift/height_m``; max age 0.5 s                     ``set_height(height_m)``
``emili_leds``      ``leds/color`` (r, g, b), each 0–1                   ``set_color(r, g, b)``
``display``         ``display/text``                                     ``show(text)``
``sound``           —                                                    ``play(name)``
==================  ===================================================  ======================

Laser sectors, in the robot frame (0 = straight ahead, counter-clockwise positive):
front |a| <= 45°, left 45° < a < 135°, back |a| >= 135°, right -135° < a < -45°. Beams
that hit nothing (inf), NaN and readings outside ``[range_min, range_max]`` are ignored.

Methods check their arguments before anything is sent and raise
:class:`~robots.errors.CommandOutOfRange` (a ``ValueError``) naming the HAL, the value
and the valid range, so a logic learns of its mistake at once instead of from the sim's log.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import BatteryState, LaserScan
from std_msgs.msg import ColorRGBA, Float64, String

from beehave.ros.hal import RosHAL, TopicInput, TopicOutput
from robots import topics
from robots.errors import CommandOutOfRange

__all__ = ["BatteryHAL", "DisplayHAL", "EmiliLedsHAL", "LaserHAL", "LiftHAL",
           "LineSensorHAL", "OdometryHAL", "SoundHAL", "STATE_INPUT_QOS"]

STATE_INPUT_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.BEST_AVAILABLE)
"""How the HALs read state echoes (``leds/state``, ``display/state``): transient-local when
every publisher offers it (the sim node latches them, so a HAL has the state as soon as it
is loaded), volatile otherwise (a robot that does not latch still reaches the HAL, at its
next echo)."""

LIFT_MAX_M = 0.30
"""EMILI's lift travel, metres above lowered (``lift/command`` takes 0–0.3 m)."""

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
    inputs = [TopicInput(topics.ODOM, Odometry, odometry_entries)]

    async def on_load(self) -> None:
        # Declared here, per key: one TopicInput's policy would apply to every key.
        for key in POSE_KEYS:
            self.blackboard.declare(key, max_age_s=self.max_age_s, deadband=self.pose_deadband)
        for key in TWIST_KEYS:
            self.blackboard.declare(key, max_age_s=self.max_age_s,
                                    deadband=self.twist_deadband)
        await super().on_load()


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


# ---- line sensor -------------------------------------------------------------------------

def line_entries(msg: Any) -> dict[str, Any]:
    """std_msgs/Float64 (NaN = no tape) → ``line/offset_m`` (None when not visible) and
    ``line/visible``."""
    visible = not math.isnan(msg.data)
    return {"line/offset_m": msg.data if visible else None, "line/visible": visible}


class LineSensorHAL(RosHAL):
    """EMILI's ground camera: where the lane tape is, from ``line_sensor`` (50 Hz). Steer
    ``angular_rps = k * offset`` to follow it."""

    name = "line_sensor"
    inputs = [TopicInput(topics.LINE_SENSOR, Float64, line_entries, max_age_s=0.5)]


# ---- lift --------------------------------------------------------------------------------

class LiftHAL(RosHAL):
    """EMILI's scissor lift: ``lift/height_m`` from ``lift/state``; :meth:`set_height`."""

    name = "lift"
    inputs = [TopicInput(topics.LIFT_STATE, Float64, lambda m: m.data, key="lift/height_m",
                         max_age_s=0.5)]
    outputs = {"command": TopicOutput(topics.LIFT_COMMAND, Float64)}

    def set_height(self, height_m: float) -> None:
        """Send the lift to ``height_m`` (0–0.3 m above lowered); returns at once — watch
        ``lift/height_m`` (the lift travels at 0.1 m/s)."""
        height = float(height_m)
        if not 0.0 <= height <= LIFT_MAX_M:
            raise CommandOutOfRange(f"HAL {self.name!r}: lift height {height_m!r} m is out "
                                    f"of range 0–{LIFT_MAX_M} m")
        self.publish("command", Float64(data=height))


# ---- LEDs, display, sound ----------------------------------------------------------------

class EmiliLedsHAL(RosHAL):
    """EMILI's LED strip: ``leds/color`` (r, g, b) from ``leds/state``; :meth:`set_color`.
    Its safe state turns the strip off."""

    name = "emili_leds"
    inputs = [TopicInput(topics.LEDS_STATE, ColorRGBA, lambda m: (m.r, m.g, m.b),
                         key="leds/color", qos=STATE_INPUT_QOS)]
    outputs = {"leds": TopicOutput(topics.LEDS, ColorRGBA)}

    def set_color(self, r: float, g: float, b: float) -> None:
        """Colour the whole strip; each channel 0–1."""
        rgb = (float(r), float(g), float(b))
        if not all(0.0 <= c <= 1.0 for c in rgb):
            raise CommandOutOfRange(f"HAL {self.name!r}: LED colour {rgb} is out of range; "
                                    "each channel must be 0–1")
        self.publish("leds", ColorRGBA(r=rgb[0], g=rgb[1], b=rgb[2], a=1.0))

    def safe_state(self) -> None:
        self.set_color(0.0, 0.0, 0.0)


class DisplayHAL(RosHAL):
    """EMILI's front display: ``display/text`` from ``display/state``; :meth:`show`."""

    name = "display"
    inputs = [TopicInput(topics.DISPLAY_STATE, String, lambda m: m.data, key="display/text",
                         qos=STATE_INPUT_QOS)]
    outputs = {"display": TopicOutput(topics.DISPLAY, String)}

    def show(self, text: str) -> None:
        """Show ``text`` (``""`` blanks the display)."""
        self.publish("display", String(data=str(text)))


class SoundHAL(RosHAL):
    """EMILI's speaker: :meth:`play` a sound by name (a file name or a text to speak)."""

    name = "sound"
    outputs = {"sound": TopicOutput(topics.SOUND, String)}

    def play(self, name: str) -> None:
        if not name:
            raise CommandOutOfRange(f"HAL {self.name!r}: a sound needs a name, got {name!r}")
        self.publish("sound", String(data=name))
