"""The sim node: a running :class:`~robots.sim.Simulation` on ROS 2, as the robots' topic
contract (:mod:`robots.topics`) describes it, and ``beehave sim`` to run one.

::

    from beehave.ros.context import RosContext
    from robots.node import SimNode
    from robots.sim import Simulation

    sim = Simulation("warehouse", real_time_factor=1.0)
    ros = RosContext()
    node = SimNode(sim, ros)        # creates the nodes, publishers and subscriptions
    ros.start(); sim.start()
    ...
    sim.stop(); node.destroy(); ros.shutdown(); sim.close()

Nodes. One rclpy node per robot, named ``sim`` in the robot's namespace (``/emili1/sim``,
``/kobuki1/sim``), so every topic name is the contract's relative one and
``ros2 node info /emili1/sim`` shows exactly one robot's interface; plus one node ``/sim``
that publishes ``/clock``. All of them are created through the caller's
:class:`~beehave.ros.context.RosContext` and served by its executor thread.

Threads. Readings are published from the sim thread (``Simulation.on_step`` callbacks; an
rclpy publish is thread-safe), so each message carries the sim time of the step it
describes: ``odom`` and the 50 Hz sensors from one callback every ``round(rate_hz / 50)``
steps (48 Hz at the default 240 Hz), ``battery_state`` every ``round(rate_hz / 5)`` steps,
``scan`` from the 50 Hz callback when the robot has a newer scan, and ``/clock`` from a
callback on every step that publishes whenever another ``1 / clock_rate_hz`` of sim time
has passed (exactly 100 Hz on average, whatever the physics rate). Commands arrive in the
executor thread and go straight to the robot's thread-safe setters.

Refused commands. A command the robot cannot take (NaN velocity, lift height out of range,
LED channel outside 0–1, unknown Kobuki colour or sound, empty sound name) is logged as an
error naming the robot, the topic, the value and what is valid, counted in
:attr:`SimNode.rejected` by the topic's full name, and dropped: the robot keeps its
previous state and the node goes on.

State echoes. ``leds/state`` and ``display/state`` are published when they change (checked
at 50 Hz, so changes made through the Python API show too) and every
``STATE_ECHO_PERIOD_S``; their publishers are latched (reliable, transient-local, depth 1),
so a late subscriber that asks for transient-local gets the state at once.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any, Self

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import BatteryState, LaserScan
from std_msgs.msg import ColorRGBA, Float64, Header, Int32, String

from beehave.clock import SimClock
from beehave.ros.context import RosContext
from beehave.ros.io import LATCHED
from robots import topics
from robots.emili import Emili
from robots.factory import Factory
from robots.kobuki import LED_COLORS, Kobuki
from robots.quad import Quad
from robots.robot import SimRobot
from robots.sim import SimState, Simulation
from robots.world import load_world

log = logging.getLogger(__name__)

__all__ = ["STATE_QOS", "SimNode", "sim_main"]

NODE_NAME = "sim"
"""The name of every node the sim node creates (one per robot namespace, one at ``/``)."""

STATE_QOS = LATCHED
"""QoS of the state echoes (``leds/state``, ``display/state``): latched."""

SENSOR_QOS = 10
"""QoS of the streams and commands: reliable, volatile, depth 10 (rclpy's default)."""

LOCKSTEP_QOS = 100
"""QoS of ``/lockstep``: reliable, deep enough for many controllers answering at once."""

_publish_drops: Counter[str] = Counter()
_publish_drops_lock = threading.Lock()


def _publish(publisher: Any, msg: Any) -> bool:
    """``publisher.publish(msg)`` from the stepping thread, except that a message Fast DDS
    gives up on is logged and dropped instead of ending the simulation.

    Fast DDS refuses a write ("cannot publish data") when the writer's history is still
    full after ``max_blocking_time`` (100 ms) — readers on a starved host that have not
    acknowledged yet. Raised in the stepping thread, that stopped the whole simulation
    (a fleet's sim, once in a stress run). Every topic here is a stream or is published
    again soon (the factory's state at its own rate; a state echo's change is sent again
    at the next step until one goes out), so the next message replaces the lost one; the
    count per topic is in :func:`publish_drops` and each first and hundredth drop is
    logged. Returns whether the message went out."""
    try:
        publisher.publish(msg)
        return True
    except _rclpy.RCLError as exc:
        if "cannot publish data" not in str(exc):
            raise
        topic = publisher.topic_name
        with _publish_drops_lock:
            _publish_drops[topic] += 1
            n = _publish_drops[topic]
        if n == 1 or n % 100 == 0:
            log.warning("sim: Fast DDS refused a message on %s (%s); dropped, the next "
                        "one replaces it (%d so far)", topic, exc, n)
        return False


def publish_drops() -> dict[str, int]:
    """Messages :func:`_publish` dropped in this process, per topic."""
    with _publish_drops_lock:
        return dict(_publish_drops)


CLOCK_REPEAT_S = 0.1
"""While the simulation is held, ``/clock`` is published again at the held time this often
(wall seconds): rclpy's time source subscribes best effort, depth 1, and a robot process
that lost the held time would otherwise wait for it until the simulation moves on."""


def stamp(time_s: float) -> Time:
    """A builtin_interfaces/Time for ``time_s`` seconds of sim time."""
    sec, nanosec = divmod(round(time_s * 1e9), 1_000_000_000)
    return Time(sec=int(sec), nanosec=int(nanosec))


class _RobotPorts:
    """One robot's node, publishers and subscriptions (the parts every robot has)."""

    def __init__(self, owner: SimNode, robot: SimRobot, node: Node) -> None:
        self.owner = owner
        self.robot = robot
        self.node = node
        self.ns = robot.namespace
        self._odom_pub = node.create_publisher(Odometry, topics.ODOM, SENSOR_QOS)
        self._scan_pub = node.create_publisher(LaserScan, topics.SCAN, SENSOR_QOS)
        self._battery_pub = node.create_publisher(BatteryState, topics.BATTERY, SENSOR_QOS)
        self._odom_msg = Odometry()
        self._odom_msg.header.frame_id = topics.MAP_FRAME
        self._odom_msg.child_frame_id = f"{self.ns}/base_link"
        self._last_scan_s = -math.inf
        lim = robot.limits
        self.subscribe(Twist, topics.CMD_VEL, self._on_cmd_vel,
                       f"finite numbers (clamped to |linear.x| <= {lim.max_linear_mps} m/s, "
                       f"|angular.z| <= {lim.max_angular_rps:.4g} rad/s)")

    # ---- commands (executor thread) -------------------------------------------------

    def subscribe(self, msg_type: type, topic: str, apply: Callable[[Any], str | None],
                  valid: str) -> None:
        """Subscribe ``topic``; ``apply(msg)`` takes the command, or returns a description
        of the value when it refuses it (then the refusal is logged and counted)."""
        full = self.node.resolve_topic_name(topic)

        def on_message(msg: Any) -> None:
            try:
                refused = apply(msg)
            except Exception as exc:  # the robot refused it: report, keep the node alive
                refused = f"{msg!r:.120} ({exc})"
            if refused is not None:
                self.owner._reject(self.ns, full, refused, valid)

        self.node.create_subscription(msg_type, topic, on_message, SENSOR_QOS)

    def _on_cmd_vel(self, msg: Twist) -> str | None:
        v, w = msg.linear.x, msg.angular.z
        if not (math.isfinite(v) and math.isfinite(w)):
            return f"linear.x={v}, angular.z={w}"
        self.robot.set_cmd_vel(v, w)
        return None

    # ---- readings (sim thread) ------------------------------------------------------

    def publish_fast(self, time_s: float, echo: bool) -> None:
        """At the odometry / sensor rate: odom, a new scan, the kind's sensors. A stream
        nobody subscribes to is not built (the message costs more than the publish)."""
        if self._odom_pub.get_subscription_count():
            self._publish_odom()
        self.robot.scan_enabled = self._scan_pub.get_subscription_count() > 0
        scan = self.robot.scan()
        if scan is not None and scan.time_s > self._last_scan_s:
            self._last_scan_s = scan.time_s
            if self._scan_pub.get_subscription_count():
                _publish(self._scan_pub, LaserScan(
                    header=self._header(scan.time_s), angle_min=scan.angle_min_rad,
                    angle_max=scan.angle_max_rad, angle_increment=scan.angle_increment_rad,
                    time_increment=0.0, scan_time=scan.scan_time_s,
                    range_min=scan.range_min_m, range_max=scan.range_max_m,
                    ranges=list(scan.ranges_m)))
        self.publish_parts(time_s, echo)

    def _publish_odom(self) -> None:
        o = self.robot.odometry()
        msg = self._odom_msg
        msg.header.stamp = stamp(o.time_s)
        pose = msg.pose.pose
        pose.position.x, pose.position.y = o.x_m, o.y_m
        pose.orientation.z = math.sin(o.yaw_rad / 2.0)
        pose.orientation.w = math.cos(o.yaw_rad / 2.0)
        msg.twist.twist.linear.x = o.linear_mps
        msg.twist.twist.angular.z = o.angular_rps
        _publish(self._odom_pub, msg)

    def publish_parts(self, time_s: float, echo: bool) -> None:
        """The kind's own sensors; ``echo``: republish the states that only go out on
        change."""

    def publish_battery(self) -> None:
        if not self._battery_pub.get_subscription_count():
            return
        b = self.robot.battery()
        _publish(self._battery_pub, BatteryState(
            header=self._header(b.time_s), voltage=b.voltage_v, current=b.current_a,
            temperature=math.nan, charge=math.nan, capacity=math.nan,
            design_capacity=math.nan, percentage=b.fraction,
            power_supply_status=(BatteryState.POWER_SUPPLY_STATUS_CHARGING if b.charging
                                 else BatteryState.POWER_SUPPLY_STATUS_DISCHARGING),
            power_supply_health=BatteryState.POWER_SUPPLY_HEALTH_GOOD,
            power_supply_technology=BatteryState.POWER_SUPPLY_TECHNOLOGY_LION,
            present=True))

    def _header(self, time_s: float) -> Header:
        return Header(stamp=stamp(time_s), frame_id=f"{self.ns}/base_link")


class _EmiliPorts(_RobotPorts):
    robot: Emili

    def __init__(self, owner: SimNode, robot: Emili, node: Node) -> None:
        super().__init__(owner, robot, node)
        self._lift_pub = node.create_publisher(Float64, topics.LIFT_STATE, SENSOR_QOS)
        self._line_pub = node.create_publisher(Float64, topics.LINE_SENSOR, SENSOR_QOS)
        self._leds_pub = node.create_publisher(ColorRGBA, topics.LEDS_STATE, STATE_QOS)
        self._display_pub = node.create_publisher(String, topics.DISPLAY_STATE, STATE_QOS)
        self._leds_sent: tuple[float, float, float] | None = None
        self._display_sent: str | None = None
        self.subscribe(Float64, topics.LIFT_COMMAND, self._on_lift,
                       f"a height of 0–{robot.lift_max_m} m")
        self.subscribe(ColorRGBA, topics.LEDS, self._on_leds, "r, g, b each 0–1 (a ignored)")
        self.subscribe(String, topics.DISPLAY, self._on_display, "any text")
        self.subscribe(String, topics.SOUND, self._on_sound, "any non-empty sound name")

    def _on_lift(self, msg: Float64) -> str | None:
        height = msg.data
        if not 0.0 <= height <= self.robot.lift_max_m:  # also refuses NaN
            return f"lift height {height} m"
        self.robot.set_lift(height)
        return None

    def _on_leds(self, msg: ColorRGBA) -> str | None:
        rgb = (msg.r, msg.g, msg.b)
        if not all(0.0 <= c <= 1.0 for c in rgb):
            return f"LED colour r={msg.r}, g={msg.g}, b={msg.b}"
        self.robot.set_leds(*rgb)
        return None

    def _on_display(self, msg: String) -> None:
        self.robot.set_display(msg.data)

    def _on_sound(self, msg: String) -> str | None:
        if not msg.data:
            return "sound ''"
        self.robot.play_sound(msg.data)
        return None

    def publish_parts(self, time_s: float, echo: bool) -> None:
        robot = self.robot
        if self._lift_pub.get_subscription_count():
            _publish(self._lift_pub, Float64(data=robot.lift_height()))
        if self._line_pub.get_subscription_count():
            offset = robot.line_sensor()
            _publish(self._line_pub, Float64(data=math.nan if offset is None else offset))
        leds = robot.leds()
        if (echo or leds != self._leds_sent) and _publish(
                self._leds_pub, ColorRGBA(r=leds[0], g=leds[1], b=leds[2], a=1.0)):
            self._leds_sent = leds  # (a change dropped goes out again at the next step)
        text = robot.display()
        if (echo or text != self._display_sent) and _publish(self._display_pub,
                                                             String(data=text)):
            self._display_sent = text


def _mask(*bits: bool) -> Int32:
    return Int32(data=sum(1 << i for i, on in enumerate(bits) if on))


class _KobukiPorts(_RobotPorts):
    robot: Kobuki

    def __init__(self, owner: SimNode, robot: Kobuki, node: Node) -> None:
        super().__init__(owner, robot, node)
        self._bumpers_pub = node.create_publisher(Int32, topics.BUMPERS, SENSOR_QOS)
        self._cliffs_pub = node.create_publisher(Int32, topics.CLIFFS, SENSOR_QOS)
        self._wheel_drop_pub = node.create_publisher(Int32, topics.WHEEL_DROP, SENSOR_QOS)
        self._buttons_pub = node.create_publisher(Int32, topics.BUTTONS, SENSOR_QOS)
        colours = ", ".join(LED_COLORS)
        self.subscribe(String, topics.KOBUKI_LED1, self._on_led(0), colours)
        self.subscribe(String, topics.KOBUKI_LED2, self._on_led(1), colours)
        self.subscribe(String, topics.SOUND, self._on_sound, ", ".join(robot.sound_names or ()))

    def _on_led(self, index: int) -> Callable[[String], str | None]:
        def apply(msg: String) -> str | None:
            if msg.data not in LED_COLORS:
                return f"LED colour {msg.data!r}"
            leds = list(self.robot.leds())
            leds[index] = msg.data  # a colour name: checked just above
            self.robot.set_leds(leds[0], leds[1])
            return None

        return apply

    def _on_sound(self, msg: String) -> str | None:
        if msg.data not in (self.robot.sound_names or ()):
            return f"sound {msg.data!r}"
        self.robot.play_sound(msg.data)
        return None

    def publish_parts(self, time_s: float, echo: bool) -> None:
        robot = self.robot
        if self._bumpers_pub.get_subscription_count():
            b = robot.bumpers()
            _publish(self._bumpers_pub, _mask(b.left, b.center, b.right))
        if self._cliffs_pub.get_subscription_count():
            c = robot.cliffs()
            _publish(self._cliffs_pub, _mask(c.left, c.center, c.right))
        if self._wheel_drop_pub.get_subscription_count():
            w = robot.wheel_drop()
            _publish(self._wheel_drop_pub, _mask(w.left, w.right))
        if self._buttons_pub.get_subscription_count():
            _publish(self._buttons_pub, _mask(*robot.buttons()))


_PORTS: dict[type[SimRobot], type[_RobotPorts]] = {Emili: _EmiliPorts, Kobuki: _KobukiPorts,
                                                    Quad: _RobotPorts}


class SimNode:
    """Puts every robot of ``sim`` on ROS 2 through ``ros`` (see the module docstring).

    Creating it creates the nodes, publishers, subscriptions and the sim's ``on_step``
    callbacks; it publishes whenever the simulation steps (the sim thread, or ``step()``
    by hand) and takes commands whenever ``ros``'s executor spins. The creator owns it and
    ends it with :meth:`destroy` (or a ``with`` block) — before ``ros.shutdown()``, since
    publishing into a shut-down context would end the sim thread with an error.

    ``clock_rate_hz``: how often ``/clock`` is published, per second of sim time.

    ``factory``: a :class:`~robots.factory.Factory` on ``sim`` whose state goes out on
    ``/factory/state`` (std_msgs/String, JSON of :meth:`Factory.state`, schema
    ``beehave/factory/state/1``; reliable, transient-local, depth 1) at 5 Hz of sim time
    and at once after every load and delivery. The caller keeps owning the factory.

    ``lockstep`` (default on): controllers that announce on ``/lockstep`` the sim time their
    next control step is due (``{"participant": id, "until_s": t}``; beehave's driving
    actions do under ``use_sim_time``) hold the simulation there until they announce again
    or let go (``"until_s": null``); ``/clock`` is published at the held time so they wake.
    A participant silent for ``lockstep_timeout_s`` of wall time while it holds the sim is
    let go with a warning (counted in :attr:`dropped`): a crashed controller never
    freezes the world.
    """

    def __init__(self, sim: Simulation, ros: RosContext, *,
                 clock_rate_hz: float = topics.CLOCK_RATE_HZ, lockstep: bool = True,
                 lockstep_timeout_s: float = topics.LOCKSTEP_TIMEOUT_S,
                 factory: Factory | None = None) -> None:
        if not (clock_rate_hz > 0 and math.isfinite(clock_rate_hz)):
            raise ValueError(f"clock_rate_hz must be positive and finite, got {clock_rate_hz}")
        if not (lockstep_timeout_s > 0 and math.isfinite(lockstep_timeout_s)):
            raise ValueError(f"lockstep_timeout_s must be positive and finite, got "
                             f"{lockstep_timeout_s}")
        self.sim = sim
        self.ros = ros
        self.clock_period_s = 1.0 / clock_rate_hz
        self.lockstep = lockstep
        self.lockstep_timeout_s = float(lockstep_timeout_s)
        self.rejected: Counter[str] = Counter()
        """Refused commands, by the topic's full name (``/emili1/lift/command``)."""
        self.dropped: Counter[str] = Counter()
        """Lockstep participants let go because they stopped answering, by participant."""
        self._participants: dict[str, tuple[float, float]] = {}  # id -> (until_s, heard)
        self._hold_at_s = math.inf  # the earliest until_s: stepping below it needs no lock
        self._held_since: float | None = None
        self._last_clock_s = -math.inf
        self._clock_sent_wall = -math.inf
        self._lock = threading.Lock()
        self._destroyed = False
        self._next_clock_s = sim.time_s
        self._next_echo_s = sim.time_s
        self._nodes: list[Node] = []
        self._removers: list[Callable[[], None]] = []
        self.factory = factory
        self._factory_lock = threading.Lock()
        try:
            clock_node = self._node("/")
            self._clock_pub = clock_node.create_publisher(Clock, topics.CLOCK, SENSOR_QOS)
            if factory is not None:
                self._factory_pub = clock_node.create_publisher(String, topics.FACTORY_STATE,
                                                                STATE_QOS)
            # A release may stop a robot (see _on_lockstep): its cmd_vel topic names it.
            self._cmd_vel_topics: dict[str, _RobotPorts] = {}
            if lockstep:
                clock_node.create_subscription(String, topics.LOCKSTEP, self._on_lockstep,
                                               LOCKSTEP_QOS)
            self.ports: dict[str, _RobotPorts] = {}
            for ns, robot in sim.robots.items():
                ports = _PORTS[type(robot)]
                self.ports[ns] = port = ports(self, robot, self._node(ns))
                self._cmd_vel_topics[port.node.resolve_topic_name(topics.CMD_VEL)] = port
            self._removers = [
                sim.on_step(self._on_clock_step),
                sim.on_step(self._on_fast_step, rate_hz=topics.ODOM_RATE_HZ),
                sim.on_step(self._on_battery_step, rate_hz=topics.BATTERY_RATE_HZ),
            ]
            if factory is not None:
                self._removers += [
                    sim.on_step(self._publish_factory, rate_hz=topics.FACTORY_STATE_RATE_HZ),
                    factory.on_event(lambda event: self._publish_factory(self.sim.time_s)),
                ]
                self._publish_factory(sim.time_s)  # latched: a late subscriber gets it
            if lockstep:
                self._removers.append(sim.set_gate(self._gate))
        except BaseException:
            self.destroy()
            raise
        log.debug("sim node: %d robot(s) on ROS 2: %s", len(self.ports), ", ".join(self.ports))

    @property
    def nodes(self) -> list[Node]:
        """The rclpy nodes: ``/sim`` (the clock) and one ``/<ns>/sim`` per robot."""
        return list(self._nodes)

    def _node(self, namespace: str) -> Node:
        node = self.ros.create_node(NODE_NAME, namespace=namespace)
        self._nodes.append(node)
        return node

    # ---- sim thread -----------------------------------------------------------------

    def _on_clock_step(self, time_s: float) -> None:
        # Every step, but cheap: one comparison unless a clock tick is due.
        if time_s + 1e-9 < self._next_clock_s:
            return
        self._next_clock_s = max(self._next_clock_s + self.clock_period_s, time_s)
        self._publish_clock(time_s)

    def _publish_clock(self, time_s: float) -> None:
        self._last_clock_s = time_s
        self._clock_sent_wall = time.monotonic()
        _publish(self._clock_pub, Clock(clock=stamp(time_s)))

    def _gate(self, time_s: float) -> bool:
        """Hold before the next step while a participant is due (see the class doc)."""
        if time_s + SimClock.SLACK_S < self._hold_at_s:
            self._held_since = None
            return False
        now = time.monotonic()
        if self._held_since is None:
            self._held_since = now
        late: list[str] = []
        with self._lock:
            if self._destroyed:
                return False
            due = [p for p, (until, _) in self._participants.items()
                   if time_s + SimClock.SLACK_S >= until]
            for p in due:
                heard = self._participants[p][1]
                if now - max(heard, self._held_since) > self.lockstep_timeout_s:
                    del self._participants[p]
                    self.dropped[p] += 1
                    late.append(p)
            self._hold_at_s = min((u for u, _ in self._participants.values()),
                                  default=math.inf)
            holding = len(due) > len(late)
        for p in late:
            log.warning("sim: lockstep participant %s did not answer within %g s (wall) at "
                        "sim time %.3f s; the simulation goes on without it", p,
                        self.lockstep_timeout_s, time_s)
        if not holding:
            self._held_since = None
            return False
        if self._last_clock_s < time_s or now - self._clock_sent_wall >= CLOCK_REPEAT_S:
            # The due controllers wake on this. Repeated while held: /clock is best effort
            # (as ROS 2 clocks are), and a process that lost the last ones (a starved one
            # on a loaded host) would stay behind the held time until the simulation moves,
            # which may wait for that very process (a leader's state a follower waits for).
            self._publish_clock(time_s)
        return True

    def _on_fast_step(self, time_s: float) -> None:
        echo = time_s + 1e-9 >= self._next_echo_s
        if echo:
            self._next_echo_s = time_s + topics.STATE_ECHO_PERIOD_S
        for ports in self.ports.values():
            ports.publish_fast(time_s, echo)

    def _on_battery_step(self, time_s: float) -> None:
        for ports in self.ports.values():
            ports.publish_battery()

    def _publish_factory(self, time_s: float) -> None:
        factory = self.factory
        if factory is None:
            return
        # A delivery and the periodic tick may come from one step: one message at a time.
        with self._factory_lock:
            _publish(self._factory_pub, String(data=json.dumps(factory.state())))

    # ---- executor thread ------------------------------------------------------------

    def _on_lockstep(self, msg: String) -> None:
        try:
            data = json.loads(msg.data)
            participant, until = data["participant"], data["until_s"]
            if not isinstance(participant, str) or not participant:
                raise ValueError("participant must be a non-empty string")
            if until is not None and not (isinstance(until, int | float)
                                          and math.isfinite(until)):
                raise ValueError("until_s must be a finite number or null")
            stop = data.get("stop")
            if stop is not None and (until is not None or stop not in self._cmd_vel_topics):
                raise ValueError(f"stop names the cmd_vel topic of a robot here, with until_s "
                                 f"null: one of {sorted(self._cmd_vel_topics)}")
        except (ValueError, KeyError, TypeError) as exc:
            self._reject("/", topics.LOCKSTEP, f"{msg.data!r:.120} ({exc})",
                         '{"participant": "<id>", "until_s": <sim time s> | null, '
                         '"stop": "<cmd_vel topic>" (optional, with null)}')
            return
        if stop is not None:
            # Before the release: the sim must not step on with the robot's old command.
            self._cmd_vel_topics[stop].robot.set_cmd_vel(0.0, 0.0)
        with self._lock:
            if until is None:
                self._participants.pop(participant, None)
            else:
                self._participants[participant] = (float(until), time.monotonic())
            self._hold_at_s = min((u for u, _ in self._participants.values()),
                                  default=math.inf)
        self.sim.wake()

    @property
    def participants(self) -> dict[str, float]:
        """The lockstep participants now, with the sim time each holds the simulation at."""
        with self._lock:
            return {p: until for p, (until, _) in self._participants.items()}

    def _reject(self, namespace: str, topic: str, value: str, valid: str) -> None:
        with self._lock:
            self.rejected[topic] += 1
        log.error("sim: robot %r refused %s on %s; valid: %s (the robot keeps its state)",
                  namespace, value, topic, valid)

    # ---- lifecycle ------------------------------------------------------------------

    def destroy(self) -> None:
        """Remove the ``on_step`` callbacks, wait until none is running, then destroy the
        publishers, subscriptions and nodes. Idempotent; the simulation keeps running."""
        with self._lock:
            if self._destroyed:
                return
            self._destroyed = True
        for remove in self._removers:
            remove()
        self._removers = []  # our on_step callbacks and our gate (no one else's)
        if self.sim.state is not SimState.CLOSED:
            # Runs between two steps: after it, no callback of ours is in flight.
            self.sim.call(lambda client: None)
        for node in reversed(self._nodes):
            self.ros.destroy_node(node)
        self._nodes = []

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.destroy()

    def __repr__(self) -> str:
        return (f"<SimNode robots={list(self.ports)} rejected={sum(self.rejected.values())}"
                f"{' destroyed' if self._destroyed else ''}>")


# ---- beehave sim ------------------------------------------------------------------------

def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="beehave sim",
        description="Run a simulated world and put its robots on ROS 2 (topics per robot "
                    "namespace, /clock in sim time) until Ctrl-C or SIGTERM.")
    parser.add_argument("world", nargs="?", default="warehouse",
                        help="a shipped world's name or a world YAML file (default: warehouse)")
    speed = parser.add_mutually_exclusive_group()
    speed.add_argument("--real-time-factor", type=float, default=1.0, metavar="X",
                       help="sim seconds per wall-clock second (default: 1.0)")
    speed.add_argument("--fast", action="store_true",
                       help="as fast as the machine goes (no pacing)")
    parser.add_argument("--clock-rate-hz", type=float, default=topics.CLOCK_RATE_HZ,
                        metavar="HZ",
                        help=f"/clock messages per second of sim time (default "
                             f"{topics.CLOCK_RATE_HZ:g}; every use_sim_time process receives "
                             "each one: a large fleet may want fewer)")
    parser.add_argument("--no-lockstep", dest="lockstep", action="store_false",
                        help="never hold the simulation for controllers that announce "
                             "their next step on /lockstep (default: hold, up to "
                             f"{topics.LOCKSTEP_TIMEOUT_S:g} s per controller)")
    parser.add_argument("--duration-s", type=float, default=None, metavar="N",
                        help="stop after N wall-clock seconds (default: until Ctrl-C)")
    parser.add_argument("--robots", type=int, default=None, metavar="N",
                        help="start only the world's first N robots (default: all)")
    parser.add_argument("--report", type=Path, default=None, metavar="FILE.json",
                        help="on a clean stop, write the facts measured in the physics "
                             "(machines, charging stations, batteries, speed zones, "
                             "deliveries) as JSON")
    parser.add_argument("--picture", type=Path, default=None, metavar="FILE.png",
                        help="on a clean stop, write a top-down picture with every robot's "
                             "trajectory")
    # -- MAVLink (robots/mavlink_endpoint.py)
    parser.add_argument("--mavlink", action="store_true",
                        help="also expose every robot as a MAVLink vehicle (ArduPilot Rover "
                             "or Copter): robot i sends to udp 127.0.0.1:BASE+i, system id "
                             "i+1 (default BASE: the world's mavlink.base_port, else 14560)")
    parser.add_argument("--mavlink-base-port", type=int, default=None, metavar="BASE",
                        help="the first robot's MAVLink port (implies --mavlink)")
    parser.add_argument("--mavlink-key-file", default=None, metavar="FILE",
                        help="MAVLink 2 signing: the vehicles sign what they send and take "
                             "only messages signed with the key in FILE (a passphrase, "
                             "hashed with SHA-256 as MAVProxy and QGroundControl do, or 64 "
                             "hex digits); implies --mavlink (docs/mavlink.md)")
    return parser


def _signing_key(args: argparse.Namespace, world: Any) -> bytes | None:
    """The MAVLink signing key ``--mavlink-key-file`` or the world's ``mavlink.key_file``
    names (ConfigError naming the file when it cannot be used)."""
    options = world.mavlink
    key_file = args.mavlink_key_file or (options.key_file if options is not None else None)
    if key_file is None:
        return None
    from hal.mavlink import load_signing_key

    return load_signing_key(key_file)


def _open_mavlink(args: argparse.Namespace, sim: Simulation,
                  signing_key: bytes | None = None) -> list[Any]:
    """The MAVLink endpoints ``--mavlink`` or the world's ``mavlink:`` asks for."""
    options = sim.world.mavlink
    if not (args.mavlink or args.mavlink_base_port is not None or options is not None
            or signing_key is not None):
        return []
    from robots.mavlink_endpoint import open_endpoints

    base = args.mavlink_base_port or (options.base_port if options is not None else 14560)
    host = options.host if options is not None else "127.0.0.1"
    endpoints = open_endpoints(sim, base_port=base, host=host, signing_key=signing_key)
    signed = ", signed (MAVLink 2 signing)" if signing_key is not None else ""
    for endpoint in endpoints.values():
        print(f"beehave sim: {endpoint.namespace} is MAVLink {endpoint.kind} system "
              f"{endpoint.system_id} at {endpoint.url}{signed} (connect with "
              f"udp:{endpoint.url.split(':', 1)[1]})", flush=True)
    return list(endpoints.values())


def sim_main(argv: list[str]) -> int:
    """``beehave sim [WORLD] [--real-time-factor X | --fast] [--no-lockstep]
    [--duration-s N] [--robots N] [--report FILE.json] [--picture FILE.png]``.

    Prints one line when the robots are on ROS 2 and one when everything has stopped;
    SIGINT and SIGTERM stop it cleanly (sim thread stopped, nodes destroyed, executor
    joined). A world with machines, depots or speed zones (``factory``) runs its
    :class:`~robots.factory.Factory` and publishes ``/factory/state``; ``--report`` and
    ``--picture`` are written after the simulation has stopped (also when it failed: the
    facts up to then are still true). Returns 0, 1 when the simulation failed or a file
    could not be written, 2 for bad arguments or a bad world.
    """
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error argparse has printed
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    if args.real_time_factor <= 0 or not math.isfinite(args.real_time_factor):
        print(f"beehave sim: --real-time-factor must be a positive number, got "
              f"{args.real_time_factor}; use --fast for no pacing", file=sys.stderr)
        return 2
    if not (math.isfinite(args.clock_rate_hz) and 1 <= args.clock_rate_hz <= 1000):
        print(f"beehave sim: --clock-rate-hz must be in [1, 1000], got {args.clock_rate_hz}",
              file=sys.stderr)
        return 2
    if args.duration_s is not None and not (math.isfinite(args.duration_s)
                                            and args.duration_s > 0):
        print(f"beehave sim: --duration-s must be a positive, finite number of seconds, got "
              f"{args.duration_s}; leave it out to run until Ctrl-C", file=sys.stderr)
        return 2
    if args.robots is not None and args.robots < 0:
        print(f"beehave sim: --robots must be 0 or more, got {args.robots}", file=sys.stderr)
        return 2
    for option, path, suffix in (("--report", args.report, ".json"),
                                 ("--picture", args.picture, ".png")):
        if path is not None and path.suffix.lower() != suffix:
            print(f"beehave sim: {option} must name a {suffix} file, got {str(path)!r}",
                  file=sys.stderr)
            return 2
    logging.basicConfig(level=logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from beehave.errors import BeehaveError

    world: str | Path = args.world
    if str(world).endswith((".yaml", ".yml")):
        world = Path(world)
    try:
        loaded = load_world(world)
        if args.robots is not None:
            loaded = loaded.with_robots(args.robots)
        signing_key = _signing_key(args, loaded)
        sim = Simulation(loaded, real_time_factor=None if args.fast else args.real_time_factor)
    except BeehaveError as exc:
        print(f"beehave sim: {exc}", file=sys.stderr)
        return 2
    factory: Factory | None = None
    if loaded.machines or loaded.depots or loaded.zones or args.report is not None:
        factory = Factory(sim)

    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        log.info("signal %d: stopping the simulation", signum)
        stop.set()

    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    code = 0
    ros: RosContext | None = None
    node: SimNode | None = None
    endpoints: list[Any] = []
    try:
        ros = RosContext()
        node = SimNode(sim, ros, lockstep=args.lockstep, factory=factory,
                       clock_rate_hz=args.clock_rate_hz)
        endpoints = _open_mavlink(args, sim, signing_key)
        ros.start()
        sim.start()
        speed = "as fast as possible" if args.fast else f"{args.real_time_factor:g}x real time"
        robots = ", ".join(f"{ns} ({r.kind})" for ns, r in sim.robots.items()) or "no robots"
        extra = "" if factory is None else f"; {topics.FACTORY_STATE} at " \
            f"{topics.FACTORY_STATE_RATE_HZ:g} Hz"
        print(f"beehave sim: world {sim.world.name!r} running {speed}: {robots}; "
              f"/clock at {args.clock_rate_hz:g} Hz{extra}; Ctrl-C to stop", flush=True)
        deadline = None if args.duration_s is None else time.monotonic() + args.duration_s
        # Wake now and then to notice a failed simulation (an on_step callback raised).
        while not stop.wait(0.5 if deadline is None
                            else max(0.0, min(0.5, deadline - time.monotonic()))):
            if sim.state is SimState.FAILED:
                code = 1
                break
            if deadline is not None and time.monotonic() >= deadline:
                break
    finally:
        try:
            sim.stop()
        except BeehaveError as exc:
            print(f"beehave sim: {exc}", file=sys.stderr)
            code = 1
        finally:
            for endpoint in endpoints:
                endpoint.close()
            if node is not None:
                node.destroy()
            if ros is not None:
                ros.shutdown()
            if not _write_outputs(sim, factory, report=args.report, picture=args.picture):
                code = 1
            sim.close()
            for signum, handler in previous.items():
                signal.signal(signum, handler)
    print("beehave sim: stopped cleanly" if code == 0 else "beehave sim: stopped after an "
          "error", flush=True)
    return code


def _write_outputs(sim: Simulation, factory: Factory | None, *, report: Path | None,
                   picture: Path | None) -> bool:
    """Write ``--report`` and ``--picture`` of a stopped simulation; False (and a line on
    stderr naming the file) when one could not be written."""
    ok = True
    if report is not None and factory is not None:
        try:
            report.parent.mkdir(parents=True, exist_ok=True)
            report.write_text(json.dumps(factory.report(), indent=2) + "\n", encoding="utf-8")
            print(f"beehave sim: facts written to {report}", flush=True)
        except OSError as exc:
            print(f"beehave sim: cannot write the report {report}: {exc}", file=sys.stderr)
            ok = False
    if picture is not None:
        try:
            if factory is not None:
                factory.render_topdown(picture)
            else:
                sim.render_topdown(picture)
            print(f"beehave sim: picture written to {picture}", flush=True)
        except (OSError, ValueError) as exc:
            print(f"beehave sim: cannot write the picture {picture}: {exc}", file=sys.stderr)
            ok = False
    return ok


class _RunningPybullet:
    """A started :class:`Simulation` with its ROS 2 node (see :mod:`beehave.simulation`)."""

    def __init__(self, sim: Simulation, node: SimNode) -> None:
        self.sim = sim
        self._node = node

    def close(self) -> None:
        try:
            self.sim.stop()
        finally:
            self._node.destroy()
            self.sim.close()


class PybulletSimulator:
    """The pybullet simulation as beehave's simulation plugin (entry point ``pybullet`` of
    group ``beehave.simulations``): ``sim:`` in a robot configuration and ``beehave sim``."""

    @staticmethod
    def start(world: str, *, real_time_factor: float | None,
              ros: RosContext) -> _RunningPybullet:
        loaded = load_world(world)
        sim = Simulation(loaded, real_time_factor=real_time_factor)
        factory = Factory(sim) if loaded.machines or loaded.depots or loaded.zones else None
        try:
            node = SimNode(sim, ros, factory=factory)
        except BaseException:
            sim.close()
            raise
        running = _RunningPybullet(sim, node)
        try:
            sim.start()
        except BaseException:
            running.close()
            raise
        return running

    @staticmethod
    def main(argv: list[str]) -> int:
        return sim_main(argv)

    @staticmethod
    def world_data(world: str) -> dict[str, Any]:
        """The world ``world`` — a shipped world's name (``warehouse``) or a YAML path, as
        ``sim: world:`` and ``beehave sim`` take it — as JSON data (the web view's map).
        Raises :class:`~robots.errors.UnknownWorld` listing the shipped worlds, or
        :class:`~robots.errors.WorldError`."""
        data: dict[str, Any] = load_world(world).model_dump(mode="json")
        return data


PYBULLET = PybulletSimulator()


if __name__ == "__main__":
    sys.exit(sim_main(sys.argv[1:]))
