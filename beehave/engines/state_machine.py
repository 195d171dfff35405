"""State machine engine over ``transitions``.

Entering a state starts its actions and sub-behaviours; the machine advances on their
outcomes (triggers ``succeeded``, ``failed``, ``stuck``, ``interrupted``, then ``done``
for any outcome no transition took), on blackboard conditions (transitions without
``on``, re-checked whenever the blackboard changes) and on events posted from outside
(:meth:`StateMachineEngine.post`)::

    sm = StateMachineEngine(
        states=[State("patrol", start=lambda: Patrol(robot)),
                State("charge", start=lambda: Charge(robot)),
                State("done", final=True)],
        transitions=[Transition("patrol", "charge", when="battery/percentage < 20"),
                     Transition("charge", "patrol", on="succeeded"),
                     Transition("*", "done", on="shutdown")],
        initial="patrol")

Leaving a state interrupts what it started and waits for it (safe states applied) before
the next state starts anything, so consecutive states may use the same action type.
Reaching a ``final`` state (and its starts ending) ends the machine; its name is the
result. A ``failed`` outcome that no transition handles fails the behaviour with
:class:`~beehave.engines.errors.UnhandledOutcome`.

Only the behaviour's thread triggers the machine, so the plain ``transitions.Machine`` is
used: its ``LockedMachine`` costs ~40 µs per trigger against ~7 µs, for nothing here.
Events from other threads go through a queue and are fired by the behaviour's thread.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from beehave.engines.engine import (
    Condition,
    DecisionEngine,
    EngineContext,
    Readable,
    Starter,
    as_starter,
    condition_label,
    format_validation_error,
    outcome_of,
    parse_condition,
    require,
)

require("transitions", extra="engines")
require("pydantic", extra="engines")

from pydantic import BaseModel, ConfigDict, Field, ValidationError  # noqa: E402

from beehave.engines.errors import EngineConfigError, UnhandledOutcome  # noqa: E402
from beehave.runnable import Runnable  # noqa: E402
from beehave.status import Status  # noqa: E402

if TYPE_CHECKING:
    import graphviz

__all__ = ["OUTCOMES", "State", "StateMachineEngine", "StateMachineSpec", "Transition"]

#: Triggers fired when what a state started has ended; ``done`` catches any outcome.
OUTCOMES = ("succeeded", "failed", "stuck", "interrupted", "done")
_TICK = "tick"  # the trigger of condition-only transitions
_MAX_CHAIN = 100  # condition transitions in a row without waiting: a loop in the design

StartLike = Starter | Callable[[], Runnable] | type[Runnable]
ConditionLike = Condition | str


@dataclass
class State:
    """A state: ``start`` lists what entering it starts (factories, classes or
    :class:`Starter`); ``final`` ends the machine once those have ended."""

    name: str
    start: StartLike | Sequence[StartLike] = ()
    final: bool = False
    starters: tuple[Starter, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        items = self.start if isinstance(self.start, (list, tuple)) else (
            [] if self.start == () else [self.start])
        self.starters = tuple(as_starter(s) for s in items)  # type: ignore[arg-type]


@dataclass
class Transition:
    """``source`` → ``dest`` when the trigger ``on`` fires and every ``when`` condition
    holds and no ``unless`` condition does.

    ``on`` is an outcome (``succeeded``, ``failed``, ``stuck``, ``interrupted``, ``done``),
    an event name posted with :meth:`StateMachineEngine.post`, or None: then the
    transition is taken as soon as its conditions hold. ``source`` may be ``"*"`` (any
    state) or a list. Conditions are callables ``(blackboard) -> bool`` or strings such as
    ``"battery/percentage < 20"``; first matching transition wins, in the order given.
    """

    source: str | Sequence[str]
    dest: str
    on: str | None = None
    when: ConditionLike | Sequence[ConditionLike] = ()
    unless: ConditionLike | Sequence[ConditionLike] = ()

    @property
    def trigger(self) -> str:
        return self.on or _TICK

    def conditions(self, field_name: str, where: str) -> list[Condition]:
        raw = getattr(self, field_name)
        items = raw if isinstance(raw, (list, tuple)) else ([] if raw == () else [raw])
        out: list[Condition] = []
        for i, item in enumerate(items):
            if isinstance(item, str):
                out.append(parse_condition(item, where=f"{where}.{field_name}[{i}]"))
            elif callable(item):
                out.append(item)
            else:
                raise EngineConfigError(f"{where}.{field_name}[{i}]: {item!r} is not a "
                                        "condition (a callable or a 'KEY OP VALUE' string)")
        return out


# -- dict / YAML form ---------------------------------------------------------------------

class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid")


class StateSpec(_Spec):
    name: str = Field(min_length=1)
    start: Any = None
    final: bool = False


class TransitionSpec(_Spec):
    source: str | list[str]
    dest: str
    on: str | None = None
    when: str | list[str] = Field(default_factory=list)
    unless: str | list[str] = Field(default_factory=list)


class StateMachineSpec(_Spec):
    """The dict / YAML form: ``states``, ``transitions``, ``initial``."""

    states: list[StateSpec] = Field(min_length=1)
    transitions: list[TransitionSpec] = Field(default_factory=list)
    initial: str


#: Turns a ``start`` entry of a dict into a :class:`Starter`; ``where`` is its key path.
StartResolver = Callable[[Any, str], Starter]


def _listify(value: Any) -> list[Any]:
    if value is None:
        return []
    return list(value) if isinstance(value, list) else [value]


# -- the engine ---------------------------------------------------------------------------

class _Model:
    """The object ``transitions`` decorates with ``state`` and the trigger methods."""

    state: str


class StateMachineEngine(DecisionEngine):
    """A state machine whose states start actions and sub-behaviours.

    ``on_step(engine)`` is called in the behaviour's thread after every decision step
    (to record or publish ``engine.state``, as the imitation example does); keep it short.
    """

    kind = "state_machine"

    def __init__(self, states: Sequence[State], transitions: Sequence[Transition], *,
                 initial: str,
                 on_step: Callable[[StateMachineEngine], None] | None = None,
                 poll_s: float = 0.05) -> None:
        self.states: dict[str, State] = {}
        for i, state in enumerate(states):
            if not isinstance(state, State):
                raise EngineConfigError(f"states[{i}]: expected a State, got {state!r}")
            if state.name in self.states:
                raise EngineConfigError(f"states[{i}]: duplicate state {state.name!r}")
            self.states[state.name] = state
        self.transitions = list(transitions)
        self.initial = initial
        self.on_step = on_step
        self.poll_s = poll_s
        self._compiled = self._compile()
        self._events: collections.deque[str] = collections.deque()
        self._events_lock = threading.Lock()
        self._state: str | None = None
        self._pending: list[Runnable] = []
        self._model: _Model | None = None
        self._tick: Callable[[], bool] | None = None
        self._fire_cache: dict[str, Callable[[], bool]] = {}

    # -- construction --------------------------------------------------------------------
    def _compile(self) -> list[tuple[Transition, list[Condition], list[Condition], list[str]]]:
        names = list(self.states)
        if self.initial not in self.states:
            raise EngineConfigError(f"initial state {self.initial!r} is not a state; "
                                    f"states: {', '.join(map(repr, names))}")
        compiled = []
        for i, tr in enumerate(self.transitions):
            where = f"transitions[{i}]"
            if not isinstance(tr, Transition):
                raise EngineConfigError(f"{where}: expected a Transition, got {tr!r}")
            sources = [tr.source] if isinstance(tr.source, str) else list(tr.source)
            for src in sources:
                if src != "*" and src not in self.states:
                    raise EngineConfigError(f"{where}.source: unknown state {src!r}; "
                                            f"states: {', '.join(map(repr, names))}")
                if src != "*" and self.states[src].final:
                    raise EngineConfigError(f"{where}.source: {src!r} is final; a final "
                                            "state has no outgoing transitions")
            if tr.dest not in self.states:
                raise EngineConfigError(f"{where}.dest: unknown state {tr.dest!r}; "
                                        f"states: {', '.join(map(repr, names))}")
            if tr.on == _TICK:
                raise EngineConfigError(f"{where}.on: {_TICK!r} is reserved for "
                                        "condition-only transitions; leave 'on' out")
            when = tr.conditions("when", where)
            unless = tr.conditions("unless", where)
            if tr.on is None and not when and not unless:
                raise EngineConfigError(f"{where}: a transition needs 'on' (an outcome or "
                                        f"event: {', '.join(OUTCOMES)}, …) or a 'when' "
                                        "condition; otherwise it would fire at once")
            compiled.append((tr, when, unless, sources))
        return compiled

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, resolve_start: StartResolver,
                  where: str = "") -> StateMachineEngine:
        """Build from the dict / YAML form (see :class:`StateMachineSpec`).

        ``resolve_start(entry, key_path)`` turns each ``start`` entry into a Starter
        (the YAML behaviour resolves action names through its registry). Errors name the
        key path, prefixed with ``where``.
        """
        prefix = f"{where}." if where else ""
        try:
            spec = StateMachineSpec.model_validate(data)
        except ValidationError as exc:
            raise EngineConfigError(format_validation_error(exc, prefix)) from None
        states = []
        for i, st in enumerate(spec.states):
            starters = [resolve_start(entry, f"{prefix}states[{i}].start" + (
                f"[{j}]" if isinstance(st.start, list) else ""))
                for j, entry in enumerate(_listify(st.start))]
            states.append(State(st.name, start=starters, final=st.final))
        transitions = [Transition(t.source, t.dest, on=t.on, when=t.when, unless=t.unless)
                       for t in spec.transitions]
        try:
            return cls(states, transitions, initial=spec.initial)
        except EngineConfigError as exc:
            raise EngineConfigError(f"{prefix}{exc}" if prefix else str(exc)) from None

    def _build_machine(self, blackboard: Readable) -> _Model:
        transitions_mod = require("transitions", extra="engines")
        model = _Model()
        configs = []
        for tr, when, unless, sources in self._compiled:
            configs.append({
                "trigger": tr.trigger,
                "source": "*" if "*" in sources else sources,
                "dest": tr.dest,
                # transitions calls guards without arguments: bind the blackboard here.
                "conditions": [_bind(c, blackboard) for c in when],
                "unless": [_bind(c, blackboard) for c in unless],
            })
        machine = transitions_mod.Machine(
            model=model, states=list(self.states), transitions=configs,
            initial=self.initial, auto_transitions=False, ignore_invalid_triggers=True,
            send_event=False)
        self._fire_cache = {
            name: _bound_trigger(event, model) for name, event in machine.events.items()}
        self._tick = self._fire_cache.get(_TICK)
        return model

    # -- public runtime API --------------------------------------------------------------
    @property
    def state(self) -> str | None:
        """The current state (None when not running)."""
        return self._state

    def post(self, event: str) -> None:
        """Fire ``event`` (a transition's ``on``) in the behaviour's thread, soon. Safe
        from any thread; events posted while the machine is not running are kept for its
        next run."""
        with self._events_lock:
            self._events.append(event)
        context = self._context
        if context is not None:
            context.wake()

    # -- the driver ----------------------------------------------------------------------
    def on_start(self, context: EngineContext) -> None:
        self._model = self._build_machine(context.blackboard)
        context.watch_blackboard()

    def run(self, context: EngineContext) -> Any:
        self._enter(context, self.initial)
        chain = 0
        while not context.interrupted:
            changed = self.step(context)
            if self.on_step is not None:
                self.on_step(self)
            assert self._state is not None
            state = self.states[self._state]
            if state.final and not self._pending:
                return state.name
            if changed or self._events:
                chain += changed
                if chain > _MAX_CHAIN:
                    raise EngineConfigError(
                        f"state machine took {_MAX_CHAIN} transitions without waiting "
                        f"(now in {self._state!r}): condition transitions form a loop")
                continue
            chain = 0
            context.wait()
        return None

    def step(self, context: EngineContext) -> bool:
        """One decision step: posted events, the outcome of the state's starts, then the
        condition transitions. Returns True when a transition was taken. Called by
        :meth:`run`; call it yourself only from a custom ``run``."""
        if self._events:
            with self._events_lock:
                event = self._events.popleft()
            fire = self._fire_cache.get(event)
            if fire is not None and fire():
                self._enter(context, self._model.state)  # type: ignore[union-attr]
                return True
        if self._pending:
            outcome = self._outcome()
            if outcome is not None:
                return self._settle(context, outcome)
        tick = self._tick
        if tick is not None and tick():
            self._enter(context, self._model.state)  # type: ignore[union-attr]
            return True
        return False

    def _outcome(self) -> str | None:
        statuses = [h.status for h in self._pending]
        if Status.FAILED in statuses:
            return "failed"
        if Status.STUCK in statuses:
            return "stuck"
        if not all(s.finished for s in statuses):
            return None
        if Status.INTERRUPTED in statuses:
            return "interrupted"
        return "succeeded"

    def _settle(self, context: EngineContext, outcome: str) -> bool:
        pending, self._pending = self._pending, []
        for handle in pending:
            if handle.status.finished:
                handle.wait(0)  # marks the outcome as seen: no ChildFailed later
                context.forget(handle)
        state = self._state
        for trigger in (outcome, "done"):
            fire = self._fire_cache.get(trigger)
            if fire is not None and fire():
                context.stop([h for h in pending if not h.status.finished])
                self._enter(context, self._model.state)  # type: ignore[union-attr]
                return True
        if outcome in ("failed", "stuck") and not context.interrupted:
            culprit = next(h for h in pending if outcome_of(h) == outcome)
            raise UnhandledOutcome(
                f"state {state!r}: {type(culprit).__name__} {culprit.name!r} {outcome}"
                f"{f' ({culprit.error!r})' if culprit.error else ''} and no transition "
                f"from {state!r} handles {outcome!r} or 'done'",
                state=state or "?", outcome=outcome) from culprit.error
        # Succeeded (or interrupted by someone else) and nobody cares: stay, whatever
        # else is still running keeps running.
        self._pending = [h for h in pending if not h.status.finished]
        return False

    def _enter(self, context: EngineContext, name: str) -> None:
        if self._pending:
            context.stop(self._pending)
            self._pending = []
        self._state = name
        starters = self.states[name].starters
        if starters:
            self._pending = [context.start(s) for s in starters]

    def on_stop(self, context: EngineContext) -> None:
        if self._pending:
            context.stop(self._pending)
            self._pending = []
        self._model = None
        self._tick = None
        self._fire_cache = {}

    # -- drawing -------------------------------------------------------------------------
    def to_graph(self) -> graphviz.Digraph:
        graphviz_mod = require("graphviz", extra="engines")
        graph = graphviz_mod.Digraph("state_machine", graph_attr={"rankdir": "LR"},
                                     node_attr={"fontname": "Helvetica"},
                                     edge_attr={"fontname": "Helvetica", "fontsize": "10"})
        graph.node("__initial__", "", shape="point", width="0.15")
        for state in self.states.values():
            label = state.name
            if state.starters:
                label += "\n" + "\n".join(f"▶ {s.name}" for s in state.starters)
            graph.node(state.name, label, shape="doublecircle" if state.final else "box",
                       style="rounded")
        graph.edge("__initial__", self.initial)
        for tr, when, unless, sources in self._compiled:
            parts = [tr.on] if tr.on else []
            parts += [f"[{condition_label(c)}]" for c in when]
            parts += [f"[not {condition_label(c)}]" for c in unless]
            targets = list(self.states) if "*" in sources else sources
            for src in targets:
                if src == "*" or self.states[src].final:
                    continue
                graph.edge(src, tr.dest, " ".join(parts))
        return graph


def _bind(condition: Condition, blackboard: Readable) -> Callable[..., bool]:
    def guard(*_args: Any, **_kwargs: Any) -> bool:
        return condition(blackboard)
    return guard


def _bound_trigger(event: Any, model: _Model) -> Callable[[], bool]:
    def fire() -> bool:
        return bool(event.trigger(model))
    return fire
