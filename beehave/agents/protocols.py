"""Interaction protocols as Behaviors: FIPA request and contract net, both sides.

Initiators are functions (:func:`request`, :func:`contract_net`) usable from any thread,
an awaitable one for asyncio code (:func:`arequest`, from a Logic), and Behaviors that
call them (:class:`RequestInitiator`, :class:`ContractNetInitiator`).
Inside a Behavior or Action every wait ends as soon as it is interrupted, and the
initiator then cancels what it started before :class:`~beehave.errors.Interrupted`
propagates: a cancel to an agent that agreed or was awarded, a reject-proposal to every
proposal not yet answered. No wait is unbounded: replies count until ``reply_by``, a
performer's report until ``done_timeout_s``, and a peer that leaves the directory ends
the wait for it at once.

Responders are Behaviors (:class:`RequestResponder`, :class:`ContractNetResponder`):
subclass one, write :meth:`Responder.perform` (and ``propose`` for contract net), register
it with the robot's manager. ``perform`` may return an :class:`~beehave.Action`: the
responder starts it under the type locks (a busy type is reported to the initiator as a
failure) and reports its result when it ends; a cancel interrupts it.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from beehave.action import Action
from beehave.agents.agent import Agent, AgentBehavior, Conversation, Mailbox
from beehave.agents.message import Message, Performative, jsonable
from beehave.errors import (
    ActionTypeBusy,
    AgentError,
    AgentUnreachable,
    ChildFailed,
    Interrupted,
    NoReply,
    ProtocolFailed,
)
from beehave.runnable import Runnable
from beehave.status import Status

log = logging.getLogger(__name__)

REQUEST = "fipa-request"
CONTRACT_NET = "fipa-contract-net"

REFUSALS = (Performative.REFUSE, Performative.NOT_UNDERSTOOD)


def cancel_quietly(conv: Conversation, receivers: list[str], performative: Performative,
                    content: Any) -> None:
    """Best effort while unwinding: an unreachable peer must not hide the first error."""
    if not receivers:
        return
    try:
        conv.send(performative, receivers, content, timeout_s=0.5)
    except (AgentError, Interrupted) as exc:
        log.warning("agent %r: could not send %s to %s in %r: %s", conv.agent.name,
                    performative.value, receivers, conv.conversation_id, exc)


# ---------------------------------------------------------------------- FIPA request
def request(agent: Agent, receiver: str, content: Any = None, *, protocol: str = REQUEST,
            timeout_s: float = 10.0) -> Any:
    """Ask ``receiver`` to do something and return the content of its ``inform``.

    ``timeout_s`` bounds the whole exchange (it is the request's ``reply_by``). Raises
    :class:`~beehave.errors.ProtocolFailed` on refuse, not-understood or failure (``reply``
    holds it) and when ``receiver`` leaves the directory; :class:`~beehave.errors.NoReply`
    at the deadline and :class:`~beehave.errors.Interrupted` when the calling Behavior or
    Action is interrupted — both after sending ``cancel``. From asyncio code (a Logic),
    await :func:`arequest` instead."""
    with agent.conversation(protocol=protocol) as conv:
        deadline = time.monotonic() + timeout_s
        conv.watch(receiver)
        sent = conv.send(Performative.REQUEST, [receiver], content, reply_by_s=timeout_s)
        try:
            while True:
                reply = conv.receive(timeout_s=max(0.0, deadline - time.monotonic()))
                if _request_done(agent, receiver, sent, reply):
                    return reply.content
        except (NoReply, Interrupted):
            cancel_quietly(conv, [receiver], Performative.CANCEL,
                            {"reason": "the initiator stopped waiting"})
            raise


async def arequest(agent: Agent, receiver: str, content: Any = None, *,
                   protocol: str = REQUEST, timeout_s: float = 10.0) -> Any:
    """:func:`request` for asyncio code (a Logic): the same exchange, awaited without
    blocking the event loop. Cancelling the awaiting task (the Logic is switched away or
    stopped) sends ``cancel`` to ``receiver`` before the :class:`asyncio.CancelledError`
    propagates, as :class:`~beehave.errors.NoReply` at the deadline does; refusals and
    failures raise :class:`~beehave.errors.ProtocolFailed`.

    ::

        class Fetch(Logic):
            async def run(self) -> None:
                done = await arequest(self.talker, "depot_1", {"bring": "steel"},
                                      timeout_s=5.0)
    """
    with agent.conversation(protocol=protocol) as conv:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        conv.watch(receiver)
        sent = await agent.asend(Message(
            performative=Performative.REQUEST, sender=agent.name, receivers=[receiver],
            conversation_id=conv.conversation_id, protocol=protocol, content=content,
            reply_by=time.time() + timeout_s))
        try:
            while True:
                reply = await conv.areceive(timeout_s=max(0.0, deadline - loop.time()))
                if _request_done(agent, receiver, sent, reply):
                    return reply.content
        except (NoReply, asyncio.CancelledError):
            # The receiver's inbox is matched (the request went out): this send hands the
            # cancel to DDS without waiting, so the loop is not blocked while unwinding.
            cancel_quietly(conv, [receiver], Performative.CANCEL,
                            {"reason": "the initiator stopped waiting"})
            raise


def _request_done(agent: Agent, receiver: str, sent: Message, reply: Message) -> bool:
    """True when ``reply`` is the inform that ends the request; raises
    :class:`~beehave.errors.ProtocolFailed` on a refusal or failure of ``receiver``;
    False for what is no answer yet (its agree, another agent's message)."""
    if reply.sender != receiver or reply.performative is Performative.AGREE:
        return False
    if reply.performative is Performative.INFORM:
        return True
    if reply.performative in (*REFUSALS, Performative.FAILURE):
        raise ProtocolFailed(
            f"agent {agent.name!r}: {receiver!r} answered the request "
            f"{sent.message_id[:8]} with {reply.performative.value}: "
            f"{reply.content!r:.200}", reply=reply)
    return False


class RequestInitiator(AgentBehavior):
    """Runs :func:`request`; its result is the inform's content."""

    def __init__(self, receiver: str, content: Any = None, *, protocol: str = REQUEST,
                 timeout_s: float = 10.0) -> None:
        self.receiver = receiver
        self.content = content
        self.protocol = protocol
        self.timeout_s = timeout_s

    def run(self) -> Any:
        return request(self.agent, self.receiver, self.content, protocol=self.protocol,
                       timeout_s=self.timeout_s)


# ---------------------------------------------------------------------- contract net
@dataclass
class Award:
    """How a contract net ended: who did the task, for what, and what they reported."""

    conversation_id: str
    awardee: str
    proposal: Any
    cost: float
    result: Any
    #: ``(agent, outcome)`` for every award tried, in order ("inform", "failure: …").
    attempts: list[tuple[str, str]] = field(default_factory=list)
    #: Seconds from sending the cfp to sending the (first) accept-proposal.
    award_latency_s: float = 0.0


def proposal_cost(proposal: Message) -> float:
    """The default cost function: ``content["cost"]`` of a proposal."""
    content = proposal.content
    if not isinstance(content, dict) or not isinstance(content.get("cost"), (int, float)):
        raise ValueError(f"proposal of {proposal.sender!r} has no numeric content['cost']: "
                         f"{content!r:.200}")
    return float(content["cost"])


def contract_net(agent: Agent, service: str, task: Any, *,
                 cost: Callable[[Message], float] = proposal_cost,
                 constraints: dict[str, Any] | None = None,
                 candidates: list[str] | None = None, reply_by_s: float = 1.0,
                 done_timeout_s: float = 60.0, protocol: str = CONTRACT_NET,
                 observer: Callable[[str, dict[str, Any]], None] | None = None) -> Award:
    """Award ``task`` to the cheapest agent offering ``service`` and wait until it is done.

    1. cfp to ``candidates`` (default: the directory's ``search(service, **constraints)``,
       without this agent), with ``reply_by`` ``reply_by_s`` from now;
    2. proposals are collected until every candidate answered or the deadline passed;
       ``cost(proposal)`` ranks them (a proposal whose cost cannot be computed counts as a
       refusal, and the proposer gets a reject-proposal saying why);
    3. accept-proposal to the cheapest, reject-proposal to the others;
    4. the awardee's inform ends it; on its failure, on silence for ``done_timeout_s`` or
       when it leaves the directory, it gets a cancel and the next cheapest is awarded
       (accept-proposal to a proposal rejected in step 3: a responder keeps its proposals
       for that). Raises :class:`~beehave.errors.ProtocolFailed` when nobody is left.

    Interrupted (a Behavior switched away): cancel to the awardee, reject-proposal to
    proposals not yet answered, cancel to the candidates that have not answered yet; then
    :class:`~beehave.errors.Interrupted`.

    ``observer(step, detail)``, when given, is told every step as it happens, in this
    thread (a mission controller's status reports): ``"cfp"`` (``candidates``),
    ``"awarded"`` (``awardee``, ``cost``, ``attempt`` from 1), ``"failed"`` (``awardee``,
    ``reason``: the next proposer is tried) and ``"done"`` (``awardee``, ``result``); each
    detail holds the ``conversation_id``. An observer that raises is logged, never
    disturbs the negotiation."""
    names = candidates if candidates is not None else [
        info.name for info in agent.directory.search(service, **(constraints or {}))
        if info.name != agent.name]
    if not names:
        known = ", ".join(a.name for a in agent.directory.agents()) or "none"
        raise ProtocolFailed(f"agent {agent.name!r}: no agent offers {service!r}"
                             f"{f' with {constraints}' if constraints else ''} "
                             f"(agents alive: {known})")
    with agent.conversation(protocol=protocol) as conv:
        def tell(step: str, **detail: Any) -> None:
            if observer is not None:
                try:
                    observer(step, {"conversation_id": conv.conversation_id, **detail})
                except Exception:
                    log.exception("agent %r: contract-net observer failed on %r",
                                  agent.name, step)

        unanswered = set(names)  # asked, no answer yet
        undecided: set[str] = set()  # proposed, neither accepted nor rejected yet
        proposals: list[tuple[float, str, Message]] = []
        current: str | None = None  # awarded, no report yet
        try:
            started = time.monotonic()
            for name in names:
                conv.watch(name)
            try:
                tell("cfp", candidates=list(names))
                conv.send(Performative.CFP, names, task, reply_by_s=reply_by_s)
            except AgentUnreachable as exc:  # the others got it: they are not kept waiting
                log.warning("agent %r: cfp not delivered: %s", agent.name, exc)
                unanswered.difference_update(exc.unreachable)
                if not unanswered:
                    raise ProtocolFailed(f"agent {agent.name!r}: no candidate for "
                                         f"{service!r} is reachable: {exc}") from exc
            deadline = started + reply_by_s
            while unanswered and time.monotonic() < deadline:
                try:
                    reply = conv.receive(timeout_s=max(0.0, deadline - time.monotonic()))
                except NoReply:
                    break
                if reply.sender not in unanswered:
                    continue
                unanswered.discard(reply.sender)
                conv.unwatch(reply.sender)
                if reply.performative is Performative.PROPOSE:
                    try:
                        proposals.append((float(cost(reply)), reply.sender, reply))
                        undecided.add(reply.sender)
                    except (ValueError, TypeError, KeyError) as exc:
                        conv.send(Performative.REJECT_PROPOSAL, [reply.sender],
                                  {"reason": f"cost not computable: {exc}"})
            if unanswered:  # late: they are not waited for
                late = sorted(unanswered)
                unanswered.clear()
                conv.send(Performative.CANCEL, late, {"reason": "no proposal before reply_by"})
            if not proposals:
                raise ProtocolFailed(f"agent {agent.name!r}: no proposal for {service!r} "
                                     f"from {names} within {reply_by_s} s")
            proposals.sort(key=lambda p: (p[0], p[1]))
            attempts: list[tuple[str, str]] = []
            latency = 0.0
            for rank, (price, name, proposal) in enumerate(proposals):
                current = name
                undecided.discard(name)
                conv.watch(name)
                conv.send(Performative.ACCEPT_PROPOSAL, [name], proposal.content,
                          in_reply_to=proposal.message_id)
                tell("awarded", awardee=name, cost=price, attempt=rank + 1)
                if rank == 0:
                    latency = time.monotonic() - started
                    losers = sorted(undecided)
                    undecided.clear()
                    if losers:
                        conv.send(Performative.REJECT_PROPOSAL, losers,
                                  {"reason": f"awarded to {name!r}"})
                outcome = _await_done(conv, name, done_timeout_s)
                if outcome.performative is Performative.INFORM:
                    attempts.append((name, "inform"))
                    current = None
                    tell("done", awardee=name, result=outcome.content)
                    return Award(conv.conversation_id, name, proposal.content, price,
                                 outcome.content, attempts, latency)
                why = outcome.content.get("reason") if isinstance(outcome.content, dict) \
                    else outcome.content
                attempts.append((name, f"{outcome.performative.value}: {why}"))
                tell("failed", awardee=name, reason=f"{outcome.performative.value}: {why}")
                # Withdraw before the next award, so that the task never runs twice: a
                # silent awardee might still do it, and so might one that "left" the
                # directory only because its announcements were late (a loaded host) —
                # an expired lease is no proof of death. A dead one never reads it.
                cancel_quietly(conv, [name], Performative.CANCEL,
                                {"reason": f"re-awarded after {outcome.performative.value}: "
                                           f"{why}"})
                current = None
            raise ProtocolFailed(f"agent {agent.name!r}: every proposer of {service!r} failed "
                                 f"the task: {attempts}")
        except Interrupted:
            why = {"reason": "the initiator was interrupted"}
            if current is not None:
                cancel_quietly(conv, [current], Performative.CANCEL, why)
            cancel_quietly(conv, sorted(undecided), Performative.REJECT_PROPOSAL, why)
            cancel_quietly(conv, sorted(unanswered), Performative.CANCEL, why)
            raise


def _await_done(conv: Conversation, name: str, done_timeout_s: float) -> Message:
    """The awardee's inform or failure; silence and departure come back as a failure."""
    deadline = time.monotonic() + done_timeout_s
    while True:
        left = deadline - time.monotonic()
        try:
            reply = conv.receive(timeout_s=max(0.0, left))
        except NoReply:
            return Message(performative=Performative.FAILURE, sender=name,
                           receivers=[conv.agent.name], conversation_id=conv.conversation_id,
                           content={"reason": f"silent for {done_timeout_s} s"})
        if reply.sender != name:
            continue  # a late proposal or a stale report of an earlier awardee
        if reply.performative in (Performative.INFORM, Performative.FAILURE, *REFUSALS):
            conv.unwatch(name)
            return reply


class ContractNetInitiator(AgentBehavior):
    """Runs :func:`contract_net`; its result is the :class:`Award`. Override :meth:`cost`
    to rank proposals your way."""

    def __init__(self, service: str, task: Any = None, *,
                 constraints: dict[str, Any] | None = None, reply_by_s: float = 1.0,
                 done_timeout_s: float = 60.0) -> None:
        self.service = service
        self.task = task
        self.constraints = constraints
        self.reply_by_s = reply_by_s
        self.done_timeout_s = done_timeout_s

    def cost(self, proposal: Message) -> float:
        """Optional hook: the price of ``proposal``, lower is better (default: its
        ``content["cost"]``). Called in this behaviour's thread as proposals arrive."""
        return proposal_cost(proposal)

    def run(self) -> Award:
        return contract_net(self.agent, self.service, self.task, cost=self.cost,
                            constraints=self.constraints, reply_by_s=self.reply_by_s,
                            done_timeout_s=self.done_timeout_s)


# ---------------------------------------------------------------------- responders
def _call_order(cfp: Message) -> tuple[float, str]:
    """A call's place in one order that every responder sees alike: when its initiator
    sent it, then its conversation (ties)."""
    return (cfp.sent_at, cfp.conversation_id)


@dataclass
class ResponderTask:
    request: Message
    action: Action | None = None


class Responder(AgentBehavior):
    """The responder side of a protocol: answers the messages of :attr:`protocol` that
    start conversations, one at a time, in this behaviour's thread; the actions it starts
    run in parallel (each under its type lock).

    When it is interrupted (switched away), every task it started gets a failure report
    and its action is interrupted with it."""

    protocol: str = REQUEST
    service: str | None = None
    """When set, the service this responder registers in the directory while it runs (with
    :meth:`service_properties`), so that initiators find it only when it can answer."""
    _box: Mailbox | None = None
    proposal_valid_s: float = 60.0
    """How long a proposal that was not accepted can still be accepted (contract net: an
    initiator re-awards a task to the next cheapest when its awardee fails)."""
    queue_tasks: bool = False
    """When True, a task whose action finds its type busy (an earlier task still drives)
    waits in :attr:`waiting`, first come first served, and starts as soon as the type is
    free — a robot that accepts work while it works. When False (the default), it is
    answered with ``failure`` naming the holder."""

    answer_cfps_in_turn: bool = False
    """Contract net: when True, a call for proposals that arrives while this responder's
    proposal for an earlier call (in the order the initiators sent them, the same for every
    responder: no two wait for each other) is undecided — neither accepted nor rejected —
    is answered once that one is decided; at the latest after half the time its initiator
    gives (``reply_by``), then with what is known. So a robot called by two auctions at once
    bids on the second knowing whether it won the first: concurrent calls spread over the
    fleet instead of all going to the one robot that was idle when they came. A proposal
    left undecided for :attr:`undecided_max_s` (an initiator that went away) no longer
    holds anything back."""
    undecided_max_s: float = 3.0
    gather_s: float = 0.05
    """With :attr:`answer_cfps_in_turn`: how long a call is held before it is answered, so
    that calls sent at about the same time are answered in the order they were sent, not
    in the order each responder happened to receive them (then two responders agree on
    which call comes first). Bounded by half the call's reply time."""

    def perform(self, task: Message) -> Any:
        """Do what ``task`` asks (a request, or the accept-proposal of an award, whose
        content is the proposal you made: put in the proposal what you need here).

        Return an :class:`~beehave.Action` to run it under the type locks — its result is
        reported with ``inform`` when it succeeds, ``failure`` otherwise — or the result
        itself (a JSON value) when it is done at once. Raise to report a failure."""
        raise NotImplementedError(f"{type(self).__name__} must override perform()")

    def refuse(self, message: Message) -> str | None:
        """Optional hook (request): a reason to refuse ``message``, or None to agree."""
        return None

    def propose(self, cfp: Message) -> Any:
        """Optional hook (contract net): the proposal for ``cfp`` (a JSON value; the
        default initiator ranks ``{"cost": …}``), or None to refuse. Default: refuse. Raising
        refuses too, with the exception as the reason."""
        return None

    def service_properties(self) -> dict[str, Any]:
        """Optional hook: the properties :attr:`service` is registered with (default
        none); called once when the responder starts."""
        return {}

    def on_child_ended(self, child: Runnable) -> None:
        box = getattr(self, "_box", None)
        if box is not None:
            box.poke()

    def run(self) -> None:
        self.tasks: dict[str, ResponderTask] = {}
        #: Accepted tasks waiting for their action type (:attr:`queue_tasks`), oldest first.
        self.waiting: list[ResponderTask] = []
        self.proposals: dict[str, tuple[Message, float]] = {}
        #: Proposals made and not yet accepted or rejected: conversation → (when, monotonic;
        #: the call's place in the order of calls, see _call_order).
        self.undecided: dict[str, tuple[float, tuple[float, str]]] = {}
        #: Calls for proposals held back (:attr:`answer_cfps_in_turn`), with the monotonic
        #: time by which each is answered whatever happens; oldest first.
        self.deferred: list[tuple[Message, float, float]] = []
        with self.agent.mailbox(protocols=[self.protocol]) as box:
            self._box = box
            if self.service is not None:
                self.agent.register(self.service, **self.service_properties())
            try:
                while True:
                    now = time.monotonic()
                    wait = (None if not self.deferred else max(0.0, min(
                        gather if gather > now else by
                        for _, gather, by in self.deferred) - now))
                    message = box._next(wait)
                    self._reap()
                    if message is not None:
                        self._handle(message)
                    self._answer_deferred()
            finally:
                if self.service is not None and self.service in self.agent.services:
                    self.agent.deregister(self.service)
                self._abandon()

    def _handle(self, message: Message) -> None:
        agent = self.agent
        kind = message.performative
        cid = message.conversation_id
        if kind is Performative.REQUEST:
            reason = self.refuse(message)
            if reason is not None:
                self._reply(message, Performative.REFUSE, {"reason": reason})
                return
            self._reply(message, Performative.AGREE)
            self._start(message)
        elif kind is Performative.CFP:
            if self.answer_cfps_in_turn:
                now, wall = time.monotonic(), time.time()
                half = max(0.0, (message.reply_by - wall) / 2
                           if message.reply_by is not None else 0.0)
                self.deferred.append((message, now + min(self.gather_s, half), now + half))
                self.deferred.sort(key=lambda entry: _call_order(entry[0]))
                return
            self._bid(message)
        elif kind is Performative.ACCEPT_PROPOSAL:
            self.undecided.pop(cid, None)
            entry = self.proposals.pop(cid, None)
            if entry is None or cid in self.tasks:
                self._reply(message, Performative.FAILURE,
                            {"reason": "no open proposal in this conversation (expired, "
                                       "cancelled, or awarded already)"})
                return
            self._start(message)
        elif kind is Performative.REJECT_PROPOSAL:
            self.undecided.pop(cid, None)  # kept for proposal_valid_s: a re-award may come
        elif kind is Performative.CANCEL:
            self.undecided.pop(cid, None)
            self.deferred = [d for d in self.deferred if d[0].conversation_id != cid]
            self.proposals.pop(cid, None)
            self.waiting = [t for t in self.waiting if t.request.conversation_id != cid]
            task = self.tasks.pop(cid, None)
            if task is not None and task.action is not None:
                task.action.interrupt()
                log.info("%s: %s cancelled by %r", self.path, cid, message.sender)
        elif kind is not Performative.NOT_UNDERSTOOD:
            agent._emit_rejected(f"{self.path} ({self.protocol} responder) does not expect "
                                 f"{kind.value} outside a task it runs", message.sender,
                                 message.to_json(), reply=True, message=message)

    def _blocked(self, order: tuple[float, str]) -> bool:
        """Whether a call at ``order`` waits: a proposal of this responder for an earlier
        call is undecided (forgetting those older than :attr:`undecided_max_s`). Only
        earlier calls hold a call back: two responders that received two calls in
        opposite orders then never wait for each other."""
        old = time.monotonic() - self.undecided_max_s
        for cid in [c for c, (at, _) in self.undecided.items() if at < old]:
            del self.undecided[cid]
        return any(earlier < order for _, earlier in self.undecided.values())

    def _answer_deferred(self) -> None:
        """Answer held calls in the order of calls: each once its gathering time has
        passed, no earlier call is held, and no proposal for an earlier one is undecided;
        or once its time is up (each answer may make a new undecided proposal: the later
        ones wait again)."""
        progress = True
        while progress:
            progress = False
            now = time.monotonic()
            for i, (message, gather, by) in enumerate(self.deferred):  # (kept in order)
                if by <= now or (i == 0 and gather <= now
                                 and not self._blocked(_call_order(message))):
                    del self.deferred[i]
                    self._bid(message)
                    progress = True
                    break

    def _bid(self, message: Message) -> None:
        """Answer a call for proposals with :meth:`propose`'s offer or a refusal."""
        cid = message.conversation_id
        self._expire_proposals()
        try:
            offer = self.propose(message)
        except Exception as exc:
            # A cfp is answered with propose, refuse or not-understood (FIPA): a task this
            # agent cannot serve (an unknown machine) is a refusal, with why.
            log.warning("%s: propose() raised on %s: %r", self.path, cid, exc)
            self._reply(message, Performative.REFUSE, {"reason": repr(exc)})
            return
        if offer is None:
            self._reply(message, Performative.REFUSE, {"reason": "no proposal"})
        elif self._reply(message, Performative.PROPOSE, jsonable(offer)):
            self._propose(cid, message)
            self.undecided[cid] = (time.monotonic(), _call_order(message))

    def _reply(self, to: Message, performative: Performative, content: Any = None) -> bool:
        try:
            self.agent.reply(to, performative, content)
        except AgentError as exc:
            log.warning("%s: could not answer %r: %s", self.path, to.sender, exc)
            return False
        return True

    def _start(self, message: Message) -> None:
        try:
            outcome = self.perform(message)
        except Exception as exc:
            self._reply(message, Performative.FAILURE, {"reason": repr(exc)})
            return
        if not isinstance(outcome, Action):
            self._reply(message, Performative.INFORM, {"result": jsonable(outcome)})
            return
        if self.queue_tasks and self.waiting:
            self.waiting.append(ResponderTask(message, outcome))  # behind the earlier ones
            return
        if self._launch(ResponderTask(message, outcome), queue=self.queue_tasks):
            self._reap()  # it may have ended already

    def _launch(self, task: ResponderTask, *, queue: bool) -> bool:
        """Start ``task``'s action; True when it runs. A busy type queues it (``queue``,
        at the front: it was next) or fails it."""
        assert task.action is not None
        while True:
            try:
                self.start_action(task.action)
                break
            except ChildFailed:
                continue  # an earlier task's action failed just now: _reap reports it
            except ActionTypeBusy as exc:
                if queue:
                    self.waiting.insert(0, task)
                else:
                    self._reply(task.request, Performative.FAILURE, {"reason": str(exc)})
                return False
        self.tasks[task.request.conversation_id] = task
        return True

    def _reap(self) -> None:
        self._reap_ended()
        while self.waiting and self._launch(self.waiting.pop(0), queue=True):
            self._reap_ended()

    def _reap_ended(self) -> None:
        for cid, task in list(self.tasks.items()):
            action = task.action
            if action is None or not action.wait(0):
                continue
            del self.tasks[cid]
            if action.status is Status.SUCCEEDED:
                self._reply(task.request, Performative.INFORM,
                            {"result": jsonable(action.result)})
            else:
                self._reply(task.request, Performative.FAILURE,
                            {"reason": f"{action.path} ended {action.status.name}"
                                       f"{f': {action.error!r}' if action.error else ''}"})

    def _expire_proposals(self) -> None:
        # Proposals are kept in the order they were made (see _propose): the expired ones
        # are at the front, and the scan stops at the first that is still valid — called
        # for every cfp, it must not walk every proposal of the last proposal_valid_s.
        now = time.monotonic()
        while self.proposals:
            cid, (_, at) = next(iter(self.proposals.items()))
            if now - at <= self.proposal_valid_s:
                return
            del self.proposals[cid]

    def _propose(self, cid: str, cfp: Message) -> None:
        """Keep a proposal made now (after any older one: see _expire_proposals)."""
        self.proposals.pop(cid, None)
        self.proposals[cid] = (cfp, time.monotonic())

    def _abandon(self) -> None:
        for cfp, _, _ in self.deferred:
            self._reply(cfp, Performative.REFUSE, {"reason": f"{self.path} stopped"})
        self.deferred.clear()
        for task in self.waiting:
            self._reply(task.request, Performative.FAILURE, {"reason": f"{self.path} stopped"})
        self.waiting.clear()
        for task in self.tasks.values():
            if task.action is not None:
                task.action.interrupt()
            self._reply(task.request, Performative.FAILURE,
                        {"reason": f"{self.path} stopped"})
        self.tasks.clear()


class RequestResponder(Responder):
    """Answers FIPA requests: agree (or refuse via :meth:`refuse`), then
    :meth:`perform`, then inform or failure."""

    protocol = REQUEST


class ContractNetResponder(Responder):
    """Answers calls for proposals with :meth:`propose` and performs awarded tasks with
    :meth:`perform` (see :class:`Responder`)."""

    protocol = CONTRACT_NET
