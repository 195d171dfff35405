"""Agent messages: a FIPA-ACL subset carried as JSON in ``std_msgs/String``.

One message is one JSON object (schema ``beehave.acl/1``)::

    {"schema": "beehave.acl/1",
     "performative": "cfp",                 # see Performative
     "message_id": "5c1e…",                 # unique; replies name it in in_reply_to
     "sender": "machine_3",
     "receivers": ["atv_1", "atv_2"],
     "conversation_id": "machine_3/9f2a…",  # every message of one conversation shares it
     "in_reply_to": null,                   # the message_id this one answers
     "reply_by": 1767225600.25,             # Unix time (s) after which no reply counts
     "protocol": "fipa-contract-net",       # null for a message outside any protocol
     "content": {"task": "deliver", "to": "machine_3"},   # any JSON value
     "sent_at": 1767225599.25,
     "auth": {"certificate": {…}, "signature": "…"}}   # signed agents (beehave.agents.trust)

On the wire (:meth:`Message.from_wire`) every field but ``in_reply_to``, ``reply_by``,
``protocol`` and ``auth`` must be present (``content`` may be null); the JSON Schema is
``beehave/agents/schemas/acl.schema.json``. Every incoming message is validated; what
fails gets a ``not-understood`` reply (see :mod:`beehave.agents.agent`).
"""

from __future__ import annotations

import json
import re
import time
import uuid
from enum import Enum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

SCHEMA = "beehave.acl/1"
"""The version tag every message carries; a receiver refuses (not-understood) any other."""

NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_]{0,62}$"
"""Agent names: they become ROS topic names (``/beehave/agents/inbox/<name>``)."""

_NAME = re.compile(NAME_PATTERN)

REQUIRED = ("schema", "performative", "message_id", "sender", "receivers", "conversation_id",
            "content", "sent_at")
"""The fields a message on the wire must have (a sender that leaves one out is answered
with not-understood naming it, never guessed for)."""


class Performative(Enum):
    """What a message does (FIPA-ACL communicative acts; the value is the wire form)."""

    REQUEST = "request"
    """Asks the receivers to perform an action (content: what to do)."""
    AGREE = "agree"
    """The receiver of a request will perform it; an inform or failure follows."""
    REFUSE = "refuse"
    """The receiver will not perform the request or call for proposals (content: why)."""
    INFORM = "inform"
    """A result or a fact: the done report of a request or an awarded task."""
    FAILURE = "failure"
    """An agreed or awarded action failed (content: why)."""
    CFP = "cfp"
    """Call for proposals (contract net): content is the task; reply by ``reply_by``."""
    PROPOSE = "propose"
    """A bid for a cfp (content: the offer, e.g. ``{"cost": 12.5}``)."""
    ACCEPT_PROPOSAL = "accept-proposal"
    """The initiator awards the task to this proposer: perform it, then inform or fail."""
    REJECT_PROPOSAL = "reject-proposal"
    """The initiator does not award the task to this proposer (for now: see docs)."""
    CANCEL = "cancel"
    """The initiator withdraws the conversation: stop what it started, award nothing."""
    NOT_UNDERSTOOD = "not-understood"
    """The receiver could not take a message (content: ``{"reason": …}``)."""


def is_agent_name(name: object) -> bool:
    return isinstance(name, str) and bool(_NAME.match(name))


def _check_name(value: str) -> str:
    if not _NAME.match(value):
        raise ValueError(f"{value!r} is not an agent name (letters, digits, '_', starting "
                         f"with a letter, at most 63 characters)")
    return value


class Message(BaseModel):
    """One ACL message. Build replies with :meth:`reply`; the agent fills ``sender``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_: str = Field(SCHEMA, alias="schema")
    performative: Performative
    message_id: str = Field(default_factory=lambda: uuid.uuid4().hex, min_length=1,
                            max_length=200)
    sender: str
    receivers: list[str] = Field(min_length=1)
    conversation_id: str = Field(min_length=1, max_length=200)
    in_reply_to: str | None = None
    reply_by: float | None = Field(None, allow_inf_nan=False)
    protocol: str | None = None
    content: Any = None
    sent_at: float = Field(default_factory=time.time, allow_inf_nan=False)
    auth: dict[str, Any] | None = None
    """The sender's certificate and signature (:mod:`beehave.agents.trust`); filled by the
    sending agent when it has keys, checked by receivers in signed mode."""

    @field_validator("schema_")
    @classmethod
    def _schema(cls, value: str) -> str:
        if value != SCHEMA:
            raise ValueError(f"unsupported schema {value!r}; this agent speaks {SCHEMA!r}")
        return value

    @field_validator("sender")
    @classmethod
    def _sender(cls, value: str) -> str:
        return _check_name(value)

    @field_validator("receivers")
    @classmethod
    def _receivers(cls, value: list[str]) -> list[str]:
        for name in value:
            _check_name(name)
        return value

    def to_json(self) -> str:
        """The wire form (``auth`` only when there is one: the schema has no null for it)."""
        return self.model_dump_json(by_alias=True,
                                    exclude={"auth"} if self.auth is None else None)

    @classmethod
    def from_json(cls, text: str) -> Message:
        """Parse and validate; raises ``ValueError`` (pydantic's ``ValidationError`` is
        one) naming the field that is wrong."""
        return cls.model_validate_json(text)

    @classmethod
    def from_wire(cls, data: Any) -> Message:
        """Validate a parsed message as it arrived: like :meth:`from_json`, and every
        field of :data:`REQUIRED` must be there (defaults are for messages built here)."""
        if not isinstance(data, dict):
            raise ValueError(f"a message is a JSON object, got {type(data).__name__}")
        missing = [name for name in REQUIRED if name not in data]
        if missing:
            raise ValueError(f"missing field{'s' if len(missing) > 1 else ''}: "
                             f"{', '.join(missing)} (required: {', '.join(REQUIRED)})")
        return cls.model_validate(data)

    def reply(self, performative: Performative, content: Any = None, *,
              reply_by: float | None = None) -> Message:
        """The answer to this message: same conversation and protocol, to its sender,
        ``in_reply_to`` this one. ``sender`` is filled by the sending agent."""
        return Message(performative=performative, sender=self.receivers[0],
                       receivers=[self.sender], conversation_id=self.conversation_id,
                       in_reply_to=self.message_id, protocol=self.protocol,
                       content=content, reply_by=reply_by)

    @property
    def seconds_left(self) -> float | None:
        """Until ``reply_by`` (negative once passed); None when there is no deadline."""
        return None if self.reply_by is None else self.reply_by - time.time()


def sender_of(text: str) -> str | None:
    """The sender named by a message that failed validation, if one can be read: the
    receiver then answers it with not-understood."""
    try:
        data = json.loads(text)
    except (ValueError, RecursionError):
        return None
    sender = data.get("sender") if isinstance(data, dict) else None
    return sender if is_agent_name(sender) else None


def jsonable(value: Any) -> Any:
    """``value`` when it survives JSON, else its ``repr`` (a result a user returned from an
    action must not make the done report unsendable)."""
    try:
        json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)
    return value
