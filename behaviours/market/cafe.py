"""The serve scenario's orders and its order source: an agent that auctions them.

    python -m behaviours.market.cafe [NAME] [--world serve] [--brokers N] [--keepers K]
                                     [--lease-s S] [--result FILE.json]

:func:`cafe_orders` makes the scenario's orders from the world's stations (the vocabulary
of ``robots/worlds/serve.yaml``: ``shelf_open``, ``shelf_narrow``, ``meeting``,
``table1..3``):

- ``tea`` (kind ``serve``): from the open shelf to table 3 — one robot that can serve
  (EMILI) does it alone;
- ``cake`` (kind ``serve``): from the narrow shelf to table 1 — two plans: ``alone`` (a
  robot that can serve fetches it itself: EMILI has no path into the aisle and refuses)
  and ``coalition`` (a ``carry`` robot fetches it and hands it over at the meeting point
  to a ``serve`` robot, which serves it); the auctioneer can only staff the coalition;
- ``napkins`` (kind ``deliver``): from the narrow shelf to table 2 — any ``carry`` robot
  that can get there (a Kobuki).

:class:`OrderSource` waits until ``brokers`` brokers (and ``keepers`` zone keepers) are
in the directory, auctions the
orders with the :class:`~beehave.agents.market.Auctioneer` (its default: the orders
that wait together are assigned jointly, each later round's bids see the queues of the
awards before it) and reports every step on
``/serve/orders`` (:data:`ORDERS_TOPIC`, JSON lines ``{"step", "detail", "stamp"}``), and
``{"step": "finished", "outcomes": {task: ...}}`` when every order is settled (also
written to ``--result`` FILE: the launcher that started it reads the outcome there, not
depending on a DDS subscription for the verdict).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from beehave.agents import AgentBehavior
from beehave.agents.market import BROKER_SERVICE, Auctioneer, Outcome, Role, Task
from beehave.errors import BeehaveError
from behaviours.fleet.process import say, serve
from behaviours.market.serving import ZONE_SERVICE

log = logging.getLogger(__name__)

__all__ = ["CAPABILITIES", "HAND_OVER_OFFSET_M", "ORDERS_TOPIC", "OrderSource",
           "cafe_orders", "outcome_dict"]

ORDERS_TOPIC = "/serve/orders"
ORDERS_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""Reliable and latched, deep enough for a whole scenario: a late watcher hears it all."""
CAPABILITIES = ("carry", "serve")
"""The market's vocabulary: ``carry`` (move an item), ``serve`` (hand it to a guest:
lift and display)."""
HAND_OVER_OFFSET_M = 0.6
"""Where the two robots stand at the meeting point: the giver this far north of its
centre (the aisle's side), the taker as far south (the tables' side), so neither stands
in the other's way on. 1.2 m between centres keeps EMILI's safety field clear."""


def _at(world: Any, name: str, dy_m: float = 0.0) -> list[Any]:
    x, y = world.station(name).center_m  # UnknownStation lists the world's stations
    return [name, [round(x, 3), round(y + dy_m, 3)]]


def cafe_orders(world: str = "serve") -> list[Task]:
    """The scenario's three orders (see the module docstring), resolved against
    ``world`` (a name or YAML path with the serve scenario's stations)."""
    from robots.world import load_world

    w = load_world(world)
    meeting_give = _at(w, "meeting", +HAND_OVER_OFFSET_M)
    meeting_take = _at(w, "meeting", -HAND_OVER_OFFSET_M)

    def steps(*pairs: tuple[str, list[Any]]) -> dict[str, Any]:
        return {"steps": [[op, *where] for op, where in pairs]}

    def location(table: str) -> tuple[float, float]:
        x, y = w.station(table).center_m
        return (x, y)

    tea = Task.make("serve", id="tea", location=location("table3"),
                    params={"item": "tea", "table": "table3"},
                    roles=[Role("serve", "serve", params=steps(
                        ("pick", _at(w, "shelf_open")), ("serve", _at(w, "table3"))))])
    cake = Task.make("serve", id="cake", location=location("table1"),
                     params={"item": "cake", "table": "table1"}, plans={
        "alone": [Role("serve", "serve", params=steps(
            ("pick", _at(w, "shelf_narrow")), ("serve", _at(w, "table1"))))],
        "coalition": [
            Role("fetch", "carry", waits_for=("serve:at_meeting",), params=steps(
                ("pick", _at(w, "shelf_narrow")), ("give", meeting_give))),
            Role("serve", "serve", waits_for=("fetch:at_meeting", "fetch:handed"),
                 params=steps(("take", meeting_take), ("serve", _at(w, "table1")))),
        ]})
    napkins = Task.make("deliver", id="napkins", location=location("table2"),
                        params={"item": "napkins", "table": "table2"},
                        roles=[Role("carry", "carry", params=steps(
                            ("pick", _at(w, "shelf_narrow")), ("serve", _at(w, "table2"))))])
    return [tea, cake, napkins]


def outcome_dict(outcome: Outcome) -> dict[str, Any]:
    """One :class:`~beehave.agents.market.Outcome` as JSON-ready data."""
    return {"task": outcome.task.id, "kind": outcome.task.kind,
            "table": outcome.task.params.get("table"), "state": outcome.state.value,
            "plan": outcome.plan, "members": dict(outcome.members),
            "results": outcome.results, "rounds": outcome.rounds, "reason": outcome.reason}


class OrderSource(AgentBehavior):
    """Waits for ``brokers`` brokers, auctions the orders, reports every step (see the
    module docstring). Its result is ``{task id: outcome dict}``."""

    def __init__(self, world: str = "serve", *, brokers: int = 3, keepers: int = 0,
                 settle_s: float = 2.0, done_timeout_s: float = 300.0,
                 result_file: str | None = None) -> None:
        if brokers < 1:
            raise BeehaveError(f"OrderSource: brokers must be 1 or more, got {brokers}")
        self.world, self.brokers, self.settle_s = world, brokers, settle_s
        self.keepers = keepers
        self.result_file = None if result_file is None else Path(result_file)
        self.done_timeout_s = done_timeout_s
        self.orders = cafe_orders(world)

    def run(self) -> dict[str, Any]:
        pub = self.ros.publisher(String, ORDERS_TOPIC, qos=ORDERS_QOS)

        def report(step: str, detail: dict[str, Any]) -> None:
            pub.publish(String(data=json.dumps({"step": step, "detail": detail,
                                                "stamp": time.time()}, default=str)))

        # Every robot bidding, and the aisle kept (a robot in it unreserved could meet
        # another head-on), before the first order goes out.
        while len(self.agent.directory.search(BROKER_SERVICE)) < self.brokers or \
                len(self.agent.directory.search(ZONE_SERVICE)) < self.keepers:
            if not self.sleep(0.2):
                return {}
        # Registered is not yet bidding: a broker refuses until its odometry is in.
        if not self.sleep(self.settle_s):
            return {}
        found = sorted(i.name for i in self.agent.directory.search(BROKER_SERVICE))
        report("brokers", {"brokers": found})
        say("brokers", brokers=found)
        auctioneer = self.start_behavior(Auctioneer(
            self.orders, capabilities=CAPABILITIES, max_rounds=10, retry_s=2.0,
            done_timeout_s=self.done_timeout_s, observer=report))
        auctioneer.wait()
        outcomes = {tid: outcome_dict(o) for tid, o in auctioneer.outcomes.items()}
        final = {"outcomes": outcomes, "error": repr(auctioneer.error)
                 if auctioneer.error is not None else None}
        if self.result_file is not None:  # whole or not at all: a reader never sees half
            partial = self.result_file.with_suffix(".partial")
            partial.write_text(json.dumps(final, default=str))
            partial.replace(self.result_file)
        report("finished", final)
        say("finished", outcomes={t: o["state"] for t, o in outcomes.items()})
        self.sleep(float("inf"))  # stay in the directory until stopped
        return outcomes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m behaviours.market.cafe",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", nargs="?", default="orders", help="its agent name")
    parser.add_argument("--world", default="serve")
    parser.add_argument("--brokers", type=int, default=3,
                        help="how many brokers to wait for before auctioning")
    parser.add_argument("--keepers", type=int, default=0,
                        help="how many zone keepers to wait for before auctioning")
    parser.add_argument("--lease-s", type=float, default=3.0, help="its directory lease")
    parser.add_argument("--result", default=None, metavar="FILE.json",
                        help="also write the final outcomes there (what a launcher reads)")
    args = parser.parse_args(argv)
    if args.brokers < 1:
        parser.error(f"--brokers must be 1 or more, got {args.brokers}")
    return serve(args.name, OrderSource, {"world": args.world, "brokers": args.brokers,
                                          "keepers": args.keepers,
                                          "result_file": args.result},
                 lease_s=args.lease_s)


if __name__ == "__main__":
    raise SystemExit(main())
