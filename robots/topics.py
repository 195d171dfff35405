"""The robots' ROS 2 interface: topic names, message types and rates (the contract between
the sim node, the HALs and the actions). Names are relative to the robot's namespace
unless they start with ``/``.

Common to every robot (DESIGN.md):

========================  =========================  =====  ==============================
topic                     type                       dir    meaning
========================  =========================  =====  ==============================
``cmd_vel``               geometry_msgs/Twist        in     linear.x (m/s), angular.z (rad/s);
                                                            the base stops 0.5 s (sim time)
                                                            after the last command
``odom``                  nav_msgs/Odometry          out    50 Hz; ground-truth pose in the
                                                            world frame ``map``, child
                                                            ``<ns>/base_link``; twist in the
                                                            robot frame
``scan``                  sensor_msgs/LaserScan      out    10 Hz; 360°, frame
                                                            ``<ns>/base_link``, inf = no hit
``battery_state``         sensor_msgs/BatteryState   out    5 Hz; ``percentage`` 0–1,
                                                            ``power_supply_status`` CHARGING
                                                            (1) on a charging station
``/clock``                rosgraph_msgs/Clock        out    100 Hz of sim time
``/lockstep``             std_msgs/String (JSON)     in     ``{"participant": id,
                                                            "until_s": t}``: hold the sim at
                                                            sim time t until ``id`` answers
                                                            again; ``"until_s": null``: let
                                                            go (``docs/simulation.md``)
========================  =========================  =====  ==============================

EMILI:

========================  =========================  =====  ==============================
``lift/command``          std_msgs/Float64           in     target height, 0–0.3 m
``lift/state``            std_msgs/Float64           out    50 Hz; the height now (m)
``leds``                  std_msgs/ColorRGBA         in     the LED strip colour (0–1)
``leds/state``            std_msgs/ColorRGBA         out    on change and 1 Hz; latched
``display``               std_msgs/String            in     the text on the display
``display/state``         std_msgs/String            out    on change and 1 Hz; latched
``sound``                 std_msgs/String            in     a sound's name to play
``line_sensor``           std_msgs/Float64           out    50 Hz; lateral offset of the
                                                            tape (m, + = tape to the left);
                                                            NaN when no tape is seen
========================  =========================  =====  ==============================

Kobuki (bit masks in std_msgs/Int32: bit 0 = left, bit 1 = centre, bit 2 = right):

========================  =========================  =====  ==============================
``bumpers``               std_msgs/Int32             out    50 Hz; pressed bumpers
``cliffs``                std_msgs/Int32             out    50 Hz; cliffs seen
``wheel_drop``            std_msgs/Int32             out    50 Hz; bit 0 left, bit 1 right
``buttons``               std_msgs/Int32             out    50 Hz; bit i = button Bi held
``leds/led1``, ``leds/led2``  std_msgs/String        in     "off", "green", "orange", "red"
``sound``                 std_msgs/String            in     on, off, recharge, button, error,
                                                            cleaning_start, cleaning_end
========================  =========================  =====  ==============================

A factory world (machines, depots, speed zones; :mod:`robots.factory`) adds one global
topic:

========================  =========================  =====  ==============================
``/factory/state``        std_msgs/String (JSON)     out    5 Hz of sim time and on every
                                                            load and delivery; latched;
                                                            schema ``beehave/factory/
                                                            state/1`` (docs/simulation.md)
========================  =========================  =====  ==============================

A command the robot cannot take (a lift height out of range, an unknown LED colour or
sound) is refused with an error in the sim node's log and counted in ``SimNode.rejected``;
the robot keeps its previous state.
"""

from __future__ import annotations

CMD_VEL = "cmd_vel"
ODOM = "odom"
SCAN = "scan"
BATTERY = "battery_state"
CLOCK = "/clock"
LOCKSTEP = "/lockstep"

LIFT_COMMAND = "lift/command"
LIFT_STATE = "lift/state"
LEDS = "leds"
LEDS_STATE = "leds/state"
DISPLAY = "display"
DISPLAY_STATE = "display/state"
SOUND = "sound"
LINE_SENSOR = "line_sensor"

BUMPERS = "bumpers"
CLIFFS = "cliffs"
WHEEL_DROP = "wheel_drop"
BUTTONS = "buttons"
KOBUKI_LED1 = "leds/led1"
KOBUKI_LED2 = "leds/led2"

ODOM_RATE_HZ = 50.0
SENSOR_RATE_HZ = 50.0
BATTERY_RATE_HZ = 5.0
CLOCK_RATE_HZ = 100.0
LOCKSTEP_TIMEOUT_S = 1.0
"""Wall seconds a lockstep participant may keep the sim waiting before it is let go."""
STATE_ECHO_PERIOD_S = 1.0
MAP_FRAME = "map"

FACTORY_STATE = "/factory/state"
FACTORY_STATE_RATE_HZ = 5.0

LEFT, CENTER, RIGHT = 1, 2, 4
"""Bits of the Kobuki masks."""
