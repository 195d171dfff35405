"""A machine agent: watches its material level and orders replenishment by contract net.

    python -m behaviours.fleet.machine NAME [--world factory] [--below 0.5]
        [--reply-by-s 1] [--bidders 1] [--only ATV]

Its level comes from the simulation (``/factory/state``). When it falls below ``--below``
of the capacity and no order of its own is open, it announces a transport order to the
agents offering ``transport`` (cfp content ``{"order", "machine", "depot"}``) and awards it
to the cheapest bid; the ATV's inform ends the order. An ATV that fails, dies (leaves the
directory) or falls silent loses the award to the next bid. Every order is tracked by the
mission controller (:mod:`behaviours.fleet.mission`), which reports it on ``/fleet/orders``.
Nobody to bid (all charging, none alive): the order fails and is announced again 3 s later.

``--only ATV`` turns coordination off: every call for proposals goes to that one ATV,
whatever the others could do (the baseline ``beehave fleet --dispatch single`` compares
the market with). Every line it prints carries ``sim_s``, the simulation's time.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from typing import Any

from std_msgs.msg import String

from beehave.agents import AgentBehavior
from beehave.agents.protocols import contract_net
from beehave.errors import BeehaveError, Interrupted, ProtocolFailed
from behaviours.fleet.mission import ORDERS_QOS, ORDERS_TOPIC, MissionController
from behaviours.fleet.process import add_trust_options, say, serve
from behaviours.fleet.site import site
from hal.factory import STATE_QOS
from robots.topics import FACTORY_STATE

log = logging.getLogger(__name__)



#: The fraction of its capacity a machine keeps in reserve: an order is due when the level
#: would fall to it (docs/fleet.md).
SAFETY_STOCK = 0.2


def _rounded(sim_s: float | None) -> float | None:
    return None if sim_s is None else round(sim_s, 1)


class Replenish(AgentBehavior):
    """The machine's behaviour (see the module docstring)."""

    def __init__(self, machine: str, *, world: str = "factory", below: float = 0.5,
                 depot: str | None = None, reply_by_s: float = 1.0,
                 done_timeout_s: float = 240.0, retry_s: float = 3.0,
                 bidders: int = 1, bidders_wait_s: float = 10.0,
                 only: str | None = None, safety_stock: float = SAFETY_STOCK) -> None:
        places = site(world)
        if machine not in places.machines:
            raise BeehaveError(f"no machine {machine!r} in world {world!r}; it has "
                               f"{sorted(places.machines)}")
        self.machine, self.world, self.below = machine, world, below
        self.depot = depot or min(places.depots)
        self.reply_by_s, self.done_timeout_s, self.retry_s = (reply_by_s, done_timeout_s,
                                                              retry_s)
        self.bidders, self.bidders_wait_s = bidders, bidders_wait_s
        self.only = only
        self.safety_stock = safety_stock
        self.consumption_per_s = places.consumption_per_s[machine]
        self.orders = 0
        self.sim_s: float | None = None  # the simulation's time of the latest state

    def _sim_time(self, latest: Any) -> float | None:
        """The simulation's time in the latest ``/factory/state`` (read anew at each call:
        the mission's reports come while the contract net runs)."""
        msg = latest.get()
        try:
            return None if msg is None else float(json.loads(msg.data)["time_s"])
        except (ValueError, KeyError, TypeError):
            return self.sim_s

    def _level(self, latest: Any) -> tuple[float, float] | None:
        msg = latest.get()
        if msg is None:
            return None
        try:
            state = json.loads(msg.data)
            entry = state["machines"][self.machine]
            self.sim_s = float(state["time_s"])
            return float(entry["level"]), float(entry["capacity"])
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("%s: unreadable %s: %s", self.machine, FACTORY_STATE, exc)
            return None

    def _await_bidders(self) -> bool:
        """Wait, at most ``bidders_wait_s``, until the directory knows ``bidders`` agents
        offering transport: a machine that has just joined learns of the fleet one
        announcement at a time, and a call sent meanwhile reaches only part of it. Then
        it orders with whoever it knows (one ATV may be gone for good). False when
        interrupted. Wall time: discovery runs in wall time."""
        deadline = time.monotonic() + self.bidders_wait_s
        while len(self.agent.directory.search("transport")) < self.bidders:
            if time.monotonic() >= deadline:
                known = [a.name for a in self.agent.directory.search("transport")]
                log.warning("%s: ordering with %d of the %d bidders expected: %s",
                            self.machine, len(known), self.bidders, known)
                return True
            if not self.sleep(0.1):
                return False
        return True

    def run(self) -> None:
        latest = self.ros.latest(String, FACTORY_STATE, qos=STATE_QOS)
        controller = MissionController(self.ros.publisher(String, ORDERS_TOPIC,
                                                          qos=ORDERS_QOS))
        while self.sleep(0.5):
            level = self._level(latest)
            if level is None or level[0] >= self.below * level[1]:
                continue
            if not self._await_bidders():
                return
            self.orders += 1
            order = f"{self.machine}-{self.orders}"
            # Due when the level would reach the safety stock: below it, the machine is
            # one hiccup away from standing still.
            stock = self.safety_stock * level[1]
            due = (self.sim_s + max(0.0, level[0] - stock) / self.consumption_per_s
                   if self.sim_s is not None and self.consumption_per_s > 0 else None)
            mission = controller.new(order, self.machine, self.depot,
                                     sim_s=lambda: self._sim_time(latest), due_sim_s=due)
            say("order", sim_s=_rounded(self.sim_s), order=order, level=round(level[0], 1),
                due_sim_s=None if due is None else round(due, 1))
            try:
                award = contract_net(
                    self.agent, "transport",
                    {"order": order, "machine": self.machine, "depot": self.depot},
                    reply_by_s=self.reply_by_s, done_timeout_s=self.done_timeout_s,
                    observer=mission.step,
                    candidates=None if self.only is None else [self.only])
                say("delivered", sim_s=_rounded(self._sim_time(latest)), order=order,
                    atv=award.awardee, attempts=award.attempts)
            except ProtocolFailed as exc:
                mission.fail(str(exc))
                say("order_failed", sim_s=_rounded(self._sim_time(latest)), order=order,
                    reason=str(exc))
                if not self.sleep(self.retry_s):
                    return
            except Interrupted:
                mission.fail("the machine agent stopped")
                raise


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m behaviours.fleet.machine",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="the machine (in the world) and its agent's name")
    parser.add_argument("--world", default="factory")
    parser.add_argument("--below", type=float, default=0.5,
                        help="order when the level falls below this fraction of capacity")
    parser.add_argument("--lease-s", type=float, default=2.0, help="its directory lease")
    parser.add_argument("--reply-by-s", type=float, default=1.0,
                        help="how long it waits for the ATVs' bids (seconds)")
    parser.add_argument("--bidders", type=int, default=1,
                        help="how many ATVs it waits (10 s at most) to know of before it "
                             "orders")
    parser.add_argument("--only", default=None, metavar="ATV",
                        help="no coordination: send every call for proposals to this ATV "
                             "alone (a baseline to compare the market with)")
    add_trust_options(parser)
    args = parser.parse_args(argv)
    places = site(args.world)
    machines = places.machines
    if args.name not in machines:
        parser.error(f"no machine {args.name!r} in world {args.world!r}; it has "
                     f"{sorted(machines)}")
    if args.only is not None and args.only not in places.robots:
        # A name no robot answers to would fail every order, silently, for ever.
        parser.error(f"--only: no robot {args.only!r} in world {args.world!r}; it has "
                     f"{places.robots}")
    if not 0 < args.below < 1:
        parser.error(f"--below must be a fraction in (0, 1), got {args.below}")
    if not 0 < args.reply_by_s < math.inf:
        parser.error(f"--reply-by-s must be a number of seconds > 0, got {args.reply_by_s}")
    if args.bidders < 1:
        parser.error(f"--bidders must be at least 1, got {args.bidders}")
    return serve(args.name, Replenish, {"machine": args.name, "world": args.world,
                                        "below": args.below, "reply_by_s": args.reply_by_s,
                                        "bidders": args.bidders, "only": args.only},
                 lease_s=args.lease_s, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
