"""Fast DDS shared-memory ports that a killed process left unfinished (``RosContext``
clears them): the next node of their domain would hang in ``rcl_node_init`` for ever. Seen
in stress runs; the native stack, read with gdb, ended in ``SharedMemGlobal::open_port``."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from beehave.testing import wall_timeout

pytest.importorskip("rclpy")

from beehave.ros.context import clear_dead_shm_ports  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SEGMENT_BYTES = 52400  # a port's size as Fast DDS makes it


def _port(path: Path, state: int, age_s: float) -> Path:
    """A port segment whose set-up state is ``state`` (2: ready; 1: being set up), made
    ``age_s`` ago."""
    path.write_bytes(state.to_bytes(4, sys.byteorder) + bytes(SEGMENT_BYTES - 4))
    os.utime(path, (time.time() - age_s,) * 2)
    return path


def test_only_ports_left_unfinished_for_a_while_are_removed(tmp_path: Path) -> None:
    dead = _port(tmp_path / "fastdds_port7411", 1, 60.0)
    created = _port(tmp_path / "fastdds_port7413", 0, 60.0)
    ready = _port(tmp_path / "fastdds_port7415", 2, 60.0)
    young = _port(tmp_path / "fastdds_port7417", 1, 0.0)  # its creator may be at work
    lock = tmp_path / "fastdds_port7411_el"  # a lock file: empty by design
    lock.touch()
    os.utime(lock, (time.time() - 60,) * 2)
    other = _port(tmp_path / "fastdds_1a2b3c4d5e6f7a8b", 1, 60.0)  # not a port
    assert sorted(clear_dead_shm_ports(tmp_path)) == ["fastdds_port7411", "fastdds_port7413"]
    assert not dead.exists() and not created.exists()
    assert ready.exists() and young.exists() and lock.exists() and other.exists()
    assert clear_dead_shm_ports(tmp_path / "missing") == []


@pytest.mark.skipif(not Path("/dev/shm").is_dir(), reason="Fast DDS's ports live in /dev/shm")
def test_a_node_starts_where_a_killed_process_left_its_domains_ports_unfinished() -> None:
    """Every port a new participant of this test's domain could take is left "being set
    up", as a process killed at that moment leaves it: without the clearing, the node
    hangs (tried: still in rcl_node_init after 20 s); with it, it comes up."""
    domain = int(os.environ["ROS_DOMAIN_ID"])
    base = 7400 + 250 * domain
    made = []
    for participant in range(10):
        for offset in (10, 11):  # its discovery and its user-data port (RTPS 9.6.1.1)
            path = Path("/dev/shm") / f"fastdds_port{base + offset + 2 * participant}"
            if not path.exists():  # (one that exists belongs to a live process)
                made.append(_port(path, 1, 60.0))
    code = ("from beehave.ros.context import RosContext\n"
            "with RosContext() as ros:\n"
            "    ros.create_node('after_a_crash')\n"
            "print('node up', flush=True)\n")
    being_set_up = (1).to_bytes(4, sys.byteorder)
    try:
        done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                              text=True, timeout=wall_timeout(0.5))
        stuck = [p.name for p in made if p.exists() and p.read_bytes()[:4] == being_set_up]
    finally:
        for path in made:
            path.unlink(missing_ok=True)
    # (The child names the ports it removed, unless another beehave process on this
    # machine, a test of another worker, started first and removed them: a stress run saw
    # that. Either way no port was left to hang the node.)
    assert done.returncode == 0 and "node up" in done.stdout, done.stderr
    assert stuck == []
