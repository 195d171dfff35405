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

from beehave.ros.context import clear_dead_shm_ports, clear_dead_shm_segments  # noqa: E402

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


# -- data segments ---------------------------------------------------------------------------

def test_only_segments_whose_lock_nobody_holds_are_removed(tmp_path: Path) -> None:
    """A live participant holds an exclusive flock on its segment's ``_el`` file; a killed
    one's lock file is free. Here the live owner is another open file of this process."""
    dead, live = tmp_path / "fastdds_00000000000000aa", tmp_path / "fastdds_00000000000000bb"
    for segment in (dead, live):
        segment.write_bytes(bytes(SEGMENT_BYTES))
        (tmp_path / f"{segment.name}_el").touch()
    lone = tmp_path / "fastdds_00000000000000cc_el"  # its owner died before the segment
    lone.touch()
    port = _port(tmp_path / "fastdds_port7411", 2, 60.0)
    port_lock = tmp_path / "fastdds_port7411_el"  # a port's lock: not a segment's
    port_lock.touch()
    with open(tmp_path / f"{live.name}_el", "rb") as owner:
        fcntl.flock(owner, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert clear_dead_shm_segments(tmp_path) == 2
        assert live.exists() and (tmp_path / f"{live.name}_el").exists()
    assert not dead.exists() and not (tmp_path / f"{dead.name}_el").exists()
    assert not lone.exists() and port.exists() and port_lock.exists()
    assert clear_dead_shm_segments(tmp_path / "missing") == 0


@pytest.mark.skipif(not SHM.is_dir(), reason="Fast DDS's segments live in /dev/shm")
def test_a_killed_participants_segment_is_removed_and_a_live_ones_kept() -> None:
    """A process SIGKILLed with a participant leaves its segment (half a megabyte of RAM,
    for ever); a live participant's segment — this process's — stays, and it still talks."""
    from std_msgs.msg import String

    from beehave.ros.context import RosContext

    def mapped(pid: int | str) -> set[str]:
        maps = Path(f"/proc/{pid}/maps").read_text(encoding="ascii", errors="replace")
        return {line.rsplit("/", 1)[1] for line in maps.splitlines()
                if "/dev/shm/fastdds_" in line and "port" not in line.rsplit("/", 1)[1]}

    code = ("import time\nfrom beehave.ros.context import RosContext\n"
            "ros = RosContext(); ros.create_node('doomed'); ros.start()\n"
            "print('up', flush=True); time.sleep(600)\n")
    child = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE,
                             text=True)
    try:
        assert child.stdout is not None and child.stdout.readline() == "up\n"
        deadline = time.monotonic() + wall_timeout(0.2)
        while not (theirs := mapped(child.pid)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert theirs, "the child maps no Fast DDS segment"
    finally:
        child.kill()
        child.wait()
    # (Left behind; another worker's RosContext, or Fast DDS itself, may remove them now.)
    with RosContext() as ros:
        node = ros.create_node("survivor")
        got: list[str] = []
        node.create_subscription(String, "/segment_test", lambda m: got.append(m.data), 10)
        pub = node.create_publisher(String, "/segment_test", 10)
        ros.start()
        ours = mapped("self")
        assert ours
        clear_dead_shm_segments()
        assert not any((SHM / name).exists() for name in theirs)
        assert all((SHM / name).exists() for name in ours)
        deadline = time.monotonic() + wall_timeout(0.2)
        while not got and time.monotonic() < deadline:
            pub.publish(String(data="still here"))
            time.sleep(0.05)
        assert got and got[0] == "still here"
