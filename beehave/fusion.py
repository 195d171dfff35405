"""Priority fusion: several logics propose commands for one actuator, an arbiter picks one.

The reflex layer often has more than one opinion about the same actuator: a wander logic
wants to drive forward, a joystick wants to steer, a bumper logic wants to back off. Like
ROS's ``twist_mux``, the :class:`Arbiter` gives every *source* a name, a priority and a
maximum age, and forwards, each cycle (``rate_hz``), the proposal of the highest priority
that is still fresh::

    inputs = {"bumper": FusionInput(priority=100, max_age_s=0.3, safety=True),
              "joystick": FusionInput(priority=50, max_age_s=0.5),
              "wander": FusionInput(priority=10, max_age_s=0.5)}
    ll.hals.register(CmdVelArbiter, name=arbiter_name("cmd_vel"),
                     actuator="cmd_vel", inputs=inputs)

    class Wander(Logic):
        async def run(self) -> None:
            drive = await self.hal(arbiter_name("cmd_vel"), Arbiter)
            while True:
                drive.propose("wander", (0.2, 0.0))    # checked here: a bad one raises
                await asyncio.sleep(0.1)

Rules, in the order the arbiter applies them each cycle:

1. A proposal is *fresh* while it is younger than its source's ``max_age_s`` and was not
   withdrawn (:meth:`Arbiter.withdraw`) or marked stale on the blackboard. Re-proposing the
   same value keeps it fresh.
2. Safety sources (``safety=True``: bumper, cliff, emergency stop) win over every
   non-safety source, whatever the priorities; among sources of one kind the higher
   priority wins (equal priorities are refused: the winner must never depend on order).
   A :class:`FusionLock` (``twist_mux``'s locks) that is engaged mutes every non-safety
   source up to its priority; a heartbeat lock also engages when it falls silent.
3. The winner's value is forwarded every cycle (so the robot's own command watchdog stays
   fed). When no fresh proposal is left, the arbiter forwards the ``safe_value`` (zero
   velocity) *once* and then stays silent: the last command never stays standing.
4. At unload (the last logic holding the arbiter ended, or shutdown) the arbiter forwards
   the safe value once more, as its ``safe_state``.

Proposals live on the blackboard under ``fusion/<actuator>/<source>`` (so the web view and
recordings see them, and a remote proposer may write them); what was forwarded is written
to ``fusion/<actuator>/winner`` as ``{"source": name or None, "value": value}``. A
proposal that arrives over the blackboard with an unknown source name or a value of the
wrong type is rejected without stopping the arbiter: logged, reported as an ENDED/FAILED
event whose subject is ``fusion:<actuator>:<source>``, counted in :attr:`Arbiter.rejected`
and written to ``fusion/<actuator>/rejected``. :meth:`Arbiter.propose` checks the same
things before writing and raises in the proposer's own code instead.

The arbiter is a HAL, not a logic: it must outlive switches of the top-level logic, it is
shared by every proposer, and the HAL manager unloads it (safe value!) when nobody uses it
any more. Subclass it for an actuator and write :meth:`Arbiter.forward` (and, to check the
values, :meth:`Arbiter.check`); :class:`hal.drive.CmdVelArbiter` is the one for
``cmd_vel``. High-level type locks stay as they are: fusion is for the reflex layer.
"""

from __future__ import annotations

import asyncio
import logging
import math
import re
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from numbers import Real
from typing import Any, ClassVar, TypeVar

from beehave.blackboard import Change, Slot
from beehave.errors import BadProposal, ConfigError, UnknownFusionSource
from beehave.events import Event, EventKind
from beehave.hal import HAL, MAX_DURATION_S
from beehave.status import Status

log = logging.getLogger(__name__)

__all__ = ["Arbiter", "FusionInput", "FusionLock", "RESERVED_NAMES", "arbiter_name", "check_name",
           "check_twist", "lock_key", "make_inputs", "make_locks", "proposal_key"]

_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")

_REJECTED: Any = object()

RESERVED_NAMES = frozenset({"winner", "rejected", "locked", "locks"})
"""Keys under ``fusion/<actuator>/`` that the arbiter writes itself: not source names."""


def arbiter_name(actuator: str) -> str:
    """The HAL name of the arbiter of ``actuator`` (``"cmd_vel"`` → ``"fusion_cmd_vel"``),
    as ``beehave run`` registers it from the ``fusion:`` section."""
    return f"fusion_{actuator}"


def proposal_key(actuator: str, source: str) -> str:
    """The blackboard key of ``source``'s proposal for ``actuator``."""
    return f"fusion/{actuator}/{source}"


def lock_key(actuator: str, lock: str) -> str:
    """The blackboard key of lock ``lock`` of ``actuator`` (True: engaged)."""
    return f"fusion/{actuator}/locks/{lock}"


def check_name(what: str, name: object) -> str:
    if not isinstance(name, str) or _NAME.fullmatch(name) is None:
        raise ConfigError(f"{what} {name!r} must be a name: a letter, then letters, digits "
                          "or '_' (it becomes a blackboard key segment)")
    return name


@dataclass(frozen=True)
class FusionInput:
    """How much one source counts: its ``priority`` (an int, higher wins), how long a
    proposal stays valid (``max_age_s``, finite seconds > 0) and whether it is a
    ``safety`` source (wins over every non-safety source)."""

    priority: int
    max_age_s: float
    safety: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.priority, int) or isinstance(self.priority, bool):
            raise ConfigError(f"fusion input priority must be an int, got {self.priority!r}")
        age = self.max_age_s
        if isinstance(age, bool) or not isinstance(age, Real) or not math.isfinite(age) \
                or not 0 < age <= MAX_DURATION_S:
            raise ConfigError(f"fusion input max_age_s must be finite seconds in (0, "
                              f"{MAX_DURATION_S:g}], got {age!r}")
        if not isinstance(self.safety, bool):
            raise ConfigError(f"fusion input safety must be true or false, got "
                              f"{self.safety!r}")
        object.__setattr__(self, "max_age_s", float(age))


@dataclass(frozen=True)
class FusionLock:
    """A lock (``twist_mux``'s locks): while engaged it mutes every non-safety source whose
    priority is at most ``priority``. It engages while its key holds True; with a
    ``max_age_s`` it is a heartbeat and also engages when its key was never written, is
    stale, or is older than that (a dead e-stop button must stop the robot, not free it)."""

    priority: int
    max_age_s: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.priority, int) or isinstance(self.priority, bool):
            raise ConfigError(f"fusion lock priority must be an int, got {self.priority!r}")
        age = self.max_age_s
        if age is not None:
            if isinstance(age, bool) or not isinstance(age, Real) or not math.isfinite(age) \
                    or not 0 < age <= MAX_DURATION_S:
                raise ConfigError(f"fusion lock max_age_s must be finite seconds in (0, "
                                  f"{MAX_DURATION_S:g}] or None, got {age!r}")
            object.__setattr__(self, "max_age_s", float(age))


_Spec = TypeVar("_Spec", FusionLock, FusionInput)


def _make_spec(cls: type[_Spec], spec: object, keys: tuple[str, ...],
               required: tuple[str, ...]) -> _Spec:
    """``spec`` as a ``cls``: one already, or a mapping of its fields (only ``keys``, with
    every one of ``required``)."""
    if isinstance(spec, cls):
        return spec
    if not isinstance(spec, Mapping):
        raise ConfigError(f"expected a {cls.__name__} or a mapping, got {spec!r:.60}")
    unknown = set(spec) - set(keys)
    if unknown:
        raise ConfigError(f"unknown key(s) {', '.join(sorted(map(str, unknown)))}"
                          f"; valid keys: {', '.join(keys)}")
    if any(key not in spec for key in required):
        raise ConfigError(f"{' and '.join(required)} "
                          f"{'is' if len(required) == 1 else 'are'} required")
    return cls(**spec)


def make_locks(actuator: str, locks: object) -> dict[str, FusionLock]:
    """Check and normalise the locks of ``actuator``'s arbiter: a mapping of lock name to
    :class:`FusionLock` (or to a mapping of its fields); None or empty: no locks."""
    if locks is None:
        return {}
    if not isinstance(locks, Mapping):
        raise ConfigError(f"arbiter {actuator!r}: locks must be a mapping of lock name → "
                          f"{{priority, max_age_s}}, got {locks!r:.80}")
    out: dict[str, FusionLock] = {}
    for name, spec in locks.items():
        check_name(f"arbiter {actuator!r}: lock name", name)
        try:
            out[name] = _make_spec(FusionLock, spec, ("priority", "max_age_s"), ("priority",))
        except ConfigError as exc:
            raise ConfigError(f"arbiter {actuator!r}: lock {name!r}: {exc}") from None
    return out


def make_inputs(actuator: str, inputs: object) -> dict[str, FusionInput]:
    """Check and normalise the inputs of ``actuator``'s arbiter: a mapping of source name to
    :class:`FusionInput` (or to a mapping of its fields). Errors name the actuator and the
    source."""
    if not isinstance(inputs, Mapping) or not inputs:
        raise ConfigError(f"arbiter {actuator!r}: inputs must be a non-empty mapping of "
                          f"source name → {{priority, max_age_s, safety}}, got {inputs!r:.80}")
    out: dict[str, FusionInput] = {}
    for name, spec in inputs.items():
        check_name(f"arbiter {actuator!r}: source name", name)
        if name in RESERVED_NAMES:
            raise ConfigError(f"arbiter {actuator!r}: source name {name!r} is reserved "
                              f"({', '.join(sorted(RESERVED_NAMES))} are written by the "
                              "arbiter itself)")
        try:
            out[name] = _make_spec(FusionInput, spec, ("priority", "max_age_s", "safety"),
                                   ("priority", "max_age_s"))
        except ConfigError as exc:
            raise ConfigError(f"arbiter {actuator!r}: input {name!r}: {exc}") from None
    # Equal priorities within one kind would make the winner depend on dict order.
    seen: dict[tuple[bool, int], str] = {}
    for name, spec in out.items():
        other = seen.setdefault((spec.safety, spec.priority), name)
        if other != name:
            kind = "safety" if spec.safety else "non-safety"
            raise ConfigError(f"arbiter {actuator!r}: inputs {other!r} and {name!r} are both "
                              f"{kind} with priority {spec.priority}; give each a different "
                              "priority")
    return out


def check_twist(value: Any) -> tuple[float, float]:
    """A ``cmd_vel`` proposal: ``(linear_mps, angular_rps)``, two finite numbers (a list
    also does, as the blackboard's JSON mirror turns tuples into lists)."""
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise TypeError(f"{value!r:.60} is not a pair of numbers")
    out: list[float] = []
    for part, label in zip(value, ("linear_mps", "angular_rps"), strict=True):
        if isinstance(part, bool) or not isinstance(part, Real) or not math.isfinite(part):
            raise TypeError(f"{label} must be a finite number, got {part!r:.30}")
        out.append(float(part))
    return out[0], out[1]


class Arbiter(HAL):
    """Forwards, each cycle, the freshest highest-priority proposal for one actuator.

    Subclass it per actuator and write :meth:`forward`; override :meth:`check` to say what a
    valid value is. Register it with the HAL manager under :func:`arbiter_name`
    (``beehave run`` does so from the ``fusion:`` section of the robot file).

    ``actuator``: the actuator's name (a blackboard key segment, e.g. ``"cmd_vel"``).
    ``inputs``: source name → :class:`FusionInput` (or a mapping of its fields).
    ``locks``: lock name → :class:`FusionLock` (or a mapping of its fields), engaged by
    writing True to :func:`lock_key` or with :meth:`set_lock`.
    ``rate_hz``: cycles per second. ``safe_value``: what is forwarded when nothing fresh is
    left and at unload (None: the class's :attr:`default_safe_value`). Ages are measured
    with the blackboard's clock (``Blackboard(clock=...)``: tests pass a fake one).

    The constructor only checks and stores its parameters (no hardware, no blackboard):
    ``beehave run`` builds one while reading the robot file to report bad values early.
    """

    name = "fusion"
    default_safe_value: ClassVar[Any] = None
    """The safe value of this kind of actuator; None: ``safe_value`` must be given."""
    expected: ClassVar[str] = "any value but None"
    """What a valid value looks like, for error messages."""

    actuator: str
    sources: dict[str, FusionInput]
    rate_hz: float
    safe_value: Any
    clock: Callable[[], float]
    cycles: int
    rejected: int
    winner: str | None
    _prefix: str
    _winner_key: str
    _rejected_key: str
    _order: tuple[tuple[str, str, float], ...]
    _slots: tuple[tuple[str, Slot, float], ...]
    _checked: dict[str, tuple[Any, Any]]
    _bad: dict[str, Any]
    _safe_sent: bool
    locks: dict[str, FusionLock]
    locked: tuple[str, ...]
    _lock_slots: tuple[tuple[str, Slot, FusionLock], ...]
    _bad_locks: dict[str, Any]

    def __init__(self, *, actuator: str, inputs: Mapping[str, FusionInput | Mapping[str, Any]],
                 rate_hz: float = 20.0, safe_value: Any = None,
                 locks: Mapping[str, FusionLock | Mapping[str, Any]] | None = None) -> None:
        self.actuator = check_name("arbiter actuator", actuator)
        self.sources = make_inputs(actuator, inputs)
        self.locks = make_locks(actuator, locks)
        if isinstance(rate_hz, bool) or not isinstance(rate_hz, Real) \
                or not math.isfinite(rate_hz) or not 0 < rate_hz <= 10_000:
            raise ConfigError(f"arbiter {actuator!r}: rate_hz must be a finite number in "
                              f"(0, 10000], got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        if safe_value is None:
            safe_value = self.default_safe_value
        if safe_value is None:
            raise ConfigError(f"arbiter {actuator!r}: safe_value is required (what to "
                              "command when no proposal is fresh)")
        try:
            self.safe_value = self.check(safe_value)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"arbiter {actuator!r}: safe_value {safe_value!r:.60} is not "
                              f"valid: {exc}; expected {self.expected}") from None
        self.clock = time.monotonic
        """Measures the proposals' ages: the blackboard's clock once loaded."""
        self.cycles = 0
        """How many cycles ran."""
        self.rejected = 0
        """How many proposals were rejected (unknown source, wrong value)."""
        self.winner: str | None = None
        """The source forwarded in the last cycle (None: the safe value, or nothing yet)."""
        self._prefix = f"fusion/{actuator}/"
        self._winner_key = f"fusion/{actuator}/winner"
        self._rejected_key = f"fusion/{actuator}/rejected"
        # Safety sources first, then by priority: the first fresh one in this order wins.
        self._order = tuple(sorted(
            ((name, self._prefix + name, spec.max_age_s) for name, spec in self.sources.items()),
            key=lambda t: (not self.sources[t[0]].safety, -self.sources[t[0]].priority)))
        # The value object last checked per source: the blackboard keeps the first object
        # of equal re-writes, so an identity test skips re-checking the value every cycle.
        self._checked = {}
        self._bad = {}
        self._safe_sent = False
        self._slots = ()
        self.locked = ()
        """The locks engaged at the last cycle."""
        self._lock_slots = ()
        self._bad_locks = {}

    # -- what subclasses write -----------------------------------------------------------

    def forward(self, value: Any) -> None:
        """Send ``value`` (already checked) to the actuator. Called by the cycle, in the
        low level's loop: keep it short and non-blocking (publish, don't wait). An
        exception ends the cycle loop like any HAL ``run`` crash: reported, restarted with
        backoff."""
        raise NotImplementedError(f"{type(self).__qualname__} must implement forward(value)")

    def check(self, value: Any) -> Any:
        """Return ``value`` as the actuator takes it, or raise ``TypeError``/``ValueError``
        saying what is wrong. Called once per new value, never per cycle."""
        if value is None:
            raise TypeError("None is not a command")
        return value

    # -- what proposers call -------------------------------------------------------------

    def propose(self, source: str, value: Any) -> None:
        """Propose ``value`` as ``source``; raises :class:`~beehave.errors.UnknownFusionSource`
        (listing the configured sources) or :class:`~beehave.errors.BadProposal` before
        anything is written. Propose again within the source's ``max_age_s`` to stay
        fresh. Safe from any thread."""
        self._checked[source] = (value, self._validate(source, value))
        self._bad.pop(source, None)
        self.blackboard.board.set(self._prefix + source, value, writer=f"fusion:{source}")

    def withdraw(self, source: str) -> None:
        """Withdraw ``source``'s proposal now (hand over to the next one at the next cycle)
        instead of letting it expire after ``max_age_s``; the next :meth:`propose` makes it
        fresh again."""
        if source not in self.sources:
            raise UnknownFusionSource(source, self.sources, actuator=self.actuator)
        self.blackboard.board.mark_stale(pattern=self._prefix + source)

    def set_lock(self, lock: str, engaged: bool) -> None:
        """Engage (True) or release (False) lock ``lock``; a heartbeat lock (``max_age_s``)
        must be released again within its max age, or it engages by itself."""
        if lock not in self.locks:
            raise UnknownFusionSource(lock, self.locks, actuator=self.actuator, kind="lock")
        if not isinstance(engaged, bool):
            raise BadProposal(f"arbiter {self.actuator!r}: lock {lock!r} must be set to "
                              f"True or False, got {engaged!r:.40}")
        self.blackboard.board.set(lock_key(self.actuator, lock), engaged,
                                  writer=f"fusion:lock:{lock}")

    def _validate(self, source: str, value: Any) -> Any:
        if source not in self.sources:
            raise UnknownFusionSource(source, self.sources, actuator=self.actuator)
        try:
            return self.check(value)
        except (TypeError, ValueError) as exc:
            raise BadProposal(f"arbiter {self.actuator!r}: proposal of source {source!r} "
                              f"rejected: {exc}; expected {self.expected}") from None

    # -- the cycle -----------------------------------------------------------------------

    async def on_load(self) -> None:
        board = self.blackboard.board
        # The blackboard stamps the proposals; ages must be read on the same clock.
        self.clock = board._clock
        for _source, key, max_age_s in self._order:
            # Watchers (web view, recordings) then see a proposal go stale, too.
            board.declare(key, max_age_s=max_age_s)
        # The blackboard's slot of each source, looked up once: a cycle reads each slot's
        # latest change as written (value, stamp, stale mark) without entry()'s per-call
        # key check and stale copy -- ten sources must cost microseconds, not tens.
        self._slots = tuple((source, board._slot(key), max_age_s)
                            for source, key, max_age_s in self._order)
        self._lock_slots = tuple((name, board._slot(lock_key(self.actuator, name)), spec)
                                 for name, spec in self.locks.items())
        # Checks every change when it is written, so that a bad value is reported even if
        # it is overwritten before the next cycle looks. The HAL's blackboard client closes
        # the subscription when the arbiter is unloaded.
        self.blackboard.subscribe(f"fusion/{self.actuator}/*", self._on_change)
        await super().on_load()

    def _on_change(self, change: Change) -> None:
        source = change.key[len(self._prefix):]
        if source in RESERVED_NAMES or change.stale:
            return
        self._admit(source, change.value)

    def _admit(self, source: str, value: Any) -> Any:
        """``value`` (on the blackboard for ``source``) as the actuator takes it, or
        :data:`_REJECTED` after reporting it (once per value)."""
        known = self._checked.get(source)
        if known is not None and known[0] is value:
            return known[1]
        if self._bad.get(source, _REJECTED) is value:
            return _REJECTED
        try:
            checked = self._validate(source, value)
        except (UnknownFusionSource, BadProposal) as exc:
            self._bad[source] = value
            self._reject(source, value, exc)
            return _REJECTED
        self._checked[source] = (value, checked)
        self._bad.pop(source, None)  # the next bad value is news again
        return checked

    def _reject(self, source: str, value: Any, exc: Exception) -> None:
        self.rejected += 1
        log.error("%s", exc)
        self.blackboard.set(self._rejected_key, {"source": source, "value": repr(value)[:80],
                                                 "reason": str(exc)})
        self.events.emit(Event(EventKind.ENDED, f"fusion:{self.actuator}:{source}",
                               Status.FAILED.name, exc))

    def select(self, now: float) -> tuple[str, Any] | None:
        """The winning ``(source, checked value)`` at time ``now``, or None when no
        proposal is fresh. Forwards nothing (a bad value found here is reported)."""
        muted = self._muted(now) if self._lock_slots else None
        for source, slot, max_age_s in self._slots:
            entry = slot.change
            if entry is None or entry.stale or now - entry.monotonic > max_age_s:
                continue
            if muted is not None and self.sources[source].priority <= muted \
                    and not self.sources[source].safety:
                continue
            checked = self._admit(source, entry.value)
            if checked is _REJECTED:
                continue
            return source, checked
        return None

    def _muted(self, now: float) -> int | None:
        """The highest priority of the engaged locks (None: none is); sets :attr:`locked`."""
        engaged: list[str] = []
        top: int | None = None
        for name, slot, spec in self._lock_slots:
            entry = slot.change
            if spec.max_age_s is not None and (
                    entry is None or entry.stale or now - entry.monotonic > spec.max_age_s):
                on = True  # a silent heartbeat: engaged
            elif entry is None:
                on = False
            elif isinstance(entry.value, bool):
                on = entry.value
                self._bad_locks.pop(name, None)
            else:  # fail safe: a lock that says nothing sensible is engaged
                on = True
                if self._bad_locks.get(name, _REJECTED) is not entry.value:
                    self._bad_locks[name] = entry.value
                    self._reject(f"locks/{name}", entry.value, BadProposal(
                        f"arbiter {self.actuator!r}: lock {name!r} must hold True or False, "
                        f"got {entry.value!r:.40}; engaged until it does"))
            if on:
                engaged.append(name)
                top = spec.priority if top is None else max(top, spec.priority)
        if tuple(engaged) != self.locked:
            self.locked = tuple(engaged)
            self.blackboard.set(f"fusion/{self.actuator}/locked", list(self.locked))
        return top

    def cycle(self) -> str | None:
        """One arbitration: forward the winner (or the safe value, once) and publish it.
        Returns the winning source (None: nothing fresh). :meth:`run` calls it at
        ``rate_hz``; tests may call it directly."""
        self.cycles += 1
        won = self.select(self.clock())
        if won is None:
            self.winner = None
            if not self._safe_sent:
                self._safe_sent = True
                self.forward(self.safe_value)
                self.blackboard.set(self._winner_key, {"source": None,
                                                       "value": self.safe_value})
            return None
        source, value = won
        self.winner = source
        self._safe_sent = False
        self.forward(value)
        self.blackboard.set(self._winner_key, {"source": source, "value": value})
        return source

    async def run(self) -> None:
        """Cycle at ``rate_hz`` until unloaded. A cycle that falls behind (a blocked loop)
        is not caught up with a burst: the schedule restarts from now."""
        loop = asyncio.get_running_loop()
        period = 1.0 / self.rate_hz
        due = loop.time()
        while True:
            self.cycle()
            due += period
            delay = due - loop.time()
            if delay < 0:
                due = loop.time()
                delay = 0.0
            await asyncio.sleep(delay)

    def safe_state(self) -> None:
        """Forward the safe value: an unloaded arbiter leaves no command standing."""
        self.winner = None
        self._safe_sent = True
        self.forward(self.safe_value)

    def snapshot(self) -> dict[str, Any]:
        """The configuration and the state: inputs, the last winner, counters."""
        return {"actuator": self.actuator, "rate_hz": self.rate_hz,
                "inputs": {n: {"priority": s.priority, "max_age_s": s.max_age_s,
                               "safety": s.safety} for n, s in self.sources.items()},
                "locks": {n: {"priority": s.priority, "max_age_s": s.max_age_s}
                          for n, s in self.locks.items()},
                "locked": list(self.locked), "winner": self.winner, "cycles": self.cycles,
                "rejected": self.rejected}
