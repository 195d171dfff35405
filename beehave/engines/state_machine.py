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
        initial="patrol", events=["shutdown"])

``"*"`` is every state but the destination (and the final states), so a wildcard never
re-enters its own destination. Building the machine refuses what would misbehave: an
``on`` that is neither an outcome nor a declared event, and a cycle of condition-only
transitions whose guards can hold together (it would loop without waiting); it warns
about unreachable states (:attr:`StateMachineEngine.warnings`). Events posted while the
machine is not running are dropped (``post`` returns False).

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
import difflib
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from beehave import breakpoints
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

from beehave.engines.errors import (  # noqa: E402
    EngineConfigError,
    UnhandledOutcome,
    UnknownEvent,
)
from beehave.engines.guards import Guard, Verdict, can_hold_together  # noqa: E402
from beehave.runnable import Runnable  # noqa: E402
from beehave.status import Status  # noqa: E402

if TYPE_CHECKING:
    import graphviz

__all__ = ["OUTCOMES", "State", "StateMachineEngine", "StateMachineSpec", "Transition"]

log = logging.getLogger(__name__)

#: Triggers fired when what a state started has ended; ``done`` catches any outcome.
OUTCOMES = ("succeeded", "failed", "stuck", "interrupted", "done")
_TICK = "tick"  # the trigger of condition-only transitions
_MAX_CHAIN = 100  # condition transitions in a row without waiting: a loop in the design
_MAX_CYCLE_PATHS = 100_000  # bound of the load-time cycle search (machines are small)
# Load-time warnings already logged by this process: a behaviour built at every switch
# (a YAML behaviour, a factory) warns once, not at every switch.
_WARNED: set[str] = set()

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
    transition is taken as soon as its conditions hold. ``source`` is a state, a list of
    states, or ``"*"``: every state except ``dest`` itself and the final states (so
    ``Transition("*", "charge", when="battery/percentage < 20")`` enters ``charge`` once
    instead of re-entering it while the battery stays low; list ``dest`` explicitly to
    restart a state, on an event or outcome). Conditions are callables
    ``(blackboard) -> bool`` or strings such as ``"battery/percentage < 20"``; first
    matching transition wins, in the order given.
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
    """The dict / YAML form: ``states``, ``transitions``, ``initial``, and ``events``: the
    names of the events posted from outside (every ``on`` that is not an outcome must be
    declared there, so a typo such as ``succeded`` is refused rather than never firing)."""

    states: list[StateSpec] = Field(min_length=1)
    transitions: list[TransitionSpec] = Field(default_factory=list)
    initial: str
    events: list[str] = Field(default_factory=list)


#: Turns a ``start`` entry of a dict into a :class:`Starter`; ``where`` is its key path.
StartResolver = Callable[[Any, str], Starter]


def _event_names(events: Iterable[str]) -> frozenset[str]:
    if isinstance(events, str):
        raise EngineConfigError(f"events: expected a list of event names, got {events!r}")
    names = []
    for i, name in enumerate(events):
        if not isinstance(name, str) or not name:
            raise EngineConfigError(f"events[{i}]: expected an event name, got {name!r}")
        if name in OUTCOMES or name == _TICK:
            raise EngineConfigError(
                f"events[{i}]: {name!r} is built in ({', '.join(OUTCOMES)} are fired by "
                "the engine when what a state started ends); declare only your own events")
        names.append(name)
    return frozenset(names)


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

    ``events`` declares the names you :meth:`post`; given, every ``on`` must be an
    outcome or one of them (without it, any ``on`` that is not a near miss of an outcome
    counts as an event). ``on_step(engine)`` is called in the behaviour's thread after
    every decision step (to record or publish ``engine.state``, as the imitation example
    does); keep it short. ``origin`` (a file name) prefixes the load warnings.
    """

    kind = "state_machine"

    def __init__(self, states: Sequence[State], transitions: Sequence[Transition], *,
                 initial: str, events: Iterable[str] | None = None,
                 on_step: Callable[[StateMachineEngine], None] | None = None,
                 poll_s: float = 0.05, origin: str = "") -> None:
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
        #: Where the machine comes from (a YAML file), named in warnings.
        self.origin = origin
        self._declared = None if events is None else _event_names(events)
        self._compiled = self._compile()
        #: The events :meth:`post` accepts: the ``on`` names that are not outcomes.
        self.events: frozenset[str] = frozenset(
            tr.on for tr, *_ in self._compiled if tr.on and tr.on not in OUTCOMES
        ) | (self._declared or frozenset())
        #: Load-time findings that are not errors (unreachable states, condition cycles
        #: that may loop); each is also logged once per process as a warning.
        self.warnings: list[str] = []
        self._check_cycles()
        self._check_reachable()
        for text in self.warnings:
            if text not in _WARNED:
                _WARNED.add(text)
                log.warning("%s", text)
        self._events: collections.deque[str] = collections.deque()
        self._events_lock = threading.Lock()
        self._running = False
        self._state: str | None = None
        self._last_transition: dict[str, Any] | None = None
        self._pending: list[Runnable] = []
        self._model: _Model | None = None
        self._fire_from: dict[str, dict[str, Callable[[], bool]]] = {}

    # -- construction --------------------------------------------------------------------
    def _sources(self, sources: Sequence[str], dest: str) -> list[str]:
        """The states a transition leaves from: ``"*"`` is every state except ``dest``
        (a wildcard never re-enters its own destination) and the final states."""
        if "*" not in sources:
            return list(sources)
        out = [s for s in sources if s != "*"]
        out += [name for name, state in self.states.items()
                if name != dest and not state.final and name not in out]
        return out

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
            if not sources:
                raise EngineConfigError(f"{where}.source: empty list; give a state, a list "
                                        "of states or '*'")
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
            if tr.on is not None:
                self._check_event_name(tr.on, f"{where}.on")
            when = tr.conditions("when", where)
            unless = tr.conditions("unless", where)
            if tr.on is None and not when and not unless:
                raise EngineConfigError(f"{where}: a transition needs 'on' (an outcome or "
                                        f"event: {', '.join(OUTCOMES)}, …) or a 'when' "
                                        "condition; otherwise it would fire at once")
            compiled.append((tr, when, unless, self._sources(sources, tr.dest)))
        return compiled

    def _check_event_name(self, name: str, where: str) -> None:
        if name in OUTCOMES:
            return
        close = difflib.get_close_matches(name, OUTCOMES, n=1, cutoff=0.75)
        hint = f": did you mean the outcome {close[0]!r}?" if close else ";"
        if self._declared is not None:
            if name not in self._declared:
                declared = ", ".join(map(repr, sorted(self._declared))) or "none"
                raise EngineConfigError(
                    f"{where}: unknown event {name!r}{hint} outcomes: {', '.join(OUTCOMES)}; "
                    f"declared events: {declared} (declare your own under 'events')")
            return
        # Without a declaration every other name is an event of the caller's, but a
        # near miss of an outcome is a typo that would never fire.
        if close:
            raise EngineConfigError(
                f"{where}: unknown event {name!r}{hint} Outcomes: {', '.join(OUTCOMES)}; "
                f"if {name!r} is an event you post, declare it: "
                f"StateMachineEngine(..., events=[{name!r}])")

    def _condition_edges(self) -> list[tuple[str, str, int, list[Guard]]]:
        edges = []
        for i, (tr, when, unless, sources) in enumerate(self._compiled):
            if tr.on is not None:
                continue
            guards = [Guard(c, True) for c in when] + [Guard(c, False) for c in unless]
            edges += [(src, tr.dest, i, guards) for src in sources]
        return edges

    def _check_cycles(self) -> None:
        """Reject cycles of condition-only transitions whose guards can all hold at once
        (the machine would loop without waiting); warn where that cannot be decided."""
        edges = self._condition_edges()
        out: dict[str, list[tuple[str, int, list[Guard]]]] = {}
        for src, dest, i, guards in edges:
            out.setdefault(src, []).append((dest, i, guards))
        order = {name: k for k, name in enumerate(self.states)}
        budget = [_MAX_CYCLE_PATHS]
        maybe: list[str] = []

        def describe(path: list[str], used: list[int]) -> str:
            states = " → ".join(map(repr, [*path, path[0]]))
            return f"{states} ({', '.join(f'transitions[{i}]' for i in used)})"

        # Simple cycles, each found once from its lowest state; a path whose guards
        # already contradict each other is not extended.
        def search(start: str, node: str, path: list[str], used: list[int],
                   guards: list[Guard]) -> None:
            for dest, i, more in out.get(node, ()):
                budget[0] -= 1
                if budget[0] < 0:
                    return
                if order[dest] < order[start] or (dest != start and dest in path):
                    continue
                answer = can_hold_together(guards + more)
                if answer.verdict is Verdict.NEVER:
                    continue
                if dest == start:
                    cycle = describe(path, [*used, i])
                    if answer.verdict is Verdict.POSSIBLE:
                        shown = ", ".join(f"{k} = {v!r}" for k, v in answer.witness.items())
                        raise EngineConfigError(
                            f"condition cycle {cycle}: every guard holds when {shown}, so "
                            "the machine would go round without waiting, restarting what "
                            "the states start; make the guards exclusive (e.g. 'x < 20' "
                            "one way, 'x > 90' back) or trigger one of them with 'on'")
                    maybe.append(f"condition cycle {cycle} may loop without waiting: its "
                                 f"guards {', '.join(answer.opaque)} are callables that "
                                 "cannot be checked before running (the running machine "
                                 "fails after 100 transitions without waiting)")
                    continue
                search(start, dest, [*path, dest], [*used, i], guards + more)

        for start in self.states:
            search(start, start, [start], [], [])
        if budget[0] < 0:
            maybe.append(f"too many condition transitions to check every cycle (more than "
                         f"{_MAX_CYCLE_PATHS} paths); loops are detected while running")
        self.warnings += [self._origin(text) for text in maybe]

    def _check_reachable(self) -> None:
        reached = {self.initial}
        frontier = [self.initial]
        while frontier:
            node = frontier.pop()
            for tr, _when, _unless, sources in self._compiled:
                if node in sources and tr.dest not in reached:
                    reached.add(tr.dest)
                    frontier.append(tr.dest)
        for name in self.states:
            if name not in reached:
                self.warnings.append(self._origin(
                    f"state {name!r} is unreachable: no transition leads to it from the "
                    f"initial state {self.initial!r}; add one or remove the state"))

    def _origin(self, text: str) -> str:
        return f"{self.origin}: {text}" if self.origin else text

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, resolve_start: StartResolver,
                  where: str = "", origin: str = "") -> StateMachineEngine:
        """Build from the dict / YAML form (see :class:`StateMachineSpec`).

        ``resolve_start(entry, key_path)`` turns each ``start`` entry into a Starter
        (the YAML behaviour resolves action names through its registry). Errors name the
        key path, prefixed with ``where``; warnings name ``origin`` (the file) and
        ``where``.
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
        label = ": ".join(part for part in (origin, where) if part)
        try:
            return cls(states, transitions, initial=spec.initial, events=spec.events,
                       origin=label)
        except EngineConfigError as exc:
            raise EngineConfigError(f"{prefix}{exc}" if prefix else str(exc)) from None

    def _build_machine(self, blackboard: Readable) -> _Model:
        transitions_mod = require("transitions", extra="engines")
        model = _Model()
        configs = []
        for tr, when, unless, sources in self._compiled:
            configs.append({
                "trigger": tr.trigger,
                "source": sources,
                "dest": tr.dest,
                # transitions calls guards without arguments: bind the blackboard here.
                "conditions": [_bind(c, blackboard) for c in when],
                "unless": [_bind(c, blackboard) for c in unless],
            })
        machine = transitions_mod.Machine(
            model=model, states=list(self.states), transitions=configs,
            initial=self.initial, auto_transitions=False, ignore_invalid_triggers=True,
            send_event=False)
        fires = {name: _bound_trigger(event, model) for name, event in machine.events.items()}
        # Per state, only the triggers it has transitions for: firing another one would
        # make transitions log "Can't trigger event …" at every decision step.
        self._fire_from = {name: {} for name in self.states}
        for tr, _when, _unless, sources in self._compiled:
            for src in sources:
                self._fire_from[src][tr.trigger] = fires[tr.trigger]
        return model

    # -- public runtime API --------------------------------------------------------------
    @property
    def state(self) -> str | None:
        """The current state (None when not running)."""
        return self._state

    def post(self, event: str) -> bool:
        """Fire ``event`` (a transition's ``on``) in the behaviour's thread, soon. Safe
        from any thread.

        Returns True when the running machine queued it. While the machine is not running
        (before its behaviour started, after it ended) the event is dropped, logged and
        False is returned: an event is about *now*, like a message on a topic nobody
        listens to, so a stale ``shutdown`` never fires at the next start. An event the
        current state has no transition for is ignored, as in ``transitions``. A name
        that is not one of :attr:`events` raises :class:`UnknownEvent`.
        """
        if event not in self.events:
            events = ", ".join(map(repr, sorted(self.events))) or "none"
            why = ("is an outcome: the engine fires it when what a state started ends; "
                   if event in OUTCOMES else "is used by no transition; ")
            raise UnknownEvent(event, self.events, message=(
                f"cannot post {event!r}: it {why}the machine's events: {events}"))
        with self._events_lock:
            if not self._running:
                log.info("event %r dropped: the state machine is not running", event)
                return False
            self._events.append(event)
        context = self._context
        if context is not None:
            context.wake()
        return True

    @property
    def last_transition(self) -> dict[str, Any] | None:
        """The last transition taken in the current (or last) run: ``source``, ``dest``,
        ``trigger`` (an outcome, an event, or ``"when"`` for a condition) and ``time``
        (wall clock, s); None before the first one."""
        last = self._last_transition
        return None if last is None else dict(last)

    def describe(self) -> dict[str, Any]:
        """Where the machine is now, JSON-serialisable: ``{"kind": "state_machine",
        "state": …, "states": […], "last_transition": {…} or None}``. Safe from any
        thread (the high-level snapshot calls it)."""
        return {"kind": "state_machine", "state": self._state, "states": list(self.states),
                "last_transition": self.last_transition,
                "structure_id": self.structure_id()}

    def structure(self) -> dict[str, Any]:
        """The machine as a graph, JSON-serialisable: ``{"kind": "state_machine",
        "initial", "states": [{"name", "final", "starts": [{"label", "action_type"}]}],
        "transitions": [{"source", "dest", "on", "when": [...], "unless": [...],
        "label"}], "events": [...]}``. A wildcard transition (``"*"``) is listed once,
        with ``"source": "*"`` and the states it leaves in ``"sources"``; ``label`` reads
        ``on [when] [not unless]`` (``action_type`` is null where a starter is a factory
        rather than an Action class)."""
        states = []
        for state in self.states.values():
            starts = [{"label": s.name, "action_type": _action_type_of(s)}
                      for s in state.starters]
            states.append({"name": state.name, "final": state.final, "starts": starts})
        transitions = []
        for tr, when, unless, sources in self._compiled:
            whens = [condition_label(c) for c in when]
            unlesses = [condition_label(c) for c in unless]
            parts = ([tr.on] if tr.on else []) + [f"[{w}]" for w in whens]
            parts += [f"[not {u}]" for u in unlesses]
            common = {"dest": tr.dest, "on": tr.on, "when": whens, "unless": unlesses,
                      "label": " ".join(parts)}
            if tr.source == "*":  # one edge from "any state", not one per state
                transitions.append({"source": "*", "sources": list(sources), **common})
            else:
                transitions += [{"source": src, **common} for src in sources]
        return {"kind": "state_machine", "initial": self.initial, "states": states,
                "transitions": transitions, "events": sorted(self.events)}

    # -- the driver ----------------------------------------------------------------------
    def on_start(self, context: EngineContext) -> None:
        self._model = self._build_machine(context.blackboard)
        self._last_transition = None
        with self._events_lock:
            self._events.clear()
            self._running = True
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
        fires = self._fire_from[self._state]  # type: ignore[index]
        if self._events:
            with self._events_lock:
                event = self._events.popleft()
            fire = fires.get(event)
            if fire is None:
                log.debug("event %r ignored: no transition from state %r takes it", event,
                          self._state)
            elif fire():
                self._enter(context, self._model.state, event)  # type: ignore[union-attr]
                return True
        if self._pending:
            outcome = self._outcome()
            if outcome is not None:
                return self._settle(context, outcome)
        tick = fires.get(_TICK)
        if tick is not None and tick():
            self._enter(context, self._model.state, "when")  # type: ignore[union-attr]
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
        fires = self._fire_from[state]  # type: ignore[index]
        for trigger in (outcome, "done"):
            fire = fires.get(trigger)
            if fire is not None and fire():
                context.stop([h for h in pending if not h.status.finished])
                self._enter(context, self._model.state, trigger)  # type: ignore[union-attr]
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

    def _enter(self, context: EngineContext, name: str, trigger: str | None = None) -> None:
        if self._pending:
            context.stop(self._pending)
            self._pending = []
        if trigger is not None:
            self._last_transition = {"source": self._state, "dest": name,
                                     "trigger": trigger, "time": time.time()}
        self._state = name
        breakpoints.entered(context.behavior, "state", name)
        starters = self.states[name].starters
        if starters:
            self._pending = [context.start(s) for s in starters]

    def on_stop(self, context: EngineContext) -> None:
        with self._events_lock:
            self._running = False
            self._events.clear()
        self._state = None  # documented: None when not running
        if self._pending:
            context.stop(self._pending)
            self._pending = []
        self._model = None
        self._fire_from = {}

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
            for src in sources:
                graph.edge(src, tr.dest, " ".join(parts))
        return graph


def _action_type_of(starter: Starter) -> str | None:
    factory = starter.factory
    action_type = getattr(factory, "action_type", None) if isinstance(factory, type) else None
    return action_type if isinstance(action_type, str) else None


def _bind(condition: Condition, blackboard: Readable) -> Callable[..., bool]:
    def guard(*_args: Any, **_kwargs: Any) -> bool:
        return condition(blackboard)
    return guard


def _bound_trigger(event: Any, model: _Model) -> Callable[[], bool]:
    def fire() -> bool:
        return bool(event.trigger(model))
    return fire
