"""HighLevelBehaviorManager: runs exactly one top-level behaviour and switches at runtime."""

from __future__ import annotations

import enum
import functools
import inspect
import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from beehave.behavior import Behavior, Idle
from beehave.blackboard import Blackboard, BlackboardView
from beehave.clock import PausableClock, VirtualClock, WallClock
from beehave.errors import (
    BeehaveError,
    ConfigError,
    ConstructorFailed,
    InvalidParameters,
    ManagerShutdown,
    NotASubclass,
    SwitchSuperseded,
    UnknownBehavior,
)
from beehave.events import Event, EventBus, EventCallback, EventKind
from beehave.hal import check_duration_s
from beehave.lifecycle import Running
from beehave.locks import TypeLocks
from beehave.runnable import Runnable, _Flag, _Pause, current
from beehave.status import Status
from beehave.substitutes import Substitute, Substitutions
from beehave.threads import WorkerPool

if TYPE_CHECKING:
    from beehave.action import Action

log = logging.getLogger(__name__)

IDLE = "idle"

_tls = threading.local()
"""``holding``: the manager whose processor role this thread took in ``_enqueue`` and has
not yet begun to execute (its events are being emitted: a subscriber that switches or
shuts down from there is inside the manager, not outside)."""


class ManagerState(enum.Enum):
    NEW = "new"
    RUNNING = "running"
    STOPPING = "stopping"
    STOPPED = "stopped"


def _done_flag() -> _Flag:
    """A request's done flag: ``threading.Event``'s ``is_set``/``set``/``wait`` on a
    condition of its own over an RLock (an Event's Lock costs Condition three caught
    AttributeErrors per request); setting it wakes only when someone waits (usually the
    caller executes its own request)."""
    lock = threading.RLock()
    return _Flag(threading.Condition(lock), lock)


@dataclass
class _Request:
    name: str
    behavior: Behavior
    fallback_from: Behavior | None = None
    done: _Flag = field(default_factory=_done_flag)
    error: BeehaveError | None = None

    def finish(self, error: BeehaveError | None = None) -> None:
        self.error = error
        self.done.set()


class HighLevelBehaviorManager(Running):
    """Runs exactly one top-level behaviour at a time, registered by name.

    ``switch(name)`` interrupts the running one, waits until every sub-behaviour and
    action has ended (at most ``stop_timeout_s``; stragglers become STUCK and their
    ``safe_state()`` is forced) and starts the next. Switches are executed one at a time;
    concurrent requests resolve to the latest, the earlier ones raise
    :class:`SwitchSuperseded`.

    Options (keyword-only): ``default`` is the behaviour started by :meth:`start`;
    ``stop_timeout_s`` bounds every stop; ``node`` is the rclpy node on which behaviours
    and actions create their ROS entities (``self.ros``); ``blackboard`` holds what they
    read as ``self.blackboard`` (default: a new, empty one; under ROS 2, the mirror of the
    low level's); ``clock`` is what ``sleep`` follows (:class:`~beehave.clock.SimClock` for
    simulation time; ``stop_timeout_s`` stays wall time); ``gil_switch_interval_s`` lowers
    Python's thread switch interval (process-wide) so that a CPU-bound thread delays an
    interrupt by at most about that much — pass None to leave the interpreter's setting
    alone.
    """

    def __init__(self, *, default: str = IDLE, stop_timeout_s: float = 2.0,
                 node: Any = None, blackboard: Blackboard | None = None,
                 clock: WallClock | None = None,
                 gil_switch_interval_s: float | None = 0.001,
                 history_len: int = 100) -> None:
        self.default = default
        self.stop_timeout_s = check_duration_s("stop_timeout_s", stop_timeout_s)
        self.node = node
        #: What behaviours and actions read as ``self.blackboard``: the low level's
        #: blackboard when both run in one process, or a read-only mirror fed over ROS 2.
        #: What ``sleep`` and the ROS helpers' timeouts follow (sim time with ``SimClock``).
        self.clock = clock if clock is not None else WallClock()
        if blackboard is None:
            blackboard = (Blackboard(clock=self.clock.now) if isinstance(self.clock, VirtualClock)
                          else Blackboard())
        self.blackboard = blackboard
        self.blackboard_view = BlackboardView(
            self.blackboard, why="behaviours and actions read the low level's blackboard; "
                                 "they change the robot through actions")
        self.events = EventBus(log)
        self._gil_switch_interval_s = gil_switch_interval_s
        self._locks = TypeLocks(self.events)
        self._registry: dict[str, tuple[type[Behavior], dict[str, Any]]] = {IDLE: (Idle, {})}
        # Entered as `_lock` where nothing waits (the same lock, without Condition's
        # Python layer).
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._state = ManagerState.NEW
        self._pending: list[_Request] = []
        self._processing = False  # one thread executes switches: the processor
        self._in_flight: _Request | None = None  # the request it executes now
        self._executor: int | None = None  # the processor's thread
        self._stopped = threading.Event()
        self._shutdown_thread: threading.Thread | None = None
        self._stopping: Behavior | None = None  # the top-level behaviour a switch stops
        self._top: Behavior | None = None
        self._top_name: str | None = None
        self._stuck: set[Runnable] = set()
        self._pool = WorkerPool(track_job=self.clock.track_job)
        self._history: deque[dict[str, Any]] = deque(maxlen=history_len)
        #: Substitution rules for the actions and sub-behaviours started from now on
        #: (:meth:`substitute`).
        self.substitutes = Substitutions()
        # Pause: one pause() or resume() at a time; the flag and the list of paused actions
        # change under the type-lock table's lock (an action that takes a lock meanwhile
        # is paused before it runs).
        self._pause_lock = threading.Lock()
        self._paused = False
        self._paused_actions: list[Action] = []
        self._pause_round = 0
        self._locks.on_take = self._lock_taken

    @property
    def clock(self) -> WallClock:
        """What ``sleep`` and timeouts follow (see the class docstring); set it before
        :meth:`start`. :attr:`run_clock` follows it."""
        return self._clock

    @clock.setter
    def clock(self, clock: WallClock) -> None:
        self._clock = clock
        #: What behaviours and actions follow (``sleep``, engines, the ROS helpers'
        #: timeouts): ``clock`` with the pauses (:meth:`pause`) cut out.
        self.run_clock = PausableClock(clock)

    # ------------------------------------------------------------------ registry
    def register(self, name: str, behavior_cls: type[Behavior], **params: Any) -> None:
        """Make ``behavior_cls`` switchable as ``name``; ``params`` go to its constructor
        (a ``switch`` may override them). Parameters the constructor cannot take are
        rejected here, not later."""
        if not isinstance(name, str) or not name:
            raise ConfigError(f"behavior name must be a non-empty str, got {name!r}")
        if name == IDLE:
            raise ConfigError("'idle' is built in (the safe behaviour) and cannot be replaced")
        if not (isinstance(behavior_cls, type) and issubclass(behavior_cls, Behavior)):
            raise NotASubclass(f"register({name!r}, …) needs a Behavior subclass, "
                               f"got {behavior_cls!r}")
        if inspect.isabstract(behavior_cls):
            missing = ", ".join(sorted(behavior_cls.__abstractmethods__))
            raise NotASubclass(f"register({name!r}, {behavior_cls.__qualname__}): it does not "
                               f"implement {missing}() — a Behavior must define run(self)")
        _check_params(name, behavior_cls, params, partial=True)
        with self._lock:
            self._registry[name] = (behavior_cls, dict(params))

    def registered_classes(self) -> list[type[Behavior]]:
        """The behaviour classes registered, each once, in the order of registration."""
        with self._lock:
            classes = [cls for cls, _params in self._registry.values()]
        return list(dict.fromkeys(classes))

    def substitute(self, pattern: str, substitute: Substitute) -> Callable[[], None]:
        """From now on, run ``substitute`` instead of every action or sub-behaviour whose
        path, name or class name matches ``pattern`` (``fnmatch``: ``"tour/Navigate*"``,
        ``"Lift"``); the behaviour that starts it gets its own object back. For tests: see
        :class:`beehave.testing.Scripted`. Returns a function that removes the rule."""
        return self.substitutes.add(pattern, substitute)

    @property
    def names(self) -> list[str]:
        """The registered behaviour names (``idle`` included)."""
        with self._lock:
            return sorted(self._registry)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the manager's thread and the ``default`` behaviour. Idempotent."""
        with self._lock:
            if self._state is not ManagerState.NEW:
                if self._state is ManagerState.RUNNING:
                    return
                raise ManagerShutdown(
                    "this HighLevelBehaviorManager was shut down; create a new one")
            if self.default not in self._registry:
                raise UnknownBehavior(self.default, self._registry)
            if self._gil_switch_interval_s is not None:
                sys.setswitchinterval(min(sys.getswitchinterval(), self._gil_switch_interval_s))
            self._state = ManagerState.RUNNING
        self.switch(self.default)

    def shutdown(self) -> None:
        """Stop the top-level behaviour and join the manager's threads, within
        ``stop_timeout_s`` + 0.25 s (a short grace for safe states included).

        A STUCK action's thread cannot be killed: one still running then is reported (a
        warning naming it) and left to end by itself; its type stays locked. Called from a
        thread of this manager (a behaviour, an action, an event callback during a switch),
        the shutdown is deferred to a thread of its own and this call returns at once — a
        thread cannot wait for its own end; a later ``shutdown()`` from outside waits for it.
        """
        deferred = self._own_thread()
        with self._lock:
            if self._state is ManagerState.NEW:
                self._state = ManagerState.STOPPED
                self._stopped.set()
                return
            first = self._state is ManagerState.RUNNING
            if first:
                self._state = ManagerState.STOPPING
                if deferred:
                    self._shutdown_thread = threading.Thread(
                        target=self._shutdown_now, name="beehave:shutdown", daemon=True)
                    self._shutdown_thread.start()
                    return
        if first:
            self._shutdown_now()
            return
        if deferred:
            return  # a shutdown is under way already
        # Another thread is shutting down: wait for it (it is bounded).
        if not self._stopped.wait(2 * self.stop_timeout_s + 1.0):
            log.warning("shutdown: still stopping after %.1f s", 2 * self.stop_timeout_s + 1.0)
        thread = self._shutdown_thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(1.0)

    def _shutdown_now(self) -> None:
        # On a virtual clock, time runs by itself meanwhile: safe states that sleep must
        # end although the test moves time by hand.
        with self.clock.free_running():
            self._stop_all()

    def _stop_all(self) -> None:
        deadline = time.monotonic() + self.stop_timeout_s
        try:
            with self._lock:
                become = not self._processing
                if become:
                    self._processing = True
            if become:
                self._run_processor(None)
            else:
                # A switch is under way; it sees STOPPING, starts nothing new and ends.
                with self._lock:
                    self._cond.wait_for(lambda: not self._processing,
                                        self.stop_timeout_s + _GRACE_S + 2 * _MARGIN_S)
                if self._top is not None:  # it did not make it in time: stop it ourselves
                    self._stop_top()
        finally:
            leftover = self._pool.shutdown(
                timeout_s=max(_MARGIN_S, deadline + _GRACE_S - time.monotonic()))
            if leftover:
                log.warning("shutdown: STUCK threads still running after %.2f s (they end "
                            "by themselves; their types stay locked): %s",
                            self.stop_timeout_s, [t.name for t in leftover])
            with self._lock:
                self._state = ManagerState.STOPPED
            self._stopped.set()

    def _own_thread(self) -> bool:
        """True when called from a thread of this manager (one that shutdown must end)."""
        caller = current()
        return ((caller is not None and caller._manager is self) or self._holding_role()
                or threading.get_ident() == self._executor or self._pool.owns_current())

    def _holding_role(self) -> bool:
        return getattr(_tls, "holding", None) is self


    # ------------------------------------------------------------------ switching
    def switch(self, name: str, **params: Any) -> Behavior:
        """Replace the top-level behaviour by a new ``name`` behaviour and return it.

        Returns once the old behaviour has ended (or was declared STUCK after
        ``stop_timeout_s``) and the new one runs. Raises :class:`UnknownBehavior` (listing
        the names), :class:`InvalidParameters` or :class:`ConstructorFailed` before anything
        is stopped, and :class:`SwitchSuperseded` when a later request overtook this one.
        Called from a behaviour of this manager, it only queues the request (waiting would
        wait for itself) and returns the new, not yet started, behaviour.
        """
        nested = self._holding_role()
        request, become = self._enqueue(name, params)
        behavior = request.behavior
        if nested or threading.get_ident() == self._executor:
            return behavior  # asked from an event callback during a switch: the loop runs it
        caller = current()
        if caller is not None and caller._manager is self:
            if become:
                self._spawn_processor()
            return behavior
        with self.clock.busy():  # a virtual clock waits while a switch is under way
            if become:
                # Nobody is switching: execute it in this thread (saves two thread hand-offs).
                self._run_processor(request)
            if not request.done.is_set():  # (it is when this thread executed it)
                with self.clock.blocked(request.done.is_set):
                    request.done.wait()  # bounded: the processor is, and finishes every request
        if request.error is not None:
            raise request.error
        return behavior

    # ------------------------------------------------------------------ pause
    @property
    def paused(self) -> bool:
        """True between :meth:`pause` and the end of the pause (``resume``, a switch, the
        shutdown)."""
        return self._paused

    def pause(self) -> bool:
        """Pause the robot where it is, keeping what runs.

        Every running action is brought to a safe stop — an action with an ``on_pause()``
        hook by that hook, any other is interrupted to its ``safe_state()`` and will run
        again after :meth:`resume` — within ``stop_timeout_s``; one that ignores it becomes
        STUCK (its safe state forced), as in a switch. The top-level behaviour, its
        sub-behaviours, their type locks and their progress stay; time stands still for
        them (``sleep``, engine timers and the ROS helpers' timeouts follow
        :attr:`run_clock`), engines decide nothing, and an action started meanwhile waits
        for the resume before it runs. The low level goes on (it sees
        ``high_level/paused``). Returns True once paused, False when it already was.
        A switch (or the shutdown) while paused ends the pause: nothing restarts, the
        paused actions end INTERRUPTED. Called from a thread of this manager (a behaviour,
        an action, an event callback) the pause is carried out in a thread of its own and
        this returns True at once.
        """
        with self._lock:
            if self._state is not ManagerState.RUNNING:
                raise ManagerShutdown(f"cannot pause: the manager is {self._state.value}")
        if self._own_thread():
            self._request_pause(self._source())
            return True
        with self.clock.busy():
            return self._pause_now("external")

    def request_pause(self) -> None:
        """Like :meth:`pause`, but returns at once; the pause is carried out in a manager
        thread and announced by a ``paused`` event (for callers that must not block: a
        ROS service, a web request)."""
        self._request_pause(self._source() if self._own_thread() else "external")

    def _request_pause(self, source: str) -> None:
        with self._lock:
            if self._state is not ManagerState.RUNNING:
                raise ManagerShutdown(f"cannot pause: the manager is {self._state.value}")
        def job() -> None:
            self._pause_now(source)

        try:
            self._pool.submit("beehave:pause", job)
        except RuntimeError:  # the pool closed meanwhile: the manager is shutting down
            raise ManagerShutdown("cannot pause: the manager is shutting down") from None

    def _source(self) -> str:
        """Who in this manager asks (recordings replay only what came from outside)."""
        caller = current()
        return caller.path if caller is not None else "manager"

    def resume(self) -> bool:
        """End the pause: actions paused by their ``on_pause()`` hook get ``on_resume()``
        and go on, the others run again from the start; time runs again for behaviours.
        Returns True when it ended a pause, False when none was on."""
        source = self._source() if self._own_thread() else "external"
        with self._pause_lock:
            with self._locks.table():
                if not self._paused:
                    return False
                hooked = [a for a in self._paused_actions
                          if a._pause is _Pause.HOOKED and not a._decided.is_set()]
            # Before anything moves again: observers see the resume before its first
            # command.
            self.events.emit(Event(EventKind.RESUMED, self._top_name or "", detail={
                "by": "resume", "source": source,
                "paused_s": round(self.run_clock.frozen_for(), 6),
                "actions": [a.path for a in self._paused_actions]}))
            # The hooks first, while everything else still stands still: an action whose
            # run() went on meanwhile could undo what its on_resume() does.
            for action in hooked:
                try:
                    with self.run_clock.unfrozen():
                        action.on_resume()
                except Exception as exc:  # it cannot go on as if nothing happened
                    self.events.emit(Event(EventKind.HOOK_FAILED, action.path,
                                           action.status.name, exc, {"hook": "on_resume"}))
                    action.interrupt()
            actions, _ = self._end_pause()
        for action in actions or []:
            action._request_resume()
        return True

    def _pause_now(self, source: str) -> bool:
        self.events.emit(Event(EventKind.PAUSE_REQUESTED, self._top_name or "",
                               detail={"source": source}))
        with self._pause_lock:
            began = time.monotonic()
            with self._locks.table() as holders:
                if self._paused:
                    return False
                self._paused = True
                self._pause_round += 1
                round_ = self._pause_round
                self.run_clock.freeze()
                self._paused_actions = list(holders)
                waits = [(a, a._request_pause(hooked=a._has_pause_hooks)) for a in holders]
            deadline = began + self.stop_timeout_s
            for action, done in waits:
                if action._pause is _Pause.HOOKED:
                    self._pool.submit(f"beehave:on_pause:{action.path}",
                                      functools.partial(self._hook_pause, action, done))
            stuck: list[Action] = []
            for action, done in waits:
                with self.clock.blocked(done.is_set):
                    if not done.wait(max(0.0, deadline - time.monotonic())):
                        action._mark_stuck()
                        stuck.append(action)
            grace = max(deadline, time.monotonic()) + _GRACE_S
            for action in stuck:
                action._wait_safe_state(grace)
            with self._locks.table():
                current = self._paused and self._pause_round == round_
            if current:  # (a switch may have ended it meanwhile)
                self.events.emit(Event(EventKind.PAUSED, self._top_name or "", detail={
                    "actions": [a.path for a, _ in waits],
                    "stuck": [a.path for a in stuck],
                    "took_s": round(time.monotonic() - began, 6)}))
            return True

    def _hook_pause(self, action: Action, done: threading.Event) -> None:
        """An action's ``on_pause()`` hook, in a pool thread (the pause waits for it)."""
        try:
            with self.run_clock.unfrozen():
                action.on_pause()
        except Exception as exc:
            self.events.emit(Event(EventKind.HOOK_FAILED, action.path, action.status.name,
                                   exc, {"hook": "on_pause"}))
            # It could not pause itself: the default way (interrupt to its safe state).
            with action._cond:
                action._pause = _Pause.WIND_DOWN
                action._cond.notify_all()
            return
        done.set()

    def _lock_taken(self, action: Action) -> None:
        """Under the lock table's lock: an action starts while the manager is paused; it
        waits for the resume before it runs."""
        if self._paused:
            action._request_pause(hooked=False)
            self._paused_actions.append(action)

    def _end_pause(self) -> tuple[list[Action] | None, float]:
        """Clear the pause (under the lock table's lock); the paused actions and how long
        it lasted, or (None, 0) when no pause was on. Time runs again for behaviours."""
        with self._locks.table():
            if not self._paused:
                return None, 0.0
            self._paused = False
            actions, self._paused_actions = self._paused_actions, []
            lasted = self.run_clock.thaw()
        return actions, lasted

    def _end_pause_by(self, why: str, subject: str) -> None:
        """A switch or the shutdown ends the pause (everything was interrupted first):
        the paused actions end INTERRUPTED, nothing restarts."""
        if not self._paused:
            # (Read without the lock: a pause that begins after this look could as well
            # begin after the locked one; it pauses the next behaviour.)
            return
        actions, lasted = self._end_pause()
        if actions is None:
            return
        for action in actions:
            action._request_resume()  # it sees its interrupt and ends
        self.events.emit(Event(EventKind.RESUMED, subject, detail={
            "by": why, "paused_s": round(lasted, 6), "actions": [a.path for a in actions]}))

    def request_switch(self, name: str, **params: Any) -> Behavior:
        """Like :meth:`switch`, but returns at once (after checking the name and the
        parameters); the switch happens in a manager thread. For callers that must not
        block, e.g. ROS parameter callbacks. However many requests arrive, one thread
        executes them and only the latest waiting one is kept (the others are superseded)."""
        request, become = self._enqueue(name, params)
        if become:
            self._spawn_processor()
        return request.behavior

    def _enqueue(self, name: str, params: dict[str, Any]) -> tuple[_Request, bool]:
        """Queue a request; returns it and whether the caller must run the processor."""
        if self._state is ManagerState.NEW:
            self.start()
        try:
            behavior = self._construct(name, params)
        except BeehaveError as exc:
            self.events.emit(Event(EventKind.SWITCH_REJECTED, name, error=exc))
            raise
        request = _Request(name, behavior)
        with self._lock:
            if self._state is not ManagerState.RUNNING:
                raise ManagerShutdown(f"cannot switch to {name!r}: the manager is "
                                      f"{self._state.value}")
            # Latest wins: a request still waiting is superseded now, so the queue holds
            # one request however many arrive.
            replaced, self._pending = self._pending, [request]
            become = not self._processing
            if become:
                self._processing = True
        # Who asked: a behaviour of this manager (its path) or "external" (an operator, an
        # interface, a test). A replay repeats only the external requests: the behaviours
        # it runs ask again by themselves.
        caller = current()
        source = caller.path if caller is not None and caller._manager is self else "external"
        if become:
            _tls.holding = self
        try:
            if self.events.wants(EventKind.SWITCH_REQUESTED):
                self.events.emit(Event(EventKind.SWITCH_REQUESTED, name, detail={
                    "params": _jsonable(params), "source": source}))
            for old in replaced:
                if old.fallback_from is None:
                    self._supersede(old, request)
                else:
                    old.finish()  # a fallback is moot once something was asked for
        finally:
            if become:
                _tls.holding = None
        return request, become

    @property
    def current(self) -> str | None:
        """The name of the running top-level behaviour (None while switching)."""
        return self._top_name

    @property
    def requested(self) -> str | None:
        """The name of the switch request waiting or being executed (the latest one:
        earlier ones were superseded), or None when none is. With :attr:`current`, what the
        manager will run once it settles: ``requested or current``."""
        with self._lock:
            asked = [r for r in self._pending if r.fallback_from is None]
            if asked:
                return asked[-1].name
            flight = self._in_flight
        return flight.name if flight is not None and flight.fallback_from is None else None

    @property
    def top(self) -> Behavior | None:
        """The running top-level behaviour object."""
        return self._top

    def subscribe(self, callback: EventCallback) -> Callable[[], None]:
        """Receive every lifecycle :class:`~beehave.events.Event`; returns an unsubscribe
        function. Callbacks run in the thread that produced the event: keep them short."""
        return self.events.subscribe(callback)

    @property
    def history(self) -> list[dict[str, Any]]:
        """Ended top-level behaviours, oldest first: name, status, error, duration."""
        with self._lock:
            return list(self._history)

    def snapshot(self) -> dict[str, Any]:
        """A JSON-serialisable picture of what runs now."""
        top = self._top
        with self._lock:
            stuck = sorted(s.path for s in self._stuck)
            history = list(self._history)[-10:]
        return {
            "time": time.time(),
            "state": self._state.value,
            "current": self._top_name,
            "paused": self._paused,
            "top": None if top is None else top._snapshot(),
            "locks": self._locks.snapshot(),
            "stuck": stuck,
            "history": history,
        }

    # ------------------------------------------------------------------ the manager thread
    def _construct(self, name: str, params: dict[str, Any]) -> Behavior:
        with self._lock:
            entry = self._registry.get(name)
            if entry is None:
                raise UnknownBehavior(name, self._registry)
        cls, registered = entry
        merged = {**registered, **params}
        _check_params(name, cls, merged, partial=False)
        try:
            behavior = cls(**merged)
        except (ValueError, TypeError, ConfigError) as exc:
            if isinstance(exc, BeehaveError) and not isinstance(exc, ConfigError):
                raise ConstructorFailed(f"behavior {name!r}: {cls.__qualname__}.__init__: "
                                        f"{exc}") from exc
            # The parameters fit the signature (checked above); the constructor's own
            # validation turned their values down (or the file one of them names).
            raise InvalidParameters(
                f"behavior {name!r}: {cls.__qualname__}.__init__ rejected the parameters "
                f"{_jsonable(merged)}: {type(exc).__name__}: {exc}") from exc
        except Exception as exc:
            # A bug in the constructor, not in what was asked for.
            raise ConstructorFailed(
                f"behavior {name!r}: {cls.__qualname__}.__init__ raised "
                f"{type(exc).__name__}: {exc} (parameters {_jsonable(merged)})") from exc
        behavior.name = name
        return behavior

    def _spawn_processor(self) -> None:
        """Run the processor in a pool thread (the caller holds the processor role)."""
        try:
            self._pool.submit("beehave:switch", self._process_reporting)
        except RuntimeError:  # the pool is shut down: nothing may start any more
            with self._lock:
                requests, self._pending = self._pending, []
                self._processing = False
                self._cond.notify_all()
            for request in requests:
                request.finish(ManagerShutdown("the manager is shut down"))

    def _process_reporting(self) -> None:
        # Nobody waits on this thread: the requests got the error as their outcome, and
        # observers get it as an event (not only the pool's log).
        try:
            self._run_processor(None)
        except Exception as exc:
            self.events.emit(Event(EventKind.SWITCH_REJECTED, "switch", error=exc))

    def _run_processor(self, own: _Request | None) -> None:
        """Execute requests until none is left. Exactly one thread holds this role at a time
        (``_processing``, taken under ``_cond`` by whoever queued into an idle manager).
        A ``switch()`` caller executing its ``own`` request hands the rest to a pool thread
        once it is done, so that it returns as soon as its own switch is."""
        self._executor = threading.get_ident()
        requests: list[_Request] = []
        try:
            while True:
                with self._lock:
                    stopping = self._state is not ManagerState.RUNNING
                    requests, self._pending = self._pending, []
                    work = bool(requests) or (self._top is not None if stopping
                                              else self._top is None)
                    if not work:
                        self._processing = False
                        self._cond.notify_all()
                        return
                    handover = own is not None and own.done.is_set()
                    if handover:
                        self._pending = requests + self._pending
                        requests = []
                if handover:
                    self._executor = None
                    self._spawn_processor()
                    return
                self._execute(requests, stopping=stopping)
        except BaseException as exc:
            # Whatever went wrong, no caller may wait forever for its request, and the
            # processor role is given back.
            failure = BeehaveError(f"switch failed: {exc!r}")
            failure.__cause__ = exc
            with self._lock:
                requests += self._pending
                self._pending = []
                self._processing = False
                self._cond.notify_all()
                empty = self._state is ManagerState.RUNNING and (
                    self._top is None or self._top.status.finished)
            for request in requests:
                if not request.done.is_set():
                    request.finish(failure)
            if empty:
                # One behaviour always runs: whatever failed, the safe one.
                with self._lock:
                    become = self._queue_locked(self._idle_request(None))
                if become:
                    self._spawn_processor()
            raise
        finally:
            if self._executor == threading.get_ident():
                self._executor = None

    def _execute(self, requests: list[_Request], *, stopping: bool) -> None:
        """Carry out one batch of requests (the processor's)."""
        if stopping:
            for request in requests:
                self._cancel(request)
            self._stop_top()
            return
        asked = [r for r in requests if r.fallback_from is None]
        fallbacks = [r for r in requests if r.fallback_from is not None]
        latest: _Request
        if asked:
            *older, latest = asked
            for request in older:
                self._supersede(request, latest)
            for request in fallbacks:
                request.finish()  # what was asked for replaces the fallback
        elif fallbacks:
            *older, latest = fallbacks
            for request in older:
                request.finish()
            if self._top is not None and latest.fallback_from is not self._top:
                latest.finish()  # something else replaced the ended behaviour already
                return
        else:
            # Nothing runs and nothing is asked for (a start that failed): one behaviour
            # always runs, so the safe one.
            log.warning("no top-level behaviour was running; starting %r", IDLE)
            latest = self._idle_request(None)
        with self._lock:
            self._in_flight = latest
        try:
            self._stop_top()
            with self._lock:
                overtaken = any(r.fallback_from is None for r in self._pending)
                stopping = self._state is not ManagerState.RUNNING
            if stopping:
                self._cancel(latest)
            elif overtaken:
                if latest.fallback_from is None:
                    self._supersede(latest, None)
                else:
                    latest.finish()
            else:
                self._start_top(latest)
        finally:
            with self._lock:
                self._in_flight = None

    def _cancel(self, request: _Request) -> None:
        """The manager shuts down before ``request`` could run: say so, to its caller and
        to observers (a ``request_switch`` caller learns it from the event)."""
        error = ManagerShutdown(f"switch to {request.name!r} cancelled: the manager is "
                                "shutting down")
        request.finish(error)
        if request.fallback_from is None:
            self.events.emit(Event(EventKind.SWITCH_REJECTED, request.name, error=error))

    def _idle_request(self, ended: Behavior | None) -> _Request:
        idle = Idle()
        idle.name = IDLE
        return _Request(IDLE, idle, fallback_from=ended)

    def _supersede(self, request: _Request, by: _Request | None) -> None:
        later = f" by {by.name!r}" if by is not None else " by a later request"
        request.finish(SwitchSuperseded(f"switch to {request.name!r} was superseded{later}"))
        self.events.emit(Event(EventKind.SWITCH_SUPERSEDED, request.name))

    def _stop_top(self) -> None:
        top = self._top
        if top is None:
            return
        self._top_name = None
        self._stopping = top  # its end is ours, not its own: no fallback to idle
        stuck_before = set(self._stuck_nodes()) if self._stuck else set()
        deadline = time.monotonic() + self.stop_timeout_s
        top._interrupt(deadline)
        # After the interrupt: what a pause froze wakes to find it, and nothing restarts.
        self._end_pause_by("shutdown" if self._state is not ManagerState.RUNNING else "switch",
                           top.name)
        # The behaviour itself gives up on its children at `deadline`; allow it a moment
        # to record that before declaring the behaviour itself STUCK.
        # Normally one wake-up: its end (the status is decided before it). Otherwise the
        # bounds of both steps: decided by the deadline, its clean-up over soon after.
        ended = top._join(max(0.0, deadline + _MARGIN_S - time.monotonic()))
        if not ended and (not top._decided.is_set() or not top._join(_MARGIN_S)):
            top._mark_stuck()
            with self._lock:
                self._record_history(top)
        # Forced safe states run in threads of their own: give them a short grace, so that
        # the switch normally returns with the hardware safe, but never waits unbounded.
        grace = max(deadline, time.monotonic()) + _GRACE_S
        for node in self._stuck_nodes() if self._stuck else ():
            if node not in stuck_before:
                node._wait_safe_state(grace)
        self._top = None
        self._stopping = None

    def _start_top(self, request: _Request) -> None:
        behavior = request.behavior
        detail: dict[str, Any] = {}
        ended = request.fallback_from
        if ended is not None:
            detail = {"after": ended.name, "status": ended.status.name}
            self.events.emit(Event(EventKind.FALLBACK, ended.path, ended.status.name,
                                   ended.error, {"to": request.name}))
        behavior._attach(None, self)
        self._top = behavior
        self._top_name = request.name
        behavior._start_thread()
        request.finish()
        if self.events.wants(EventKind.SWITCH_COMPLETED):
            self.events.emit(Event(EventKind.SWITCH_COMPLETED, request.name, detail=detail))

    # ------------------------------------------------------------------ callbacks from items
    def _node_ended(self, node: Runnable, was_stuck: bool) -> None:
        """Called in the item's own thread, as the last thing it does."""
        if node in self._stuck:  # (decided by now: nobody adds it any more)
            with self._lock:
                self._stuck.discard(node)
        if node.parent is not None:
            return
        with self._lock:
            self._record_history(node)
            ended_on_its_own = (isinstance(node, Behavior) and node is self._top
                                and node is not self._stopping
                                and self._state is ManagerState.RUNNING
                                and not any(r.fallback_from is None for r in self._pending))
            become = False
            if ended_on_its_own:
                assert isinstance(node, Behavior)
                # Nothing else is asked for: fall back to the safe behaviour.
                become = self._queue_locked(self._idle_request(node))
        if become:
            self._spawn_processor()

    def _queue_locked(self, request: _Request) -> bool:
        """With ``_cond`` held: queue ``request``; True when the caller took the processor
        role and must run it (no switch was being executed)."""
        self._pending.append(request)
        become = not self._processing
        self._processing = True
        return become

    def _record_history(self, node: Runnable) -> None:
        """With ``_cond`` held: note an ended (or STUCK) top-level behaviour, once."""
        if node._in_history:
            return
        node._in_history = True
        self._history.append({"name": node.name, "status": node.status.name,
                              "error": None if node.error is None else repr(node.error),
                              "elapsed_s": node.elapsed_s})

    def _stuck_add(self, node: Runnable) -> None:
        with self._lock:
            self._stuck.add(node)

    def _stuck_nodes(self) -> list[Runnable]:
        with self._lock:
            return list(self._stuck)


_MARGIN_S = 0.05
"""What a stop allows beyond the deadline for a behaviour to record its end (twice: the
behaviour, then its thread), before it is declared STUCK."""
_GRACE_S = 0.1
"""How long a switch waits, after its deadline, for forced safe states (documented in
docs/concepts.md): a STUCK action's ``safe_state()`` normally has run when ``switch()``
returns, and one that hangs is reported (SAFE_STATE_OVERDUE) instead of blocking it."""


@functools.lru_cache(maxsize=256)
def _signature(cls: type[Behavior]) -> inspect.Signature | None:
    """A class's constructor signature (inspect takes ~30 µs; a switch asks every time)."""
    try:
        return inspect.signature(cls)
    except (TypeError, ValueError):  # builtins without a signature: let the call decide
        return None


@functools.lru_cache(maxsize=1024)
def _names_fit(cls: type[Behavior], names: frozenset[str], partial: bool) -> TypeError | None:
    """Whether a constructor takes keyword arguments of these names (binding depends on
    the names alone; a switch asks every time): None, or binding's error."""
    signature = _signature(cls)
    if signature is None:
        return None
    try:
        (signature.bind_partial if partial else signature.bind)(**dict.fromkeys(names))
    except TypeError as exc:
        return exc
    return None


def _check_params(name: str, cls: type[Behavior], params: dict[str, Any], *, partial: bool) -> None:
    exc = _names_fit(cls, frozenset(params), partial)
    if exc is not None:
        signature = _signature(cls)
        assert signature is not None
        accepted = [p for p in signature.parameters if p not in ("args", "kwargs")]
        raise InvalidParameters(
            f"behavior {name!r} ({cls.__name__}) rejects parameters {_jsonable(params)}: "
            f"{exc}; it accepts: {', '.join(accepted) or 'no parameters'}") from exc


def _jsonable(params: dict[str, Any]) -> dict[str, Any]:
    return {k: v if isinstance(v, (str, int, float, bool, type(None))) else repr(v)
            for k, v in params.items()}


__all__ = ["HighLevelBehaviorManager", "ManagerState", "Status"]
