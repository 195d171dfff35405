"""The initiator "host" of tests/test_agents_hosts.py: one agent that, once the directory
lists an agent offering ``--service``, runs one contract net for it and prints the award.

    python tests/agents_host_node.py NAME [--service transport] [--wait-s 30]

It runs inside a network namespace, so it prints what it saw instead of being asked:
JSON lines ``{"event": "ready"}`` (its name taken), ``{"event": "found", "agents": [...]}``
(what the directory listed), then ``{"event": "award", "awardee": …, "result": …,
"attempts": …}`` or ``{"event": "error", "error": …}`` (exit status 1).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents_events import say  # noqa: E402

from beehave.agents import Agent  # noqa: E402
from beehave.agents.protocols import contract_net  # noqa: E402
from beehave.errors import BeehaveError  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import wall_timeout  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("name")
    parser.add_argument("--service", default="transport")
    parser.add_argument("--lease-s", type=float, default=1.0)
    parser.add_argument("--wait-s", type=float, default=30.0)
    args = parser.parse_args()
    with RosContext() as ros, Agent(args.name, ros=ros, lease_s=args.lease_s) as agent:
        say("ready", name=agent.name)
        deadline = time.monotonic() + args.wait_s
        # The directory has no "appeared" wait of its own; its subscription would do, but
        # the responder may already be listed, and a short poll reads more plainly here.
        while not (found := [a.name for a in agent.directory.search(args.service)
                             if a.name != agent.name]):
            if time.monotonic() > deadline:
                known = [a.name for a in agent.directory.agents()]
                say("error", error=f"no agent offers {args.service!r} within "
                                   f"{args.wait_s} s; directory: {known}")
                return 1
            time.sleep(0.05)
        say("found", agents=found)
        try:
            award = contract_net(agent, args.service, {"to": "machine_1", "kg": 20},
                                 # Positive bounds (the one candidate answers and reports
                                 # at once, ending both early): shares of the suite's bound.
                                 reply_by_s=wall_timeout(0.25),
                                 done_timeout_s=wall_timeout(0.25))
        except BeehaveError as exc:
            say("error", error=f"{type(exc).__name__}: {exc}")
            return 1
        say("award", awardee=award.awardee, cid=award.conversation_id, result=award.result,
            attempts=award.attempts, award_latency_s=award.award_latency_s)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
