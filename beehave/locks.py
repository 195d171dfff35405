"""Type locks: at most one running action per ``action_type``, across all behaviours."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from beehave.errors import ActionTypeBusy, Interrupted
from beehave.events import Event, EventBus, EventKind
from beehave.status import Status

if TYPE_CHECKING:
    from beehave.action import Action


@dataclass
class _Hold:
    holder: Action
    since: float


class TypeLocks:
    """The lock table of one manager.

    A lock is taken before the action's thread starts and released after its
    ``safe_state()`` ran, when its thread is about to end — so a STUCK action keeps its
    type until its ``run`` really returns. Preempting callers queue in FIFO order and the
    lock passes straight to the head of the queue: no third action can slip in between.
    """

    def __init__(self, events: EventBus) -> None:
        # Entered as `_lock` where nothing waits: the same lock, without Condition's
        # Python layer (every action's end releases its type here).
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._held: dict[str, _Hold] = {}
        self._queues: dict[str, deque[Action]] = {}
        self._preempting = 0  # how many wait in the queues (changed under the lock)
        self._events = events
        #: Called under the table's lock with every action that takes a lock (the manager
        #: pauses an action that starts while it is paused).
        self.on_take: Callable[[Action], None] | None = None

    def acquire(self, action: Action, *, preempt: bool, timeout_s: float,
                cancelled: Callable[[], bool]) -> None:
        """Take ``action.action_type`` for ``action`` or raise :class:`ActionTypeBusy`.

        With ``preempt`` the holder is interrupted and the call waits up to ``timeout_s``
        for it to end; a holder that ignores the interrupt is marked STUCK (its safe state
        forced) and ActionTypeBusy is raised. Raises :class:`Interrupted` when
        ``cancelled()`` becomes true while waiting.
        """
        kind = action.action_type
        with self._lock:
            queue = self._queues.setdefault(kind, deque())
            hold = self._held.get(kind)
            if hold is None and not queue:
                self._take(kind, action)
                return
            if not preempt:
                blocker = hold.holder if hold else queue[0]
                self._events.emit(Event(EventKind.LOCK_REJECTED, action.path, detail={
                    "action_type": kind, "holder": blocker.path}))
                if hold is None:  # only preemptors waiting: name the one that wins next
                    raise ActionTypeBusy(kind, blocker, time.monotonic(),
                                         reason="it is waiting to preempt the type")
                raise ActionTypeBusy(kind, hold.holder, hold.since, reason=_why(hold.holder))
            queue.append(action)
            self._preempting += 1
            deadline = time.monotonic() + timeout_s
            interrupted: set[int] = set()
            stuck_holder: _Hold | None = None
            try:
                while True:
                    hold = self._held.get(kind)
                    if hold is None and queue[0] is action:
                        self._take(kind, action)
                        return
                    if cancelled():
                        raise Interrupted(f"{action.path}: interrupted while waiting to "
                                          f"preempt action type {kind!r}")
                    if hold is not None and hold.holder.status is Status.STUCK:
                        raise ActionTypeBusy(kind, hold.holder, hold.since,
                                             reason=_why(hold.holder))
                    if hold is not None and id(hold.holder) not in interrupted:
                        interrupted.add(id(hold.holder))
                        self._events.emit(Event(EventKind.LOCK_PREEMPTED, hold.holder.path,
                                                detail={"action_type": kind,
                                                        "by": action.path}))
                        hold.holder.interrupt()
                        continue
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        if hold is None:  # free, but promised to a preemptor ahead of us
                            raise ActionTypeBusy(kind, queue[0], time.monotonic(),
                                                 reason="it is waiting to preempt the type")
                        stuck_holder = hold
                        break
                    self._cond.wait(remaining)
            finally:
                queue.remove(action)
                self._preempting -= 1
                self._cond.notify_all()
        # Outside the lock: safe_state() is user code.
        assert stuck_holder is not None
        stuck_holder.holder._mark_stuck()
        raise ActionTypeBusy(kind, stuck_holder.holder, stuck_holder.since,
                             reason=f"it ignored its interrupt for {timeout_s} s and is STUCK")

    def _take(self, kind: str, action: Action) -> None:
        self._held[kind] = _Hold(action, time.monotonic())
        if self.on_take is not None:
            self.on_take(action)

    @contextmanager
    def table(self) -> Iterator[list[Action]]:
        """Hold the table (no lock is taken or released meanwhile) and give its holders."""
        with self._lock:
            yield [hold.holder for hold in self._held.values()]

    def release(self, action: Action) -> None:
        with self._lock:
            hold = self._held.get(action.action_type)
            if hold is not None and hold.holder is action:
                del self._held[action.action_type]
                if self._queues.get(action.action_type):  # preemptors wait for it
                    self._cond.notify_all()

    def poke(self) -> None:
        """Wake preempting waiters so they re-check whether their caller was interrupted.

        Read without the lock first: a waiter that queues after this look checks whether
        it was cancelled (under the lock) before it waits, so none is missed; and an
        interrupt — every action's, in every switch — then costs no lock when nobody
        waits to preempt (the common case)."""
        if not self._preempting:
            return
        with self._lock:
            self._cond.notify_all()

    def snapshot(self) -> dict[str, dict[str, Any]]:
        now = time.monotonic()
        with self._lock:
            return {kind: {"holder": h.holder.path, "class": type(h.holder).__name__,
                           "status": h.holder.status.name, "held_s": now - h.since,
                           "safe_state_pending": h.holder.safe_state_pending}
                    for kind, h in sorted(self._held.items())}


def _why(holder: Action) -> str:
    """Why a STUCK holder still has its type (empty for a running one)."""
    if holder.status is not Status.STUCK:
        return ""
    if holder.safe_state_pending:
        return ("the holder is STUCK and its safe_state() has not returned: the type "
                "stays locked until it does")
    return "the holder is STUCK: its run() ignores its interrupt; the type is free when it returns"
