"""beehave's Fast DDS profile (beehave/ros/fastdds_profile.xml): a RosContext's process runs
without Fast DDS's TypeLookup service, whose reply thread crashed a robot process of a stress
run (SIGSEGV in TypeLookupManager::notify_callbacks, from its core file), and still talks to
a plain rclpy program that keeps Fast DDS's defaults.

The processes are real: what runs is read from /proc (the threads Fast DDS names), what is
said is received over DDS."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from beehave.testing import wall_timeout

pytest.importorskip("rclpy")

from beehave.ros import context  # noqa: E402
from beehave.ros.context import (  # noqa: E402
    FASTDDS_PROFILE,
    FASTDDS_PROFILE_ENV,
    use_fastdds_profile,
)

ROOT = Path(__file__).resolve().parent.parent
#: Fast DDS 3.2 names its TypeLookup service's threads dds.tls.request and dds.tls.replies.
TYPELOOKUP_THREADS = "dds.tls."

# A child that makes one participant and prints the names of its process's threads.
THREADS = """
import os, sys
mode = sys.argv[1]
if mode == "beehave":
    from beehave.ros.context import RosContext
    ctx = RosContext()
    node = ctx.create_node("profile_probe")
else:
    import rclpy
    rclpy.init()
    node = rclpy.create_node("profile_probe")
print(" ".join(sorted(open(f"/proc/self/task/{t}/comm").read().strip()
                      for t in os.listdir("/proc/self/task"))), flush=True)
"""

# A RosContext's node publishes nav_msgs/Odometry (a type the listener's process has not
# used before it subscribes) until a plain rclpy listener with Fast DDS's defaults has five.
TALKER = """
import time
from nav_msgs.msg import Odometry
from beehave.ros.context import RosContext
ctx = RosContext()
ctx.start()
node = ctx.create_node("profile_talker")
pub = node.create_publisher(Odometry, "profile_check", 10)
end = time.monotonic() + float(__import__("sys").argv[1])
while time.monotonic() < end:
    pub.publish(Odometry())
    time.sleep(0.05)
ctx.shutdown()
"""
LISTENER = """
import sys, time
import rclpy
from nav_msgs.msg import Odometry
rclpy.init()
node = rclpy.create_node("plain_listener")
got = []
node.create_subscription(Odometry, "profile_check", got.append, 10)
end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < end and len(got) < 5:
    rclpy.spin_once(node, timeout_sec=0.05)
print("received", len(got), flush=True)
"""


def _env_without_profile() -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop(FASTDDS_PROFILE_ENV, None)
    return env


def _threads(mode: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", THREADS, mode], env=_env_without_profile(),
                         capture_output=True, text=True, timeout=wall_timeout(1.0), cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    return set(out.stdout.split())


def test_the_profile_turns_type_propagation_off_and_is_packaged() -> None:
    root = ET.parse(FASTDDS_PROFILE).getroot()
    ns = {"d": "http://www.eprosima.com"}
    participant = root.find("d:profiles/d:participant", ns)
    assert participant is not None and participant.get("is_default_profile") == "true"
    props = {p.findtext("d:name", namespaces=ns): p.findtext("d:value", namespaces=ns)
             for p in participant.iterfind(".//d:property", ns)}
    assert props == {"fastdds.type_propagation": "disabled"}
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert '"ros/fastdds_profile.xml"' in pyproject  # shipped with the wheel


def test_a_ros_context_runs_without_the_typelookup_service() -> None:
    plain = _threads("plain")
    ours = _threads("beehave")
    # The control: Fast DDS's defaults start the service (else this test proves nothing).
    assert any(t.startswith(TYPELOOKUP_THREADS) for t in plain), plain
    assert not any(t.startswith(TYPELOOKUP_THREADS) for t in ours), ours
    assert any(t.startswith("dds.") for t in ours), ours  # a participant was made


def test_a_ros_context_talks_to_a_plain_rclpy_program_with_the_defaults() -> None:
    env = _env_without_profile()
    bound_s = wall_timeout(0.5)
    talker = subprocess.Popen([sys.executable, "-c", TALKER, str(bound_s)], env=env, cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        listener = subprocess.run([sys.executable, "-c", LISTENER, str(bound_s)], env=env,
                                  capture_output=True, text=True, timeout=bound_s * 2)
    finally:
        talker.kill()
        talker.communicate()
    assert listener.returncode == 0, listener.stderr[-2000:]
    assert "received 5" in listener.stdout, (listener.stdout, listener.stderr[-2000:])


def test_a_profile_of_the_users_own_is_kept_and_a_missing_property_is_named(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(context, "_warned_profile", set())
    own = tmp_path / "mine.xml"
    own.write_text('<dds xmlns="http://www.eprosima.com"><profiles/></dds>')
    monkeypatch.setenv(FASTDDS_PROFILE_ENV, str(own))
    with caplog.at_level(logging.WARNING, logger="beehave.ros.context"):
        assert use_fastdds_profile() == str(own)
        use_fastdds_profile()  # said once per file
    assert os.environ[FASTDDS_PROFILE_ENV] == str(own)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "fastdds.type_propagation" in said[0] and str(own) in said[0]

    caplog.clear()
    fine = tmp_path / "fine.xml"
    fine.write_text(FASTDDS_PROFILE.read_text())
    monkeypatch.setenv(FASTDDS_PROFILE_ENV, str(fine))
    with caplog.at_level(logging.WARNING, logger="beehave.ros.context"):
        assert use_fastdds_profile() == str(fine)
    assert not caplog.records

    monkeypatch.delenv(FASTDDS_PROFILE_ENV)
    assert use_fastdds_profile() == str(FASTDDS_PROFILE)
    assert os.environ[FASTDDS_PROFILE_ENV] == str(FASTDDS_PROFILE)
