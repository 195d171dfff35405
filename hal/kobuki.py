"""HALs for the Kobuki over ROS 2: bumpers, cliffs and wheel drop, buttons, LEDs, sound.

The Kobuki also has odometry, a battery and a laser: use the shared
:class:`~hal.mobile_base.OdometryHAL`, :class:`~hal.mobile_base.BatteryHAL` and
:class:`~hal.mobile_base.LaserHAL` (re-exported here), which read the topics every robot has.

==================  ===================================================  ======================
HAL ``name``        blackboard keys (writer ``hal:<name>``)              methods
==================  ===================================================  ======================
``kobuki_bumpers``  ``bumper/left``, ``bumper/center``, ``bumper/right``
``kobuki_cliffs``   ``cliff/left``, ``cliff/center``, ``cliff/right``,
                    ``wheel_drop/left``, ``wheel_drop/right``
``kobuki_buttons``  ``button/0``, ``button/1``, ``button/2``
``kobuki_leds``     —                                                    ``set(led1, led2)``
``kobuki_sound``    —                                                    ``play(name)``
==================  ===================================================  ======================

All keys are bools, True while pressed / seen / dropped / held, decoded from the
``std_msgs/Int32`` bit masks of :mod:`robots.topics` (bit 0 left, 1 centre, 2 right;
``wheel_drop`` bit 0 left, 1 right; ``buttons`` bit i = Bi); max age 0.5 s (they arrive at
50 Hz). LED colours are ``off``, ``green``, ``orange``, ``red``; sounds are Kobuki's
built-in sequences (:data:`SOUNDS`). A bad name raises
:class:`~robots.errors.CommandOutOfRange` listing the valid ones, before anything is sent.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from std_msgs.msg import Int32, String

from beehave.ros.hal import RosHAL, TopicInput, TopicOutput
from hal.mobile_base import BatteryHAL, LaserHAL, OdometryHAL
from robots import topics
from robots.errors import CommandOutOfRange

__all__ = ["LED_COLORS", "SOUNDS", "BatteryHAL", "KobukiBumpersHAL", "KobukiButtonsHAL",
           "KobukiCliffsHAL", "KobukiLedsHAL", "KobukiSoundHAL", "LaserHAL", "OdometryHAL"]

LED_COLORS = ("off", "green", "orange", "red")
"""The colours a Kobuki LED shows (``leds/led1``, ``leds/led2``)."""
SOUNDS = ("on", "off", "recharge", "button", "error", "cleaning_start", "cleaning_end")
"""Kobuki's built-in sound sequences (kobuki_msgs/Sound values 0–6)."""

_MAX_AGE_S = 0.5


def bits(prefix: str, names: tuple[str, ...]) -> Callable[[Any], dict[str, bool]]:
    """A conversion of an Int32 bit mask into ``<prefix>/<name>`` bools, bit i = names[i]."""
    keys = tuple(f"{prefix}/{name}" for name in names)

    def convert(msg: Any) -> dict[str, bool]:
        mask = int(msg.data)
        return {key: bool(mask >> i & 1) for i, key in enumerate(keys)}

    return convert


_TRIPLE = ("left", "center", "right")


class KobukiBumpersHAL(RosHAL):
    """Which bumpers are pressed, from ``bumpers``."""

    name = "kobuki_bumpers"
    inputs = [TopicInput(topics.BUMPERS, Int32, bits("bumper", _TRIPLE), max_age_s=_MAX_AGE_S)]


class KobukiCliffsHAL(RosHAL):
    """Which cliff sensors see no floor (``cliffs``) and which wheels hang in the air
    (``wheel_drop``): stop before the robot falls."""

    name = "kobuki_cliffs"
    inputs = [TopicInput(topics.CLIFFS, Int32, bits("cliff", _TRIPLE), max_age_s=_MAX_AGE_S),
              TopicInput(topics.WHEEL_DROP, Int32, bits("wheel_drop", ("left", "right")),
                         max_age_s=_MAX_AGE_S)]


class KobukiButtonsHAL(RosHAL):
    """Which of the buttons B0–B2 are held down, from ``buttons``."""

    name = "kobuki_buttons"
    inputs = [TopicInput(topics.BUTTONS, Int32, bits("button", ("0", "1", "2")),
                         max_age_s=_MAX_AGE_S)]


def _check(hal: str, what: str, value: str, valid: tuple[str, ...]) -> None:
    if value not in valid:
        raise CommandOutOfRange(f"HAL {hal!r}: unknown {what} {value!r}; valid: "
                                f"{', '.join(valid)}")


class KobukiLedsHAL(RosHAL):
    """The Kobuki's two LEDs: :meth:`set`. Its safe state turns both off."""

    name = "kobuki_leds"
    outputs = {"led1": TopicOutput(topics.KOBUKI_LED1, String, state=True),
               "led2": TopicOutput(topics.KOBUKI_LED2, String, state=True)}

    def set(self, led1: str, led2: str) -> None:
        """Set LED1 and LED2, each to ``off``, ``green``, ``orange`` or ``red``. Both names
        are checked before either LED changes."""
        _check(self.name, "LED1 colour", led1, LED_COLORS)
        _check(self.name, "LED2 colour", led2, LED_COLORS)
        self.publish("led1", String(data=led1))
        self.publish("led2", String(data=led2))

    def safe_state(self) -> None:
        self.set("off", "off")


class KobukiSoundHAL(RosHAL):
    """The Kobuki's beeper: :meth:`play` one of its built-in sequences."""

    name = "kobuki_sound"
    outputs = {"sound": TopicOutput(topics.SOUND, String)}

    def play(self, name: str) -> None:
        """Play ``name``, one of :data:`SOUNDS`."""
        _check(self.name, "sound", name, SOUNDS)
        self.publish("sound", String(data=name))
