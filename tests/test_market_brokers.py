"""TravelBroker's bids (``behaviours/market/brokers.py``): planned paths, the queue, the
battery and the deadline — computed without a robot (pose and battery are hooks)."""

from __future__ import annotations

import time
from typing import Any

import pytest

from beehave.agents.market import Job, Role, Task, cheapest_insertion
from beehave.planning import GridPlanner, OccupancyMap, Rect
from behaviours.fleet.site import site
from behaviours.market import TravelBroker
from behaviours.market.serving import ServeBroker

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


# ---- what the brokers bid: the marginal cost of the cheapest place (issue 24, item 2) ----
def _bid(broker: TravelBroker, job: Job, queue: list[Job], *, running: int = 0
         ) -> tuple[float, int] | str:
    """What the broker's bid is made of, as :meth:`Broker._price` computes it."""
    assert broker.inserts, "the broker must bid marginal insertion costs (queue_cost)"
    return cheapest_insertion(job, queue, broker._queue_cost, fixed=running)


def test_the_bid_is_the_marginal_sum_of_completion_times_at_the_cheapest_place() -> None:
    broker = Here(at=(1.0, 3.0), battery=90.0)
    far, near = _job((1.0, 5.6)), _job((1.0, 3.4))  # 2.6 m and 0.4 m away, on one line
    far_s, near_s = 2.6 / 0.5 + 5.0, 0.4 / 0.5 + 5.0
    # Not running yet: the near role goes first and delays the far one by its own time.
    cost, place = _bid(broker, near, [far])
    assert place == 0
    # Its own time, and the far one's delay: its handling and the 0.4 m back (the far
    # one's drive from there is 0.4 m shorter).
    assert cost == pytest.approx(near_s + 5.0, abs=0.3)
    assert cost < broker.cost(near, [far])  # the end of the queue would be dearer
    # The far one runs already: it keeps its place and the near one comes after it.
    cost, place = _bid(broker, near, [far], running=1)
    assert place == 1
    assert cost == pytest.approx(far_s + 2.2 / 0.5 + 5.0, abs=0.3)


def test_an_order_that_makes_a_queued_role_miss_its_deadline_is_not_bid() -> None:
    broker = Here(at=(1.0, 3.0), battery=90.0)
    urgent = _job((1.0, 5.6), deadline=time.time() + 2.6 / 0.5 + 5.0 + 3.0)
    cost, place = _bid(broker, _job((1.0, 1.0)), [urgent])
    assert place == 1  # before it, the urgent role would be late
    assert broker.queue_cost([_job((1.0, 1.0)), urgent]).startswith(
        "would miss the deadline of")


class ServeStanding(ServeBroker):
    """A serving broker at a fixed pose, with the aisle held by ``holder`` (or free)."""

    def __init__(self, at: tuple[float, float], holder: str | None = None,
                 **options: Any) -> None:
        super().__init__("serve", **options)
        self.at, self.holder = at, holder

    def pose(self) -> tuple[float, float] | None:
        return self.at

    def battery_pct(self) -> float | None:
        return 90.0

    def zone_holders(self) -> dict[str, str]:
        return {} if self.holder is None else {"shelf_aisle": self.holder}


def _napkins() -> Job:
    shelf, table = (1.3, 6.65), (5.7, 2.95)
    t = Task.make("deliver", id="napkins", roles=[Role("carry", "carry", params={
        "steps": [["pick", "shelf_narrow", list(shelf)], ["serve", "table2", list(table)]]})])
    return Job(t, "main", "carry", conversation_id="c", initiator="boss")


def test_a_serving_bid_drives_at_the_aisles_limit_and_waits_for_its_holder() -> None:
    kobuki = {"capabilities": ("carry",), "speed_mps": 0.45}
    free = ServeStanding((3.1, 4.6), **kobuki)
    held = ServeStanding((3.1, 4.6), holder="kobuki2", **kobuki)
    job = _napkins()
    free_s, held_s = free.cost(job, []), held.cost(job, [])
    assert isinstance(free_s, float) and isinstance(held_s, float)
    # The drive at the robot's own speed, ignoring the aisle's 0.25 m/s, is too short.
    naive_s = sum(free.planner.plan(a, b).length_m for a, b in
                  [((3.1, 4.6), (1.3, 6.65)), ((1.3, 6.65), (5.7, 2.95))]) / 0.45 + 4.0
    assert free_s > naive_s + 5.0
    # Another robot in the aisle: it waits at the aisle until that one can be out.
    zone = next(z for z in site("serve").zones if z.name == "shelf_aisle")
    assert held_s >= free_s + 0.5 * held._crossing_s(zone)
    assert held.inserts and free.inserts  # and they bid marginal insertion costs
