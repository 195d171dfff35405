"""The lifecycle of everything beehave runs: behaviours, actions, logics."""

from __future__ import annotations

from enum import Enum


class Status(Enum):
    """Where a behaviour, action or logic is in its life.

    The transitions happen in one place (the framework's driver); user code only reads them.
    ``PENDING → RUNNING → {SUCCEEDED, FAILED, INTERRUPTED}``, or ``RUNNING → STUCK`` when the
    owner gave up waiting for an interrupted action.
    """

    PENDING = "PENDING"
    """Created, not yet started."""
    RUNNING = "RUNNING"
    """Its ``run`` is executing in its own thread (or task, for a logic)."""
    SUCCEEDED = "SUCCEEDED"
    """``run`` returned without being interrupted; ``.result`` holds its return value."""
    FAILED = "FAILED"
    """``run`` raised; the exception is on ``.error`` (with its traceback)."""
    INTERRUPTED = "INTERRUPTED"
    """It was asked to stop and ended within the owner's ``stop_timeout_s``."""
    STUCK = "STUCK"
    """It ignored its interrupt for ``stop_timeout_s``: its ``safe_state()`` was forced and
    its owner went on; an action keeps its type lock until its thread really ends."""

    @property
    def finished(self) -> bool:
        """True once the outcome is decided (a STUCK thread may still be alive)."""
        return self not in (Status.PENDING, Status.RUNNING)

    @property
    def succeeded(self) -> bool:
        return self is Status.SUCCEEDED
