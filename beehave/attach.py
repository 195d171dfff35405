"""Slots that another layer fills on a manager for its behaviours and logics to reach.

The core names the slot (``self.fleet`` reads ``"fleet"``); the layer that fills it (the
agents' :class:`~beehave.agents.fleet.Fleet`) attaches itself here, so the core never
imports it. A high level is keyed by its manager, a low level by its blackboard (what a
logic reaches).
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

from beehave.errors import ConfigError

_SLOTS: weakref.WeakKeyDictionary[object, dict[str, Any]] = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


def attach(owner: object, slot: str, value: Any) -> None:
    """Fill ``slot`` of ``owner`` (a manager, or a low level's blackboard) with ``value``."""
    with _LOCK:
        _SLOTS.setdefault(owner, {})[slot] = value


def detach(value: Any, slot: str) -> None:
    """Empty ``slot`` wherever ``value`` fills it."""
    with _LOCK:
        for slots in list(_SLOTS.values()):
            if slots.get(slot) is value:
                del slots[slot]


def attached(owner: object, slot: str, *, missing: str) -> Any:
    """What fills ``slot`` of ``owner``; :class:`ConfigError` with ``missing`` when nothing
    does."""
    with _LOCK:
        value = _SLOTS.get(owner, {}).get(slot)
    if value is None:
        raise ConfigError(missing)
    return value
