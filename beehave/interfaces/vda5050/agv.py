"""The robot as a VDA 5050 2.1 AGV on an MQTT broker (paho-mqtt 2).

:class:`Vda5050Interface` connects to the broker of the robot's ``vda5050:`` section,
subscribes to ``order`` and ``instantActions``, and publishes ``state``,
``visualization``, ``connection`` and ``factsheet`` under
``{interfaceName}/v2/{manufacturer}/{serialNumber}/``. It owns three threads: paho's
network loop (which also reconnects, with backoff), a worker that handles incoming
messages one at a time (so paho's loop never waits for a switch), and a publisher that
sends ``state`` on every change and at least every ``state_period_s``, and
``visualization`` at ``visualization_rate_hz``.

Everything it receives and sends is checked against the 2.1.0 schemas
(:mod:`.validation`). A message that fails, an order that breaks the rules
(:mod:`.order`) or an action the AGV does not support becomes an entry of the state's
``errors`` naming the field — never an exception in a thread, never a disturbed order.

Orders run as a beehave behaviour (``executor``, by default
:class:`behaviours.vda5050.OrderExecution`) that the interface switches to through the
control plane (:class:`beehave.interfaces.core.ControlPlane`); ``cancelOrder`` and
``startPause``/``stopPause`` pause the robot in place and resume it (``hl.pause()``:
every action to a safe stop, the order's behaviour keeps its place); a pause from
elsewhere (ROS 2, HTTP) shows on the state's ``paused`` flag too.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, Protocol

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from beehave.errors import ConfigError, Vda5050ValidationError
from beehave.events import Event, EventKind
from beehave.interfaces.vda5050 import validation
from beehave.interfaces.vda5050.order import (
    INSTANT_ACTIONS,
    NODE_ACTIONS,
    STANDSTILL_TIMEOUT_S,
    ActionStatus,
    AgvOrders,
    OrderRejected,
    Point,
    error_entry,
)

if TYPE_CHECKING:
    from beehave.config import Vda5050Options
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.lowlevel import LowLevelBehaviorManager

log = logging.getLogger(__name__)

VERSION = "2.1.0"
"""The protocol version beehave speaks (``version`` in every header)."""
MAJOR = "v2"
"""The topic's ``majorVersion`` level."""

QOS = {"order": 0, "instantActions": 0, "state": 0, "visualization": 0, "connection": 1,
       "factsheet": 0}
"""QoS per topic as VDA 5050 2.1 asks (section 6.1): 0 for everything but the connection
topic; ``connection`` and ``factsheet`` are retained."""


class NodeMap(Protocol):
    """How order nodes are placed on the robot's map (``behaviours.vda5050.WorldNodes``)."""

    def locate(self, node_id: str, position: dict[str, Any] | None) -> Point: ...
    def check_route(self, points: Sequence[tuple[str, Point]]) -> Sequence[Any] | None: ...
    def charging_station_at(self, point: Point) -> str | None: ...


class Control(Protocol):
    """The part of the control plane (``beehave.interfaces.core.ControlPlane``) the AGV
    uses."""

    def switch(self, name: str, params: Any = None) -> dict[str, Any]: ...
    def stop(self) -> dict[str, Any]: ...
    def pause(self) -> dict[str, Any]: ...
    def resume(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class Topics:
    """The six topics of one AGV."""

    prefix: str

    @classmethod
    def of(cls, interface_name: str, manufacturer: str, serial_number: str) -> Topics:
        return cls(f"{interface_name}/{MAJOR}/{manufacturer}/{serial_number}")

    def __getitem__(self, topic: str) -> str:
        return f"{self.prefix}/{topic}"


def timestamp() -> str:
    """ISO 8601 UTC with milliseconds, as the headers want it."""
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


@dataclass
class Telemetry:
    """What the robot's ROS 2 topics say now (written by the executor thread)."""

    x_m: float | None = None
    y_m: float | None = None
    theta_rad: float = 0.0
    vx_mps: float = 0.0
    omega_rps: float = 0.0
    battery_percent: float | None = None
    charging: bool = False
    driving: bool = False


STATE_PERIOD_MAX_S = 30.0
"""VDA 5050 2.1 (6.10): the AGV sends a state at least every 30 s, changes or not."""

DRIVING_MPS = 0.01
"""Speeds (m/s, and rad/s for turning) above which the AGV counts as ``driving``."""


def _driving(t: Telemetry) -> bool:
    return abs(t.vx_mps) > DRIVING_MPS or abs(t.omega_rps) > DRIVING_MPS


class Vda5050Interface:
    """One robot on a VDA 5050 broker (see the module docstring).

    Build it before the high-level manager starts (it registers the order behaviour as
    ``options.behavior``), then :meth:`start` it with the robot's high-level ROS 2 node
    and a control plane; :meth:`close` publishes ``OFFLINE`` and ends its threads.
    """

    def __init__(self, options: Vda5050Options, *, high: HighLevelBehaviorManager,
                 executor: type[Any], source: str = "<dict>") -> None:
        self.options = options
        self.high = high
        self._executor = executor
        self.topics = Topics.of(options.interface_name, options.manufacturer,
                                options.serial_number)
        node_map = getattr(executor, "node_map", None)
        if node_map is None:
            raise ConfigError(f"{source}: vda5050.executor: {executor.__qualname__} has no "
                              "node_map (a class attribute making a NodeMap from a world "
                              "name), so order nodes cannot be placed")
        try:
            self.nodes: NodeMap = node_map(options.world)
        except Exception as exc:
            raise ConfigError(f"{source}: vda5050.world: {exc}") from exc
        self.telemetry = Telemetry()
        #: Seconds between periodic states: ``state_period_s``, at most 30 s (the standard).
        self.state_period_s = min(options.state_period_s, STATE_PERIOD_MAX_S)
        if options.state_period_s > STATE_PERIOD_MAX_S:
            log.warning("%s: vda5050.state_period_s %g s is longer than VDA 5050 allows; "
                        "a state is sent every %g s", source, options.state_period_s,
                        STATE_PERIOD_MAX_S)
        self._wake = threading.Event()
        self._announce = threading.Event()  # connected: publish ONLINE and the factsheet
        self.orders = AgvOrders(locate=self.nodes.locate, check_route=self.nodes.check_route,
                                position=self._position,
                                standing_still=lambda: not _driving(self.telemetry),
                                on_change=self._wake.set)
        high.register(options.behavior, executor, orders=self.orders, world=options.world,
                      speed_mps=options.speed_mps, lift_pick_m=options.lift_pick_m,
                      lift_drop_m=options.lift_drop_m)
        for topic in validation.TOPICS:
            # Made now (the order schema: jsonschema ~25 ms, its compilation by
            # fastjsonschema ~60 ms): not when the first order waits.
            validation.validator(topic)
            validation.fast_validator(topic)
        self._header_ids: dict[str, itertools.count[int]] = {
            t: itertools.count() for t in validation.TOPICS}
        self._inbox: queue.SimpleQueue[tuple[str, bytes] | None] = queue.SimpleQueue()
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []
        self._subscriptions: list[Any] = []
        self._node: Any = None
        self._client: mqtt.Client | None = None
        self._control: Control | None = None
        self._own_control: Any = None
        self._unsubscribe_high: Callable[[], None] | None = None
        #: ``time.perf_counter()`` when the last accepted order arrived (benchmarks).
        self.last_order_received_at: float | None = None
        #: How often the connection went up (1 after the first connect).
        self.connects = 0
        self.connected = threading.Event()
        #: Every message sent, per topic (counts), for tests and benchmarks.
        self.sent: dict[str, int] = dict.fromkeys(validation.TOPICS, 0)

    # ---- lifecycle ----------------------------------------------------------------------

    def start(self, *, control: Control | None = None, node: Any = None,
              low: LowLevelBehaviorManager | None = None, name: str = "robot") -> None:
        """Connect (in the background: an unreachable broker is reported and retried with
        backoff) and start publishing. ``node``: the high-level ROS 2 node whose ``odom``
        and ``battery_state`` feed the state's position, velocity and battery.
        ``control``: the control plane to switch through; without one the interface makes
        its own (``ControlPlane(high, low=low, name=name)``) and closes it in
        :meth:`close`."""
        if control is None:
            from beehave.interfaces.core import ControlPlane

            control = self._own_control = ControlPlane(self.high, low=low, name=name)
        self._control = control
        # A pause from anywhere (startPause, ROS 2, HTTP) is the state's ``paused`` flag.
        self._unsubscribe_high = self.high.subscribe(self._on_high_event)
        if node is not None:
            self._subscribe_ros(node)
            prepare = getattr(self._executor, "prepare", None)
            if callable(prepare):
                prepare(node)  # the order behaviour's ROS entities, before the first order
        opts = self.options.broker
        client = mqtt.Client(CallbackAPIVersion.VERSION2,
                             client_id=f"beehave-{self.options.manufacturer}-"
                                       f"{self.options.serial_number}",
                             reconnect_on_failure=True)
        if opts.username_env is not None:
            user = os.environ.get(opts.username_env)
            if user is None:
                raise ConfigError(f"vda5050.broker.username_env: environment variable "
                                  f"{opts.username_env!r} is not set")
            password = os.environ.get(opts.password_env) if opts.password_env else None
            client.username_pw_set(user, password)
        if opts.tls:
            client.tls_set(ca_certs=opts.ca_file)
        client.reconnect_delay_set(min_delay=1, max_delay=max(1, int(opts.reconnect_max_s)))
        client.will_set(self.topics["connection"],
                        json.dumps(self._connection("CONNECTIONBROKEN")),
                        qos=QOS["connection"], retain=True)
        client.on_connect = self._on_connect
        client.on_connect_fail = self._on_connect_fail
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        self._client = client
        for target, name in ((self._work, "vda5050-worker"), (self._publish_loop,
                                                                 "vda5050-publisher")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        client.connect_async(opts.host, opts.port, keepalive=opts.keepalive_s)
        client.loop_start()

    def close(self) -> None:
        """Publish the final state and ``OFFLINE`` (a clean stop, so the will is not sent),
        disconnect and end every thread this interface started."""
        self._closing.set()
        unsubscribe, self._unsubscribe_high = self._unsubscribe_high, None
        if unsubscribe is not None:
            unsubscribe()
        self._inbox.put(None)
        self._wake.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
            if thread.is_alive():
                log.warning("vda5050: thread %s still running 5 s after close()", thread.name)
        self._threads.clear()
        client = self._client
        if client is not None:
            if self.connected.is_set():
                try:
                    self._publish("state", self.state())
                    info = self._publish("connection", self._connection("OFFLINE"),
                                         retain=True)
                    if info is not None:
                        info.wait_for_publish(timeout=2.0)
                except (RuntimeError, ValueError):
                    log.warning("vda5050: could not publish OFFLINE", exc_info=True)
            client.disconnect()
            client.loop_stop()
            self._client = None
        if self._own_control is not None:
            self._own_control.close()
            self._own_control = None
        if self._node is not None:
            for sub in self._subscriptions:
                self._node.destroy_subscription(sub)
            self._subscriptions.clear()
            self._node = None

    # ---- ROS 2 telemetry ----------------------------------------------------------------

    def _subscribe_ros(self, node: Any) -> None:
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import BatteryState

        self._node = node
        t = self.telemetry

        def on_odom(msg: Odometry) -> None:
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            first = t.x_m is None
            t.x_m, t.y_m = float(p.x), float(p.y)
            if first:
                self._wake.set()  # the position is known now: the master wants it
            t.theta_rad = math.atan2(2.0 * (q.w * q.z + q.x * q.y),
                                     1.0 - 2.0 * (q.y * q.y + q.z * q.z))
            self.update_velocity(float(msg.twist.twist.linear.x),
                                 float(msg.twist.twist.angular.z))

        def on_battery(msg: BatteryState) -> None:
            t.battery_percent = max(0.0, min(100.0, float(msg.percentage) * 100.0))
            charging = msg.power_supply_status == BatteryState.POWER_SUPPLY_STATUS_CHARGING
            if charging != t.charging:
                t.charging = charging
                self._wake.set()

        self._subscriptions = [node.create_subscription(Odometry, "odom", on_odom, 10),
                               node.create_subscription(BatteryState, "battery_state",
                                                        on_battery, 10)]

    def update_velocity(self, vx_mps: float, omega_rps: float) -> None:
        """The measured velocity (the odometry calls it; a test or benchmark without a
        robot may too). Starting or stopping is a change the state reports, and what the
        waits for a standstill (pause, cancel, HARD actions) are woken by."""
        t = self.telemetry
        t.vx_mps, t.omega_rps = vx_mps, omega_rps
        if t.driving != (driving := _driving(t)):
            t.driving = driving
            self._wake.set()
            self.orders.notify()

    def _position(self) -> Point | None:
        t = self.telemetry
        return None if t.x_m is None or t.y_m is None else (t.x_m, t.y_m)

    # ---- MQTT callbacks (paho's thread: never block here) -------------------------------

    def _on_connect(self, client: mqtt.Client, _userdata: Any, _flags: Any,
                    reason: Any, _props: Any) -> None:
        if reason.is_failure:
            log.warning("vda5050: broker %s:%d refused the connection: %s",
                        self.options.broker.host, self.options.broker.port, reason)
            return
        for topic in ("order", "instantActions"):
            client.subscribe(self.topics[topic], qos=QOS[topic])
        self.connects += 1
        self.connected.set()
        log.info("vda5050: connected to %s:%d as %s", self.options.broker.host,
                 self.options.broker.port, self.topics.prefix)
        # ONLINE, the factsheet and a fresh state go out from the publisher thread: paho's
        # loop never waits for building or validating a message.
        self._announce.set()
        self._wake.set()

    def _on_connect_fail(self, _client: mqtt.Client, _userdata: Any) -> None:
        log.warning("vda5050: no MQTT broker reachable at %s:%d; retrying (every %g s at "
                    "most)", self.options.broker.host, self.options.broker.port,
                    self.options.broker.reconnect_max_s)

    def _on_disconnect(self, _client: mqtt.Client, _userdata: Any, _flags: Any,
                       reason: Any, _props: Any) -> None:
        self.connected.clear()
        if not self._closing.is_set():
            log.warning("vda5050: lost the broker %s:%d (%s); reconnecting",
                        self.options.broker.host, self.options.broker.port, reason)

    def _on_message(self, _client: mqtt.Client, _userdata: Any,
                    message: mqtt.MQTTMessage) -> None:
        self._inbox.put((message.topic, bytes(message.payload)))

    # ---- incoming -----------------------------------------------------------------------

    def _work(self) -> None:
        while True:
            item = self._inbox.get()
            if item is None:
                return
            topic, payload = item
            try:
                self.handle(topic, payload)
            except Exception as exc:  # a bug of ours: report it in the state, keep going
                log.exception("vda5050: handling a message on %s failed", topic)
                self.orders.add_error(error_entry(
                    "internalError", f"handling a message on {topic} failed: {exc!r}",
                    references={"topic": topic}))

    def handle(self, topic: str, payload: bytes) -> None:
        """Handle one incoming message (the worker thread calls it; tests may too)."""
        kind = topic.rsplit("/", 1)[-1]
        received_at = time.perf_counter()
        try:
            message = json.loads(payload)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            self.orders.add_error(error_entry(
                "validationError", f"{kind}: not valid JSON: {exc}",
                references={"topic": kind}))
            return
        found = validation.problems(kind, message)  # type: ignore[arg-type]
        if found:
            refs = {"topic": kind, "field": found[0].field or "(message)"}
            refs.update(_message_references(message))
            self.orders.add_error(error_entry(
                "validationError", f"{kind} breaks the VDA 5050 {VERSION} schema: "
                + "; ".join(str(p) for p in found), references=refs))
            return
        for key in ("manufacturer", "serialNumber"):
            ours = self.options.manufacturer if key == "manufacturer" else \
                self.options.serial_number
            if message[key] != ours:
                self.orders.add_error(error_entry(
                    "validationError", f"{kind} is addressed to {key} {message[key]!r}, "
                    f"this AGV is {ours!r}", references={
                        "topic": kind, "field": key, **_message_references(message)}))
                return
        major = str(message["version"]).split(".", 1)[0]
        if major != VERSION.split(".", 1)[0]:
            self.orders.add_error(error_entry(
                "validationError", f"{kind} has version {message['version']!r}; this AGV "
                f"speaks VDA 5050 {VERSION} (any 2.x.y is understood)", references={
                    "topic": kind, "field": "version", **_message_references(message)}))
            return
        if kind == "order":
            self._order(message, received_at)
        else:
            self._instant_actions(message)

    def _order(self, message: dict[str, Any], received_at: float) -> None:
        try:
            accepted = self.orders.accept(message)
        except OrderRejected as exc:
            # Every rejection names the topic and the order it refuses (7.1), so a master
            # can match it to what it sent.
            have = {r["referenceKey"] for r in exc.entry["errorReferences"]}
            exc.entry["errorReferences"].extend(
                {"referenceKey": k, "referenceValue": v}
                for k, v in {"topic": "order", **_message_references(message)}.items()
                if k not in have)
            self.orders.add_error(exc.entry)
            return
        if not accepted:
            log.info("vda5050: order %r update %d again: ignored (a resend)",
                     message["orderId"], message["orderUpdateId"])
            # A master resends when it is unsure the order arrived, typically after it
            # missed states (QoS 0) while the broker was away: answer with a state.
            self._wake.set()
            return
        self.last_order_received_at = received_at
        self._run_orders()

    def _run_orders(self) -> None:
        name = self.options.behavior
        if self.orders.paused or not self.orders.active():
            return
        if (self.high.requested or self.high.current) != name:
            assert self._control is not None
            self._control.switch(name)

    def _instant_actions(self, message: dict[str, Any]) -> None:
        for i, action in enumerate(message["actions"]):
            kind = action["actionType"]
            state = self.orders.add_instant(action)
            if kind not in INSTANT_ACTIONS:
                why = (f"{kind!r} is not an instant action this AGV supports; supported: "
                       f"{', '.join(INSTANT_ACTIONS)}")
                self.orders.set_action(state.action_id, ActionStatus.FAILED, why)
                self.orders.add_error(error_entry(
                    "validationError", f"instantActions: actions[{i}].actionType: {why}",
                    references={"topic": "instantActions",
                                "field": f"actions[{i}].actionType",
                                "actionId": state.action_id}))
                continue
            self.orders.set_action(state.action_id, ActionStatus.RUNNING)
            ok, result = getattr(self, f"_do_{kind}")(state.action_id)
            self.orders.set_action(state.action_id,
                                   ActionStatus.FINISHED if ok else ActionStatus.FAILED, result)

    def _stop_executor(self) -> bool:
        assert self._control is not None
        self._control.stop()  # every action to its safe state
        return self.orders.wait_not_executing(timeout_s=self.high.stop_timeout_s + 2.0)

    def _wait_standstill(self, action_id: str, kind: str) -> str:
        """Wait until the AGV stands still (6.6.3, 6.8.2: the instant action is FINISHED
        then), at most ``STANDSTILL_TIMEOUT_S``; a robot that keeps moving is reported as
        an error rather than waited for forever. Returns a note for the result."""
        if self.orders.wait_standstill(timeout_s=STANDSTILL_TIMEOUT_S):
            return ""
        t = self.telemetry
        self.orders.add_error(error_entry(
            "standstillError", f"{kind}: the AGV still moves ({t.vx_mps:.2f} m/s, "
            f"{t.omega_rps:.2f} rad/s) {STANDSTILL_TIMEOUT_S:g} s after it was stopped",
            references={"actionId": action_id}, level="FATAL"))
        return " (the AGV did not stand still)"

    def _do_cancelOrder(self, action_id: str) -> tuple[bool, str]:  # noqa: N802
        if not self.orders.active():
            self.orders.add_error(error_entry(
                "noOrderToCancel", "cancelOrder: the AGV has no order to cancel",
                references={"actionId": action_id}))
            return False, "no order to cancel"
        ended = self._stop_executor()
        self.orders.cancel(f"cancelled by cancelOrder {action_id!r}")
        note = self._wait_standstill(action_id, "cancelOrder")
        return True, ("order cancelled" + ("" if ended else " (behaviour still stopping)")
                      + note)

    def _on_high_event(self, event: Event) -> None:
        if event.kind is EventKind.PAUSED:
            self.orders.set_paused(True)
        elif event.kind is EventKind.RESUMED:
            self.orders.set_paused(False)

    def _do_startPause(self, action_id: str) -> tuple[bool, str]:  # noqa: N802
        assert self._control is not None
        self.orders.set_paused(True)
        # The robot pauses in place (hl.pause): the running actions stop through their
        # safe state and go on after stopPause; they stay RUNNING in the state (the 2.1.0
        # schema has no PAUSED for actions: the state's ``paused`` flag says it).
        self._control.pause()
        deadline = time.monotonic() + self.high.stop_timeout_s + 2.0
        while not self.high.paused and time.monotonic() < deadline:
            time.sleep(0.005)
        return True, "paused" + self._wait_standstill(action_id, "startPause")

    def _do_stopPause(self, action_id: str) -> tuple[bool, str]:  # noqa: N802
        assert self._control is not None
        self.orders.set_paused(False)
        self._control.resume()
        self._run_orders()
        return True, "resumed"

    def _do_factsheetRequest(self, action_id: str) -> tuple[bool, str]:  # noqa: N802
        self._publish("factsheet", self.factsheet(), retain=True)
        return True, "factsheet published"

    def _do_stateRequest(self, action_id: str) -> tuple[bool, str]:  # noqa: N802
        self._wake.set()
        return True, "state published"

    def _do_startCharging(self, action_id: str) -> tuple[bool, str]:  # noqa: N802
        here = self._position()
        station = None if here is None else self.nodes.charging_station_at(here)
        if station is None:
            self.orders.add_error(error_entry(
                "chargingError", f"startCharging: the AGV is not on a charging station "
                f"(at {here})", references={"actionId": action_id}))
            return False, "not on a charging station"
        return True, f"charging at {station}"

    def _do_stopCharging(self, action_id: str) -> tuple[bool, str]:  # noqa: N802
        return True, "charging stops when the AGV leaves the station"

    # ---- outgoing -----------------------------------------------------------------------

    def _header(self, topic: str) -> dict[str, Any]:
        return {"headerId": next(self._header_ids[topic]), "timestamp": timestamp(),
                "version": VERSION, "manufacturer": self.options.manufacturer,
                "serialNumber": self.options.serial_number}

    def _connection(self, state: str) -> dict[str, Any]:
        return {**self._header("connection"), "connectionState": state}

    def state(self) -> dict[str, Any]:
        """The ``state`` message now."""
        t = self.telemetry
        message = {**self._header("state"), **self.orders.state_fields(),
                   "driving": _driving(t),
                   "operatingMode": "AUTOMATIC",
                   "batteryState": {"batteryCharge": t.battery_percent or 0.0,
                                    "charging": t.charging},
                   "safetyState": {"eStop": "NONE", "fieldViolation": False},
                   "velocity": {"vx": t.vx_mps, "vy": 0.0, "omega": t.omega_rps}}
        position = self._agv_position()
        if position is not None:
            message["agvPosition"] = position
        return message

    def _agv_position(self) -> dict[str, Any] | None:
        t = self.telemetry
        if t.x_m is None or t.y_m is None:
            return None
        return {"x": t.x_m, "y": t.y_m, "theta": t.theta_rad, "mapId": self.options.world,
                "positionInitialized": True}

    def visualization(self) -> dict[str, Any]:
        t = self.telemetry
        message: dict[str, Any] = {**self._header("visualization"),
                                   "velocity": {"vx": t.vx_mps, "vy": 0.0,
                                                "omega": t.omega_rps}}
        position = self._agv_position()
        if position is not None:
            message["agvPosition"] = position
        return message

    def factsheet(self) -> dict[str, Any]:
        """The ``factsheet``: EMILI's type and geometry (overridable in the YAML under
        ``vda5050.factsheet``), the supported actions and the protocol limits."""
        opts = self.options
        scopes: dict[str, list[str]] = {}
        for kind in NODE_ACTIONS:
            scopes.setdefault(kind, []).extend(["NODE", "EDGE"])
        for kind in INSTANT_ACTIONS:
            scopes.setdefault(kind, []).append("INSTANT")
        sheet: dict[str, Any] = {
            **self._header("factsheet"),
            "typeSpecification": {"seriesName": opts.serial_number, "agvKinematic": "DIFF",
                                  "agvClass": "CARRIER", "maxLoadMass": 50.0,
                                  "localizationTypes": ["NATURAL"],
                                  "navigationTypes": ["AUTONOMOUS"]},
            "physicalParameters": {"speedMin": 0.0, "speedMax": opts.speed_mps,
                                   "accelerationMax": 1.0, "decelerationMax": 1.0,
                                   "heightMin": 0.0, "heightMax": 0.3, "width": 0.6,
                                   "length": 0.8},
            "protocolLimits": {"maxStringLens": {}, "maxArrayLens": {},
                               "timing": {"minOrderInterval": 0.1, "minStateInterval": 0.02,
                                          "defaultStateInterval": self.state_period_s,
                                          "visualizationInterval":
                                              1.0 / opts.visualization_rate_hz}},
            "protocolFeatures": {
                "optionalParameters": [],
                "agvActions": [{"actionType": kind, "actionScopes": s}
                               for kind, s in scopes.items()]},
            "agvGeometry": {},
            "loadSpecification": {"loadPositions": ["lift"]},
        }
        for key, value in opts.factsheet.items():
            if isinstance(value, dict) and isinstance(sheet.get(key), dict):
                sheet[key] = {**sheet[key], **value}
            else:
                sheet[key] = value
        return sheet

    def _publish(self, topic: str, message: dict[str, Any], *, retain: bool = False
                 ) -> mqtt.MQTTMessageInfo | None:
        """Validate and send. A message that breaks the schema is beehave's bug: it is
        logged as an ERROR; a state is replaced by a reduced, valid one (the AGV must
        never fall silent, 6.10), any other message is not sent."""
        try:
            validation.check(topic, message)  # type: ignore[arg-type]
        except Vda5050ValidationError as exc:
            if topic != "state":
                log.exception("vda5050: not sending an invalid %s message", topic)
                return None
            log.error("vda5050: BUG: the state breaks the VDA 5050 %s schema; sending a "
                      "reduced valid state instead: %s", VERSION, exc)
            message = validation.repaired_state(message, str(exc))
        client = self._client
        if client is None:
            return None
        info = client.publish(self.topics[topic], json.dumps(message), qos=QOS[topic],
                              retain=retain)
        if info.rc == mqtt.MQTT_ERR_SUCCESS:
            self.sent[topic] += 1
        return info

    def _publish_loop(self) -> None:
        state_period = self.state_period_s
        vis_period = 1.0 / self.options.visualization_rate_hz
        now = time.monotonic()
        next_state, next_vis = now, now + vis_period
        while not self._closing.is_set():
            self._wake.wait(timeout=max(0.0, min(next_state, next_vis) - time.monotonic()))
            if self._closing.is_set():
                return
            now = time.monotonic()
            woken = self._wake.is_set()
            if self._announce.is_set() and self.connected.is_set():
                self._announce.clear()
                self._publish("connection", self._connection("ONLINE"), retain=True)
                self._publish("factsheet", self.factsheet(), retain=True)
            if woken or now >= next_state:
                self._wake.clear()
                if self.connected.is_set():
                    self._publish("state", self.state())
                # A state sent on a change restarts the period; a periodic one keeps the
                # cadence (timed from the schedule, not from this late wake-up, which
                # would stretch every period by the wake-up and publishing time).
                next_state = _next_tick(next_state, state_period, now, restart=woken)
            if now >= next_vis:
                if self.connected.is_set():
                    self._publish("visualization", self.visualization())
                next_vis = _next_tick(next_vis, vis_period, now, restart=False)


def _message_references(message: Any) -> dict[str, str]:
    """The references of a refused message that a master matches to what it sent."""
    if not isinstance(message, dict):
        return {}
    return {k: str(message[k]) for k in ("headerId", "orderId", "orderUpdateId")
            if k in message and isinstance(message[k], str | int) and
            not isinstance(message[k], bool)}


def _next_tick(scheduled: float, period_s: float, now: float, *, restart: bool) -> float:
    """The next time of a periodic message: one period after ``scheduled``, or after
    ``now`` when restarted or when a whole period was missed (no burst to catch up)."""
    following = scheduled + period_s
    return now + period_s if restart or following <= now else following


def make_interface(options: Vda5050Options, *, high: HighLevelBehaviorManager,
                   import_class: Callable[..., type[Any]], source: str) -> Vda5050Interface:
    """Build the interface of a robot configuration's ``vda5050:`` section (``Robot``
    calls it); errors name the file and the key."""
    from beehave.behavior import Behavior

    executor = import_class(options.executor, base=Behavior,
                            where=f"{source}: vda5050.executor")
    return Vda5050Interface(options, high=high, executor=executor, source=source)
