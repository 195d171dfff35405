"""Breakpoints: pause the robot when a state, a tree node or an action type is entered.

A debugger for behaviours, as Groot2 Pro offers for trees, over the manager's own pause
(:meth:`~beehave.HighLevelBehaviorManager.pause`): when the robot gets to a breakpoint,
every action goes to its safe state, the behaviour keeps its place, and
:meth:`Breakpoints.resume` ("continue") lets it go on::

    bps = Breakpoints(hl)
    bps.add("action_type", "driving")     # before any driving action runs
    bps.add("state", "charge")            # a state machine enters "charge"
    bps.add("node", "root/charge?/dock")  # a tree node (its path, or its name) is entered
    ...
    bps.hit         # where it stopped: {"kind", "target", "path", "stamp"} or None
    bps.resume()    # continue
    bps.close()

What "entered" means, per kind:

- ``action_type``: an action of that type starts (its ``started`` event, before its
  ``run``); the action then waits for the resume before it moves. An action run again
  after a pause is not a new entry.
- ``state``: a state machine enters the state (also re-entered by a transition to itself).
- ``node``: a tree node is ticked into a new status from one that was not RUNNING
  (INVALID, SUCCESS or FAILURE → RUNNING, SUCCESS or FAILURE): a leaf that starts, a
  condition whose outcome changes; a condition that keeps holding stops the robot once,
  not at every tick.

The checks run in the robot's threads and cost a dictionary lookup when no breakpoint is
set; the pause itself is carried out in a manager thread (:meth:`request_pause`), and
the thread that hit the breakpoint waits until the pause is on (an action before its
``run``, a behaviour before its engine starts what it entered). The engines report entries
through :func:`entered`; actions are watched on the manager's events. One
:class:`Breakpoints` per manager: whoever creates it closes it.
"""

from __future__ import annotations

import logging
import threading
import time
import weakref
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from beehave.behavior import running_engines
from beehave.errors import BadRequest, BeehaveError, UnknownNameError
from beehave.events import Event, EventKind
from beehave.runnable import current

if TYPE_CHECKING:
    from beehave.highlevel import HighLevelBehaviorManager

log = logging.getLogger(__name__)

__all__ = ["KINDS", "Breakpoints", "UnknownBreakpointTarget", "entered", "of"]

#: The kinds of breakpoints and what their target names.
KINDS = {"state": "a state of a state machine",
         "node": "a behaviour-tree node (its path, or its name)",
         "action_type": "an action type"}

# Weak both ways: the Breakpoints refer to their manager, so a strong value would keep
# the key (the manager) alive for ever once nobody closes them.
_BY_MANAGER: weakref.WeakKeyDictionary[Any, weakref.ref[Breakpoints]] = (
    weakref.WeakKeyDictionary())


def _points(manager: Any) -> Breakpoints | None:
    ref = _BY_MANAGER.get(manager)
    return None if ref is None else ref()


class UnknownBreakpointTarget(UnknownNameError):
    """A breakpoint on a state, node or action type that does not exist."""

    def __init__(self, kind: str, name: str, choices: Iterable[str]) -> None:
        self.kind = {"state": "state", "node": "tree node",
                     "action_type": "action type"}.get(kind, kind)
        super().__init__(name, choices)
        listed = ", ".join(repr(c) for c in self.choices) or "none"
        self.args = (f"no breakpoint possible on {self.kind} {name!r}: it does not exist; "
                     f"known {self.kind}s: {listed}",)


def of(manager: Any) -> Breakpoints | None:
    """The :class:`Breakpoints` of ``manager``, or None."""
    return _points(manager)


def entered(behavior: Any, kind: str, target: str, *, also: str | None = None) -> None:
    """An engine tells that ``behavior``'s engine entered ``target`` (a state name, a tree
    node path; ``also``: another name that may be set, a node's plain name). Called in the
    behaviour's thread; costs a lookup when the manager has no breakpoints."""
    manager = getattr(behavior, "_manager", None)
    if manager is None:
        return
    points = _points(manager)
    if points is not None:
        seen = points._pauses
        if points._check(kind, target, also, behavior.path):
            # Before the engine starts what it entered: not a step before the pause.
            points._await_paused(behavior, seen)


def wanted(behavior: Any, kind: str) -> bool:
    """Whether ``behavior``'s manager has breakpoints of ``kind`` (engines skip their
    comparisons otherwise)."""
    manager = getattr(behavior, "_manager", None)
    points = None if manager is None else _points(manager)
    return points is not None and bool(points._targets[kind])


class Breakpoints:
    """The breakpoints of one high-level manager (see the module docstring).

    ``choices(kind)`` lists what may be set (the states and nodes of the engines that run
    or are registered with an ``engine`` parameter, the action types of every imported
    Action class); :meth:`add` refuses anything else with
    :class:`UnknownBreakpointTarget` naming them.
    """

    def __init__(self, high: HighLevelBehaviorManager) -> None:
        if of(high) is not None:
            raise BeehaveError("this manager has its Breakpoints already (beehave.breakpoints"
                               ".of(manager) returns them)")
        self.high = high
        self._lock = threading.Lock()
        self._targets: dict[str, frozenset[str]] = {k: frozenset() for k in KINDS}
        self._hit: dict[str, Any] | None = None
        # Pauses seen begin or end (paused and resumed events), and the behaviours waiting
        # for the one they asked for.
        self._pauses = 0
        self._waiting: set[Any] = set()
        self._unsubscribe: Callable[[], None] | None = high.subscribe(self._on_event)
        _BY_MANAGER[high] = weakref.ref(self)

    # -- setting ---------------------------------------------------------------------------
    def add(self, kind: str, target: str) -> dict[str, list[str]]:
        """Set a breakpoint; returns :meth:`listing`."""
        kind, target = self._checked(kind, target)
        if target not in self.choices(kind):
            raise UnknownBreakpointTarget(kind, target, self.choices(kind))
        with self._lock:
            self._targets[kind] = self._targets[kind] | {target}
        return self.listing()

    def remove(self, kind: str, target: str) -> dict[str, list[str]]:
        """Remove a breakpoint (one that is not set is not an error); returns
        :meth:`listing`."""
        kind, target = self._checked(kind, target)
        with self._lock:
            self._targets[kind] = self._targets[kind] - {target}
        return self.listing()

    def clear(self) -> None:
        with self._lock:
            self._targets = {k: frozenset() for k in KINDS}

    def listing(self) -> dict[str, list[str]]:
        """``{kind: [targets]}`` for every kind."""
        targets = self._targets
        return {kind: sorted(targets[kind]) for kind in KINDS}

    @staticmethod
    def _checked(kind: Any, target: Any) -> tuple[str, str]:
        if kind not in KINDS:
            raise BadRequest(f"unknown breakpoint kind {kind!r}; valid: "
                             f"{', '.join(repr(k) for k in KINDS)}")
        if not isinstance(target, str) or not target or len(target) > 500:
            raise BadRequest(f"a {kind} breakpoint needs a name (a string of 1 to 500 "
                             f"characters), got {str(target)[:80]!r}")
        return kind, target

    def choices(self, kind: str) -> list[str]:
        """What a breakpoint of ``kind`` may name now."""
        if kind == "action_type":
            return sorted(_action_types())
        out: set[str] = set()
        for structure in self._structures():
            if kind == "state" and structure.get("kind") == "state_machine":
                out.update(s["name"] for s in structure.get("states", []))
            elif kind == "node" and structure.get("kind") == "behaviour_tree":
                for node in structure.get("nodes", []):
                    out.update((node["path"], node["name"]))
        return sorted(out)

    def _structures(self) -> list[dict[str, Any]]:
        from beehave.engines.engine import DecisionEngine

        engines: list[Any] = []
        for _name, (_cls, params) in list(self.high._registry.items()):
            engines += [v for v in params.values() if isinstance(v, DecisionEngine)]

        engines += [engine for _path, engine in running_engines(self.high.top)]
        out = []
        for engine in {id(e): e for e in engines}.values():
            structure = engine.structure()
            if structure is not None:
                out.append(structure)
        return out

    # -- hitting and continuing -------------------------------------------------------------
    @property
    def hit(self) -> dict[str, Any] | None:
        """Where the robot stopped: ``{"kind", "target", "path", "stamp"}`` (``path`` is
        the behaviour or action that entered it), or None (no breakpoint holds it now)."""
        hit = self._hit
        if hit is not None and not self.high.paused:
            return None  # resumed by someone else (the pause button, a switch)
        return None if hit is None else dict(hit)

    def resume(self) -> bool:
        """Continue: end the pause (whoever paused). Returns whether a pause ended."""
        self._hit = None
        return self.high.resume()

    def state(self) -> dict[str, Any]:
        """``{"breakpoints": listing, "hit": hit or None, "paused": bool}``."""
        return {"breakpoints": self.listing(), "hit": self.hit, "paused": self.high.paused}

    def _check(self, kind: str, target: str, also: str | None, path: str) -> bool:
        """Pause when ``target`` (or ``also``) is a breakpoint; whether a pause was asked
        for."""
        targets = self._targets[kind]
        if not targets:
            return False
        name = target if target in targets else also if also in targets else None
        if name is None:
            return False
        return self._stop(kind, name, path)

    def _stop(self, kind: str, target: str, path: str) -> bool:
        """Ask for the pause; whether it was asked for (not when one is on already, nor
        once the manager shuts down)."""
        if self.high.paused:
            return False
        self._hit = {"kind": kind, "target": target, "path": path, "stamp": time.time()}
        log.info("breakpoint on %s %r hit by %s: pausing", kind, target, path)
        try:
            self.high.request_pause()
        except BeehaveError as exc:  # shutting down: nothing to pause
            log.info("breakpoint %s %r: no pause (%s)", kind, target, exc)
            return False
        return True

    def _await_paused(self, behavior: Any, seen: int) -> None:
        """In ``behavior``'s thread, after its engine entered a breakpoint: wait until
        the pause it asked for is on (a ``paused`` event, or any pause ending) or the
        behaviour is interrupted (a switch, the shutdown), at most ``stop_timeout_s`` +
        0.25 s.
        The pause is carried out in a manager thread; the engine would otherwise start the
        state's actions first, and they would move before it lands."""
        high = self.high

        def reached() -> bool:
            return self._pauses != seen or behavior._interrupt_requested

        cond = behavior._cond
        with self._lock:
            self._waiting.add(behavior)
        try:
            with high.clock.blocked(reached), cond:
                cond.wait_for(reached, high.stop_timeout_s + 0.25)
        finally:
            with self._lock:
                self._waiting.discard(behavior)

    def _on_event(self, event: Event) -> None:
        if event.kind in (EventKind.PAUSED, EventKind.RESUMED):
            with self._lock:
                self._pauses += 1
                waiting = list(self._waiting)
            for behavior in waiting:
                with behavior._cond:
                    behavior._cond.notify_all()
            if event.kind is EventKind.RESUMED:
                # Whoever ended the pause (the pause button, a switch): a later pause is
                # not this breakpoint's.
                self._hit = None
            return
        if event.kind is not EventKind.STARTED or not self._targets["action_type"]:
            return
        if event.detail.get("resumed"):
            return  # the same action going on after a pause: not a new entry
        from beehave.action import Action

        node = current()
        if not isinstance(node, Action) or node.path != event.subject:
            return
        action_type = node.action_type
        if not isinstance(action_type, str):
            return
        if self._check("action_type", action_type, None, event.subject):
            # In the action's own thread, before its run(): not a step before the pause.
            node._await_pause(self.high.stop_timeout_s)

    def close(self) -> None:
        """Stop watching; the breakpoints are gone (a pause they caused stays)."""
        unsubscribe, self._unsubscribe = self._unsubscribe, None
        if unsubscribe is not None:
            unsubscribe()
        if _points(self.high) is self:
            del _BY_MANAGER[self.high]


def _action_types() -> set[str]:
    from beehave.action import Action

    out: set[str] = set()
    stack = list(Action.__subclasses__())
    seen: set[type] = set()
    while stack:
        cls = stack.pop()
        if cls in seen:
            continue
        seen.add(cls)
        stack.extend(cls.__subclasses__())
        action_type = getattr(cls, "action_type", None)
        if isinstance(action_type, str) and action_type:
            out.add(action_type)
    return out
