"""One agent process of the fleet (a machine, a charging station): a ROS 2 context, an
:class:`~beehave.agents.Agent` and a :class:`~beehave.HighLevelBehaviorManager` running one
top-level behaviour, until SIGINT or SIGTERM."""

from __future__ import annotations

import json
import signal
import sys
import threading
from typing import Any

from beehave import HighLevelBehaviorManager
from beehave.agents import Agent, AgentNameTaken
from beehave.behavior import Behavior
from beehave.events import Event, EventKind


def say(event: str, **detail: Any) -> None:
    """One JSON line on stdout: what the launcher (and a user) reads."""
    print(json.dumps({"event": event, **detail}), flush=True)


def serve(name: str, behavior: type[Behavior], params: dict[str, Any], *,
          lease_s: float = 2.0) -> int:
    """Run ``behavior`` as agent ``name``; exit status 0, 3 when the name is taken, 1 when
    the behaviour failed."""
    sys.setswitchinterval(0.001)  # a thread woken by a message runs within 1 ms
    from beehave.ros.context import RosContext

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    failed: list[str] = []
    with RosContext() as ros:
        try:
            agent = Agent(name, ros=ros, lease_s=lease_s)
        except AgentNameTaken as exc:
            say("taken", agent=name, error=str(exc))
            return 3
        with agent, HighLevelBehaviorManager(stop_timeout_s=2.0) as hl:
            hl.node = agent.node
            agent.attach(hl)

            def on_event(event: Event) -> None:
                if event.kind is EventKind.AGENT_NAME_LOST or (
                        event.subject == "main" and event.kind is EventKind.ENDED
                        and event.status == "FAILED"):
                    failed.append(f"{event.kind.value} {event.status}: {event.error!r}")
                    stop.set()

            hl.subscribe(on_event)
            hl.register("main", behavior, **params)
            hl.switch("main")
            say("ready", agent=name)
            stop.wait()
    if failed:
        say("failed", agent=name, error=failed[0])
        return 1
    return 0
