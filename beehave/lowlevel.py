"""The low-level behaviour manager: one asyncio loop of logics, a blackboard and HALs.

::

    ll = LowLevelBehaviorManager(default="led")
    ll.register("led", LedLogic, threshold=20)
    ll.register("display", DisplayLogic)
    ll.hals.register(DebugHAL)
    with ll:                       # the loop runs in its own thread
        ll.switch("display")       # from any thread: returns once "display" runs
        ll.blackboard.get("battery/percentage")

or, inside an asyncio program, ``await ll.run()`` (until :meth:`shutdown` or cancellation)
and ``await ll.switch_async("display")`` from coroutines in that loop.

Exactly one top-level logic runs at a time. ``switch`` cancels it and its sub-logics, waits
until they have ended (at most ``stop_timeout_s``; a logic that ignores its cancellation
is reported STUCK), then starts the new one. The ``default`` logic runs when nothing else
was selected and whenever a top-level logic ends on its own; a crash is kept on
``last_failed`` and reported as a FALLBACK event.

Never block the loop: a logic or HAL that calls ``time.sleep`` or blocking I/O holds every
other logic. A watchdog thread notices (warning and LOOP_BLOCKED event naming the culprit
after ``loop_lag_warn_s``); calls from other threads fail with
:class:`~beehave.errors.LoopBlocked` instead of waiting for ever once the loop has been
blocked for ``stop_timeout_s``, and ``shutdown()`` then forces the HALs' safe states from
its own thread and raises it.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import enum
import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Coroutine
from typing import Any, Self, TypeVar

from beehave.blackboard import Blackboard, Subscription, Watcher
from beehave.clock import VirtualClock, WallClock
from beehave.errors import (
    AlreadyStarted,
    BeehaveError,
    InvalidParameters,
    LoopBlocked,
    ManagerShutdown,
    NotASubclass,
    UnknownLogic,
)
from beehave.events import Event, EventBus, EventCallback, EventKind
from beehave.hal import HALManager, check_duration_s, check_params, wait_ignoring_cancel
from beehave.logic import Logic, Runtime, stop_logics
from beehave.status import Status
from beehave.substitutes import Substitute
from beehave.watchdog import LoopWatchdog

log = logging.getLogger(__name__)

__all__ = ["LowLevelBehaviorManager", "new_event_loop"]

T = TypeVar("T")


def new_event_loop() -> asyncio.AbstractEventLoop:
    """A new event loop: uvloop's when it is installed (the ``fast`` extra), else asyncio's."""
    try:
        import uvloop
    except ImportError:
        return asyncio.new_event_loop()
    return uvloop.new_event_loop()


class _Phase(enum.Enum):
    NEW = "new"
    RUNNING = "running"
    STOPPING = "stopping"
    STOPPED = "stopped"


class _HandOver:
    """An owner of HAL references between two top-level logics (see ``hal_handover_s``).

    A fresh one per change of the top-level logic, released as a whole when its own timer
    fires: a reference handed over by a later change never rides on an earlier, shorter
    grace period."""

    def __init__(self) -> None:
        self.timer: asyncio.TimerHandle | None = None

    def __repr__(self) -> str:
        return f"<hal handover {id(self):#x}>"


class LowLevelBehaviorManager:
    """Runs the low level: the switchable top-level logic, the blackboard and the HALs.

    ``default``: the logic (registered name) that runs when none is selected.
    ``stop_timeout_s``: how long a switch waits for a cancelled logic (or an unload for a
    HAL) before reporting it STUCK and going on; also how long the loop may stay blocked
    before calls from other threads and ``shutdown()`` give up with
    :class:`~beehave.errors.LoopBlocked`. ``hal_backoff_initial_s`` / ``hal_backoff_max_s``:
    restart delays of a crashed HAL. ``loop_lag_warn_s``: a callback that holds the loop
    longer than this is reported (warning + LOOP_BLOCKED event naming it).
    ``hal_handover_s``: after the top-level logic changed, how long the HALs the old one
    used stay loaded for the new one to take over; those it did not ask for by then are
    unloaded (0: unload at once). ``use_uvloop``: run the context manager's loop on uvloop
    if installed. ``clock``: a :class:`~beehave.clock.VirtualClock` makes the context
    manager's loop follow virtual time (``asyncio.sleep``, timeouts, HAL periods, the
    blackboard's ages) — the test kit's; the default is wall time. Every duration must be
    finite and positive (:class:`~beehave.errors.ConfigError`).
    """

    def __init__(self, *, default: str | None = None, blackboard: Blackboard | None = None,
                 stop_timeout_s: float = 2.0, hal_backoff_initial_s: float = 0.1,
                 hal_backoff_max_s: float = 5.0, loop_lag_warn_s: float = 0.2,
                 hal_handover_s: float = 0.5, use_uvloop: bool = True,
                 clock: WallClock | None = None) -> None:
        # Checked first: nothing is built from a duration that cannot be waited for.
        stop_timeout_s = check_duration_s("stop_timeout_s", stop_timeout_s)
        hal_backoff_initial_s = check_duration_s("hal_backoff_initial_s", hal_backoff_initial_s)
        hal_backoff_max_s = check_duration_s("hal_backoff_max_s", hal_backoff_max_s)
        self.loop_lag_warn_s = check_duration_s("loop_lag_warn_s", loop_lag_warn_s)
        self.hal_handover_s = check_duration_s("hal_handover_s", hal_handover_s, allow_zero=True)
        self.events = EventBus(log)
        #: What the loop's time follows (its ``time()``): wall time, or a virtual clock.
        self.clock = clock if clock is not None else WallClock()
        if blackboard is None:
            blackboard = (Blackboard(clock=self.clock.now) if isinstance(self.clock, VirtualClock)
                          else Blackboard())
        self.blackboard = blackboard
        if self.blackboard.on_error is None:
            self.blackboard.on_error = self._subscriber_failed
        self.hals = HALManager(self.blackboard, events=self.events,
                               backoff_initial_s=hal_backoff_initial_s,
                               backoff_max_s=hal_backoff_max_s,
                               stop_timeout_s=stop_timeout_s)
        self.default = default
        self.stop_timeout_s = stop_timeout_s
        self.use_uvloop = use_uvloop
        self.last_failed: Logic | None = None
        """The last top-level logic that crashed (its ``.error`` says how)."""
        self.history: deque[Logic] = deque(maxlen=32)
        """The top-level logics that ended, oldest first (the last 32)."""
        self._runtime = Runtime(self.blackboard, self.hals, self.events, stop_timeout_s)
        # The owner of the HAL references that an ended top-level logic hands over to its
        # successor (see Runtime.handover); each is released hal_handover_s after the last
        # reference was handed to it. _handovers: those that may still hold references.
        self._handover = _HandOver()
        self._handovers: set[_HandOver] = set()
        self._registry: dict[str, tuple[type[Logic], dict[str, Any]]] = {}
        self._top: Logic | None = None
        self._selected: tuple[str, dict[str, Any]] | None = None
        self._phase = _Phase.NEW
        self._phase_lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_tid: int | None = None
        self._stop: asyncio.Event | None = None
        self._switch_lock: asyncio.Lock | None = None
        self._inflight: set[asyncio.Task[Any]] = set()
        self._started = threading.Event()
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None
        self._thread_error: BaseException | None = None
        self._watchdog: LoopWatchdog | None = None
        self._abandoned: LoopBlocked | None = None
        self._abandoning: threading.Event | None = None  # set once the escalation is done
        self._stop_waiters: set[concurrent.futures.Future[None]] = set()

    # -- registry ------------------------------------------------------------------------

    def register(self, name: str, logic_cls: type[Logic], **params: Any) -> None:
        """Make ``logic_cls`` selectable as top-level logic ``name``; ``params`` go to its
        constructor (checked now: :class:`~beehave.errors.InvalidParameters`)."""
        if not (isinstance(logic_cls, type) and issubclass(logic_cls, Logic)):
            raise NotASubclass(f"register({name!r}, …) needs a Logic subclass, got {logic_cls!r}")
        check_params(logic_cls, name, params)
        self._registry[name] = (logic_cls, dict(params))

    def substitute(self, pattern: str, substitute: Substitute) -> Callable[[], None]:
        """From now on, run ``substitute`` instead of every logic (top-level or sub-logic)
        whose path, name or class name matches ``pattern`` (``fnmatch``). For tests: see
        :class:`beehave.testing.Scripted`; a HAL is substituted by registering another
        class under its name (``ll.hals.register(ScriptedHAL, name="lift")``). Returns a
        function that removes the rule."""
        return self._runtime.substitutes.add(pattern, substitute)

    @property
    def registered(self) -> list[str]:
        return sorted(self._registry)

    def _create(self, name: str, params: dict[str, Any]) -> Logic:
        """Resolve and construct before anything is stopped, so a bad request changes
        nothing."""
        try:
            cls, base = self._registry[name]
        except KeyError:
            err = UnknownLogic(name, self._registry)
            self.events.emit(Event(EventKind.SWITCH_REJECTED, name, error=err))
            raise err from None
        merged = {**base, **params}
        try:
            check_params(cls, name, merged)
            logic = cls(**merged)
        except InvalidParameters as err:
            self.events.emit(Event(EventKind.SWITCH_REJECTED, name, error=err))
            raise
        except Exception as exc:
            self.events.emit(Event(EventKind.SWITCH_REJECTED, name, error=exc))
            raise InvalidParameters(f"logic {name!r}: {cls.__qualname__}(**{merged!r}) "
                                    f"raised {exc!r}") from exc
        logic.name = name
        return logic

    # -- state ---------------------------------------------------------------------------

    @property
    def current(self) -> str | None:
        """The name of the running top-level logic (None when none runs)."""
        top = self._top
        return top.name if top is not None and top.status is Status.RUNNING else None

    @property
    def logic(self) -> Logic | None:
        """The running top-level logic's handle."""
        return self._top

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        """The loop the low level runs in (None before start and after shutdown)."""
        return self._loop

    @property
    def running(self) -> bool:
        return self._phase is _Phase.RUNNING

    def subscribe(self, callback: EventCallback) -> Callable[[], None]:
        """Call ``callback(event)`` for every lifecycle event (logics, switches, HALs);
        returns a function that unsubscribes. Callbacks run in the loop's thread, except
        LOOP_BLOCKED: the watchdog's notifier thread delivers it (the loop cannot), and
        calling back into the manager from there is bounded like from any other thread."""
        return self.events.subscribe(callback)

    def snapshot(self) -> dict[str, Any]:
        """A JSON-serialisable view: running logic tree, HALs, blackboard, last failure."""
        if self._in_foreign_thread():
            try:
                return self.call(self._snapshot_async())
            except (ManagerShutdown, LoopBlocked):
                pass  # read it from here: introspection matters most when the loop is stuck
        return self._snapshot()

    async def _snapshot_async(self) -> dict[str, Any]:
        return self._snapshot()

    def _snapshot(self) -> dict[str, Any]:
        top = self._top
        failed = self.last_failed
        return {
            "phase": self._phase.value,
            "current": self.current,
            "default": self.default,
            "registered": self.registered,
            "logic": None if top is None else top.snapshot(),
            "stuck": sorted(lg.path for lg in self._runtime.stuck),
            "last_failed": None if failed is None else {
                "name": failed.name, "error": repr(failed.error),
                "ended_at": failed.ended_at},
            "hals": self.hals.snapshot(),
            "blackboard": self.blackboard.snapshot(),
            "loop": None if self._loop is None else type(self._loop).__module__,
            "loop_blocked": self._blocked_info(),
        }

    def _blocked_info(self) -> dict[str, Any] | None:
        watchdog = self._watchdog
        blocked = self._abandoned or (watchdog.blocked() if watchdog is not None else None)
        if blocked is None:
            return None
        return {"culprit": blocked.culprit, "where": blocked.where,
                "blocked_s": round(blocked.blocked_s, 3)}

    # -- switching -----------------------------------------------------------------------

    def switch(self, name: str, **params: Any) -> Logic | None:
        """Make ``name`` the top-level logic; callable from any thread but the loop's.

        From another thread it blocks until the old logic (and its sub-logics) has ended and
        the new one runs, and returns the new logic. Before the manager runs it only
        records the choice (returns None). Inside the loop use :meth:`switch_async` — a
        blocking call there would deadlock, so it raises. Unknown names raise
        :class:`~beehave.errors.UnknownLogic` listing the registered ones; nothing is
        stopped then. Switching to the running logic's name restarts it.
        """
        with self._phase_lock:
            if self._phase is _Phase.NEW:
                self._create(name, params)  # validate now; the object itself is discarded
                self._selected = (name, dict(params))
                return None
            if self._phase is not _Phase.RUNNING:
                raise ManagerShutdown(f"low-level manager is {self._phase.value}; cannot "
                                      f"switch to {name!r}")
        if not self._in_foreign_thread():
            raise BeehaveError(f"switch({name!r}) was called inside the low level's loop, "
                               f"where blocking would deadlock; use `await "
                               f"ll.switch_async({name!r})`")
        return self.call(self.switch_async(name, **params))

    async def switch_async(self, name: str, **params: Any) -> Logic:
        """:meth:`switch` for coroutines running in the low level's loop."""
        if self._phase is not _Phase.RUNNING or self._switch_lock is None:
            raise ManagerShutdown(f"low-level manager is {self._phase.value}; cannot switch "
                                  f"to {name!r}")
        logic = self._create(name, params)
        began = time.monotonic()
        self._announce(EventKind.SWITCH_REQUESTED, name,
                       {"from": self.current, "fallback": False})
        cancelled = False
        async with self._switch_lock:
            old_name = self.current  # under the lock: a concurrent switch may have run
            old = self._top
            self._top = None
            self._new_handover()
            if old is not None:
                try:
                    await stop_logics([old], self._runtime)
                except asyncio.CancelledError:
                    # The old logic is gone either way (stop_logics waits out its bound):
                    # finish the switch, so that a caller who stopped waiting does not
                    # leave the robot with no logic at all; then tell it.
                    cancelled = True
            if self._phase is not _Phase.RUNNING:
                raise ManagerShutdown(f"low-level manager shut down while switching to "
                                      f"{name!r}")
            self._start_top(logic)
        self._announce(EventKind.SWITCH_COMPLETED, name,
                       {"from": old_name, "fallback": False,
                        "duration_s": round(time.monotonic() - began, 6)})
        if cancelled:
            raise asyncio.CancelledError
        return logic

    def _announce(self, kind: EventKind, name: str, detail: dict[str, Any]) -> None:
        # Every change of the running logic -- first start, switch, fallback -- goes out as
        # SWITCH_REQUESTED/SWITCH_COMPLETED, so whoever follows the events (the ROS
        # ``logic`` parameter) always agrees with ``current``.
        status = Status.RUNNING.name if kind is EventKind.SWITCH_COMPLETED else None
        self.events.emit(Event(kind, name, status, detail=detail))

    def _start_default_or_selected(self, name: str, params: dict[str, Any], *,
                                   previous: str | None, fallback: bool) -> None:
        detail = {"from": previous, "fallback": fallback}
        self._announce(EventKind.SWITCH_REQUESTED, name, detail)
        began = time.monotonic()
        self._start_top(self._create(name, params))
        self._announce(EventKind.SWITCH_COMPLETED, name,
                       {**detail, "duration_s": round(time.monotonic() - began, 6)})

    def _start_top(self, logic: Logic) -> None:
        logic._start(self._runtime, parent=None, name=None)
        self._top = logic
        task = logic.task
        assert task is not None
        task.add_done_callback(functools.partial(self._top_done, logic))

    def _top_done(self, logic: Logic, _task: asyncio.Task[None]) -> None:
        self._top_ended(logic)

    # -- HALs across a change of the top-level logic -------------------------------------

    def _new_handover(self) -> None:
        """A fresh owner for the references the ending top-level logic hands over."""
        self._handover = _HandOver()
        if self._runtime.handover is not None:  # None once tearing down
            self._runtime.handover = self._handover

    def _handed_over(self, owner: object) -> None:
        """A logic handed a HAL reference to ``owner`` (Runtime.on_handover): (re)start
        the wait after which ``owner`` lets go. Armed per hand-over, so a sub-logic that
        ends late still gets the whole grace period and is released after it."""
        loop = self._loop
        if not isinstance(owner, _HandOver) or loop is None:
            return
        self._handovers.add(owner)
        if owner.timer is not None:
            owner.timer.cancel()
        owner.timer = loop.call_later(self.hal_handover_s, self._handover_due, owner)

    def _handover_due(self, owner: _HandOver) -> None:
        owner.timer = None
        if owner is self._handover:
            self._new_handover()  # later hand-overs get a grace period of their own
        task = asyncio.get_running_loop().create_task(self._release_handover(owner),
                                                      name="beehave-lowlevel-hal-handover")
        self._inflight.add(task)
        task.add_done_callback(self._inflight.discard)

    async def _release_handover(self, owner: _HandOver) -> None:
        """Release what ``owner`` holds -- only that: another change may have handed over
        references a moment ago, and they have their own owner and timer."""
        self._handovers.discard(owner)
        for name in list(self.hals.loaded):
            if self.hals.holds(name, owner):
                await self.hals.release(name, owner=owner, wait=False)

    def _top_ended(self, logic: Logic) -> None:
        self.history.append(logic)
        if logic.status is Status.FAILED:
            self.last_failed = logic
        if logic is not self._top or self._phase is not _Phase.RUNNING:
            return  # switched away or shutting down: the switch started the next one
        self._top = None
        nxt = self.default if self.default is not None and logic.name != self.default else None
        self.events.emit(Event(EventKind.FALLBACK, logic.path, logic.status.name, logic.error,
                               {"to": nxt, "next": nxt}))
        if nxt is None:
            return
        try:
            self._start_default_or_selected(nxt, {}, previous=logic.name, fallback=True)
        except BeehaveError as err:  # reported by _create as SWITCH_REJECTED
            log.error("default logic %r cannot start: %r", nxt, err)

    # -- running -------------------------------------------------------------------------

    async def run(self) -> None:
        """Run the low level in the current loop until :meth:`shutdown` or cancellation;
        then stop the logics, unload the HALs (safe states) and close the watchers."""
        loop = asyncio.get_running_loop()
        with self._phase_lock:
            if self._phase is not _Phase.NEW:
                raise AlreadyStarted(f"low-level manager is {self._phase.value}; create a "
                                     "new one to run again")
            self._loop = loop
            self._loop_tid = threading.get_ident()
            self._stop = asyncio.Event()
            self._switch_lock = asyncio.Lock()
            self._runtime.handover = self._handover
            self._runtime.on_handover = self._handed_over
            self.blackboard.bind(loop)
            self._phase = _Phase.RUNNING
            selected = self._selected
            self._watchdog = LoopWatchdog(loop, threading.get_ident(), self.events,
                                          warn_s=self.loop_lag_warn_s,
                                          block_s=self.stop_timeout_s)
            self._watchdog.start()
        try:
            name, params = selected if selected is not None else (self.default, {})
            if name is not None:
                self._start_default_or_selected(name, params, previous=None, fallback=False)
            self._started.set()
            await self._stop.wait()
        finally:
            with self._phase_lock:
                if self._phase is _Phase.RUNNING:  # not after an abandoning shutdown
                    self._phase = _Phase.STOPPING
            teardown = loop.create_task(self._teardown(), name="beehave-lowlevel-teardown")
            try:
                await wait_ignoring_cancel(teardown)
            finally:
                watchdog, self._watchdog = self._watchdog, None
                if watchdog is not None:
                    watchdog.stop()
                with self._phase_lock:
                    self._phase = _Phase.STOPPED
                    self._loop = None
                    self._loop_tid = None
                self._started.set()
                self._mark_stopped()
            teardown.result()

    def _mark_stopped(self) -> None:
        with self._phase_lock:
            self._stopped.set()
            waiters, self._stop_waiters = self._stop_waiters, set()
        for waiter in waiters:
            try:
                waiter.set_result(None)
            except concurrent.futures.InvalidStateError:
                pass

    async def _teardown(self) -> None:
        me = asyncio.current_task()
        self._runtime.handover = None  # nobody comes next: logics release their HALs now
        top = self._top
        self._top = None
        if top is not None:
            await stop_logics([top], self._runtime)
        inflight = {t for t in self._inflight if t is not me and not t.done()}
        if inflight:
            await asyncio.wait(inflight, timeout=self.stop_timeout_s)
        if self._runtime.stuck:  # one more chance for logics that ignored cancellation
            await stop_logics(list(self._runtime.stuck), self._runtime)
        for owner in [*self._handovers, self._handover]:
            if owner.timer is not None:
                owner.timer.cancel()
                owner.timer = None
            await self._release_handover(owner)
        await self.hals.close()
        for sub in self.blackboard.subscriptions:
            if isinstance(sub, Watcher) and sub.loop is asyncio.get_running_loop():
                sub.close()
        self.blackboard.unbind()

    def shutdown(self) -> None:
        """Stop everything: the top-level logic and its sub-logics, then the HALs.

        From another thread it waits until the low level has stopped (and its thread, when
        started as a context manager, has ended); inside the loop it only asks. Idempotent.

        Bounded even when a logic or HAL blocks the loop: once the loop has not answered
        for ``stop_timeout_s``, the safe states of the loaded HALs are forced from this
        thread (each at most once, bounded by ``stop_timeout_s`` together), the manager
        is left STOPPED, and :class:`~beehave.errors.LoopBlocked` is raised naming the
        culprit. The loop's thread is then abandoned to the code that blocks it; should it
        ever return, the teardown finishes there (safe states are not repeated).
        """
        # On a virtual clock, time runs by itself meanwhile: a HAL's safe state or a
        # logic's cleanup that sleeps must end although the test moves time by hand.
        with self.clock.free_running():
            self._shutdown()

    def _shutdown(self) -> None:
        with self._phase_lock:
            if self._phase is _Phase.NEW:
                self._phase = _Phase.STOPPED
                self._stopped.set()
                self._started.set()
                return
            if self._abandoned is not None:
                return  # already given up on, and said so
            loop, stop = self._loop, self._stop
            waiter: concurrent.futures.Future[None] = concurrent.futures.Future()
            if self._stopped.is_set():
                waiter.set_result(None)
            else:
                self._stop_waiters.add(waiter)
        if loop is not None and stop is not None:
            if self._in_foreign_thread():
                try:
                    loop.call_soon_threadsafe(stop.set)
                except RuntimeError:  # loop already closed
                    pass
            else:
                stop.set()
                return
        watchdog = self._watchdog
        unwatch = watchdog.watch(waiter) if watchdog is not None else None
        try:
            waiter.result()  # resolved when stopped, failed by the watchdog when blocked
        except LoopBlocked as blocked:
            raise self._abandon(blocked) from None
        except ManagerShutdown:
            # The watchdog stopped under us: the loop's teardown ended (it marks us
            # stopped next) or another shutdown gave up on the loop (say so here too).
            abandoning = self._abandoning
            if abandoning is not None:
                abandoning.wait()
                if self._abandoned is not None:
                    raise self._abandoned from None
            self._stopped.wait(self.stop_timeout_s)
        finally:
            if unwatch is not None:
                unwatch()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    def _abandon(self, blocked: LoopBlocked) -> LoopBlocked:
        """Shutdown's escalation when the loop does not run: force the HALs' safe states
        from this thread, leave the manager in a defined state, say what happened."""
        with self._phase_lock:
            abandoning = self._abandoning
            if abandoning is None:  # the first to give up escalates; the others wait
                self._abandoning = threading.Event()
                self._phase = _Phase.STOPPED
        if abandoning is not None:
            abandoning.wait()  # bounded: the escalation joins its helper for stop_timeout_s
            assert self._abandoned is not None
            return self._abandoned
        try:
            return self._escalate(blocked)
        finally:
            assert self._abandoning is not None
            self._abandoning.set()

    def _escalate(self, blocked: LoopBlocked) -> LoopBlocked:
        watchdog = self._watchdog
        if watchdog is not None:
            watchdog.stop()
        forced: list[str] = []
        # In a helper thread, so that a safe_state that blocks too cannot hang us.
        helper = threading.Thread(target=lambda: forced.extend(self.hals.force_safe_states()),
                                  name="beehave-lowlevel-safe-states", daemon=True)
        helper.start()
        helper.join(self.stop_timeout_s)
        hals = ", ".join(repr(n) for n in forced) or "none loaded"
        late = " (still running after stop_timeout_s: abandoned too)" if helper.is_alive() \
            else ""
        error = LoopBlocked(
            f"low-level shutdown gave up: {blocked}. Safe states forced from the shutdown "
            f"thread for HALs: {hals}{late}. The loop's thread stays blocked in "
            f"{blocked.culprit} and is abandoned.",
            culprit=blocked.culprit, where=blocked.where, blocked_s=blocked.blocked_s)
        self._abandoned = error
        log.error("%s", error)
        return error

    def call(self, coro: Coroutine[Any, Any, T], *, timeout_s: float | None = None) -> T:
        """Run ``coro`` in the low level's loop from another thread and return its result
        (a tracked task: shutdown waits for it).

        Never waits for a loop that does not run: once the loop has been blocked for
        ``stop_timeout_s`` the call fails with :class:`~beehave.errors.LoopBlocked`
        (naming the culprit) and the request is cancelled -- withdrawn if the loop had not
        begun it; if it had, it is cancelled when the loop runs again, and a switch that
        was already stopping the old logic completes (read ``current`` to know).
        ``timeout_s`` bounds the coroutine itself (``TimeoutError``; it is cancelled too).
        """
        if timeout_s is not None:
            try:
                timeout_s = check_duration_s("timeout_s", timeout_s)
            except BeehaveError:
                coro.close()
                raise
        loop = self._loop
        if loop is None or self._phase is not _Phase.RUNNING:
            coro.close()
            raise ManagerShutdown(f"low-level manager is {self._phase.value}")
        if not self._in_foreign_thread():
            coro.close()
            raise BeehaveError("call() blocks; inside the loop, await the coroutine instead")
        watchdog = self._watchdog
        withdrawn = threading.Event()
        request: concurrent.futures.Future[T] = asyncio.run_coroutine_threadsafe(
            self._tracked(coro, withdrawn), loop)
        # The caller waits on its own future, which either the request or the watchdog
        # completes -- whichever comes first.
        waiter: concurrent.futures.Future[T] = concurrent.futures.Future()
        request.add_done_callback(functools.partial(_copy_outcome, waiter))
        unwatch = watchdog.watch(waiter) if watchdog is not None else None
        try:
            return waiter.result(timeout_s)
        except (LoopBlocked, TimeoutError):
            withdrawn.set()  # a request the loop has not begun yet never begins
            request.cancel()
            raise
        finally:
            if unwatch is not None:
                unwatch()

    async def _tracked(self, coro: Coroutine[Any, Any, T],
                       withdrawn: threading.Event | None = None) -> T:
        if withdrawn is not None and withdrawn.is_set():
            coro.close()
            raise asyncio.CancelledError
        task = asyncio.current_task()
        assert task is not None
        task.set_name(f"call:{getattr(coro, '__qualname__', 'coroutine')}")
        self._inflight.add(task)
        try:
            return await coro
        finally:
            self._inflight.discard(task)

    def _in_foreign_thread(self) -> bool:
        return self._loop_tid is not None and threading.get_ident() != self._loop_tid

    def _subscriber_failed(self, sub: Subscription, exc: BaseException) -> None:
        self.events.emit(Event(EventKind.ENDED, f"blackboard:{sub.pattern}",
                               Status.FAILED.name, exc))

    # -- context manager: the loop in its own thread ---------------------------------------

    def __enter__(self) -> Self:
        if self._thread is not None or self._phase is not _Phase.NEW:
            raise AlreadyStarted(f"low-level manager is {self._phase.value}")
        self._thread = threading.Thread(target=self._thread_main, name="beehave-lowlevel",
                                        daemon=True)
        self._thread.start()
        self._started.wait()
        if self._stopped.is_set():  # run() failed while starting
            self._thread.join()
            raise self._thread_error or ManagerShutdown("low-level manager stopped at start")
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def _thread_main(self) -> None:  # the loop's thread
        if isinstance(self.clock, VirtualClock):
            loop = self.clock.new_event_loop()
        else:
            loop = new_event_loop() if self.use_uvloop else asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self.run())
        except BaseException as exc:  # raised again by __enter__ when it happens at start
            self._thread_error = exc
            log.error("low-level manager stopped with an error", exc_info=exc)
        finally:
            try:
                loop.run_until_complete(loop.shutdown_asyncgens())
            finally:
                asyncio.set_event_loop(None)
                loop.close()
                self._started.set()
                self._mark_stopped()


def _copy_outcome(waiter: concurrent.futures.Future[T],
                  request: concurrent.futures.Future[T]) -> None:
    try:
        if request.cancelled():
            waiter.cancel()
        elif (error := request.exception()) is not None:
            waiter.set_exception(error)
        else:
            waiter.set_result(request.result())
    except concurrent.futures.InvalidStateError:
        pass  # the watchdog failed the waiter first
