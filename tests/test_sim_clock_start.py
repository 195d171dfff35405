"""A robot on sim time starts its behaviours only once the simulation's time has reached it
(issue 23, defect 1): started before its first ``/clock``, a behaviour ran at a time of 0
that the simulation never had, then saw time jump to where the simulation already was, and
the recording carried the false time. Real DDS: the simulation here is a plain rclpy node
that publishes ``/clock`` from 9.5 s on, the way ``beehave sim`` does when the robot is
started late."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")

from rosgraph_msgs.msg import Clock  # noqa: E402

from beehave import Behavior  # noqa: E402
from beehave.config import parse_config  # noqa: E402
from beehave.errors import SimClockNotStarted  # noqa: E402
from beehave.recording import Recorder, read_recording  # noqa: E402
from beehave.robot import Robot  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, beehave_threads, wait_until  # noqa: E402

SIM_START_S = 9.5


class Ticker(Behavior):
    """Counts its sleeps of 0.1 s: on a clock that jumps, one sleep would swallow many."""

    def __init__(self) -> None:
        self.ticks: list[float] = []

    def run(self) -> None:
        while not self.interrupted:
            self.ticks.append(self.manager.clock.now())
            self.sleep(0.1)


def _config(**extra: object):  # type: ignore[no-untyped-def]
    return parse_config({"namespace": "late_robot", "use_sim_time": True,
                         "behaviors": {"ticker": {"class": "tests.test_sim_clock_start:Ticker"}},
                         "default_behavior": "ticker", **extra}, source="late.yaml")


class _Simulation:
    """/clock from ``SIM_START_S`` on, 10 ms of sim time per 5 ms of wall time, beginning
    ``delay_s`` after :meth:`start` (the robot is already waiting then)."""

    def __init__(self, ros: RosContext, delay_s: float) -> None:
        self.node = ros.create_node("late_sim")
        self.pub = self.node.create_publisher(Clock, "/clock", 10)
        self.delay_s = delay_s
        self.first_sent_at: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="test-late-sim", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        if self._stop.wait(self.delay_s):
            return
        t = SIM_START_S
        while not self._stop.is_set():
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = int(t), round((t % 1) * 1e9)
            if self.first_sent_at is None:
                self.first_sent_at = time.monotonic()
            self.pub.publish(msg)
            t += 0.01
            time.sleep(0.005)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(WALL_TIMEOUT_S)


def test_behaviours_start_on_the_first_clock_and_the_recording_has_no_false_time(
        tmp_path: Path) -> None:
    path = tmp_path / "late.mcap"
    with RosContext() as ros:
        sim = _Simulation(ros, delay_s=1.0)
        robot = Robot(_config(), ros=ros)
        try:
            with Recorder(path, flush_period_s=0.02) as recorder:
                recorder.attach_robot(robot)
                sim.start()
                robot.start()  # returns once /clock came, with the ticker started
                assert sim.first_sent_at is not None
                assert robot.high is not None
                assert wait_until(lambda: robot.high is not None
                                  and robot.high.current == "ticker")
                ticker = robot.high.top
                assert ticker is not None and type(ticker).__name__ == "Ticker"
                assert wait_until(lambda: len(ticker.ticks) >= 20)  # type: ignore[attr-defined]
                ticks = list(ticker.ticks)  # type: ignore[attr-defined]
        finally:
            robot.shutdown()
            sim.close()
    # The first tick ran at the simulation's time, and none was skipped: each 0.1 s.
    assert ticks[0] >= SIM_START_S, ticks[:3]
    steps = [b - a for a, b in zip(ticks, ticks[1:], strict=False)]
    # (A sleep that swallowed the jump to SIM_START_S would step 9.5 s; a ticker thread late
    # by l wall seconds on a loaded host steps 0.1 + 2 l, the fake sim running at 2x.)
    assert max(steps) < 0.1 + 0.2, steps

    rec = read_recording(path)
    samples = [m.data["sim_time_s"] for m in rec.of("/late_robot/beehave/clock")]
    assert samples and min(samples) >= SIM_START_S, samples[:5]
    sim_at = rec.sim_time("late_robot")
    assert sim_at is not None
    started = [m for m in rec.of("/late_robot/beehave/events/high")
               if m.data["kind"] == "started" and m.data["subject"] == "ticker"]
    assert started and sim_at(started[0].log_time_ns) >= SIM_START_S
    # And it replays: the ticker's steps, each 0.1 s of sim time, the same as recorded.
    from beehave.recording.replay import replay

    result = replay(path, _config(), speed=None)
    assert result.sim_time and result.divergence is None, result.divergence
    # The recorder was closed before the robot: the replay compares up to its end.
    assert [w for w in result.warnings if "still ran" not in w] == [], result.warnings


def test_a_robot_without_clock_refuses_to_start_naming_the_cause() -> None:
    before = set(beehave_threads())
    with RosContext() as ros:
        robot = Robot(_config(sim_clock_timeout_s=0.3), ros=ros)
        t0 = time.monotonic()
        with pytest.raises(SimClockNotStarted) as err:
            robot.start()
        waited = time.monotonic() - t0
    text = str(err.value)
    for needed in ("late.yaml", "/clock", "sim_clock_timeout_s=0.3", "use_sim_time: false",
                   "ROS_DOMAIN_ID", "this robot sees 0 publisher(s) of /clock"):
        assert needed in text, text
    assert waited >= 0.3
    assert robot.high is not None and robot.high.current is None  # nothing ever ran
    assert wait_until(lambda: not [t for t in beehave_threads() if t not in before])
