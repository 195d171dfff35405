"""Lifecycle events: what the managers tell observers (logging, ROS bridge, web view)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

log = logging.getLogger(__name__)


class EventKind(Enum):
    """What happened."""

    STARTED = "started"
    """A behaviour, action or logic began to run."""
    ENDED = "ended"
    """It ended; ``status`` and ``error`` say how."""
    STUCK = "stuck"
    """It ignored its interrupt for ``stop_timeout_s``; its safe state was forced."""
    STUCK_RELEASED = "stuck_released"
    """A STUCK action's thread finally ended and its type lock was released."""
    SAFE_STATE_OVERDUE = "safe_state_overdue"
    """The forced ``safe_state()`` of a STUCK action had not returned when the switch (or
    shutdown) had to go on; it keeps running in a thread of its own, and the action's type
    stays locked until it returns."""
    SAFE_STATE_RAN = "safe_state_ran"
    """An action's (or a HAL's) ``safe_state()`` returned: the proof, in events and
    recordings, that the hardware was left predictable. ``status`` is how the action ended
    (INTERRUPTED, FAILED, STUCK), ``detail`` has ``took_s`` (and ``forced`` when a STUCK
    action's or a blocked loop's safe state was forced from another thread)."""
    SAFE_STATE_FAILED = "safe_state_failed"
    """``safe_state()`` raised; the error is attached."""
    HOOK_FAILED = "hook_failed"
    """An optional hook (``on_child_ended``, ``on_interrupt``) raised; the error is attached
    and raised again in the behaviour's own thread."""
    PAUSE_REQUESTED = "pause_requested"
    """``hl.pause()`` (or ``request_pause()``) was called: recordings replay it from here."""
    PAUSED = "paused"
    """``hl.pause()`` took effect: ``subject`` is the top-level behaviour, ``detail`` has
    ``actions`` (the paths paused), ``stuck`` (those that ignored it and became STUCK) and
    ``took_s``. Emitted once every action stands in its safe state."""
    RESUMED = "resumed"
    """The pause ended: ``detail`` has ``by`` (``resume``, or the ``switch``/``shutdown``
    that ended it: then nothing restarts), ``paused_s`` and ``actions``."""
    SWITCH_REQUESTED = "switch_requested"
    SWITCH_COMPLETED = "switch_completed"
    SWITCH_SUPERSEDED = "switch_superseded"
    SWITCH_REJECTED = "switch_rejected"
    """Unknown name or parameters the constructor rejects; nothing was stopped."""
    FALLBACK = "fallback"
    """A top-level behaviour (or logic) ended on its own; the manager started its fallback."""
    LOCK_REJECTED = "lock_rejected"
    LOCK_PREEMPTED = "lock_preempted"
    RESTARTED = "restarted"
    """A HAL whose run() crashed was restarted."""
    LOOP_BLOCKED = "loop_blocked"
    """The low level's event loop did not answer for ``loop_lag_warn_s``: ``subject`` names
    the culprit (``logic:<path>``, ``hal:<name>``), ``detail`` says where and for how long.
    Emitted from the watchdog thread (the loop cannot), and once more with
    ``detail["ended"]`` True from the loop when it answers again."""
    MESSAGE_REJECTED = "message_rejected"
    """An agent received a message it could not take (malformed JSON, a schema error, not
    addressed to it, no one to deliver it to): ``subject`` is the agent, ``detail`` says
    why and who sent it; the sender got a not-understood reply when one could be named."""
    AGENT_NAME_LOST = "agent_name_lost"
    """An agent learnt after it started that an older process holds its name (discovery had
    not reached it while it checked): it closes itself; ``detail`` names the holder."""


@dataclass(frozen=True)
class Event:
    """One lifecycle event. ``subject`` is the path of the thing (``tour/drive``)."""

    kind: EventKind
    subject: str
    status: str | None = None
    error: BaseException | None = None
    detail: dict[str, Any] = field(default_factory=dict)
    stamp: float = field(default_factory=time.time)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-serialisable form."""
        return {
            "kind": self.kind.value,
            "subject": self.subject,
            "status": self.status,
            "error": None if self.error is None else repr(self.error),
            "detail": self.detail,
            "stamp": self.stamp,
        }


EventCallback = Callable[[Event], None]


class EventBus:
    """Delivers events synchronously, in the thread that produced them.

    Keep callbacks short (hand work to your own queue): they run inside the framework's
    driver. A callback that raises is logged with its traceback and stays subscribed; it
    is an observer and must not break what it observes.
    """

    def __init__(self, logger: logging.Logger | None = None) -> None:
        self._subscribers: tuple[EventCallback, ...] = ()
        self._lock = threading.Lock()
        self._log = logger or log

    def subscribe(self, callback: EventCallback) -> Callable[[], None]:
        """Call ``callback(event)`` for every event; returns a function that unsubscribes."""
        with self._lock:
            self._subscribers = (*self._subscribers, callback)

        def unsubscribe() -> None:
            with self._lock:
                self._subscribers = tuple(s for s in self._subscribers if s is not callback)

        return unsubscribe

    def wants(self, kind: EventKind) -> bool:
        """Whether an event of ``kind`` would reach anyone (a subscriber or the log): hot
        paths build their events only then."""
        if self._subscribers or self._log.isEnabledFor(logging.DEBUG):
            return True
        # (A tuple: membership by identity, without hashing the Enum member in Python.)
        return kind in _WARN_KINDS and self._log.isEnabledFor(logging.WARNING)

    def emit(self, event: Event, *, log_it: bool = True) -> None:
        """Log ``event`` (``log_it`` False: another bus logs it) and give it to every
        subscriber."""
        warn = event.kind in _WARN or (event.kind is EventKind.FALLBACK and event.error is not None)
        level = logging.WARNING if warn else logging.DEBUG
        if log_it and self._log.isEnabledFor(level):
            self._log.log(level, "%s", describe(event))
        for callback in self._subscribers:
            try:
                callback(event)
            except Exception:
                self._log.exception("event subscriber %r raised on %s", callback, event.kind)


def describe(event: Event) -> str:
    """One log line for ``event``."""
    if event.kind is EventKind.FALLBACK:
        to = event.detail.get("to")
        text = (f"{event.subject} ended {event.status or ''} on its own; "
                + (f"starting {to!r}" if to else "nothing to fall back to"))
    else:
        text = f"{event.kind.value} {event.subject}{f' {event.status}' if event.status else ''}"
    if event.kind in _WARN and event.detail:
        text += " (" + ", ".join(f"{k}={v}" for k, v in event.detail.items()) + ")"
    if event.error is not None:
        text += f" error={event.error!r}"
    return text


_WARN = {EventKind.STUCK, EventKind.SAFE_STATE_FAILED, EventKind.HOOK_FAILED,
         EventKind.RESTARTED, EventKind.SAFE_STATE_OVERDUE, EventKind.MESSAGE_REJECTED,
         EventKind.AGENT_NAME_LOST}
_WARN_KINDS = tuple(_WARN)
