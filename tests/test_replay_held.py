"""Replay timing (issue 23). A message nobody was subscribed to is held for a subscription
made a moment later -- and only then: a Lift of the demo's replay heard the lift state of
long before, ended at once, and the replay showed a false chime divergence 2 s later. And
the replay's clock passes every deadline, as the live one did: a loop of sleeps must not
lose steps to a jump."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from rclpy.serialization import serialize_message  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

from beehave import Action, Behavior  # noqa: E402
from beehave.config import parse_config  # noqa: E402
from beehave.recording import schema  # noqa: E402
from beehave.recording.reader import ChannelInfo, Recorded, Recording  # noqa: E402
from beehave.recording.replay import HOLD_S, replay  # noqa: E402

SEEN: list[tuple[str, float, float]] = []  # (action, sim time it started, first value heard)


class Look(Action):
    """Subscribe to ``level``, note the first value heard, stay subscribed ``hold_s``."""

    action_type = "look"

    def __init__(self, name: str, hold_s: float = 0.0) -> None:
        self.name, self.hold_s = name, hold_s

    def run(self) -> float:
        started = self.manager.clock.now()
        heard: list[float] = []
        self.ros.subscription(Float64, "level", lambda m: heard.append(m.data))
        while not heard and self.sleep(0.05):
            pass
        value = heard[0]
        SEEN.append((self.name, started, value))
        self.sleep(self.hold_s)
        return value


class Watcher(Behavior):
    def run(self) -> None:
        self.sleep(1.0)  # level is published, nobody listens
        self.start_action(Look("first", hold_s=0.9)).wait()
        self.start_action(Look("second")).wait()  # subscribes as the first one ends
        self.sleep(10.0)


def _recording() -> Recording:
    """What a live run of ``Watcher`` on sim time records: ``level`` is published every
    0.25 s (at 0.1, 0.35, …) with its sim time as value; the recorder has heard it from
    the start."""
    t0_ns = 1_800_000_000 * 10**9
    messages: list[Recorded] = []
    channels: dict[str, ChannelInfo] = {}

    def put(topic: str, t_s: float, data: object, encoding: str = "json",
            schema_name: str = "") -> None:
        info = channels.setdefault(topic, ChannelInfo(topic, encoding, schema_name))
        info.count += 1
        messages.append(Recorded(topic, t0_ns + round(t_s * 1e9), data, encoding,
                                 schema_name))

    for channel, name in ((schema.BLACKBOARD, "beehave.BlackboardChange"),
                          (schema.EVENTS_LOW, "beehave.Event"),
                          (schema.OUTPUTS, "beehave.HalCommand")):
        channels[schema.topic("bot", channel)] = ChannelInfo(schema.topic("bot", channel),
                                                             "json", name)
    put("/bot/beehave/events/high", 0.0, {
        "kind": "switch_requested", "subject": "watcher", "status": None, "error": None,
        "detail": {"params": {}, "source": "external"}})
    for i in range(61):
        t = i * 0.05
        put("/bot/beehave/clock", t, {"sim_time_s": 100.0 + t, "stamp": 0.0})
    for i in range(12):
        t = i * 0.25 + 0.1
        put("/bot/level", t, bytes(serialize_message(Float64(data=100.0 + t))), "cdr",
            "std_msgs/msg/Float64")
    messages.sort(key=lambda m: m.log_time_ns)
    return Recording([Path("synthetic.mcap")], messages, channels, False, {},
                     {"std_msgs/msg/Float64": schema.ros_msgdef(Float64).encode()})


def test_a_new_subscription_hears_the_next_message_not_an_old_one() -> None:
    import importlib

    # The configuration imports this file as ``tests.test_replay_held``: its SEEN.
    seen: list[tuple[str, float, float]] = importlib.import_module(
        "tests.test_replay_held").SEEN
    seen.clear()
    config = parse_config({"namespace": "bot", "use_sim_time": True,
                           "behaviors": {"watcher": {
                               "class": "tests.test_replay_held:Watcher"}},
                           "default_behavior": "watcher"}, source="held.yaml")
    result = replay(_recording(), config, speed=None, high=True)
    assert [name for name, _, _ in seen] == ["first", "second"], (seen, result.warnings)
    for name, started, value in seen:
        # Live, the first message after the subscription (0.25 s apart); the replay may
        # hand one that came up to HOLD_S before (the recording's times are when the
        # recorder heard it), never an older one.
        assert started - HOLD_S <= value <= started + 0.25, (name, started, value, seen)


class Pacer(Behavior):
    """Only sleeps in a loop, with a short action each step: no input ever moves the
    replay's clock."""

    def run(self) -> None:
        while not self.interrupted:
            self.start_action(_Step()).wait()
            self.sleep(0.2)


class _Step(Action):
    action_type = "step"

    def run(self) -> None:
        self.sleep(0.05)


def test_a_behaviour_that_only_sleeps_replays_every_step_without_warnings(
        tmp_path: Path) -> None:
    """Issue 23, defect 2: the replay's clock moved only at inputs, so a loop of sleeps
    was woken once by a jump over several of its deadlines (steps lost) and the replay
    warned that it "did not catch up with the recording"."""
    import time

    from beehave.recording.cli import finish_recording, robots_started, start_recording
    from beehave.robot import Robot
    from beehave.ros.context import RosContext

    config = parse_config({"namespace": "pacer", "hals": ["debug"],
                           "behaviors": {"pace": {"class": "tests.test_replay_held:Pacer"}},
                           "default_behavior": "pace"}, source="pacer.yaml")
    path = tmp_path / "pacer.mcap"
    with RosContext() as ros:
        robot = Robot(config, ros=ros)
        recorder = start_recording(path, [robot])
        try:
            robot.start()
            robots_started(recorder, [robot])
            time.sleep(2.0)  # a live run of about ten steps, recorded
        finally:
            robot.shutdown()
            finish_recording(recorder)
    result = replay(path, config, speed=None)
    def ended_steps(outputs: list[Any]) -> list[str]:
        return [o.key for o in outputs
                if o.key.startswith("high:pace/_Step") and o.value[0] == "ended"]

    steps = ended_steps(result.expected)
    assert len(steps) >= 5, result.expected
    assert result.warnings == [], result.warnings
    assert result.divergence is None, result.divergence
    assert ended_steps(result.outputs) == steps


def test_at_the_shutdown_an_extra_replayed_output_is_dropped_a_missing_one_is_not() -> None:
    """The live logics raced the recorded shutdown: one that had no time to react to the
    last input before its HAL's safe state is not a divergence of the replay, which was fed
    that input. A safe state that commands something else still is."""
    from beehave.recording.replay import Output, _drop_shutdown_extras, compare

    expected = [Output("leds.set", ["green"], 1.0), Output("leds.set", ["off"], 10.05)]
    got = [Output("leds.set", ["green"], 1.0), Output("leds.set", ["amber"], 10.01),
           Output("leds.set", ["off"], 10.06), Output("high:tour", ["ended"], 10.02)]
    kept = _drop_shutdown_extras(expected, got, shutdown_s=10.0)
    assert [o.value for o in kept] == [["green"], ["off"], ["ended"]]
    assert compare(expected, [o for o in kept if not o.key.startswith("high")]) is None
    # A safe state that set something else: the recorded "off" is missing -> divergence.
    wrong = [Output("leds.set", ["green"], 1.0), Output("leds.set", ["red"], 10.06)]
    div = compare(expected, _drop_shutdown_extras(expected, wrong, shutdown_s=10.0))
    assert div is not None and div.expected == ["off"] and div.got is None
