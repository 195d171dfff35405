"""An agent process for tests/test_agents.py and tests/test_agents_hosts.py.

    python tests/agents_node.py NAME [--service transport] [--cost 3.0] [--lease-s 1.0]
                                     [--task-s 0.0] [--propose-delay-s 0.0]

It offers ``--service`` with a ContractNetResponder (proposal ``{"cost": COST}``; an award
runs a ``Deliver`` action of ``--task-s`` seconds) and a RequestResponder that echoes the
request's content. Every protocol step is printed on stdout as a JSON line
(``{"event": "cfp"|"perform"|"done"|"interrupted"|"cancel"|…, "cid": …}``); ``ready``
once the agent is alive, ``taken`` (and exit status 3) when its name is.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents_events import say  # noqa: E402

from beehave import Action, Event, EventKind, HighLevelBehaviorManager  # noqa: E402
from beehave.agents import Agent, AgentBehavior, AgentNameTaken, Message  # noqa: E402
from beehave.agents.protocols import ContractNetResponder, RequestResponder  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402


class Deliver(Action):
    action_type = "driving"

    def __init__(self, cid: str, duration_s: float) -> None:
        self.cid = cid
        self.duration_s = duration_s

    def run(self) -> dict[str, Any]:
        say("perform", cid=self.cid)
        if self.duration_s > 0 and not self.sleep(self.duration_s):
            say("interrupted", cid=self.cid)
            return {"delivered": False}
        say("done", cid=self.cid)
        return {"delivered": True}


class Transport(ContractNetResponder):
    def __init__(self, service: str, cost: float, task_s: float,
                 propose_delay_s: float) -> None:
        self.service = service
        self.cost = cost
        self.task_s = task_s
        self.propose_delay_s = propose_delay_s

    def service_properties(self) -> dict[str, Any]:
        return {"cost": self.cost}

    def propose(self, cfp: Message) -> Any:
        say("cfp", cid=cfp.conversation_id)
        if self.propose_delay_s > 0:
            self.sleep(self.propose_delay_s)
        return {"cost": self.cost}

    def perform(self, task: Message) -> Any:
        return Deliver(task.conversation_id, self.task_s)


class Echo(RequestResponder):
    service = "echo"

    def perform(self, task: Message) -> Any:
        return task.content


class Serve(AgentBehavior):
    def __init__(self, service: str, cost: float, task_s: float,
                 propose_delay_s: float) -> None:
        self.args = (service, cost, task_s, propose_delay_s)

    def run(self) -> None:
        self.start_behavior(Echo())
        self.start_behavior(Transport(*self.args))
        while not {"echo", self.args[0]} <= set(self.agent.services):  # both listen
            self.sleep(0.01)
        say("ready", name=self.agent.name)
        self.sleep(math.inf)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("name")
    parser.add_argument("--service", default="transport")
    parser.add_argument("--cost", type=float, default=1.0)
    parser.add_argument("--lease-s", type=float, default=1.0)
    parser.add_argument("--task-s", type=float, default=0.0)
    parser.add_argument("--propose-delay-s", type=float, default=0.0)
    args = parser.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with RosContext() as ros:
        try:
            agent = Agent(args.name, ros=ros, lease_s=args.lease_s)
        except AgentNameTaken as exc:
            say("taken", error=str(exc))
            return 3
        route = agent._route

        def traced(message: Message) -> None:  # every arrival, before anyone handles it
            say("got", performative=message.performative.value,
                cid=message.conversation_id, sender=message.sender)
            route(message)

        agent._route = traced  # type: ignore[method-assign]
        def on_event(event: Event) -> None:
            if event.kind is EventKind.AGENT_NAME_LOST:
                say("taken", error=str(event.error))
                lost.set()
                stop.set()
            else:
                say("rejected", **{k: str(v) for k, v in event.detail.items()})

        lost = threading.Event()
        agent.events.subscribe(on_event)
        with agent, HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
            agent.attach(hl)
            hl.register("serve", Serve, service=args.service, cost=args.cost, task_s=args.task_s,
                        propose_delay_s=args.propose_delay_s)
            hl.switch("serve")
            stop.wait()
    return 3 if lost.is_set() else 0


if __name__ == "__main__":
    raise SystemExit(main())
