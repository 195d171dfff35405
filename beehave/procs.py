"""Child processes that do not outlive the process that started them.

A demo or scenario that starts helper processes (an order agent, a droid) and is killed
with ``kill -9`` runs no cleanup: without help its children run on -- for minutes, still
on the DDS domain, still sending orders. On Linux the kernel can send a child a signal when
its parent dies (``prctl(PR_SET_PDEATHSIG)``); :func:`dies_with_parent` asks for it::

    subprocess.Popen([...], preexec_fn=dies_with_parent)

Elsewhere it does nothing (the children are still ended by the normal shutdown paths).

It runs between ``fork`` and ``exec`` in a copy of a process whose other threads (DDS,
physics) may have held any lock at the fork, so it calls only what was resolved here at
import (libc's ``prctl``; no ``dlopen``, no import). The kernel's "parent" is the *thread*
that called ``Popen``: start such children from a thread that outlives them (the main one).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

_PR_SET_PDEATHSIG = 1
_prctl = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None


def dies_with_parent() -> None:
    """In the child, before ``exec``: SIGTERM when the parent dies (Linux), and at once
    if it already has (it died between ``fork`` and here)."""
    if _prctl is None:
        return
    parent = os.getppid()
    _prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != parent or parent == 1:
        os.kill(os.getpid(), signal.SIGTERM)
