"""Brokers that bid marginal insertion costs (``Broker.queue_cost``,
``beehave.agents.market.cheapest_insertion``): the bid is what the role adds to the cost
of the broker's whole queue at its cheapest place, the roles it would delay included,
and an awarded role is put at that place (re-planned when the award arrives)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

pytest.importorskip("rclpy")

from agent_procs import directory_state  # noqa: E402

from beehave import Action, HighLevelBehaviorManager, Status  # noqa: E402
from beehave.agents import (  # noqa: E402
    Agent,
    Auctioneer,
    Outcome,
    Role,
    Task,
    TaskState,
    auction,
)
from beehave.agents.market import Broker, Job, cheapest_insertion  # noqa: E402
from beehave.errors import Interrupted  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import wait_until, wall_timeout  # noqa: E402

# Half the suite's one bound (beehave.testing), scaled for load like it: also the auctions'
# reply_by_s, kept at 30 s on an idle machine so that a round that runs to its deadline
# takes no longer than before.
WAIT_S = wall_timeout(0.5)


def completion_sum(queue: list[float]) -> float:
    total = done_at = 0.0
    for duration_s in queue:
        done_at += duration_s
        total += done_at
    return total


# ---------------------------------------------------------------------- pure
def test_the_bid_is_the_marginal_cost_of_the_cheapest_place() -> None:
    # Queue 10 s then 20 s (completion times 10 + 30 = 40). A 5 s role first: 5 + 15 +
    # 35 = 55, so it adds 15 — less than its own completion time last (35), which is
    # what a bid that ignores whom it delays would say.
    assert cheapest_insertion(5.0, [10.0, 20.0], completion_sum) == (15.0, 0)
    # A long role goes last: before the others it would delay both.
    assert cheapest_insertion(50.0, [10.0, 20.0], completion_sum) == (80.0, 2)


def test_running_roles_keep_their_place() -> None:
    # The 10 s role runs: the 5 s one can only go after it (10 + 15 + 35 = 60: +20).
    assert cheapest_insertion(5.0, [10.0, 20.0], completion_sum, fixed=1) == (20.0, 1)
    assert cheapest_insertion(5.0, [10.0], completion_sum, fixed=1) == (15.0, 1)


def test_infeasible_places_are_skipped_and_a_refusal_says_why() -> None:
    def at_most_two(queue: list[float]) -> float | str:
        return completion_sum(queue) if len(queue) <= 2 else "at most 2 roles"

    def never_first(queue: list[float]) -> float | None:
        return None if queue and queue[0] == 1.0 else completion_sum(queue)

    assert cheapest_insertion(1.0, [10.0, 20.0], at_most_two) == "at most 2 roles"
    assert cheapest_insertion(1.0, [10.0], never_first) == (11.0, 1)
    assert cheapest_insertion(1.0, [10.0], lambda q: "no odometry") == \
        "the queue as it is: no odometry"


# ---------------------------------------------------------------------- a broker over DDS
class Timed(Action):
    """Performs a role: the ``hold`` role waits for the test's gate."""

    action_type = "role"

    def __init__(self, job: Job, started: list[str], gate: threading.Event) -> None:
        self.job, self.started, self.gate = job, started, gate

    def run(self) -> str:
        self.started.append(self.job.task.id)
        while self.job.role.params.get("hold") and not self.gate.is_set():
            if not self.sleep(0.01):
                raise Interrupted(f"{self.path}: interrupted while held")
        return self.job.task.id


class Inserting(Broker):
    """Its metric: the sum of its roles' completion times; a role takes
    ``params["duration_s"]``."""

    capabilities = ("carry",)

    def __init__(self, started: list[str], gate: threading.Event) -> None:
        self.started, self.gate = started, gate

    def queue_cost(self, queue: list[Job]) -> float:
        return completion_sum([float(j.role.params["duration_s"]) for j in queue])

    def perform_role(self, job: Job) -> Action:
        return Timed(job, self.started, self.gate)


@pytest.fixture
def ros() -> Iterator[RosContext]:
    with RosContext() as context:
        yield context


def _task(tid: str, duration_s: float, **params: Any) -> Task:
    return Task.make("deliver", id=tid, roles=[
        Role("carry", "carry", params={"duration_s": duration_s, **params})])


def test_a_short_role_is_bid_and_queued_before_a_long_one(ros: RosContext) -> None:
    started: list[str] = []
    gate = threading.Event()
    with Agent("ins_broker", ros=ros, lease_s=1.0, probe_s=0.3) as robot, \
            Agent("ins_boss", ros=ros, lease_s=1.0, probe_s=0.3) as boss, \
            HighLevelBehaviorManager(stop_timeout_s=0.5) as robot_hl, \
            HighLevelBehaviorManager(stop_timeout_s=0.5) as boss_hl:
        robot.attach(robot_hl)
        robot_hl.register("broker", Inserting, started=started, gate=gate)
        robot_hl.switch("broker")
        assert wait_until(lambda: [i.name for i in boss.directory.search("broker")]
                          == ["ins_broker"], WAIT_S), directory_state(
            boss, f"the broker is not in the boss's directory after {WAIT_S:g} s")
        boss.attach(boss_hl)
        # Sequential: each task is announced once the one before is awarded, so the
        # broker bids on the queue the earlier awards made. "hold" runs until the gate
        # opens; "long" (10 s) queues behind it; "short" (2 s) is cheapest before "long".
        tasks = [_task("hold", 1.0, hold=True), _task("long", 10.0), _task("short", 2.0)]
        boss_hl.register("alloc", Auctioneer, tasks=tasks, batch=False, reply_by_s=WAIT_S)
        boss_hl.switch("alloc")
        top = boss_hl.top
        assert top is not None
        assert wait_until(lambda: all(len(o.rounds) for o in top.outcomes.values()), WAIT_S)
        # The gate opens once the broker holds all three awards: an award still on its way
        # when "hold" ends would find "long" started (seen beside a CPU hog).
        broker = robot_hl.top
        assert wait_until(lambda: len(broker._jobs) == 3, WAIT_S)  # type: ignore[union-attr]
        gate.set()
        assert top.wait(WAIT_S) and top.status is Status.SUCCEEDED, top.error
        outcomes: dict[str, Outcome] = top.result
        assert all(o.state is TaskState.COMPLETED for o in outcomes.values())
        # Marginal bids: "long" after "hold" adds its completion time, 11 (1 + 11 - 1);
        # "short" before "long" adds 1 + 3 + 13 - 12 = 5: its own 3 plus the 2 s it delays
        # "long" (last it would have added 13).
        cost = {tid: o.rounds[-1]["cost"] for tid, o in outcomes.items()}
        assert cost == {"hold": pytest.approx(1.0), "long": pytest.approx(11.0),
                        "short": pytest.approx(5.0)}
        assert started == ["hold", "short", "long"]


def test_a_rejected_bid_is_not_kept(ros: RosContext) -> None:
    """An auction never accepts a bid it rejected (a task auctioned again gets a new
    round): the broker forgets it at once instead of keeping every bid for
    ``proposal_valid_s``."""
    gate = threading.Event()
    gate.set()
    with Agent("rej_a", ros=ros, lease_s=1.0, probe_s=0.3) as a, \
            Agent("rej_b", ros=ros, lease_s=1.0, probe_s=0.3) as b, \
            Agent("rej_boss", ros=ros, lease_s=1.0, probe_s=0.3) as boss, \
            HighLevelBehaviorManager(stop_timeout_s=0.5) as hl_a, \
            HighLevelBehaviorManager(stop_timeout_s=0.5) as hl_b:
        for agent, hl in ((a, hl_a), (b, hl_b)):
            agent.attach(hl)
            hl.register("broker", Inserting, started=[], gate=gate)
            hl.switch("broker")
        assert wait_until(lambda: len(boss.directory.search("broker")) == 2, WAIT_S)
        outcome = auction(boss, _task("t_rej", 1.0), reply_by_s=WAIT_S)
        assert outcome.state is TaskState.COMPLETED
        loser = hl_b.top if outcome.members["carry"] == "rej_a" else hl_a.top
        assert isinstance(loser, Inserting)
        assert wait_until(lambda: not loser.proposals), loser.proposals
