"""Every error beehave raises derives from :class:`BeehaveError`.

Messages name the actor and the thing (behaviour name, action type, blackboard key, HAL
name) and, for a bad name, what exists.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


class BeehaveError(Exception):
    """Root of all beehave errors."""


#: A name longer than this is cut in an :class:`UnknownNameError`'s message.
MAX_NAME_SHOWN_CHARS = 100


def shorten(text: str, limit: int) -> str:
    """``text``, cut to ``limit`` characters with a note of how long it was."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}… ({len(text)} characters, cut)"


class UnknownNameError(BeehaveError, KeyError):
    """A name (behaviour, logic, HAL …) that is not registered.

    ``.kind`` is what was looked up, ``.name`` the bad name and ``.choices`` the valid names.
    """

    kind = "name"

    def __init__(self, name: str, choices: Iterable[str]) -> None:
        self.name = name
        self.choices = sorted(choices)
        listed = ", ".join(repr(c) for c in self.choices) or "none"
        # The name may come from outside: cut, so that a message bounded by an interface
        # still holds the valid names (a 10k-character name pushed them out).
        shown = shorten(name, MAX_NAME_SHOWN_CHARS) if isinstance(name, str) else name
        super().__init__(f"unknown {self.kind} {shown!r}; registered: {listed}")

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


class UnknownBehavior(UnknownNameError):
    kind = "behavior"


class UnknownLogic(UnknownNameError):
    kind = "logic"


class UnknownHAL(UnknownNameError):
    kind = "HAL"


class InvalidParameters(BeehaveError, TypeError):
    """Parameters that a behaviour's (or logic's) constructor rejects.

    Raised by ``register`` and ``switch`` before anything is stopped, so the running
    behaviour keeps running.
    """


class ConstructorFailed(BeehaveError):
    """A behaviour's (or logic's) own constructor raised although its parameters fit its
    signature: the fault is in that ``__init__``, not in the parameters. ``__cause__`` is
    the exception it raised."""


class ReservedAttribute(BeehaveError, AttributeError):
    """User code assigned an attribute that beehave owns (``status``, ``result``, ``path``
    …) on a behaviour or action; choose another name."""


class ActionTypeBusy(BeehaveError):
    """``start_action`` found the action type locked by another action.

    ``.action_type``, ``.holder`` (the running action) and ``.since`` (its lock time,
    ``time.monotonic()``) say who has it.
    """

    def __init__(self, action_type: str, holder: Any, since: float, *, reason: str = "") -> None:
        import time

        self.action_type = action_type
        self.holder = holder
        self.since = since
        owner = getattr(holder, "parent", None)
        owner_txt = f" of behavior {owner.name!r}" if owner is not None else ""
        held = time.monotonic() - since
        extra = f" ({reason})" if reason else ""
        super().__init__(
            f"action type {action_type!r} is held by {type(holder).__name__} "
            f"{getattr(holder, 'name', '?')!r}{owner_txt} "
            f"(status {holder.status.name}) for {held:.3f} s{extra}"
        )


class Interrupted(BeehaveError):
    """Raised inside a behaviour's thread when a framework call cannot go on because the
    behaviour was interrupted (e.g. while waiting for a preempted type lock). Letting it
    propagate out of ``run`` ends the behaviour as INTERRUPTED, not FAILED."""


class ChildFailed(BeehaveError):
    """An action or sub-behaviour failed and its behaviour had not waited for it.

    Raised in the behaviour's thread at its next framework call (``sleep``, ``start_*``) or
    when its ``run`` returns; ``.child`` is the failed handle, ``__cause__`` its error.
    Catch it to carry on; uncaught, it fails the behaviour in turn.
    """

    def __init__(self, child: Any) -> None:
        self.child = child
        super().__init__(
            f"{type(child).__name__} {child.name!r} failed: {child.error!r}"
        )


class SwitchSuperseded(BeehaveError):
    """A ``switch`` request was overtaken by a later one before it took effect."""


class ManagerShutdown(BeehaveError):
    """The manager was shut down (or never started) and cannot do what was asked."""


class LoopBlocked(BeehaveError, TimeoutError):
    """The low level's event loop stayed blocked (a logic or HAL that does not ``await``)
    longer than the manager's ``stop_timeout_s``, so a call into it cannot finish.

    ``.culprit`` names what holds the loop (``logic 'leds'``, ``HAL 'debug'``),
    ``.where`` the line it is stuck at (``file.py:42 in run``) and ``.blocked_s`` for how
    long it had been blocked. Raised by calls from other threads (``switch``, ``call``)
    and by ``shutdown()`` after it forced the HALs' safe states.
    """

    def __init__(self, message: str, *, culprit: str = "", where: str = "",
                 blocked_s: float = 0.0) -> None:
        super().__init__(message)
        self.culprit = culprit
        self.where = where
        self.blocked_s = blocked_s


class ClockNotSettled(BeehaveError, TimeoutError):
    """A :class:`~beehave.clock.VirtualClock` could not move time: the managers' workers did
    not come to rest (every one waiting) within its wall-time bound — a loop that never
    sleeps, or a wait that does not go through the clock. The message names them."""


class SimClockNotStarted(BeehaveError, TimeoutError):
    """A robot on ``use_sim_time`` got no ``/clock`` within ``sim_clock_timeout_s``: its
    behaviours never started."""


class AlreadyStarted(BeehaveError):
    """A behaviour, action or logic object was started twice; create a new one."""


class BlackboardError(BeehaveError):
    """A blackboard key or pattern that is not valid."""


class GoalFailed(BeehaveError):
    """A ROS 2 action goal that did not succeed: the server rejected it, aborted it, or
    it was cancelled by another client. ``status`` is ``"REJECTED"``, ``"ABORTED"`` or
    ``"CANCELED"``; ``result`` is the result message the server sent (None when rejected)."""

    def __init__(self, message: str, *, status: str, result: object = None) -> None:
        super().__init__(message)
        self.status = status
        self.result = result


class UnknownKey(BlackboardError, KeyError):
    """A blackboard key that holds no value. ``.key`` is the key, ``.close`` the existing
    keys that look like it (possibly empty) and ``.total`` how many keys hold a value."""

    def __init__(self, key: str, close: Iterable[str] = (), *, total: int = 0,
                 robot: str = "") -> None:
        self.key = key
        self.close = list(close)
        self.total = total
        where = f"{robot}: " if robot else ""
        hint = (f"; did you mean {', '.join(repr(c) for c in self.close)}?" if self.close
                else f"; {total} keys hold a value (list them with a pattern, e.g. '**')")
        super().__init__(f"{where}blackboard key {key!r} holds no value{hint}")

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


class BadRequest(BeehaveError, ValueError):
    """A request to a network interface (:mod:`beehave.interfaces`) whose shape is wrong:
    a name that is not a string, a count that is negative, a body that is not an object.
    The message names the field and what it takes."""


class HALError(BeehaveError):
    """A HAL plugin that cannot be loaded or used."""


class ConfigError(BeehaveError):
    """A configuration file or value that is not valid."""


class NotASubclass(BeehaveError, TypeError):
    """Something registered or started that is not the kind of class beehave expects."""


class NoPath(BeehaveError):
    """A path planner found no way to the goal (it is off the map, inside an obstacle's
    inflation, or cut off); the message says which."""


class AgentError(BeehaveError):
    """Something the agent layer (``beehave.agents``) could not do: the message names the
    agent, the peer and the conversation."""


class AgentNameTaken(AgentError):
    """An agent with this name is already alive in the DDS domain (seen in the directory);
    agent names are unique per domain. Pick another name, or stop the other process."""


class AgentUnreachable(AgentError):
    """A message could not be handed to a receiver: no inbox of that name is matched on
    DDS within the send timeout (the agent is not running, or discovery has not reached
    it). ``unreachable`` names the receivers that did not get the message (the others
    did)."""

    unreachable: tuple[str, ...] = ()


class NoReply(AgentError, TimeoutError):
    """No message arrived in a conversation or mailbox before its timeout or reply-by
    deadline."""


class ProtocolFailed(AgentError):
    """An interaction protocol ended without success: the peer refused, failed, did not
    understand, or nobody was left to ask. ``reply`` is the message that ended it (None
    when it ended by silence or for lack of candidates)."""

    def __init__(self, message: str, *, reply: object = None) -> None:
        super().__init__(message)
        self.reply = reply


class Vda5050Error(BeehaveError):
    """A VDA 5050 interface problem (``beehave.interfaces.vda5050``): an order the AGV
    cannot take, a message that breaks the schema, a broker that cannot be reached."""


class Vda5050ValidationError(Vda5050Error, ValueError):
    """A VDA 5050 message that breaks the 2.1.0 JSON schema; the message names each
    offending field by its path (``nodes[1].nodePosition.x``)."""


class RecordingError(BeehaveError):
    """A recording cannot be written, read or replayed: the file is not MCAP, lacks the
    channels a replay needs (they are named, with the ones it has), or a recorder option
    is out of range. Exported from :mod:`beehave.recording`."""


class UnknownFusionSource(UnknownNameError):
    """A proposal for an actuator from a source its arbiter does not know, or a lock it
    does not have (``beehave.fusion``); ``.actuator`` names the actuator, ``.choices`` the
    sources (or locks)."""

    kind = "fusion source"

    def __init__(self, name: str, choices: Iterable[str], *, actuator: str,
                 kind: str = "fusion source") -> None:
        self.kind = kind
        super().__init__(name, choices)
        self.actuator = actuator
        self.args = (f"arbiter {actuator!r}: {self.args[0]}",)


class BadProposal(BeehaveError, TypeError):
    """A proposal whose value the actuator's arbiter cannot take (``beehave.fusion``): the
    message names the actuator, the source, what is wrong and what is expected."""


class MavlinkError(BeehaveError):
    """Something a MAVLink vehicle did not do (``hal.mavlink``): the message names the
    connection, the vehicle's system id and the command or message."""


class VehicleLost(MavlinkError):
    """The vehicle's heartbeat stopped for longer than the link's ``heartbeat_timeout_s``:
    its values are stale and whatever waited on it stops."""


class CommandRejected(MavlinkError):
    """The vehicle answered a command with a COMMAND_ACK that is not ACCEPTED, or a mission
    upload with a MISSION_ACK that is not ACCEPTED; ``result`` is the MAVLink result name."""

    def __init__(self, message: str, *, result: str = "") -> None:
        super().__init__(message)
        self.result = result


class MavlinkTimeout(MavlinkError, TimeoutError):
    """The vehicle did not answer within the timeout, after every retry."""


class UnknownMode(UnknownNameError, MavlinkError):
    """A flight mode the vehicle's firmware does not have; ``choices`` lists its modes."""

    kind = "mode"

    def __init__(self, name: str, choices: Iterable[str], *, vehicle: str = "vehicle") -> None:
        super().__init__(name, choices)
        self.args = (f"unknown mode {name!r} for a {vehicle}; valid modes: "
                     f"{', '.join(self.choices)}",)


class MissionStalled(MavlinkError):
    """A vehicle running a mission made no progress for the stall time (blocked by an
    obstacle it cannot pass). ``remaining`` holds the waypoints it did not reach yet,
    ``position`` where it stands (north_m, east_m, alt_m)."""

    def __init__(self, message: str, *, remaining: list[object],
                 position: tuple[float, float, float]) -> None:
        super().__init__(message)
        self.remaining = remaining
        self.position = position


class InvalidTask(AgentError, ValueError):
    """A market task (``beehave.agents.market``) that is malformed: the message names the
    task, the key path (``plans[1].roles[0].capability``) and what is valid there."""


class UnknownCapability(InvalidTask, UnknownNameError):
    """A role needs a capability that no broker offers (or that is outside the
    auctioneer's vocabulary); ``.choices`` are the capabilities that exist."""

    kind = "capability"

    def __init__(self, name: str, choices: Iterable[str], *, where: str = "") -> None:
        UnknownNameError.__init__(self, name, choices)
        listed = ", ".join(repr(c) for c in self.choices) or "none"
        self.args = (f"{where}unknown capability {name!r}; offered: {listed}",)


class RendezvousTimeout(AgentError, TimeoutError):
    """A coalition member waited in vain for another role's event (``Job.wait_for``):
    the message names the task, the role and the event, and the events reached so far."""


class TaskFailed(ProtocolFailed):
    """A market task failed for good (no assignment within the rounds allowed, its
    deadline passed, or no plan's capabilities are offered). ``outcome`` is its
    :class:`~beehave.agents.market.Outcome`: every round, who did what, and why it ended."""

    def __init__(self, message: str, *, outcome: object = None) -> None:
        super().__init__(message)
        self.outcome = outcome
