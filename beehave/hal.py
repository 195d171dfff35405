"""HAL plugins: what the low level knows about hardware, and the manager that loads them.

A HAL (hardware abstraction layer) keeps blackboard entries current (battery, buttons,
pose …) and offers methods that logics call to drive the hardware (LEDs, display …)::

    class BatteryHAL(HAL):
        name = "battery"

        async def run(self) -> None:          # optional: keep the blackboard current
            while True:
                self.blackboard.set("battery/percentage", read_adc())
                await asyncio.sleep(0.5)

        def safe_state(self) -> None:         # optional: leave the hardware predictable
            ...

Logics ask for a HAL by name (``await self.hal("battery")``); the :class:`HALManager`
loads it on first request, shares the one instance among all logics, and stops it (then
calls ``safe_state()``) when the last logic using it ends. A ``run()`` that raises is
restarted with bounded exponential backoff; meanwhile the HAL's entries read as stale.

HALs are found by the name given to :meth:`HALManager.register`, or through the
``beehave.hals`` entry-point group, so a third-party package can add one::

    [project.entry-points."beehave.hals"]
    battery = "my_robot.hals:BatteryHAL"
"""

from __future__ import annotations

import asyncio
import importlib.metadata
import inspect
import logging
import math
import threading
import time
from collections.abc import Awaitable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self, TypeVar

from beehave.blackboard import Blackboard, BlackboardClient
from beehave.errors import ConfigError, HALError, InvalidParameters, ManagerShutdown, UnknownHAL
from beehave.events import Event, EventBus, EventKind
from beehave.status import Status

log = logging.getLogger(__name__)

__all__ = ["HAL", "HALManager", "ENTRY_POINT_GROUP", "MAX_DURATION_S", "check_duration_s"]

ENTRY_POINT_GROUP = "beehave.hals"

MAX_DURATION_S = 86400.0
"""The longest duration :func:`check_duration_s` accepts: a day (as the high level's
``stop_timeout_s``)."""

H = TypeVar("H", bound="HAL")


class HAL:
    """Base class of HAL plugins. Nothing must be overridden; set the ``name``.

    The manager creates the instance (``self.blackboard`` is already there in
    ``__init__``, which receives the parameters given to :meth:`HALManager.register`) and
    runs, in this order: :meth:`on_load`, :meth:`run` (as a supervised task), and at unload
    :meth:`safe_state`. Calling ``super().__init__()`` is not needed.
    """

    name: ClassVar[str] = ""
    """The name logics ask for (``await self.hal("debug")``)."""

    blackboard: BlackboardClient
    """The blackboard, writing as ``"hal:<name>"``."""
    status: Status
    """RUNNING while loaded and its ``run`` is healthy; FAILED between a crash and its
    restart; INTERRUPTED once unloaded."""
    error: BaseException | None
    """The last exception ``run`` raised (kept after a restart)."""
    restarts: int
    """How many times ``run`` was restarted after a crash."""
    node: Any
    """The low level's ROS 2 node when it runs under ROS (``beehave run``), else None."""
    events: EventBus
    """The low level's event bus: report what goes wrong outside ``run`` here."""

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        self = super().__new__(cls)
        self.status = Status.PENDING
        self.error = None
        self.restarts = 0
        self.node = None
        return self

    async def on_load(self) -> None:
        """Called once when the HAL is loaded, before any logic gets it: open devices,
        publish the initial state. Raising here makes the load fail with :class:`HALError`."""

    async def run(self) -> None:
        """Keep the blackboard current (optional). Runs as a task while the HAL is loaded;
        cancelled at unload. If it raises, it is called again after a backoff, on the same
        instance, so it must be restartable. Returning ends it for good (the HAL stays
        loaded)."""

    def safe_state(self) -> None | Awaitable[None]:
        """Leave the hardware predictable (LEDs off, motors stopped). Called once when the
        HAL is unloaded; may be a coroutine function."""
        return None

    def on_unload(self) -> None:
        """Release what :meth:`on_load` acquired (devices, ROS entities). Called once at
        unload, after :meth:`safe_state` (which may still use them)."""


@dataclass
class _Loaded:
    hal: HAL
    owners: list[object] = field(default_factory=list)
    ready: asyncio.Task[None] | None = None
    task: asyncio.Task[None] | None = None
    unloading: asyncio.Task[None] | None = None
    loaded_at: float = field(default_factory=time.monotonic)
    load_began: bool = False
    """``on_load`` was entered: from then on ``safe_state`` is owed, whatever happens."""
    abandoned: bool = False
    """Unloaded while ``on_load`` still ran and ignored its cancellation."""
    winding: bool = False
    """``on_load`` ended (cancelled or failed) and ``_start`` is winding the HAL down."""


_ANON = object()


def claim_safe_state(hal: HAL) -> bool:
    """True exactly once per HAL instance: whoever gets True runs ``safe_state``.

    The loop's unload and the shutdown escalation of a blocked loop (another thread) may
    both try; the hardware must see one safe state, not two, and never none.
    """
    with _SAFE_STATE_LOCK:
        if getattr(hal, "_beehave_safe_state_claimed", False):
            return False
        hal._beehave_safe_state_claimed = True  # type: ignore[attr-defined]
        hal._beehave_safe_state_done = threading.Event()  # type: ignore[attr-defined]
        return True


def _safe_state_done(hal: HAL) -> threading.Event | None:
    """Set once the claimed ``safe_state`` has returned (None: nobody claimed it yet)."""
    done: threading.Event | None = getattr(hal, "_beehave_safe_state_done", None)
    return done


_SAFE_STATE_LOCK = threading.Lock()


class HALManager:
    """Loads HAL plugins on request, shares them, restarts crashed ones, unloads unused ones.

    ``backoff_initial_s`` is the first restart delay after a crash; it doubles per crash up
    to ``backoff_max_s`` and starts again from the beginning once ``run`` stayed up for
    ``backoff_max_s``. Loading and releasing happen in the low level's loop.

    ``stop_timeout_s`` bounds each step of an unload: a cancelled ``run`` (or ``on_load``)
    that has not ended by then is reported STUCK (event) and the unload goes on --
    ``safe_state`` and ``on_unload`` run anyway, and the stuck task is cancelled again at
    :meth:`close`. An ``async`` ``safe_state`` gets the same bound.
    """

    def __init__(self, blackboard: Blackboard | None = None, *, events: EventBus | None = None,
                 backoff_initial_s: float = 0.1, backoff_max_s: float = 5.0,
                 stop_timeout_s: float = 2.0) -> None:
        self.blackboard = blackboard if blackboard is not None else Blackboard()
        self.events = events if events is not None else EventBus(log)
        self.backoff_initial_s = check_duration_s("backoff_initial_s", backoff_initial_s)
        self.backoff_max_s = check_duration_s("backoff_max_s", backoff_max_s)
        self.stop_timeout_s = check_duration_s("stop_timeout_s", stop_timeout_s)
        self._registry: dict[str, tuple[type[HAL], dict[str, Any]]] = {}
        self._entry_points: dict[str, importlib.metadata.EntryPoint] | None = None
        self._loaded: dict[str, _Loaded] = {}
        self._unloading: set[asyncio.Task[None]] = set()
        # Entries on their way out (no longer in _loaded, safe_state maybe not run yet): the
        # escalation of a blocked loop forces their safe states too, and a new load of the
        # same name waits until the old instance is gone.
        self._leaving: dict[int, tuple[str, _Loaded]] = {}
        self._stuck: dict[asyncio.Task[None], str] = {}
        self._closed = False
        #: Handed to every HAL as ``hal.node`` (the low level's ROS node, or None).
        self.node: Any = None

    # -- registry ------------------------------------------------------------------------

    def register(self, hal_cls: type[HAL], *, name: str | None = None, **params: Any) -> None:
        """Make ``hal_cls`` loadable under ``name`` (default: its ``name`` attribute);
        ``params`` go to its constructor. Registering replaces an entry point of that name."""
        if not (isinstance(hal_cls, type) and issubclass(hal_cls, HAL)):
            raise HALError(f"{hal_cls!r} is not a HAL subclass")
        hal_name = name or hal_cls.name
        if not hal_name:
            raise HALError(f"HAL class {hal_cls.__qualname__} has no name; set the class "
                           "attribute `name` or pass name=")
        check_params(hal_cls, hal_name, params)
        self._registry[hal_name] = (hal_cls, dict(params))

    def _discover(self) -> dict[str, importlib.metadata.EntryPoint]:
        if self._entry_points is None:
            eps = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)
            self._entry_points = {ep.name: ep for ep in eps}
        return self._entry_points

    def available(self) -> list[str]:
        """Every HAL name that can be loaded: registered ones and entry points."""
        return sorted({*self._registry, *self._discover()})

    def resolve(self, name: str) -> tuple[type[HAL], dict[str, Any]]:
        """The class and parameters ``name`` stands for; imports an entry point if needed."""
        if name in self._registry:
            return self._registry[name]
        ep = self._discover().get(name)
        if ep is None:
            raise UnknownHAL(name, self.available())
        try:
            cls = ep.load()
        except Exception as exc:
            raise HALError(f"HAL {name!r}: cannot import entry point {ep.value!r} of group "
                           f"{ENTRY_POINT_GROUP!r}: {exc!r}") from exc
        if not (isinstance(cls, type) and issubclass(cls, HAL)):
            raise HALError(f"HAL {name!r}: entry point {ep.value!r} is {cls!r}, not a HAL "
                           "subclass")
        self._registry[name] = (cls, {})
        return self._registry[name]

    # -- loading -------------------------------------------------------------------------

    @property
    def loaded(self) -> dict[str, HAL]:
        """The HALs that are loaded now, by name."""
        return {n: e.hal for n, e in self._loaded.items() if e.ready is None}

    def refs(self, name: str) -> int:
        """How many references hold ``name`` loaded (0 when it is not loaded)."""
        entry = self._loaded.get(name)
        return 0 if entry is None else len(entry.owners)

    def holds(self, name: str, owner: object) -> bool:
        """Whether ``owner`` holds a reference to HAL ``name``."""
        entry = self._loaded.get(name)
        return entry is not None and any(o is owner for o in entry.owners)

    async def load(self, name: str, *, owner: object | None = None) -> HAL:
        """Load HAL ``name`` if needed and return the shared instance.

        Each call takes one reference for ``owner``; one owner holds at most one reference
        (a logic asking twice gets the same instance). Without an owner every call takes a
        reference of its own; give it back with :meth:`release`. Raises
        :class:`~beehave.errors.UnknownHAL` listing the available names.
        """
        if self._closed:
            raise ManagerShutdown(f"HAL manager is shut down; cannot load HAL {name!r}")
        entry = self._loaded.get(name)
        while entry is None and (previous := self._unload_of(name)) is not None:
            # The old instance first gets its safe_state and on_unload (bounded), so the
            # hardware never sees the new on_load before the old stop.
            await wait_ignoring_cancel(previous)
            if self._closed:
                raise ManagerShutdown(f"HAL manager is shut down; cannot load HAL {name!r}")
            entry = self._loaded.get(name)
        if entry is None:
            cls, params = self.resolve(name)
            hal = cls.__new__(cls)
            entry = _Loaded(hal)
            self._loaded[name] = entry
            entry.ready = asyncio.get_running_loop().create_task(
                self._start(name, entry, cls, params), name=f"hal:{name}:load")
        key = _ANON if owner is None else owner
        if key is _ANON or not any(o is key for o in entry.owners):
            entry.owners.append(key)
        try:
            if entry.ready is not None:
                await asyncio.shield(entry.ready)
        except BaseException:
            await self.release(name, owner=owner)
            raise
        return entry.hal

    async def _start(self, name: str, entry: _Loaded, cls: type[HAL],
                     params: dict[str, Any]) -> None:
        hal = entry.hal
        client = self.blackboard.client(f"hal:{name}")
        hal.blackboard = client
        hal.node = self.node
        hal.events = self.events
        try:
            hal.__init__(**params)  # type: ignore[misc]  # __new__ ran above, on purpose
        except Exception as exc:
            self._forget(name, entry)
            client.close()
            hal.status = Status.FAILED
            hal.error = exc
            self.events.emit(Event(EventKind.ENDED, f"hal:{name}", Status.FAILED.name, exc))
            raise HALError(f"HAL {name!r} failed to load: {exc!r}") from exc
        entry.load_began = True
        try:
            await hal.on_load()
        except BaseException as exc:  # also cancellation: the hardware may be half set up
            self._forget(name, entry)
            failed = isinstance(exc, Exception)
            hal.status = Status.FAILED if failed else Status.INTERRUPTED
            if failed:
                hal.error = exc
            if not entry.abandoned:  # else the unload that gave up on us did this already
                entry.winding = True  # unload() now waits for us: _wind_down is bounded
                self._leave(name, entry)
                try:
                    await self._wind_down(name, entry)
                finally:
                    self._left(entry)
                self.events.emit(Event(EventKind.ENDED, f"hal:{name}", hal.status.name,
                                       exc if failed else None, {"phase": "on_load"}))
            if failed:
                raise HALError(f"HAL {name!r} failed to load: {exc!r}") from exc
            raise
        if entry.abandoned:  # on_load ignored its cancellation; safe_state already ran
            hal.status = Status.INTERRUPTED
            return
        hal.status = Status.RUNNING
        entry.task = asyncio.get_running_loop().create_task(self._supervise(name, hal),
                                                            name=f"hal:{name}")
        entry.ready = None
        self.events.emit(Event(EventKind.STARTED, f"hal:{name}", Status.RUNNING.name))
        if not entry.owners:  # everyone who asked for it let go while it was loading
            await self._unload(name, entry)

    def _forget(self, name: str, entry: _Loaded) -> None:
        if self._loaded.get(name) is entry:
            del self._loaded[name]

    def _unload_of(self, name: str) -> asyncio.Task[None] | None:
        for leaving_name, entry in list(self._leaving.values()):
            task = entry.unloading
            if leaving_name == name and task is not None and not task.done():
                return task
        return None

    def _leave(self, name: str, entry: _Loaded) -> None:
        self._forget(name, entry)
        self._leaving[id(entry)] = (name, entry)

    def _left(self, entry: _Loaded) -> None:
        self._leaving.pop(id(entry), None)

    async def _supervise(self, name: str, hal: HAL) -> None:
        delay = self.backoff_initial_s
        writer = f"hal:{name}"
        while True:
            started = time.monotonic()
            try:
                await hal.run()
                return
            except Exception as exc:
                hal.status = Status.FAILED
                hal.error = exc
                stale = self.blackboard.mark_stale(writer=writer)
                if time.monotonic() - started >= self.backoff_max_s:
                    delay = self.backoff_initial_s
                self.events.emit(Event(EventKind.ENDED, writer, Status.FAILED.name, exc,
                                       {"restart_in_s": delay, "stale_keys": stale}))
            await asyncio.sleep(delay)
            hal.restarts += 1
            hal.status = Status.RUNNING
            self.events.emit(Event(EventKind.RESTARTED, writer, Status.RUNNING.name, hal.error,
                                   {"restarts": hal.restarts, "after_s": delay}))
            delay = min(delay * 2, self.backoff_max_s)

    async def release(self, name: str, *, owner: object | None = None,
                      wait: bool = True) -> None:
        """Give back ``owner``'s reference; the last one unloads the HAL (cancels ``run``,
        calls ``safe_state()``, marks its entries stale). Unknown references are ignored.

        ``wait=False`` starts the unload without waiting for it (a logic that ends does
        not count the HAL's stop against its own ``stop_timeout_s``); :meth:`close` and a
        new :meth:`load` of the same name still wait for it."""
        entry = self._loaded.get(name)
        if entry is None:
            return
        key = _ANON if owner is None else owner
        for i, o in enumerate(entry.owners):
            if o is key:
                del entry.owners[i]
                break
        else:
            return
        if not entry.owners and entry.ready is None:
            await self._unload(name, entry, wait=wait)

    def transfer(self, name: str, *, owner: object, to: object) -> bool:
        """Hand ``owner``'s reference to HAL ``name`` over to ``to`` without unloading it
        (``to`` ends up holding one reference); False when ``owner`` held none."""
        entry = self._loaded.get(name)
        if entry is None:
            return False
        for i, o in enumerate(entry.owners):
            if o is owner:
                if any(x is to for x in entry.owners):
                    del entry.owners[i]
                else:
                    entry.owners[i] = to
                return True
        return False

    async def _unload(self, name: str, entry: _Loaded, *, wait: bool = True) -> None:
        # The unload is a task of its own, started once: a caller that is cancelled while
        # it waits (a logic stopped twice) must not cut it short, or safe_state would
        # never run and the HAL's task would be destroyed while pending.
        self._leave(name, entry)
        if entry.unloading is None:
            task = asyncio.get_running_loop().create_task(self._unload_now(name, entry),
                                                          name=f"hal:{name}:unload")
            entry.unloading = task
            self._unloading.add(task)

            def unloaded(done: asyncio.Task[None]) -> None:
                self._unloading.discard(done)
                self._left(entry)

            task.add_done_callback(unloaded)
        if wait:
            await wait_ignoring_cancel(entry.unloading)

    async def _unload_now(self, name: str, entry: _Loaded) -> None:
        hal = entry.hal
        writer = f"hal:{name}"
        task = entry.task
        stuck = False
        if task is not None and not task.done():
            task.cancel()
            if not await _wait_bounded(task, self.stop_timeout_s):
                stuck = True
                self._mark_stuck(name, hal, task, "run")
        await self._wind_down(name, entry)
        if not stuck:
            hal.status = Status.INTERRUPTED
        self.events.emit(Event(EventKind.ENDED, writer, hal.status.name))

    def _mark_stuck(self, name: str, hal: HAL, task: asyncio.Task[None], phase: str) -> None:
        hal.status = Status.STUCK
        self._stuck[task] = name

        def ended(_: asyncio.Task[None]) -> None:
            self._stuck.pop(task, None)
            if hal.status is Status.STUCK:
                hal.status = Status.INTERRUPTED

        task.add_done_callback(ended)
        self.events.emit(Event(EventKind.STUCK, f"hal:{name}", Status.STUCK.name,
                               detail={"phase": phase, "stop_timeout_s": self.stop_timeout_s}))
        log.warning("HAL %r: %s() ignored its cancellation for %.3f s; unloading it anyway "
                    "(safe_state runs now, the task is cancelled again at shutdown)",
                    name, phase, self.stop_timeout_s)

    async def _wind_down(self, name: str, entry: _Loaded) -> None:
        """safe_state (once per instance, bounded), on_unload, then the entries go stale."""
        hal = entry.hal
        writer = f"hal:{name}"
        if entry.load_began and claim_safe_state(hal):
            began = time.monotonic()
            try:
                result = hal.safe_state()
                if inspect.isawaitable(result):
                    await _bounded(result, self.stop_timeout_s,
                                   f"HAL {name!r}: safe_state() did not finish within "
                                   f"stop_timeout_s={self.stop_timeout_s} s")
            except Exception as exc:
                hal.error = exc
                self.events.emit(Event(EventKind.SAFE_STATE_FAILED, writer, hal.status.name,
                                       exc))
            else:
                self.events.emit(Event(EventKind.SAFE_STATE_RAN, writer, hal.status.name,
                                       detail={"took_s": round(time.monotonic() - began, 6)}))
            finally:
                _set_done(hal)
        elif entry.load_began:
            # Claimed elsewhere: the escalation of a blocked loop forced it from another
            # thread. on_unload may close what safe_state still uses: wait (bounded).
            done = _safe_state_done(hal)
            deadline = time.monotonic() + self.stop_timeout_s
            while done is not None and not done.is_set() and time.monotonic() < deadline:
                await asyncio.sleep(0.005)
        if entry.load_began:
            try:
                hal.on_unload()
            except Exception as exc:
                hal.error = exc
                self.events.emit(Event(EventKind.ENDED, writer, Status.FAILED.name, exc,
                                       {"phase": "on_unload"}))
        hal.blackboard.close()
        self.blackboard.mark_stale(writer=writer)

    async def unload(self, name: str) -> None:
        """Unload HAL ``name`` now, whoever holds it (used at shutdown). A HAL that is still
        loading has its ``on_load`` cancelled (bounded by ``stop_timeout_s``)."""
        entry = self._loaded.get(name)
        if entry is None:
            return
        entry.owners.clear()
        ready = entry.ready
        if ready is not None:
            ready.cancel()
            if await _wait_bounded(ready, self.stop_timeout_s):
                return  # _start wound it down
            if entry.winding:
                # on_load obeyed; _start is in safe_state/on_unload, which are bounded
                # themselves. Cutting that short would leave the hardware half stopped.
                await wait_ignoring_cancel(ready)
                return
            entry.abandoned = True
            self._leave(name, entry)
            try:
                self._mark_stuck(name, entry.hal, ready, "on_load")
                await self._wind_down(name, entry)
            finally:
                self._left(entry)
            self.events.emit(Event(EventKind.ENDED, f"hal:{name}", Status.STUCK.name))
            return
        await self._unload(name, entry)

    async def close(self) -> None:
        """Unload every HAL and refuse new loads; cancel the STUCK ones once more."""
        self._closed = True
        # All at once: each unload is bounded, so shutdown is too -- not N times over.
        names = list(self._loaded)
        outcomes = await asyncio.gather(*(self.unload(n) for n in names),
                                        return_exceptions=True)
        for name, outcome in zip(names, outcomes, strict=True):
            if isinstance(outcome, Exception):
                log.error("HAL %r: unload at shutdown failed: %r", name, outcome)
        if self._unloading:  # unloads that releases started; each is bounded
            await wait_bounded_all(set(self._unloading), 3 * self.stop_timeout_s)
        stuck = {t for t in self._stuck if not t.done()}
        for task in stuck:
            task.cancel()
        if stuck:
            await wait_bounded_all(stuck, self.stop_timeout_s)
        for task, name in list(self._stuck.items()):
            if not task.done():
                log.error("HAL %r: task %r still ignores its cancellation at shutdown; it is "
                          "abandoned", name, task.get_name())

    def force_safe_states(self) -> list[str]:
        """Run the safe state of every loaded HAL that has not had it yet, in the calling
        thread (the escalation of a shutdown whose loop is blocked); returns their names.

        An ``async`` safe_state runs in a fresh event loop of this thread, bounded by
        ``stop_timeout_s``. Errors are logged and reported as events, never raised.
        """
        done: list[str] = []
        # The ones being unloaded too: their unload may be what blocks the loop.
        # (Copies first, atomically: the loop's thread may change them if it runs again.)
        for name, entry in [*self._loaded.copy().items(), *self._leaving.copy().values()]:
            hal = entry.hal
            if not entry.load_began or not claim_safe_state(hal):
                continue
            began = time.monotonic()
            try:
                result = hal.safe_state()
                if inspect.isawaitable(result):
                    asyncio.run(_bounded(result, self.stop_timeout_s,
                                         f"HAL {name!r}: safe_state() did not finish within "
                                         f"stop_timeout_s={self.stop_timeout_s} s"))
            except Exception as exc:
                hal.error = exc
                log.error("HAL %r: forced safe_state() raised %r", name, exc)
                self.events.emit(Event(EventKind.SAFE_STATE_FAILED, f"hal:{name}",
                                       hal.status.name, exc, {"forced": True}))
            else:
                self.events.emit(Event(
                    EventKind.SAFE_STATE_RAN, f"hal:{name}", hal.status.name,
                    detail={"took_s": round(time.monotonic() - began, 6), "forced": True}))
            finally:
                _set_done(hal)
            done.append(name)
        return done

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """``{name: {status, refs, restarts, error, loaded_s}}`` for the loaded HALs."""
        now = time.monotonic()
        return {name: {"status": e.hal.status.name, "refs": len(e.owners),
                       "restarts": e.hal.restarts,
                       "error": None if e.hal.error is None else repr(e.hal.error),
                       "loaded_s": round(now - e.loaded_at, 3)}
                for name, e in list(self._loaded.items())}


def _set_done(hal: HAL) -> None:
    done = _safe_state_done(hal)
    if done is not None:
        done.set()


async def wait_ignoring_cancel(task: asyncio.Future[Any]) -> None:
    """Wait for ``task`` to end even if we are cancelled meanwhile (then re-raise), so no
    task outlives its owner. Only for tasks that are bounded themselves."""
    cancelled = False
    while not task.done():
        try:
            await asyncio.wait({task})
        except asyncio.CancelledError:
            cancelled = True
    if cancelled:
        raise asyncio.CancelledError


async def _wait_bounded(task: asyncio.Future[Any], timeout_s: float) -> bool:
    """Wait at most ``timeout_s`` for ``task``; True when it ended. A cancellation of the
    waiter does not cut the (short) wait: it is raised again afterwards."""
    await wait_bounded_all({task}, timeout_s)
    return task.done()


async def wait_bounded_all(tasks: set[asyncio.Task[Any]] | set[asyncio.Future[Any]],
                            timeout_s: float) -> None:
    """Wait at most ``timeout_s`` for all of ``tasks``. A cancellation of the waiter does
    not cut the (short) wait: it is raised again afterwards."""
    deadline = time.monotonic() + timeout_s
    pending = {t for t in tasks if not t.done()}
    cancelled = False
    while pending:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        try:
            _, pending = await asyncio.wait(pending, timeout=remaining)
        except asyncio.CancelledError:
            cancelled = True
    if cancelled:
        raise asyncio.CancelledError


async def _bounded(awaitable: Awaitable[Any], timeout_s: float, message: str) -> None:
    try:
        async with asyncio.timeout(timeout_s):
            await awaitable
    except TimeoutError:
        raise HALError(message) from None


def check_params(cls: type, name: str, params: dict[str, Any]) -> None:
    """Raise :class:`InvalidParameters` when ``cls(**params)`` would be rejected by its
    ``__init__`` (checked before anything is started or stopped)."""
    init = cls.__init__  # type: ignore[misc]
    if init is object.__init__:
        if params:
            raise InvalidParameters(f"{cls.__qualname__} {name!r} takes no parameters, got "
                                    f"{sorted(params)}")
        return
    try:
        inspect.signature(init).bind(None, **params)
    except TypeError as exc:
        raise InvalidParameters(f"{cls.__qualname__} {name!r} rejects parameters "
                                f"{sorted(params)}: {exc}") from exc
    except ValueError:  # no signature available: let the constructor decide
        pass


def check_duration_s(name: str, value: object, *, allow_zero: bool = False) -> float:
    """``value`` as a float when it is a finite number of seconds (> 0, or ≥ 0 with
    ``allow_zero``); else :class:`~beehave.errors.ConfigError` naming ``name``.

    Infinity and NaN are refused on purpose: an infinite timeout overflows the thread and
    loop primitives, and NaN compares false with everything, so every wait would end at once.
    So is anything beyond :data:`MAX_DURATION_S` (a day, the high level's cap too): a huge
    finite wait overflows ``threading.Event.wait`` just the same, and no robot timeout means
    a week.
    """
    bound = "≥ 0" if allow_zero else "> 0"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{name} must be a number of seconds {bound} and at most "
                          f"{MAX_DURATION_S:g}, got {value!r}")
    seconds = float(value)
    if not math.isfinite(seconds) or seconds < 0 or (seconds == 0 and not allow_zero) \
            or seconds > MAX_DURATION_S:
        raise ConfigError(f"{name} must be a finite number of seconds {bound} and at most "
                          f"{MAX_DURATION_S:g} (a day), got {value!r}")
    return seconds
