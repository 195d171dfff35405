"""A manager served over HTTP for the web-view tests (breakpoints, graphs, timeline)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from beehave import HighLevelBehaviorManager
from beehave.interfaces import ControlPlane
from beehave.interfaces.http import HttpServer


@contextlib.contextmanager
def served(manager: HighLevelBehaviorManager, *, name: str = "emili1", **options: Any
           ) -> Iterator[HttpServer]:
    """``manager`` as robot ``name`` behind a started :class:`HttpServer` (``options``:
    its keywords, e.g. ``host``, ``token``); the server and the control plane are ended
    on the way out, the manager is left to its owner."""
    plane = ControlPlane(manager, name=name)
    try:
        with HttpServer(plane, **options) as server:
            yield server
    finally:
        plane.close()
