"""The wire protocol as docs/agents.md specifies it, driven by an outside agent in plain
rclpy + std_msgs (``tests/outside_agent.py``) against beehave agents in open mode: what
beehave sends matches the JSON Schemas shipped in ``beehave/agents/schemas/``, a message
that lacks a required field is refused with a not-understood naming it, and a cfp the
responder cannot serve is answered with ``refuse`` and a reason."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")
jsonschema = pytest.importorskip("jsonschema")

from outside_agent import Outsider  # noqa: E402

from beehave import HighLevelBehaviorManager  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402

SCHEMAS = Path(__file__).resolve().parents[1] / "beehave" / "agents" / "schemas"
WAIT_S = WALL_TIMEOUT_S


def _schema(name: str) -> dict[str, Any]:
    schema: dict[str, Any] = json.loads((SCHEMAS / f"{name}.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    return schema


@pytest.fixture
def outsider() -> Iterator[Outsider]:
    ext = Outsider("wire_ext", wait_s=WAIT_S)
    try:
        yield ext
    finally:
        ext.close()


def _responder(name: str) -> Any:
    """A beehave agent whose contract-net responder serves ``transport`` to known machines
    only (an unknown one raises in ``propose``, as the fleet's ATV does)."""
    from beehave.agents import Agent, Message
    from beehave.agents.protocols import ContractNetResponder, RequestResponder

    class Transport(ContractNetResponder):
        service = "transport"

        def propose(self, cfp: Message) -> Any:
            machine = cfp.content["to"]
            if machine not in ("m1", "m2"):
                raise KeyError(f"unknown machine {machine!r}")
            return {"cost": 1.0, "to": machine}

        def perform(self, task: Message) -> Any:
            return {"delivered": task.content["to"]}

    class Echo(RequestResponder):
        def perform(self, task: Message) -> Any:
            return task.content

    agent = Agent(name, probe_s=0.3, lease_s=1.0)
    hl = HighLevelBehaviorManager(stop_timeout_s=0.5)
    hl.node = agent.node
    agent.attach(hl)
    hl.start()
    hl.register("transport", Transport)
    hl.switch("transport")
    hl.register("echo", Echo)
    return agent, hl, Echo


def test_what_beehave_sends_matches_the_shipped_schemas_and_cfps_it_cannot_serve_are_refused(
        outsider: Outsider) -> None:
    acl, directory = _schema("acl"), _schema("directory")
    agent, hl, _ = _responder("wire_atv")
    try:
        assert wait_until(lambda: agent.directory.search("transport") != [], WAIT_S)
        good = outsider.send(outsider.message("cfp", "wire_atv", {"to": "m1"},
                                              protocol="fipa-contract-net"))
        proposal = outsider.wait("inbox", WAIT_S, performative="propose",
                                 in_reply_to=good["message_id"])
        assert proposal["content"] == {"cost": 1.0, "to": "m1"}
        accept = outsider.reply(proposal, "accept-proposal", proposal["content"])
        # A done report of a task: inform, its content {"result": <what perform returned>}.
        done = outsider.wait("inbox", WAIT_S, performative="inform",
                             in_reply_to=accept["message_id"])
        assert done["content"] == {"result": {"delivered": "m1"}}
        # A cfp it cannot serve: refuse, with the reason (not failure).
        bad = outsider.send(outsider.message("cfp", "wire_atv", {"to": "nowhere"},
                                             protocol="fipa-contract-net"))
        refusal = outsider.wait("inbox", WAIT_S, in_reply_to=bad["message_id"])
        assert refusal["performative"] == "refuse"
        assert "unknown machine 'nowhere'" in refusal["content"]["reason"]
        for message in (proposal, done, refusal):
            jsonschema.validate(message, acl)
        assert wait_until(lambda: any(e.get("agent") == "wire_atv" for e in outsider.entries),
                          WAIT_S)
        with outsider.cond:
            entries = [e for e in outsider.entries if e.get("agent") == "wire_atv"]
        for entry in entries:
            jsonschema.validate(entry, directory)
    finally:
        hl.shutdown()
        agent.close()


@pytest.mark.parametrize(("performative", "drop"), [("request", "message_id"),
                                                    ("cfp", "content"),
                                                    ("request", "sent_at")])
def test_a_message_without_a_required_field_gets_a_not_understood_naming_it(
        outsider: Outsider, performative: str, drop: str) -> None:
    agent, hl, echo = _responder("wire_rq")
    try:
        hl.switch("echo")
        assert wait_until(lambda: "transport" not in agent.services, WAIT_S)
        protocol = "fipa-request" if performative == "request" else "fipa-contract-net"
        if performative == "cfp":
            hl.switch("transport")
            assert wait_until(lambda: "transport" in agent.services, WAIT_S)
        message = outsider.message(performative, "wire_rq", {"to": "m1"}, protocol=protocol)
        del message[drop]
        outsider.send(message)
        answer = outsider.wait("inbox", WAIT_S, conversation_id=message["conversation_id"])
        assert answer["performative"] == "not-understood", answer
        assert f"missing field: {drop}" in answer["content"]["reason"]
        # Nobody invents the id the sender never used.
        assert answer["in_reply_to"] == message.get("message_id")
    finally:
        hl.shutdown()
        agent.close()
