"""Input checks of the ready-made actions (no robot needed)."""

from __future__ import annotations

import math
from typing import Any

import pytest

from beehave.testing import WALL_TIMEOUT_S

pytest.importorskip("rclpy")

from beehave.errors import BeehaveError  # noqa: E402
from behaviours.actions import Goal, Lift, LiftError, resolve_goal  # noqa: E402


@pytest.mark.parametrize("bad", [(math.nan, 0.0), (math.inf, 1.0), (True, 2.0), (1.0,),
                                 ("1", 2), None])
def test_goals_must_be_finite_coordinates(bad: object) -> None:
    with pytest.raises(BeehaveError, match="finite numbers"):
        resolve_goal(bad, None)  # type: ignore[arg-type]


def test_station_goals_come_from_the_world() -> None:
    goal = resolve_goal("emili_dropoff", "warehouse")
    assert goal == Goal(10.0, 2.0, "emili_dropoff")
    with pytest.raises(BeehaveError, match="emili_pickup"):
        resolve_goal("emili_dropof", "warehouse")  # the error lists the stations
    with pytest.raises(BeehaveError, match="pass world="):
        resolve_goal("emili_dropoff", None)


def test_lift_height_is_checked_before_anything_moves() -> None:
    with pytest.raises(LiftError, match="0.5 m is outside 0–0.3 m"):
        Lift(0.5)


class _DeadPublisher:
    """A publisher whose every publish fails (fault injection: the middleware is gone)."""

    def publish(self, msg: object) -> None:
        raise RuntimeError("publisher destroyed")


def _drive_with_a_dead_publisher(outcome: object) -> object:
    from beehave import Behavior, HighLevelBehaviorManager
    from behaviours.actions import DriveBase

    class Broken(DriveBase):
        def _open(self) -> None:
            self._cmd = _DeadPublisher()

        def drive(self) -> object:
            if isinstance(outcome, BaseException):
                raise outcome
            return outcome

    class Do(Behavior):
        def __init__(self, action: Broken) -> None:
            self.action = action

        def run(self) -> None:
            self.start_action(self.action).wait()

    action = Broken()
    with HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        hl.register("do", Do, action=action)
        assert hl.switch("do").wait(WALL_TIMEOUT_S)
        assert action.wait(WALL_TIMEOUT_S)
    return action


def test_a_failing_stop_does_not_hide_the_drives_own_error() -> None:
    from beehave import Status

    action: Any = _drive_with_a_dead_publisher(ValueError("lost the odometry"))
    assert action.status is Status.FAILED
    assert isinstance(action.error, ValueError), action.error
    assert "zero velocity afterwards failed" in "".join(getattr(action.error, "__notes__", []))


def test_a_failing_stop_after_success_fails_the_drive() -> None:
    from beehave import Status

    action: Any = _drive_with_a_dead_publisher(3)
    assert action.status is Status.FAILED
    assert "publisher destroyed" in str(action.error)
