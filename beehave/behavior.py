"""Behavior: decides what the robot does, by starting actions and sub-behaviours."""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from typing import Any, ClassVar, Self, TypeVar

from beehave.action import Action
from beehave.attach import attached
from beehave.errors import ChildFailed, Interrupted, NotASubclass
from beehave.events import Event, EventKind
from beehave.runnable import Runnable
from beehave.status import Status

log = logging.getLogger(__name__)

A = TypeVar("A", bound=Action)
B = TypeVar("B", bound="Behavior")


NO_FLEET = ("no fleet is attached to this manager: make a beehave.agents.fleet.Fleet(agent) "
            "and call fleet.attach(manager)")


class Behavior(Runnable):
    """Subclass it and write :meth:`run`, which decides and starts actions.

    ``run`` executes in the behaviour's own thread. Actions and sub-behaviours started
    here never outlive the behaviour: when ``run`` returns (or the behaviour is
    interrupted) the ones still running are interrupted and waited for, up to the
    manager's ``stop_timeout_s``; those that ignore the interrupt become STUCK.

    A child that fails is surfaced: unless you ``wait()`` for it yourself, the next
    ``sleep``/``start_*`` call (or the end of ``run``) raises :class:`ChildFailed`.
    Catch it to carry on.
    """

    #: The top-level logic the low level should run while this is the top-level behaviour
    #: (a name registered with the LowLevelBehaviorManager), or None to leave it alone.
    #: Carried over ROS 2 in ``beehave/high_level/state``.
    logic: ClassVar[str | None] = None

    _children: list[Runnable]
    _unobserved_failures: list[Runnable]
    _accepting: bool
    _hook_errors: list[Exception]
    _hook_pending: bool  # interrupted, and its on_interrupt() hook has not run yet
    _names: Counter[str]
    _awaiting: set[Runnable] | None
    #: The decision engine driving this behaviour now (set by ``DecisionEngine.drive``).
    _engine: Any
    #: Whether the class has an ``on_child_ended`` hook to call (most have none).
    _HOOKS_CHILD_END: ClassVar[bool] = False
    _HAS_CHILDREN: ClassVar[bool] = True

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._HOOKS_CHILD_END = cls.on_child_ended is not Behavior.on_child_ended

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        self = super().__new__(cls)
        self.__dict__.update(_engine=None, _children=[], _names=Counter(),
                             _unobserved_failures=[], _hook_errors=[], _accepting=True,
                             _awaiting=None, _hook_pending=False)
        return self

    def start_action(self, action: A, *, preempt: bool = False) -> A:
        """Start ``action`` in its own thread and return it (the handle).

        Raises :class:`ActionTypeBusy` naming the holder when its ``action_type`` is
        taken. With ``preempt=True`` the holder is interrupted and waited for (its
        ``safe_state`` included, at most ``stop_timeout_s``), then ``action`` starts.
        """
        if not isinstance(action, Action):
            raise NotASubclass(f"{self.path}: start_action() takes an Action instance, "
                               f"got {action!r}; use start_behavior() for behaviours")
        manager = self._before_start(action)
        try:
            manager._locks.acquire(action, preempt=preempt, timeout_s=manager.stop_timeout_s,
                                   cancelled=lambda: self._interrupt_requested)
        except BaseException:
            action._detach()  # not started: the caller may try the same object again
            raise
        # Only what really starts is substituted (a refused action stood in for nothing).
        manager.substitutes.apply(action, path=action.path)
        try:
            self._adopt(action)
        except BaseException:
            manager._locks.release(action)
            raise
        action._start_thread()
        return action

    @property
    def fleet(self) -> Any:
        """The shared state of every agent of the fleet (a
        :class:`beehave.agents.fleet.Fleet`), once one is attached to this behaviour's
        manager (``Fleet.attach(manager)``)."""
        return attached(self.manager, "fleet", missing=NO_FLEET)

    def start_behavior(self, behavior: B) -> B:
        """Start ``behavior`` as a sub-behaviour in its own thread and return it."""
        if not isinstance(behavior, Behavior):
            raise NotASubclass(f"{self.path}: start_behavior() takes a Behavior instance, "
                               f"got {behavior!r}; use start_action() for actions")
        manager = self._before_start(behavior)
        manager.substitutes.apply(behavior, path=behavior.path)
        self._adopt(behavior)
        behavior._start_thread()
        return behavior

    @classmethod
    def prepare_node(cls, node: Any) -> None:
        """Optional hook: the robot made its high-level ROS node ``node``, and nothing runs
        yet — neither level, nor this behaviour.

        Called once per behaviour class the robot's configuration names (``beehave run``),
        before the low level starts: declare here the node's parameters that a logic may
        set from its first moment (a speed limit the low level sets at once would
        otherwise meet an undeclared parameter).
        """

    def on_child_ended(self, child: Runnable) -> None:
        """Optional hook: ``child`` (an action or sub-behaviour of this one) has ended.

        Called in the child's thread, after its status is final: keep it short — set an
        event or post to a queue that your ``run`` waits on (decision engines do).
        """

    def on_interrupt(self) -> None:
        """Optional hook: this behaviour was asked to stop (its children already were).

        Called in the interrupting thread; keep it short — wake whatever ``run`` waits on
        besides ``self.sleep`` (which wakes by itself).
        """

    @property
    def children(self) -> list[Runnable]:
        """The actions and sub-behaviours started and not yet cleaned up."""
        with self._cond_lock:
            return list(self._children)

    # ------------------------------------------------------------------ driver
    def _before_start(self, child: Runnable) -> Any:
        manager = self._manager
        if manager is None or self._status is not Status.RUNNING:
            raise Interrupted(f"{self.path}: cannot start {child.name!r}: the behaviour is "
                              f"{self._status.name}, not running")
        with self._cond_lock:
            self._raise_pending()
            self._prune()
        if self._interrupt_requested:
            raise Interrupted(f"{self.path}: interrupted; not starting {child.name!r}")
        child._attach(self, manager)
        with self._cond_lock:
            # Paths name things in events and snapshots: the second `Drive` started by this
            # behaviour is `Drive#2` (its name stays `Drive`), so the two can be told apart.
            name = child.name
            self._names[name] += 1
            count = self._names[name]
        suffix = f"#{count}" if count > 1 else ""
        child._suffix = suffix
        # Its path is known from here on (this behaviour's is fixed while it runs): made
        # once, not at each of the substitution check, the thread's name and the events.
        child._path, child._path_name = f"{self.path}/{name}{suffix}", name
        return manager

    def _adopt(self, child: Runnable) -> None:
        with self._cond_lock:
            # Checked under the same lock the interrupt takes, so no child escapes it.
            if self._interrupt_requested or not self._accepting:
                raise Interrupted(f"{self.path}: interrupted; not starting {child.name!r}")
            self._children.append(child)

    def _prune(self) -> None:
        """Forget children whose threads are over (keeps long-running behaviours small)."""
        # (Ended implies decided; a STUCK child is kept until its thread has ended too.
        # Flags and status read directly: this runs at every start.)
        done = [c for c in self._children if c._ended._on and c._status is not Status.STUCK]
        if done:
            self._children = [c for c in self._children if c not in done]

    def _on_interrupt(self, deadline: float | None) -> None:
        with self._cond_lock:
            children = list(self._children)
        for child in children:
            child._interrupt(deadline)
        # The hook before its own thread is woken; the thread, which may see its interrupt
        # flag without being woken, waits for the hook before it decides its status
        # (_hook_pending, _after_run): an error the hook raises decides it. (A loaded
        # machine's thread ended INTERRUPTED before the hook had raised; a stress run.)
        try:
            self.on_interrupt()
        except Exception as exc:  # must not break the switch that is interrupting us
            self._hook_failed("on_interrupt", exc)
        # Its own thread last (its interrupt flag is set already): woken threads queue for
        # the interpreter roughly in the order they were woken, so when this one's turn
        # comes its children have mostly ended, and it collects them at once instead of
        # waiting for them and being woken a second time.
        with self._cond_lock:
            self._hook_pending = False
            self._cond.notify_all()

    def _after_run(self, error: BaseException | None) -> BaseException | None:
        assert self._manager is not None
        with self._cond_lock:
            self._accepting = False
            children = list(self._children)
            deadline = self._stop_deadline
        if deadline is None:
            deadline = time.monotonic() + self._manager.stop_timeout_s
        if not self._interrupt_requested:
            orphans = [c.path for c in children if not c._decided._on]
            if orphans:
                # A common slip: run() returned without waiting for what it started.
                log.info("%s: run() returned while %s still ran; they are interrupted now "
                         "(a behaviour's actions never outlive it: wait() for them to let "
                         "them finish)", self.path, ", ".join(orphans))
        # (After a switch's interrupt, often every child has ended by the time this runs:
        # then nothing is left to interrupt, wait for or declare STUCK.)
        running = [c for c in children if not c._ended._on]
        if running:
            for child in running:
                child._interrupt(deadline)
            self._await_children(running, deadline)
            for child in running:
                if not child._decided._on:
                    child._mark_stuck()
            for child in running:
                if child._status is not Status.STUCK and not child._ended._on:
                    # It has decided; its clean-up is just finishing (bounded all the same).
                    child._join(max(0.0, deadline - time.monotonic()) + 0.05)
        if self._hook_pending:  # the interrupting thread is in on_interrupt()
            def hooked() -> bool:
                return not self._hook_pending

            with self._manager.clock.blocked(hooked), self._cond_lock:
                self._cond.wait_for(hooked, max(0.0, deadline - time.monotonic()))
        with self._cond_lock:
            if error is None and self._hook_errors:
                error = self._hook_errors[0]
            elif error is None and not self._interrupt_requested and self._unobserved_failures:
                failed = self._unobserved_failures[0]
                error = ChildFailed(failed)
                error.__cause__ = failed.error
        return error

    def _await_children(self, children: list[Runnable], deadline: float) -> None:
        """Wait until every child has ended or is STUCK, at most until ``deadline``: one
        wake-up when the last one settles (``_child_settled``), not one per child."""
        awaiting = {c for c in children if not c._ended._on and c._status is not Status.STUCK}
        if not awaiting:
            return
        with self._cond_lock:
            # (A child that settles before this counts itself out here.)
            self._awaiting = {c for c in awaiting
                              if not c._ended._on and c._status is not Status.STUCK}
        assert self._manager is not None

        def settled() -> bool:
            return not self._awaiting

        try:
            with self._manager.clock.blocked(settled), self._cond_lock:
                self._cond.wait_for(settled, max(0.0, deadline - time.monotonic()))
        finally:
            with self._cond_lock:
                self._awaiting = None

    def _child_settled(self, child: Runnable) -> None:
        """Called by ``child`` once it has ended or become STUCK."""
        with self._cond_lock:
            awaiting = self._awaiting
            if awaiting and child in awaiting:
                awaiting.discard(child)
                if not awaiting:
                    self._cond.notify_all()

    def _mark_stuck(self) -> None:
        super()._mark_stuck()
        for child in self.children:
            child._mark_stuck()

    def _record_child_end(self, child: Runnable) -> None:
        if child.status is not Status.FAILED:  # (final by now: no lock needed to read it)
            return
        with self._cond_lock:
            if child.status is Status.FAILED:
                self._unobserved_failures.append(child)
                self._cond.notify_all()

    def _call_child_hook(self, child: Runnable) -> None:
        try:
            self.on_child_ended(child)
        except Exception as exc:
            self._hook_failed("on_child_ended", exc)

    def _hook_failed(self, hook: str, exc: Exception) -> None:
        """A user hook raised: surface it in this behaviour's thread (next framework call,
        or the end of run) and report it as an event — never log-and-drop."""
        with self._cond_lock:
            self._hook_errors.append(exc)
            self._cond.notify_all()
        if self._manager is not None:
            self._manager.events.emit(Event(EventKind.HOOK_FAILED, self.path,
                                            self._status.name, exc, {"hook": hook}))

    def _observed(self, child: Runnable) -> None:
        with self._cond_lock:
            if child in self._unobserved_failures:
                self._unobserved_failures.remove(child)

    def _wake_reason(self) -> bool:
        return (self._interrupt_requested or bool(self._unobserved_failures)
                or bool(self._hook_errors))

    def _raise_pending(self) -> None:
        if self._hook_errors:
            raise self._hook_errors.pop(0)
        if self._unobserved_failures:
            failed = self._unobserved_failures.pop(0)
            raise ChildFailed(failed) from failed.error

    def _snapshot(self) -> dict[str, Any]:
        snap = super()._snapshot()
        snap["kind"] = "behavior"
        engine = self._engine
        if engine is not None:
            # A behaviour whose run() calls engine.drive(self): where its engine is.
            snap["engine"] = engine.describe()
        snap["children"] = [c._snapshot() for c in self.children]
        return snap


class Idle(Behavior):
    """The built-in safe behaviour: starts nothing, so nothing moves. Runs when nothing
    else does, and after a top-level behaviour ended."""

    def run(self) -> None:
        # No deadline: nothing for a virtual clock to jump to while the robot idles.
        self.sleep(math.inf)


def running_engines(top: Runnable | None) -> list[tuple[str, Any]]:
    """``(path, engine)`` of every decision engine driving ``top`` or a behaviour under it
    now, depth first (what viewers, breakpoints and recordings look at)."""
    found: list[tuple[str, Any]] = []

    def walk(node: Any) -> None:
        engine = getattr(node, "_engine", None)
        if engine is not None:
            found.append((node.path, engine))
        for child in list(getattr(node, "children", ())):
            walk(child)

    if top is not None:
        walk(top)
    return found
