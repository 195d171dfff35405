"""RosHAL: topic → blackboard inputs with conversion, outputs, clean unload."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from typing import Any

import pytest

pytest.importorskip("rclpy")

from ros_probe import Probe  # noqa: E402
from std_msgs.msg import ColorRGBA, Float64  # noqa: E402

from beehave import Event, Logic, LowLevelBehaviorManager  # noqa: E402
from beehave.errors import HALError  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.ros.hal import RosHAL, TopicInput, TopicOutput  # noqa: E402
from beehave.testing import wait_until  # noqa: E402


def to_percent(msg: Float64) -> float:
    if msg.data < 0:
        raise ValueError(f"negative charge {msg.data}")
    return msg.data * 100.0


class BatteryLeds(RosHAL):
    name = "battery_leds"
    inputs = [TopicInput("charge", Float64, to_percent, key="battery/percentage",
                         max_age_s=0.3)]
    outputs = {"leds": TopicOutput("leds", ColorRGBA)}

    def show(self, red: float, green: float) -> None:
        self.publish("leds", ColorRGBA(r=red, g=green, b=0.0, a=1.0))

    def safe_state(self) -> None:
        self.show(0.0, 0.0)  # lights off; the publisher still exists here


class Mirror(Logic):
    """Red below 20 %, green otherwise."""

    async def run(self) -> Any:
        hal = await self.hal("battery_leds")
        assert isinstance(hal, BatteryLeds)
        async for change in self.blackboard.watch("battery/percentage"):
            if not change.stale:
                hal.show(1.0, 0.0) if change.value < 20 else hal.show(0.0, 1.0)


@pytest.fixture
def setup() -> Iterator[tuple[LowLevelBehaviorManager, Probe, list[Event]]]:
    ros = RosContext()
    node = ros.create_node("beehave_low_level", namespace="halbot")
    ros.start()
    ll = LowLevelBehaviorManager(default="mirror", stop_timeout_s=1.0)
    ll.register("mirror", Mirror)
    ll.hals.register(BatteryLeds)
    ll.hals.node = node
    events: list[Event] = []
    ll.subscribe(events.append)
    probe = Probe()
    with ll:
        yield ll, probe, events
    probe.close()
    ros.shutdown()


def test_inputs_outputs_staleness_and_unload(setup: tuple[LowLevelBehaviorManager, Probe,
                                                          list[Event]]) -> None:
    ll, probe, events = setup
    leds = probe.record(ColorRGBA, "/halbot/leds")
    charge = probe.node.create_publisher(Float64, "/halbot/charge", 10)
    assert probe.wait(lambda: charge.get_subscription_count() == 1)
    # A colour sent before the probe's subscription met the HAL's publisher is lost
    # (volatile): the charge is sent again until the colour arrives.
    assert probe.wait(lambda: charge.publish(Float64(data=0.5)) is None
                      and bool(leds) and leds[-1].g == 1.0)
    assert ll.blackboard.get("battery/percentage") == 50.0
    assert ll.blackboard.entry("battery/percentage").writer == "hal:battery_leds"  # type: ignore[union-attr]
    charge.publish(Float64(data=0.1))
    assert probe.wait(lambda: leds[-1].r == 1.0)
    # Silence makes the entry stale after max_age_s.
    assert wait_until(lambda: ll.blackboard.is_stale("battery/percentage"))
    # A message the conversion rejects is reported, not dropped silently.
    charge.publish(Float64(data=-1.0))
    assert wait_until(lambda: any(e.error is not None and "negative charge" in str(e.error)
                                  for e in events))
    # Unloading (switching to no logic) runs safe_state (lights off) and destroys the
    # subscription and publisher.
    ll.default = None
    ll.shutdown()
    assert probe.wait(lambda: leds[-1].r == 0.0 and leds[-1].g == 0.0)
    assert probe.wait(lambda: charge.get_subscription_count() == 0)
    assert probe.wait(lambda: probe.publishers("/halbot/leds") == 0)


def test_without_a_node_the_load_fails_clearly() -> None:
    ll = LowLevelBehaviorManager()
    ll.hals.register(BatteryLeds)

    async def main() -> None:
        with pytest.raises(HALError, match="needs the low level's node"):
            await ll.hals.load("battery_leds")

    asyncio.run(main())


def test_a_non_finite_max_age_is_rejected_naming_the_topic() -> None:
    from beehave.errors import ConfigError

    with pytest.raises(ConfigError, match=r"TopicInput\('charge'\)\.max_age_s.*inf"):
        TopicInput("charge", Float64, to_percent, key="battery/percentage",
                   max_age_s=float("inf"))


def test_service_calls_reuse_one_client_and_fail_clearly(
        setup: tuple[LowLevelBehaviorManager, Probe, list[Event]]) -> None:
    from std_srvs.srv import Trigger

    ll, probe, _ = setup
    served: list[int] = []

    def reset(_req: Any, response: Any) -> Any:
        served.append(1)
        response.success = True
        return response

    probe.node.create_service(Trigger, "/halbot/reset", reset)
    owner = object()

    async def use() -> tuple[list[bool], int, str]:
        hal = await ll.hals.load("battery_leds", owner=owner)
        assert isinstance(hal, BatteryLeds)
        try:
            answers = [(await hal.call(Trigger, "/halbot/reset", Trigger.Request())).success
                       for _ in range(20)]
            clients = sum(1 for kind, _ in hal._entities if kind == "client")
            try:
                await hal.call(Trigger, "/halbot/nobody", Trigger.Request(), timeout_s=0.3)
            except HALError as exc:
                missing = str(exc)
            else:
                missing = ""
            return answers, clients, missing
        finally:
            await ll.hals.release("battery_leds", owner=owner)

    answers, clients, missing = ll.call(use(), timeout_s=20.0)
    assert answers == [True] * 20 and len(served) == 20
    assert clients == 1  # one per service, not one per call
    assert "'/halbot/nobody' is not available within 0.3 s" in missing


class Indicator(RosHAL):
    """A state output (the strip's colour) beside an output that acts (a beep)."""

    name = "indicator"
    outputs = {"strip": TopicOutput("strip", ColorRGBA, state=True),
               "beep": TopicOutput("beep", Float64)}


def test_a_state_output_reaches_a_subscriber_that_matches_later() -> None:
    """An LED colour set before DDS matched the robot's node must not be lost: logics
    publish state on change only, so the strip would stay wrong until the next change.
    The last state is re-sent on a new match, newest last; an output that acts is not."""
    ros = RosContext()
    node = ros.create_node("beehave_low_level", namespace="latebot")
    ros.start()
    ll = LowLevelBehaviorManager(stop_timeout_s=1.0)
    ll.hals.register(Indicator)
    ll.hals.node = node
    probe = Probe()
    try:
        with ll:
            hal = ll.call(ll.hals.load("indicator"), timeout_s=5)
            assert isinstance(hal, Indicator)
            hal.publish("strip", ColorRGBA(r=1.0, a=1.0))
            hal.publish("strip", ColorRGBA(b=1.0, a=1.0))  # the state: blue
            hal.publish("beep", Float64(data=1.0))
            assert hal._publishers["strip"].get_subscription_count() == 0  # nobody yet
            strip = probe.record(ColorRGBA, "/latebot/strip")
            beeps = probe.record(Float64, "/latebot/beep")
            assert probe.wait(lambda: bool(strip))
            assert [(m.r, m.b) for m in strip] == [(0.0, 1.0)]  # only the last state
            second = probe.record(ColorRGBA, "/latebot/strip")  # another late joiner
            assert probe.wait(lambda: bool(second))
            assert second[-1].b == 1.0
            hal.publish("strip", ColorRGBA(g=1.0, a=1.0))
            assert probe.wait(lambda: strip[-1].g == 1.0 and second[-1].g == 1.0)
            time.sleep(0.3)
            assert beeps == []  # a command that acts is never repeated
    finally:
        probe.close()
        ros.shutdown()
