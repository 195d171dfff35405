"""DecisionEngine: one small interface behind which state machines, trees and networks decide.

An engine decides *inside the owning behaviour's thread*. It never starts threads for its
decisions: it starts actions and sub-behaviours through the behaviour (so type locks,
safe states and structured concurrency hold as for hand-written behaviours) and waits
for their outcomes, blackboard changes or an interrupt through an :class:`EngineContext`.

Run an engine as a behaviour of its own::

    sm = StateMachineEngine(states=[...], transitions=[...], initial="patrol")
    hl.register("patrol", EngineBehavior, engine=sm)

or from inside your own behaviour's ``run`` with ``return engine.drive(self)``.

What a state or tree leaf starts is a :class:`Starter`: a factory that builds a *new*
action or behaviour each time (an action object runs only once), plus the preempt policy.
Conditions are callables ``condition(blackboard) -> bool``; :func:`parse_condition` turns
``"battery/percentage < 20"`` into one (that is what YAML files use).
"""

from __future__ import annotations

import abc
import hashlib
import importlib
import json
import operator
import re
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, Self, TypeAlias

import yaml

from beehave.action import Action
from beehave.behavior import Behavior
from beehave.engines.errors import EngineBusy, EngineConfigError, MissingExtra, NotRenderable
from beehave.errors import NotASubclass
from beehave.runnable import Runnable

if TYPE_CHECKING:
    import graphviz

    from beehave.blackboard import Subscription

__all__ = [
    "BlackboardCondition", "Condition", "DecisionEngine", "EngineBehavior", "EngineContext",
    "Readable", "StartLike", "Starter", "as_starter", "condition_label", "format_validation_error",
    "outcome_of", "parse_condition", "require",
]


def require(module: str, *, extra: str) -> ModuleType:
    """Import an optional dependency, or raise :class:`MissingExtra` naming the extra."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtra(
            f"{module!r} is not installed; it comes with the {extra!r} extra: "
            f"pip install 'beehave-robotics[{extra}]'") from exc


class Readable(Protocol):
    """What a condition reads: a :class:`~beehave.Blackboard` or anything with ``get``."""

    def get(self, key: str, default: Any = None) -> Any: ...


Condition: TypeAlias = Callable[[Readable], bool]
"""A guard: called with the blackboard, returns whether it holds. Keep it cheap and
side-effect free; engines call it on every decision step."""

_OPS: dict[str, Callable[[Any, Any], Any]] = {
    "<=": operator.le, ">=": operator.ge, "==": operator.eq, "!=": operator.ne,
    "<": operator.lt, ">": operator.gt,
}
_COND = re.compile(r"\s*(not\s+)?([^\s<>=!]+)\s*(?:(<=|>=|==|!=|<|>)\s*([^\s<>=!].*?))?\s*")


class BlackboardCondition:
    """``key OP value`` (or ``key`` / ``not key`` for truthiness) over the blackboard.

    A missing key never holds (``not key`` holds when it is missing or falsy). A value
    that cannot be compared (``None < 20``) does not hold either, rather than raising in
    the middle of a decision.
    """

    __slots__ = ("key", "op", "value", "negate", "text")

    def __init__(self, key: str, op: str | None = None, value: Any = None, *,
                 negate: bool = False) -> None:
        if op is not None and op not in _OPS:
            raise EngineConfigError(f"condition on {key!r}: unknown operator {op!r}; "
                                    f"valid: {', '.join(_OPS)}")
        self.key, self.op, self.value, self.negate = key, op, value, negate
        if op is None:
            self.text = f"not {key}" if negate else key
        else:
            self.text = f"{key} {op} {value!r}"

    def __call__(self, blackboard: Readable) -> bool:
        current = blackboard.get(self.key)
        if self.op is None:
            return not current if self.negate else bool(current)
        if current is None:
            return False
        try:
            return bool(_OPS[self.op](current, self.value))
        except TypeError:
            return False

    def __repr__(self) -> str:
        return f"BlackboardCondition({self.text!r})"

    def __str__(self) -> str:
        return self.text


def parse_condition(text: str, *, where: str = "condition") -> BlackboardCondition:
    """Parse ``"battery/percentage < 20"``, ``"docked == true"``, ``"obstacle"`` or
    ``"not docked"``; the value is read as YAML (numbers, true/false, strings).

    ``where`` names the place for the error message (a YAML key path).
    """
    match = _COND.fullmatch(text) if isinstance(text, str) else None
    if match is None or (match.group(1) and match.group(3)):
        raise EngineConfigError(
            f"{where}: cannot read condition {text!r}; expected 'KEY OP VALUE' with OP one "
            f"of {', '.join(_OPS)} (e.g. 'battery/percentage < 20'), 'KEY' or 'not KEY'")
    negate, key, op, raw = match.groups()
    value = None
    if op is not None:
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = raw
    return BlackboardCondition(key, op, value, negate=bool(negate))


def condition_label(condition: Callable[..., Any]) -> str:
    """A short human-readable name of a condition, for graphs and errors."""
    if isinstance(condition, BlackboardCondition):
        return condition.text
    label = getattr(condition, "label", None)
    if isinstance(label, str):
        return label
    name = getattr(condition, "__name__", None)
    if isinstance(name, str) and name != "<lambda>":
        return name
    return type(condition).__name__ if name is None else "condition"


@dataclass(frozen=True)
class Starter:
    """What a state or leaf starts: ``factory()`` builds a fresh Action or Behavior.

    ``preempt`` is passed to ``start_action`` (interrupt a holder of the same type instead
    of failing with ActionTypeBusy); ``label`` names it in graphs and errors.
    """

    factory: Callable[[], Runnable]
    preempt: bool = False
    label: str = ""

    @property
    def name(self) -> str:
        return self.label or getattr(self.factory, "__name__", "start")

    def build(self) -> Runnable:
        built = self.factory()
        if not isinstance(built, (Action, Behavior)):
            raise NotASubclass(f"starter {self.name!r} built {built!r}; it must return a new "
                               "Action or Behavior instance")
        return built


#: What engines accept wherever something is started.
StartLike: TypeAlias = "Starter | Callable[[], Runnable] | type[Runnable]"


def as_starter(spec: Starter | Callable[[], Runnable] | type[Runnable], *,
               preempt: bool = False, label: str = "") -> Starter:
    """Accept a :class:`Starter`, an Action/Behavior class (built without arguments) or a
    zero-argument factory. Objects are refused: an action can run only once."""
    if isinstance(spec, Starter):
        return spec
    if isinstance(spec, Runnable):
        raise NotASubclass(
            f"got the object {spec!r}; engines start a fresh action each time, so pass a "
            f"factory (lambda: {type(spec).__name__}(...)) or the class")
    if isinstance(spec, type):
        if not issubclass(spec, (Action, Behavior)):
            raise NotASubclass(f"{spec!r} is not an Action or Behavior subclass")
        return Starter(spec, preempt, label or spec.__name__)
    if callable(spec):
        return Starter(spec, preempt, label)
    raise NotASubclass(f"cannot start {spec!r}: pass an Action/Behavior class or a factory")


def outcome_of(handle: Runnable) -> str:
    """The trigger name of a finished handle: ``succeeded``, ``failed``, ``interrupted``
    or ``stuck`` (its Status, lower case)."""
    return handle.status.name.lower()


class EngineContext:
    """One run of an engine inside one behaviour: what the engine may do there.

    Created by :meth:`DecisionEngine.drive`; an engine receives it in ``run`` and hooks.
    Everything here is called from the behaviour's thread, except :meth:`wake` (any thread).
    """

    def __init__(self, behavior: Behavior, *, poll_s: float) -> None:
        self.behavior = behavior
        self.poll_s = poll_s
        # Set by wake(); waited on through the manager's clock, so that poll_s and a tree's
        # rate follow sim time or a test's virtual time. The behaviour's own condition:
        # an interrupt notifies it, so a paused simulation or a virtual clock that stands
        # still cannot keep a plain behaviour that drives an engine from stopping.
        self._cond = behavior._cond
        self._woken = False
        self._handles: list[Runnable] = []
        self._subscription: Subscription | None = None

    # -- reading the world ---------------------------------------------------------------
    @property
    def blackboard(self) -> Any:
        """The behaviour's blackboard (the manager's, or its ROS 2 mirror)."""
        return self.behavior.blackboard

    @property
    def interrupted(self) -> bool:
        return self.behavior.interrupted

    def watch_blackboard(self, pattern: str = "**") -> None:
        """Wake the engine whenever a key matching ``pattern`` changes (conditions are then
        re-evaluated at once rather than at the next poll)."""
        if self._subscription is None:
            self._subscription = self.behavior.blackboard.subscribe(
                pattern, lambda _change: self.wake())

    # -- waiting -------------------------------------------------------------------------
    def wake(self) -> None:
        """Make the current or next :meth:`wait` return. Safe from any thread."""
        with self._cond:
            self._woken = True
            self._cond.notify_all()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait until something may have changed — a child ended, the blackboard changed,
        :meth:`wake` was called or an interrupt came — or ``timeout_s`` passed.

        Returns False once the behaviour is interrupted. Inside an
        :class:`EngineBehavior`, child ends and interrupts wake it at once; in another
        behaviour they are noticed within ``poll_s``.
        """
        if self.behavior.interrupted:
            return False
        limit = self.poll_s if timeout_s is None else min(timeout_s, self.poll_s)
        behavior = self.behavior
        with self._cond:
            # While the manager is paused, only an interrupt ends the wait: the engine
            # decides nothing (a child's end or a blackboard change waits for resume()).
            behavior.manager.run_clock.wait(
                self._cond, lambda: self._woken or behavior.interrupted, limit,
                frozen_escape=lambda: behavior.interrupted)
            self._woken = False
        return not behavior.interrupted

    def now(self) -> float:
        """The manager's clock time without its pauses (sim or virtual time where the
        manager has one)."""
        return self.behavior.manager.run_clock.now()

    # -- starting and stopping -----------------------------------------------------------
    def start(self, starter: Starter) -> Runnable:
        """Build what ``starter`` makes and start it as a child of the behaviour."""
        child = starter.build()
        if isinstance(child, Action):
            self.behavior.start_action(child, preempt=starter.preempt)
        else:
            assert isinstance(child, Behavior)
            self.behavior.start_behavior(child)
        self._handles.append(child)
        return child

    def stop(self, handles: Sequence[Runnable]) -> None:
        """Interrupt ``handles`` and wait until they ended (safe states applied), each at
        most the manager's ``stop_timeout_s``; waiting marks their outcome as seen."""
        for handle in handles:
            handle.interrupt()
        deadline = time.monotonic() + self.behavior.manager.stop_timeout_s
        # A switch gave the whole tree a deadline: do not wait past it, so that the
        # framework (not this engine) declares stragglers STUCK, on time.
        switch_deadline = self.behavior.stop_deadline
        if switch_deadline is not None:
            deadline = min(deadline, switch_deadline)
        for handle in handles:
            handle.wait(max(0.0, deadline - time.monotonic()))
        self._handles = [h for h in self._handles if h not in handles]

    def forget(self, handle: Runnable) -> None:
        """The engine has taken ``handle``'s outcome: stop tracking it."""
        if handle in self._handles:
            self._handles.remove(handle)

    @property
    def running(self) -> list[Runnable]:
        """What this run started and has not stopped or forgotten."""
        return [h for h in self._handles if not h.status.finished]

    def close(self) -> None:
        """End of the run: stop what is still running, drop the blackboard subscription."""
        try:
            self.stop(self.running)
        finally:
            if self._subscription is not None:
                self._subscription.close()
                self._subscription = None


class DecisionEngine(abc.ABC):
    """Subclass it and write :meth:`run`; the optional hooks are :meth:`on_start`,
    :meth:`on_stop` and :meth:`to_graph`.

    One engine object drives one behaviour at a time (a second concurrent
    :meth:`drive` raises :class:`EngineBusy`); it can be driven again after that run ended,
    so registering a behaviour with an engine parameter and switching to it twice works.
    """

    #: The engine's kind in YAML files and graphs ("state_machine", "tree", "neural").
    kind: ClassVar[str] = "engine"
    #: Upper bound of a wait when nothing wakes the engine (outside an EngineBehavior).
    poll_s: float = 0.05

    _drive_lock: threading.Lock
    _context: EngineContext | None
    _structure_memo: tuple[str | None] | None

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        self = super().__new__(cls)
        self._drive_lock = threading.Lock()
        self._context = None
        self._structure_memo = None
        return self

    def drive(self, behavior: Behavior) -> Any:
        """Decide inside ``behavior`` (call it from its ``run``) until the engine is done
        or the behaviour is interrupted; return the engine's result.

        Whatever happens, what the engine started is interrupted and waited for before this
        returns (safe states applied) and :meth:`on_stop` has run.
        """
        if not self._drive_lock.acquire(blocking=False):
            owner = self._context.behavior.path if self._context else "?"
            raise EngineBusy(f"{type(self).__name__} already drives behaviour {owner!r}; "
                             "give each behaviour its own engine")
        context = EngineContext(behavior, poll_s=self.poll_s)
        self._context = context
        if isinstance(behavior, EngineBehavior):
            behavior._engine_context = context
        behavior._engine = self  # its snapshot shows where the engine is
        try:
            self.on_start(context)
            try:
                return self.run(context)
            finally:
                self.on_stop(context)
        finally:
            try:
                context.close()
            finally:
                if isinstance(behavior, EngineBehavior):
                    behavior._engine_context = None
                behavior._engine = None
                self._context = None
                self._drive_lock.release()

    def on_start(self, context: EngineContext) -> None:
        """Called in the behaviour's thread before :meth:`run`: build per-run state here
        (subscribe to the blackboard, start a training thread you then own)."""

    @abc.abstractmethod
    def run(self, context: EngineContext) -> Any:
        """Decide until done: start children with ``context.start``, wait with
        ``context.wait`` and return when finished or ``context.interrupted``.

        The return value becomes the behaviour's result; raise to fail the behaviour.
        """

    def on_stop(self, context: EngineContext) -> None:
        """Called in the behaviour's thread after :meth:`run` ended, however it ended:
        stop what you started (the context then interrupts whatever is left), join
        threads you own."""

    def to_graph(self) -> graphviz.Digraph:
        """The engine's structure as a graphviz graph (``beehave graph`` renders it)."""
        raise NotRenderable(f"{type(self).__name__} has no graph to draw")

    def structure(self) -> dict[str, Any] | None:
        """What the engine is made of, for viewers that draw it (the web view's graphs),
        JSON-serialisable with at least ``"kind"``; None (the default): nothing to draw.
        A state machine gives its states and labelled transitions, a tree its nodes.

        It changes rarely, so :meth:`describe` carries only its :meth:`structure_id` and a
        viewer asks for the structure itself when that id is new to it (``GET
        /api/robots/{robot}/structure``). Override it in your own engine, and call
        :meth:`structure_changed` when it changes."""
        return None

    def structure_id(self) -> str | None:
        """A short id of :meth:`structure` (a hash of it), computed once until
        :meth:`structure_changed`; None when there is no structure."""
        memo = self._structure_memo
        if memo is None:
            structure = self.structure()
            digest = None if structure is None else hashlib.sha1(
                json.dumps(structure, sort_keys=True, default=str).encode()).hexdigest()[:12]
            memo = self._structure_memo = (digest,)
        return memo[0]

    def structure_changed(self) -> None:
        """The structure changed: the next :meth:`structure_id` is computed again."""
        self._structure_memo = None

    def describe(self) -> dict[str, Any]:
        """Where the engine is now, as a small JSON-serialisable dict with at least
        ``"kind"``: the current state of a state machine, the node statuses of a tree, the
        last decision of a network. Called from other threads (the manager's
        ``snapshot()``, the ROS 2 state topic) while the engine runs, so it only reads.

        Override it in your own engine; the default names the kind only.
        """
        return {"kind": self.kind}


class EngineBehavior(Behavior):
    """A behaviour that is nothing but its engine: ``run`` drives ``engine``.

    Child ends and interrupts wake the engine at once (no polling). Register it with an
    engine (or subclass it and pass the engine up)::

        hl.register("patrol", EngineBehavior, engine=build_patrol_machine())
    """

    _engine_context: EngineContext | None = None

    def __init__(self, engine: DecisionEngine, *, name: str | None = None) -> None:
        if not isinstance(engine, DecisionEngine):
            raise NotASubclass(f"EngineBehavior needs a DecisionEngine, got {engine!r}")
        self.engine = engine
        if name:
            self.name = name

    def run(self) -> Any:
        return self.engine.drive(self)

    def _wake_engine(self) -> None:
        context = self._engine_context
        if context is not None:
            context.wake()

    def on_child_ended(self, child: Runnable) -> None:
        self._wake_engine()

    def on_interrupt(self) -> None:
        self._wake_engine()

    def _snapshot(self) -> dict[str, Any]:
        snap = super()._snapshot()
        # What users most want to see of a running behaviour: where its engine is (also
        # before and after it drives).
        snap["engine"] = self.engine.describe()
        return snap


def format_validation_error(exc: Any, prefix: str = "") -> str:
    """A pydantic ``ValidationError`` as ``key.path[2].field: what was expected (got …)``
    lines, each key path prefixed with ``prefix``."""
    lines = []
    for err in exc.errors():
        path = prefix + _loc(err["loc"])
        got = err.get("input")
        shown = "" if isinstance(got, (dict, list)) else f" (got {got!r})"
        lines.append(f"{path.rstrip('.') or '<top>'}: {err['msg']}{shown}")
    return "; ".join(lines)


def _loc(loc: Iterable[Any]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out
