"""The lifecycle that Behavior and Action share: one thread, one Status, cooperative interrupts.

This module is the driver; users subclass :class:`beehave.Behavior` or
:class:`beehave.Action` and never this class directly. Every status transition happens
here, under the object's own condition variable, so observers never see a half-made change.
"""

from __future__ import annotations

import abc
import threading
import time
import traceback
from typing import TYPE_CHECKING, Any, Self

from beehave.clock import WallClock
from beehave.errors import AlreadyStarted, ConfigError, Interrupted, ManagerShutdown
from beehave.events import Event, EventKind
from beehave.status import Status

if TYPE_CHECKING:
    from beehave.behavior import Behavior
    from beehave.blackboard import BlackboardView
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.ros.io import RosIO

_local = threading.local()
_WALL = WallClock()


def current() -> Runnable | None:
    """The behaviour or action whose thread is calling, or None."""
    return getattr(_local, "node", None)


class Runnable(abc.ABC):
    """A unit of work that runs :meth:`run` in a thread of its own, owned by its parent."""

    #: Shown in snapshots and events; defaults to the class name. Set it in ``__init__``.
    name: str
    #: ``run``'s return value once SUCCEEDED.
    result: Any
    #: The exception ``run`` raised (FAILED), with its ``__traceback__``.
    error: BaseException | None
    #: The behaviour that started it (None for a top-level behaviour).
    parent: Behavior | None
    started_at: float | None
    ended_at: float | None
    _manager: HighLevelBehaviorManager | None
    _status: Status
    _interrupt_requested: bool
    _stop_deadline: float | None
    _cond: threading.Condition
    _decided: threading.Event
    _started: bool
    _ros: RosIO | None
    _ended: threading.Event
    _traceback: str

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        # Runtime state lives here so that subclasses need not call super().__init__().
        self = super().__new__(cls)
        self.name = cls.__name__
        self.result = None
        self.error = None
        self.parent = None
        self.started_at = None  # time.monotonic()
        self.ended_at = None
        self._manager = None
        self._traceback = ""
        self._status = Status.PENDING
        self._interrupt_requested = False
        self._stop_deadline = None
        self._cond = threading.Condition(threading.Lock())
        self._decided = threading.Event()
        self._started = False
        self._ros = None
        self._ended = threading.Event()
        return self

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
    def interrupted(self) -> bool:
        """True once an interrupt was requested: wind down and return."""
        return self._interrupt_requested

    @property
    def path(self) -> str:
        """``parent/…/name``: where this sits in the running tree."""
        return self.name if self.parent is None else f"{self.parent.path}/{self.name}"

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
        if self._manager is None:
            raise ManagerShutdown(f"{self.name!r} is not started: it has no blackboard yet")
        return self._manager.blackboard_view

    @property
    def ros(self) -> RosIO:
        """Robot I/O over ROS 2 on the manager's node: ``publisher``, ``subscription``,
        ``client``, ``call``, ``timer`` and ``latest`` (see :mod:`beehave.ros.io`).
        Everything created here is destroyed when this behaviour or action ends, whatever
        its status — after ``safe_state()``, which may still use it."""
        manager = self.manager
        with self._cond:
            if self._ros is None:
                if manager.node is None:
                    raise ConfigError(
                        f"{self.path}: self.ros needs a ROS node: run the robot with "
                        f"`beehave run ROBOT.yaml`, or pass node= to HighLevelBehaviorManager")
                from beehave.ros.io import RosIO

                self._ros = RosIO(manager.node, owner=self.path, cond=self._cond,
                                  interrupted=lambda: self._interrupt_requested,
                                  clock=manager.clock)
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
        """Wait ``seconds``; return False at once when interrupted, True otherwise."""
        clock = self._manager.clock if self._manager is not None else _WALL
        with self._cond:
            clock.wait(self._cond, self._wake_reason, seconds)
            self._raise_pending()
            return not self._interrupt_requested

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the outcome is decided (any final status, STUCK included).

        Returns False on timeout. A behaviour that waits for its own child this way has
        seen the outcome, so a failure of that child is not raised again as ChildFailed.
        """
        done = self._decided.wait(timeout)
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
        with self._cond:
            if self._manager is not None:
                raise AlreadyStarted(
                    f"{type(self).__name__} {self.name!r} was already started "
                    f"(status {self._status.name}); create a new object for each run")
            self._manager = manager
            self.parent = parent

    def _detach(self) -> None:
        with self._cond:
            if self._status is Status.PENDING:
                self._manager = None
                self.parent = None

    def _start_thread(self) -> None:
        assert self._manager is not None
        with self._cond:
            self._started = True
            self._status = Status.RUNNING
            self.started_at = time.monotonic()
        self._manager._pool.submit(f"beehave:{self.path}", self._main)

    def _main(self) -> None:
        _local.node = self
        try:
            assert self._manager is not None
            self._manager.events.emit(Event(EventKind.STARTED, self.path, Status.RUNNING.name))
            error: BaseException | None = None
            try:
                self.result = self.run()
            except BaseException as exc:  # recorded on the handle and surfaced to the parent
                error = exc
            error = self._after_run(error)
            self._finish(error)
        finally:
            _local.node = None
            self._ended.set()

    def _join(self, timeout: float | None = None) -> bool:
        """Wait until its ``run`` and clean-up are over (the thread goes back to the pool)."""
        return self._ended.wait(timeout)

    def _after_run(self, error: BaseException | None) -> BaseException | None:
        """Behavior ends its children here; returns the error that decides the status."""
        return error

    def _finish(self, error: BaseException | None) -> None:
        with self._cond:
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
                self.error = error
                self._traceback = "".join(traceback.format_exception(error))
            self._status = status
            self.ended_at = time.monotonic()
        manager = self._manager
        assert manager is not None
        try:
            if not was_stuck and status is not Status.SUCCEEDED:
                self._enter_safe_state()
            if self._ros is not None:
                self._ros.destroy_all()
            self._release()
            with self._cond:
                # The owner may have given up on us while safe_state() hung.
                stuck_now = self._status is Status.STUCK
            if self.parent is not None:
                # Before _decided: whoever wait()s for us must find the failure recorded.
                self.parent._record_child_end(self)
            self._decided.set()
            kind = EventKind.STUCK_RELEASED if stuck_now else EventKind.ENDED
            manager.events.emit(Event(kind, self.path, self._status.name, self.error,
                                      {"elapsed_s": self.elapsed_s}))
            if self.parent is not None:
                self.parent._call_child_hook(self)
        finally:
            manager._node_ended(self, was_stuck or self._status is Status.STUCK)

    def _mark_stuck(self) -> None:
        """Its owner stopped waiting: force the safe state; the thread may end later.

        Also for an item whose clean-up hangs (a ``safe_state()`` that blocks): its status
        was final already, it becomes STUCK so that nobody waits for it any longer, and its
        safe state is not called a second time.
        """
        assert self._manager is not None
        with self._cond:
            if self._decided.is_set() or self._status is Status.PENDING:
                return
            force_safe_state = self._status is Status.RUNNING
            self._status = Status.STUCK
            self.ended_at = self.ended_at or time.monotonic()
            # Under our lock, so that _finish cannot remove it before it is added.
            self._manager._stuck_add(self)
        self._manager.events.emit(Event(EventKind.STUCK, self.path, Status.STUCK.name))
        if force_safe_state:
            self._enter_safe_state()
            if self._ros is not None:
                # Whatever run() publishes from now on would undo the safe state.
                self._ros.destroy_all()
        self._decided.set()

    def _interrupt(self, deadline: float | None) -> None:
        with self._cond:
            if self._interrupt_requested:
                return
            self._interrupt_requested = True
            self._stop_deadline = deadline
            self._cond.notify_all()
        self._on_interrupt(deadline)

    def _on_interrupt(self, deadline: float | None) -> None:
        """Behavior passes the interrupt to its children; Action wakes lock waiters."""

    def _enter_safe_state(self) -> None:
        """Action calls ``safe_state()``; a behaviour has no hardware of its own."""

    def _release(self) -> None:
        """Action releases its type lock (after its safe state)."""

    def _wake_reason(self) -> bool:
        return self._interrupt_requested

    def _raise_pending(self) -> None:
        """Behavior raises ChildFailed here; called with ``_cond`` held."""

    def _wait_decided(self, deadline: float) -> bool:
        return self._decided.wait(max(0.0, deadline - time.monotonic()))

    @property
    def elapsed_s(self) -> float | None:
        if self.started_at is None:
            return None
        end = self.ended_at if self.ended_at is not None else time.monotonic()
        return end - self.started_at

    def _snapshot(self) -> dict[str, Any]:
        started_wall = None
        if self.started_at is not None:
            started_wall = time.time() - (time.monotonic() - self.started_at)
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
