"""The JSON-lines channel between the agent processes of the agent tests and the tests.

A node (``tests/agents_node.py``, ``tests/agents_host_node.py``) reports each step with
:func:`say`; the test reads its stdout with :func:`read_events`. No beehave import: both
sides load it as it is.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable
from typing import Any

_print_lock = threading.Lock()


def say(event: str, **detail: Any) -> None:
    """Print one event as a JSON line (whole, whichever thread prints)."""
    with _print_lock:
        print(json.dumps({"event": event, **detail}), flush=True)


def read_events(lines: Iterable[str], events: list[dict[str, Any]],
                cond: threading.Condition) -> None:
    """Append each JSON line of ``lines`` (a node's stdout) to ``events`` under ``cond``,
    then ``{"event": "exited"}`` once it ends; every waiter on ``cond`` is woken each time.
    Lines that are not JSON (a library's own output) are skipped."""
    for line in lines:
        try:
            event = json.loads(line)
        except ValueError:
            continue
        with cond:
            events.append(event)
            cond.notify_all()
    with cond:
        events.append({"event": "exited"})
        cond.notify_all()
