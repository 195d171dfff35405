"""Every VDA 5050 message in and out is checked against the official 2.1.0 JSON schemas.

The schemas ship in ``schemas/`` beside this module (MIT, VDA; see ``schemas/NOTICE.md``).
:func:`problems` returns what is wrong with a message as :class:`Problem` entries, each
naming the offending field by its path (``nodes[1].nodePosition.x``) — the adapter turns
them into ``validationError`` entries of the AGV's state, so a fleet manager sees which
field to fix. :func:`check` raises :class:`~beehave.errors.Vda5050ValidationError` instead:
the adapter calls it on what it sends, where a problem is beehave's bug.

Whether a message is valid is answered by a compiled validator (``fastjsonschema``, made
once per schema: a 1,000-node order in 10-30 ms instead of 110-660 ms with
``jsonschema``); only a message it finds invalid goes through ``jsonschema``, whose
errors name the fields. ``jsonschema`` stays the reference: should the two disagree
about a message, ``jsonschema``'s verdict counts. Without ``fastjsonschema`` installed
(it comes with the ``vda5050`` extra) every check is made by ``jsonschema``, slower.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from typing import Any, Literal

from jsonschema import Draft202012Validator  # type: ignore[import-untyped]
from jsonschema.exceptions import ValidationError  # type: ignore[import-untyped]

from beehave.errors import Vda5050ValidationError

try:
    import fastjsonschema
except ImportError:  # pragma: no cover - the vda5050 extra installs it
    fastjsonschema = None  # type: ignore[assignment]

Topic = Literal["order", "instantActions", "state", "visualization", "connection",
                "factsheet"]
TOPICS: tuple[Topic, ...] = ("order", "instantActions", "state", "visualization",
                             "connection", "factsheet")
"""The six VDA 5050 topics, each with its own schema file."""


@dataclass(frozen=True)
class Problem:
    """One way a message breaks its schema: ``field`` is the JSON path of the offending
    value (``""`` for the message itself), ``message`` what is wrong with it."""

    field: str
    message: str

    def __str__(self) -> str:
        return f"{self.field or '(message)'}: {self.message}"


@functools.cache
def schema(topic: Topic) -> dict[str, Any]:
    """One topic's official schema (read once per process)."""
    if topic not in TOPICS:
        raise Vda5050ValidationError(f"no VDA 5050 schema for topic {topic!r}; topics: "
                                     f"{', '.join(TOPICS)}")
    text = resources.files(__package__).joinpath("schemas", f"{topic}.schema").read_text(
        encoding="utf-8")
    loaded: dict[str, Any] = json.loads(text)
    Draft202012Validator.check_schema(loaded)
    return loaded


@functools.cache
def validator(topic: Topic) -> Draft202012Validator:
    """The ``jsonschema`` validator of one topic's schema (made once per process): the
    reference, and the one whose errors name the fields."""
    return Draft202012Validator(schema(topic))


@functools.cache
def fast_validator(topic: Topic) -> Callable[[Any], bool]:
    """``is_valid(message)`` for one topic, compiled once per process (``fastjsonschema``,
    formats not checked, as ``jsonschema`` does not check them either); ``jsonschema``'s
    ``is_valid`` when ``fastjsonschema`` is not installed."""
    if fastjsonschema is None:
        return validator(topic).is_valid
    compiled = fastjsonschema.compile(schema(topic), use_formats=False)
    failure = fastjsonschema.JsonSchemaValueException

    def is_valid(message: Any) -> bool:
        try:
            compiled(message)
        except failure:
            return False
        return True

    return is_valid


def is_valid(topic: Topic, message: Any) -> bool:
    """Whether ``message`` is valid for ``topic`` (the compiled validator; when it says
    no, ``jsonschema`` decides)."""
    return fast_validator(topic)(message) or validator(topic).is_valid(message)


def field_path(error: ValidationError) -> str:
    """``nodes[1].nodePosition.x`` for an error at that place; a missing required key is
    named as the field it should have been (``nodes[0].released``)."""
    path = ""
    for part in error.absolute_path:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    if error.validator == "required" and isinstance(error.instance, dict):
        # jsonschema reports a missing key at its parent; the user wants the key itself.
        missing = [k for k in error.validator_value if k not in error.instance]
        if missing:
            path = f"{path}.{missing[0]}" if path else str(missing[0])
    return path


def problems(topic: Topic, message: Any) -> list[Problem]:
    """What is wrong with ``message`` for ``topic`` (empty when it is valid), in document
    order, at most one entry per field."""
    if fast_validator(topic)(message):
        return []
    found: dict[str, Problem] = {}
    for error in sorted(validator(topic).iter_errors(message),
                        key=lambda e: [str(p) for p in e.absolute_path]):
        where = field_path(error)
        found.setdefault(where, Problem(where, error.message))
    return list(found.values())


def check(topic: Topic, message: Any) -> None:
    """Raise :class:`~beehave.errors.Vda5050ValidationError` listing every problem when
    ``message`` breaks the ``topic`` schema."""
    found = problems(topic, message)
    if found:
        raise Vda5050ValidationError(f"{topic} message breaks the VDA 5050 2.1.0 schema: "
                                     + "; ".join(str(p) for p in found))


_STATE_DEFAULTS: dict[str, Any] = {
    "orderId": "", "orderUpdateId": 0, "lastNodeId": "", "lastNodeSequenceId": 0,
    "nodeStates": [], "edgeStates": [], "driving": False, "actionStates": [],
    "batteryState": {"batteryCharge": 0.0, "charging": False},
    "operatingMode": "AUTOMATIC", "errors": [],
    "safetyState": {"eStop": "NONE", "fieldViolation": False}}
"""Schema-valid values for every required field of a state besides the header."""


def repaired_state(message: dict[str, Any], why: str) -> dict[str, Any]:
    """A schema-valid state made from an invalid one (beehave's bug): list items that
    break the schema are left out, other broken fields fall back to a valid default (or
    are dropped when optional), and an ``internalError`` says so — so the AGV still
    reports instead of falling silent. The header is kept (it is made by beehave and is
    valid); should the repair not be enough, only the header and defaults remain."""
    fixed = dict(message)
    drop_items: dict[str, set[int]] = {}
    reset: set[str] = set()
    for error in validator("state").iter_errors(message):
        path = list(error.absolute_path)
        if not path:
            reset.update(k for k in _STATE_DEFAULTS if k not in fixed)
            continue
        key = str(path[0])
        if len(path) >= 2 and isinstance(path[1], int) and isinstance(fixed.get(key), list):
            drop_items.setdefault(key, set()).add(path[1])
        else:
            reset.add(key)
    for key, gone in drop_items.items():
        fixed[key] = [item for i, item in enumerate(fixed[key]) if i not in gone]
    for key in reset:
        if key in _STATE_DEFAULTS:
            fixed[key] = _STATE_DEFAULTS[key]
        else:
            fixed.pop(key, None)
    note = {"errorType": "internalError", "errorLevel": "WARNING",
            "errorDescription": f"beehave made a state that breaks the schema; parts left "
                                f"out: {why}"[:1000],
            "errorReferences": []}
    fixed["errors"] = [*fixed.get("errors", []), note]
    if is_valid("state", fixed):
        return fixed
    header: dict[str, Any] = {
        k: message[k] for k in ("headerId", "timestamp", "version", "manufacturer",
                                "serialNumber") if k in message}
    return {**header, **_STATE_DEFAULTS, "errors": [note]}
