"""Ready-made behaviours: described in YAML, commanded from outside, or random.

- :class:`YamlBehavior` runs a behaviour described entirely in a YAML file (state machine,
  tree or network; see ``docs/yaml_behaviors.md``).
- :class:`CommandedBehavior` executes commands that any interface puts into a
  :class:`CommandQueue` (``queue.put(dict)`` or ``queue.feed_json(text)`` from a ROS 2
  topic, HTTP, MQTT …).
- :class:`RandomBehavior` takes seeded random decisions, for soak tests.
"""

from __future__ import annotations

import collections
import inspect
import json
import logging
import random
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from beehave.action import Action
from beehave.behavior import Behavior
from beehave.engines.engine import format_validation_error
from beehave.errors import ActionTypeBusy, BeehaveError, ChildFailed, ConfigError
from beehave.runnable import Runnable
from beehave.status import Status

# The YAML behaviour lives beside its format (the loader starts sub-files as YAML
# behaviours); it is offered here with the other ready-made ones.
from behaviours.yaml_schema import Factory, YamlBehavior, YamlBehaviorError

__all__ = ["Command", "CommandError", "CommandQueue", "CommandedBehavior", "Outcome",
           "RandomBehavior", "YamlBehavior", "YamlBehaviorError"]

log = logging.getLogger(__name__)


# -- commanded ----------------------------------------------------------------------------

class CommandError(BeehaveError):
    """A command that cannot be executed: malformed JSON, a schema violation, an unknown
    action or parameters the action rejects. The queue also records it in ``rejected``."""


class _StartCommand(BaseModel):
    model_config = ConfigDict(extra="forbid")
    action: str | None = Field(default=None, min_length=1)
    params: dict[str, Any] = Field(default_factory=dict)
    preempt: bool = False
    cancel: str | None = Field(default=None, min_length=1)
    id: str | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> _StartCommand:
        if (self.action is None) == (self.cancel is None):
            raise ValueError("a command has exactly one of 'action' (start it) or 'cancel' "
                             "(an action name, a command id or 'all')")
        if self.cancel is not None and (self.params or self.preempt):
            raise ValueError("'cancel' takes no 'params' or 'preempt'")
        return self


@dataclass(frozen=True)
class Command:
    """A validated command. ``kind`` is ``"start"`` or ``"cancel"``."""

    kind: Literal["start", "cancel"]
    target: str  # the action name, or what to cancel
    params: Mapping[str, Any]
    preempt: bool
    id: str


@dataclass(frozen=True)
class Outcome:
    """What became of a command: ``status`` is a Status name, ``"BUSY"`` (the action type
    was held) or ``"CANCELLED"``; ``detail`` holds the result or the error's repr."""

    id: str
    action: str
    status: str
    detail: Any = None
    time: float = field(default_factory=time.time)


@dataclass(frozen=True)
class Rejected:
    """A malformed command: what arrived and why it was refused."""

    received: Any
    reason: str
    time: float = field(default_factory=time.time)


class CommandQueue:
    """A thread-safe queue of commands for a :class:`CommandedBehavior`.

    Any interface feeds it: ``put(dict)`` from Python, ``feed_json(text)`` from a ROS 2
    ``std_msgs/String`` topic, HTTP or MQTT. The schema (JSON)::

        {"action": "drive", "params": {"goal_m": 3.0}, "preempt": false, "id": "c1"}
        {"cancel": "drive"}          # an action name, a command id, or "all"

    Commands are validated on arrival against ``actions`` (name → Action class or factory
    taking the params): a malformed one raises :class:`CommandError` *and* is recorded in
    :attr:`rejected` — never silently dropped. :attr:`outcomes` records what became of the
    accepted ones (the last ``history_len``).
    """

    def __init__(self, actions: Mapping[str, Factory], *, history_len: int = 100) -> None:
        if not actions:
            raise ConfigError("a CommandQueue needs at least one action it can start")
        self.actions = dict(actions)
        self._cond = threading.Condition()
        self._items: collections.deque[Command] = collections.deque()
        self._wakers: list[Callable[[], None]] = []
        self._counter = 0
        self.rejected: collections.deque[Rejected] = collections.deque(maxlen=history_len)
        self.outcomes: collections.deque[Outcome] = collections.deque(maxlen=history_len)

    def put(self, command: Mapping[str, Any]) -> Command:
        """Validate ``command`` and queue it; return the validated :class:`Command`."""
        return self._put(command, command)

    def _put(self, command: Mapping[str, Any], received: Any) -> Command:
        try:
            parsed = self._validate(command)
        except CommandError as exc:
            self._reject(received, str(exc))
            raise
        with self._cond:
            self._items.append(parsed)
            wakers = list(self._wakers)
            self._cond.notify_all()
        for wake in wakers:
            wake()
        return parsed

    def feed_json(self, text: str | bytes) -> Command:
        """Parse a JSON command (e.g. a ROS 2 ``std_msgs/String`` payload) and :meth:`put` it.
        Malformed JSON raises :class:`CommandError` and is recorded in :attr:`rejected`."""
        try:
            data = json.loads(text)
        except (ValueError, TypeError) as exc:
            reason = f"malformed JSON command {_short(text)}: {exc}"
            self._reject(text, reason)
            raise CommandError(reason) from None
        if not isinstance(data, dict):
            reason = (f"a command is a JSON object like {{\"action\": NAME, \"params\": {{…}}}}, "
                      f"got {_short(text)}")
            self._reject(text, reason)
            raise CommandError(reason)
        return self._put(data, text)

    def _validate(self, command: Mapping[str, Any]) -> Command:
        if not isinstance(command, Mapping):
            raise CommandError(f"a command is a mapping, got {command!r}")
        try:
            raw = _StartCommand.model_validate(dict(command))
        except ValidationError as exc:
            raise CommandError(f"invalid command {_short(command)}: "
                               f"{format_validation_error(exc)}") from None
        with self._cond:
            self._counter += 1
            ident = raw.id or f"cmd{self._counter}"
        if raw.cancel is not None:
            return Command("cancel", raw.cancel, {}, False, ident)
        assert raw.action is not None
        factory = self.actions.get(raw.action)
        if factory is None:
            raise CommandError(f"unknown action {raw.action!r}; known: "
                               f"{', '.join(map(repr, sorted(self.actions)))}")
        try:
            inspect.signature(factory).bind(**raw.params)
        except TypeError as exc:
            raise CommandError(f"action {raw.action!r} rejects params {raw.params}: "
                               f"{exc}") from None
        except ValueError:  # no signature to check: the call will tell
            pass
        return Command("start", raw.action, dict(raw.params), raw.preempt, ident)

    def _reject(self, received: Any, reason: str) -> None:
        self.rejected.append(Rejected(received, reason))
        log.warning("command rejected: %s", reason)

    def _take(self) -> list[Command]:
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def _add_waker(self, wake: Callable[[], None]) -> None:
        with self._cond:
            self._wakers.append(wake)

    def _remove_waker(self, wake: Callable[[], None]) -> None:
        with self._cond:
            if wake in self._wakers:
                self._wakers.remove(wake)

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


def _short(value: Any, limit: int = 120) -> str:
    text = value if isinstance(value, str) else repr(value)
    return text if len(text) <= limit else text[:limit] + "…"


def _start_child(parent: Behavior, child: Any, *, preempt: bool, what: str) -> Runnable:
    """Start what a factory built: an Action (with ``preempt``) or a sub-Behavior."""
    if isinstance(child, Action):
        return parent.start_action(child, preempt=preempt)
    if isinstance(child, Behavior):
        return parent.start_behavior(child)
    raise ConfigError(f"{what} built {child!r}, not an Action or Behavior")


class _Wakeful(Behavior):
    """A behaviour whose ``run`` waits on one event that child ends, interrupts and
    outside feeds set (so it never polls)."""

    _wake_event: threading.Event

    def _event(self) -> threading.Event:
        event = self.__dict__.get("_wake_event")
        if event is None:
            event = self._wake_event = threading.Event()
        return event

    def wake(self) -> None:
        self._event().set()
        with self._cond:  # the runnable's condition: a clock wait in _wait_wake sleeps on it
            self._cond.notify_all()

    def _wait_wake(self, timeout_s: float | None) -> bool:
        """Wait for a wake-up or ``timeout_s`` (the manager's clock); False once
        interrupted."""
        event = self._event()
        with self._cond:
            self.manager.clock.wait(self._cond,
                                    lambda: event.is_set() or self._interrupt_requested,
                                    timeout_s)
        event.clear()
        return not self.interrupted

    def on_child_ended(self, child: Runnable) -> None:
        self.wake()

    def on_interrupt(self) -> None:
        self.wake()


class CommandedBehavior(_Wakeful):
    """Executes the commands of a :class:`CommandQueue` as they arrive.

    Each ``action`` command starts its action (``preempt`` as given); a command on a busy
    action type is recorded as ``BUSY``. ``cancel`` interrupts running commanded actions
    by name, id, or ``all``. A failing action does not end the behaviour: its failure is
    recorded in ``queue.outcomes`` (and logged), so the operator sees it. Interrupting the
    behaviour interrupts every commanded action (safe states applied).
    """

    def __init__(self, queue: CommandQueue, *, topic: str | None = None) -> None:
        if not isinstance(queue, CommandQueue):
            raise ConfigError(f"CommandedBehavior needs a CommandQueue, got {queue!r}")
        self.queue = queue
        self.topic = topic
        self.running: dict[str, tuple[Command, Runnable]] = {}
        self._status_pub: Any = None

    def run(self) -> None:
        self.queue._add_waker(self.wake)
        if self.topic is not None:
            self._listen(self.topic)
        try:
            while True:
                self._collect()
                for command in self.queue._take():
                    self._execute(command)
                # Child ends, new commands and the interrupt all wake this; the timeout
                # is only a safety net.
                if not self._wait_wake(1.0):
                    break
        finally:
            self.queue._remove_waker(self.wake)
            for _, handle in list(self.running.values()):
                handle.interrupt()
            for command, handle in list(self.running.values()):
                handle.wait(self.manager.stop_timeout_s)
                self._record(command, handle)
            self.running.clear()

    def _execute(self, command: Command) -> None:
        if command.kind == "cancel":
            hits = [(c, h) for c, h in self.running.values()
                    if command.target in ("all", c.target, c.id)]
            for _, handle in hits:
                handle.interrupt()
            if not hits:
                self._outcome(Outcome(command.id, command.target, "CANCELLED",
                                      "nothing running matched"))
            return
        try:
            child = _start_child(self, self.queue.actions[command.target](**command.params),
                                 preempt=command.preempt, what=f"action {command.target!r}")
        except ActionTypeBusy as busy:
            self._outcome(Outcome(command.id, command.target, "BUSY", str(busy)))
            return
        except (ChildFailed, BeehaveError) as exc:
            if self.interrupted:
                return
            self._outcome(Outcome(command.id, command.target, "FAILED", repr(exc)))
            return
        except Exception as exc:  # the factory raised: recorded as the command's failure
            self._outcome(Outcome(command.id, command.target, "FAILED", repr(exc)))
            return
        self.running[command.id] = (command, child)

    def _listen(self, topic: str) -> None:
        """Take commands from ``topic`` (std_msgs/String, the JSON schema of
        :class:`CommandQueue`, relative to the robot's namespace) and report every outcome
        and every refusal on ``<topic>/status`` (std_msgs/String, JSON)."""
        from std_msgs.msg import String

        self._status_pub = self.ros.publisher(String, f"{topic}/status")

        def on_command(msg: Any) -> None:  # in the ROS executor thread
            try:
                self.queue.feed_json(msg.data)
            except CommandError as exc:  # recorded in queue.rejected; answered here
                self._publish({"status": "REJECTED", "detail": str(exc)})

        self.ros.subscription(String, topic, on_command)

    def _publish(self, report: dict[str, Any]) -> None:
        if self._status_pub is not None:
            from std_msgs.msg import String

            self._status_pub.publish(String(data=json.dumps(report, default=repr)))

    def _outcome(self, outcome: Outcome) -> None:
        self.queue.outcomes.append(outcome)
        self._publish({"id": outcome.id, "action": outcome.action, "status": outcome.status,
                       "detail": outcome.detail})

    def _collect(self) -> None:
        for ident, (command, handle) in list(self.running.items()):
            if handle.status.finished:
                handle.wait(0)  # seen: no ChildFailed
                del self.running[ident]
                self._record(command, handle)

    def _record(self, command: Command, handle: Runnable) -> None:
        detail = handle.result if handle.status is Status.SUCCEEDED else (
            None if handle.error is None else repr(handle.error))
        if handle.status is Status.FAILED:
            log.warning("command %s (%s) failed: %r", command.id, command.target, handle.error)
        self._outcome(Outcome(command.id, command.target, handle.status.name,
                                           detail))


# -- random -------------------------------------------------------------------------------

RandomFactory = Callable[[random.Random], Runnable]


@dataclass(frozen=True)
class RandomStep:
    """One random decision: which choice, what it started, how it ended."""

    choice: str
    name: str
    hold_s: float
    status: str


class RandomBehavior(_Wakeful):
    """Seeded random decisions, for soak tests: the same ``seed`` gives the same sequence.

    Each step picks one of ``choices`` (name → ``factory(rng)`` that builds an Action or
    Behavior, using ``rng`` for random goals), starts it, and holds it for a random time
    from ``hold_s`` — interrupting it if it has not ended by then. ``steps`` bounds the run
    (None: until interrupted). Failures are recorded in :attr:`history`, not raised,
    unless ``fail_fast``; ``preempt`` is passed to ``start_action``.
    """

    def __init__(self, choices: Mapping[str, RandomFactory], *, seed: int = 0,
                 steps: int | None = None, hold_s: tuple[float, float] = (0.0, 0.5),
                 weights: Sequence[float] | None = None, preempt: bool = True,
                 fail_fast: bool = False) -> None:
        if not choices:
            raise ConfigError("RandomBehavior needs at least one choice")
        if weights is not None and len(weights) != len(choices):
            raise ConfigError(f"weights has {len(weights)} entries for {len(choices)} choices")
        low, high = hold_s
        if not 0 <= low <= high:
            raise ConfigError(f"hold_s must be (min, max) with 0 <= min <= max, got {hold_s}")
        self.choices = dict(choices)
        self.seed = seed
        self.steps = steps
        self.hold_s = (float(low), float(high))
        self.weights = None if weights is None else list(weights)
        self.preempt = preempt
        self.fail_fast = fail_fast
        self.history: list[RandomStep] = []

    def plan(self, n: int) -> list[str]:
        """The first ``n`` choices this seed makes (without running anything)."""
        rng = random.Random(f"decisions:{self.seed}")
        return [self._pick(rng)[0] for _ in range(n)]

    def _pick(self, rng: random.Random) -> tuple[str, float]:
        names = list(self.choices)
        choice = rng.choices(names, weights=self.weights)[0]
        return choice, rng.uniform(*self.hold_s)

    def run(self) -> dict[str, int]:
        # Two streams: what factories draw (goals) does not shift the decisions.
        rng = random.Random(f"decisions:{self.seed}")
        goals = random.Random(f"goals:{self.seed}")
        done = 0
        while not self.interrupted and (self.steps is None or done < self.steps):
            choice, hold = self._pick(rng)
            child = _start_child(self, self.choices[choice](goals), preempt=self.preempt,
                                 what=f"choice {choice!r}")
            deadline = time.monotonic() + hold
            while not child.status.finished:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._wait_wake(remaining):
                    break
            if not child.status.finished:
                child.interrupt()
            child.wait(self.manager.stop_timeout_s)
            self.history.append(RandomStep(choice, child.name, hold, child.status.name))
            if self.fail_fast and child.status is Status.FAILED:
                raise ChildFailed(child) from child.error
            done += 1
        counts = collections.Counter(step.status for step in self.history)
        return dict(counts)
