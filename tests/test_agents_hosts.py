"""Agents on two hosts: two Linux network namespaces joined by a veth pair.

Each namespace is a host with its own network stack: its own loopback and one interface on
a private subnet (``10.231.0.1/24`` and ``10.231.0.2/24``); nothing else, so every DDS
packet between the two agents crosses the veth "wire" and nothing leaves the pair. An
agent process runs in each (``ip netns exec``): a contract-net responder
(``tests/agents_node.py``) on host B, an initiator (``tests/agents_host_node.py``) on host
A. They must find each other in the directory and complete a contract net, with discovery
as a real fleet configures it: multicast on the subnet (``ROS_AUTOMATIC_DISCOVERY_RANGE=
SUBNET``) or, where there is no multicast, a list of peers (``ROS_STATIC_PEERS``).

Fast DDS offers shared memory between processes of one machine, and both namespaces share
``/dev/shm``. ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` keeps the multicast case on UDP, as
between real hosts. It does not bind the static-peers case: with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` the ROS 2 middleware adds the shared-memory
transport itself (``docs/ros.md``). In both cases the veth's packet counters show that
the traffic crossed the wire.

Needs root (``ip netns add``). Where the namespaces cannot be created, the test is skipped
with the command and its error. Namespace and veth names carry this process's pid, and are
deleted in a ``finally`` — a crashed run leaves names no later run uses.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from agents_events import read_events  # noqa: E402

from beehave.testing import WALL_TIMEOUT_S, wall_timeout  # noqa: E402

TESTS = Path(__file__).resolve().parent
SUBNET = "10.231.0"  # private (RFC 1918), only ever inside the two namespaces
# For the whole exchange: a share of the suite's bound (45 s on an idle machine), scaled for
# load like it.
DEADLINE_S = wall_timeout(0.75)


@dataclass
class Host:
    namespace: str
    interface: str
    address: str


def _ip(*args: str) -> str:
    """Run ``ip ARGS``; raises CalledProcessError with ip's own message on failure."""
    done = subprocess.run(["ip", *args], capture_output=True, text=True,
                          timeout=WALL_TIMEOUT_S)
    if done.returncode != 0:
        raise subprocess.CalledProcessError(done.returncode, ["ip", *args], done.stdout,
                                            done.stderr)
    return done.stdout


@pytest.fixture
def hosts() -> Iterator[tuple[Host, Host]]:
    """Two namespaces joined by a veth pair, IPv6 off (every packet on the wire is then
    the agents' IPv4 traffic), deleted afterwards whatever happened."""
    if shutil.which("ip") is None:
        pytest.skip("network namespaces cannot be created: the `ip` command (Debian "
                    "package iproute2) is not installed")
    pid = os.getpid()
    a = Host(f"beehave_a_{pid}", f"bh{pid}a", f"{SUBNET}.1")
    b = Host(f"beehave_b_{pid}", f"bh{pid}b", f"{SUBNET}.2")
    created: list[str] = []
    try:
        try:
            for host in (a, b):
                _ip("netns", "add", host.namespace)
                created.append(host.namespace)
            # Created straight inside the namespaces: the root namespace never sees it.
            _ip("link", "add", a.interface, "netns", a.namespace, "type", "veth",
                "peer", "name", b.interface, "netns", b.namespace)
        except (subprocess.CalledProcessError, OSError) as exc:
            # The one skip: this machine or user cannot make namespaces. Failures of the
            # configuration below are the test's own and fail it.
            detail = exc.stderr.strip() if isinstance(exc, subprocess.CalledProcessError) \
                else str(exc)
            command = " ".join(exc.cmd) if isinstance(exc, subprocess.CalledProcessError) \
                else "ip"
            pytest.skip(f"network namespaces cannot be created here (needs root and "
                        f"CAP_NET_ADMIN): `{command}` failed: {detail}")
        for host in (a, b):
            for sysctl in ("net.ipv6.conf.all.disable_ipv6=1",
                           "net.ipv6.conf.default.disable_ipv6=1"):
                _ip("netns", "exec", host.namespace, "sysctl", "-q", "-w", sysctl)
            _ip("-n", host.namespace, "addr", "add", f"{host.address}/24", "dev",
                host.interface)
            _ip("-n", host.namespace, "link", "set", "lo", "up")
            _ip("-n", host.namespace, "link", "set", host.interface, "up")
            # Multicast (DDS discovery goes to 239.255.0.1) needs a route, as on a host
            # with a default route: without one, discovery fails in some runs.
            _ip("-n", host.namespace, "route", "add", "224.0.0.0/4", "dev", host.interface)
        yield a, b
    finally:
        for namespace in created:  # deleting a namespace destroys its end of the veth,
            subprocess.run(["ip", "netns", "del", namespace],  # and so the pair
                           capture_output=True, timeout=WALL_TIMEOUT_S)


class HostProc:
    """A process in a namespace whose JSON lines on stdout are collected as they come."""

    def __init__(self, host: Host, script: str, *args: str, env: dict[str, str]) -> None:
        self.host = host
        # `ip netns exec` execs the command: the pid is python's, to be killed by it.
        self.popen = subprocess.Popen(
            ["ip", "netns", "exec", host.namespace, sys.executable, str(TESTS / script),
             *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        self.events: list[dict[str, Any]] = []
        self.stderr = ""
        self._cond = threading.Condition()
        self._threads = [threading.Thread(target=self._read, daemon=True),
                         threading.Thread(target=self._read_stderr, daemon=True)]
        for thread in self._threads:
            thread.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        read_events(self.popen.stdout, self.events, self._cond)

    def _read_stderr(self) -> None:
        assert self.popen.stderr is not None
        self.stderr = self.popen.stderr.read()[-3000:]

    def wait_event(self, *kinds: str, deadline: float) -> dict[str, Any]:
        """The first event of one of ``kinds`` (or ``exited``), waiting until ``deadline``
        (time.monotonic)."""
        def found() -> dict[str, Any] | None:
            return next((e for e in self.events if e["event"] in (*kinds, "exited")), None)

        with self._cond:
            self._cond.wait_for(lambda: found() is not None, deadline - time.monotonic())
            event = found()
        assert event is not None and event["event"] != "exited", \
            f"{self.host.namespace}: no {kinds} before the deadline; events: {self.events}"
        return event

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGKILL)
        self.popen.wait(WALL_TIMEOUT_S)
        for thread in self._threads:
            thread.join(WALL_TIMEOUT_S)


def _counters(host: Host) -> dict[str, int]:
    link = json.loads(_ip("-n", host.namespace, "-s", "-j", "link", "show", host.interface))
    stats = link[0]["stats64"]
    return {"rx_packets": stats["rx"]["packets"], "tx_packets": stats["tx"]["packets"]}


@pytest.mark.parametrize("discovery", ["subnet-multicast", "static-peers"])
def test_contract_net_between_two_hosts(hosts: tuple[Host, Host], discovery: str) -> None:
    a, b = hosts
    deadline = time.monotonic() + DEADLINE_S
    base = dict(os.environ, FASTDDS_BUILTIN_TRANSPORTS="UDPv4")  # (SUBNET only: above)
    base.pop("ROS_STATIC_PEERS", None)

    def env(peer: Host) -> dict[str, str]:
        if discovery == "subnet-multicast":
            return dict(base, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")
        # No multicast: LOCALHOST alone would find nobody here, the peer list does.
        return dict(base, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                    ROS_STATIC_PEERS=peer.address)

    procs: list[HostProc] = []
    try:
        responder = HostProc(b, "agents_node.py", "atv_on_b", "--service", "transport",
                             "--cost", "2.5", "--lease-s", "1.0", env=env(a))
        procs.append(responder)
        initiator = HostProc(a, "agents_host_node.py", "machine_on_a", "--service",
                             "transport", "--wait-s", str(DEADLINE_S - 10), env=env(b))
        procs.append(initiator)

        responder.wait_event("ready", deadline=deadline)
        found = initiator.wait_event("found", "error", deadline=deadline)
        assert found["event"] == "found", \
            f"{found}; responder: {responder.events}, veth: {_counters(a)} {_counters(b)}"
        assert found["agents"] == ["atv_on_b"]

        award = initiator.wait_event("award", "error", deadline=deadline)
        assert award["event"] == "award", f"{award}; stderr: {initiator.stderr}"
        assert award["awardee"] == "atv_on_b"
        # The responder's inform-done carries its Deliver action's result.
        assert award["result"] == {"result": {"delivered": True}}
        assert award["attempts"] == [["atv_on_b", "inform"]]
        # The responder's side of the same conversation: the cfp, the task performed.
        for kind in ("cfp", "perform", "done"):
            event = responder.wait_event(kind, deadline=deadline)
            assert event["cid"] == award["cid"], f"{kind}: {event} vs {award}"

        # Both directions crossed the veth (IPv6 is off: these are the agents' packets).
        for host in (a, b):
            counters = _counters(host)
            assert counters["rx_packets"] > 0 and counters["tx_packets"] > 0, \
                f"{host.namespace} {host.interface}: {counters}"
    finally:
        for proc in procs:
            proc.kill()
