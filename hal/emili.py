"""HALs for EMILI over ROS 2: line sensor, lift, LED strip, display, speaker.

EMILI also has odometry, a battery and a laser: those HALs every mobile robot shares live
in :mod:`hal.mobile_base` (re-exported here).

Each HAL is one function of the robot, built on :class:`~beehave.ros.hal.RosHAL`: it
subscribes to the robot's topics (:mod:`robots.topics`, relative to the low level's
namespace) when a logic first asks for it, keeps its blackboard keys current, and offers
the methods that drive the hardware. They work the same against the simulation
(``beehave sim``) and a real robot that speaks the same topics.

==================  ===================================================  ======================
HAL ``name``        blackboard keys (writer ``hal:<name>``)              methods
==================  ===================================================  ======================
``line_sensor``     ``line/offset_m`` (m, + = tape to the left; None
                    when no tape), ``line/visible``; max age 0.5 s
``lift``            ``lift/height_m``; max age 0.5 s                     ``set_height(height_m)``
``emili_leds``      ``leds/color`` (r, g, b), each 0–1                   ``set_color(r, g, b)``
``display``         ``display/text``                                     ``show(text)``
``sound``           —                                                    ``play(name)``
==================  ===================================================  ======================

Methods check their arguments before anything is sent and raise
:class:`~robots.errors.CommandOutOfRange` (a ``ValueError``) naming the HAL, the value
and the valid range, so a logic learns of its mistake at once instead of from the sim's log.
"""

from __future__ import annotations

import math
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import ColorRGBA, Float64, String

from beehave.ros.hal import RosHAL, TopicInput, TopicOutput
from hal.mobile_base import BatteryHAL, LaserHAL, OdometryHAL
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
    outputs = {"leds": TopicOutput(topics.LEDS, ColorRGBA, state=True)}

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
    outputs = {"display": TopicOutput(topics.DISPLAY, String, state=True)}

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
