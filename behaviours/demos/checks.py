"""What every scenario ends with: its checks, measured in the physics, as a table.

A check is ``(name, ok, measured)``: what was checked, whether it held, and the measured
figure as text (so a reader sees how close a pass or a failure was)."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import time
from pathlib import Path
from typing import TextIO

from rich.table import Table
from rich.text import Text

from beehave.procs import dies_with_parent

Check = tuple[str, bool, str]

#: How long :meth:`Processes.stop` waits after SIGINT before it kills.
STOP_TIMEOUT_S = 15.0


def checks_table(title: str, results: list[Check]) -> Table:
    """The checks as a table: check, ok/FAILED, measured."""
    table = Table(title=title)
    for col in ("check", "result", "measured"):
        table.add_column(col)
    for name, ok, measured in results:
        table.add_row(name, Text("ok", style="green") if ok else Text("FAILED", style="red"),
                      measured)
    return table


def process_failures(failed: dict[str, int], log_dir: Path) -> list[Check]:
    """A failed check naming every scenario process that died, with its exit code and
    log; none when all ran to the end."""
    if not failed:
        return []
    return [("every process ran to the end", False,
             ", ".join(f"{n} exit {c} (log: {log_dir / (n + '.log')})"
                       for n, c in sorted(failed.items())))]


class Processes:
    """Child processes of a scenario by name, each with its log file (``log_dir/name.log``),
    run in ``cwd``; killed by PID in the end."""

    def __init__(self, log_dir: Path, *, cwd: Path | None = None) -> None:
        self.log_dir = log_dir
        self.cwd = cwd
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._logs: list[TextIO] = []

    def start(self, name: str, argv: list[str]) -> None:
        log = open(self.log_dir / f"{name}.log", "w")  # noqa: SIM115 - closed in kill_all
        self._logs.append(log)
        # A scenario killed with -9 (or a test worker ended by its timeout) runs no
        # cleanup: its sim, robots and agents must not run on without it.
        self.procs[name] = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT,
                                            stdin=subprocess.DEVNULL, cwd=self.cwd,
                                            preexec_fn=dies_with_parent)

    def dead(self) -> dict[str, int]:
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def stop(self, names: list[str], timeout_s: float = STOP_TIMEOUT_S) -> dict[str, int]:
        """SIGINT (a clean stop), then SIGKILL what is still there after ``timeout_s``."""
        for name in names:
            with contextlib.suppress(ProcessLookupError):
                self.procs[name].send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        codes = {}
        for name in names:
            proc = self.procs[name]
            try:
                codes[name] = proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                codes[name] = proc.wait()
        return codes

    def kill_all(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log in self._logs:
            log.close()
