"""Free UDP ports for the suite's MAVLink links, chosen where nobody else picks one.

A port the kernel hands out for ``bind(0)`` and that the test then closes and binds again is
an ephemeral port: any other socket of the machine may take it in between (a stress run's
MAVLink link failed with "Address already in use"). These come from below the kernel's
ephemeral range and below the DDS ports (7400 and up), in a slice of 20 per
``ROS_DOMAIN_ID`` (each xdist worker has its own domain; two suites on one machine use
different ranges, see conftest.py), and each is checked free when chosen.
"""

from __future__ import annotations

import os
import random
import socket

_FIRST = 2000
_PER_DOMAIN = 20  # 2000 + 20 * 232 + 20 < 7400, the first DDS port


def _candidates() -> list[int]:
    domain = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    start = _FIRST + _PER_DOMAIN * domain
    ports = list(range(start, start + _PER_DOMAIN))
    random.shuffle(ports)
    return ports


def free_udp_ports(count: int) -> list[int]:
    """``count`` distinct free UDP ports on 127.0.0.1 (held together while choosing)."""
    held: list[socket.socket] = []
    try:
        for port in _candidates():
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                s.close()
                continue
            held.append(s)
            if len(held) == count:
                return [h.getsockname()[1] for h in held]
        raise AssertionError(f"fewer than {count} free UDP ports in this domain's slice")
    finally:
        for s in held:
            s.close()


def free_udp_port() -> int:
    return free_udp_ports(1)[0]


def free_udp_port_pair() -> int:
    """A free UDP port whose successor is free too (``beehave sim`` uses BASE and BASE+1)."""
    last = max(_candidates())
    for base in _candidates():
        if base == last:  # its successor is another domain's
            continue
        try:
            ports = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
            try:
                ports[0].bind(("127.0.0.1", base))
                ports[1].bind(("127.0.0.1", base + 1))
                return base
            finally:
                for s in ports:
                    s.close()
        except OSError:
            continue
    raise AssertionError("no two consecutive free UDP ports in this domain's slice")
