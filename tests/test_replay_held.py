"""Replay timing (issue 23). A message nobody was subscribed to is held for a subscription
made a moment later -- and only then: a Lift of the demo's replay heard the lift state of
long before, ended at once, and the replay showed a false chime divergence 2 s later. And
the replay's clock passes every deadline, as the live one did: a loop of sleeps must not
lose steps to a jump."""

from __future__ import annotations

import collections
import time
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
from beehave.testing import wait_until  # noqa: E402

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


class _Synthetic:
    """A recording written by hand, of robot ``prefix``: :meth:`put` adds a message at
    ``t_s`` seconds from its start, :meth:`event` a high-level event."""

    T0_NS = 1_800_000_000 * 10**9

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.messages: list[Recorded] = []
        self.channels: dict[str, ChannelInfo] = {}
        for channel, name in ((schema.BLACKBOARD, "beehave.BlackboardChange"),
                              (schema.EVENTS_LOW, "beehave.Event"),
                              (schema.OUTPUTS, "beehave.HalCommand")):
            topic = schema.topic(prefix, channel)
            self.channels[topic] = ChannelInfo(topic, "json", name)

    def put(self, topic: str, t_s: float, data: object, encoding: str = "json",
            schema_name: str = "") -> None:
        info = self.channels.setdefault(topic, ChannelInfo(topic, encoding, schema_name))
        info.count += 1
        self.messages.append(Recorded(topic, self.T0_NS + round(t_s * 1e9), data, encoding,
                                      schema_name))

    def event(self, t_s: float, kind: str, subject: str, status: str | None = None,
              detail: dict[str, Any] | None = None) -> None:
        self.put(schema.topic(self.prefix, schema.EVENTS_HIGH), t_s, {
            "kind": kind, "subject": subject, "status": status, "error": None,
            "detail": detail or {}})

    def recording(self) -> Recording:
        self.messages.sort(key=lambda m: m.log_time_ns)
        return Recording([Path("synthetic.mcap")], self.messages, self.channels, False, {},
                         {"std_msgs/msg/Float64": schema.ros_msgdef(Float64).encode()})


def _recording() -> Recording:
    """What a live run of ``Watcher`` on sim time records: ``level`` is published every
    0.25 s (at 0.1, 0.35, …) with its sim time as value; the recorder has heard it from
    the start."""
    rec = _Synthetic("bot")
    rec.event(0.0, "switch_requested", "watcher",
              detail={"params": {}, "source": "external"})
    # What the live high level did before its shutdown (the replay's clock stands once it
    # has done as much): the two looks start, hear the next level and end.
    for t, kind, subject, status in ((0.0, "started", "watcher", "RUNNING"),
                                     (0.0, "switch_completed", "watcher", None),
                                     (1.0, "started", "watcher/first", "RUNNING"),
                                     (2.0, "ended", "watcher/first", "SUCCEEDED"),
                                     (2.0, "started", "watcher/second", "RUNNING"),
                                     (2.1, "ended", "watcher/second", "SUCCEEDED")):
        rec.event(t, kind, subject, status)
    for i in range(61):
        t = i * 0.05
        rec.put("/bot/beehave/clock", t, {"sim_time_s": 100.0 + t, "stamp": 0.0})
    for i in range(12):
        t = i * 0.25 + 0.1
        rec.put("/bot/level", t, bytes(serialize_message(Float64(data=100.0 + t))), "cdr",
                "std_msgs/msg/Float64")
    return rec.recording()


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
        COUNTS["step"] += 1


#: What the live robot did (the module as the robot imports it: ``tests.test_replay_held``).
COUNTS: collections.Counter[str] = collections.Counter()


def _live() -> Any:
    """This module as the robot's configuration imports it (pytest may import the test
    file under another name): where the live robot's ``COUNTS`` and ``STEPS`` are."""
    import importlib

    return importlib.import_module("tests.test_replay_held")


def _record_live(tmp_path: Path, behaviour: str, what: str, count: int) -> tuple[Any, Path]:
    """Run ``behaviour`` (a class of this file) as a robot's default behaviour, recorded,
    until it has done ``what`` ``count`` times (``COUNTS``; not a wall time, which a loaded
    host shortens); returns the robot's configuration and the file."""
    from beehave.recording.cli import finish_recording, robots_started, start_recording
    from beehave.robot import Robot
    from beehave.ros.context import RosContext

    config = parse_config({"namespace": "pacer", "hals": ["debug"],
                           "behaviors": {"pace": {
                               "class": f"tests.test_replay_held:{behaviour}"}},
                           "default_behavior": "pace"}, source="pacer.yaml")
    path = tmp_path / "pacer.mcap"
    _live().COUNTS.clear()
    with RosContext() as ros:
        robot = Robot(config, ros=ros)
        recorder = start_recording(path, [robot])
        try:
            robot.start()
            robots_started(recorder, [robot])
            assert wait_until(lambda: _live().COUNTS[what] >= count), dict(_live().COUNTS)
        finally:
            robot.shutdown()
            finish_recording(recorder)
    return config, path


def test_a_behaviour_that_only_sleeps_replays_every_step_without_warnings(
        tmp_path: Path) -> None:
    """Issue 23, defect 2: the replay's clock moved only at inputs, so a loop of sleeps
    was woken once by a jump over several of its deadlines (steps lost) and the replay
    warned that it "did not catch up with the recording". And (CI, a loaded host): live,
    each step comes a little late, so a step the shutdown cut off live is due earlier in
    the replay -- the replay must not start it."""
    config, path = _record_live(tmp_path, "Pacer", "step", 8)  # about 2 s
    result = replay(path, config, speed=None)
    def ended_steps(outputs: list[Any]) -> list[str]:
        return [o.key for o in outputs
                if o.key.startswith("high:pace/_Step") and o.value[0] == "ended"]

    steps = ended_steps(result.expected)
    assert len(steps) >= 5, result.expected
    assert result.warnings == [], result.warnings
    assert result.divergence is None, result.divergence
    assert ended_steps(result.outputs) == steps


@pytest.mark.parametrize("cut_by", ["the shutdown", "a switch"])
def test_a_step_cut_off_live_does_not_start_in_the_replay(cut_by: str) -> None:
    """CI, a loaded host: live, each step of ``Pacer`` came 1.5 ms late, so the shutdown
    (or a switch asked for from outside) at 2.004 s came before the ninth step, which an
    exact replay has due at 2.0 s; an input at 2.003 s moved the replay's clock past it and
    the replay started a step the robot never did (a false divergence)."""
    rec = _Synthetic("pacer")
    rec.event(0.0, "switch_requested", "pace", detail={"params": {}, "source": "external"})
    rec.event(0.0, "started", "pace", "RUNNING")
    rec.event(0.0, "switch_completed", "pace")
    for k in range(8):
        t = k * 0.2515
        name = "pace/_Step" + (f"#{k + 1}" if k else "")
        rec.event(t, "started", name, "RUNNING", {"action_type": "step"})
        rec.event(t + 0.05, "ended", name, "SUCCEEDED")
    rec.put(schema.topic("pacer", schema.BLACKBOARD), 2.003, {
        "key": "high_level/locks", "value": {}, "stamp": 2.003, "writer": "ros:high_level",
        "stale": False})
    if cut_by == "a switch":
        rec.event(2.004, "switch_requested", "idle",
                  detail={"params": {}, "source": "external"})
        rec.event(2.0045, "ended", "pace", "INTERRUPTED")
        rec.event(2.005, "started", "idle", "RUNNING")
        rec.event(2.005, "switch_completed", "idle")
        rec.event(3.0, "ended", "idle", "INTERRUPTED")  # the shutdown
    else:
        rec.event(2.004, "ended", "pace", "INTERRUPTED")
    config = parse_config({"namespace": "pacer", "hals": ["debug"],
                           "behaviors": {"pace": {"class": "tests.test_replay_held:Pacer"}},
                           "default_behavior": "pace"}, source="pacer.yaml")
    result = replay(rec.recording(), config, speed=None, high=True)
    assert result.divergence is None, result.divergence
    assert result.warnings == [], result.warnings
    assert [o.key for o in result.outputs if o.key.startswith("high:pace/_Step")] == \
        [o.key for o in result.expected if o.key.startswith("high:pace/_Step")]


class Beacon(Behavior):
    """A control loop that emits no event: publishes ``beacon`` every 0.1 s."""

    def run(self) -> None:
        beacon = self.ros.publisher(Float64, "beacon")
        while not self.interrupted:
            beacon.publish(Float64(data=self.manager.clock.now()))
            COUNTS["beacon"] += 1
            self.sleep(0.1)


def test_a_loop_without_events_runs_in_the_replay_up_to_the_shutdown(
        tmp_path: Path) -> None:
    """The replay holds back the waits that live ended only after the shutdown, not every
    wait once the last event is done: a loop that emits none (a driving loop publishing
    cmd_vel) must run as long as it ran live (a replay of Kobuki published 4 of its 1,588
    cmd_vel messages)."""
    config, path = _record_live(tmp_path, "Beacon", "beacon", 15)  # about 1.5 s
    live = _live().COUNTS["beacon"]
    result = replay(path, config, speed=None)
    sent = [c for c in result.commands if c.topic.endswith("/beacon")]
    assert result.divergence is None and result.warnings == [], result
    # One at the start and one every 0.1 s of the recording's time until the shutdown: as
    # many as live published, or more where live came late (each live step a little late
    # on a loaded host: a stress run's live loop published 15, the replay 18 in the same
    # recorded time; a loop that emits no event is not held back by the replay's lead).
    pace = {o.value[0]: o.t_s for o in result.expected if o.key == "high:pace"}
    assert {"started", "ended"} <= pace.keys(), result.expected
    fits = int((pace["ended"] - pace["started"]) / 0.1) + 1
    assert live - 2 <= len(sent) <= max(live, fits) + 1, (live, pace, [c.t_s for c in sent])


STEPS: list[tuple[str, float]] = []  # (what, the behaviour's clock then)


class SlowStarter(Behavior):
    """Computes for a while before its first sleep, then steps every 0.25 s."""

    def run(self) -> None:
        STEPS.append(("start", self.manager.clock.now()))
        began = time.monotonic()
        while time.monotonic() - began < 0.15:  # CPU, not a wait: the clock must not move
            pass
        while not self.interrupted:
            STEPS.append(("step", self.manager.clock.now()))
            self.start_action(_Step()).wait()
            self.sleep(0.2)


def test_the_replay_clock_waits_for_a_behaviour_still_starting(tmp_path: Path) -> None:
    """CI, a loaded host: the replay moved its clock to the first input while the default
    behaviour had not yet reached its first sleep, so every replayed step came that much
    later than the recorded ones, and one the recording shows just before the shutdown
    was missing ("did not catch up ... 19 of 20 events")."""
    steps: list[tuple[str, float]] = _live().STEPS
    config, path = _record_live(tmp_path, "SlowStarter", "step", 8)  # about 2 s
    steps.clear()
    result = replay(path, config, speed=None)
    recorded = [o for o in result.expected
                if o.key.startswith("high:pace/_Step") and o.value[0] == "started"]
    assert len(recorded) >= 2, result.expected  # a loaded host starts the robot late
    assert steps[0][0] == "start" and len(steps) == 1 + len(recorded), (steps, recorded)
    started = steps[0][1]
    times = [t for what, t in steps[1:]]
    # No time passes on the replay's clock while the behaviour computes; then its steps
    # come exactly every 0.25 s.
    assert times == pytest.approx([started + 0.25 * k for k in range(len(times))],
                                  abs=1e-6), (steps, result.warnings)
    assert result.divergence is None, result.divergence
    assert result.warnings == [], result.warnings


def test_the_settle_bound_counts_the_threads_cpu_time_not_wall_time() -> None:
    """CI, a loaded host: the default behaviour began its computing late, the settle's
    bound (then 1 s of wall time) ran out during it, and the clock moved on. A thread that
    gets no CPU (here: one that sleeps) spends none of the bound; one that computes does."""
    import threading

    from beehave.recording.replay import _CpuBudget
    from beehave.threads import WorkerPool

    pool = WorkerPool()
    try:
        idle = _CpuBudget(pool, 0.05)
        done = threading.Event()
        pool.submit("sleeper", lambda: time.sleep(0.3) or done.set())
        assert wait_until(done.is_set)
        assert not idle.spent()

        busy = _CpuBudget(pool, 0.05)
        stop = threading.Event()

        def compute() -> None:
            while not stop.is_set():
                pass

        pool.submit("computer", compute)
        try:
            assert wait_until(busy.spent)  # 0.05 s of CPU time
        finally:
            stop.set()
    finally:
        pool.shutdown(timeout_s=5.0)


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
