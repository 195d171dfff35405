"""A market broker, in a process of its own (``tests/test_market.py``,
``benchmarks/bench_market.py``) or in the test's process (:class:`ScriptedBroker`).

    python tests/market_node.py NAME --caps carry,display [--cost 1.0] [--lease-s 1.0]
                                     [--lie]

The broker bids ``cost + 10 × its queue length`` for every role whose capability it
has. An awarded role runs the *script* the task gives in the role's params, step by step
(``"sleep:0.5"``, ``"signal:at_meeting"``, ``"wait:serve:at_meeting"``, ``"fail_first:N"``:
fail the first N times this broker performs the role), so a test writes
the choreography of a coalition in the task itself. ``--lie``: it bids, then ignores the
award (never starts). Every step is printed as a JSON line (``ready``, ``perform``,
``step``, ``ended``, ``ignored``).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents_events import say  # noqa: E402

from beehave import Action, HighLevelBehaviorManager  # noqa: E402
from beehave.agents import Agent, AgentBehavior, Message, Performative  # noqa: E402
from beehave.agents.market import Broker, Job  # noqa: E402
from beehave.errors import Interrupted  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402

Report = Callable[..., None]


class Script(Action):
    """Performs one role by its script (``job.role.params["script"]``)."""

    action_type = "role"  # one role at a time per robot: the others queue
    performed: Counter[tuple[str, str, str]] = Counter()  # (broker, task, role) → times

    def __init__(self, job: Job, report: Report, me: str) -> None:
        self.job = job
        self.report = report
        self.me = me

    def run(self) -> dict[str, Any]:
        job = self.job
        ids = {"task": job.task.id, "role": job.role.name, "broker": self.me}
        self.report("perform", **ids)
        Script.performed[(self.me, job.task.id, job.role.name)] += 1
        try:
            for step in job.role.params.get("script", []):
                op, _, arg = step.partition(":")
                self.report("step", step=step, **ids)
                if op == "sleep" and not self.sleep(float(arg)):
                    raise Interrupted(f"{self.path}: interrupted in {step}")
                if op == "signal":
                    job.signal(arg)
                elif op == "wait":
                    job.wait_for(arg, timeout_s=float(job.role.params.get("wait_s", 20.0)))
                elif op == "fail_first" and \
                        Script.performed[(self.me, job.task.id, job.role.name)] <= int(arg):
                    raise RuntimeError(f"{self.path}: scripted failure ({step})")
        except BaseException as exc:
            self.report("ended", outcome=type(exc).__name__, **ids)
            raise
        self.report("ended", outcome="done", **ids)
        return {"by": self.me, "role": job.role.name}


class ScriptedBroker(Broker):
    """``refuse``: the reason it gives for every role instead of a bid. ``forge``: the
    JSON value it puts on the wire as the cost of each of its bids (a negative number,
    ``true``, a string: what a broken or hostile broker might send)."""

    def __init__(self, caps: list[str], cost: float = 1.0, *, lie: bool = False,
                 report: Report = say, refuse: str | None = None,
                 forge: Any = None) -> None:
        self.capabilities = tuple(caps)
        self.base = cost
        self.lie = lie
        self.report = report
        self.refusal = refuse
        self.forge = forge

    def cost(self, job: Job, queue: list[Job]) -> float | str | None:
        if self.refusal is not None:
            return self.refusal
        return self.base + 10.0 * len(queue)

    def _reply(self, to: Message, performative: Performative, content: Any = None) -> bool:
        if self.forge is not None and performative is Performative.PROPOSE:
            content = {**content, "bids": [{**b, "cost": self.forge}
                                           for b in content["bids"]]}
        return super()._reply(to, performative, content)

    def perform_role(self, job: Job) -> Action:
        return Script(job, self.report, self.agent.name)

    def _handle(self, message: Message) -> None:
        if self.lie and message.performative is Performative.ACCEPT_PROPOSAL:
            self.report("ignored", broker=self.agent.name, cid=message.conversation_id)
            return  # a broker that bids and never starts
        super()._handle(message)


class Serve(AgentBehavior):
    def __init__(self, caps: list[str], cost: float, lie: bool) -> None:
        self.args = (caps, cost)
        self.lie = lie

    def run(self) -> None:
        self.start_behavior(ScriptedBroker(*self.args, lie=self.lie))
        while "broker" not in self.agent.services:
            self.sleep(0.01)
        say("ready", name=self.agent.name)
        self.sleep(float("inf"))


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("name")
    parser.add_argument("--caps", default="carry")
    parser.add_argument("--cost", type=float, default=1.0)
    parser.add_argument("--lease-s", type=float, default=1.0)
    parser.add_argument("--lie", action="store_true")
    args = parser.parse_args()
    sys.setswitchinterval(0.001)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with RosContext() as ros:
        agent = Agent(args.name, ros=ros, lease_s=args.lease_s, probe_s=0.3)
        with agent, HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
            agent.attach(hl)
            hl.register("serve", Serve, caps=args.caps.split(","), cost=args.cost,
                        lie=args.lie)
            hl.switch("serve")
            stop.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
