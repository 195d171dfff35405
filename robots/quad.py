"""A simple quadrotor for the simulation: a kinematic flyer with an altitude (world kind
``quad``).

Not an aerodynamic model: the flyer follows a velocity command (world frame, metres per
second, plus a yaw rate) under an acceleration limit, like a multicopter whose autopilot
tracks velocity well. What matters for cooperation is what it can and cannot reach:

- **Altitude.** ``z_m`` is the height of its body above the floor; it stays ≥ 0 (it sits
  on the floor when landed) and ≤ ``max_alt_m``.
- **Obstacles.** Before each move a ray is cast at its altitude from where it is to where it
  would be (plus ``clearance_m``): a wall, shelf or obstacle taller than its altitude stops
  the horizontal motion; one lower than its altitude is flown over. It has no collision
  shape itself: ground robots and their lasers do not see it.
- **Battery.** Hovering draws ``hover_w``; moving adds ``drive_w_per_mps`` per m/s; on the
  floor only the idle draw. An empty battery makes it descend and stop.
- **Watchdog.** Without a new command for ``cmd_timeout_s`` (sim time) it brakes to a hover.
- **Motors.** :meth:`Quad.set_motors` (False) stops them, as disarming does: in the air it
  falls (gravity, no lift) until it hits the floor; commands are ignored until they run again.
- **The world.** It never leaves the floor's rectangle: at an edge it stops as at a wall.

``set_cmd_vel(linear, angular)`` (the ROS contract's Twist) flies forward along its heading
at its altitude; :meth:`Quad.set_velocity` sets all three axes.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import pybullet  # type: ignore[import-not-found]  # no stubs

from robots.errors import CommandOutOfRange
from robots.robot import BatteryModel, DriveLimits, Odometry, SimRobot
from robots.world import RobotSpec

if TYPE_CHECKING:
    from robots.sim import Simulation


@dataclass(frozen=True)
class Position3D:
    """Where the flyer is (world frame, metres) and how it moves (m/s), at ``time_s``."""

    time_s: float
    x_m: float
    y_m: float
    z_m: float
    yaw_rad: float
    vx_mps: float
    vy_mps: float
    vz_mps: float


@dataclass(frozen=True)
class _VelCmd:
    vx: float
    vy: float
    vz: float
    yaw_rate: float
    time_s: float


class Quad(SimRobot):
    """A kinematic quadrotor (see the module doc). Created by the Simulation."""

    kind = "quad"
    urdf = "quad.urdf"
    # wheel_radius_m is the spawn height of the body above the floor (it starts landed).
    limits = DriveLimits(wheel_radius_m=0.03, track_m=0.0, max_linear_mps=3.0,
                         max_angular_rps=math.pi / 2, wheel_torque_nm=0.0)
    battery_model = BatteryModel(capacity_wh=60.0, voltage_empty_v=13.2, voltage_full_v=16.8,
                                 idle_w=2.0, drive_w_per_mps=8.0, turn_w_per_rps=0.0,
                                 charge_w=120.0)
    scan_height_m = 0.0
    hover_w: ClassVar[float] = 150.0
    max_climb_mps: ClassVar[float] = 1.5
    max_accel_mps2: ClassVar[float] = 3.0
    max_alt_m: ClassVar[float] = 30.0
    clearance_m: ClassVar[float] = 0.3
    body_offset_m: ClassVar[float] = 0.03
    """Height of the body centre above the floor when landed."""

    def __init__(self, sim: Simulation, spec: RobotSpec, body_id: int, index: int) -> None:
        # Not SimRobot.__init__: a flyer has no wheels, joints or laser.
        self._sim = sim
        self._client = sim._client
        self.spec = spec
        self.namespace = spec.namespace
        self.body_id = body_id
        self.index = index
        self.scan_enabled = False
        self._lock = threading.Lock()
        cid = self._client._client
        pybullet.changeDynamics(body_id, -1, mass=0.0, physicsClientId=cid)  # kinematic
        self._cid = cid
        start = spec.start
        self._x, self._y, self._z = start.x_m, start.y_m, 0.0
        self._yaw = start.yaw_rad
        self._v = np.zeros(3)
        self._yaw_rate = 0.0
        self._vcmd = _VelCmd(0.0, 0.0, 0.0, 0.0, -math.inf)
        self._pos = Position3D(0.0, self._x, self._y, 0.0, self._yaw, 0.0, 0.0, 0.0)
        self._odom = Odometry(0.0, self._x, self._y, self._yaw, 0.0, 0.0)
        self._init_battery(spec)
        self._scan = None
        self._sounds = []
        self._path = [(start.x_m, start.y_m)]
        self._next_path_s = 0.0
        self._extra_power_w = 0.0
        self._blocked = False
        self._motors_on = True
        width, depth = sim.world.floor.size_m
        self._bounds = (0.0, 0.0, float(width), float(depth))

    # ---- commands (any thread) ------------------------------------------------------

    def set_velocity(self, vx_mps: float, vy_mps: float, vz_mps: float = 0.0,
                     yaw_rate_rps: float = 0.0) -> None:
        """Fly with this velocity (world frame: x east, y north, z up), clamped to the
        limits; repeat at ≥ 5 Hz or the watchdog brakes to a hover."""
        values = (vx_mps, vy_mps, vz_mps, yaw_rate_rps)
        if not all(math.isfinite(float(v)) for v in values):
            raise CommandOutOfRange(f"{self.namespace}: velocity must be finite numbers, got "
                                    f"{values}")
        vmax = self.limits.max_linear_mps
        speed = math.hypot(vx_mps, vy_mps)
        scale = vmax / speed if speed > vmax else 1.0
        climb = max(-self.max_climb_mps, min(self.max_climb_mps, float(vz_mps)))
        rate = max(-self.limits.max_angular_rps, min(self.limits.max_angular_rps,
                                                     float(yaw_rate_rps)))
        self._vcmd = _VelCmd(vx_mps * scale, vy_mps * scale, climb, rate, self._sim.time_s)

    def set_cmd_vel(self, linear_mps: float, angular_rps: float) -> None:
        """Forward along the heading and a yaw rate, at the current altitude."""
        v = float(linear_mps)
        if not (math.isfinite(v) and math.isfinite(float(angular_rps))):
            raise CommandOutOfRange(f"{self.namespace}: cmd_vel must be finite numbers, "
                                    f"got ({linear_mps}, {angular_rps})")
        self.set_velocity(v * math.cos(self._yaw), v * math.sin(self._yaw), 0.0, angular_rps)

    def set_motors(self, on: bool) -> None:
        """Run or stop the motors (stopped: no lift, velocity commands have no effect; in
        the air the flyer falls)."""
        self._motors_on = bool(on)

    @property
    def motors(self) -> bool:
        """Whether the motors run (see :meth:`set_motors`)."""
        return self._motors_on

    # ---- readings (any thread) ------------------------------------------------------

    def position(self) -> Position3D:
        """Position, altitude and velocity at the last step."""
        return self._pos

    @property
    def altitude_m(self) -> float:
        return self._pos.z_m

    @property
    def landed(self) -> bool:
        return self._pos.z_m <= 0.01

    @property
    def blocked(self) -> bool:
        """True while an obstacle taller than its altitude stops its horizontal motion."""
        return self._blocked

    def cmd_vel(self) -> tuple[float, float]:
        c = self._vcmd
        return (math.hypot(c.vx, c.vy), c.yaw_rate)

    # ---- simulation side (sim thread only) ------------------------------------------

    def _apply(self, time_s: float) -> None:
        dt = self._sim.step_s
        cmd = self._vcmd
        if time_s - cmd.time_s > self._sim.cmd_timeout_s:
            target = np.zeros(3)
            rate = 0.0
        else:
            target = np.array([cmd.vx, cmd.vy, cmd.vz])
            rate = cmd.yaw_rate
        if self._charge_wh <= 0.0:
            target = np.array([0.0, 0.0, -0.5])  # empty: come down
        if not self._motors_on:
            if self._z > 0.0:  # no lift: a fall, keeping its horizontal speed
                self._v = self._v + np.array([0.0, 0.0, -9.81 * dt])
            else:
                self._v = np.zeros(3)
            rate = 0.0
        else:
            if self._z <= 0.0 and target[2] <= 0.0:
                target = np.zeros(3)  # on the floor it does not slide
            dv = target - self._v
            step = self.max_accel_mps2 * dt
            norm = float(np.linalg.norm(dv))
            self._v = self._v + (dv if norm <= step else dv * (step / norm))
        nx = self._x + self._v[0] * dt
        ny = self._y + self._v[1] * dt
        self._blocked = False
        if self._v[0] or self._v[1]:
            speed = math.hypot(self._v[0], self._v[1])
            ahead = (self._x + self._v[0] / speed * self.clearance_m + self._v[0] * dt,
                     self._y + self._v[1] / speed * self.clearance_m + self._v[1] * dt)
            z = max(self._z, 0.02)
            hit = pybullet.rayTest([self._x, self._y, z], [ahead[0], ahead[1], z],
                                   physicsClientId=self._cid)[0]
            if hit[0] >= 0 and hit[0] != self.body_id:
                self._blocked = True
                self._v[0] = self._v[1] = 0.0
                nx, ny = self._x, self._y
        x0, y0, x1, y1 = self._bounds
        if not (x0 <= nx <= x1 and y0 <= ny <= y1):  # the world's edge stops it
            self._blocked = True
            nx, ny = min(max(nx, x0), x1), min(max(ny, y0), y1)
            self._v[0] = self._v[1] = 0.0
        self._x, self._y = float(nx), float(ny)
        self._z = float(min(self.max_alt_m, max(0.0, self._z + self._v[2] * dt)))
        if self._z <= 0.0:
            if not self._motors_on:
                self._v[:] = 0.0  # it hit the floor
            self._v[2] = 0.0
        self._yaw = math.remainder(self._yaw + rate * dt, 2 * math.pi)
        self._yaw_rate = rate
        pybullet.resetBasePositionAndOrientation(
            self.body_id, [self._x, self._y, self._z + self.body_offset_m],
            pybullet.getQuaternionFromEuler([0.0, 0.0, self._yaw]), physicsClientId=self._cid)

    def _update_state(self, time_s: float) -> None:
        vx, vy, vz = (float(v) for v in self._v)
        self._pos = Position3D(time_s, self._x, self._y, self._z, self._yaw, vx, vy, vz)
        c, s = math.cos(self._yaw), math.sin(self._yaw)
        self._odom = Odometry(time_s, self._x, self._y, self._yaw, vx * c + vy * s,
                              self._yaw_rate)

    def _sense(self, time_s: float, dt_s: float, *, scan: bool) -> None:
        self._extra_power_w = self.hover_w if self._z > 0.01 and self._motors_on else 0.0
        # The base class does battery and path; the flyer has no laser (scan=False).
        super()._sense(time_s, dt_s, scan=False)

    def _update_battery(self, time_s: float, dt_s: float, odom: Odometry) -> None:
        # Horizontal speed counts whatever the heading (the base model uses linear_mps).
        moving = Odometry(odom.time_s, odom.x_m, odom.y_m, odom.yaw_rad,
                          math.hypot(self._pos.vx_mps, self._pos.vy_mps), 0.0)
        super()._update_battery(time_s, dt_s, moving)

    def _outline_distance_m(self, angles: np.ndarray) -> np.ndarray:
        return np.full(len(angles), 0.3)
