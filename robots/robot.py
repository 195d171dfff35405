"""The simulated robot base class and the readings every robot gives.

A :class:`SimRobot` is a handle that the :class:`robots.sim.Simulation` creates for each
robot of its world (``sim.robot("emili1")``). Its public methods are safe from any thread:

- commands (``set_cmd_vel``, and the kind-specific ones: lift, LEDs …) are stored and
  applied by the simulation at its next physics step;
- readings (``pose``, ``odometry``, ``scan``, ``battery`` …) return immutable snapshots that
  the simulation thread replaces as it steps; none of them calls into pybullet.

Models shared by all kinds:

- **Drive.** ``set_cmd_vel(linear_mps, angular_rps)`` is clamped to the kind's limits and
  turned into wheel speeds by differential-drive kinematics
  (``left = (v - w * track / 2) / r``); each wheel runs under pybullet velocity control with
  a maximum motor torque, so robots accelerate quickly but not instantly, push against walls
  and slip when blocked.
- **Watchdog.** When no ``set_cmd_vel`` came for ``cmd_timeout_s`` of *sim* time
  (default 0.5 s, an argument of the Simulation), the robot stops — as a real base does when
  its driver loses the connection. Send commands at ≥ 5 Hz to keep driving.
- **Odometry** is ground truth in the world frame (no drift): pose from the base link,
  twist from its velocity rotated into the robot frame (``linear_mps`` along the heading).
- **Laser scan.** One 360° scan around the base centre, cast with ``rayTestBatch`` at the
  scanner height (``scan_rate_hz``, default 10 Hz). Every ray starts where it leaves the
  robot's own outline, so the robot never sees itself; ranges are measured from the centre,
  ``inf`` where nothing is hit within ``range_max_m``.
- **Battery.** Power = idle draw (the kind's, or the world's ``battery.idle_w`` for this
  robot) + a part proportional to speed and turn rate (+ the lift
  while it moves, on EMILI); the state of charge falls by power × dt / capacity. While the
  robot's centre is inside a ``charging`` station the charger supplies the robot and
  charges at ``charge_w``. Voltage is linear in the state of charge between empty and full;
  current is negative while discharging (the sensor_msgs/BatteryState convention). An empty
  battery stops the drive until it is recharged.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import pybullet  # type: ignore[import-not-found]  # no stubs

from robots.errors import CommandOutOfRange
from robots.world import RobotSpec

if TYPE_CHECKING:
    from pybullet_utils.bullet_client import BulletClient  # type: ignore[import-untyped]

    from robots.sim import Simulation

URDF_DIR = Path(__file__).parent / "urdf"
"""Where the robots' URDF files live."""


@dataclass(frozen=True)
class Pose2D:
    """Position on the floor (metres) and heading (radians, 0 = +x, counter-clockwise)."""

    x_m: float
    y_m: float
    yaw_rad: float


@dataclass(frozen=True)
class Odometry:
    """What nav_msgs/Odometry carries: the pose in the world (``odom``) frame and the twist
    in the robot (``base_link``) frame, stamped with the sim time ``time_s``."""

    time_s: float
    x_m: float
    y_m: float
    yaw_rad: float
    linear_mps: float
    angular_rps: float

    @property
    def pose(self) -> Pose2D:
        return Pose2D(self.x_m, self.y_m, self.yaw_rad)


@dataclass(frozen=True)
class LaserScan:
    """What sensor_msgs/LaserScan carries. ``ranges_m[i]`` is the distance from the robot
    centre at angle ``angle_min_rad + i * angle_increment_rad`` (robot frame,
    counter-clockwise from straight ahead); ``inf`` where nothing was hit."""

    time_s: float
    angle_min_rad: float
    angle_max_rad: float
    angle_increment_rad: float
    range_min_m: float
    range_max_m: float
    ranges_m: tuple[float, ...]
    scan_time_s: float

    def range_at(self, angle_rad: float) -> float:
        """The range of the beam nearest to ``angle_rad`` (robot frame)."""
        wrapped = (angle_rad - self.angle_min_rad) % (2 * math.pi)
        index = round(wrapped / self.angle_increment_rad) % len(self.ranges_m)
        return self.ranges_m[index]


@dataclass(frozen=True)
class BatteryState:
    """What sensor_msgs/BatteryState carries. ``fraction`` is 0–1 (BatteryState.percentage
    is a fraction too); ``current_a`` is negative while discharging."""

    time_s: float
    fraction: float
    voltage_v: float
    current_a: float
    charging: bool
    capacity_wh: float

    @property
    def percentage(self) -> float:
        """State of charge in percent (0–100)."""
        return self.fraction * 100.0


@dataclass(frozen=True)
class BatteryModel:
    """Parameters of the battery model (see the module docstring)."""

    capacity_wh: float
    voltage_empty_v: float
    voltage_full_v: float
    idle_w: float
    drive_w_per_mps: float
    turn_w_per_rps: float
    charge_w: float


@dataclass(frozen=True)
class DriveLimits:
    """Differential-drive geometry and limits."""

    wheel_radius_m: float
    track_m: float
    max_linear_mps: float
    max_angular_rps: float
    wheel_torque_nm: float


@dataclass(frozen=True)
class Sound:
    """One ``play_sound`` call: sim time and the sound's name."""

    time_s: float
    name: str


@dataclass(frozen=True)
class _Cmd:
    linear_mps: float
    angular_rps: float
    time_s: float


class SimRobot:
    """A simulated differential-drive robot; subclasses add their kind's parts.

    Created by the :class:`~robots.sim.Simulation`, never by hand. Subclasses set the class
    attributes below and may override the sim-thread hooks ``_apply(time_s)`` and
    ``_sense(time_s, tick)``.
    """

    kind: ClassVar[str]
    urdf: ClassVar[str]
    limits: ClassVar[DriveLimits]
    battery_model: ClassVar[BatteryModel]
    scan_height_m: ClassVar[float]
    """Height of the scan plane above the floor."""
    scan_beams: ClassVar[int] = 360
    scan_range_max_m: ClassVar[float] = 20.0
    sound_names: ClassVar[tuple[str, ...] | None] = None
    """The sounds the robot knows; None: any name (a file name or a text to speak)."""
    path_interval_s: ClassVar[float] = 0.1

    def __init__(self, sim: Simulation, spec: RobotSpec, body_id: int, index: int) -> None:
        self._sim = sim
        self._client: BulletClient = sim._client
        self.spec = spec
        self.namespace = spec.namespace
        self.body_id = body_id
        self.index = index
        #: Cast the laser (the most expensive sensor, ~1.3 ms a scan). The sim node turns
        #: it off while nobody subscribes to the robot's ``scan``; ``scan()`` then keeps
        #: returning the last one.
        self.scan_enabled = True
        self._lock = threading.Lock()
        self._links = {self._client.getJointInfo(body_id, j)[12].decode(): j
                       for j in range(self._client.getNumJoints(body_id))}
        self._joints = {self._client.getJointInfo(body_id, j)[1].decode(): j
                        for j in range(self._client.getNumJoints(body_id))}
        # Bound once: BulletClient looks every call up by name (a few µs each), and these
        # run every step for every robot.
        cid = self._client._client
        self._base_pose = functools.partial(pybullet.getBasePositionAndOrientation,
                                            physicsClientId=cid)
        self._base_velocity = functools.partial(pybullet.getBaseVelocity, physicsClientId=cid)
        self._motors = functools.partial(pybullet.setJointMotorControlArray,
                                         physicsClientId=cid)
        self._ray_batch = functools.partial(pybullet.rayTestBatch, physicsClientId=cid)
        self._contacts = functools.partial(pybullet.getContactPoints, physicsClientId=cid)
        self._joint_state = functools.partial(pybullet.getJointState, physicsClientId=cid)
        self._com_z_m = float(self._client.getDynamicsInfo(body_id, -1)[3][2])
        self._wheels = [self._joints["left_wheel_joint"], self._joints["right_wheel_joint"]]
        self._cmd = _Cmd(0.0, 0.0, -math.inf)
        self._applied: tuple[float, float] | None = None
        start = spec.start
        self._odom = Odometry(0.0, start.x_m, start.y_m, start.yaw_rad, 0.0, 0.0)
        self._init_battery(spec)
        self._scan: LaserScan | None = None
        self._sounds: list[Sound] = []
        self._path: list[tuple[float, float]] = [(start.x_m, start.y_m)]
        self._next_path_s = 0.0
        self._extra_power_w = 0.0
        #: Beams per scan: the world's ``laser.beams`` for this robot, else the kind's.
        self.beams = spec.laser.beams or self.scan_beams
        angles = np.linspace(-math.pi, math.pi, self.beams, endpoint=False)
        self._scan_angles = angles
        self._scan_dirs = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        self._scan_start_m = self._outline_distance_m(angles) + 0.01
        self._setup_dynamics()
        self._init_parts()

    def _init_parts(self) -> None:
        """Called at the end of construction: set up the kind's own parts (joints, links,
        their state). The base has none."""

    # ---- commands (any thread) ------------------------------------------------------

    def set_cmd_vel(self, linear_mps: float, angular_rps: float) -> None:
        """Drive with ``linear_mps`` forward and ``angular_rps`` counter-clockwise (the
        geometry_msgs/Twist ``linear.x`` and ``angular.z``), clamped to the robot's limits.
        Applied at the next physics step; repeat at ≥ 5 Hz or the watchdog stops the robot
        after ``cmd_timeout_s`` of sim time."""
        lim = self.limits
        v, w = float(linear_mps), float(angular_rps)
        if not (math.isfinite(v) and math.isfinite(w)):
            raise CommandOutOfRange(f"{self.namespace}: cmd_vel must be finite numbers, "
                                    f"got ({linear_mps}, {angular_rps})")
        v = max(-lim.max_linear_mps, min(lim.max_linear_mps, v))
        w = max(-lim.max_angular_rps, min(lim.max_angular_rps, w))
        self._cmd = _Cmd(v, w, self._sim.time_s)

    def stop(self) -> None:
        """Stop driving now (zero velocity command)."""
        self.set_cmd_vel(0.0, 0.0)

    def play_sound(self, name: str) -> None:
        """Play a sound: recorded with the sim time in :meth:`sounds` (the sim has no
        speaker). Kinds with a fixed set of sounds reject other names, listing them."""
        if self.sound_names is not None and name not in self.sound_names:
            raise CommandOutOfRange(f"{self.namespace}: unknown sound {name!r}; "
                                    f"sounds: {', '.join(self.sound_names)}")
        with self._lock:
            self._sounds.append(Sound(self._sim.time_s, name))

    # ---- readings (any thread) ------------------------------------------------------

    def pose(self) -> Pose2D:
        """Where the robot is now (ground truth, world frame)."""
        return self._odom.pose

    def odometry(self) -> Odometry:
        """Pose and twist at the last physics step, stamped with its sim time."""
        return self._odom

    def scan(self) -> LaserScan | None:
        """The latest 360° laser scan (``scan_rate_hz``), or None before the first one."""
        return self._scan

    def battery(self) -> BatteryState:
        """The battery now: state of charge, voltage, current, charging flag."""
        return self._battery

    def sounds(self) -> list[Sound]:
        """Every sound played so far, oldest first."""
        with self._lock:
            return list(self._sounds)

    def path(self) -> list[tuple[float, float]]:
        """The positions the robot has driven through (sampled every 0.1 s sim time when it
        moved), for pictures."""
        with self._lock:
            return list(self._path)

    def cmd_vel(self) -> tuple[float, float]:
        """The velocity the drive is set to (after clamping, the watchdog and the battery)."""
        return self._applied or (0.0, 0.0)

    def __repr__(self) -> str:
        p = self._odom
        return (f"<{type(self).__name__} {self.namespace!r} at ({p.x_m:.2f}, {p.y_m:.2f}, "
                f"{math.degrees(p.yaw_rad):.0f}°)>")

    # ---- simulation side (sim thread only) ------------------------------------------

    def _outline_distance_m(self, angles: np.ndarray) -> np.ndarray:
        """Distance from the base centre to the robot's outline along each angle, in the
        scan plane: where the laser rays start. Subclasses describe their footprint."""
        raise NotImplementedError

    def _setup_dynamics(self) -> None:
        c = self._client
        # Casters and body slide (frictionless casters); only the wheels grip the floor.
        c.changeDynamics(self.body_id, -1, lateralFriction=0.0, spinningFriction=0.0,
                         rollingFriction=0.0)
        for joint in self._wheels:
            c.changeDynamics(self.body_id, joint, lateralFriction=1.0, spinningFriction=0.0,
                             rollingFriction=0.0)
            # The URDF loader gives every joint a velocity motor; free the wheels first.
            c.setJointMotorControl2(self.body_id, joint, c.VELOCITY_CONTROL, force=0.0)

    def _post(self, action: Callable[[BulletClient], None]) -> None:
        """Run ``action(client)`` in the sim thread before the next step."""
        self._sim._post(action)

    def _drive_command(self, time_s: float) -> tuple[float, float]:
        cmd = self._cmd
        if time_s - cmd.time_s > self._sim.cmd_timeout_s or self._charge_wh <= 0.0:
            return (0.0, 0.0)
        return (cmd.linear_mps, cmd.angular_rps)

    def _apply(self, time_s: float) -> None:
        """Before a physics step: set the wheel motors if the command changed."""
        target = self._drive_command(time_s)
        if target == self._applied:
            return
        self._applied = target
        v, w = target
        lim = self.limits
        half = lim.track_m / 2
        left = (v - w * half) / lim.wheel_radius_m
        right = (v + w * half) / lim.wheel_radius_m
        self._motors(
            self.body_id, self._wheels, pybullet.VELOCITY_CONTROL,
            targetVelocities=[left, right], forces=[lim.wheel_torque_nm] * 2)

    def _update_state(self, time_s: float) -> None:
        """After every physics step: the odometry snapshot."""
        # The centre of mass, which both URDFs put straight above the base origin.
        (x, y, _z), quat = self._base_pose(self.body_id)
        (vx, vy, _vz), (_wx, _wy, wz) = self._base_velocity(self.body_id)
        qx, qy, qz, qw = quat
        yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
        linear = vx * math.cos(yaw) + vy * math.sin(yaw)
        self._odom = Odometry(time_s, x, y, yaw, linear, wz)

    def _sense(self, time_s: float, dt_s: float, *, scan: bool) -> None:
        """At the sensor rate (``sensor_rate_hz``): battery, path and, when ``scan``, the
        laser. Subclasses extend it with their own sensors."""
        odom = self._odom
        self._update_battery(time_s, dt_s, odom)
        if time_s >= self._next_path_s:
            self._next_path_s = time_s + self.path_interval_s
            last = self._path[-1]
            if math.hypot(odom.x_m - last[0], odom.y_m - last[1]) > 0.02:
                with self._lock:
                    self._path.append((odom.x_m, odom.y_m))
        if scan and self.scan_enabled:
            self._scan = self._cast_scan(time_s, odom)

    def _init_battery(self, spec: RobotSpec) -> None:
        """The battery as the world gives it (capacity, charge, idle draw), else the kind's."""
        model = self.battery_model
        capacity = spec.battery.capacity_wh or model.capacity_wh
        self._charge_wh = capacity * spec.battery.initial_fraction
        self._capacity_wh = capacity
        self._battery = self._battery_state(0.0, capacity, 0.0, False)
        self._idle_w = model.idle_w if spec.battery.idle_w is None else spec.battery.idle_w

    def _battery_state(self, time_s: float, capacity_wh: float, power_w: float,
                       charging: bool) -> BatteryState:
        model = self.battery_model
        fraction = max(0.0, min(1.0, self._charge_wh / capacity_wh))
        voltage = model.voltage_empty_v + fraction * (model.voltage_full_v
                                                      - model.voltage_empty_v)
        current = (model.charge_w if charging else -power_w) / voltage
        return BatteryState(time_s, fraction, voltage, current, charging, capacity_wh)

    def _update_battery(self, time_s: float, dt_s: float, odom: Odometry) -> None:
        model = self.battery_model
        charging = any(s.contains(odom.x_m, odom.y_m)
                       for s in self._sim._charging_stations)
        power = (self._idle_w + model.drive_w_per_mps * abs(odom.linear_mps)
                 + model.turn_w_per_rps * abs(odom.angular_rps) + self._extra_power_w)
        delta_wh = (model.charge_w if charging else -power) * dt_s / 3600.0
        self._charge_wh = max(0.0, min(self._capacity_wh, self._charge_wh + delta_wh))
        self._battery = self._battery_state(time_s, self._capacity_wh, power, charging)

    def _cast_scan(self, time_s: float, odom: Odometry) -> LaserScan:
        cos_y, sin_y = math.cos(odom.yaw_rad), math.sin(odom.yaw_rad)
        rot = np.array([[cos_y, -sin_y], [sin_y, cos_y]])
        dirs = self._scan_dirs @ rot.T
        center = np.array([odom.x_m, odom.y_m])
        starts = center + dirs * self._scan_start_m[:, None]
        ends = center + dirs * self.scan_range_max_m
        z = np.full((len(dirs), 1), self.scan_height_m)
        hits = self._ray_batch(np.hstack([starts, z]).tolist(),
                                         np.hstack([ends, z]).tolist())
        fractions = np.array([h[2] if h[0] >= 0 else np.inf for h in hits])
        ranges = self._scan_start_m + fractions * (self.scan_range_max_m - self._scan_start_m)
        increment = 2 * math.pi / self.beams
        return LaserScan(
            time_s=time_s, angle_min_rad=float(self._scan_angles[0]),
            angle_max_rad=float(self._scan_angles[-1]), angle_increment_rad=increment,
            range_min_m=float(self._scan_start_m.min()), range_max_m=self.scan_range_max_m,
            ranges_m=tuple(ranges.tolist()), scan_time_s=1.0 / self._sim.scan_rate_hz)
