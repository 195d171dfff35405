"""Recordings and robots for the timeline tests (test_http_timeline.py): robots that
patrol (a behaviour whose ``driving`` action moves the odometry on the blackboard),
recorded into one MCAP file the way ``beehave run --record`` records a fleet (events +
blackboard, one prefix per robot)."""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

from beehave import Action, Behavior, HighLevelBehaviorManager
from beehave.recording import Recorder
from beehave.testing import wait_until


class Roll(Action):
    """Drives a circle: writes the pose and the speed on the blackboard every 20 ms."""

    action_type = "driving"

    def __init__(self, *, laps: float = 1.0, period_s: float = 4.0) -> None:
        self.laps = laps
        self.period_s = period_s

    def run(self) -> None:
        board = self.manager.blackboard
        steps = int(self.laps * self.period_s / 0.02)
        for i in range(steps + 1):
            angle = 2 * math.pi * i / (self.period_s / 0.02)
            board.set("odom/x_m", 3.0 + 1.5 * math.cos(angle), writer="hal:odometry")
            board.set("odom/y_m", 2.0 + 1.5 * math.sin(angle), writer="hal:odometry")
            board.set("odom/yaw_rad", angle + math.pi / 2, writer="hal:odometry")
            board.set("speed_mps", round(abs(math.sin(angle)), 4), writer="hal:odometry")
            board.set("battery/percentage", 90.0 - 5.0 * i / max(1, steps),
                      writer="hal:battery")
            if not self.sleep(0.02):
                return
        board.set("speed_mps", 0.0, writer="hal:odometry")


class Beep(Action):
    action_type = "sound"

    def run(self) -> None:
        self.sleep(60.0)


class Patrol(Behavior):
    """Rolls a lap while it beeps, then waits."""

    def __init__(self, laps: float = 1.0) -> None:
        self.laps = laps

    def run(self) -> None:
        self.start_action(Beep())
        roll = self.start_action(Roll(laps=self.laps))
        roll.wait()
        self.manager.blackboard.set("patrol/done", True, writer="behavior:patrol")
        while self.sleep(0.05):
            pass


def make_recording(path: Path, *, laps: dict[str, float] | None = None) -> Path:
    """A fleet recording: each robot (prefix → laps, default ``emili1`` one lap and
    ``kobuki1`` half a lap; 4 s a lap) patrols in a manager of its own, then idles."""
    laps = {"emili1": 1.0, "kobuki1": 0.5} if laps is None else laps
    with contextlib.ExitStack() as stack:
        managers = {}
        for name in laps:
            hl = stack.enter_context(HighLevelBehaviorManager(stop_timeout_s=0.5))
            hl.register("patrol", Patrol)
            hl.blackboard.set("odom/x_m", 4.5, writer="hal:odometry")
            hl.blackboard.set("odom/y_m", 2.0, writer="hal:odometry")
            hl.blackboard.set("battery/percentage", 90.0, writer="hal:battery")
            managers[name] = hl
        with Recorder(path, flush_period_s=0.05) as recorder:
            for name, hl in managers.items():
                recorder.attach_events(hl.events, prefix=name, level="high")
                recorder.attach_blackboard(hl.blackboard, prefix=name)
                hl.blackboard.set("mission", "start", writer="test")
            for name, hl in managers.items():
                hl.switch("patrol", laps=laps[name])
            for name in sorted(laps, key=laps.__getitem__):  # the shortest patrol first
                hl = managers[name]
                assert wait_until(lambda hl=hl: hl.blackboard.get("patrol/done") is True)
                hl.switch("idle")
                hl.blackboard.set("mission", "done", writer="test")
    return path


if __name__ == "__main__":  # a recording to look at: python -m tests.timeline_fixtures OUT
    import sys

    print(make_recording(Path(sys.argv[1])))
