"""Logic: a small reactive coroutine of the low level (LED colour, display symbol …).

Subclass it and write ``async def run(self)``::

    class LedLogic(Logic):
        def __init__(self, threshold: float = 20) -> None:   # params from register()
            self.threshold = threshold

        async def run(self) -> None:
            leds = await self.hal("debug")
            async for change in self.blackboard.watch("battery/percentage"):
                leds.set_leds("red" if change.value < self.threshold else "green")

Inside ``run``: ``self.blackboard`` (writes as ``"logic:<path>"``), ``await self.hal(name)``
and ``self.start_logic(other)``. ``super().__init__()`` is not needed.

Structured concurrency: a sub-logic belongs to the logic that started it and never outlives
it. When a logic's ``run`` ends — returned, raised or cancelled — its sub-logics are
cancelled and awaited before it counts as ended; then its blackboard subscriptions are
closed and its HAL references given back. A sub-logic that fails cancels its parent, which
then ends FAILED with :class:`~beehave.errors.ChildFailed` (catch errors inside the
sub-logic if it should not take its parent down). Cancellation arrives as
``asyncio.CancelledError`` inside ``run``: use ``try/finally`` for cleanup, and let it
propagate.

The logic object is its own handle: ``.name``, ``.path``, ``.status``, ``.error``,
``.result``, ``.children``, ``await .wait()``.
"""

from __future__ import annotations

import abc
import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Self, TypeVar, overload

from beehave.attach import attached
from beehave.blackboard import Blackboard, BlackboardClient
from beehave.errors import AlreadyStarted, BeehaveError, ChildFailed, HALError
from beehave.events import Event, EventBus, EventKind
from beehave.hal import HAL, HALManager, wait_bounded_all
from beehave.status import Status
from beehave.substitutes import Substitutions

log = logging.getLogger(__name__)

__all__ = ["Logic"]

L = TypeVar("L", bound="Logic")
H = TypeVar("H", bound=HAL)


@dataclass
class Runtime:
    """What a running logic reaches through its manager."""

    blackboard: Blackboard
    hals: HALManager
    events: EventBus
    stop_timeout_s: float = 2.0
    stuck: set[Logic] = field(default_factory=set)
    """Logics that ignored their cancellation; the manager cancels them again at shutdown."""
    handover: object | None = None
    """While set, a top-level logic that ends hands its HAL references (and those of its
    sub-logics) to this owner instead of releasing them, so the next top-level logic finds
    the HALs it shares with the old one still loaded; the manager releases them later."""
    on_handover: Callable[[object], None] | None = None
    """Called with ``handover`` after each reference handed to it: the manager (re)starts
    the grace period then, also for a sub-logic that ends late."""
    substitutes: Substitutions = field(default_factory=Substitutions)
    """Substitution rules for the logics started from now on (tests)."""


class Logic(abc.ABC):
    """Base class of the low level's reactive coroutines; override :meth:`run`."""

    name: str
    """The registered name (top level) or the name given to ``start_logic`` (default: the
    class name)."""
    error: BaseException | None
    """What ``run`` raised (FAILED), with its traceback."""
    result: Any
    """What ``run`` returned (SUCCEEDED)."""
    parent: Logic | None
    started_at: float | None
    ended_at: float | None
    _status: Status
    _runtime: Runtime | None
    _task: asyncio.Task[None] | None
    _children: list[Logic]
    _client: BlackboardClient | None
    _hal_names: list[str]
    _child_failure: Logic | None
    _ending: bool

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        # Runtime state lives here so subclasses need not call super().__init__().
        self = super().__new__(cls)
        self.name = cls.__name__
        self.error = None
        self.result = None
        self.parent = None
        self.started_at = None
        self.ended_at = None
        self._status = Status.PENDING
        self._runtime = None
        self._task = None
        self._children = []
        self._client = None
        self._hal_names = []
        self._child_failure = None
        self._ending = False
        return self

    @abc.abstractmethod
    async def run(self) -> Any:
        """The logic itself. Called once, as a task in the low level's loop.

        React to blackboard changes, drive HALs, start sub-logics. Returning ends the logic
        (SUCCEEDED, ``.result`` holds the value); raising fails it (``.error``); being
        cancelled (switch, parent ended) ends it INTERRUPTED.
        """

    # -- inside run ----------------------------------------------------------------------

    @property
    def blackboard(self) -> BlackboardClient:
        """The blackboard, writing as ``"logic:<path>"``; available while the logic runs."""
        if self._client is None:
            raise BeehaveError(f"logic {self.name!r} is not running: self.blackboard is "
                               "available inside run()")
        return self._client

    @overload
    async def hal(self, name: str) -> HAL: ...

    @overload
    async def hal(self, name: str, kind: type[H]) -> H: ...

    async def hal(self, name: str, kind: type[HAL] | None = None) -> HAL:
        """Load HAL ``name`` (shared with other logics) and return it; this logic holds a
        reference until it ends. ``kind`` checks (and types) the class: ``await
        self.hal("debug", DebugHAL)``."""
        runtime = self._require_runtime("hal()")
        hal = await runtime.hals.load(name, owner=self)
        if name not in self._hal_names:
            self._hal_names.append(name)
        if kind is not None and not isinstance(hal, kind):
            raise HALError(f"HAL {name!r} is a {type(hal).__qualname__}, not a "
                           f"{kind.__qualname__} (logic {self.path!r})")
        return hal

    def start_logic(self, logic: L, *, name: str | None = None) -> L:
        """Start ``logic`` as a sub-logic of this one and return it (its own handle).

        It runs concurrently and is cancelled when this logic ends; if it fails, this logic
        is cancelled and fails with :class:`~beehave.errors.ChildFailed`.
        """
        runtime = self._require_runtime("start_logic()")
        if self._ending:
            raise BeehaveError(f"logic {self.path!r} is ending; cannot start sub-logic "
                               f"{name or type(logic).__name__!r}")
        logic._start(runtime, parent=self, name=name)
        return logic

    @property
    def fleet(self) -> Any:
        """The shared state of every agent of the fleet (a
        :class:`beehave.agents.fleet.Fleet`), once one is attached to this low level;
        available inside run()."""
        from beehave.behavior import NO_FLEET

        return attached(self._require_runtime("self.fleet").blackboard, "fleet",
                        missing=NO_FLEET)

    def _require_runtime(self, what: str) -> Runtime:
        if self._runtime is None or self._status is not Status.RUNNING:
            raise BeehaveError(f"logic {self.name!r} is not running ({self._status.name}); "
                               f"{what} works inside run()")
        return self._runtime

    # -- the handle ----------------------------------------------------------------------

    @property
    def status(self) -> Status:
        return self._status

    @property
    def path(self) -> str:
        """``parent/child`` names from the top-level logic down."""
        return self.name if self.parent is None else f"{self.parent.path}/{self.name}"

    @property
    def children(self) -> tuple[Logic, ...]:
        """The sub-logics that have not ended yet."""
        return tuple(self._children)

    @property
    def task(self) -> asyncio.Task[None] | None:
        return self._task

    async def wait(self) -> Status:
        """Wait until this logic has ended (sub-logics included); return its status.

        Never raises the logic's error: read ``.error``.
        """
        if self._task is None:
            raise BeehaveError(f"logic {self.name!r} was never started")
        await asyncio.wait({self._task})
        return self._status

    def snapshot(self) -> dict[str, Any]:
        """``{name, type, status, error, duration_s, children}`` of this logic and below."""
        end = self.ended_at if self.ended_at is not None else time.monotonic()
        return {"name": self.name, "type": type(self).__qualname__,
                "status": self._status.name,
                "error": None if self.error is None else repr(self.error),
                "duration_s": None if self.started_at is None
                else round(end - self.started_at, 6),
                "children": [c.snapshot() for c in self._children]}

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.path!r} {self._status.name}>"

    # -- the driver (the only place that changes status) ---------------------------------

    def _start(self, runtime: Runtime, *, parent: Logic | None, name: str | None) -> None:
        if self._task is not None or self._status is not Status.PENDING:
            raise AlreadyStarted(f"logic {self.path!r} was already started; create a new "
                                 f"{type(self).__name__}")
        if name is not None:
            self.name = name
        self.parent = parent
        self._runtime = runtime
        self._client = runtime.blackboard.client(f"logic:{self.path}")
        if parent is not None:
            parent._children.append(self)
        runtime.substitutes.apply(self, path=self.path)
        self._status = Status.RUNNING
        self.started_at = time.monotonic()
        self._task = asyncio.get_running_loop().create_task(self._drive(),
                                                            name=f"logic:{self.path}")
        runtime.events.emit(Event(EventKind.STARTED, self.path, Status.RUNNING.name))

    async def _drive(self) -> None:
        runtime = self._runtime
        assert runtime is not None
        outcome = Status.SUCCEEDED
        error: BaseException | None = None
        cancelled = False
        try:
            try:
                self.result = await self.run()
            finally:
                self._ending = True
                await stop_logics(self._children, runtime)
        except asyncio.CancelledError:
            cancelled = True
            if self._child_failure is not None:
                outcome, error = Status.FAILED, _child_failed(self._child_failure)
            else:
                outcome = Status.INTERRUPTED
        except Exception as exc:
            outcome, error = Status.FAILED, exc
        finally:
            await self._release(runtime)
            self._finish(outcome, error, runtime)
        if cancelled and self._child_failure is None:
            raise asyncio.CancelledError

    async def _release(self, runtime: Runtime) -> None:
        if self._client is not None:
            self._client.close()
        root = self
        while root.parent is not None:
            root = root.parent
        token = runtime.handover
        hand_over = token is not None and root._ending
        for name in self._hal_names:
            if hand_over and runtime.hals.transfer(name, owner=self, to=token):
                if runtime.on_handover is not None:
                    runtime.on_handover(token)
                continue
            try:
                # Not waiting for the unload: a HAL's slow stop is the HAL's (bounded and
                # reported as its own), not this logic's, which obeyed.
                await runtime.hals.release(name, owner=self, wait=False)
            except asyncio.CancelledError:
                continue  # keep releasing
        self._hal_names.clear()

    def _finish(self, outcome: Status, error: BaseException | None, runtime: Runtime) -> None:
        if self._status is Status.STUCK:  # gave up on earlier; keep what was reported
            self._status = outcome if outcome is not Status.SUCCEEDED else Status.INTERRUPTED
        else:
            self._status = outcome
        self.error = error
        self.ended_at = time.monotonic()
        runtime.stuck.discard(self)
        parent = self.parent
        if parent is not None:
            try:
                parent._children.remove(self)
            except ValueError:
                pass
            if outcome is Status.FAILED and not parent._ending and parent._task is not None \
                    and not parent._task.done() and parent._child_failure is None:
                parent._child_failure = self
                parent._task.cancel()
        runtime.events.emit(Event(EventKind.ENDED, self.path, outcome.name, error,
                                  {"duration_s": round(self.ended_at - (self.started_at or 0),
                                                       6)}))


def _child_failed(child: Logic) -> ChildFailed:
    err = ChildFailed(child)
    err.__cause__ = child.error
    return err


async def stop_logics(logics: list[Logic], runtime: Runtime) -> None:
    """Cancel ``logics`` and wait until they have ended, at most ``stop_timeout_s``; those
    that ignore the cancellation are marked STUCK (reported, re-cancelled at shutdown)."""
    tasks = {lg._task: lg for lg in list(logics) if lg._task is not None and not lg._task.done()}
    if not tasks:
        return
    for task in tasks:
        task.cancel()
    cancelled = False
    try:
        await wait_bounded_all(set(tasks), runtime.stop_timeout_s)
    except asyncio.CancelledError:
        cancelled = True  # raised again once the stuck ones are reported
    for task in [t for t in tasks if not t.done()]:
        logic = tasks[task]
        logic._status = Status.STUCK
        runtime.stuck.add(logic)
        runtime.events.emit(Event(EventKind.STUCK, logic.path, Status.STUCK.name,
                                  detail={"stop_timeout_s": runtime.stop_timeout_s}))
    if cancelled:
        raise asyncio.CancelledError
