"""The blackboard: named variables that push their changes to whoever subscribed.

Keys are ``/``-separated paths (``battery/percentage``). HALs write the hardware state,
logics watch what they react to::

    async for change in self.blackboard.watch("battery/percentage"):
        led.set("red" if change.value < 20 else "green")

Threads and the loop
    A blackboard works on its own, like a dict whose callbacks run synchronously in the
    thread that calls :meth:`Blackboard.set` (this is how the high level can keep a mirror).
    Callbacks never run under the blackboard's lock, so a slow one (a "battery low →
    switch" that waits for a behaviour to end) blocks no other thread's ``set``,
    ``subscribe`` or ``close``. The changes of one key are delivered one at a time and in
    the order of the writes: a write made while another thread is still notifying that
    key's subscribers, or by one of its callbacks, is stored at once and delivered by the
    thread already notifying, right after the running callback. Changes of different keys
    written by different threads may be delivered concurrently.
    Once it is *bound* to an asyncio loop (the :class:`~beehave.lowlevel.LowLevelBehaviorManager`
    binds it; the first :meth:`~Blackboard.watch` inside a running loop binds it too), a set
    made in the loop's thread notifies at once, and a set from any other thread stores the
    value immediately (so :meth:`~Blackboard.get` sees it) and hands the notification into
    the loop. Callbacks and watchers then always run in the loop's thread.

Patterns
    ``battery/percentage`` matches that key only; ``*`` matches exactly one segment
    (``leds/*`` matches ``leds/front`` but not ``leds/front/left``); ``**`` matches zero or
    more segments, so ``battery/**`` watches the whole subtree including ``battery`` itself
    and ``**`` alone watches everything. A segment is either a name or a wildcard:
    ``led*`` is not a valid pattern.

Slow watchers
    A watcher keeps at most one pending change per key: when a key changes again before the
    watcher has taken the previous change, the newer one replaces it (``Watcher.coalesced``
    counts how often). Writers never wait for readers, memory stays bounded by the number of
    keys, and the last value written is always delivered.

Freshness and relevance
    Writing the value a key already holds (same type, equal) only refreshes the entry's
    freshness and stamp: nobody is woken, since nothing changed.
    :meth:`Blackboard.declare` gives a key a ``max_age_s`` (the entry becomes stale when no
    one wrote it for that long; bound to a loop, watchers receive a ``stale=True`` change)
    and a numeric ``deadband`` (a new value closer than ``deadband`` to the last published
    one only refreshes the entry's freshness; nobody is woken — the *Monitor* of the
    ROS-JADE agent architecture). A writer's entries can be marked stale at once with
    :meth:`Blackboard.mark_stale` (the HAL manager does so when a HAL crashes).
"""

from __future__ import annotations

import asyncio
import logging
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from numbers import Real
from typing import Any, Self

from beehave.errors import BlackboardError

log = logging.getLogger(__name__)

__all__ = ["Blackboard", "BlackboardClient", "BlackboardView", "Change", "Subscription", "Watcher",
           "from_json", "matches", "to_json"]

_SEGMENT = re.compile(r"[^/*\s]+")
_KEY = re.compile(r"[^/*\s]+(?:/[^/*\s]+)*")

ChangeCallback = Callable[["Change"], None]
ErrorHook = Callable[["Subscription", BaseException], None]


class Change:
    """One value of one key, as it was written: the blackboard's entry *is* its latest change.

    ``key``, ``value``, ``stamp`` (``time.time()`` of the write), ``monotonic``
    (``time.monotonic()`` of the write, for ages), ``writer`` (who wrote it: ``"hal:debug"``,
    ``"logic:led"`` or None) and ``stale`` (the writer is gone or silent for longer than the
    key's ``max_age_s``). Treat it as read-only; it is shared by every subscriber.
    """

    __slots__ = ("key", "value", "stamp", "monotonic", "writer", "stale")

    def __init__(self, key: str, value: Any, stamp: float, monotonic: float,
                 writer: str | None, stale: bool = False) -> None:
        self.key = key
        self.value = value
        self.stamp = stamp
        self.monotonic = monotonic
        self.writer = writer
        self.stale = stale

    @property
    def age_s(self) -> float:
        """Seconds since the value was written."""
        return time.monotonic() - self.monotonic

    def as_stale(self) -> Change:
        """The same value, flagged stale."""
        return Change(self.key, self.value, self.stamp, self.monotonic, self.writer, True)

    def as_dict(self) -> dict[str, Any]:
        """A strict-JSON form (the value encoded by :func:`to_json`)."""
        return {"value": to_json(self.value), "stamp": self.stamp, "stale": self.stale,
                "writer": self.writer, "age_s": round(self.age_s, 6)}

    def __repr__(self) -> str:
        flag = ", stale" if self.stale else ""
        return f"Change({self.key!r}, {self.value!r}, writer={self.writer!r}{flag})"


_FLOAT_TAG = "$float"
_NON_FINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def to_json(value: Any) -> Any:
    """``value`` as strict JSON data (what :meth:`Change.as_dict` and the ROS 2 bridge send).

    Tuples become lists, mapping keys strings, and values JSON cannot hold their ``repr``.
    Non-finite floats, which strict JSON lacks, become tagged objects —
    ``{"$float": "inf"}``, ``{"$float": "-inf"}``, ``{"$float": "nan"}`` — so that "nothing
    in range" (``inf``) is still a number after :func:`from_json`, not the string
    ``'inf'`` that fails ``front_m < 0.5``.
    """
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        return {_FLOAT_TAG: "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    return repr(value)


def from_json(value: Any) -> Any:
    """The inverse of :func:`to_json` for its JSON data: tagged non-finite floats become
    floats again (in lists and mappings too); everything else is returned as it is."""
    if isinstance(value, dict):
        if len(value) == 1 and _FLOAT_TAG in value:
            tag = value[_FLOAT_TAG]
            if isinstance(tag, str) and tag in _NON_FINITE:
                return _NON_FINITE[tag]
        return {k: from_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [from_json(v) for v in value]
    return value


def _same(old: Any, new: Any) -> bool:
    """Whether writing ``new`` over ``old`` changes nothing (same type, equal value).

    NaN counts as the same value as NaN (also inside lists, tuples and dicts): a sensor
    that keeps reporting "no reading" has not changed, although ``nan != nan``."""
    if type(old) is not type(new):
        return False
    try:
        if old == new:
            return True
    except Exception:  # values whose comparison fails (numpy arrays …) count as changes
        return False
    # Only unequal values get here, so the NaN checks cost nothing on the common path.
    if isinstance(old, float):
        return math.isnan(old) and math.isnan(new)
    if isinstance(old, (list, tuple)):
        return len(old) == len(new) and all(_same(a, b) for a, b in zip(old, new, strict=True))
    if isinstance(old, dict):
        return old.keys() == new.keys() and all(_same(v, new[k]) for k, v in old.items())
    return False


def check_key(key: object) -> str:
    """Return ``key`` if it is a valid key, else raise :class:`BlackboardError` naming it."""
    if not isinstance(key, str) or _KEY.fullmatch(key) is None:
        raise BlackboardError(
            f"invalid blackboard key {key!r}: use non-empty '/'-separated names without "
            "spaces or '*', e.g. 'battery/percentage'")
    return key


#: The longest pattern accepted (characters): far above any real key, far below what a
#: pathological pattern would need to cost anything.
MAX_PATTERN_CHARS = 512


def _compile(pattern: object) -> tuple[str, ...]:
    if not isinstance(pattern, str) or not pattern:
        raise BlackboardError(f"invalid blackboard pattern {pattern!r}: expected e.g. "
                              "'battery/percentage', 'leds/*' or 'battery/**'")
    if len(pattern) > MAX_PATTERN_CHARS:
        raise BlackboardError(f"invalid blackboard pattern {pattern[:40]!r}…: "
                              f"{len(pattern)} characters, at most {MAX_PATTERN_CHARS}")
    segments = tuple(pattern.split("/"))
    for seg in segments:
        if seg not in ("*", "**") and _SEGMENT.fullmatch(seg) is None:
            raise BlackboardError(
                f"invalid blackboard pattern {pattern[:80]!r}: segment {seg[:40]!r} must be "
                "a name, '*' (one segment) or '**' (any number of segments)")
    # Consecutive '**' match what one does: fold them (the matcher's cost stays the same).
    folded: list[str] = []
    for seg in segments:
        if not (seg == "**" and folded and folded[-1] == "**"):
            folded.append(seg)
    return tuple(folded)


def _match(pat: tuple[str, ...], key: tuple[str, ...]) -> bool:
    """Whether ``key`` matches ``pat``: one pass over the pattern, keeping the set of key
    positions reachable so far (time O(len(pat) × len(key)), no recursion)."""
    reach = {0}
    for seg in pat:
        if seg == "**":
            start = min(reach)
            reach = set(range(start, len(key) + 1))
        else:
            reach = {i + 1 for i in reach
                     if i < len(key) and (seg == "*" or seg == key[i])}
        if not reach:
            return False
    return len(key) in reach


def matches(pattern: str, key: str) -> bool:
    """Whether ``key`` matches ``pattern`` (see the module docstring for the syntax)."""
    return _match(_compile(pattern), tuple(check_key(key).split("/")))


def _within(old: Any, new: Any, deadband: float) -> bool:
    """Whether ``new`` is closer than ``deadband`` to ``old`` (numbers or number vectors)."""
    if isinstance(old, bool) or isinstance(new, bool):
        return False
    if isinstance(old, Real) and isinstance(new, Real):
        return abs(float(new) - float(old)) < deadband
    if (isinstance(old, (tuple, list)) and isinstance(new, (tuple, list))
            and len(old) == len(new)
            and all(isinstance(v, Real) and not isinstance(v, bool) for v in (*old, *new))):
        return math.dist(old, new) < deadband
    return False


class Slot:
    """Everything the blackboard knows about one key; looked up once per ``set``."""

    __slots__ = ("key", "parts", "change", "notified", "subs", "max_age_s", "deadband",
                 "timer", "outbox", "delivering")

    def __init__(self, key: str) -> None:
        self.key = key
        self.parts = tuple(key.split("/"))
        self.change: Change | None = None
        self.notified: Change | None = None
        self.subs: tuple[Subscription, ...] = ()
        self.max_age_s: float | None = None
        self.deadband: float | None = None
        self.timer: asyncio.TimerHandle | None = None
        # Unbound delivery (under the blackboard's lock): changes waiting, in write order,
        # with "only if still current" (stale marks), and whether a thread delivers them.
        self.outbox: deque[tuple[Change, bool]] = deque()
        self.delivering = False


class Subscription:
    """A registration for the changes of every key matching ``pattern``.

    Close it (or leave its ``with`` block) to stop receiving; whoever subscribed owns it
    (a logic's or HAL's subscriptions are closed when it ends). A callback that raises is
    closed, its exception is kept on ``.error`` and reported to the blackboard's
    ``on_error`` hook (the low-level manager turns it into an event).
    """

    def __init__(self, board: Blackboard, pattern: str, callback: ChangeCallback | None) -> None:
        self.board = board
        self.pattern = pattern
        self.parts = _compile(pattern)
        self.callback = callback
        self.closed = False
        self.error: BaseException | None = None

    def deliver(self, change: Change) -> None:
        """Called by the blackboard for each matching change (in the notifying thread)."""
        assert self.callback is not None
        if self.closed:
            # Delivery runs outside the blackboard's lock, so close() does not wait for a
            # delivery under way: a subscription closed meanwhile must not be called any
            # more (a callback that had already started may still finish).
            return
        try:
            self.callback(change)
        except Exception as exc:  # an observer must not break the writer: record + report
            self.error = exc
            self.close()
            self.board._report(self, exc)

    def close(self) -> None:
        """Stop receiving changes; idempotent. No delivery starts after it returns; a
        callback another thread is running at that moment may still finish."""
        if not self.closed:
            self.closed = True
            self.board._unsubscribe(self)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.pattern!r}{', closed' if self.closed else ''})"


_FAIRNESS_STREAK = 64
"""A watcher yields to the loop after this many changes handed out without waiting."""


class Watcher(Subscription):
    """An async iterator over the changes of keys matching a pattern.

    Created by :meth:`Blackboard.watch`; iterate it in the blackboard's loop. It holds at
    most one pending change per key (see *Slow watchers* in the module docstring). Iteration
    ends when it is closed.
    """

    def __init__(self, board: Blackboard, pattern: str, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__(board, pattern, None)
        self.loop = loop
        self.coalesced = 0
        """How many changes were replaced by a newer one before this watcher took them."""
        self._pending: dict[str, Change] = {}
        self._waiter: asyncio.Future[None] | None = None
        self._streak = 0  # changes handed out in a row without suspending

    @property
    def pending(self) -> int:
        """How many keys have a change waiting to be taken."""
        return len(self._pending)

    def deliver(self, change: Change) -> None:
        pending = self._pending
        if change.key in pending:
            self.coalesced += 1
        pending[change.key] = change
        waiter = self._waiter
        if waiter is not None:
            self._waiter = None
            if not waiter.done():
                if self.board._on_wake:
                    self.board._woke()
                waiter.set_result(None)

    def _wake(self) -> None:
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def close(self) -> None:
        if self.closed:
            return
        super().close()
        if self._waiter is not None:
            try:
                self.loop.call_soon_threadsafe(self._wake)
            except RuntimeError:  # loop already closed: nobody is waiting any more
                pass

    def __aiter__(self) -> Watcher:
        return self

    async def next(self, timeout_s: float | None = None) -> Change | None:
        """The next change, or None when none came within ``timeout_s`` — for logics that
        also act on time (blinking, timeouts). Cancellation-safe; do not build this with
        ``asyncio.wait_for(watcher.__anext__(), …)``: on Python 3.11 ``wait_for`` can
        swallow a cancellation that arrives as a change does, leaving the logic STUCK."""
        try:
            async with asyncio.timeout(timeout_s):
                return await self.__anext__()
        except TimeoutError:
            return None

    async def __anext__(self) -> Change:
        pending = self._pending
        if pending:
            self._streak += 1
            if self._streak >= _FAIRNESS_STREAK:
                # A logic that writes what it watches would otherwise never suspend:
                # the loop (and its cancellation) would starve.
                self._streak = 0
                await asyncio.sleep(0)
        else:
            self._streak = 0
        while not pending:
            if self.closed:
                raise StopAsyncIteration
            waiter = self.loop.create_future()
            self._waiter = waiter
            try:
                await waiter
            finally:
                self._waiter = None
        key = next(iter(pending))
        return pending.pop(key)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    def __enter__(self) -> Self:
        return self


class Blackboard:
    """Named variables with change notification. See the module docstring for the rules.

    ``clock`` (default ``time.monotonic``) measures ages; tests may pass a fake one.
    ``on_error(subscription, exc)`` is called when a callback raises.
    """

    def __init__(self, *, clock: Callable[[], float] = time.monotonic,
                 on_error: ErrorHook | None = None) -> None:
        self._slots: dict[str, Slot] = {}
        self._subs: list[Subscription] = []
        self._lock = threading.RLock()
        self._clock = clock
        self.on_error = on_error
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_tid: int | None = None
        self._pending: dict[str, Slot] = {}
        self._flush_scheduled = False
        self._taps: tuple[ChangeCallback, ...] = ()
        self._on_wake: tuple[Callable[[], None], ...] = ()

    # -- binding -------------------------------------------------------------------------

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        """The loop notifications run in, or None (synchronous, like a dict)."""
        return self._loop

    def bind(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Deliver notifications in ``loop`` (default: the running one); call it in that loop.

        ``bind(None)`` outside a running loop, or :meth:`unbind`, returns to synchronous
        delivery.
        """
        if loop is None:
            loop = asyncio.get_running_loop()
        with self._lock:
            if self._loop is not None and self._loop is not loop and not self._loop.is_closed():
                raise BlackboardError("blackboard is already bound to another running loop")
            self._loop = loop
            self._loop_tid = threading.get_ident()

    def unbind(self) -> None:
        """Deliver what is pending and return to synchronous delivery (call it in the loop)."""
        self._flush()
        with self._lock:
            for slot in self._slots.values():
                if slot.timer is not None:
                    slot.timer.cancel()
                    slot.timer = None
            self._loop = None
            self._loop_tid = None

    # -- writing -------------------------------------------------------------------------

    def set(self, key: str, value: Any, *, writer: str | None = None,
            stale: bool = False) -> None:
        """Write ``value`` under ``key`` and notify the subscribers whose pattern matches.

        Safe from any thread; never blocks on readers. ``writer`` is remembered on the entry
        (a :class:`BlackboardClient` fills it in for you). ``stale=True`` stores the value
        already flagged stale — for a mirror copying another blackboard's stale entry: one
        change, and none at all when the entry holds that value, stale, already (writing
        it then marking it stale would tell subscribers it was fresh in between).
        """
        slot = self._slots.get(key)
        if slot is None:
            slot = self._slot(key)
        if threading.get_ident() == self._loop_tid:
            change = self._store(slot, value, writer, stale)
            if change is not None:
                self._notify(slot, change)
            return
        first: Change | None
        with self._lock:
            loop = self._loop
            change = first = self._store(slot, value, writer, stale)
            if change is None:
                return
            if loop is not None:
                self._pending[key] = slot
                if self._flush_scheduled:
                    return
                self._flush_scheduled = True
            elif slot.delivering:
                slot.outbox.append((change, False))
                return  # the thread delivering this key takes it, in order
            elif not slot.subs:
                slot.notified = change  # nobody to tell
                return
            else:
                slot.delivering = True
                if slot.outbox:
                    # Left by a delivery that an on_error hook's exception ended: those
                    # older changes go first.
                    slot.outbox.append((change, False))
                    first = None
        if loop is None:
            self._deliver(slot, first)
            return
        try:
            loop.call_soon_threadsafe(self._flush)
        except RuntimeError:  # the loop closed without unbinding: fall back to synchronous
            with self._lock:
                self._loop = None
                self._loop_tid = None
            self._flush()

    def _store(self, slot: Slot, value: Any, writer: str | None,
               stale: bool = False) -> Change | None:
        old = slot.change
        deadband = slot.deadband
        now = self._clock()
        if old is not None and old.stale == stale and (
                _same(old.value, value) if deadband is None
                else _within(old.value, value, deadband)):
            if stale:
                return None  # still the same stale value: nothing to refresh or tell
            # Not a relevant change: the sensor is alive (freshness), nobody is woken.
            slot.change = Change(slot.key, old.value, time.time(), now, writer)
            return None
        change = slot.change = Change(slot.key, value, time.time(), now, writer, stale)
        taps = self._taps
        if taps:  # inline, not _tapped(): a recorder taps every set, so each call counts
            for tap in taps:
                try:
                    tap(change)
                except Exception:
                    self._tap_failed(tap, change)
        return change

    # -- taps (recorders) ------------------------------------------------------------------

    def tap(self, callback: ChangeCallback, *,
            on_wake: Callable[[], None] | None = None) -> Callable[[], None]:
        """Call ``callback(change)`` for every change *stored* -- each write that changed
        the entry and each entry that went stale -- in the thread that made it, before any
        subscriber hears of it and without coalescing. Returns a function that removes it.

        For recorders (:mod:`beehave.recording`), not for logic: it runs inside ``set`` (a
        HAL's or logic's write waits for it), so it must only hand the change on (append
        to a queue). One that raises is logged and removed; it never breaks the write.

        ``on_wake()``, when given, tells a recorder *when* the loop's logics look at the
        blackboard, so that a replay can hand a logic together what it saw together
        (:mod:`beehave.recording`): it runs in the loop's thread just before a watcher
        wakes the task waiting on it, and when a task creates a watcher -- that task's
        next step reads what was stored until then. The same rules as for the tap apply.
        """
        with self._lock:
            self._taps = (*self._taps, callback)
            if on_wake is not None:
                self._on_wake = (*self._on_wake, on_wake)

        def remove() -> None:
            with self._lock:
                self._taps = tuple(t for t in self._taps if t is not callback)
                self._on_wake = tuple(h for h in self._on_wake if h is not on_wake)

        return remove

    def _woke(self) -> None:
        """Run the taps' ``on_wake`` hooks (in the loop's thread)."""
        for hook in self._on_wake:
            try:
                hook()
            except Exception:
                log.exception("blackboard tap hook %r raised; it was removed", hook)
                with self._lock:
                    self._on_wake = tuple(h for h in self._on_wake if h is not hook)

    def _tapped(self, change: Change) -> None:
        for tap in self._taps:
            try:
                tap(change)
            except Exception:
                self._tap_failed(tap, change)

    def _tap_failed(self, tap: ChangeCallback, change: Change) -> None:
        log.exception("blackboard tap %r raised on %r; it was removed", tap, change.key)
        with self._lock:
            self._taps = tuple(t for t in self._taps if t is not tap)

    def _notify(self, slot: Slot, change: Change) -> None:
        slot.notified = change
        for sub in slot.subs:
            sub.deliver(change)
        if slot.max_age_s is not None and slot.timer is None and not change.stale:
            self._arm(slot)

    def _deliver(self, slot: Slot, first: Change | None = None) -> None:
        """Unbound delivery, outside the lock: the calling thread (which claimed
        ``slot.delivering``) delivers ``first``, then every change of ``slot`` queued
        meanwhile by other threads or by the callbacks themselves."""
        try:
            if first is not None:
                self._notify(slot, first)
            while True:
                with self._lock:
                    if not slot.outbox:
                        slot.delivering = False
                        return
                    change, only_if_current = slot.outbox.popleft()
                if only_if_current and slot.change is not change:
                    continue
                self._notify(slot, change)
        except BaseException:
            # An on_error hook that raised ends this delivery: the next writer of the key
            # goes on with what is left rather than finding delivery claimed forever.
            with self._lock:
                slot.delivering = False
            raise

    def _flush(self) -> None:
        with self._lock:
            pending = self._pending
            self._pending = {}
            self._flush_scheduled = False
        for slot in pending.values():
            change = slot.change
            if change is not None and change is not slot.notified:
                self._notify(slot, change)

    def _slot(self, key: str) -> Slot:
        with self._lock:
            slot = self._slots.get(key)
            if slot is None:
                slot = Slot(check_key(key))
                slot.subs = tuple(s for s in self._subs if _match(s.parts, slot.parts))
                self._slots[key] = slot
            return slot

    def _call_in_loop(self, fn: Callable[..., None], *args: Any) -> None:
        loop = self._loop
        if loop is None or threading.get_ident() == self._loop_tid:
            fn(*args)
            return
        try:
            loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:
            fn(*args)

    # -- freshness and relevance -----------------------------------------------------------

    def declare(self, key: str, *, max_age_s: float | None = None,
                deadband: float | None = None) -> None:
        """Give ``key`` a freshness limit and/or a numeric deadband (see the module doc).

        ``max_age_s``: the entry reads as stale when it was not written for that long.
        ``deadband``: numbers (or equal-length number sequences, by Euclidean distance)
        closer than this to the last published value refresh the entry without notifying.
        """
        for label, limit in (("max_age_s", max_age_s), ("deadband", deadband)):
            if limit is not None and not (isinstance(limit, Real) and limit >= 0):
                raise BlackboardError(f"{label} for blackboard key {key!r} must be a "
                                      f"number >= 0, got {limit!r}")
        slot = self._slots.get(key) or self._slot(key)
        slot.max_age_s = None if max_age_s is None else float(max_age_s)
        slot.deadband = None if deadband is None else float(deadband)
        if slot.max_age_s is not None and slot.change is not None and self._loop is not None:
            self._call_in_loop(self._arm_if_idle, slot)

    def _arm_if_idle(self, slot: Slot) -> None:
        if slot.timer is None and slot.change is not None and not slot.change.stale:
            self._arm(slot)

    def _arm(self, slot: Slot) -> None:
        loop = self._loop
        if loop is None or slot.change is None or slot.max_age_s is None:
            return
        remaining = slot.change.monotonic + slot.max_age_s - self._clock()
        slot.timer = loop.call_later(max(remaining, 0.0), self._check_age, slot)

    def _check_age(self, slot: Slot) -> None:
        slot.timer = None
        change = slot.change
        if change is None or change.stale or slot.max_age_s is None:
            return
        if self._clock() - change.monotonic < slot.max_age_s:
            self._arm(slot)
            return
        stale = slot.change = change.as_stale()
        if self._taps:
            self._tapped(stale)
        self._notify(slot, stale)

    def mark_stale(self, *, writer: str | None = None, pattern: str | None = None) -> list[str]:
        """Flag the entries written by ``writer`` and/or matching ``pattern`` as stale.

        Their watchers receive the ``stale=True`` change; the next write makes an entry
        fresh again. Returns the keys that were marked. With neither argument, marks all.
        """
        parts = None if pattern is None else _compile(pattern)
        marked: list[tuple[Slot, Change]] = []
        with self._lock:
            for slot in self._slots.values():
                change = slot.change
                if change is None or change.stale:
                    continue
                if writer is not None and change.writer != writer:
                    continue
                if parts is not None and not _match(parts, slot.parts):
                    continue
                stale = slot.change = change.as_stale()
                marked.append((slot, stale))
                if self._taps:
                    self._tapped(stale)
        if self._loop is None:
            for slot, stale in marked:
                with self._lock:
                    slot.outbox.append((stale, True))
                    if slot.delivering:
                        continue
                    slot.delivering = True
                self._deliver(slot)
        else:
            for slot, stale in marked:
                self._call_in_loop(self._notify_if_current, slot, stale)
        return [slot.key for slot, _ in marked]

    def _notify_if_current(self, slot: Slot, change: Change) -> None:
        if slot.change is change:
            self._notify(slot, change)

    # -- reading -------------------------------------------------------------------------

    def get(self, key: str, default: Any = None, *, fresh: bool = False) -> Any:
        """The value under ``key``, or ``default`` when it was never written.

        With ``fresh=True`` a stale entry also gives ``default``. Safe from any thread.
        """
        slot = self._slots.get(key)
        change = None if slot is None else slot.change
        if change is None:
            if slot is None and key not in self._slots:
                check_key(key)
            return default
        if fresh and self._is_stale(slot, change):  # type: ignore[arg-type]
            return default
        return change.value

    def entry(self, key: str) -> Change | None:
        """The latest change of ``key`` (value, stamp, writer, stale flag), or None."""
        slot = self._slots.get(key)
        if slot is None:
            check_key(key)
            return None
        change = slot.change
        if change is not None and not change.stale and self._is_stale(slot, change):
            return change.as_stale()
        return change

    def is_stale(self, key: str) -> bool:
        """True when ``key`` was never written, was marked stale, or is older than its
        ``max_age_s``."""
        entry = self.entry(key)
        return entry is None or entry.stale

    def _is_stale(self, slot: Slot, change: Change) -> bool:
        if change.stale:
            return True
        return slot.max_age_s is not None and self._clock() - change.monotonic > slot.max_age_s

    def keys(self, pattern: str = "**") -> list[str]:
        """The keys that hold a value and match ``pattern``, sorted."""
        parts = _compile(pattern)
        return sorted(k for k, s in list(self._slots.items())
                      if s.change is not None and _match(parts, s.parts))

    def __contains__(self, key: object) -> bool:
        slot = self._slots.get(key) if isinstance(key, str) else None
        return slot is not None and slot.change is not None

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def __len__(self) -> int:
        return sum(1 for s in list(self._slots.values()) if s.change is not None)

    def snapshot(self, pattern: str = "**") -> dict[str, dict[str, Any]]:
        """A JSON-serialisable view: ``{key: {value, stamp, stale, writer, age_s}}``.

        Declared keys that were never written appear with ``value`` None and ``stale`` True.
        """
        parts = _compile(pattern)
        out: dict[str, dict[str, Any]] = {}
        for key, slot in sorted(list(self._slots.items())):
            if not _match(parts, slot.parts):
                continue
            change = self.entry(key)
            if change is not None:
                out[key] = change.as_dict()
            elif slot.max_age_s is not None:
                out[key] = {"value": None, "stamp": None, "stale": True, "writer": None,
                            "age_s": None}
        return out

    # -- subscribing ---------------------------------------------------------------------

    def subscribe(self, pattern: str, callback: ChangeCallback) -> Subscription:
        """Call ``callback(change)`` for every change of a key matching ``pattern``.

        Bound to a loop, callbacks run in the loop's thread; unbound, in the writer's
        thread. Keep them short. Returns the :class:`Subscription` (close it to stop).
        """
        return self._add(Subscription(self, pattern, callback))

    def watch(self, pattern: str, *, initial: bool = True) -> Watcher:
        """An async iterator over the changes of keys matching ``pattern``.

        With ``initial`` (the default) it first yields the current entries, so a logic sees
        the state it starts in, not only what changes later. Call it in the blackboard's
        loop (an unbound blackboard binds itself to the running loop).
        """
        if self._loop is None:
            try:
                self.bind(asyncio.get_running_loop())
            except RuntimeError:
                raise BlackboardError(
                    f"watch({pattern!r}) needs a running asyncio loop; use subscribe() for a "
                    "synchronous callback") from None
        assert self._loop is not None
        if self._on_wake and threading.get_ident() == self._loop_tid:
            self._woke()  # the calling task starts looking at the board
        watcher = Watcher(self, pattern, self._loop)
        with self._lock:
            self._add(watcher)
            if initial:
                for slot in self._slots.values():
                    if slot.change is not None and _match(watcher.parts, slot.parts):
                        watcher._pending[slot.key] = self.entry(slot.key) or slot.change
        return watcher

    def _add(self, sub: Subscription) -> Subscription:
        with self._lock:
            self._subs.append(sub)
            for slot in self._slots.values():
                if _match(sub.parts, slot.parts):
                    slot.subs = (*slot.subs, sub)
        return sub

    def _unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            try:
                self._subs.remove(sub)
            except ValueError:
                return
            for slot in self._slots.values():
                if sub in slot.subs:
                    slot.subs = tuple(s for s in slot.subs if s is not sub)

    @property
    def subscriptions(self) -> tuple[Subscription, ...]:
        """The open subscriptions and watchers."""
        return tuple(self._subs)

    def _report(self, sub: Subscription, exc: BaseException) -> None:
        log.error("blackboard subscriber for %r raised; it was closed", sub.pattern,
                  exc_info=exc)
        if self.on_error is not None:
            self.on_error(sub, exc)

    def close(self) -> None:
        """Close every subscription and watcher (watchers' iterations end)."""
        for sub in list(self._subs):
            sub.close()

    def client(self, writer: str) -> BlackboardClient:
        """A view that writes as ``writer`` and owns the subscriptions made through it."""
        return BlackboardClient(self, writer)


class BlackboardClient:
    """The blackboard as one writer sees it: a logic's or HAL's ``self.blackboard``.

    Writes are tagged with ``writer``; subscriptions and watchers made through it are closed
    by :meth:`close` (the framework calls it when the logic or HAL ends).
    """

    def __init__(self, board: Blackboard, writer: str) -> None:
        self.board = board
        self.writer = writer
        self._owned: list[Subscription] = []

    def set(self, key: str, value: Any) -> None:
        """Write ``value`` under ``key`` as this client's writer."""
        self.board.set(key, value, writer=self.writer)

    def get(self, key: str, default: Any = None, *, fresh: bool = False) -> Any:
        return self.board.get(key, default, fresh=fresh)

    def entry(self, key: str) -> Change | None:
        return self.board.entry(key)

    def is_stale(self, key: str) -> bool:
        return self.board.is_stale(key)

    def declare(self, key: str, *, max_age_s: float | None = None,
                deadband: float | None = None) -> None:
        self.board.declare(key, max_age_s=max_age_s, deadband=deadband)

    def keys(self, pattern: str = "**") -> list[str]:
        return self.board.keys(pattern)

    def snapshot(self, pattern: str = "**") -> dict[str, dict[str, Any]]:
        return self.board.snapshot(pattern)

    def subscribe(self, pattern: str, callback: ChangeCallback) -> Subscription:
        sub = self.board.subscribe(pattern, callback)
        self._owned.append(sub)
        return sub

    def watch(self, pattern: str, *, initial: bool = True) -> Watcher:
        watcher = self.board.watch(pattern, initial=initial)
        self._owned.append(watcher)
        return watcher

    async def wait_for(self, key: str, predicate: Callable[[Any], bool] = bool) -> Any:
        """Wait until ``predicate(value)`` holds for ``key`` (checked on the current value
        first) and return that value."""
        async with self.watch(key) as changes:
            async for change in changes:
                if not change.stale and predicate(change.value):
                    return change.value
        raise BlackboardError(f"stopped watching blackboard key {key!r}")

    def close(self) -> None:
        for sub in self._owned:
            sub.close()
        self._owned.clear()

    def __repr__(self) -> str:
        return f"BlackboardClient(writer={self.writer!r})"



class BlackboardView:
    """A read-only view of a :class:`Blackboard` (what the high level sees of the low
    level's blackboard: a mirror fed over ROS 2). Writing raises, so that a value written
    to the mirror is never silently lost."""

    def __init__(self, board: Blackboard, *, why: str = "it is read-only") -> None:
        self._board = board
        self._why = why

    def get(self, key: str, default: Any = None, *, fresh: bool = False) -> Any:
        return self._board.get(key, default, fresh=fresh)

    def entry(self, key: str) -> Change | None:
        return self._board.entry(key)

    def is_stale(self, key: str) -> bool:
        return self._board.is_stale(key)

    def keys(self, pattern: str = "**") -> list[str]:
        return self._board.keys(pattern)

    def snapshot(self, pattern: str = "**") -> dict[str, dict[str, Any]]:
        return self._board.snapshot(pattern)

    def subscribe(self, pattern: str, callback: ChangeCallback) -> Subscription:
        return self._board.subscribe(pattern, callback)

    def __contains__(self, key: object) -> bool:
        return key in self._board

    def set(self, key: str, value: Any, *, writer: str | None = None) -> None:
        raise BlackboardError(f"cannot set {key!r}: {self._why}")
