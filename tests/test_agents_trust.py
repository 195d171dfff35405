"""Signed agents, tested from the specification (docs/agents.md, "Trust model" and "The
wire"): an outside agent in plain rclpy + std_msgs + ``cryptography``
(``tests/outside_agent.py``) signs with keys that ``beehave keys`` made and talks with
beehave agents in ``signed`` mode; what is unsigned, signed by a stranger, signed with
another name's key, altered or replayed is refused with a not-understood naming the reason,
a WARNING, and a copy on ``/beehave/agents/messages``.

The beehave side runs in this process (its log is caplog) and as agent processes
(``tests/agents_node.py``, the fleet's charging station), killed by PID in a ``finally``.
"""

from __future__ import annotations

import base64
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("cryptography")
jsonschema = pytest.importorskip("jsonschema")

from agent_procs import AgentProc, stop_all  # noqa: E402
from cryptography.hazmat.primitives import serialization  # noqa: E402
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey  # noqa: E402
from outside_agent import Outsider, canonical, verify  # noqa: E402

from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCHEMAS = ROOT / "beehave" / "agents" / "schemas"
NODE = Path(__file__).with_name("agents_node.py")
WAIT_S = WALL_TIMEOUT_S


def _keys(folder: Path, *names: str) -> Path:
    """``beehave keys init`` and ``beehave keys issue NAME`` (the command's own ``main``:
    a process each would cost seconds of imports; the first test runs the real command)."""
    from beehave.cli import main

    assert main(["keys", "init", "--dir", str(folder)]) == 0
    for name in names:
        assert main(["keys", "issue", name, "--dir", str(folder)]) == 0
    return folder


def _cli(*args: str, code: int = 0) -> subprocess.CompletedProcess[str]:
    done = subprocess.run([sys.executable, "-m", "beehave.cli", *args], capture_output=True,
                          text=True, cwd=ROOT, timeout=WAIT_S)
    assert done.returncode == code, (args, done.returncode, done.stdout, done.stderr)
    return done


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _keys(tmp_path_factory.mktemp("keys"), "tr_boss", "tr_worker", "ext_a", "ext_c",
                 "tr_holder", "tr_station", "tr_seeker", "tr_robot",
                 "tr_mboss", "tr_broker", "keeper_shelf_aisle")


@pytest.fixture(scope="module")
def strangers(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Another fleet's authority, which issued a certificate for ext_a's name."""
    return _keys(tmp_path_factory.mktemp("strangers"), "ext_a", "tr_holder")


@pytest.fixture
def outsiders() -> Iterator[list[Outsider]]:
    made: list[Outsider] = []
    try:
        yield made
    finally:
        for outsider in made:
            outsider.close()


@pytest.fixture
def procs() -> Iterator[list[AgentProc]]:
    started: list[AgentProc] = []
    try:
        yield started
    finally:
        stop_all(started)


def _signed_agent(name: str, keys: Path, **options: Any) -> Any:
    from beehave.agents import Agent
    from beehave.agents.trust import Trust

    return Agent(name, trust=Trust.load(name, mode="signed", keys_dir=keys), probe_s=0.3,
                 lease_s=1.0, **options)


def _refusals(outsider: Outsider, since: int = 0) -> list[dict[str, Any]]:
    with outsider.cond:
        return [m for m in outsider.inbox[since:] if m["performative"] == "not-understood"]


def _saw(proc: AgentProc, kind: str) -> bool:
    with proc.cond:
        return any(e["event"] == kind for e in proc.events)


# ---------------------------------------------------------------------- keys
def test_beehave_keys_writes_a_certificate_an_outsider_can_check(tmp_path: Path) -> None:
    folder = tmp_path / "k"
    _cli("keys", "init", "--dir", str(folder))
    _cli("keys", "issue", "atv_7", "--dir", str(folder))
    cert = json.loads((folder / "atv_7.cert").read_text())
    jsonschema.validate(cert, json.loads((SCHEMAS / "cert.schema.json").read_text()))
    assert cert["agent"] == "atv_7"
    fleet = serialization.load_pem_public_key((folder / "fleet.pub").read_bytes())
    assert isinstance(fleet, Ed25519PublicKey)
    raw = fleet.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    import hashlib

    assert cert["fleet"] == hashlib.sha256(raw).hexdigest()[:16]
    body = {k: v for k, v in cert.items() if k != "signature"}
    fleet.verify(base64.b64decode(cert["signature"]), canonical(body))  # raises if wrong
    key = serialization.load_pem_private_key((folder / "atv_7.key").read_bytes(), None)
    assert base64.b64decode(cert["public_key"]) == key.public_key().public_bytes(
        serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    assert (folder / "fleet.key").stat().st_mode & 0o077 == 0  # private keys: owner only
    assert (folder / "atv_7.key").stat().st_mode & 0o077 == 0
    # A second init would void every certificate: refused unless --force.
    again = _cli("keys", "init", "--dir", str(folder), code=2)
    assert "exists" in again.stderr and "--force" in again.stderr
    bad = _cli("keys", "issue", "no spaces", "--dir", str(folder), code=2)
    assert "not valid" in bad.stderr


# ---------------------------------------------------------------------- an outsider joins
def test_a_signed_outsider_bids_in_a_signed_contract_net_and_is_awarded(
        keys: Path, outsiders: list[Outsider]) -> None:
    from beehave.agents.protocols import contract_net

    ext = Outsider("ext_a", keys=keys, services={"transport": {"kind": "outside"}},
                   wait_s=WAIT_S)
    outsiders.append(ext)
    fleet_pub = (keys / "fleet.pub").read_bytes()
    with _signed_agent("tr_boss", keys) as boss:
        assert wait_until(lambda: boss.directory.alive("ext_a"), WAIT_S), \
            "the signed outsider's directory entry was not taken"
        result: dict[str, Any] = {}

        def answer() -> None:
            cfp = ext.wait("inbox", WAIT_S, performative="cfp")
            assert verify(cfp, fleet_pub) == "tr_boss"  # signed by the fleet's tr_boss
            jsonschema.validate(cfp, json.loads((SCHEMAS / "acl.schema.json").read_text()))
            ext.reply(cfp, "propose", {"cost": 1.0, "to": cfp["content"]["to"]})
            accept = ext.wait("inbox", WAIT_S, performative="accept-proposal")
            assert verify(accept, fleet_pub) == "tr_boss"
            result["accept"] = accept
            ext.reply(accept, "inform", {"result": {"delivered": accept["content"]["to"]}})

        thread = threading.Thread(target=answer)
        thread.start()
        award = contract_net(boss, "transport", {"to": "machine_3"}, reply_by_s=WAIT_S / 4,
                             done_timeout_s=WAIT_S)
        thread.join(WAIT_S)
        assert award.awardee == "ext_a"
        assert award.result == {"result": {"delivered": "machine_3"}}
        assert result["accept"]["content"] == {"cost": 1.0, "to": "machine_3"}


@pytest.mark.parametrize("how", ["unsigned", "stranger", "other_name", "altered", "stale",
                                 "expired"])
def test_an_outsider_without_the_fleets_key_is_refused_visibly(
        how: str, keys: Path, strangers: Path, outsiders: list[Outsider],
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="beehave.agents")
    folder = {"unsigned": None, "stranger": strangers}.get(how, keys)
    sign_as = {"other_name": "ext_c", "expired": "ext_old"}.get(how)
    if how == "expired":  # a certificate that ran out a moment after it was issued
        from beehave.agents.trust import issue

        issue(keys, "ext_old", days=1e-6)
    ext = Outsider("ext_a", keys=folder, sign_as=sign_as, services={"transport": {}},
                   wait_s=WAIT_S)
    outsiders.append(ext)
    reasons = {"unsigned": "unsigned message", "stranger": "not by this fleet's authority",
               "other_name": "signed with the key certified for 'ext_c'",
               "altered": "bad signature", "stale": "stale message from 'ext_a'",
               "expired": "certificate of 'ext_old' expired"}
    def forge() -> dict[str, Any]:
        message = ext.message("request", "tr_worker", {"do": "it"}, protocol="fipa-request",
                              sent_at=time.time() - 120 if how == "stale" else None)
        if how == "altered":  # signed, then changed on the way
            message = {**message, "content": {"do": "something else"}}
        return message

    with _signed_agent("tr_worker", keys) as worker:
        box = worker.mailbox(protocols=["fipa-request"])
        message = forge()
        ext.send(message)
        refusal = ext.wait("inbox", WAIT_S, performative="not-understood",
                           in_reply_to=message["message_id"])
        assert reasons[how] in refusal["content"]["reason"]
        assert refusal["sender"] == "tr_worker"
        assert refusal["conversation_id"] != message["conversation_id"]  # its own one
        # The refusal is on the sniffer topic for anyone to see, and in the log.
        copy = _refusal_copy(ext, forge, sent=[message["message_id"]])
        assert reasons[how] in copy["content"]["reason"]
        assert any(r.levelno == logging.WARNING and "refused request from 'ext_a'" in
                   r.getMessage() and reasons[how] in r.getMessage() for r in caplog.records)
        assert len(box) == 0  # nothing reached the responder side
        # Its directory entry is refused too (never found by search), with a WARNING.
        if how in ("unsigned", "stranger", "other_name"):
            assert wait_until(lambda: any("refused the directory entry of 'ext_a'"
                                          in r.getMessage() for r in caplog.records), WAIT_S)
            assert not worker.directory.alive("ext_a")


# ---------------------------------------------------------------------- spoofing and replay


def _refusal_copy(spoof: Outsider, forge: Callable[[], dict[str, Any]], *,
                  sent: list[str] | None = None) -> dict[str, Any]:
    """The copy of a refusal of one of ``sent`` (message ids) or of further forged
    messages, which are sent until one reaches ``spoof`` on /beehave/agents/messages
    (volatile: a copy sent before the agent's publisher has matched the outsider's new
    subscription is not delivered to it; under load that takes a while)."""
    sent = list(sent or [])
    deadline = time.monotonic() + WAIT_S

    def found() -> dict[str, Any] | None:
        return next((m for m in spoof.copies if m.get("performative") == "not-understood"
                     and m.get("in_reply_to") in sent), None)

    while True:
        with spoof.cond:
            hit = found()
        if hit is not None:
            return hit
        forged = forge()
        sent.append(forged["message_id"])
        spoof.send(forged)
        with spoof.cond:
            spoof.cond.wait_for(lambda: found() is not None,
                                max(0.0, min(3.0, deadline - time.monotonic())))
            hit = found()
        if hit is not None:
            return hit
        assert time.monotonic() < deadline, \
            f"{spoof.name}: no refusal of {sent} on the copies within {WAIT_S} s"


@pytest.mark.parametrize("place", ["station", "zone_keeper"])
def test_a_signed_station_or_zone_keeper_refuses_a_spoofed_release(
        place: str, keys: Path, strangers: Path, outsiders: list[Outsider],
        procs: list[AgentProc], monkeypatch: pytest.MonkeyPatch) -> None:
    """The factory's charging station (keys by --mode/--keys) and the serve scenario's
    aisle keeper (keys by BEEHAVE_AGENT_MODE/KEYS): leased reservations by request."""
    from beehave.agents.protocols import request

    if place == "station":
        name, protocol = "tr_station", "charging"
        args = ["-m", "behaviours.fleet.station", name, "--station", "charger1",
                "--lease-s", "1.0", "--mode", "signed", "--keys", str(keys)]
    else:
        name, protocol = "keeper_shelf_aisle", "zone"
        args = ["-m", "behaviours.market.serving", "shelf_aisle", "--world", "serve",
                "--lease-s", "1.0"]
        monkeypatch.setenv("BEEHAVE_AGENT_MODE", "signed")
        monkeypatch.setenv("BEEHAVE_AGENT_KEYS", str(keys))
    keeper = AgentProc(name, [sys.executable, *args], wait_s=WAIT_S)
    procs.append(keeper)
    keeper.wait_event("ready")
    with _signed_agent("tr_holder", keys) as holder:
        assert wait_until(lambda: holder.directory.alive(name), WAIT_S)
        granted = request(holder, name, {"op": "reserve", "lease_s": 30},
                          protocol=protocol, timeout_s=WAIT_S)
        assert granted["result"]["holder"] == "tr_holder"
        # A participant of the domain writes release as tr_holder: unsigned, and signed
        # with a key another fleet issued for that name.
        for i, folder in enumerate((None, strangers)):
            spoof = Outsider(f"ext_spoof{i}", keys=folder,
                             sign_as="tr_holder" if folder else None, wait_s=WAIT_S)
            outsiders.append(spoof)
            copy = _refusal_copy(spoof, lambda spoof=spoof: spoof.message(
                "request", name, {"op": "release"}, protocol=protocol, sender="tr_holder"))
            assert "refused" in copy["content"]["reason"]
            assert copy["receivers"] == ["tr_holder"]
        assert not _saw(keeper, "released")
        # The holder still holds: its renew is granted.
        renewed = request(holder, name, {"op": "renew", "lease_s": 30},
                          protocol=protocol, timeout_s=WAIT_S)
        assert renewed["result"]["holder"] == "tr_holder"


def test_a_spoofed_award_and_a_replayed_accept_are_refused(
        keys: Path, outsiders: list[Outsider], procs: list[AgentProc],
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BEEHAVE_AGENT_MODE", "signed")
    monkeypatch.setenv("BEEHAVE_AGENT_KEYS", str(keys))
    worker = AgentProc("tr_worker", [sys.executable, str(NODE), "tr_worker", "--lease-s",
                                     "1.0"], wait_s=WAIT_S)
    procs.append(worker)
    worker.wait_event("ready")
    boss = Outsider("ext_a", keys=keys, wait_s=WAIT_S)
    outsiders.append(boss)
    cfp = boss.send(boss.message("cfp", "tr_worker", {"to": "m1"},
                                 protocol="fipa-contract-net", reply_by=None))
    proposal = boss.wait("inbox", WAIT_S, performative="propose",
                         conversation_id=cfp["conversation_id"])
    # A spoofed award: accept-proposal as ext_a, signed with ext_c's key.
    thief = Outsider("ext_c", keys=keys, wait_s=WAIT_S)
    outsiders.append(thief)
    forged = thief.message("accept-proposal", "tr_worker", proposal["content"],
                           conversation_id=cfp["conversation_id"],
                           protocol="fipa-contract-net", sender="ext_a",
                           in_reply_to=proposal["message_id"])
    thief.send(forged)
    refusal = boss.wait("inbox", WAIT_S, performative="not-understood",
                        in_reply_to=forged["message_id"])
    assert "signed with the key certified for 'ext_c'" in refusal["content"]["reason"]
    # The real award is taken and performed once; its replay is refused.
    accept = boss.reply(proposal, "accept-proposal", proposal["content"])
    boss.wait("inbox", WAIT_S, performative="inform", conversation_id=cfp["conversation_id"])
    boss.send_text("tr_worker", json.dumps(accept))
    replay = boss.wait("inbox", WAIT_S, performative="not-understood",
                       in_reply_to=accept["message_id"])
    assert "replayed" in replay["content"]["reason"]
    with worker.cond:
        performed = [e for e in worker.events if e["event"] == "perform"]
    assert len(performed) == 1
    assert _saw(worker, "rejected")


# ---------------------------------------------------------------------- the robot YAML
def test_a_robot_yaml_names_its_keys_and_runs_a_signed_agent(keys: Path,
                                                             tmp_path: Path) -> None:
    import shutil

    from beehave.config import parse_config
    from beehave.errors import ConfigError
    from beehave.robot import Robot

    folder = tmp_path / "keys"
    folder.mkdir()
    for name in ("fleet.pub", "tr_robot.key", "tr_robot.cert"):
        shutil.copy(keys / name, folder / name)
    yaml_file = tmp_path / "robot.yaml"
    section = {"name": "tr_robot", "lease_s": 1.0, "mode": "signed", "keys": "keys"}
    config = parse_config({"namespace": "tr_robot", "stop_timeout_s": 0.5,
                           "agent": section}, source=str(yaml_file))
    with _signed_agent("tr_seeker", keys) as seeker, Robot(config) as robot:
        assert robot.agent is not None and robot.agent.trust.verifying
        assert wait_until(lambda: seeker.directory.alive("tr_robot"), WAIT_S), \
            "the robot's signed entry was not taken"
    (folder / "tr_robot.key").unlink()
    with pytest.raises(ConfigError, match=r"robot.yaml: agent: cannot read the private key "
                                          r".*tr_robot.key"):
        with Robot(config):
            pass


# ---------------------------------------------------------------------- modes
def test_open_mode_says_so_once_per_process_and_a_bad_mode_is_named(
        monkeypatch: pytest.MonkeyPatch, keys: Path) -> None:
    script = ("import logging\n"
              "logging.basicConfig(format='%(levelname)s %(name)s %(message)s')\n"
              "from beehave.agents import Agent\n"
              "with Agent('tr_open_a', probe_s=0.2), Agent('tr_open_b', probe_s=0.2):\n"
              "    pass\n")
    env = {k: v for k, v in os.environ.items()
           if k not in ("BEEHAVE_AGENT_MODE", "BEEHAVE_AGENT_KEYS")}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=ROOT, env=env, timeout=WAIT_S)
    assert done.returncode == 0, done.stderr
    assert done.stderr.count("agents run in OPEN mode") == 1, done.stderr
    assert "WARNING beehave.agents.agent agents run in OPEN mode" in done.stderr
    from beehave.agents.trust import Trust
    from beehave.errors import ConfigError

    monkeypatch.setenv("BEEHAVE_AGENT_MODE", "paranoid")
    with pytest.raises(ConfigError, match=r"BEEHAVE_AGENT_MODE='paranoid' is not one of "
                                          r"\['open', 'signed'\]"):
        Trust.from_env("tr_x")
    monkeypatch.setenv("BEEHAVE_AGENT_MODE", "signed")
    with pytest.raises(ConfigError, match="signed mode needs the fleet's public key"):
        Trust.from_env("tr_x")
    # A key that is not the certificate's is refused at start, naming the problem.
    with pytest.raises(ConfigError, match="the key does not belong to the certificate"):
        Trust.load("tr_boss", keys_dir=keys, key=keys / "tr_worker.key")
    with pytest.raises(ConfigError, match="the certificate is for 'tr_worker'"):
        Trust.load("tr_boss", keys_dir=keys, certificate=keys / "tr_worker.cert")


def test_a_signed_market_refuses_a_spoofed_and_a_replayed_award(
        keys: Path, outsiders: list[Outsider], procs: list[AgentProc],
        monkeypatch: pytest.MonkeyPatch) -> None:
    from beehave.agents.market import Role, Task, TaskState, auction

    monkeypatch.setenv("BEEHAVE_AGENT_MODE", "signed")
    monkeypatch.setenv("BEEHAVE_AGENT_KEYS", str(keys))
    broker = AgentProc("tr_broker", [sys.executable, str(ROOT / "tests" / "market_node.py"),
                                     "tr_broker", "--caps", "carry", "--cost", "1.0",
                                     "--lease-s", "1.0"], wait_s=WAIT_S)
    procs.append(broker)
    broker.wait_event("ready")
    sniffer = Outsider("ext_c", keys=keys, wait_s=WAIT_S)  # a fleet member, listening to every copy
    outsiders.append(sniffer)
    with _signed_agent("tr_mboss", keys) as boss:
        assert wait_until(lambda: boss.directory.alive("tr_broker"), WAIT_S)
        task = Task.make("deliver", id="t_signed", roles=[
            Role("carry", "carry", params={"script": ["sleep:0.01"]})])
        outcome = auction(boss, task, reply_by_s=WAIT_S)
        assert outcome.state is TaskState.COMPLETED
        assert outcome.members == {"carry": "tr_broker"}
        award = sniffer.wait("copies", WAIT_S, performative="accept-proposal",
                             sender="tr_mboss")
        # Replayed as it was sent (its signature is good): refused as a replay.
        sniffer.send_text("tr_broker", json.dumps(award))
        replay = sniffer.wait("copies", WAIT_S, performative="not-understood",
                              in_reply_to=award["message_id"])
        assert "replayed" in replay["content"]["reason"]
        # A new award forged as the auctioneer's, signed with the sniffer's own key.
        forged = sniffer.message("accept-proposal", "tr_broker", award["content"],
                                 protocol=award["protocol"], sender="tr_mboss")
        sniffer.send(forged)
        refusal = sniffer.wait("copies", WAIT_S, performative="not-understood",
                               in_reply_to=forged["message_id"])
        assert "signed with the key certified for 'ext_c'" in refusal["content"]["reason"]
    with broker.cond:
        performed = [e for e in broker.events if e["event"] == "perform"]
    assert len(performed) == 1, broker.events
