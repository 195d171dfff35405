"""beehave's test kit: a virtual clock, fixtures, substitutes and assertions.

The fixtures come with the pytest plugin (:mod:`beehave.testing.plugin`, loaded by pytest
whenever beehave is installed); everything else is importable from here. See
``docs/testing.md``.
"""

from beehave.clock import VirtualClock
from beehave.errors import ClockNotSettled
from beehave.testing.assertions import (
    Entry,
    EventLog,
    assert_lock_held_by,
    assert_safe_state_ran,
)
from beehave.testing.fakes import (
    SLOWDOWN,
    WALL_TIMEOUT_S,
    Mark,
    Scripted,
    ScriptedAction,
    ScriptedHAL,
    Timeline,
    beehave_threads,
    native_stacks,
    no_thread_left,
    wait_until,
    wall_timeout,
)
from beehave.testing.lockstep import Lockstep

__all__ = [
    "SLOWDOWN", "WALL_TIMEOUT_S", "ClockNotSettled", "Entry", "EventLog", "Lockstep", "Mark",
    "Scripted", "ScriptedAction", "ScriptedHAL", "Timeline", "VirtualClock",
    "assert_lock_held_by", "assert_safe_state_ran", "beehave_threads", "native_stacks",
    "no_thread_left",
    "wait_until",
    "wall_timeout",
]
