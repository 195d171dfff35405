"""Fakes for testing behaviours without a robot: scripted stand-ins (by substitution or
by hand), a scripted HAL, and a timeline recorder.

Use them in your own tests::

    hl.substitute("Navigate", Scripted(duration_s=30.0, result=True))  # by name
    ll.hals.register(ScriptedHAL, name="lift", values={"lift/height_m": 0.0})
    timeline = Timeline()
    drive = ScriptedAction("driving", duration_s=0.2, timeline=timeline)
"""

from __future__ import annotations

import asyncio
import math
import os
import shutil
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from beehave.action import Action
from beehave.errors import ConfigError
from beehave.hal import HAL
from beehave.logic import Logic


def _slowdown() -> float:
    raw = os.environ.get("BEEHAVE_TEST_SLOWDOWN", "1")
    try:
        factor = float(raw)
    except ValueError:
        raise ConfigError(f"BEEHAVE_TEST_SLOWDOWN must be a number (how much slower this "
                          f"machine is than an idle one), got {raw!r}") from None
    if not (math.isfinite(factor) and factor >= 1.0):
        raise ConfigError(f"BEEHAVE_TEST_SLOWDOWN must be a finite number >= 1, got {raw!r}")
    return factor


SLOWDOWN = _slowdown()
"""How much slower than an idle 2-core machine this one may be (environment variable
``BEEHAVE_TEST_SLOWDOWN``, default 1; ``make test-stress`` sets it)."""

WALL_TIMEOUT_S = 60.0 * SLOWDOWN
"""The one bound of every wall-clock wait in tests (``wait_until``, processes coming up,
messages arriving over DDS or MQTT). A safety net, never a timing: a test that passes
waits only as long as its condition takes; a generous bound only makes a real failure
slower to report. Scaled by :data:`SLOWDOWN`."""


def wall_timeout(fraction: float = 1.0) -> float:
    """``fraction`` of :data:`WALL_TIMEOUT_S`: for a wait that needs a shorter bound (a
    negative check that something does *not* happen must still end)."""
    return WALL_TIMEOUT_S * fraction


class Scripted:
    """A substitute that stands in for an action, a behaviour or a logic (see
    :meth:`HighLevelBehaviorManager.substitute` and :meth:`LowLevelBehaviorManager.substitute`).

    The object keeps its identity and attributes (so the behaviour that started it reads
    ``.status``, ``.result`` and its own parameters as usual), but instead of its own
    ``run`` it waits ``duration_s`` on its manager's clock (interruptibly; ``math.inf``:
    until interrupted or cancelled), then returns ``result`` or raises ``raises`` (an
    exception instance or class). An action's ``safe_state`` becomes a recorded no-op: the
    hardware it would command is not there.

    ``replaced`` lists the objects it stood in for, in order; ``safe_states`` the paths of
    those whose safe state ran.
    """

    def __init__(self, *, duration_s: float = 0.0, result: Any = None,
                 raises: BaseException | type[BaseException] | None = None) -> None:
        if isinstance(duration_s, bool) or not isinstance(duration_s, (int, float)) \
                or math.isnan(duration_s) or duration_s < 0:
            raise ConfigError(f"Scripted(duration_s=…) takes a number of seconds >= 0 "
                              f"(math.inf: until interrupted), got {duration_s!r}")
        if raises is not None and not (isinstance(raises, BaseException) or (
                isinstance(raises, type) and issubclass(raises, BaseException))):
            raise ConfigError(f"Scripted(raises=…) takes an exception or exception class, "
                              f"got {raises!r}")
        self.duration_s = float(duration_s)
        self.result = result
        self.raises = raises
        self._lock = threading.Lock()
        self.replaced: list[Any] = []
        self.safe_states: list[str] = []

    def __repr__(self) -> str:
        return (f"Scripted(duration_s={self.duration_s}, result={self.result!r}, "
                f"raises={self.raises!r})")

    def _outcome(self, obj: Any) -> Any:
        if self.raises is not None:
            if isinstance(self.raises, BaseException):
                raise self.raises
            raise self.raises(f"{getattr(obj, 'path', obj)}: scripted failure")
        return self.result

    def __call__(self, obj: Any) -> None:
        with self._lock:
            self.replaced.append(obj)
        duration_s = self.duration_s
        if isinstance(obj, Logic):
            async def run_logic() -> Any:
                if math.isinf(duration_s):
                    await asyncio.Event().wait()  # until cancelled
                await asyncio.sleep(duration_s)
                return self._outcome(obj)
            obj.run = run_logic  # type: ignore[method-assign]
            return

        def run() -> Any:
            if not obj.sleep(duration_s):
                return None  # interrupted: the status says so
            return self._outcome(obj)
        obj.run = run
        if isinstance(obj, Action):
            def safe_state() -> None:
                with self._lock:
                    self.safe_states.append(obj.path)
            obj.safe_state = safe_state  # type: ignore[method-assign]


class ScriptedHAL(HAL):
    """A HAL stand-in: register it under the name of the one it replaces
    (``ll.hals.register(ScriptedHAL, name="lift", values={...})``).

    When loaded it writes ``values`` to the blackboard; every method a logic calls on it is
    recorded in ``calls`` (``(method, args, kwargs)``, shared by every load when you pass
    your own list) and returns ``returns.get(method)``. ``safe_state`` is recorded as a
    call too.
    """

    name = "scripted"

    def __init__(self, *, values: dict[str, Any] | None = None,
                 returns: dict[str, Any] | None = None,
                 calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]] | None = None
                 ) -> None:
        self.values = dict(values or {})
        self.returns = dict(returns or {})
        self.calls = calls if calls is not None else []

    async def on_load(self) -> None:
        for key, value in self.values.items():
            self.blackboard.set(key, value)

    def safe_state(self) -> None:
        self.calls.append(("safe_state", (), {}))

    def __getattr__(self, method: str) -> Callable[..., Any]:
        if method.startswith("_"):
            raise AttributeError(method)

        def call(*args: Any, **kwargs: Any) -> Any:
            self.calls.append((method, args, kwargs))
            return self.returns.get(method)
        call.__name__ = method
        return call


@dataclass(frozen=True)
class Mark:
    t: float
    what: str  # "run", "end", "safe_begin", "safe"
    path: str
    action_type: str


class Timeline:
    """Thread-safe record of run start/end and safe_state calls, with live invariants:
    ``max_concurrent[type]`` is the most actions of one type ever active at once — inside
    ``run`` or inside ``safe_state`` (a safe state still commands the hardware, so the type
    lock covers it too)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.marks: list[Mark] = []
        self.active: Counter[str] = Counter()
        self.max_concurrent: Counter[str] = Counter()
        self.safe_calls: Counter[int] = Counter()
        self._inside: dict[str, Counter[int]] = {}

    def record(self, what: str, action: Action) -> None:
        with self._lock:
            kind = action.action_type
            # An action is active while inside run or safe_state (a STUCK action's forced
            # safe state may run beside its run): count actions, not calls.
            inside = self._inside.setdefault(kind, Counter())
            if what in ("run", "safe_begin"):
                inside[id(action)] += 1
            elif what in ("end", "safe"):
                inside[id(action)] -= 1
                if inside[id(action)] <= 0:
                    del inside[id(action)]
            if what == "safe":
                self.safe_calls[id(action)] += 1
            self.active[kind] = len(inside)
            self.max_concurrent[kind] = max(self.max_concurrent[kind], self.active[kind])
            self.marks.append(Mark(time.monotonic(), what, action.path, kind))

    def times(self, what: str, path: str) -> list[float]:
        with self._lock:
            return [m.t for m in self.marks if m.what == what and m.path == path]


class ScriptedAction(Action):
    """An action that does what it is told: run ``duration_s`` (interruptibly), then
    return ``result`` or raise ``raises``; ``ignore_interrupt_s`` keeps it running that
    long after an interrupt (``float('inf')`` until ``release`` is set) to provoke STUCK;
    ``safe_state_s`` makes its ``safe_state`` take that long (``float('inf')`` until
    ``safe_release`` is set)."""

    def __init__(self, action_type: str = "scripted", *, duration_s: float = 0.0,
                 result: Any = None, raises: BaseException | None = None,
                 ignore_interrupt_s: float = 0.0, timeline: Timeline | None = None,
                 name: str | None = None, safe_state_s: float = 0.0) -> None:
        # action_type is per instance here; real actions set it on the class.
        self.action_type = action_type  # type: ignore[misc]
        self.duration_s = duration_s
        self.scripted_result = result
        self.raises = raises
        self.ignore_interrupt_s = ignore_interrupt_s
        self.timeline = timeline
        self.release = threading.Event()
        self.safe_state_s = safe_state_s
        self.safe_release = threading.Event()
        self.safe_state_calls = 0
        if name:
            self.name = name

    def run(self) -> Any:
        if self.timeline:
            self.timeline.record("run", self)
        try:
            completed = self.sleep(self.duration_s)
            if not completed and self.ignore_interrupt_s > 0:
                forever = self.ignore_interrupt_s == float("inf")
                self.release.wait(None if forever else self.ignore_interrupt_s)
            if self.raises is not None:
                raise self.raises
            return self.scripted_result
        finally:
            if self.timeline:
                self.timeline.record("end", self)

    def safe_state(self) -> None:
        if self.timeline:
            self.timeline.record("safe_begin", self)
        try:
            if self.safe_state_s > 0:
                forever = self.safe_state_s == float("inf")
                self.safe_release.wait(None if forever else self.safe_state_s)
        finally:
            self.safe_state_calls += 1
            if self.timeline:
                self.timeline.record("safe", self)


@contextmanager
def no_thread_left(what: str = "the managers") -> Iterator[None]:
    """Fail (AssertionError naming them) when the block leaves a beehave thread running:
    wrap a manager's whole life, its shutdown included."""
    before = set(beehave_threads())
    yield
    leaked = [t for t in beehave_threads() if t not in before]
    assert not leaked, f"threads left after {what}: {leaked}"


def beehave_threads() -> list[threading.Thread]:
    """The threads beehave runs (their names start with ``beehave``): for leak checks."""
    return [t for t in threading.enumerate() if t.name.startswith("beehave")]


def wait_until(predicate: Callable[[], bool], timeout_s: float | None = None) -> bool:
    """Poll ``predicate`` until true or ``timeout_s`` (default :data:`WALL_TIMEOUT_S`)
    passed; for conditions that have no event to wait on (a thread ending, a message from
    another process). A safety net in tests, not a timing."""
    deadline = time.monotonic() + (WALL_TIMEOUT_S if timeout_s is None else timeout_s)
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return bool(predicate())


def native_stacks(pid: int, timeout_s: float = 30.0) -> str:
    """The C stacks of every thread of process ``pid``, read with gdb when it is installed
    (empty text otherwise, or when gdb cannot attach). For a child that hangs inside a
    native library (a DDS participant that never finishes starting, say), where the Python
    stacks that ``faulthandler`` writes on SIGABRT stop at the call into it. Call it before
    ending the process; it pauses the process while gdb reads it."""
    gdb = shutil.which("gdb")
    if gdb is None:
        return ""
    try:
        run = subprocess.run([gdb, "-p", str(pid), "-batch", "-nx",
                              "-ex", "thread apply all bt 25"],
                             capture_output=True, text=True, timeout=timeout_s)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"(gdb could not read process {pid}: {exc})"
    lines = [line for line in run.stdout.splitlines()
             if line.startswith(("Thread ", "#"))]
    return "\n".join(lines)
