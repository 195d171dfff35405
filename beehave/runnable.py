"""The lifecycle that Behavior and Action share: one thread, one Status, cooperative interrupts.

This module is the driver; users subclass :class:`beehave.Behavior` or
:class:`beehave.Action` and never this class directly. Every status transition happens
here, under the object's own condition variable, so observers never see a half-made change.
"""

from __future__ import annotations

import abc
import enum
import math
import sys
import sysconfig
import threading
import time
import traceback
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Self

from beehave.blackboard import Blackboard, BlackboardView, ChangeCallback, Subscription
from beehave.clock import WallClock
from beehave.errors import (
    AlreadyStarted,
    ConfigError,
    Interrupted,
    ManagerShutdown,
    ReservedAttribute,
)
from beehave.events import Event, EventKind
from beehave.status import Status

if TYPE_CHECKING:
    from beehave.behavior import Behavior
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.ros.io import RosIO

_local = threading.local()
_STDLIB = sysconfig.get_paths()["stdlib"]
_WALL = WallClock()


def current() -> Runnable | None:
    """The behaviour or action whose thread is calling, or None."""
    return getattr(_local, "node", None)


_RESERVED = {
    "status": "its lifecycle status", "result": "run()'s return value",
    "error": "the exception run() raised", "parent": "the behaviour that started it",
    "path": "where it sits in the running tree", "interrupted": "the interrupt flag",
    "alive": "whether its thread runs", "manager": "the manager it runs under",
    "blackboard": "the robot's state (read-only)", "ros": "its ROS 2 I/O",
    "stop_deadline": "the deadline of a stop", "elapsed_s": "its running time",
    "started_at": "its start time", "ended_at": "its end time",
    "children": "its running actions and sub-behaviours",
    "safe_state_error": "the exception safe_state() raised",
}
"""Attributes beehave owns on every behaviour and action; user code that assigns one gets
:class:`ReservedAttribute` naming it (``name`` is yours to set). Each is a read-only
property (see :func:`_reserve`), so beehave's own state changes are plain attribute stores:
a ``__setattr__`` check would cost a Python call on each of dozens per switch."""


def _refuse(attr: str) -> Callable[[Any, Any], None]:
    def refuse(self: Any, value: Any) -> None:
        raise ReservedAttribute(
            f"{type(self).__name__}.{attr} is beehave's ({_RESERVED[attr]}) and cannot be "
            f"assigned; store yours under another name, e.g. self.my_{attr}")
    return refuse


def _absent(attr: str) -> Callable[[Any], Any]:
    def absent(self: Any) -> Any:
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {attr!r}")
    return absent


_REPLACEABLE = frozenset({"ros", "blackboard"})
"""The reserved names a class body may define with a plain attribute: its I/O, which a
test double replaces (a fake ``ros``). Any other would hide what beehave keeps there
(``result = None``: the handle's result reads None for ever), so a class body may not."""


def _reserve(cls: type) -> None:
    """Make the reserved names of ``cls``'s own body read-only properties (a property
    without a setter gets one that raises :class:`ReservedAttribute`); a reserved name that
    is no property there (a class attribute would hide beehave's value) is refused at once,
    but for the I/O a test double replaces (:data:`_REPLACEABLE`).
    On :class:`Runnable` itself, the names only a subclass has (``children``,
    ``safe_state_error``) are absent until then, and refused."""
    for attr in _RESERVED:
        if attr not in cls.__dict__:
            if cls is Runnable:
                setattr(cls, attr, property(_absent(attr), _refuse(attr)))
            continue
        found = cls.__dict__[attr]
        if not isinstance(found, property):
            if attr in _REPLACEABLE:
                continue
            raise ReservedAttribute(
                f"{cls.__name__}.{attr} is beehave's ({_RESERVED[attr]}) and cannot be "
                f"defined; name yours differently, e.g. my_{attr}")
        if found.fset is None:
            setattr(cls, attr, found.setter(_refuse(attr)))


class _Pause(enum.Enum):
    """How the manager's pause holds an action (actions only, see :class:`Action`)."""

    NONE = "none"
    """Not paused."""
    HOOKED = "hooked"
    """Paused through its own ``on_pause()`` hook: ``run`` stays where it is."""
    WIND_DOWN = "wind down"
    """Asked to wind down: ``interrupted`` reads True, ``run`` returns, the hardware goes
    to its safe state, and ``run`` starts again at the resume."""


class _Flag:
    """A one-way flag that threads wait for, kept on its owner's condition: a
    ``threading.Event`` would bring a lock and a condition of its own to every behaviour
    and action (a switch makes and ends dozens of them). Setting it takes the lock and
    wakes the condition only when someone waits for the flag (not for the owner's
    ``sleep``)."""

    __slots__ = ("_cond", "_lock", "_on", "_waiters")

    def __init__(self, cond: threading.Condition, lock: threading.RLock) -> None:
        self._cond = cond
        self._lock = lock  # the condition's, entered without Condition's Python layer
        self._on = False
        self._waiters = 0

    def is_set(self) -> bool:
        return self._on

    def set(self) -> None:
        # A waiter counts itself (under the lock) before it reads the flag: when this
        # reads no waiter, any later one finds the flag set and does not wait.
        self._on = True
        if self._waiters:
            with self._lock:
                self._cond.notify_all()

    def _set_locked(self) -> None:
        """``set`` for a caller that holds the owner's lock."""
        self._on = True
        if self._waiters:
            self._cond.notify_all()

    def wait(self, timeout: float | None = None) -> bool:
        if self._on:
            return True
        with self._lock:
            self._waiters += 1
            try:
                return self._cond.wait_for(self.is_set, timeout)
            finally:
                self._waiters -= 1


class _OwnedView(BlackboardView):
    """The blackboard as one behaviour or action sees it: its subscriptions are closed
    when it ends, as a logic's are."""

    def __init__(self, board: Blackboard, owner: str) -> None:
        super().__init__(board, why="behaviours and actions read the low level's blackboard; "
                                    "they change the robot through actions")
        self._owner = owner
        self._lock = threading.Lock()
        self._subscriptions: list[Subscription] | None = []

    def subscribe(self, pattern: str, callback: ChangeCallback) -> Subscription:
        subscription = super().subscribe(pattern, callback)
        with self._lock:
            if self._subscriptions is not None:
                self._subscriptions = [s for s in self._subscriptions if not s.closed]
                self._subscriptions.append(subscription)
                return subscription
        subscription.close()
        raise ManagerShutdown(f"{self._owner}: has ended; it cannot subscribe to {pattern!r}")

    def close(self) -> None:
        with self._lock:
            subscriptions, self._subscriptions = self._subscriptions or [], None
        for subscription in subscriptions:
            subscription.close()


class Runnable(abc.ABC):
    """A unit of work that runs :meth:`run` in a thread of its own, owned by its parent."""

    #: Shown in snapshots and events; defaults to the class name. Set it in ``__init__``.
    name: str
    __result: Any
    __error: BaseException | None
    _parent: Behavior | weakref.ref[Behavior] | None
    __started_at: float | None
    __ended_at: float | None
    _manager: HighLevelBehaviorManager | None
    _status: Status
    _interrupt_requested: bool
    _stop_deadline: float | None
    _cond_lock: threading.RLock
    _cond: threading.Condition
    _decided: _Flag
    _started: bool
    _ros: RosIO | None
    _ended: _Flag
    _traceback: str
    _view: _OwnedView | None
    _interrupted_at: float | None
    _thread_id: int | None
    _holds: int
    _safe_done: _Flag | None
    _safe_thread_id: int | None
    _overdue_reported: bool
    _in_history: bool
    _suffix: str
    _path: str | None
    _path_name: str | None
    _pause: _Pause
    _paused_done: threading.Event | None
    _pause_safe: bool
    #: Whether it has a ``safe_state()`` to call (an action: yes; a behaviour has no
    #: hardware of its own).
    _HAS_SAFE_STATE: ClassVar[bool] = False
    #: Whether it has children to interrupt before its own thread is woken (a behaviour).
    _HAS_CHILDREN: ClassVar[bool] = False

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        # Runtime state lives here so that subclasses need not call super().__init__().
        self = super().__new__(cls)
        # An RLock under the condition: Condition then finds the lock's own C methods
        # instead of raising and catching three AttributeErrors to fall back on its
        # Python ones (3 µs per item at creation, a Python call per wait and notify).
        # Hot paths enter `_cond_lock` itself: the same lock, without Condition's Python layer.
        lock = threading.RLock()
        cond = threading.Condition(lock)
        self.__dict__.update(
            name=cls.__name__, _parent=None,
            _manager=None, _traceback="", _status=Status.PENDING,
            _interrupt_requested=False, _stop_deadline=None,
            _cond_lock=lock, _cond=cond, _decided=_Flag(cond, lock),
            _started=False, _ros=None, _view=None, _ended=_Flag(cond, lock),
            _interrupted_at=None, _thread_id=None,
            # What keeps the type lock and the ROS entities: run(), plus a forced
            # safe_state() while one runs. Whichever of them ends last releases them.
            _holds=1,
            # Set while a safe_state() runs (in its own thread or in run's): who waits for
            # the hardware to be safe waits on it.
            _safe_done=None, _safe_thread_id=None, _overdue_reported=False,
            _in_history=False,
            _suffix="",  # "#2" for the second child of that name in its behaviour
            _path=None,  # path, kept once started (events name it often) …
            _path_name=None,  # … for the name it was made with
            # Pause (actions only, see Action): how a pause holds it; set once it is
            # paused (or ended); its hardware made safe by the pause and run() not yet
            # restarted.
            _pause=_Pause.NONE, _paused_done=None, _pause_safe=False)
        # What the reserved names read (private to this class: a subclass's own
        # `self._result` or `self._error` must not be beehave's).
        self.__result = self.__error = None
        self.__started_at = self.__ended_at = None  # time.monotonic()
        return self

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        _reserve(cls)

    def __init__(self, name: str | None = None) -> None:
        """Optional: ``super().__init__(name="front_lift")`` names it (the py_trees habit);
        parameters of your own go to your own ``__init__``."""
        if name is not None:
            if not isinstance(name, str) or not name or "/" in name:
                raise ConfigError(f"{type(self).__name__}: name must be a non-empty str "
                                  f"without '/', got {name!r}")
            self.name = name

    # ------------------------------------------------------------------ user hooks
    @abc.abstractmethod
    def run(self) -> Any:
        """Do the work. Called once, in this object's own thread.

        Check :attr:`interrupted` (or use :meth:`sleep`) often and return soon after it
        becomes true. The return value becomes :attr:`result`; an exception makes the
        status FAILED with the exception on :attr:`error`.
        """

    # ------------------------------------------------------------------ handle API
    @property
    def status(self) -> Status:
        return self._status

    @property
    def result(self) -> Any:
        """``run``'s return value once SUCCEEDED."""
        return self.__result

    @property
    def error(self) -> BaseException | None:
        """The exception ``run`` raised (FAILED), with its ``__traceback__``."""
        return self.__error

    @property
    def started_at(self) -> float | None:
        """When it started (``time.monotonic()``), or None."""
        return self.__started_at

    @property
    def ended_at(self) -> float | None:
        """When its status became final or STUCK (``time.monotonic()``), or None."""
        return self.__ended_at

    @property
    def parent(self) -> Behavior | None:
        """The behaviour that started it (None for a top-level behaviour). Once this has
        ended it holds its parent weakly (the parent holds it in ``children``): None when
        nothing keeps the parent any more."""
        parent = self._parent
        if isinstance(parent, weakref.ref):
            return parent()
        return parent

    @property
    def interrupted(self) -> bool:
        """True once an interrupt was requested — or, for an action without an
        ``on_pause()`` hook, while the manager pauses it: wind down and return."""
        return self._interrupt_requested or self._pause is _Pause.WIND_DOWN

    @property
    def path(self) -> str:
        """``parent/…/name``: where this sits in the running tree (fixed once it runs:
        renaming a running behaviour renames it, not the paths its children have)."""
        path = self._path
        name = self.name
        if path is None or self._path_name is not name:
            own = f"{name}{self._suffix}"
            parent = self.parent
            path = own if parent is None else f"{parent.path}/{own}"
            if self._started:
                self._path, self._path_name = path, name
        return path

    @property
    def stop_deadline(self) -> float | None:
        """When a switch interrupted this, the ``time.monotonic()`` by which it must have
        stopped (after that its stragglers are declared STUCK); None otherwise."""
        return self._stop_deadline

    @property
    def blackboard(self) -> BlackboardView:
        """The robot's state as the low level sees it: a read-only view of the manager's
        blackboard (over ROS 2, a mirror of the low level's). To change the robot, start
        an action; to tell the low level something, choose its logic (``Behavior.logic``)."""
        manager = self._manager
        if manager is None:
            raise ManagerShutdown(f"{self.name!r} is not started: it has no blackboard yet")
        with self._cond_lock:
            if self._view is None:
                self._view = _OwnedView(manager.blackboard, self.path)
            return self._view

    @property
    def ros(self) -> RosIO:
        """Robot I/O over ROS 2 on the manager's node: ``publisher``, ``subscription``,
        ``client``, ``call``, ``timer`` and ``latest`` (see :mod:`beehave.ros.io`).
        Everything created here is destroyed when this behaviour or action ends, whatever
        its status — after ``safe_state()``, which may still use it."""
        manager = self.manager
        with self._cond_lock:
            if self._ros is None:
                if manager.node is None:
                    raise ConfigError(
                        f"{self.path}: self.ros needs a ROS node: run the robot with "
                        f"`beehave run ROBOT.yaml`, or pass node= to HighLevelBehaviorManager")
                from beehave.ros.io import RosIO

                self._ros = RosIO(manager.node, owner=self.path, cond=self._cond,
                                  interrupted=lambda: self.interrupted,
                                  clock=manager.run_clock)
            return self._ros

    @property
    def manager(self) -> HighLevelBehaviorManager:
        """The manager this runs under (set when it is started)."""
        if self._manager is None:
            raise ManagerShutdown(f"{self.name!r} is not started: it has no manager yet")
        return self._manager

    @property
    def alive(self) -> bool:
        """True while its ``run`` or clean-up executes (a STUCK item stays alive until its
        ``run`` returns)."""
        return self._started and not self._ended.is_set()

    def sleep(self, seconds: float) -> bool:
        """Wait ``seconds`` (``math.inf``: until interrupted); return False at once when
        interrupted, True otherwise. While the manager is paused, time stands still: the
        sleep goes on with what it had left after ``resume()``."""
        clock = self._manager.run_clock if self._manager is not None else _WALL
        timeout_s = _timeout(seconds, self, "sleep(seconds)")
        with self._cond_lock:
            clock.wait(self._cond, self._wake_reason, timeout_s)
            if self._HAS_CHILDREN:  # (a child's failure, raised in its behaviour)
                self._raise_pending()
            return not (self._interrupt_requested or self._pause is _Pause.WIND_DOWN)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the outcome is decided (any final status, STUCK included).

        Returns False on timeout (None or ``math.inf``: no timeout). A behaviour that waits
        for its own child this way has seen the outcome, so a failure of that child is not
        raised again as ChildFailed.
        """
        done = self._block_on(self._decided, _timeout(timeout, self, "wait(timeout)"))
        if done and self.parent is not None:
            self.parent._observed(self)
        return done

    def interrupt(self) -> None:
        """Ask it to stop (cooperatively). Safe from any thread; idempotent."""
        self._interrupt(None)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.path!r} {self._status.name}>"

    # ------------------------------------------------------------------ driver
    def _attach(self, parent: Behavior | None, manager: HighLevelBehaviorManager) -> None:
        with self._cond_lock:
            if self._manager is not None:
                raise AlreadyStarted(
                    f"{type(self).__name__} {self.name!r} was already started "
                    f"(status {self._status.name}); create a new object for each run")
            self._manager = manager
            self._parent = parent

    def _detach(self) -> None:
        with self._cond_lock:
            if self._status is Status.PENDING:
                self._manager = None
                self._parent = None
                self._suffix = ""
                self._path = None

    def _start_thread(self) -> None:
        assert self._manager is not None
        with self._cond_lock:
            self._started = True
            self._status = Status.RUNNING
            self.__started_at = time.monotonic()
        self._manager._pool.submit(f"beehave:{self.path}", self._main)

    def _main(self) -> None:
        _local.node = self
        self._thread_id = threading.get_ident()
        ended = True
        try:
            assert self._manager is not None
            events = self._manager.events
            if events.wants(EventKind.STARTED):
                # An action's type rides along: a recording then tells who held which type
                # lock when (the timeline of `beehave view`).
                kind = getattr(self, "action_type", None)
                events.emit(Event(EventKind.STARTED, self.path, Status.RUNNING.name,
                                  detail={"action_type": kind} if kind else {}))
            error: BaseException | None = None
            again = self._pause_point(None, ran=False)
            while again:
                error = None
                try:
                    self.__result = self.run()
                except BaseException as exc:  # recorded on the handle, surfaced to the parent
                    error = exc
                again = self._pause_point(error, ran=True)
            if self._HAS_CHILDREN:
                error = self._after_run(error)
            ended = self._finish(error)
        finally:
            _local.node = None
            self._thread_id = None
            if ended:
                self._ended.set()
                # _tell_parent and _let_go_of_parent, inline (a switch ends a dozen items).
                parent = self._parent  # (strong until now)
                if parent is not None:
                    parent._child_settled(self)  # type: ignore[union-attr]
                    self._parent = weakref.ref(parent)  # type: ignore[arg-type]

    def _tell_parent(self) -> None:
        """It has ended or become STUCK: a parent collecting its children counts it."""
        parent = self._parent  # (strong until _let_go_of_parent)
        if parent is not None and not isinstance(parent, weakref.ref):
            parent._child_settled(self)

    def _let_go_of_parent(self) -> None:
        """Its life is over: hold the parent weakly, so that a behaviour and its children
        (which refer to each other) are freed as soon as nobody keeps them, not by the
        garbage collector's cycle search (a switch would leave a dozen such cycles)."""
        parent = self._parent
        if parent is not None and not isinstance(parent, weakref.ref):
            self._parent = weakref.ref(parent)

    def _join(self, timeout: float | None = None) -> bool:
        """Wait until its ``run`` and clean-up are over (the thread goes back to the pool)."""
        return self._block_on(self._ended, timeout)

    def _block_on(self, event: _Flag, timeout_s: float | None) -> bool:
        """``event.wait(timeout_s)`` (wall time), telling the manager's clock that this
        thread waits for another worker (a virtual clock may then move time)."""
        manager = self._manager
        if manager is None:
            return event.wait(timeout_s)
        with manager.clock.blocked(event.is_set):
            return event.wait(timeout_s)

    def _after_run(self, error: BaseException | None) -> BaseException | None:
        """Behavior ends its children here; returns the error that decides the status."""
        return error

    def _pause_point(self, error: BaseException | None, *, ran: bool) -> bool:
        """Before the first ``run`` (``ran`` False) and after each: whether to call ``run``
        (again). Action waits out a pause here; a behaviour runs once."""
        return not ran

    def _finish(self, error: BaseException | None) -> bool:
        """Decide the status, apply the safe state, release what it holds, tell the parent
        and the manager. Returns True when the caller is to end the item's life; False for
        a STUCK item, whose life _end_of_life ends (here, or in the thread of its forced
        safe state when that returns later)."""
        with self._cond_lock:
            was_stuck = self._status is Status.STUCK
            if was_stuck:
                status = Status.STUCK
            elif error is None:
                status = Status.INTERRUPTED if self._interrupt_requested else Status.SUCCEEDED
            elif isinstance(error, Interrupted) and self._interrupt_requested:
                status = Status.INTERRUPTED
            else:
                status = Status.FAILED
            if status is Status.FAILED:
                self.__error = error
                self._traceback = "".join(traceback.format_exception(error))
            self._status = status
            if self.__ended_at is None:
                self.__ended_at = time.monotonic()
            self._holds -= 1
            last = self._holds == 0
            # (A pause already made it safe and nothing ran since: not twice.)
            safe_state = (not was_stuck and status is not Status.SUCCEEDED
                          and not self._pause_safe and self._HAS_SAFE_STATE)
            if safe_state and self._safe_done is None:
                self._safe_done = _Flag(self._cond, self._cond_lock)
        if was_stuck:
            # Its owner gave up on it; the forced safe state (if any) ran or runs elsewhere,
            # and whichever of the two returns last ends its life (_end_of_life).
            if last:
                self._end_of_life(stuck=True)
            return False
        manager = self._manager
        assert manager is not None
        stuck_now = False
        parent: Behavior | None = self._parent  # type: ignore[assignment]  # (strong while it lives)
        try:
            if safe_state:
                self._run_safe_state()
            if self._ros is not None or self._view is not None:
                self._destroy_io()
            self._release()
            if parent is not None and self._status is Status.FAILED:
                # Before _decided: whoever wait()s for us must find the failure recorded.
                parent._record_child_end(self)
            with self._cond_lock:
                self._decided._set_locked()
                # The owner may have given up on us while safe_state() hung; after
                # _decided it no longer can (_mark_stuck checks it under this lock).
                stuck_now = self._status is Status.STUCK
            if self._paused_done is not None:
                self._paused_done.set()  # a pause waiting for it: it has ended instead
            kind = EventKind.STUCK_RELEASED if stuck_now else EventKind.ENDED
            if manager.events.wants(kind):
                manager.events.emit(Event(kind, self.path, self._status.name, self.__error,
                                          {"elapsed_s": self.elapsed_s}))
            if parent is not None and parent._HOOKS_CHILD_END:
                parent._call_child_hook(self)
        finally:
            # (The manager keeps top-level behaviours and STUCK items; a child that never
            # was STUCK is none of its business.)
            if parent is None or stuck_now or manager._stuck:
                manager._node_ended(self, stuck_now)
        return True

    def _end_of_life(self, *, stuck: bool) -> None:
        """The last of run() and a forced safe_state() has returned: give back the type lock
        and the ROS entities, and tell the manager."""
        manager = self._manager
        assert manager is not None
        try:
            self._destroy_io()
            self._release()
            if self.parent is not None:
                self.parent._record_child_end(self)
            manager.events.emit(Event(EventKind.STUCK_RELEASED, self.path, self._status.name,
                                      self.error, {"elapsed_s": self.elapsed_s}))
            if self.parent is not None:
                self.parent._call_child_hook(self)
        finally:
            manager._node_ended(self, stuck)
            self._ended.set()
            self._tell_parent()
            self._let_go_of_parent()

    def _destroy_io(self) -> None:
        """Close what this item created: its ROS entities and blackboard subscriptions."""
        if self._ros is not None:
            self._ros.destroy_all()
        if self._view is not None:
            self._view.close()

    def _mark_stuck(self) -> None:
        """Its owner stopped waiting: force the safe state; the thread may end later.

        The forced ``safe_state()`` runs in a thread of its own, so that the owner (a
        switch, a shutdown, a preempting behaviour) goes on within its bound; whoever must
        see it applied waits for it with :meth:`_wait_safe_state`. The type lock stays held
        until both it and ``run`` have returned.

        Also for an item whose clean-up hangs (a ``safe_state()`` that blocks): its status
        was final already, it becomes STUCK so that nobody waits for it any longer, and its
        safe state is not called a second time.
        """
        manager = self._manager
        assert manager is not None
        with self._cond_lock:
            if self._decided.is_set() or self._status is Status.PENDING:
                return
            force_safe_state = self._status is Status.RUNNING and self._HAS_SAFE_STATE
            ended_as = None if self._status is Status.RUNNING else self._status
            self._status = Status.STUCK
            if self.__ended_at is None:
                self.__ended_at = time.monotonic()
            if force_safe_state:
                self._holds += 1
                self._safe_done = _Flag(self._cond, self._cond_lock)
            # Under our lock, so that _finish cannot remove it before it is added.
            manager._stuck_add(self)
        manager.events.emit(Event(EventKind.STUCK, self.path, Status.STUCK.name,
                                  detail=self._stuck_detail(ended_as)))
        if force_safe_state:
            try:
                manager._pool.submit(f"beehave:safe_state:{self.path}", self._forced_safe_state)
            except RuntimeError:  # the pool is shut down: a thread of its own, all the same
                threading.Thread(target=self._forced_safe_state, daemon=True,
                                 name=f"beehave:safe_state:{self.path}").start()
        self._decided.set()
        self._tell_parent()
        if self._paused_done is not None:
            self._paused_done.set()

    def _forced_safe_state(self) -> None:
        try:
            self._run_safe_state()
            # Whatever run() publishes from now on would undo the safe state.
            self._destroy_io()
        finally:
            with self._cond_lock:
                self._holds -= 1
                last = self._holds == 0
            if last:
                self._end_of_life(stuck=True)

    def _run_safe_state(self) -> None:
        """Call the safe state here, so that others can see it is under way (and where)."""
        done = self._safe_done  # (_finish makes it beside the status that calls for it)
        if done is None:
            with self._cond_lock:
                if self._safe_done is None:
                    self._safe_done = _Flag(self._cond, self._cond_lock)
                done = self._safe_done
        self._safe_thread_id = threading.get_ident()
        try:
            self._enter_safe_state()
        finally:
            self._safe_thread_id = None
            done.set()

    def _wait_safe_state(self, deadline: float) -> bool:
        """Wait until a safe state under way (if any) returned, at most until ``deadline``;
        report it (once) when it is overdue. True when none is pending."""
        done = self._safe_done
        if done is None or self._block_on(done, max(0.0, deadline - time.monotonic())):
            return True
        with self._cond_lock:
            report = not self._overdue_reported
            self._overdue_reported = True
        if report and self._manager is not None:
            self._manager.events.emit(Event(
                EventKind.SAFE_STATE_OVERDUE, self.path, self._status.name,
                detail={"running_s": round(time.monotonic() - (self.ended_at or 0.0), 3),
                        "at": self._where(self._safe_thread_id),
                        "action_type": getattr(self, "action_type", None)}))
        return False

    @property
    def safe_state_pending(self) -> bool:
        """True while its ``safe_state()`` runs (forced or not) and has not returned."""
        done = self._safe_done
        return done is not None and not done.is_set()

    def _stuck_detail(self, ended_as: Status | None) -> dict[str, Any]:
        manager = self._manager
        timeout_s = manager.stop_timeout_s if manager is not None else None
        since = self._interrupted_at
        if ended_as is None:
            ignored = "its interrupt"
        elif self.safe_state_pending:
            ignored = f"nothing: it ended {ended_as.name} but its safe_state() has not returned"
        else:
            ignored = f"nothing: it ended {ended_as.name} but its clean-up has not finished"
        return {
            "ignored": ignored,
            "for_s": None if since is None else round(time.monotonic() - since, 3),
            "stop_timeout_s": timeout_s,
            "at": self._where(self._thread_id),
        }

    def _where(self, ident: int | None) -> str | None:
        """Where thread ``ident`` is now (the user's line, and the call it is blocked in),
        for STUCK reports."""
        frame = sys._current_frames().get(ident) if ident is not None else None
        if frame is None:
            return None
        stack = traceback.extract_stack(frame, limit=40)
        innermost = stack[-1]
        # The innermost frame is often the standard library (a wait, a socket read): name
        # the user's line that called it too.
        for summary in reversed(stack):
            if not summary.filename.startswith(_STDLIB):
                break
        where = f"{summary.filename}:{summary.lineno} in {summary.name}"
        if summary is not innermost:
            where += f" (blocked in {innermost.name}, {Path(innermost.filename).name})"
        return where

    def _interrupt(self, deadline: float | None) -> None:
        if self._interrupt_requested:  # (it only ever turns true: no lock needed to see it)
            return
        with self._cond_lock:
            if self._interrupt_requested:
                return
            self._interrupt_requested = True
            self._interrupted_at = time.monotonic()
            self._stop_deadline = deadline
            if not self._HAS_CHILDREN:
                self._cond.notify_all()
            else:  # until its on_interrupt() hook has run (Behavior._after_run waits)
                self._hook_pending = True
        self._on_interrupt(deadline)

    def _on_interrupt(self, deadline: float | None) -> None:
        """Behavior passes the interrupt to its children, then wakes its own thread;
        Action wakes lock waiters."""

    def _enter_safe_state(self) -> None:
        """Action calls ``safe_state()``; a behaviour has no hardware of its own."""

    def _release(self) -> None:
        """Action releases its type lock (after its safe state)."""

    def _wake_reason(self) -> bool:
        return self._interrupt_requested or self._pause is _Pause.WIND_DOWN

    def _raise_pending(self) -> None:
        """Behavior raises ChildFailed here; called with ``_cond`` held."""

    @property
    def elapsed_s(self) -> float | None:
        started = self.__started_at
        if started is None:
            return None
        ended = self.__ended_at
        return (ended if ended is not None else time.monotonic()) - started

    def _snapshot(self) -> dict[str, Any]:
        started_wall = None
        if self.__started_at is not None:
            started_wall = time.time() - (time.monotonic() - self.__started_at)
        return {
            "name": self.name,
            "path": self.path,
            "class": type(self).__name__,
            "status": self._status.name,
            "started_at": started_wall,
            "elapsed_s": self.elapsed_s,
            "alive": self.alive,
            "error": None if self.error is None else repr(self.error),
        }


_reserve(Runnable)


def _timeout(seconds: float | None, owner: Runnable, call: str) -> float | None:
    """A timeout for the waits of threading: None for "no timeout" (None, inf, or more
    than threading can wait for). ``owner`` and ``call`` name it in the error."""
    if seconds is None:
        return None
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or math.isnan(seconds):
        raise ConfigError(f"{owner.path}: {call} takes a number of seconds (math.inf for no "
                          f"limit), got {seconds!r}")
    if seconds > threading.TIMEOUT_MAX:
        return None
    return max(0.0, float(seconds))
