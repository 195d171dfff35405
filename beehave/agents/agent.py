"""Agent: a named participant of the DDS domain with a directory entry and an inbox.

::

    with Agent("machine_3", services={"replenish": {"material": "steel"}}) as agent:
        atvs = agent.directory.search("transport", zone="north")
        with agent.conversation(protocol="my-protocol") as conv:
            conv.send(Performative.REQUEST, [atvs[0].name], {"to": "machine_3"})
            answer = conv.receive(timeout_s=5.0)

Transport. Each agent subscribes to its inbox ``/beehave/agents/inbox/<name>``
(``std_msgs/String`` holding one JSON :class:`~beehave.agents.message.Message`; reliable,
volatile, keep-last ``inbox_depth``). A sender keeps one publisher per receiver and waits,
at most ``send_timeout_s``, until DDS has matched it with the receiver's inbox before the
first message; after that every message is handed to DDS at once. "Reliable" is DDS
reliability: a matched reader gets every message, in order per sender, retransmitted when
lost, as long as both processes live and the reader keeps up within ``inbox_depth``
messages. Nothing is stored for an agent that is not running; a message to a receiver that
dies in flight is lost — protocols bound every wait and watch the directory for that.

Threads. Messages arrive in the ROS executor thread and are sorted there, without user
code: to an open :class:`Conversation` (by conversation id), to a :class:`Mailbox` that
claims their protocol or performative, or — when they name no protocol, or are a
not-understood — to the agent's :attr:`Agent.inbox`. A message of a protocol that no
mailbox claims is answered with not-understood at once (its initiator must not wait for
its timeout); a reply to a conversation that is closed is logged and dropped. Waits are
blocking (``receive``: for threads, ending early with
:class:`~beehave.errors.Interrupted` when the calling Behavior or Action is interrupted)
or awaitable (``areceive``: for Logics). Agent timeouts are wall time (they bound network
waits, which a simulation clock does not pace).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import math
import queue
import threading
import time
import uuid
import weakref
from collections import deque
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.duration import Duration
from rclpy.exceptions import InvalidHandle
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from beehave import runnable as _runnable
from beehave.action import Action
from beehave.agents.directory import (
    DIRECTORY_TOPIC,
    EXPIRY_CHECK_S,
    Announcement,
    Directory,
    EntryState,
)
from beehave.agents.message import Message, Performative, is_agent_name, sender_of
from beehave.agents.trust import Mode, Refused, Trust
from beehave.behavior import Behavior
from beehave.errors import (
    AgentError,
    AgentNameTaken,
    AgentUnreachable,
    ConfigError,
    Interrupted,
    NoReply,
)
from beehave.events import Event, EventBus, EventKind
from beehave.hal import check_duration_s
from beehave.lifecycle import Closing

if TYPE_CHECKING:
    from rclpy.node import Node

    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.ros.context import RosContext

log = logging.getLogger(__name__)

INBOX_PREFIX = "/beehave/agents/inbox/"

MESSAGES_TOPIC = "/beehave/agents/messages"
"""Every agent publishes a copy of each message it sends here (the same JSON as on the
inboxes), while anyone listens — the role of JADE's Sniffer: ``beehave fleet --http`` lists
them live. Best effort and volatile: a slow or absent listener never delays a sender, and
no inbox gains a reader (an inbox's readers are how a sender knows its receiver is there)."""

MESSAGES_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                          reliability=ReliabilityPolicy.BEST_EFFORT,
                          durability=DurabilityPolicy.VOLATILE)

DIRECTORY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""Each writer keeps only its newest entry, and hands it to every reader that joins."""

DIRECTORY_READER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                                  reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.TRANSIENT_LOCAL)


_MODE_SAID: set[Mode] = set()
_MODE_LOCK = threading.Lock()


def _say_mode(trust: Trust) -> None:
    """Once per process and mode: which trust mode the agents run in (open is loud)."""
    with _MODE_LOCK:
        if trust.mode in _MODE_SAID:
            return
        _MODE_SAID.add(trust.mode)
    if trust.mode is Mode.OPEN:
        log.warning("agents run in OPEN mode: any participant of this DDS domain can send "
                    "messages and directory entries as any agent. Use signed mode for a "
                    "real fleet (`beehave keys`, docs/agents.md#trust-model)")
    else:
        log.info("agents run in signed mode (fleet %s)", trust.fleet)


REFUSALS_QUEUED = 100
"""Signed mode: refusals (not-understood) waiting to be sent at most; more are not answered
(they are still logged and reported as events)."""


def inbox_qos(depth: int) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def current_waiter() -> tuple[threading.Condition | None, Callable[[], bool], str]:
    """How the calling thread waits: a Behavior or Action on its own condition, woken by
    its interrupt (as ``self.ros`` waits do); any other thread on the mailbox's."""
    node = _runnable.current()
    if node is None:
        return None, lambda: False, "a thread"
    return node._cond, lambda: node._interrupt_requested, node.path


class Mailbox(Closing):
    """Messages for one consumer, in arrival order (made by :meth:`Agent.mailbox`,
    :meth:`Agent.conversation`, or the agent's own :attr:`Agent.inbox`).

    At most ``maxlen`` wait; beyond that the oldest is dropped with a logged event
    (MESSAGE_REJECTED), never silently."""

    def __init__(self, agent: Agent, *, protocols: Iterable[str] | None = None,
                 performatives: Iterable[Performative] | None = None,
                 maxlen: int = 1000, label: str = "inbox") -> None:
        self.agent = agent
        self.protocols = frozenset(protocols) if protocols is not None else None
        self.performatives = (frozenset(performatives) if performatives is not None
                              else None)
        self.label = label
        self._maxlen = maxlen
        self._queue: deque[Message] = deque()
        self._lock = threading.Lock()
        self._own_cond = threading.Condition()
        self._conds: dict[threading.Condition, int] = {}
        self._async: list[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = []
        self._poked = False
        self.closed = False

    def accepts(self, message: Message) -> bool:
        """Whether this mailbox claims ``message`` (not asked for conversations)."""
        if self.protocols is not None and message.protocol not in self.protocols:
            return False
        return self.performatives is None or message.performative in self.performatives

    def __len__(self) -> int:
        return len(self._queue)

    # ------------------------------------------------------------------ delivery
    def _deliver(self, message: Message) -> None:
        dropped = None
        with self._lock:
            self._queue.append(message)
            if len(self._queue) > self._maxlen:
                dropped = self._queue.popleft()
        if dropped is not None:
            self.agent._emit_rejected(f"{self.label} is full ({self._maxlen} messages): "
                                      f"dropped the oldest", dropped.sender, dropped.to_json())
        self._wake()

    def poke(self) -> None:
        """Wake a waiting :meth:`_next` without a message (e.g. a child action ended)."""
        with self._lock:
            self._poked = True
        self._wake()

    def _wake(self) -> None:
        with self._lock:
            conds = list(self._conds)
            waiters = list(self._async)
        for cond in conds:
            with cond:
                cond.notify_all()
        for loop, event in waiters:
            try:
                loop.call_soon_threadsafe(event.set)
            except RuntimeError:  # that loop is closed: its waiter is gone
                pass

    # ------------------------------------------------------------------ waiting
    def _next(self, timeout_s: float | None) -> Message | None:
        """The next message, or None when poked or at the timeout. Raises
        :class:`~beehave.errors.Interrupted` when the calling runnable is interrupted."""
        cond, interrupted, who = current_waiter()
        if cond is None:
            cond = self._own_cond
        with self._lock:
            self._conds[cond] = self._conds.get(cond, 0) + 1
        try:
            with cond:
                cond.wait_for(lambda: bool(self._queue) or self._poked or self.closed
                              or interrupted(), timeout_s)
        finally:
            with self._lock:
                self._conds[cond] -= 1
                if not self._conds[cond]:
                    del self._conds[cond]
        with self._lock:
            if self._queue:
                return self._queue.popleft()
            self._poked = False
        if interrupted():
            raise Interrupted(f"{who}: interrupted while waiting for a message in "
                              f"{self.agent.name}'s {self.label}")
        if self.closed:
            raise AgentError(f"agent {self.agent.name!r}: {self.label} is closed")
        return None

    def receive(self, *, timeout_s: float | None = 10.0) -> Message:
        """The next message; waits at most ``timeout_s`` (None: no limit) and raises
        :class:`~beehave.errors.NoReply` then. Called from a Behavior or Action, it raises
        :class:`~beehave.errors.Interrupted` as soon as that is interrupted."""
        _check_wait("receive", timeout_s)
        if timeout_s is not None and timeout_s > threading.TIMEOUT_MAX:
            timeout_s = None  # math.inf: threading's waits refuse it
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            message = self._next(left)
            if message is not None:
                return message
            if deadline is not None and time.monotonic() >= deadline:
                raise NoReply(f"agent {self.agent.name!r}: no message in its {self.label} "
                              f"within {timeout_s} s")

    async def areceive(self, *, timeout_s: float | None = 10.0) -> Message:
        """:meth:`receive` for asyncio code (a Logic): awaits without blocking the loop;
        cancelling the task cancels the wait."""
        _check_wait("areceive", timeout_s)
        loop = asyncio.get_running_loop()
        event = asyncio.Event()
        entry = (loop, event)
        with self._lock:
            self._async.append(entry)
        deadline = None if timeout_s is None else loop.time() + timeout_s
        try:
            while True:
                with self._lock:
                    if self._queue:
                        return self._queue.popleft()
                if self.closed:
                    raise AgentError(f"agent {self.agent.name!r}: {self.label} is closed")
                left = (None if deadline is None or math.isinf(deadline)
                        else deadline - loop.time())
                if left is not None and left <= 0:
                    raise NoReply(f"agent {self.agent.name!r}: no message in its "
                                  f"{self.label} within {timeout_s} s")
                event.clear()
                try:
                    await asyncio.wait_for(event.wait(), left)
                except TimeoutError:
                    pass
        finally:
            with self._lock:
                self._async.remove(entry)

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Stop receiving; messages it would have claimed go elsewhere from now on."""
        self.closed = True
        self.agent._remove_mailbox(self)
        self._wake()



class Conversation(Mailbox):
    """One conversation this agent takes part in: every message with its
    ``conversation_id`` comes here, whatever its protocol. Made by
    :meth:`Agent.conversation`; close it (or use ``with``) when done — replies that arrive
    later are logged and dropped.

    :meth:`watch` a peer and its disappearance from the directory (lease expired, closed)
    arrives here as a ``failure`` from it with ``content["reason"]`` saying so, so that a
    protocol waiting on that peer learns it without waiting for its timeout.
    """

    def __init__(self, agent: Agent, conversation_id: str, protocol: str | None) -> None:
        super().__init__(agent, label=f"conversation {conversation_id!r}")
        self.conversation_id = conversation_id
        self.protocol = protocol
        self._watched: set[str] = set()

    def send(self, performative: Performative, receivers: Iterable[str], content: Any = None,
             *, reply_by_s: float | None = None, in_reply_to: str | None = None,
             timeout_s: float | None = None) -> Message:
        """Send a message of this conversation; ``reply_by_s`` sets its ``reply_by`` that
        many seconds from now. Returns the message as sent."""
        message = Message(performative=performative, sender=self.agent.name,
                          receivers=list(receivers), conversation_id=self.conversation_id,
                          in_reply_to=in_reply_to, protocol=self.protocol, content=content,
                          reply_by=None if reply_by_s is None else time.time() + reply_by_s)
        return self.agent.send(message, timeout_s=timeout_s)

    def watch(self, name: str) -> None:
        """Report ``name``'s departure from the directory here (see the class doc). A peer
        that this agent has not seen in the directory yet (discovery is under way, or it
        is no directory member) is not reported missing: the send's match wait and the
        protocol's timeouts bound that case."""
        with self._lock:
            self._watched.add(name)

    def unwatch(self, name: str) -> None:
        with self._lock:
            self._watched.discard(name)

    def _departed(self, name: str, reason: str) -> None:
        with self._lock:
            if name not in self._watched:
                return
            self._watched.discard(name)
        self._deliver(Message(performative=Performative.FAILURE, sender=name,
                              receivers=[self.agent.name],
                              conversation_id=self.conversation_id, protocol=self.protocol,
                              content={"reason": f"agent {name!r} left the directory "
                                                 f"({reason})", "departed": True}))


_ATTACHED: weakref.WeakKeyDictionary[HighLevelBehaviorManager, Agent] = \
    weakref.WeakKeyDictionary()


def _check_wait(what: str, timeout_s: object) -> None:
    if timeout_s is None:
        return
    if (isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float))
            or math.isnan(timeout_s) or timeout_s < 0):
        raise ConfigError(f"{what}(timeout_s=…) takes seconds ≥ 0, math.inf or None, "
                          f"got {timeout_s!r}")


def agent_of(manager: HighLevelBehaviorManager) -> Agent:
    """The agent attached to ``manager`` (see :meth:`Agent.attach`)."""
    agent = _ATTACHED.get(manager)
    if agent is None:
        raise ConfigError("no agent is attached to this HighLevelBehaviorManager: call "
                          "agent.attach(manager), or give the robot YAML an `agent:` section")
    return agent


class Agent(Closing):
    """A named agent: a directory entry kept alive by a lease, an inbox, and the API to
    talk (see the module doc).

    ``node``: the rclpy node to create its topics on (it must be spun, e.g. by a
    :class:`~beehave.ros.context.RosContext`); or ``ros``: a context to create one in; with
    neither, the agent makes and owns a context of its own. ``services``: what it offers
    from the start (``{"transport": {"payload_kg": 50}}``). ``lease_s``: how long others
    keep its entry without news (it announces every ``lease_s / 4``). ``probe_s``: how
    long it listens for a holder of its name before it takes it. ``trust``: its keys and
    mode (:class:`~beehave.agents.trust.Trust`; default: from ``BEEHAVE_AGENT_MODE`` and
    ``BEEHAVE_AGENT_KEYS``, else open mode without keys — said once per process in the
    log, at WARNING).

    Raises :class:`~beehave.errors.AgentNameTaken` when an agent of this name is alive in
    the domain. :meth:`close` (or ``with``) removes it from every directory at once.
    """

    def __init__(self, name: str, *, node: Node | None = None, ros: RosContext | None = None,
                 services: dict[str, dict[str, Any]] | None = None, lease_s: float = 2.0,
                 probe_s: float = 1.0, inbox_depth: int = 1000,
                 send_timeout_s: float = 2.0, trust: Trust | None = None) -> None:
        if not is_agent_name(name):
            raise ConfigError(f"agent name {name!r} is not valid: letters, digits and '_', "
                              f"starting with a letter, at most 63 characters (it names the "
                              f"ROS topic {INBOX_PREFIX}<name>)")
        self.name = name
        self.lease_s = check_duration_s(f"agent {name!r}: lease_s", lease_s)
        probe_s = check_duration_s(f"agent {name!r}: probe_s", probe_s)
        self.send_timeout_s = check_duration_s(f"agent {name!r}: send_timeout_s",
                                               send_timeout_s)
        self.events = EventBus(log)
        self.trust = trust if trust is not None else Trust.from_env(name)
        if not isinstance(self.trust, Trust):
            raise ConfigError(f"agent {name!r}: trust must be a Trust, got "
                              f"{type(self.trust).__name__}")
        _say_mode(self.trust)
        self._refusals: dict[str, float] = {}  # directory warnings: agent -> last logged
        self.directory = Directory(name)
        self._services: dict[str, dict[str, Any]] = {}
        for service, properties in (services or {}).items():
            self._services[service] = _checked_properties(name, service, properties)
        self._lock = threading.Lock()
        self._incarnation = uuid.uuid4().hex
        self._started_at = time.time()
        self._state = EntryState.JOINING
        self._conversations: dict[str, Conversation] = {}
        self._closed_conversations: deque[str] = deque(maxlen=2000)
        self._mailboxes: list[Mailbox] = []
        self._publishers: dict[str, Any] = {}
        self._buses: list[EventBus] = [self.events]
        self._managers: list[weakref.ref[HighLevelBehaviorManager]] = []
        self._ids = itertools.count()
        self._closed = False
        self._close_done = threading.Event()
        self._own_ros: RosContext | None = None
        self.inbox = Mailbox(self, label="inbox")
        if node is None:
            from beehave.ros.context import RosContext

            if ros is None:
                ros = self._own_ros = RosContext()
                ros.start()
            # Unique: a refused duplicate must not clash with the holder's node name.
            node = ros.create_node(f"beehave_agent_{name}_{self._incarnation[:8]}")
            self._own_node = True
        else:
            self._own_node = False
        self._ros = ros
        self.node: Node = node
        self._outbox: queue.Queue[Message | None] = queue.Queue()
        self._outbox_thread = threading.Thread(target=self._send_later, args=(self._outbox,),
                                               name=f"beehave:agent-outbox:{name}", daemon=True)
        self._outbox_thread.start()
        # Refusals of signed mode go out on their own, bounded: forged messages that claim
        # absent senders (each waits up to 1 s for an inbox) never delay real replies.
        self._refusal_box: queue.Queue[Message | None] = queue.Queue(maxsize=REFUSALS_QUEUED)
        self._refusal_thread = threading.Thread(
            target=self._send_later, args=(self._refusal_box, 1.0),
            name=f"beehave:agent-refusals:{name}", daemon=True)
        self._refusal_thread.start()
        self._news = threading.Event()
        self._dir_pub = node.create_publisher(String, DIRECTORY_TOPIC, DIRECTORY_QOS)
        self._copies = node.create_publisher(String, MESSAGES_TOPIC, MESSAGES_QOS)
        self._entities: list[tuple[str, Any]] = [("publisher", self._dir_pub),
                                                 ("publisher", self._copies)]
        self._entities.append(("subscription", node.create_subscription(
            String, DIRECTORY_TOPIC, self._on_directory, DIRECTORY_READER_QOS)))
        self._entities.append(("subscription", node.create_subscription(
            String, INBOX_PREFIX + name, self._on_inbox, inbox_qos(inbox_depth))))
        # Leases are wall time for every agent: on a robot's node under use_sim_time a
        # timer of the node's clock would stop whenever the simulation stalls, and every
        # robot would leave the directory at once (issue 11).
        self._wall = Clock(clock_type=ClockType.STEADY_TIME)
        self._entities.append(("timer", node.create_timer(EXPIRY_CHECK_S,
                                                          self.directory._expire,
                                                          clock=self._wall)))
        self._remove_listener = self.directory._on_departure(self._peer_departed)
        #: Set when the agent lost its name to an older process after it started (then it
        #: is closed, and sending raises this).
        self.error: AgentNameTaken | None = None
        self.directory._name_lost = self._lose_name
        try:
            self._probe(probe_s)
        except BaseException:
            self.close()
            raise
        self._entities.append(("timer", node.create_timer(self.lease_s / 4, self._announce,
                                                          clock=self._wall)))

    # ------------------------------------------------------------------ directory
    def _probe(self, probe_s: float) -> None:
        """Announce JOINING, then listen: the name is ours when no live (or older joining)
        holder has been heard once every directory writer DDS knows of has been heard, and
        ``probe_s`` has passed (at most 3 × ``probe_s``)."""
        self._announce()
        start = time.monotonic()
        while True:
            conflict = self.directory.conflict
            if conflict is not None:
                raise self._taken(conflict)
            elapsed = time.monotonic() - start
            writers = self.node.count_publishers(DIRECTORY_TOPIC) - 1
            if (elapsed >= probe_s and self.directory._heard_count() >= writers) \
                    or elapsed >= 3 * probe_s:
                break
            self._news.wait(0.02)
            self._news.clear()
        self._state = EntryState.ALIVE
        self._announce()

    def _taken(self, holder: Announcement) -> AgentNameTaken:
        return AgentNameTaken(
            f"agent name {self.name!r} is taken: a process announcing it "
            f"{holder.state.value} since "
            f"{time.strftime('%H:%M:%S', time.localtime(holder.started_at))} "
            f"(incarnation {holder.incarnation[:8]}) is alive in this DDS domain "
            f"(ROS_DOMAIN_ID); choose another name or stop that process")

    def _lose_name(self, holder: Announcement) -> None:
        """An older holder of our name showed up after the probe (discovery was slow):
        step down, so that one name never answers twice (executor thread)."""
        self.error = self._taken(holder)
        log.error("agent %r: %s; closing this one", self.name, self.error)
        event = Event(EventKind.AGENT_NAME_LOST, f"agent:{self.name}", None, self.error,
                      {"holder": holder.incarnation, "holder_started_at": holder.started_at})
        self._emit(event)
        # Not here: close() destroys the subscription whose callback is running.
        self._closer = threading.Thread(target=self.close, name=f"beehave:agent-close:"
                                                                f"{self.name}", daemon=True)
        self._closer.start()

    def _announce(self) -> None:
        with self._lock:
            if self._closed and self._state is not EntryState.LEAVING:
                return
            announcement = Announcement(agent=self.name, incarnation=self._incarnation,
                                        started_at=self._started_at, state=self._state,
                                        lease_s=self.lease_s,
                                        services={k: dict(v) for k, v in self._services.items()},
                                        sent_at=time.time())
        if self.trust.signing:
            text = self.trust.dumps(announcement.model_dump(mode="json", by_alias=True,
                                                            exclude={"auth"}))
        else:
            text = announcement.model_dump_json(by_alias=True, exclude={"auth"})
        try:
            self._dir_pub.publish(String(data=text))
        except InvalidHandle:
            if not self._closed:
                raise
            return  # the announce timer fired while close() destroyed the publisher
        self.directory._set_own(announcement)

    def _on_directory(self, msg: String) -> None:
        if self.trust.verifying:
            try:
                data = json.loads(msg.data)
                if not isinstance(data, dict):
                    raise Refused("a directory entry is a JSON object")
                self.trust.check_entry(data)
            except (ValueError, RecursionError, Refused) as exc:
                self._refused_entry(msg.data, str(exc))
                return
        self.directory._receive(msg.data)
        self._news.set()

    def _refused_entry(self, text: str, reason: str) -> None:
        """A directory entry signed mode does not take: a WARNING, at most one per claimed
        agent every 10 s (entries repeat every lease / 4)."""
        try:
            data = json.loads(text)
            who = data.get("agent") if isinstance(data, dict) else None
        except (ValueError, RecursionError):
            who = None
        who = who if isinstance(who, str) and is_agent_name(who) else "?"
        now = time.monotonic()
        if now - self._refusals.get(who, -math.inf) < 10.0:
            return
        if len(self._refusals) > 1000:
            self._refusals.clear()
        self._refusals[who] = now
        log.warning("agent %r: refused the directory entry of %r: %s", self.name, who, reason)

    def register(self, service: str, **properties: Any) -> None:
        """Offer ``service`` with these properties (JSON values), replacing an earlier
        registration of it; every agent sees it within one network delay."""
        checked = _checked_properties(self.name, service, properties)
        with self._lock:
            self._services[service] = checked
        self._announce()

    def deregister(self, service: str) -> None:
        """Stop offering ``service``; a KeyError names the services offered when it is not."""
        with self._lock:
            if service not in self._services:
                raise KeyError(f"agent {self.name!r} does not offer {service!r}; it offers: "
                               f"{', '.join(sorted(self._services)) or 'nothing'}")
            del self._services[service]
        self._announce()

    @property
    def services(self) -> dict[str, dict[str, Any]]:
        with self._lock:
            return {k: dict(v) for k, v in self._services.items()}

    def _peer_departed(self, name: str, reason: str) -> None:
        with self._lock:
            conversations = list(self._conversations.values())
        for conversation in conversations:
            conversation._departed(name, reason)

    # ------------------------------------------------------------------ sending
    def send(self, message: Message, *, timeout_s: float | None = None) -> Message:
        """Send ``message`` to each of its receivers (``sender`` becomes this agent).

        The first message to a receiver waits until DDS has matched its inbox, at most
        ``timeout_s`` (default ``send_timeout_s``; the receivers are waited for together).
        Those matched get the message; if any is not,
        :class:`~beehave.errors.AgentUnreachable` names them (``.unreachable``) after the
        others were served. :class:`~beehave.errors.Interrupted` when the calling Behavior
        or Action is interrupted meanwhile. Returns the message as sent."""
        if self.error is not None:
            raise self.error
        if self._closed:
            raise AgentError(f"agent {self.name!r} is closed; it cannot send")
        message = message.model_copy(update={"sender": self.name, "sent_at": time.time(),
                                             "auth": None})
        if self.trust.signing:
            text = String(data=self.trust.dumps(message.model_dump(
                mode="json", by_alias=True, exclude={"auth"})))
        else:
            text = String(data=message.to_json())
        limit = self.send_timeout_s if timeout_s is None else timeout_s
        if self._copies.get_subscription_count() > 0:  # nothing to do while nobody listens
            self._copies.publish(text)
        pending = {receiver: self._publisher(receiver) for receiver in message.receivers}
        ready = [r for r, p in pending.items() if p.get_subscription_count() > 0]
        for receiver in ready:  # the common case: no waiting at all
            pending.pop(receiver).publish(text)
        if pending:
            self._wait_matched(pending, limit, text)
        return message

    async def asend(self, message: Message, *, timeout_s: float | None = None) -> Message:
        """:meth:`send` for asyncio code: does not block the loop while it waits for a
        receiver's inbox to be matched."""
        if all(self._publisher(r).get_subscription_count() > 0 for r in message.receivers):
            return self.send(message, timeout_s=timeout_s)
        return await asyncio.to_thread(self.send, message, timeout_s=timeout_s)

    def reply(self, to: Message, performative: Performative, content: Any = None, *,
              timeout_s: float | None = None) -> Message:
        """Answer ``to`` (same conversation and protocol, to its sender)."""
        return self.send(to.reply(performative, content), timeout_s=timeout_s)

    def _publisher(self, receiver: str) -> Any:
        with self._lock:
            publisher = self._publishers.get(receiver)
            if publisher is None:
                publisher = self.node.create_publisher(String, INBOX_PREFIX + receiver,
                                                       inbox_qos(1000))
                self._publishers[receiver] = publisher
            return publisher

    def _wait_matched(self, pending: dict[str, Any], timeout_s: float, text: String) -> None:
        """Publish ``text`` to each receiver of ``pending`` as soon as its inbox matches."""
        cond, interrupted, who = current_waiter()
        cond = cond if cond is not None else threading.Condition()
        deadline = time.monotonic() + timeout_s
        # DDS matching raises no event rclpy hands to another thread: look in short slices.
        while pending:
            for receiver in [r for r, p in pending.items() if p.get_subscription_count()]:
                pending.pop(receiver).publish(text)
            if not pending:
                return
            if interrupted():
                raise Interrupted(f"{who}: interrupted while agent {self.name!r} waited "
                                  f"for the inbox of {sorted(pending)}")
            left = deadline - time.monotonic()
            if left <= 0:
                missing = sorted(pending)
                known = [r for r in missing if self.directory.alive(r)]
                error = AgentUnreachable(
                    f"agent {self.name!r}: no inbox of {missing} matched on DDS within "
                    f"{timeout_s} s (in the directory: {known or 'none of them'}; live "
                    f"agents: {', '.join(a.name for a in self.directory.agents()) or 'none'})")
                error.unreachable = tuple(missing)
                raise error
            with cond:
                cond.wait_for(interrupted, min(0.01, left))

    def _send_later(self, box: queue.Queue[Message | None],
                    timeout_s: float | None = None) -> None:
        """An outbox thread: replies the executor thread must not wait for."""
        while True:
            message = box.get()
            if message is None:
                return
            try:
                self.send(message, timeout_s=timeout_s)
            except AgentError as exc:
                log.warning("agent %r: could not send %s to %s: %s", self.name,
                            message.performative.value, message.receivers, exc)

    # ------------------------------------------------------------------ receiving
    def _on_inbox(self, msg: String) -> None:
        """Executor thread: validate and sort; never raises."""
        text = msg.data
        try:
            data = json.loads(text)
            message = Message.from_wire(data)
        except (ValueError, RecursionError) as exc:
            reason = str(exc).replace("\n", "; ")
            self._emit_rejected(f"invalid message: {reason}", sender_of(text), text,
                                reply=True)
            return
        if self.name not in message.receivers:
            self._emit_rejected(f"misaddressed: this is the inbox of {self.name!r}, the "
                                f"message is for {message.receivers}", message.sender, text,
                                reply=True, message=message)
            return
        if self.trust.verifying:
            try:
                self.trust.check_message(data)
            except Refused as exc:
                log.warning("agent %r: refused %s from %r: %s", self.name,
                            message.performative.value, message.sender, exc)
                self._emit_rejected(f"refused: {exc}", message.sender, text, reply=True,
                                    message=message, refused=True)
                return
        self._route(message)

    def _route(self, message: Message) -> None:
        with self._lock:
            conversation = self._conversations.get(message.conversation_id)
            closed = (conversation is None
                      and message.conversation_id in self._closed_conversations)
            box = None
            if conversation is None and not closed:
                box = next((b for b in self._mailboxes if b.accepts(message)), None)
        if conversation is not None:
            conversation._deliver(message)
        elif closed:
            log.info("agent %r: %s from %r for the closed conversation %r dropped (it came "
                     "after the conversation ended)", self.name, message.performative.value,
                     message.sender, message.conversation_id)
        elif box is not None:
            box._deliver(message)
        elif message.protocol is not None \
                and message.performative is not Performative.NOT_UNDERSTOOD:
            # Part of a protocol nobody here runs: waiting in the inbox, it would leave
            # its initiator waiting for its timeout.
            with self._lock:
                served = sorted({p for b in self._mailboxes for p in (b.protocols or ())})
            self._emit_rejected(f"no responder for protocol {message.protocol!r} in agent "
                                f"{self.name!r} (it serves: {', '.join(served) or 'none'})",
                                message.sender, message.to_json(), reply=True,
                                message=message)
        else:
            self.inbox._deliver(message)

    def _emit(self, event: Event) -> None:
        """To the agent's own bus and every manager it is attached to, logged once."""
        for i, bus in enumerate(list(self._buses)):
            bus.emit(event, log_it=i == 0)

    def _emit_rejected(self, reason: str, sender: str | None, text: str, *,
                       reply: bool = False, message: Message | None = None,
                       refused: bool = False) -> None:
        detail = {"reason": reason, "sender": sender, "message": text[:300]}
        event = Event(EventKind.MESSAGE_REJECTED, f"agent:{self.name}", None, None, detail)
        self._emit(event)
        if not reply or sender is None or self._closed:
            return
        if message is not None and message.performative is Performative.NOT_UNDERSTOOD:
            return  # never answer a not-understood with one: two agents would ping-pong
        conversation_id, in_reply_to = _ids_of(text, message)
        if refused:
            # Its own conversation: a forged message must not end the conversation of the
            # agent it claims to be from (that one gets the refusal in its inbox).
            conversation_id = f"refused/{uuid.uuid4().hex[:16]}"
        answer = Message(
            performative=Performative.NOT_UNDERSTOOD, sender=self.name, receivers=[sender],
            conversation_id=conversation_id, in_reply_to=in_reply_to,
            protocol=message.protocol if message is not None and not refused else None,
            content={"reason": reason, "message": text[:500]})
        if not refused:
            self._outbox.put(answer)
            return
        try:
            self._refusal_box.put_nowait(answer)
        except queue.Full:
            log.info("agent %r: %d refusals wait to be sent; not answering %r", self.name,
                     REFUSALS_QUEUED, sender)

    # ------------------------------------------------------------------ consumers
    def conversation(self, *, protocol: str | None = None,
                     conversation_id: str | None = None) -> Conversation:
        """Open a conversation (a new id ``<name>/<random>`` unless given)."""
        cid = conversation_id or f"{self.name}/{uuid.uuid4().hex[:16]}"
        conversation = Conversation(self, cid, protocol)
        with self._lock:
            if self._closed:
                raise AgentError(f"agent {self.name!r} is closed")
            if cid in self._conversations:
                raise AgentError(f"agent {self.name!r}: conversation {cid!r} is open already")
            self._conversations[cid] = conversation
        return conversation

    def mailbox(self, *, protocols: Iterable[str] | None = None,
                performatives: Iterable[Performative] | None = None) -> Mailbox:
        """A mailbox that claims the messages (outside open conversations) of these
        protocols and performatives (None: any); the first open mailbox that claims a
        message gets it, the agent's :attr:`inbox` gets what none claims."""
        box = Mailbox(self, protocols=protocols, performatives=performatives,
                      label=f"mailbox for {sorted(protocols) if protocols else 'any'}")
        with self._lock:
            if self._closed:
                raise AgentError(f"agent {self.name!r} is closed")
            self._mailboxes.append(box)
        return box

    def _remove_mailbox(self, box: Mailbox) -> None:
        with self._lock:
            if isinstance(box, Conversation):
                if self._conversations.get(box.conversation_id) is box:
                    del self._conversations[box.conversation_id]
                    self._closed_conversations.append(box.conversation_id)
            elif box in self._mailboxes:
                self._mailboxes.remove(box)

    def receive(self, *, timeout_s: float | None = 10.0) -> Message:
        """The next message of :attr:`inbox` (see :meth:`Mailbox.receive`)."""
        return self.inbox.receive(timeout_s=timeout_s)

    async def areceive(self, *, timeout_s: float | None = 10.0) -> Message:
        return await self.inbox.areceive(timeout_s=timeout_s)

    # ------------------------------------------------------------------ robots
    def attach(self, manager: HighLevelBehaviorManager) -> None:
        """Make this the agent of ``manager``: its Behaviors and Actions reach it as
        ``self.agent`` (:class:`AgentBehavior`, :class:`AgentAction`) or
        ``agent_of(self.manager)``, and its events go to the manager's bus too."""
        _ATTACHED[manager] = self
        with self._lock:
            self._buses.append(manager.events)
            self._managers.append(weakref.ref(manager))

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Leave: tell every directory (the entry vanishes at once), close every mailbox
        and conversation, destroy the topics (and the node and context it made)."""
        with self._lock:
            closing = self._closed
            self._closed = True
            # One that lost its name says no goodbye: the holder's entry must stay.
            was_alive = self._state is EntryState.ALIVE and self.error is None
            self._state = EntryState.LEAVING
            boxes = [*self._conversations.values(), *self._mailboxes, self.inbox]
            managers = [m() for m in self._managers]
        if closing:
            if threading.current_thread() is not getattr(self, "_closer", None):
                self._close_done.wait()  # another thread is closing it: until it is closed
            return
        try:
            if was_alive:
                self._announce()
                # The goodbye must reach the readers before the writer is destroyed.
                self._dir_pub.wait_for_all_acked(Duration(seconds=0.3))
            self._remove_listener()
            for box in boxes:
                box.close()
            self._outbox.put(None)
            while True:  # the refusals thread ends with its queue, unsent ones dropped
                try:
                    self._refusal_box.get_nowait()
                except queue.Empty:
                    break
            self._refusal_box.put(None)
            for thread in (self._outbox_thread, self._refusal_thread):
                if thread is not threading.current_thread():
                    thread.join()
            for manager in managers:
                if manager is not None and _ATTACHED.get(manager) is self:
                    del _ATTACHED[manager]
            with self._lock:
                entities = list(self._entities) + [("publisher", p)
                                                   for p in self._publishers.values()]
                self._entities.clear()
                self._publishers.clear()
            for kind, entity in reversed(entities):
                try:
                    getattr(self.node, f"destroy_{kind}")(entity)
                except Exception:  # the node may be gone already (its owner shut it down)
                    log.debug("agent %r: destroying a %s failed", self.name, kind, exc_info=True)
            if self._own_node and self._ros is not None and self._own_ros is None:
                self._ros.destroy_node(self.node)
            if self._own_ros is not None:
                self._own_ros.shutdown()
        finally:
            self._close_done.set()

    @property
    def closed(self) -> bool:
        return self._closed


    def __repr__(self) -> str:
        return f"<Agent {self.name!r} {self._state.value}>"


def _checked_properties(agent: str, service: str, properties: Any) -> dict[str, Any]:
    if not isinstance(service, str) or not service:
        raise ConfigError(f"agent {agent!r}: a service name must be a non-empty str, got "
                          f"{service!r}")
    if not isinstance(properties, dict):
        raise ConfigError(f"agent {agent!r}: service {service!r}: properties must be a "
                          f"mapping, got {type(properties).__name__}")
    try:
        json.dumps(properties)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"agent {agent!r}: service {service!r}: properties must be JSON "
                          f"values: {exc}") from None
    return dict(properties)


def _ids_of(text: str, message: Message | None) -> tuple[str, str | None]:
    """The conversation and message ids of a rejected message, as far as they can be read."""
    if message is not None:
        return message.conversation_id, message.message_id
    try:
        data = json.loads(text)
    except (ValueError, RecursionError):
        data = None
    if not isinstance(data, dict):
        data = {}
    cid, mid = data.get("conversation_id"), data.get("message_id")
    cid = cid if isinstance(cid, str) and 0 < len(cid) <= 200 else \
        f"not-understood/{uuid.uuid4().hex[:16]}"
    mid = mid if isinstance(mid, str) and 0 < len(mid) <= 200 else None
    return cid, mid


class _HasAgent:
    manager: HighLevelBehaviorManager

    @property
    def agent(self) -> Agent:
        """The agent of the manager this runs under (see :meth:`Agent.attach`)."""
        return agent_of(self.manager)


class AgentBehavior(_HasAgent, Behavior):
    """A :class:`~beehave.Behavior` that talks to other agents through ``self.agent``."""


class AgentAction(_HasAgent, Action):
    """An :class:`~beehave.Action` that talks to other agents through ``self.agent``."""
