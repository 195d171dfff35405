"""RosHAL: a HAL that maps ROS 2 topics to blackboard entries and offers outputs.

Declare what comes in and what goes out; the base class creates the subscriptions and
publishers on the low level's node when the HAL is loaded and destroys them at unload::

    class BatteryHAL(RosHAL):
        name = "battery"
        inputs = [TopicInput("battery_state", BatteryState,
                             lambda m: {"battery/percentage": m.percentage * 100.0,
                                        "battery/charging": m.power_supply_status == 1},
                             max_age_s=2.0)]
        outputs = {"leds": TopicOutput("leds", ColorRGBA)}

        def set_leds(self, r: float, g: float, b: float) -> None:
            self.publish("leds", ColorRGBA(r=r, g=g, b=b, a=1.0))

A conversion returns either one value (stored under ``key``) or a dict of key → value (then
leave ``key`` None). A conversion that raises is reported (event + log) and that message is
skipped; the entries keep their last values and become stale after ``max_age_s``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from rclpy.qos import QoSProfile

from beehave.errors import HALError
from beehave.events import Event, EventKind
from beehave.hal import HAL, check_duration_s
from beehave.ros.io import flush

log = logging.getLogger(__name__)

STATE_RESEND_S = 0.2
"""How often (wall seconds) a HAL with state outputs looks for subscribers that matched
since its last look, to send them the last state."""


@dataclass(frozen=True)
class TopicInput:
    """``topic`` (relative to the robot namespace) of ``msg_type``, converted by
    ``convert(msg)`` into the blackboard under ``key`` (or a dict of keys)."""

    topic: str
    msg_type: type
    convert: Callable[[Any], Any]
    key: str | None = None
    max_age_s: float | None = None
    deadband: float | None = None
    qos: QoSProfile | int = 10

    def __post_init__(self) -> None:
        if self.max_age_s is not None:
            check_duration_s(f"TopicInput({self.topic!r}).max_age_s", self.max_age_s)


@dataclass(frozen=True)
class TopicOutput:
    """An output on ``topic`` (relative to the robot namespace) of ``msg_type``.

    ``state=True``: each message is the device's whole state (an LED colour, a display
    text), so its last one is sent again to a subscriber that matches later (within
    :data:`STATE_RESEND_S`). A command
    published before DDS discovery matched the robot's node is otherwise lost, and a
    logic that publishes only on change would leave the device wrong until the next
    change. Never for commands that act (velocities, sounds): repeating those moves the
    robot or plays the sound again."""

    topic: str
    msg_type: type
    qos: QoSProfile | int = 10
    state: bool = False


class RosHAL(HAL):
    """Base of HALs backed by ROS 2 topics and services (see the module docstring)."""

    inputs: ClassVar[Sequence[TopicInput]] = ()
    outputs: ClassVar[Mapping[str, TopicOutput]] = {}

    async def on_load(self) -> None:
        if self.node is None:
            raise HALError(f"HAL {self.name!r} talks to the robot over ROS 2 and needs the low "
                           "level's node: run the robot with `beehave run ROBOT.yaml`")
        self._entities: list[tuple[str, Any]] = []
        self._publishers: dict[str, Any] = {}
        self._clients: dict[tuple[type, str], Any] = {}  # service clients, kept until unload
        self._closed = False
        self._loop = asyncio.get_running_loop()
        for spec in self.inputs:
            for key in ([spec.key] if spec.key else []):
                self.blackboard.declare(key, max_age_s=spec.max_age_s, deadband=spec.deadband)
            sub = self.node.create_subscription(spec.msg_type, spec.topic,
                                                self._input_callback(spec), spec.qos)
            self._entities.append(("subscription", sub))
        self._last: dict[str, Any] = {}  # the state outputs' last messages
        self._matched: dict[str, int] = {}  # their subscriber counts at the last look
        self._publish_lock = threading.Lock()  # orders a publish and a re-send
        for name, out in self.outputs.items():
            pub = self.node.create_publisher(out.msg_type, out.topic, out.qos)
            self._publishers[name] = pub
            self._entities.append(("publisher", pub))
        if any(out.state for out in self.outputs.values()):
            # Polled, not rclpy's "matched" event: a publisher with event callbacks that is
            # destroyed under the EventsExecutor can crash the process (ros2/rclpy#1644).
            self._entities.append(("timer", self.node.create_timer(
                STATE_RESEND_S, self._resend_to_new_subscribers)))

    def _input_callback(self, spec: TopicInput) -> Callable[[Any], None]:
        declared: set[str] = set()

        def on_message(msg: Any) -> None:  # in the ROS executor thread
            if self._closed:
                return  # unloading: a late message must not make stale entries fresh
            try:
                value = spec.convert(msg)
                if spec.key is not None:
                    self.blackboard.set(spec.key, value)
                    return
                if not isinstance(value, dict):
                    raise TypeError(f"convert() must return a dict of key → value when "
                                    f"TopicInput.key is None, got {type(value).__name__}")
                for key, item in value.items():
                    if key not in declared and (spec.max_age_s or spec.deadband):
                        self.blackboard.declare(key, max_age_s=spec.max_age_s,
                                                deadband=spec.deadband)
                        declared.add(key)
                    self.blackboard.set(key, item)
            except Exception as exc:
                log.error("HAL %r: cannot convert a message on %s: %r", self.name,
                          spec.topic, exc)
                self.error = exc
                self._report(exc, spec.topic)

        return on_message

    def _resend_to_new_subscribers(self) -> None:  # in the ROS executor thread
        with self._publish_lock:
            if self._closed:
                return
            for name, out in self.outputs.items():
                pub = self._publishers.get(name)
                if not out.state or pub is None:
                    continue
                count = pub.get_subscription_count()
                if count > self._matched.get(name, 0) and name in self._last:
                    pub.publish(self._last[name])
                self._matched[name] = count

    def _report(self, exc: BaseException, topic: str) -> None:
        # Events are delivered in the loop's thread, like every other low-level event.
        self._loop.call_soon_threadsafe(self.events.emit, Event(
            EventKind.ENDED, f"hal:{self.name}:{topic}", "FAILED", exc))

    def publish(self, output: str, msg: Any) -> None:
        """Publish ``msg`` on the declared output ``output``."""
        try:
            pub = self._publishers[output]
        except (KeyError, AttributeError):
            raise HALError(f"HAL {self.name!r} has no output {output!r}; declared: "
                           f"{', '.join(sorted(self.outputs)) or 'none'}") from None
        if not self.outputs[output].state:
            pub.publish(msg)
            return
        with self._publish_lock:  # a re-send never overtakes a newer state
            self._last[output] = msg
            self._matched[output] = pub.get_subscription_count()  # those have it now
            pub.publish(msg)

    async def call(self, srv_type: type, service: str, request: Any, *,
                   timeout_s: float = 5.0) -> Any:
        """Call a ROS service from a logic without blocking the loop; at most ``timeout_s``
        in all (waiting for the service included). One client per service and type is
        kept for the HAL's lifetime, so a call after the first pays no discovery."""
        timeout_s = check_duration_s("timeout_s", timeout_s)
        if getattr(self, "_closed", True):
            raise HALError(f"HAL {self.name!r} is not loaded: cannot call {service!r}")
        client = self._clients.get((srv_type, service))
        if client is None:
            client = self.node.create_client(srv_type, service)
            self._clients[(srv_type, service)] = client
            self._entities.append(("client", client))
        ready = False
        try:
            async with asyncio.timeout(timeout_s):  # not wait_for: see Watcher.next
                while not client.service_is_ready():
                    await asyncio.sleep(0.05)
                ready = True
                return await self._answer(client, request)
        except TimeoutError:
            why = "did not answer" if ready else "is not available"
            raise HALError(f"HAL {self.name!r}: service {service!r} {why} within "
                           f"{timeout_s} s") from None

    async def _answer(self, client: Any, request: Any) -> Any:
        """Send ``request`` and await the response in the loop (rclpy answers in its
        executor thread)."""
        future = client.call_async(request)
        done: asyncio.Future[Any] = self._loop.create_future()

        def finished(f: Any) -> None:  # in the ROS executor thread
            def resolve() -> None:
                if done.done():
                    return
                error = f.exception()
                if error is not None:
                    done.set_exception(error)
                else:
                    done.set_result(f.result())

            self._loop.call_soon_threadsafe(resolve)

        future.add_done_callback(finished)
        try:
            return await done
        except asyncio.CancelledError:
            future.cancel()
            raise

    def on_unload(self) -> None:
        with getattr(self, "_publish_lock", contextlib.nullcontext()):
            self._closed = True  # no re-send starts once the publishers may be destroyed
        for kind, entity in reversed(getattr(self, "_entities", [])):
            if kind == "publisher":
                flush(entity)  # what safe_state() just sent must reach the robot
            getattr(self.node, f"destroy_{kind}")(entity)
        self._entities = []
        self._publishers = {}
        self._clients = {}
