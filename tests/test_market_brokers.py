"""TravelBroker's bids (``behaviours/market/brokers.py``): planned paths, the queue, the
battery and the deadline — computed without a robot (pose and battery are hooks)."""

from __future__ import annotations

import time

import pytest

from beehave.agents.market import Job, Role, Task
from beehave.planning import GridPlanner, OccupancyMap, Rect
from behaviours.market import TravelBroker

WALL = Rect((5.0, 3.0), (0.2, 4.0))  # a wall across the middle, open at both ends


class Here(TravelBroker):
    capabilities = ("carry",)

    def __init__(self, *, at: tuple[float, float] | None, battery: float | None,
                 **options: float) -> None:
        super().__init__(GridPlanner(OccupancyMap((10.0, 6.0), (WALL,)),
                                     robot_radius_m=0.2), speed_mps=0.5, handling_s=5.0,
                         **options)  # type: ignore[arg-type]
        self.at, self.charge = at, battery

    def pose(self) -> tuple[float, float] | None:
        return self.at

    def battery_pct(self) -> float | None:
        return self.charge

    def perform_role(self, job: Job) -> None:
        return None


def _job(location: tuple[float, float], **task: float) -> Job:
    t = Task.make("deliver", location=location, roles=[Role("carry", "carry")],
                  **task)  # type: ignore[arg-type]
    return Job(t, "main", "carry", conversation_id="c", initiator="boss")


def test_the_bid_is_the_planned_drive_around_obstacles_plus_handling() -> None:
    broker = Here(at=(1.0, 3.0), battery=90.0)
    straight = broker.cost(_job((1.0, 5.0)), [])
    around = broker.cost(_job((9.0, 3.0)), [])  # behind the wall: longer than 8 m
    assert straight == pytest.approx(2.0 / 0.5 + 5.0, abs=0.2)
    assert isinstance(around, float) and around > 8.0 / 0.5 + 5.0 + 1.0


def test_the_queue_comes_first_and_a_full_queue_refuses() -> None:
    broker = Here(at=(1.0, 3.0), battery=90.0)
    first = _job((1.0, 5.0))
    alone = broker.cost(_job((1.0, 1.0)), [])
    after = broker.cost(_job((1.0, 1.0)), [first])  # via (1, 5): 2 m + 4 m, two handlings
    assert isinstance(alone, float) and isinstance(after, float)
    assert after == pytest.approx(6.0 / 0.5 + 10.0, abs=0.3) and after > alone
    assert broker.cost(_job((1.0, 1.0)), [first, first]) == \
        "2 roles queued already (at most 2)"


def test_refusals_name_the_reason() -> None:
    assert Here(at=None, battery=90.0).cost(_job((1, 1)), []) == "no odometry yet"
    assert Here(at=(1, 3), battery=None).cost(_job((1, 1)), []) == "no battery reading"
    low = Here(at=(1.0, 3.0), battery=20.1).cost(_job((9.0, 3.0)), [])
    assert isinstance(low, str) and "below the reserve of 20 %" in low
    late = Here(at=(1.0, 3.0), battery=90.0).cost(
        _job((9.0, 3.0), deadline=time.time() + 1.0), [])
    assert isinstance(late, str) and late.startswith("would miss the deadline")
    blocked = Here(at=(1.0, 3.0), battery=90.0).cost(_job((5.0, 3.0)), [])  # in the wall
    assert isinstance(blocked, str) and blocked.startswith("no path")
