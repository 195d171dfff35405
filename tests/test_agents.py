"""The agent layer over real DDS: directory, messages, FIPA request and contract net.

Other agents run as separate processes (``tests/agents_node.py``) on this run's
ROS_DOMAIN_ID (conftest), and are killed by PID in a ``finally``. Waits are on conditions
with generous timeouts; the only time bound asserted is the issue's promise that a killed
agent leaves every directory within its lease + 0.5 s.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from agent_procs import AgentProc, directory_state, stop_all  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from beehave import (  # noqa: E402
    Action,
    Behavior,
    HighLevelBehaviorManager,
    Logic,
    LowLevelBehaviorManager,
    Status,
)
from beehave.agents import (  # noqa: E402
    Agent,
    AgentBehavior,
    AgentNameTaken,
    AgentUnreachable,
    Change,
    DirectoryEvent,
    Message,
    NoReply,
    Performative,
    ProtocolFailed,
)
from beehave.agents.agent import INBOX_PREFIX, inbox_qos  # noqa: E402
from beehave.agents.protocols import (  # noqa: E402
    REQUEST,
    Award,
    ContractNetInitiator,
    ContractNetResponder,
    RequestInitiator,
    RequestResponder,
    arequest,
    contract_net,
    request,
)
from beehave.errors import ConfigError, Interrupted  # noqa: E402
from beehave.events import EventKind  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402

NODE = Path(__file__).with_name("agents_node.py")
LEASE_S = 1.0
WAIT_S = WALL_TIMEOUT_S  # the suite's one bound (beehave.testing): the machine may be loaded
PROBE_S = 0.3  # names in this file are unique: a short probe keeps the tests fast
#: How long an awardee may stay silent before the task goes to the next bidder: a timing
#: under test, yet long enough that an honest reply over DDS on a loaded host is not late.
SILENT_S = 3.0
# A negative check (no reply is to come) always runs to its end: short on purpose. A loaded
# machine can only make it miss a wrong reply, never fail a right test.
QUIET_S = 0.3


class Proc(AgentProc):
    """An agent process (``tests/agents_node.py``) whose JSON lines are collected as they
    come."""

    def __init__(self, name: str, **options: Any) -> None:
        args = [sys.executable, str(NODE), name, "--lease-s", str(LEASE_S)]
        for key, value in options.items():
            args += [f"--{key.replace('_', '-')}", str(value)]
        super().__init__(name, args, wait_s=WAIT_S)

    def saw(self, kind: str, **match: Any) -> bool:
        with self.cond:
            return any(e["event"] == kind and all(e.get(k) == v for k, v in match.items())
                       for e in self.events)


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    started: list[Proc] = []
    try:
        yield started
    finally:
        stop_all(started)


@pytest.fixture
def ros() -> Iterator[RosContext]:
    with RosContext() as context:
        yield context


def _wait(predicate: Callable[[], bool], what: str, timeout_s: float = WAIT_S) -> None:
    """For state without a notifier (the directory as another agent sees it)."""
    assert wait_until(predicate, timeout_s), f"timed out waiting for {what}"


def _spawn(procs: list[Proc], name: str, **options: Any) -> Proc:
    proc = Proc(name, **options)
    procs.append(proc)
    return proc


def test_a_node_that_ignores_sigterm_is_aborted_with_its_stacks_shown(
        monkeypatch: pytest.MonkeyPatch, procs: list[Proc]) -> None:
    """The kit's own promise: a node hung in its shutdown costs TERM_WAIT_S, not the whole
    WALL_TIMEOUT_S, and the warning shows where its threads were (SIGABRT, faulthandler)."""
    import agent_procs

    monkeypatch.setattr(agent_procs, "TERM_WAIT_S", 1.0)
    here = str(Path(__file__).parent)
    script = (f"import signal, sys, time; sys.path.insert(0, {here!r}); "
              "import agents_events; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
              "agents_events.say('ready'); time.sleep(600)")
    proc = AgentProc("stubborn", [sys.executable, "-c", script])
    procs.append(proc)  # type: ignore[arg-type]  # (killed by the fixture if this fails)
    proc.wait_event("ready")
    t0 = time.monotonic()
    with pytest.warns(UserWarning, match="stubborn did not end within 1 s of SIGTERM") as seen:
        proc.stop()
    assert time.monotonic() - t0 < WALL_TIMEOUT_S / 4  # not the whole bound
    assert proc.popen.returncode == -6  # SIGABRT
    stacks = str(seen[0].message)
    assert "Current thread" in stacks and 'File "<string>", line 1' in stacks, stacks


# ---------------------------------------------------------------------- messages
def test_message_schema_refuses_bad_fields_by_name() -> None:
    good = Message(performative=Performative.CFP, sender="m1", receivers=["a"],
                   conversation_id="c1", content={"x": 1})
    again = Message.from_json(good.to_json())
    assert again == good
    with pytest.raises(ValueError, match="performative"):
        Message.from_json(good.to_json().replace('"cfp"', '"shout"'))
    with pytest.raises(ValueError, match="unsupported schema"):
        Message.from_json(good.to_json().replace("beehave.acl/1", "beehave.acl/9"))
    with pytest.raises(ValueError, match="not an agent name"):
        Message(performative=Performative.CFP, sender="no spaces", receivers=["a"],
                conversation_id="c1")
    reply = good.reply(Performative.PROPOSE, {"cost": 2})
    assert (reply.receivers, reply.conversation_id, reply.in_reply_to, reply.protocol) == \
        (["m1"], "c1", good.message_id, None)


def test_agent_options_are_checked(ros: RosContext) -> None:
    with pytest.raises(ConfigError, match="agent name 'bad name'"):
        Agent("bad name", ros=ros)
    with pytest.raises(ConfigError, match="lease_s"):
        Agent("fine", ros=ros, lease_s=0)
    # NaN would make every wait end at once, infinity overflow the waits.
    with pytest.raises(ConfigError, match="agent 'fine': probe_s"):
        Agent("fine", ros=ros, probe_s=math.nan)
    with pytest.raises(ConfigError, match="agent 'fine': send_timeout_s"):
        Agent("fine", ros=ros, send_timeout_s=math.inf)
    with pytest.raises(ConfigError, match="JSON"):
        Agent("fine", ros=ros, services={"x": {"f": object()}})


# ---------------------------------------------------------------------- directory
def test_register_search_by_constraints_subscribe_and_deregister(ros: RosContext) -> None:
    with Agent("dir_seeker", ros=ros, probe_s=PROBE_S, lease_s=LEASE_S) as seeker:
        seen: list[DirectoryEvent] = []
        cond = threading.Condition()

        def note(event: DirectoryEvent) -> None:
            with cond:
                seen.append(event)
                cond.notify_all()

        unsubscribe = seeker.directory.subscribe("transport", note, zone="north")
        with Agent("dir_offer", ros=ros, probe_s=PROBE_S, lease_s=LEASE_S,
                   services={"transport": {"zone": "north", "kg": 50}}) as offer:
            with cond:
                assert cond.wait_for(lambda: len(seen) >= 1, WAIT_S), "no APPEARED"
            assert (seen[0].change, seen[0].agent.name) == (Change.APPEARED, "dir_offer")
            assert [a.name for a in seeker.directory.search("transport", zone="north",
                                                             kg=50)] == ["dir_offer"]
            assert seeker.directory.search("transport", zone="south") == []
            assert seeker.directory.search("transport", colour="red") == []
            offer.register("transport", zone="south")  # moves out of the subscription
            with cond:
                assert cond.wait_for(lambda: len(seen) >= 2, WAIT_S), seen
            assert seen[1].change is Change.DISAPPEARED
            offer.register("charging", slots=2)
            _wait(lambda: bool(seeker.directory.search("charging", slots=2)), "charging")
            offer.deregister("charging")
            _wait(lambda: not seeker.directory.search("charging"), "deregistered charging")
            with pytest.raises(KeyError, match="offers: transport"):
                offer.deregister("charging")
            offer.register("transport", zone="north")
            with cond:
                assert cond.wait_for(lambda: len(seen) >= 3, WAIT_S), seen
        # A clean close leaves at once (no lease wait).
        with cond:
            assert cond.wait_for(lambda: len(seen) >= 4, WAIT_S), seen
        assert (seen[3].change, seen[3].reason) == (Change.DISAPPEARED, "left")
        unsubscribe()


def test_killed_agent_disappears_within_its_lease(ros: RosContext,
                                                   procs: list[Proc]) -> None:
    proc = _spawn(procs, "dir_victim")
    gone = threading.Event()
    reasons: list[str] = []
    with Agent("dir_watcher", ros=ros, probe_s=PROBE_S, lease_s=LEASE_S) as watcher:
        def note(event: DirectoryEvent) -> None:
            if event.agent.name == "dir_victim" and event.change is Change.DISAPPEARED:
                reasons.append(event.reason)
                gone.set()

        watcher.directory.subscribe("transport", note)
        proc.wait_event("ready")
        _wait(lambda: watcher.directory.alive("dir_victim"), "dir_victim in the directory")
        killed_at = time.monotonic()
        proc.kill()
        assert gone.wait(WAIT_S), directory_state(watcher, "the killed agent never left "
                                                   "the directory")
        # Gone because its lease ran out, not for another reason. How late is no check: the
        # directory adds the time its own process stalled to every lease, and beside two
        # busy loops that made 6.6 s of a 1 s lease (a stress run).
        assert reasons == ["lease expired"], \
            f"{reasons} after {time.monotonic() - killed_at:.2f} s (lease {LEASE_S} s)"
        assert watcher.directory.search("transport") == []


def test_a_name_alive_elsewhere_is_refused(ros: RosContext, procs: list[Proc]) -> None:
    proc = _spawn(procs, "dup_name")
    proc.wait_event("ready")
    with pytest.raises(AgentNameTaken, match="'dup_name' is taken"):
        # A generous probe: DDS discovery of a new process can take seconds under load.
        Agent("dup_name", ros=ros, lease_s=LEASE_S, probe_s=3.0)
    second = _spawn(procs, "dup_name")
    second.wait_event("taken")
    assert second.popen.wait(WAIT_S) == 3
    assert proc.popen.poll() is None  # the holder goes on
    with Agent("dup_asker", ros=ros, probe_s=PROBE_S) as asker:
        _wait(lambda: asker.directory.alive("dup_name"), "dup_name")
        assert request(asker, "dup_name", "still there", timeout_s=WAIT_S) == \
            {"result": "still there"}


# ---------------------------------------------------------------------- messages
def test_malformed_and_misaddressed_messages_get_not_understood(
        ros: RosContext, procs: list[Proc]) -> None:
    target = _spawn(procs, "nu_target")
    target.wait_event("ready")
    with Agent("nu_probe", ros=ros, probe_s=PROBE_S, lease_s=LEASE_S) as probe:
        raw = probe.node.create_publisher(String, INBOX_PREFIX + "nu_target", inbox_qos(10))
        _wait(lambda: raw.get_subscription_count() > 0, "nu_target's inbox")
        valid = Message(performative=Performative.REQUEST, sender="nu_probe",
                        receivers=["nu_target"], conversation_id="nu/1",
                        protocol="fipa-request", content="hi")
        bad: dict[str, str] = {
            "nu/json": "{not json",
            "nu/field": json.dumps({"schema": "beehave.acl/1", "sender": "nu_probe",
                                    "conversation_id": "nu/field", "receivers": ["nu_target"],
                                    "performative": "shout"}),
            "nu/schema": valid.model_copy(update={"conversation_id": "nu/schema"})
            .to_json().replace("beehave.acl/1", "beehave.acl/0"),
            "nu/address": valid.model_copy(update={"conversation_id": "nu/address",
                                                   "receivers": ["somebody_else"]}).to_json(),
            "nu/list": "[1, 2, 3]",
        }
        for text in bad.values():
            raw.publish(String(data=text))
        answers: dict[str, Message] = {}
        while len(answers) < 3:
            message = probe.receive(timeout_s=WAIT_S)
            assert message.performative is Performative.NOT_UNDERSTOOD, message
            answers[message.conversation_id] = message
        assert set(answers) == {"nu/field", "nu/schema", "nu/address"}
        assert "performative" in answers["nu/field"].content["reason"]
        assert "unsupported schema" in answers["nu/schema"].content["reason"]
        assert "misaddressed" in answers["nu/address"].content["reason"]
        # Every bad message was reported on the target's event bus, the nameless ones too.
        _wait(lambda: sum(e["event"] == "rejected" for e in target.events) >= len(bad),
              "rejected events")
        # And it goes on answering.
        assert request(probe, "nu_target", "ok?", timeout_s=WAIT_S) == {"result": "ok?"}
        # Our own agent answers a not-understood to nothing (no ping-pong) and reports
        # a stranger's message it cannot read.
        events: list[Any] = []
        probe.events.subscribe(events.append)
        own = probe.node.create_publisher(String, INBOX_PREFIX + "nu_probe", inbox_qos(10))
        _wait(lambda: own.get_subscription_count() > 0, "own inbox")
        own.publish(String(data="garbage"))
        _wait(lambda: any(e.kind is EventKind.MESSAGE_REJECTED for e in events),
              "MESSAGE_REJECTED")
        with pytest.raises(NoReply):
            probe.receive(timeout_s=QUIET_S)


def test_a_rejected_message_is_logged_once_however_many_managers_listen(
        ros: RosContext, caplog: pytest.LogCaptureFixture) -> None:
    with Agent("once_agent", ros=ros, probe_s=PROBE_S) as agent, \
            HighLevelBehaviorManager(stop_timeout_s=5.0) as hl:
        agent.attach(hl)  # its own bus and the manager's: both get the event
        events: list[Any] = []
        hl.subscribe(events.append)
        inbox = agent.node.create_publisher(String, INBOX_PREFIX + "once_agent",
                                            inbox_qos(10))
        _wait(lambda: inbox.get_subscription_count() > 0, "inbox")
        with caplog.at_level(logging.WARNING):
            inbox.publish(String(data="garbage"))
            _wait(lambda: any(e.kind is EventKind.MESSAGE_REJECTED for e in events),
                  "MESSAGE_REJECTED on the manager's bus")
        lines = [r for r in caplog.records if "message_rejected agent:once_agent" in
                 r.getMessage()]
        assert len(lines) == 1, [r.getMessage() for r in lines]


def test_interrupted_receive_ends_the_behavior(ros: RosContext) -> None:
    class Listen(AgentBehavior):
        def run(self) -> None:
            self.agent.receive(timeout_s=math.inf)

    with Agent("wait_agent", ros=ros, probe_s=PROBE_S) as agent, \
            HighLevelBehaviorManager(stop_timeout_s=5.0) as hl:
        agent.attach(hl)
        hl.register("listen", Listen)
        listening = hl.switch("listen")
        hl.switch("idle")
        assert listening.status is Status.INTERRUPTED, listening.error
        assert isinstance(listening.error, Interrupted) or listening.error is None


def test_awaitable_api_for_logics(ros: RosContext) -> None:
    with Agent("async_a", ros=ros, probe_s=PROBE_S) as a, \
            Agent("async_b", ros=ros, probe_s=PROBE_S) as b:
        async def talk() -> Message:
            with a.conversation(protocol="chat") as conv:
                await a.asend(Message(performative=Performative.INFORM, sender="async_a",
                                      receivers=["async_b"],
                                      conversation_id=conv.conversation_id, content=1))
                got = await b.areceive(timeout_s=WAIT_S)
                b.reply(got, Performative.INFORM, got.content + 1)
                return await conv.areceive(timeout_s=WAIT_S)

        answer = asyncio.run(talk())
        assert (answer.sender, answer.content) == ("async_b", 2)

        async def nothing() -> None:
            await a.areceive(timeout_s=QUIET_S)

        with pytest.raises(NoReply):
            asyncio.run(nothing())

        async def bad(timeout: Any) -> None:
            await a.areceive(timeout_s=timeout)

        for wrong in (float("nan"), -1.0, "2", True):
            with pytest.raises(ConfigError, match="areceive"):
                asyncio.run(bad(wrong))
            with pytest.raises(ConfigError, match="receive"):
                a.receive(timeout_s=wrong)  # type: ignore[arg-type]


def test_unattached_manager_names_the_fix() -> None:
    class Ask(AgentBehavior):
        def run(self) -> None:
            self.agent.receive(timeout_s=0.1)

    with HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        hl.register("ask", Ask)
        asking = hl.switch("ask")
        asking.wait(WAIT_S)
        assert isinstance(asking.error, ConfigError)
        assert "agent.attach(manager)" in str(asking.error)


# ---------------------------------------------------------------------- protocols
def test_request_round_trip_as_a_behavior(ros: RosContext, procs: list[Proc]) -> None:
    target = _spawn(procs, "rq_target")
    target.wait_event("ready")
    with Agent("rq_asker", ros=ros, probe_s=PROBE_S) as asker, \
            HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        asker.attach(hl)
        _wait(lambda: asker.directory.alive("rq_target"), "rq_target")
        hl.register("ask", RequestInitiator, receiver="rq_target",
                    content={"bring": "steel"}, timeout_s=WAIT_S)
        asking = hl.switch("ask")
        assert asking.wait(WAIT_S)
        assert asking.status is Status.SUCCEEDED, asking.error
        assert asking.result == {"result": {"bring": "steel"}}
        # A refusal is a typed failure that carries the reply.
        with pytest.raises(ProtocolFailed, match="not-understood|refuse") as failed:
            request(asker, "rq_target", None, protocol="nobody-serves-this",
                    timeout_s=WAIT_S)
        assert isinstance(failed.value.reply, Message) or failed.value.reply is None


def _initiator(hl: HighLevelBehaviorManager, **params: Any) -> Behavior:
    hl.register("cnp", ContractNetInitiator, **params)
    return hl.switch("cnp")


def test_contract_net_awards_the_cheapest_and_re_awards_when_it_is_killed(
        ros: RosContext, procs: list[Proc]) -> None:
    # The cheapest would take long: it is killed mid-task, the next cheapest finishes.
    cheap = _spawn(procs, "cn_cheap", cost=1.0, task_s=60.0)
    middle = _spawn(procs, "cn_middle", cost=2.0, task_s=0.1)
    dear = _spawn(procs, "cn_dear", cost=3.0, task_s=0.1)
    for proc in (cheap, middle, dear):
        proc.wait_event("ready")
    with Agent("cn_machine", ros=ros, probe_s=PROBE_S, lease_s=LEASE_S) as machine, \
            HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        machine.attach(hl)
        _wait(lambda: len(machine.directory.search("transport")) == 3, "three transporters")
        running = _initiator(hl, service="transport", task={"to": "cn_machine"},
                             reply_by_s=WAIT_S, done_timeout_s=WAIT_S)
        cheap.wait_event("perform")
        cid = cheap.wait_event("got", performative="accept-proposal")["cid"]
        middle.wait_event("got", performative="reject-proposal", cid=cid)
        dear.wait_event("got", performative="reject-proposal", cid=cid)
        cheap.kill()
        assert running.wait(WAIT_S)
        assert running.status is Status.SUCCEEDED, running.error
        award = running.result
        assert isinstance(award, Award)
        assert award.awardee == "cn_middle"
        assert award.result == {"result": {"delivered": True}}
        assert [name for name, _ in award.attempts] == ["cn_cheap", "cn_middle"]
        assert "left the directory" in award.attempts[0][1]
        middle.wait_event("done", cid=cid)
        assert not dear.saw("perform")  # awarded at most once each, and only these two


def test_interrupted_initiator_cancels_and_leaves_no_award(
        ros: RosContext, procs: list[Proc]) -> None:
    quick = _spawn(procs, "ci_quick", cost=1.0, task_s=60.0)
    slow = _spawn(procs, "ci_slow", cost=0.5, propose_delay_s=60.0)
    for proc in (quick, slow):
        proc.wait_event("ready")
    with Agent("ci_machine", ros=ros, probe_s=PROBE_S, lease_s=LEASE_S) as machine, \
            HighLevelBehaviorManager(stop_timeout_s=2.0) as hl:
        machine.attach(hl)
        _wait(lambda: len(machine.directory.search("transport")) == 2, "two transporters")
        # 1. Switched away while proposals are awaited: the proposer that answered gets a
        #    reject-proposal, the one that has not gets a cancel.
        negotiating = _initiator(hl, service="transport", task={}, reply_by_s=WAIT_S,
                                 done_timeout_s=WAIT_S)
        cid = slow.wait_event("cfp")["cid"]
        quick.wait_event("cfp", cid=cid)
        hl.switch("idle")
        assert negotiating.status is Status.INTERRUPTED
        slow.wait_event("got", performative="cancel", cid=cid)
        # The quick proposal was either in (reject-proposal) or still on its way (cancel).
        _wait(lambda: quick.saw("got", performative="reject-proposal", cid=cid)
              or quick.saw("got", performative="cancel", cid=cid), "quick withdrawn")
        # 2. Switched away while the awardee works: it gets a cancel and stops.
        working = _initiator(hl, service="transport", task={}, reply_by_s=0.5,
                             done_timeout_s=WAIT_S)
        quick.wait_event("perform")
        cid2 = quick.wait_event("got", performative="accept-proposal")["cid"]
        hl.switch("idle")
        assert working.status is Status.INTERRUPTED
        quick.wait_event("got", performative="cancel", cid=cid2)
        quick.wait_event("interrupted", cid=cid2)
        assert not slow.saw("perform")
        assert not slow.saw("got", performative="accept-proposal")


# ---------------------------------------------------------------------- in one process
class Hold(Action):
    """Holds the "driving" lock until interrupted (or ``seconds``)."""

    action_type = "driving"
    ended: list[str] = []

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def run(self) -> str:
        finished = self.sleep(self.seconds)
        Hold.ended.append("done" if finished else "interrupted")
        return "held"


class Drive(RequestResponder):
    def perform(self, task: Message) -> Any:
        return Hold(float(task.content))


class Bidder(ContractNetResponder):
    service = "haul"

    def __init__(self, cost: float, seconds: float) -> None:
        self.price = cost
        self.seconds = seconds

    def propose(self, cfp: Message) -> Any:
        return {"cost": self.price}

    def perform(self, task: Message) -> Any:
        return Hold(self.seconds)


@pytest.fixture
def robots(ros: RosContext) -> Iterator[Callable[..., Agent]]:
    """Agents that each run one responder behaviour under their own manager."""
    opened: list[tuple[Agent, HighLevelBehaviorManager]] = []

    def make(name: str, behavior: type[Behavior], **params: Any) -> Agent:
        agent = Agent(name, ros=ros, lease_s=LEASE_S, probe_s=PROBE_S)
        hl = HighLevelBehaviorManager(stop_timeout_s=1.0)
        hl.start()
        opened.append((agent, hl))
        agent.attach(hl)
        hl.register("serve", behavior, **params)
        hl.switch("serve")
        return agent

    try:
        yield make
    finally:
        for agent, hl in opened:
            hl.shutdown()
            agent.close()


def test_tasks_run_as_actions_under_the_type_locks_and_cancel_interrupts_them(
        ros: RosContext, robots: Callable[..., Agent]) -> None:
    Hold.ended.clear()
    driver = robots("lock_driver", Drive)
    with Agent("lock_boss", ros=ros, probe_s=PROBE_S) as boss:
        _wait(lambda: boss.directory.alive("lock_driver"), "lock_driver")
        first: list[BaseException] = []

        def long_request() -> None:
            try:
                request(boss, "lock_driver", 60.0, timeout_s=3.0)
            except BaseException as exc:  # noqa: BLE001 - inspected below
                first.append(exc)

        asking = threading.Thread(target=long_request)
        asking.start()
        _wait(lambda: any(lock for lock in driver_locks(driver)), "the driving lock held")
        with pytest.raises(ProtocolFailed, match="driving") as busy:
            request(boss, "lock_driver", 0.0, timeout_s=WAIT_S)
        assert isinstance(busy.value.reply, Message)
        assert busy.value.reply.performative is Performative.FAILURE
        asking.join(WAIT_S)
        assert len(first) == 1 and isinstance(first[0], NoReply)  # then it sent cancel
        _wait(lambda: Hold.ended == ["interrupted"], "the cancelled action's end")


def driver_locks(agent: Agent) -> list[Any]:
    manager = next(m() for m in agent._managers)
    assert manager is not None
    return list(manager.snapshot()["locks"].values())


def test_a_silent_awardee_is_cancelled_and_the_task_re_awarded(
        ros: RosContext, robots: Callable[..., Agent]) -> None:
    Hold.ended.clear()
    robots("quiet_cheap", Bidder, cost=1.0, seconds=60.0)
    robots("quiet_dear", Bidder, cost=2.0, seconds=0.0)
    with Agent("quiet_boss", ros=ros, probe_s=PROBE_S) as boss:
        _wait(lambda: len(boss.directory.search("haul")) == 2, "two haulers")
        award = contract_net(boss, "haul", {}, reply_by_s=WAIT_S, done_timeout_s=SILENT_S)
        assert award.awardee == "quiet_dear"
        assert award.attempts[0] == ("quiet_cheap", f"failure: silent for {SILENT_S} s")
        assert award.result == {"result": "held"}
        _wait(lambda: sorted(Hold.ended) == ["done", "interrupted"], "both actions ended")


class InTurnBidder(ContractNetResponder):
    """Bids its base price plus 10 per task it already has (running or queued), and
    answers concurrent calls in turn (``answer_cfps_in_turn``; without it, this test
    fails: the cheap one wins both)."""

    service = "haul_in_turn"
    answer_cfps_in_turn = True

    def __init__(self, cost: float) -> None:
        self.price = cost

    def propose(self, cfp: Message) -> Any:
        # Pricing takes a while (a path planner): the other call is in the mailbox by then.
        self.sleep(0.3)
        return {"cost": self.price + 10 * (len(self.tasks) + len(self.waiting))}

    def perform(self, task: Message) -> Any:
        return Hold(1.0)


def test_two_calls_at_once_go_to_two_bidders_when_they_answer_in_turn(
        ros: RosContext, robots: Callable[..., Agent]) -> None:
    """Two initiators call at the same instant. Answering each call at once, the cheap
    bidder would offer its idle price to both and win both (the other stays idle); in
    turn, its second bid knows the first award and the dear one wins the second."""
    robots("turn_cheap", InTurnBidder, cost=1.0)
    robots("turn_dear", InTurnBidder, cost=2.0)
    with Agent("turn_boss_a", ros=ros, probe_s=PROBE_S) as a, \
            Agent("turn_boss_b", ros=ros, probe_s=PROBE_S) as b:
        for boss in (a, b):
            _wait(lambda boss=boss: len(boss.directory.search("haul_in_turn")) == 2,
                  "two bidders")
        start = threading.Barrier(2)
        awards: dict[str, Any] = {}

        def order(boss: Agent) -> None:
            start.wait(WAIT_S)
            try:
                awards[boss.name] = contract_net(boss, "haul_in_turn", {}, reply_by_s=WAIT_S)
            except BaseException as exc:  # noqa: BLE001 - inspected below
                awards[boss.name] = exc

        threads = [threading.Thread(target=order, args=(boss,)) for boss in (a, b)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(3 * WAIT_S)
        assert not any(t.is_alive() for t in threads)
        assert sorted(award.awardee for award in awards.values()) == ["turn_cheap",
                                                                      "turn_dear"], awards
        # Each at the first award (not the cheap one's "busy" failure, then a re-award),
        # and the dear one at its idle price: it was not asked to outbid a phantom.
        assert [len(award.attempts) for award in awards.values()] == [1, 1], awards
        costs = {award.awardee: award.cost for award in awards.values()}
        assert costs == {"turn_cheap": 1.0, "turn_dear": 2.0}, awards


def test_an_unreachable_candidate_does_not_stop_the_others(
        ros: RosContext, robots: Callable[..., Agent]) -> None:
    robots("reach_real", Bidder, cost=1.0, seconds=0.0)
    with Agent("reach_boss", ros=ros, probe_s=PROBE_S, send_timeout_s=0.3) as boss:
        _wait(lambda: boss.directory.alive("reach_real"), "reach_real")
        with pytest.raises(AgentUnreachable, match="reach_ghost") as missing:
            boss.send(Message(performative=Performative.INFORM, sender="reach_boss",
                              receivers=["reach_ghost"], conversation_id="reach/1"))
        assert missing.value.unreachable == ("reach_ghost",)
        award = contract_net(boss, "haul", {}, candidates=["reach_ghost", "reach_real"],
                             reply_by_s=WAIT_S)
        assert award.awardee == "reach_real"


class EchoLogic(Logic):
    """A Logic that answers every message of its agent's inbox (asyncio API)."""

    def __init__(self, talker: Agent) -> None:
        self.talker = talker

    async def run(self) -> None:
        while True:
            message = await self.talker.areceive(timeout_s=None)
            await self.talker.asend(message.reply(Performative.INFORM, message.content))


def test_a_logic_talks_with_the_awaitable_api(ros: RosContext) -> None:
    with Agent("logic_echo", ros=ros, probe_s=PROBE_S) as echo, \
            Agent("logic_asker", ros=ros, probe_s=PROBE_S) as asker, \
            LowLevelBehaviorManager(stop_timeout_s=0.5) as ll:
        ll.register("echo", EchoLogic, talker=echo)
        ll.switch("echo")
        with asker.conversation() as conv:
            conv.send(Performative.REQUEST, ["logic_echo"], {"n": 7})
            answer = conv.receive(timeout_s=WAIT_S)
        assert (answer.performative, answer.content) == (Performative.INFORM, {"n": 7})


class AskLogic(Logic):
    """A Logic that runs a FIPA request with the awaitable initiator; its result is the
    inform's content, its error what arequest raised."""

    def __init__(self, talker: Agent, receiver: str, content: Any = None,
                 protocol: str = REQUEST) -> None:
        self.talker, self.receiver, self.content = talker, receiver, content
        self.protocol = protocol

    async def run(self) -> Any:
        return await arequest(self.talker, self.receiver, self.content,
                              protocol=self.protocol, timeout_s=WAIT_S)


def _ended(logic: Logic | None) -> Logic:
    assert logic is not None
    _wait(lambda: logic.status is not Status.RUNNING, f"{logic.path} to end")
    return logic


def test_a_logic_runs_a_fipa_request_and_cancels_it_when_switched_away(
        ros: RosContext, procs: list[Proc]) -> None:
    target = _spawn(procs, "arq_target")
    target.wait_event("ready")
    with Agent("arq_asker", ros=ros, probe_s=PROBE_S) as asker, \
            Agent("arq_silent", ros=ros, probe_s=PROBE_S) as silent, \
            silent.mailbox(protocols=[REQUEST]) as held, \
            LowLevelBehaviorManager(stop_timeout_s=0.5) as ll:
        _wait(lambda: asker.directory.alive("arq_target"), "arq_target")
        ll.register("ask", AskLogic, talker=asker, receiver="arq_target",
                    content={"bring": "steel"})
        ll.register("refused", AskLogic, talker=asker, receiver="arq_target",
                    protocol="nobody-serves-this")
        ll.register("hold", AskLogic, talker=asker, receiver="arq_silent", content="wait")
        # Across processes: agree, then the inform's content.
        asked = _ended(ll.switch("ask"))
        assert asked.status is Status.SUCCEEDED, asked.error
        assert asked.result == {"result": {"bring": "steel"}}
        assert target.saw("got", performative="request", sender="arq_asker")
        # A refusal (not-understood: nobody serves that protocol) is a typed failure.
        refused = _ended(ll.switch("refused"))
        assert isinstance(refused.error, ProtocolFailed), refused.error
        assert refused.error.reply is not None
        assert refused.error.reply.performative is Performative.NOT_UNDERSTOOD
        # Switched away while it waits: the receiver gets a cancel of that conversation.
        holding = ll.switch("hold")
        asked_to_hold = held.receive(timeout_s=WAIT_S)
        assert (asked_to_hold.performative, asked_to_hold.content) == \
            (Performative.REQUEST, "wait")
        ll.switch("ask")  # switching returns once the old logic has ended
        assert holding is not None and holding.status is Status.INTERRUPTED
        cancel = held.receive(timeout_s=WAIT_S)
        assert cancel.performative is Performative.CANCEL
        assert cancel.conversation_id == asked_to_hold.conversation_id


class QueuedBidder(Bidder):
    """A hauler that accepts work while it works: awarded tasks wait for the lock."""

    queue_tasks = True


def test_queued_tasks_wait_for_their_type_and_run_in_order(
        ros: RosContext, robots: Callable[..., Agent]) -> None:
    Hold.ended.clear()
    robots("queue_hauler", QueuedBidder, cost=1.0, seconds=0.3)
    with Agent("queue_boss", ros=ros, probe_s=PROBE_S) as boss:
        _wait(lambda: boss.directory.alive("queue_hauler"), "queue_hauler")
        steps: list[tuple[str, dict[str, Any]]] = []
        awards: list[Any] = []

        def order(i: int) -> None:
            awards.append(contract_net(
                boss, "haul", {"n": i}, reply_by_s=WAIT_S, done_timeout_s=WAIT_S,
                observer=lambda step, detail: steps.append((step, detail))))

        threads = [threading.Thread(target=order, args=(i,)) for i in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(3 * WAIT_S)
        # Without the queue, the 2nd and 3rd awards fail ("driving" is busy) and, with
        # nobody else to ask, raise ProtocolFailed.
        assert len(awards) == 3 and all(a.awardee == "queue_hauler" for a in awards)
        assert Hold.ended == ["done", "done", "done"]
        assert all(a.attempts == [("queue_hauler", "inform")] for a in awards)
    kinds = [s for s, _ in steps]
    assert kinds.count("cfp") == kinds.count("awarded") == kinds.count("done") == 3
    assert all("conversation_id" in d for _, d in steps)
    assert all(d["awardee"] == "queue_hauler" and d["attempt"] == 1
               for s, d in steps if s == "awarded")


def test_an_observer_sees_the_re_award_and_cannot_break_the_protocol(
        ros: RosContext, robots: Callable[..., Agent]) -> None:
    Hold.ended.clear()
    robots("obs_cheap", Bidder, cost=1.0, seconds=60.0)
    robots("obs_dear", Bidder, cost=2.0, seconds=0.0)
    with Agent("obs_boss", ros=ros, probe_s=PROBE_S) as boss:
        _wait(lambda: len(boss.directory.search("haul")) == 2, "two haulers")
        steps: list[str] = []

        def observer(step: str, detail: dict[str, Any]) -> None:
            steps.append(f"{step}:{detail.get('awardee', '')}")
            raise RuntimeError("a broken observer")  # logged, never disturbs the protocol

        award = contract_net(boss, "haul", {}, reply_by_s=WAIT_S, done_timeout_s=SILENT_S,
                             observer=observer)
        assert award.awardee == "obs_dear"
    assert steps == ["cfp:", "awarded:obs_cheap", "failed:obs_cheap", "awarded:obs_dear",
                     "done:obs_dear"]


def test_a_stalled_observer_does_not_expire_the_leases_of_live_agents(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A process that did not run for longer than a lease (a loaded host) must not read
    every peer as dead: their announcements may wait in its queue behind the check."""
    from beehave.agents import directory as d

    clock = [1000.0]
    monkeypatch.setattr(d.time, "monotonic", lambda: clock[0])  # type: ignore[attr-defined]
    view = d.Directory("observer")
    departed: list[str] = []
    view._on_departure(lambda name, reason: departed.append(f"{name}: {reason}"))
    entry = {"schema": d.DIRECTORY_SCHEMA, "agent": "peer", "incarnation": "i1",
             "started_at": 1.0, "state": "alive", "lease_s": 2.0, "services": {}}
    view._receive(json.dumps(entry))
    view._expire()
    clock[0] += 5.0  # the observer stalled 5 s: more than the lease
    view._expire()
    assert view.get("peer") is not None and departed == []
    view._receive(json.dumps(entry))  # the queued announcement arrives
    for _ in range(25):  # then the peer really falls silent: 2.5 s of regular checks
        clock[0] += d.EXPIRY_CHECK_S
        view._expire()
    assert view.get("peer") is None and departed == ["peer: lease expired"]


def test_a_directory_that_reads_behind_does_not_expire_the_leases_of_live_agents(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Its checks run on time, but its own entry has not come back for 5 s: the topic's
    messages wait in this process (its executor behind on a loaded host), a peer's among
    them. The peer stays (seen: a machine dropped a live ATV with a killed one, failing
    the order instead of re-awarding it); once the own entry comes back and the peer has
    really gone silent, it expires after its lease."""
    from beehave.agents import directory as d

    clock = [1000.0]
    monkeypatch.setattr(d.time, "monotonic", lambda: clock[0])  # type: ignore[attr-defined]
    view = d.Directory("machine")

    def entry(name: str, incarnation: str) -> str:
        return json.dumps({"schema": d.DIRECTORY_SCHEMA, "agent": name,
                           "incarnation": incarnation, "started_at": 1.0, "state": "alive",
                           "lease_s": 2.0, "services": {}})

    own = entry("machine", "m1")
    view._set_own(d.Announcement.model_validate_json(own))
    departed: list[str] = []
    view._on_departure(lambda name, reason: departed.append(f"{name}: {reason}"))
    view._receive(own)
    view._receive(entry("atv", "a1"))

    def checks(seconds: float, *, own_back: bool) -> None:
        for step in range(round(seconds / d.EXPIRY_CHECK_S)):
            clock[0] += d.EXPIRY_CHECK_S
            if own_back and step % 5 == 4:  # every 0.5 s, lease / 4
                view._receive(own)
            view._expire()

    checks(5.0, own_back=False)  # regular checks; nothing read for 5 s
    assert view.get("atv") is not None and departed == []
    view._receive(own)  # the queue is read: our own entry, the peer's...
    view._receive(entry("atv", "a1"))
    checks(1.5, own_back=True)
    assert view.get("atv") is not None
    checks(1.0, own_back=True)  # the peer silent past its 2 s lease, we read on time
    assert view.get("atv") is None and departed == ["atv: lease expired"]


def test_every_sent_message_is_copied_to_the_messages_topic_for_listeners(
        ros: RosContext) -> None:
    """The sniffer topic: a listener gets each message as sent (same JSON), and its reader
    does not make an absent agent's inbox look present."""
    from std_msgs.msg import String

    from beehave.agents.agent import MESSAGES_QOS, MESSAGES_TOPIC
    from beehave.errors import AgentUnreachable

    heard: list[Message] = []
    cond = threading.Condition()

    def on_copy(msg: String) -> None:
        with cond:
            heard.append(Message.from_json(msg.data))
            cond.notify_all()

    listener = ros.create_node("messages_listener")
    listener.create_subscription(String, MESSAGES_TOPIC, on_copy, MESSAGES_QOS)
    with Agent("sniffed_a", ros=ros, probe_s=PROBE_S) as a, \
            Agent("sniffed_b", ros=ros, probe_s=PROBE_S) as b:
        _wait(lambda: a._copies.get_subscription_count() > 0, "the listener to match")
        sent = a.send(Message(performative=Performative.REQUEST, sender="sniffed_a",
                              receivers=["sniffed_b"], conversation_id="c1", content={"n": 1}))
        got = b.receive(timeout_s=WAIT_S)
        with cond:
            assert cond.wait_for(lambda: len(heard) >= 1, WAIT_S)
        assert heard[0] == sent == got
        with pytest.raises(AgentUnreachable, match="nobody_here"):
            a.send(Message(performative=Performative.INFORM, sender="sniffed_a",
                           receivers=["nobody_here"], conversation_id="c2"), timeout_s=0.3)
