"""A responder's open proposals (contract net, auctions): kept in the order they were
made, expired from the oldest, and never walked in full on every cfp."""

from __future__ import annotations

import pytest

from beehave.agents import Message, Performative
from beehave.agents import protocols as protocols_module
from beehave.agents.protocols import ContractNetResponder


def _cfp(cid: str) -> Message:
    return Message(performative=Performative.CFP, sender="boss", receivers=["me"],
                   conversation_id=cid, content={})


def test_expired_proposals_go_oldest_first_and_a_new_proposal_is_the_newest(
        monkeypatch: pytest.MonkeyPatch) -> None:
    clock = [100.0]
    monkeypatch.setattr(protocols_module.time, "monotonic", lambda: clock[0])
    responder = ContractNetResponder()
    responder.proposal_valid_s = 10.0
    responder.proposals = {}
    for cid, at in (("a", 100.0), ("b", 101.0), ("a", 102.0)):  # a proposes again
        clock[0] = at
        responder._propose(cid, _cfp(cid))
    assert list(responder.proposals) == ["b", "a"]
    clock[0] = 111.5  # b (101) is older than 10 s, a (102) is not
    responder._expire_proposals()
    assert list(responder.proposals) == ["a"]
    clock[0] = 112.5
    responder._expire_proposals()
    assert responder.proposals == {}
