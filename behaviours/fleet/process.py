"""One agent process of the fleet (a machine, a charging station): a ROS 2 context, an
:class:`~beehave.agents.Agent` and a :class:`~beehave.HighLevelBehaviorManager` running one
top-level behaviour, until SIGINT or SIGTERM."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from typing import Any

from beehave import HighLevelBehaviorManager
from beehave.agents import Agent, AgentNameTaken
from beehave.behavior import Behavior
from beehave.errors import ConfigError
from beehave.events import Event, EventKind


def say(event: str, **detail: Any) -> None:
    """One JSON line on stdout: what the launcher (and a user) reads."""
    print(json.dumps({"event": event, **detail}), flush=True)


def add_trust_options(parser: argparse.ArgumentParser) -> None:
    """``--mode`` and ``--keys``: how the agent signs and what it takes
    (docs/agents.md#trust-model); without them, ``BEEHAVE_AGENT_MODE`` and
    ``BEEHAVE_AGENT_KEYS`` decide."""
    parser.add_argument("--mode", choices=["open", "signed"], default=None,
                        help="open: nothing checked; signed: take only what the fleet's "
                             "certified keys signed (default: $BEEHAVE_AGENT_MODE, else open)")
    parser.add_argument("--keys", default=None, metavar="DIR",
                        help="the folder `beehave keys` wrote (fleet.pub, NAME.key, "
                             "NAME.cert; default: $BEEHAVE_AGENT_KEYS)")


def trust_of(name: str, args: argparse.Namespace) -> Any:
    """The :class:`~beehave.agents.trust.Trust` the options ask for (None: the environment
    decides)."""
    from beehave.agents.trust import Trust

    mode, keys = getattr(args, "mode", None), getattr(args, "keys", None)
    if mode is None and keys is None:
        return None
    if keys is None:
        return Trust(str(mode), name=name)
    return Trust.load(name, mode=mode or "signed", keys_dir=keys)


def serve(name: str, behavior: type[Behavior], params: dict[str, Any], *,
          lease_s: float = 2.0, args: argparse.Namespace | None = None) -> int:
    """Run ``behavior`` as agent ``name``; exit status 0, 3 when the name is taken, 1 when
    the behaviour failed, 2 for keys that cannot be used (``{"event": "config"}``)."""
    sys.setswitchinterval(0.001)  # a thread woken by a message runs within 1 ms
    from beehave.ros.context import RosContext

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    failed: list[str] = []
    with RosContext() as ros:
        try:
            agent = Agent(name, ros=ros, lease_s=lease_s,
                          trust=trust_of(name, args) if args is not None else None)
        except AgentNameTaken as exc:
            say("taken", agent=name, error=str(exc))
            return 3
        except ConfigError as exc:
            say("config", agent=name, error=str(exc))
            return 2
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
