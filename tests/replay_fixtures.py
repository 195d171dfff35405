"""A recorded low level for the replay tests (``test_replay*.py``)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from beehave.config import RobotConfig
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.recording import Recorder
from beehave.robot import Robot
from hal.debug import DebugHAL, DebugRobot


@contextlib.contextmanager
def recorded_low(path: Path, config: RobotConfig,
                 hardware: DebugRobot) -> Iterator[LowLevelBehaviorManager]:
    """A low level on the debug HAL of ``hardware``, running and recorded to ``path`` (as
    ``beehave run --record`` records it, without ROS)."""
    robot = Robot(config, only="low")
    low = robot.low
    assert low is not None
    low.hals.register(DebugHAL, robot=hardware)
    with Recorder(path, flush_period_s=0.1) as recorder:
        recorder.attach_robot(robot)
        with low:
            yield low
