"""Input checks of the ready-made actions (no robot needed)."""

from __future__ import annotations

import math

import pytest

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
