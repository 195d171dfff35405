"""A node process of the agent tests, whose JSON lines (:mod:`agents_events`) are collected
as they come; and :func:`stop_all`, which ends a test's processes.

No beehave import: tests and benchmarks load it as it is.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import warnings
from collections.abc import Iterable, Sequence
from typing import Any

from agents_events import read_events

from beehave.testing import WALL_TIMEOUT_S, wall_timeout

TERM_WAIT_S = wall_timeout(0.25)
"""How long a node gets to end after SIGTERM (it takes well under a second) before it is
sent SIGABRT, which makes it print its threads' stacks (``PYTHONFAULTHANDLER=1``, set for
every child by ``tests/conftest.py``) and end: one that hung in its shutdown once held a
test's teardown for the whole WALL_TIMEOUT_S, and nobody saw where."""


class AgentProc:
    """``args`` run as a process; its stdout events land in :attr:`events`."""

    def __init__(self, name: str, args: Sequence[str], *, wait_s: float = WALL_TIMEOUT_S) -> None:
        self.name = name
        self.wait_s = wait_s
        # stderr to a file, copied to this process's stderr when the node has ended (a
        # failing test shows it, as before), and read for the stacks of a hung node.
        self.stderr = tempfile.TemporaryFile(prefix=f"{name}-stderr-")
        try:
            self.popen = subprocess.Popen(list(args), stdout=subprocess.PIPE, text=True,
                                          stderr=self.stderr, env=dict(os.environ))
        except BaseException:
            self.stderr.close()
            raise
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
        self._drain_stderr()

    def terminate(self) -> None:
        if self.popen.poll() is None:
            self.popen.terminate()

    def stop(self) -> None:
        self.terminate()
        try:
            self.popen.wait(TERM_WAIT_S)
            hung = False
        except subprocess.TimeoutExpired:
            hung = True
            self.popen.send_signal(signal.SIGABRT)  # its stacks, then it ends
            try:
                self.popen.wait(wall_timeout(0.1))
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(WALL_TIMEOUT_S)
        self.reader.join(WALL_TIMEOUT_S)
        text = self._drain_stderr()
        if hung:  # shown in pytest's warnings summary even when the test passed
            warnings.warn(f"{self.name} did not end within {TERM_WAIT_S:g} s of SIGTERM "
                          f"and was aborted; its stderr ends:\n{text[-6000:]}", stacklevel=2)

    def _drain_stderr(self) -> str:
        """The node's stderr, once it has ended: copied to this process's stderr (where
        pytest captures it), the file closed; "" when drained before."""
        if self.stderr.closed:
            return ""
        self.stderr.seek(0)
        text = self.stderr.read().decode("utf-8", errors="replace")
        self.stderr.close()
        sys.stderr.write(text)
        return text


def stop_all(procs: Iterable[AgentProc]) -> None:
    """SIGTERM every process first, then wait for each: on a loaded machine one after the
    other can outrun a test's timeout. Each is waited for even when another one's stop
    raised."""
    procs = list(procs)
    for proc in procs:
        proc.terminate()
    errors: list[BaseException] = []
    for proc in procs:
        try:
            proc.stop()
        except Exception as exc:  # the others still end
            errors.append(exc)
    if errors:
        raise errors[0]


def directory_state(agent: Any, what: str) -> str:
    """``what``, and why an agent's directory may not have changed as expected (in stress
    runs a killed agent stayed 60 s, a new one never appeared in 30 s): whether its expiry
    timer still runs, when it last heard its own announcement, how far behind it reads
    (counted off every lease), and each entry's age."""
    d = agent.directory
    now = time.monotonic()

    def ago(t: float | None) -> str:
        return "never" if t is None else f"{now - t:.2f} s ago"

    entries = {name: f"renewed {ago(e.renewed_at)}, lease {e.announcement.lease_s} s"
               for name, e in list(d._entries.items())}
    frames = sys._current_frames()
    executors = "".join(
        f"\n{t.name} ({'alive' if t.is_alive() else 'ended'}):\n"
        + "".join(traceback.format_stack(frames[t.ident])[-8:])
        for t in threading.enumerate()
        if t.name == "beehave:ros-executor" and t.ident in frames)
    return (f"{what}; the agent's last expiry check {ago(d._checked_at)}, its own "
            f"announcement last heard {ago(d._own_heard_at)}, receive lag "
            f"{d._receive_lag(now):.2f} s; entries: {entries}; threads: "
            f"{[t.name for t in threading.enumerate()]}; the ROS executors' stacks:"
            f"{executors or ' none'}")
