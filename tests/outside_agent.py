"""Another team's agent, written from docs/agents.md alone: plain rclpy + std_msgs +
``cryptography``, no beehave import. The trust tests (``tests/test_agents_trust.py``) drive
beehave agents with it.

It announces a directory entry on ``/beehave/agents/directory`` (reliable, transient-local,
keep-last 1) every ``lease_s / 4``, reads its inbox ``/beehave/agents/inbox/<name>``
(reliable, volatile, keep-last 1000) and the copies on ``/beehave/agents/messages`` (best
effort), and signs what it sends with an Ed25519 key and the certificate ``beehave keys
issue`` wrote: ``"auth": {"certificate": <the .cert file>, "signature": base64(Ed25519 over
the canonical JSON of the object without "auth")}``, canonical JSON being
``json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False)``.
"""

from __future__ import annotations

import base64
import json
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import rclpy
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

DIRECTORY = "/beehave/agents/directory"
MESSAGES = "/beehave/agents/messages"
INBOX = "/beehave/agents/inbox/"
DIRECTORY_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                           reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
INBOX_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
MESSAGES_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                          reliability=ReliabilityPolicy.BEST_EFFORT,
                          durability=DurabilityPolicy.VOLATILE)


def canonical(obj: Any) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"),
                      ensure_ascii=False).encode()


def verify(obj: dict[str, Any], fleet_pub_pem: bytes) -> str:
    """The agent that signed ``obj`` (a message or directory entry), checked against the
    fleet's public key as the spec says; raises when anything does not hold."""
    fleet = serialization.load_pem_public_key(fleet_pub_pem)
    assert isinstance(fleet, Ed25519PublicKey)
    cert = obj["auth"]["certificate"]
    body = {k: v for k, v in cert.items() if k != "signature"}
    fleet.verify(base64.b64decode(cert["signature"]), canonical(body))
    key = Ed25519PublicKey.from_public_bytes(base64.b64decode(cert["public_key"]))
    key.verify(base64.b64decode(obj["auth"]["signature"]),
               canonical({k: v for k, v in obj.items() if k != "auth"}))
    return str(cert["agent"])


class Outsider:
    """One outside agent. ``keys``: the folder `beehave keys` wrote (uses NAME.key and
    NAME.cert), or None to send unsigned; ``sign_as``: another name's key and
    certificate from that folder (an impersonation)."""

    def __init__(self, name: str, *, keys: Path | None = None, sign_as: str | None = None,
                 services: dict[str, dict[str, Any]] | None = None,
                 lease_s: float = 1.0, wait_s: float) -> None:
        self.name = name
        # How long a send waits for the receiver's inbox to match: the test's bound (no
        # beehave import here, so the test passes WALL_TIMEOUT_S in).
        self.wait_s = wait_s
        self.services = services or {}
        self.lease_s = lease_s
        self.key: Ed25519PrivateKey | None = None
        self.cert: dict[str, Any] | None = None
        if keys is not None:
            who = sign_as or name
            key = serialization.load_pem_private_key((keys / f"{who}.key").read_bytes(), None)
            assert isinstance(key, Ed25519PrivateKey)
            self.key = key
            self.cert = json.loads((keys / f"{who}.cert").read_text())
        self.incarnation = uuid.uuid4().hex
        self.started_at = time.time()
        self.inbox: list[dict[str, Any]] = []
        self.copies: list[dict[str, Any]] = []
        self.entries: list[dict[str, Any]] = []  # directory entries heard
        self.cond = threading.Condition()
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"outsider_{name}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.directory = self.node.create_publisher(String, DIRECTORY, DIRECTORY_QOS)
        self.node.create_subscription(String, INBOX + name, self._on_inbox, INBOX_QOS)
        self.node.create_subscription(String, MESSAGES, self._on_copy, MESSAGES_QOS)
        self.node.create_subscription(String, DIRECTORY, self._on_entry, QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.publishers: dict[str, Any] = {}
        self.node.create_timer(lease_s / 4, self.announce)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        self.announce()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # the context was shut down
            pass

    # ------------------------------------------------------------------ wire
    def signed(self, obj: dict[str, Any]) -> dict[str, Any]:
        if self.key is None:
            return obj
        signature = self.key.sign(canonical(obj))
        return {**obj, "auth": {"certificate": self.cert,
                                "signature": base64.b64encode(signature).decode()}}

    def announce(self, state: str = "alive") -> None:
        entry = {"schema": "beehave.directory/1", "agent": self.name,
                 "incarnation": self.incarnation, "started_at": self.started_at,
                 "state": state, "lease_s": self.lease_s, "services": self.services,
                 "sent_at": time.time()}
        self.directory.publish(String(data=json.dumps(self.signed(entry))))

    def message(self, performative: str, receiver: str, content: Any, *,
                conversation_id: str | None = None, protocol: str | None = None,
                in_reply_to: str | None = None, sender: str | None = None,
                reply_by: float | None = None,
                sent_at: float | None = None) -> dict[str, Any]:
        """A message as the spec has it (signed when this outsider has keys)."""
        return self.signed({
            "schema": "beehave.acl/1", "performative": performative,
            "message_id": uuid.uuid4().hex, "sender": sender or self.name,
            "receivers": [receiver],
            "conversation_id": conversation_id or f"{self.name}/{uuid.uuid4().hex[:12]}",
            "in_reply_to": in_reply_to, "reply_by": reply_by, "protocol": protocol,
            "content": content, "sent_at": time.time() if sent_at is None else sent_at})

    def send_text(self, receiver: str, text: str, timeout_s: float | None = None) -> None:
        publisher = self.publishers.get(receiver)
        if publisher is None:
            publisher = self.publishers[receiver] = self.node.create_publisher(
                String, INBOX + receiver, INBOX_QOS)
        deadline = time.monotonic() + (self.wait_s if timeout_s is None else timeout_s)
        while publisher.get_subscription_count() == 0:
            assert time.monotonic() < deadline, f"no inbox of {receiver} matched"
            time.sleep(0.01)
        publisher.publish(String(data=text))

    def send(self, message: dict[str, Any]) -> dict[str, Any]:
        self.send_text(message["receivers"][0], json.dumps(message))
        return message

    def reply(self, to: dict[str, Any], performative: str, content: Any) -> dict[str, Any]:
        return self.send(self.message(performative, to["sender"], content,
                                      conversation_id=to["conversation_id"],
                                      protocol=to["protocol"], in_reply_to=to["message_id"]))

    def _on_inbox(self, msg: String) -> None:
        with self.cond:
            self.inbox.append(json.loads(msg.data))
            self.cond.notify_all()

    def _on_copy(self, msg: String) -> None:
        with self.cond:
            self.copies.append(json.loads(msg.data))
            self.cond.notify_all()

    def _on_entry(self, msg: String) -> None:
        with self.cond:
            self.entries.append(json.loads(msg.data))
            self.cond.notify_all()

    def wait(self, where: str, timeout_s: float, **match: Any) -> dict[str, Any]:
        """The first message in ``inbox`` or ``copies`` whose fields equal ``match``."""
        def found() -> dict[str, Any] | None:
            return next((m for m in getattr(self, where)
                         if all(m.get(k) == v for k, v in match.items())), None)

        with self.cond:
            self.cond.wait_for(lambda: found() is not None, timeout_s)
            hit = found()
        assert hit is not None, f"{self.name}: no {match} in {where} within {timeout_s} s: " \
                                f"{getattr(self, where)}"
        return hit

    def close(self) -> None:
        self.announce("leaving")
        time.sleep(0.05)
        self.executor.shutdown(timeout_sec=1)
        self.node.destroy_node()
        self.context.try_shutdown()
        self.thread.join(self.wait_s)
