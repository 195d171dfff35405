"""EMILI: the intralogistics transport robot — lift, LED strip, display, speaker, line
sensor.

Geometry (``robots/urdf/emili.urdf``): body 0.90 × 0.60 × 0.30 m, 0.05 m ground clearance,
wheels of radius 0.10 m on a 0.50 m track, ball casters front and back; 72 kg in all.
Limits: 1.0 m/s, 1.0 rad/s. Battery (default): 1 kWh, 21–29.4 V (7S Li-ion).

Parts and their models:

- **Laser.** The front and back scanners are published as one merged 360° scan around the
  base centre, 0.10 m above the floor, 360 beams, 20 m range (see :class:`SimRobot`).
- **Lift** (scissor lift, a prismatic joint): ``set_lift(height_m)`` moves the load plate to
  0–0.30 m above its lowered position at up to 0.10 m/s under position control;
  ``lift_height()`` reads the joint. It draws 100 W while it moves.
- **LED strip**: ``set_leds(r, g, b)`` (0–1 each) recolours the strip's visual shape, so
  the colour shows in any rendered picture.
- **Display** (``set_display``) and **speaker** (``play_sound``, any name) are recorded.
- **Line sensor**: a ground camera 0.30 m ahead of the axle sees a 0.15 × 0.20 m patch of
  floor. ``line_sensor()`` is the lateral offset of the nearest lane tape from the patch
  centre — computed from the world's tape polylines, not from pixels: positive when the
  tape is to the robot's left (steer ``angular_rps = k * offset`` to follow it), None when
  no tape is in view.
"""

from __future__ import annotations

import math

import numpy as np

from robots.errors import CommandOutOfRange
from robots.robot import BatteryModel, DriveLimits, SimRobot


class Emili(SimRobot):
    """A simulated EMILI. Get it from the simulation: ``sim.robot("emili1")``."""

    kind = "emili"
    urdf = "emili.urdf"
    limits = DriveLimits(wheel_radius_m=0.10, track_m=0.50, max_linear_mps=1.0,
                         max_angular_rps=1.0, wheel_torque_nm=40.0)
    battery_model = BatteryModel(capacity_wh=1000.0, voltage_empty_v=21.0,
                                 voltage_full_v=29.4, idle_w=30.0, drive_w_per_mps=80.0,
                                 turn_w_per_rps=40.0, charge_w=300.0)
    scan_height_m = 0.10
    body_half_length_m = 0.45
    body_half_width_m = 0.30
    lift_max_m = 0.30
    lift_speed_mps = 0.10
    lift_power_w = 100.0
    camera_offset_m = 0.30
    """How far ahead of the axle the ground camera looks."""
    camera_half_width_m = 0.10
    """Half the width of floor the ground camera sees across the robot."""
    camera_half_length_m = 0.075
    """Half the length of floor the ground camera sees along the robot."""

    def _init_parts(self) -> None:
        self._lift_joint = self._joints["lift_joint"]
        self._led_link = self._links["led_strip"]
        self._lift_target_m = 0.0
        self._lift_m = 0.0
        self._leds: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._display = ""
        self._post(self._hold_lift)

    # ---- commands (any thread) ------------------------------------------------------

    def set_lift(self, height_m: float) -> None:
        """Move the lift plate to ``height_m`` (0–0.30 m above lowered); returns at once,
        the lift travels at 0.10 m/s — watch :meth:`lift_height`."""
        height = float(height_m)
        if not 0.0 <= height <= self.lift_max_m:
            raise CommandOutOfRange(f"{self.namespace}: lift height {height_m} m is out of "
                                    f"range 0–{self.lift_max_m} m")
        self._lift_target_m = height
        self._post(self._hold_lift)

    def set_leds(self, r: float, g: float, b: float) -> None:
        """Colour the LED strip; each channel 0–1 (std_msgs/ColorRGBA without alpha)."""
        color = (float(r), float(g), float(b))
        if not all(0.0 <= c <= 1.0 for c in color):
            raise CommandOutOfRange(f"{self.namespace}: LED colour channels must be 0–1, "
                                    f"got {color}")
        self._leds = color
        link = self._led_link

        def recolour(client: object) -> None:
            self._client.changeVisualShape(self.body_id, link, rgbaColor=[*color, 1.0])

        self._post(recolour)

    def set_display(self, text: str) -> None:
        """Show ``text`` on the front display."""
        self._display = str(text)

    # ---- readings (any thread) ------------------------------------------------------

    def lift_target(self) -> float:
        """The commanded lift height, metres."""
        return self._lift_target_m

    def lift_height(self) -> float:
        """The lift plate's height above lowered now, metres (read at the sensor rate)."""
        return self._lift_m

    def leds(self) -> tuple[float, float, float]:
        """The LED strip's colour (r, g, b), each 0–1."""
        return self._leds

    def display(self) -> str:
        """What the display shows."""
        return self._display

    def line_sensor(self) -> float | None:
        """Lateral offset in metres of the nearest lane tape under the ground camera:
        positive when the tape is to the left, None when the camera sees no tape.

        The camera sees a patch of floor 0.15 m long and 0.20 m wide centred 0.30 m ahead
        of the axle. For each lane, the tape pieces inside the patch are averaged (weighted
        by length) into one lateral position — on a straight tape that is where it crosses
        the patch, at a corner it leans towards the new direction, as a camera's line
        detector would. The lane whose position is nearest the centre wins.
        """
        odom = self._odom
        c, s = math.cos(odom.yaw_rad), math.sin(odom.yaw_rad)
        cam_x = odom.x_m + self.camera_offset_m * c
        cam_y = odom.y_m + self.camera_offset_m * s
        best: float | None = None
        for lane in self._sim.world.lanes:
            half_u = self.camera_half_length_m + lane.width_m / 2
            half_v = self.camera_half_width_m + lane.width_m / 2
            # The polyline in the camera frame: u ahead, v to the left.
            pts = [(c * (x - cam_x) + s * (y - cam_y), -s * (x - cam_x) + c * (y - cam_y))
                   for x, y in lane.points_m]
            total = weighted = 0.0
            for a, b in zip(pts, pts[1:], strict=False):
                piece = _clip(a, b, half_u, half_v)
                if piece is None:
                    continue
                (u0, v0), (u1, v1) = piece
                length = math.hypot(u1 - u0, v1 - v0)
                if length == 0.0:
                    continue
                total += length
                weighted += length * (v0 + v1) / 2
            if total > 0.0:
                offset = weighted / total
                if best is None or abs(offset) < abs(best):
                    best = offset
        return best

    # ---- simulation side ------------------------------------------------------------

    def _outline_distance_m(self, angles: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            along = self.body_half_length_m / np.abs(np.cos(angles))
            across = self.body_half_width_m / np.abs(np.sin(angles))
        result: np.ndarray = np.minimum(along, across)
        return result

    def _hold_lift(self, client: object) -> None:
        self._client.setJointMotorControl2(
            self.body_id, self._lift_joint, self._client.POSITION_CONTROL,
            targetPosition=self._lift_target_m, force=3000.0, maxVelocity=self.lift_speed_mps)

    def _sense(self, time_s: float, dt_s: float, *, scan: bool) -> None:
        height = float(self._joint_state(self.body_id, self._lift_joint)[0])
        moving = abs(height - self._lift_m) > 1e-4
        self._lift_m = height
        self._extra_power_w = self.lift_power_w if moving else 0.0
        super()._sense(time_s, dt_s, scan=scan)


def _clip(a: tuple[float, float], b: tuple[float, float], half_u: float, half_v: float
          ) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The part of segment a–b inside the rectangle |u| <= half_u, |v| <= half_v
    (Liang–Barsky), or None."""
    du, dv = b[0] - a[0], b[1] - a[1]
    t0, t1 = 0.0, 1.0
    for p, q in ((-du, a[0] + half_u), (du, half_u - a[0]),
                 (-dv, a[1] + half_v), (dv, half_v - a[1])):
        if p == 0.0:
            if q < 0.0:
                return None
            continue
        t = q / p
        if p < 0.0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 > t1:
            return None
    return ((a[0] + t0 * du, a[1] + t0 * dv), (a[0] + t1 * du, a[1] + t1 * dv))
