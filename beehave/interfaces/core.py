"""The control-plane core: what every network interface offers, validated in one place.

ROS 2 (:mod:`beehave.ros.bridge`), VDA 5050 over MQTT and HTTP/WebSocket
(:mod:`beehave.interfaces.http`) are thin adapters over one :class:`ControlPlane`: they
parse their own wire format, call these methods and map the typed errors to their own
error form (an HTTP 4xx, a VDA 5050 ``errors`` entry, a refused ROS parameter). None of
them checks a behaviour name or a parameter itself, so the three always agree on what is
valid and on what the error says.

Errors (all :class:`~beehave.errors.BeehaveError`):

- :class:`~beehave.errors.UnknownBehavior` — a name that is not registered (lists them);
- :class:`~beehave.errors.InvalidParameters` — parameters the constructor cannot take, or
  values that are not JSON;
- :class:`~beehave.errors.ConstructorFailed` — the behaviour's own ``__init__`` raised;
- :class:`~beehave.errors.ManagerShutdown` — the manager is not running any more;
- :class:`~beehave.errors.UnknownKey` — a blackboard key that holds no value (names close
  matches);
- :class:`~beehave.errors.BadRequest` — a request of the wrong shape (a name that is not a
  string, parameters that are not a mapping, a negative ``limit``);
- :class:`~beehave.errors.BlackboardError` — a key or pattern that is not valid.
"""

from __future__ import annotations

import difflib
import inspect
import logging
import math
import threading
import time
import typing
from collections import deque
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from pydantic import TypeAdapter, ValidationError

from beehave.behavior import running_engines
from beehave.blackboard import Blackboard, check_key, to_json
from beehave.breakpoints import KINDS as BREAKPOINT_KINDS
from beehave.breakpoints import Breakpoints, UnknownBreakpointTarget
from beehave.breakpoints import of as breakpoints_of
from beehave.errors import BadRequest, InvalidParameters, UnknownBehavior, UnknownKey
from beehave.errors import shorten as _shorten
from beehave.events import Event
from beehave.highlevel import IDLE, HighLevelBehaviorManager

if TYPE_CHECKING:
    from beehave.lowlevel import LowLevelBehaviorManager

log = logging.getLogger(__name__)

#: The schema of :meth:`ControlPlane.status` (published on ``beehave/high_level/state``).
STATE_SCHEMA = "beehave/high_level/state/2"
#: The schema of :meth:`ControlPlane.snapshot`.
SNAPSHOT_SCHEMA = "beehave/snapshot/1"

EventDict = dict[str, Any]
EventListener = Callable[[EventDict], None]


class ControlPlane:
    """One robot's operations for network interfaces: switch, stop, status, snapshot,
    blackboard, events.

    ``high`` is the robot's high level; ``low`` its low level when it runs in this process
    (its logics and its events are then included); ``blackboard`` is what
    :meth:`blackboard` reads (default ``high.blackboard``: under ROS 2 the mirror of the
    low level's); ``name`` names the robot in what the adapters send; ``events_kept`` is
    the length of the event ring buffer that :meth:`events` reads; ``low_refresh_s``: how
    old the low level's part of :meth:`snapshot` may get when no low-level event came (it
    is re-read at once after every one: reading it crosses into the low level's loop,
    which at a viewer's 20 Hz cost a robot more than the rest of the snapshot).

    Every method is safe from any thread. The plane subscribes to the managers' events
    when it is created and unsubscribes in :meth:`close` (whoever creates it closes it).
    """

    def __init__(self, high: HighLevelBehaviorManager, *,
                 low: LowLevelBehaviorManager | None = None,
                 blackboard: Blackboard | None = None, name: str = "robot",
                 events_kept: int = 500, low_refresh_s: float = 1.0) -> None:
        if not isinstance(events_kept, int) or isinstance(events_kept, bool) \
                or events_kept < 1:
            raise BadRequest(f"ControlPlane {name!r}: events_kept must be an int >= 1, "
                             f"got {events_kept!r}")
        self.high = high
        self.low = low
        self.name = name
        #: What :meth:`blackboard` reads (adapters may subscribe to it for live updates).
        self.board = blackboard if blackboard is not None else high.blackboard
        self._lock = threading.Lock()
        self._ring: deque[EventDict] = deque(maxlen=events_kept)
        self._seq = 0
        self._listeners: tuple[EventListener, ...] = ()
        self._closed = False
        self.low_refresh_s = low_refresh_s
        self._low_cache: tuple[float, dict[str, Any]] | None = None
        self._low_dirty = True
        self._unsubscribe = [high.subscribe(self._on_high_event)]
        if low is not None:
            self._unsubscribe.append(low.subscribe(self._on_low_event))

    # -- what can run -----------------------------------------------------------------------

    def behaviors(self) -> list[dict[str, Any]]:
        """The registered top-level behaviours, ``idle`` included, sorted by name:
        ``{"name", "class", "doc", "current", "parameters": [{"name", "type", "default",
        "required"}]}``. A parameter given at registration shows that value as its default
        and is not required."""
        current = self.high.current
        return [_describe(name, cls, registered, current == name)
                for name, (cls, registered) in _registry(self.high)]

    def logics(self) -> list[dict[str, Any]]:
        """The registered top-level logics in the same shape ([] without a low level)."""
        low = self.low
        if low is None:
            return []
        current = low.current
        return [_describe(name, cls, registered, current == name)
                for name, (cls, registered) in _registry(low)]

    # -- commands ---------------------------------------------------------------------------

    def switch(self, name: str, params: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Ask the high level to switch to ``name`` with ``params`` and return at once:
        ``{"requested": name, "params": {...}}``.

        Everything is checked before anything stops: the name (registered, else
        :class:`~beehave.errors.UnknownBehavior` listing the names), the parameters (a
        mapping of names to JSON values, accepted by the constructor, else
        :class:`~beehave.errors.InvalidParameters`), the constructor itself
        (:class:`~beehave.errors.ConstructorFailed`). The switch then runs in a manager
        thread; its outcome arrives as events (``switch_completed``, or
        ``switch_superseded`` when a later request overtook it)."""
        checked = self.check_switch(name, params)
        self.high.request_switch(name, **checked)
        return {"requested": name, "params": to_json(checked)}

    def check_switch(self, name: str, params: Mapping[str, Any] | None = None
                     ) -> dict[str, Any]:
        """What :meth:`switch` checks before anything stops, without switching: raises
        :class:`~beehave.errors.BadRequest`, :class:`~beehave.errors.UnknownBehavior`
        (listing the names) or :class:`~beehave.errors.InvalidParameters` (naming the
        parameter and the type it expects); returns the parameters converted to the
        constructor's annotated types, ready for ``high.request_switch(name, **params)``
        (which still reports a constructor that raises). For adapters that need the
        behaviour object the switch creates (the ROS 2 ``execute_behavior`` goal follows
        it to its end)."""
        if not isinstance(name, str):
            raise BadRequest(f"{self.name}: the behaviour to switch to must be a string, got "
                             f"{type(name).__name__} {name!r}; registered: "
                             f"{', '.join(self.high.names)}")
        names = self.high.names
        if name not in names:
            raise UnknownBehavior(name, names)
        checked = _check_params(name, params)
        cls = dict(self.high._registry)[name][0]  # same package: the framework's manager
        return _check_types(name, cls, checked)

    def stop(self) -> dict[str, Any]:
        """Switch to ``idle``: every action is interrupted and ends in its safe state."""
        return self.switch(IDLE)

    def pause(self) -> dict[str, Any]:
        """Pause the robot in place (:meth:`HighLevelBehaviorManager.pause`) and return at
        once: ``{"pausing": True}``, or ``{"pausing": False, "paused": True}`` when it is
        paused already. The ``paused`` event says when every action stands safe."""
        if self.high.paused:
            return {"pausing": False, "paused": True}
        self.high.request_pause()
        return {"pausing": True}

    def resume(self) -> dict[str, Any]:
        """End the pause: ``{"resumed": True}``, or ``{"resumed": False}`` when none was on
        (nothing is refused: a resume of a running robot changes nothing)."""
        return {"resumed": self.high.resume()}

    # -- breakpoints ------------------------------------------------------------------------

    def breakpoints(self) -> dict[str, Any]:
        """``{"breakpoints": {kind: [targets]}, "hit": {"kind", "target", "path",
        "stamp"} or None, "paused": bool, "choices": {kind: [names]}}`` (see
        :mod:`beehave.breakpoints`)."""
        points = self._breakpoints()
        out = points.state()
        out["choices"] = {kind: points.choices(kind) for kind in BREAKPOINT_KINDS}
        return out

    def set_breakpoint(self, kind: str, target: str) -> dict[str, Any]:
        """Pause the robot when ``target`` (a state, a tree node, an action type: ``kind``)
        is entered; an unknown kind is a :class:`~beehave.errors.BadRequest`, an unknown
        target an :class:`~beehave.breakpoints.UnknownBreakpointTarget` naming the valid
        ones. Returns :meth:`breakpoints`."""
        self._breakpoints().add(kind, target)
        return self.breakpoints()

    def clear_breakpoint(self, kind: str, target: str) -> dict[str, Any]:
        """Remove a breakpoint; returns :meth:`breakpoints`. One that is not set is not an
        error, but a target that is neither set nor a valid choice (a typo, which would
        leave the meant breakpoint set) is an
        :class:`~beehave.breakpoints.UnknownBreakpointTarget` naming both."""
        points = self._breakpoints()
        if kind in BREAKPOINT_KINDS:  # a bad kind or target: remove() says which
            known = set(points.listing()[kind]) | set(points.choices(kind))
            if isinstance(target, str) and target and target not in known:
                raise UnknownBreakpointTarget(kind, target, sorted(known))
        points.remove(kind, target)
        return self.breakpoints()

    def continue_(self) -> dict[str, Any]:
        """Continue after a breakpoint (ends the pause): ``{"resumed": bool}``."""
        return {"resumed": self._breakpoints().resume()}

    def _breakpoints(self) -> Breakpoints:
        # Looked up each time, not kept: another plane of the same manager (VDA 5050's own,
        # a ROS bridge's) may have made them and closed them with itself since.
        with self._lock:
            points = breakpoints_of(self.high)
            if points is None:
                points = Breakpoints(self.high)
                self._unsubscribe.append(points.close)  # ours: closed with the plane
            return points

    def structures(self) -> list[dict[str, Any]]:
        """The structure of every running decision engine (what a viewer draws once; the
        updates carry only its ``structure_id`` and the statuses):
        ``[{"path", "structure_id", **engine.structure()}]`` (see
        :meth:`~beehave.engines.engine.DecisionEngine.structure`)."""
        out: list[dict[str, Any]] = []
        for path, engine in running_engines(self.high.top):
            structure = engine.structure()
            if structure is not None:
                out.append({"path": path, "structure_id": engine.structure_id(),
                            **to_json(structure)})
        return out

    # -- what runs --------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """What runs now, in strict JSON (the ``beehave/high_level/state/2`` message)::

            {"schema", "stamp", "behavior", "logic",          # the top-level names
             "running": [{"path", "kind", "class", "status", "action_type"}],
             "engines": [{"path", "kind", ...the engine's own snapshot}],
             "locks": {action_type: holder path}, "stuck": [paths],
             "paused": bool}                                  # hl.pause() is on

        ``logic`` is the logic the top-level behaviour asks the low level for (its class
        attribute ``logic``); ``engines`` has one entry per running behaviour driven by a
        decision engine (a state machine's state, a tree's node statuses)."""
        return _status(self.high.snapshot(), self.high.top)

    def snapshot(self) -> dict[str, Any]:
        """Everything a viewer draws, in strict JSON: :meth:`status` plus ``"robot"``
        (this plane's name), ``"tree"`` (the running top-level behaviour with its
        sub-behaviours and actions, each with status, durations and its engine),
        ``"lock_details"`` (who holds each type lock since when), ``"history"`` (the last
        ended top-level behaviours) and ``"low"`` (the low level's logic tree, HALs and
        loop health, as of its last event or at most ``low_refresh_s`` old; None without
        a low level — its blackboard is :meth:`blackboard`)."""
        high = self.high.snapshot()
        out = _status(high, self.high.top)
        out.update({"schema": SNAPSHOT_SCHEMA, "robot": self.name,
                    "tree": to_json(high["top"]), "lock_details": to_json(high["locks"]),
                    "history": to_json(high["history"]), "manager": high["state"]})
        out["low"] = self._low_snapshot()
        return out

    def _low_snapshot(self) -> dict[str, Any] | None:
        low = self.low
        if low is None:
            return None
        now = time.monotonic()
        cached = self._low_cache
        if cached is not None and not self._low_dirty and now - cached[0] < self.low_refresh_s:
            return cached[1]
        self._low_dirty = False  # before reading: an event during the read marks it again
        snap = dict(low.snapshot())
        snap.pop("blackboard", None)  # served by blackboard(), which viewers poll apart
        encoded: dict[str, Any] = to_json(snap)
        self._low_cache = (now, encoded)
        return encoded

    def blackboard(self, *, key: str | None = None, pattern: str = "**"
                   ) -> dict[str, dict[str, Any]]:
        """Blackboard entries: ``{key: {"value", "stamp", "age_s", "stale", "writer"}}``.

        ``key`` reads one entry (one that holds no value raises
        :class:`~beehave.errors.UnknownKey` naming close matches); otherwise every key that
        matches ``pattern`` (``*`` one segment, ``**`` any). Values are strict JSON
        (:func:`~beehave.blackboard.to_json`: ``inf`` as ``{"$float": "inf"}``)."""
        board = self.board
        if key is not None:
            if not isinstance(key, str):
                raise BadRequest(f"{self.name}: a blackboard key must be a string, got "
                                 f"{type(key).__name__}")
            check_key(key)
            entry = board.entry(key)
            if entry is None:
                keys = board.keys()
                close = difflib.get_close_matches(key, keys, n=5, cutoff=0.5)
                raise UnknownKey(key, close, total=len(keys), robot=self.name)
            return {key: entry.as_dict()}
        if not isinstance(pattern, str):
            raise BadRequest(f"{self.name}: a blackboard pattern must be a string, got "
                             f"{type(pattern).__name__}")
        return board.snapshot(pattern)

    # -- events -----------------------------------------------------------------------------

    def events(self, *, after_seq: int = 0, limit: int = 200) -> list[dict[str, Any]]:
        """The kept events with ``seq > after_seq``, oldest first, at most ``limit`` (the
        newest ones when more are kept). Each is :meth:`Event.as_dict` in strict JSON plus
        ``"seq"`` (monotonic from 1, never reused: pass the last one seen as ``after_seq``
        to read on) and ``"source"`` (``"high"`` or ``"low"``)."""
        for label, value in (("after_seq", after_seq), ("limit", limit)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise BadRequest(f"{self.name}: events {label} must be an int >= 0, got "
                                 f"{value!r}")
        with self._lock:
            kept = [e for e in self._ring if e["seq"] > after_seq]
        return kept[len(kept) - limit:] if limit < len(kept) else kept

    def subscribe(self, callback: EventListener) -> Callable[[], None]:
        """Call ``callback(event_dict)`` for every event from now on (the dicts that
        :meth:`events` returns); returns a function that unsubscribes.

        The callback runs in the thread that produced the event — a behaviour's, an
        action's, the low level's loop: hand the dict to your own queue or loop and never
        block there. A callback that raises is logged and stays subscribed. After
        unsubscribing, a call that another thread had already begun may still finish."""
        with self._lock:
            self._listeners = (*self._listeners, callback)

        def unsubscribe() -> None:
            with self._lock:
                self._listeners = tuple(c for c in self._listeners if c is not callback)

        return unsubscribe

    def close(self) -> None:
        """Unsubscribe from the managers and drop every listener. Idempotent; the managers
        keep running (whoever started them stops them)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._listeners = ()
            unsubscribe, self._unsubscribe = self._unsubscribe, []
        for fn in unsubscribe:
            fn()

    # -- internals --------------------------------------------------------------------------

    def _on_high_event(self, event: Event) -> None:
        self._record(event, "high")

    def _on_low_event(self, event: Event) -> None:
        self._low_dirty = True  # the logic tree, a HAL or the loop changed: read it again
        self._record(event, "low")

    def _record(self, event: Event, source: str) -> None:
        data = event.as_dict()
        # params, exceptions, paths … as JSON, bounded: a refused switch with a 5 MB
        # parameter must not make every reader of the log (and every new WebSocket
        # client) receive it again.
        data["detail"] = to_json(data["detail"])
        data = {key: bounded(value) for key, value in data.items()}  # the error's text too
        data["source"] = source
        with self._lock:
            if self._closed:
                return
            self._seq += 1
            data["seq"] = self._seq
            self._ring.append(data)
            listeners = self._listeners
        for callback in listeners:
            try:
                callback(data)
            except Exception:  # an observer must not break what it observes
                log.exception("control plane %r: event listener %r raised", self.name,
                              callback)


# ---- helpers ---------------------------------------------------------------------------------

#: What an event keeps of a text (characters), a list or an object (items), and how deep.
MAX_TEXT_CHARS = 1000
MAX_ITEMS = 100
MAX_DEPTH = 8


def shorten(text: str, limit: int = MAX_TEXT_CHARS) -> str:
    """``text``, cut to ``limit`` characters with a note of how long it was."""
    return _shorten(text, limit)


def bounded(value: Any, depth: int = 0) -> Any:
    """A JSON value cut to a bounded size: texts to :data:`MAX_TEXT_CHARS` characters,
    lists and objects to :data:`MAX_ITEMS` items (a ``"…"`` entry says how many were
    left out), nesting to :data:`MAX_DEPTH` levels."""
    if isinstance(value, str):
        return shorten(value)
    if isinstance(value, (list, tuple)):
        if depth >= MAX_DEPTH:
            return f"… (a list of {len(value)} items, cut)"
        out = [bounded(v, depth + 1) for v in value[:MAX_ITEMS]]
        if len(value) > MAX_ITEMS:
            out.append(f"… ({len(value) - MAX_ITEMS} more items, cut)")
        return out
    if isinstance(value, dict):
        if depth >= MAX_DEPTH:
            return f"… (an object of {len(value)} keys, cut)"
        items = list(value.items())
        out_map = {shorten(str(k), 200): bounded(v, depth + 1) for k, v in items[:MAX_ITEMS]}
        if len(items) > MAX_ITEMS:
            out_map["…"] = f"{len(items) - MAX_ITEMS} more keys, cut"
        return out_map
    return value


def _registry(manager: Any) -> list[tuple[str, tuple[type, dict[str, Any]]]]:
    """The manager's registry, sorted by name. Read from the framework's own managers
    (same package); copied so a concurrent ``register`` cannot change it under us."""
    return sorted(dict(manager._registry).items())


def _type_name(annotation: Any) -> str | None:
    if annotation is inspect.Parameter.empty:
        return None
    if isinstance(annotation, str):  # `from __future__ import annotations`
        return annotation
    if typing.get_origin(annotation) is typing.Annotated:  # float (Gt(gt=0))
        base, *extras = typing.get_args(annotation)
        return f"{_type_name(base)} ({', '.join(repr(e) for e in extras)})"
    if isinstance(annotation, type):
        return annotation.__name__
    return repr(annotation).replace("typing.", "")


def _describe(name: str, cls: type, registered: dict[str, Any], current: bool
              ) -> dict[str, Any]:
    params: list[dict[str, Any]] = []
    try:
        signature = inspect.signature(cls)
    except (TypeError, ValueError):
        signature = None
    if signature is not None:
        hints = _annotations(cls)
        for p in signature.parameters.values():
            if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
                continue
            if p.name in registered:
                default, required = to_json(registered[p.name]), False
            elif p.default is p.empty:
                default, required = None, True
            else:
                default, required = to_json(p.default), False
            params.append({"name": p.name,
                           "type": _type_name(hints.get(p.name, p.annotation)),
                           "default": default, "required": required})
    # The class's own docstring only: an undocumented behaviour would otherwise be
    # described by the framework base class's ("Subclass it and write run…").
    own = cls.__dict__.get("__doc__")
    doc = inspect.cleandoc(own) if isinstance(own, str) else ""
    return {"name": name, "class": f"{cls.__module__}.{cls.__qualname__}",
            "doc": doc.split("\n\n")[0].strip(), "current": current, "parameters": params}


def _is_json(value: Any) -> bool:
    if value is None or isinstance(value, (bool, int, str)):
        return True
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, list):
        return all(_is_json(v) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, str) and _is_json(v) for k, v in value.items())
    return False


def _check_params(name: str, params: Mapping[str, Any] | None) -> dict[str, Any]:
    """``params`` as a plain dict, refused unless it maps names to JSON values (what every
    wire format can carry); the constructor's own check comes in ``request_switch``."""
    if params is None:
        return {}
    if not isinstance(params, Mapping):
        raise InvalidParameters(f"behavior {name!r}: parameters must be a mapping of "
                                f"parameter names to values, got {type(params).__name__}")
    out: dict[str, Any] = {}
    for key, value in params.items():
        if not isinstance(key, str) or not key.isidentifier():
            raise InvalidParameters(f"behavior {name!r}: parameter name {key!r} is not a "
                                    f"valid identifier")
        if not _is_json(value):
            raise InvalidParameters(f"behavior {name!r}: parameter {key!r} must be a JSON "
                                    f"value (string, number, bool, null, list, object), "
                                    f"got {type(value).__name__} {value!r}")
        out[key] = value
    return out


def _annotations(cls: type) -> dict[str, Any]:
    """The constructor's parameter annotations, resolved (``from __future__ import
    annotations`` included) with their ``Annotated`` constraints; {} when there are none."""
    init = cls.__dict__.get("__init__") or getattr(cls, "__init__")  # noqa: B009
    try:
        return typing.get_type_hints(init, include_extras=True)
    except Exception:  # an unresolvable forward reference: what is a real object still counts
        raw = getattr(init, "__annotations__", {}) or {}
        return {k: v for k, v in raw.items() if not isinstance(v, str)}


def _adapter(annotation: Any) -> TypeAdapter[Any] | None:
    try:
        return TypeAdapter(annotation)
    except Exception:  # a type pydantic cannot check (an arbitrary class): the constructor
        return None    # decides, as before


def _check_types(name: str, cls: type, params: dict[str, Any]) -> dict[str, Any]:
    """``params`` validated against the constructor's annotations (pydantic, lax: a JSON
    ``1`` is a fine ``float``, a list a fine ``tuple``; constraints declared with
    ``Annotated[float, Gt(0)]`` hold), converted to the annotated types; else
    :class:`InvalidParameters` naming the parameter, the expected type and the value.
    Unannotated parameters, ``Any`` and types pydantic cannot check pass unchanged; names
    the constructor does not take are left to the manager's own check."""
    if not params:
        return params
    try:
        accepted = inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return params
    hints = _annotations(cls)
    out = dict(params)
    for key, value in params.items():
        annotation = hints.get(key)
        if key not in accepted or annotation is None or annotation is Any:
            continue
        adapter = _adapter(annotation)
        if adapter is None:
            continue
        try:
            out[key] = adapter.validate_python(value)
        except ValidationError as exc:
            why = "; ".join(err.get("msg", "invalid") for err in exc.errors())
            raise InvalidParameters(
                f"behavior {name!r}: parameter {key!r} expects {_type_name(annotation)}, "
                f"got {type(value).__name__} {shorten(repr(value), 200)}: {why}") from None
    return out


def _status(snap: dict[str, Any], top: Any) -> dict[str, Any]:
    """The ``beehave/high_level/state/2`` dict from a high-level snapshot."""
    running: list[dict[str, Any]] = []
    engines: list[dict[str, Any]] = []

    def walk(node: dict[str, Any] | None) -> None:
        if node is None:
            return
        if node["status"] == "RUNNING":
            running.append({"path": node["path"], "kind": node["kind"],
                            "class": node["class"], "status": node["status"],
                            "action_type": node.get("action_type")})
            engine = node.get("engine")
            if isinstance(engine, dict):
                # to_json: an engine's snapshot may hold tuples, inf, enum members …
                encoded = to_json(engine)
                encoded.pop("path", None)
                engines.append({"path": node["path"], **encoded})
        for child in node.get("children", []):
            walk(child)

    walk(snap["top"])
    return {"schema": STATE_SCHEMA, "stamp": time.time(), "behavior": snap["current"],
            "logic": None if top is None else getattr(type(top), "logic", None),
            "running": running, "engines": engines,
            "locks": {k: v["holder"] for k, v in snap["locks"].items()},
            "stuck": snap["stuck"], "paused": bool(snap.get("paused", False))}


__all__ = ["SNAPSHOT_SCHEMA", "STATE_SCHEMA", "ControlPlane"]
