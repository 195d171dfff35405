"""A node process of the agent tests, whose JSON lines (:mod:`agents_events`) are collected
as they come; and :func:`stop_all`, which ends a test's processes.

No beehave import: tests and benchmarks load it as it is.
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
from collections.abc import Iterable, Sequence
from typing import Any

from agents_events import read_events

from beehave.testing import WALL_TIMEOUT_S


class AgentProc:
    """``args`` run as a process; its stdout events land in :attr:`events`."""

    def __init__(self, name: str, args: Sequence[str], *, wait_s: float = WALL_TIMEOUT_S) -> None:
        self.name = name
        self.wait_s = wait_s
        self.popen = subprocess.Popen(list(args), stdout=subprocess.PIPE, text=True,
                                      env=dict(os.environ))
        self.events: list[dict[str, Any]] = []
        self.cond = threading.Condition()
        assert self.popen.stdout is not None
        self.reader = threading.Thread(target=read_events,
                                       args=(self.popen.stdout, self.events, self.cond),
                                       daemon=True)
        self.reader.start()

    def wait_event(self, kind: str, *, timeout_s: float | None = None,
                   **match: Any) -> dict[str, Any]:
        """The first event ``kind`` whose fields equal ``match``; fails after the wait."""
        wait_s = self.wait_s if timeout_s is None else timeout_s

        def found() -> dict[str, Any] | None:
            return next((e for e in self.events if e["event"] == kind
                         and all(e.get(k) == v for k, v in match.items())), None)

        with self.cond:
            self.cond.wait_for(lambda: found() is not None, wait_s)
            hit = found()
        assert hit is not None, f"{self.name}: no {kind!r} {match} within {wait_s} s; " \
                                f"events: {self.events}"
        return hit

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGKILL)
        self.popen.wait(WALL_TIMEOUT_S)
        self.reader.join(WALL_TIMEOUT_S)

    def terminate(self) -> None:
        if self.popen.poll() is None:
            self.popen.terminate()

    def stop(self) -> None:
        self.terminate()
        try:
            self.popen.wait(WALL_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            self.popen.wait(WALL_TIMEOUT_S)
        self.reader.join(WALL_TIMEOUT_S)


def stop_all(procs: Iterable[AgentProc]) -> None:
    """SIGTERM every process first, then wait for each: on a loaded machine one after the
    other can outrun a test's timeout."""
    procs = list(procs)
    for proc in procs:
        proc.terminate()
    for proc in procs:
        proc.stop()
