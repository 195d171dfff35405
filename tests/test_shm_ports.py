"""Fast DDS shared-memory ports that a killed process left unfinished (``RosContext``
clears them): the next node of their domain would hang in ``rcl_node_init`` for ever. Seen
in stress runs; the native stack, read with gdb, ended in ``SharedMemGlobal::open_port``."""

from __future__ import annotations

import contextlib
import fcntl
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from beehave.testing import wall_timeout

pytest.importorskip("rclpy")

from beehave.ros.context import clear_dead_shm_ports  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SEGMENT_BYTES = 52400  # a port's size as Fast DDS makes it


SHM = Path("/dev/shm")
#: Domains no other test or benchmark uses (tests/conftest.py: 1-100 by default, benchmarks
#: 101-200): this test fills a domain's ports with dead ones, and removes them after.
SPARE_DOMAINS = range(201, 206)
LOCKED = bytes(32)  # a glibc named semaphore (x86-64: 32 bytes) at 0: a locked mutex


def _port(path: Path, state: int, age_s: float) -> Path:
    """A port segment whose set-up state is ``state`` (2: ready; 1: being set up), made
    ``age_s`` ago."""
    path.write_bytes(state.to_bytes(4, sys.byteorder) + bytes(SEGMENT_BYTES - 4))
    os.utime(path, (time.time() - age_s,) * 2)
    return path


def _mutex(shm: Path, port: Path) -> Path:
    """The port's mutex, locked, as a process killed while it held it leaves it."""
    path = shm / f"sem.{port.name}_mutex"
    path.write_bytes(LOCKED)
    return path


def test_only_ports_left_unfinished_for_a_while_are_removed(tmp_path: Path) -> None:
    dead = _port(tmp_path / "fastdds_port7411", 1, 60.0)
    dead_mutex = _mutex(tmp_path, dead)
    created = _port(tmp_path / "fastdds_port7413", 0, 60.0)
    corrupted = _port(tmp_path / "fastdds_port7419", 3, 60.0)
    empty = tmp_path / "fastdds_port7421"  # killed before it wrote a byte
    empty.touch()
    os.utime(empty, (time.time() - 60,) * 2)
    ready = _port(tmp_path / "fastdds_port7415", 2, 60.0)
    ready_mutex = _mutex(tmp_path, ready)  # (not ours to judge: the port is in use)
    young = _port(tmp_path / "fastdds_port7417", 1, 0.0)  # its creator may be at work
    lock = tmp_path / "fastdds_port7411_el"  # a lock file: empty by design
    lock.touch()
    os.utime(lock, (time.time() - 60,) * 2)
    other = _port(tmp_path / "fastdds_1a2b3c4d5e6f7a8b", 1, 60.0)  # not a port
    waiter = os.open(dead, os.O_RDONLY)  # a process that has the dead port open
    try:
        removed = clear_dead_shm_ports(tmp_path)
        # It sees the port corrupted: a process waiting for it to be ready stops waiting.
        assert os.pread(waiter, 4, 0) == (3).to_bytes(4, sys.byteorder)
    finally:
        os.close(waiter)
    assert sorted(removed) == [
        "fastdds_port7411", "fastdds_port7413", "fastdds_port7419", "fastdds_port7421"]
    assert not any(p.exists() for p in (dead, dead_mutex, created, corrupted, empty))
    assert all(p.exists() for p in (ready, ready_mutex, young, lock, other))
    assert clear_dead_shm_ports(tmp_path / "missing") == []


@pytest.mark.skipif(not SHM.is_dir(), reason="Fast DDS's ports live in /dev/shm")
@pytest.mark.parametrize("killed_s_ago", [60.0, 5.0])
def test_a_node_starts_where_a_killed_process_left_its_domains_ports_unfinished(
        killed_s_ago: float) -> None:
    """Every port a new participant of a domain could take is left "being set up", its
    mutex locked, as a process killed ``killed_s_ago`` leaves them. Without the clearing
    the node hangs (tried: still in rcl_node_init after 20 s). Clearing the ports but not
    their mutexes costs it 2 s, and leaves the mutexes of the ports it did not take locked.

    Killed 5 s ago, the ports are too young to clear when the node's context starts: the
    participant waits on one until the context, watching meanwhile, releases it at 10 s (a
    stress run: a sim started just after the previous test had killed a process hung for
    90 s, when only the start was cleared)."""
    def ports(domain: int) -> list[Path]:
        # A participant's shared-memory port is its user-data unicast port (RTPS 9.6.1.1:
        # 7400 + 250 * domain + 11 + 2 * participant id); the first participant takes id 0.
        return [SHM / f"fastdds_port{7400 + 250 * domain + 11 + 2 * p}" for p in range(10)]

    with contextlib.ExitStack() as claims:
        # A spare domain with no ports, claimed for the test (two suites on one machine
        # must not plant dead ports under each other's child).
        domain = next((d for d in SPARE_DOMAINS if _claim(claims, d)
                       and not any(p.exists() for p in ports(d))), None)
        if domain is None:
            pytest.skip(f"every spare domain {SPARE_DOMAINS} is claimed or has ports")
        _node_after_a_crash(domain, ports(domain), killed_s_ago)


def _claim(claims: contextlib.ExitStack, domain: int) -> bool:
    """Whether this process now holds ``domain``'s claim (a lock on a file, released with
    ``claims`` or when the process dies)."""
    lock = claims.enter_context(
        open(Path(tempfile.gettempdir()) / f"beehave-test-shm-domain-{domain}.lock", "a"))
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _node_after_a_crash(domain: int, ports: list[Path], killed_s_ago: float) -> None:
    made = [_port(path, 1, killed_s_ago) for path in ports]
    mutexes = [_mutex(SHM, path) for path in made]
    code = ("from beehave.ros.context import RosContext\n"
            "with RosContext() as ros:\n"
            "    ros.create_node('after_a_crash')\n"
            "print('node up', flush=True)\n")
    being_set_up = (1).to_bytes(4, sys.byteorder)
    try:
        done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                              text=True, timeout=wall_timeout(0.5),
                              env=dict(os.environ, ROS_DOMAIN_ID=str(domain)))
        stuck = [p.name for p in made if p.exists() and p.read_bytes()[:4] == being_set_up]
        locked = [m.name for m in mutexes if m.exists() and m.read_bytes()[:4] == LOCKED[:4]]
    finally:  # the domain is this test's alone: whatever is left of its ports goes
        for path in made:
            for leftover in (path, SHM / f"sem.{path.name}_mutex", SHM / f"{path.name}_el"):
                leftover.unlink(missing_ok=True)
    # (Which process removed them is not checked: any beehave process that starts first,
    # a test of another worker, does. A stress run saw that.)
    assert done.returncode == 0 and "node up" in done.stdout, done.stderr
    assert stuck == [] and locked == []
