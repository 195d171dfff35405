"""Kobuki (the TurtleBot 2 base): bumpers, cliff sensors, wheel drop, two LEDs, sounds,
three buttons.

Geometry (``robots/urdf/kobuki.urdf``): round body of radius 0.175 m, wheels of radius
0.035 m on a 0.230 m track, casters front and back; 2.4 kg. Limits: 0.7 m/s, π rad/s.
Battery (default): 4S Li-ion 2200 mAh, 32.6 Wh, 13.2–16.8 V. A small laser scanner on the
top plate (as on a TurtleBot 2) gives the 360° ``scan`` at 0.12 m above the floor.

Sensors, read at ``sensor_rate_hz`` (default 50 Hz, Kobuki's own rate):

- **Bumpers** (left, centre, right) from the contact points between the body and anything
  but the floor: the contact's bearing in the robot frame picks the bumper — centre within
  ±30° of straight ahead, left 30°–90°, right −30°–−90°; the rear has no bumper.
- **Cliffs** (left, centre, right at +45°, 0°, −45°, 0.16 m from the centre): each casts
  one ray straight down from just under the body; it reports a cliff when the floor is not
  within 0.02 m below the wheels' contact plane (a hole, the floor's edge).
- **Wheel drop** (left, right): the wheel has touched nothing for the last three sensor
  readings (60 ms) — it hangs over a hole or the robot was lifted.
- **Buttons** B0–B2: ``press_button(i)`` holds one down for ``hold_s`` of sim time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from robots.errors import CommandOutOfRange
from robots.robot import BatteryModel, DriveLimits, SimRobot

LedColor = Literal["off", "green", "orange", "red"]
LED_COLORS: tuple[LedColor, ...] = ("off", "green", "orange", "red")
LED_RGBA = {"off": (0.2, 0.2, 0.2, 1.0), "green": (0.0, 0.9, 0.1, 1.0),
             "orange": (1.0, 0.55, 0.0, 1.0), "red": (0.95, 0.05, 0.05, 1.0)}


@dataclass(frozen=True)
class Triple:
    """Three sensors on the left, in the centre and on the right."""

    left: bool
    center: bool
    right: bool

    def any(self) -> bool:
        return self.left or self.center or self.right


@dataclass(frozen=True)
class WheelDrop:
    left: bool
    right: bool


class Kobuki(SimRobot):
    """A simulated Kobuki. Get it from the simulation: ``sim.robot("kobuki1")``."""

    kind = "kobuki"
    urdf = "kobuki.urdf"
    limits = DriveLimits(wheel_radius_m=0.035, track_m=0.230, max_linear_mps=0.7,
                         max_angular_rps=math.pi, wheel_torque_nm=1.5)
    battery_model = BatteryModel(capacity_wh=32.6, voltage_empty_v=13.2, voltage_full_v=16.8,
                                 idle_w=5.0, drive_w_per_mps=12.0, turn_w_per_rps=3.0,
                                 charge_w=40.0)
    scan_height_m = 0.123
    scan_range_max_m = 12.0
    radius_m = 0.175
    sound_names = ("on", "off", "recharge", "button", "error", "cleaning_start",
                   "cleaning_end")
    """Kobuki's built-in sequences (kobuki_msgs/Sound values 0–6)."""
    bumper_center_half_angle_rad = math.radians(30)
    cliff_angles_rad = (math.radians(45), 0.0, math.radians(-45))
    cliff_radius_m = 0.16
    cliff_drop_m = 0.02
    button_count = 3

    def _init_parts(self) -> None:
        self._led_links = [self._links["led1"], self._links["led2"]]
        self._leds: tuple[LedColor, LedColor] = ("off", "off")
        self._bumpers = Triple(False, False, False)
        self._cliffs = Triple(False, False, False)
        self._wheel_drop = WheelDrop(False, False)
        self._airborne = [0, 0]
        self._buttons_until_s = [-math.inf] * self.button_count

    # ---- commands (any thread) ------------------------------------------------------

    def set_leds(self, led1: LedColor, led2: LedColor) -> None:
        """Set both LEDs to one of ``off``, ``green``, ``orange``, ``red``."""
        for value in (led1, led2):
            if value not in LED_COLORS:
                raise CommandOutOfRange(f"{self.namespace}: unknown LED colour {value!r}; "
                                        f"colours: {', '.join(LED_COLORS)}")
        self._leds = (led1, led2)
        links = list(self._led_links)

        def recolour(client: object) -> None:
            for link, value in zip(links, (led1, led2), strict=True):
                self._client.changeVisualShape(self.body_id, link,
                                               rgbaColor=list(LED_RGBA[value]))

        self._post(recolour)

    def press_button(self, index: int, *, hold_s: float = 0.2) -> None:
        """Hold button ``index`` (0–2) down for ``hold_s`` of sim time (for tests and
        demos: the sim has no fingers)."""
        if index not in range(self.button_count):
            raise CommandOutOfRange(f"{self.namespace}: no button {index}; buttons: 0, 1, 2")
        with self._lock:
            self._buttons_until_s[index] = self._sim.time_s + hold_s

    # ---- readings (any thread) ------------------------------------------------------

    def leds(self) -> tuple[LedColor, LedColor]:
        return self._leds

    def bumpers(self) -> Triple:
        """Which bumpers are pressed (at the sensor rate)."""
        return self._bumpers

    def cliffs(self) -> Triple:
        """Which cliff sensors see no floor (at the sensor rate)."""
        return self._cliffs

    def wheel_drop(self) -> WheelDrop:
        """Which wheels hang in the air (at the sensor rate)."""
        return self._wheel_drop

    def buttons(self) -> tuple[bool, bool, bool]:
        """Whether buttons B0, B1, B2 are held down now."""
        now = self._sim.time_s
        with self._lock:
            b0, b1, b2 = (now < until for until in self._buttons_until_s)
        return (b0, b1, b2)

    # ---- simulation side ------------------------------------------------------------

    def _outline_distance_m(self, angles: np.ndarray) -> np.ndarray:
        # The scanner sits on the top plate: only its own 0.035 m housing is in the way.
        return np.full(len(angles), 0.04)

    def _sense(self, time_s: float, dt_s: float, *, scan: bool) -> None:
        super()._sense(time_s, dt_s, scan=scan)
        odom = self._odom
        cos_y, sin_y = math.cos(odom.yaw_rad), math.sin(odom.yaw_rad)
        ground = self._sim._ground_ids
        left = center = right = False
        for contact in self._contacts(bodyA=self.body_id, linkIndexA=-1):
            if contact[2] in ground:
                continue
            px, py = contact[5][0] - odom.x_m, contact[5][1] - odom.y_m
            bearing = math.atan2(-sin_y * px + cos_y * py, cos_y * px + sin_y * py)
            if abs(bearing) <= self.bumper_center_half_angle_rad:
                center = True
            elif 0 < bearing <= math.pi / 2:
                left = True
            elif -math.pi / 2 <= bearing < 0:
                right = True
        self._bumpers = Triple(left, center, right)

        # pybullet reports the centre of mass; the base origin is on the wheel axle.
        base_z = self._base_pose(self.body_id)[0][2] - self._com_z_m
        floor_z = base_z - self.limits.wheel_radius_m
        start_z = floor_z + 0.010  # just under the body (0.013 m clearance)
        end_z = floor_z - 0.10
        starts, ends = [], []
        for angle in self.cliff_angles_rad:
            x = odom.x_m + self.cliff_radius_m * math.cos(odom.yaw_rad + angle)
            y = odom.y_m + self.cliff_radius_m * math.sin(odom.yaw_rad + angle)
            starts.append([x, y, start_z])
            ends.append([x, y, end_z])
        cliff = [hit[0] < 0 or hit[3][2] < floor_z - self.cliff_drop_m
                 for hit in self._ray_batch(starts, ends)]
        self._cliffs = Triple(*cliff)

        for i, joint in enumerate(self._wheels):
            touching = bool(self._contacts(bodyA=self.body_id, linkIndexA=joint))
            self._airborne[i] = 0 if touching else self._airborne[i] + 1
        self._wheel_drop = WheelDrop(self._airborne[0] >= 3, self._airborne[1] >= 3)
