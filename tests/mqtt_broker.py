"""The VDA 5050 tests' broker and master: a real mosquitto per test (started with its own
configuration file on a free port, killed by PID) and the demo's master-control client."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from behaviours.demos.vda5050_master import (
    Broker,
    Master,
    TlsFiles,
    action,
    edge,
    free_port,
    make_tls_files,
    node,
)

__all__ = ["Broker", "Master", "TlsFiles", "action", "broker", "edge", "free_port",
           "make_tls_files", "node"]


@pytest.fixture
def broker() -> Iterator[Broker]:
    with Broker() as running:
        yield running
