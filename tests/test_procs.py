"""A helper process started with ``dies_with_parent`` ends when its parent is killed with
``kill -9`` (issue 23: the demo's order agent ran on for up to 600 s)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from beehave.testing import wait_until

ROOT = Path(__file__).resolve().parents[1]
# The control (no guard: the child runs on) is a negative check that runs to its end: short
# on purpose; a loaded machine cannot make a child that outlives its parent die of itself.
RUNS_ON_S = 1.0

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="PR_SET_PDEATHSIG is Linux's")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie is dead; it waits only for its (new) parent to reap it.
    stat = Path(f"/proc/{pid}/stat").read_text()
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.parametrize("guarded", [True, False])
def test_a_child_dies_with_its_killed_parent(guarded: bool) -> None:
    parent_code = textwrap.dedent(f"""
        import subprocess, sys, time
        from beehave.procs import dies_with_parent
        child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"],
                                 preexec_fn=dies_with_parent if {guarded} else None)
        print(child.pid, flush=True)
        time.sleep(120)
    """)
    parent = subprocess.Popen([sys.executable, "-c", parent_code], cwd=ROOT,
                              stdout=subprocess.PIPE, text=True)
    child_pid = None
    try:
        assert parent.stdout is not None
        child_pid = int(parent.stdout.readline())
        assert _alive(child_pid)
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        if guarded:
            assert wait_until(lambda: not _alive(child_pid))
        else:  # the control: without it, the child runs on
            assert not wait_until(lambda: not _alive(child_pid), timeout_s=RUNS_ON_S)
    finally:
        if parent.poll() is None:
            parent.kill()
        if child_pid is not None and _alive(child_pid):
            os.kill(child_pid, signal.SIGKILL)
