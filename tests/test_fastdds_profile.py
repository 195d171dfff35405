"""beehave's Fast DDS profile (beehave/fastdds.py, beehave/fastdds_profile.xml): a RosContext's
process runs without Fast DDS's TypeLookup service, whose reply thread crashed a robot process
of a stress run (SIGSEGV in TypeLookupManager::notify_callbacks, from its core file), and
still talks, both ways, to a plain rclpy program that keeps Fast DDS's defaults.

The processes are real: what runs is read from /proc (the threads Fast DDS names), what is
said is received over DDS."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from beehave import fastdds
from beehave.fastdds import (
    FASTDDS_PROFILE,
    FASTDDS_PROFILE_ENV,
    LEGACY_PROFILE_ENV,
    type_propagation,
    use_fastdds_profile,
)
from beehave.testing import wall_timeout

ROOT = Path(__file__).resolve().parent.parent
#: Fast DDS 3.2 names its TypeLookup service's threads dds.tls.requests.<n> and
#: dds.tls.replies.<n> (/proc shows the first 15 characters).
TYPELOOKUP_THREADS = "dds.tls."

# The first lines of every child: a node named argv[2], made by a RosContext ("beehave", its
# executor thread serving it) or by plain rclpy with Fast DDS's defaults ("plain").
NODE = """
import os, sys, time
if sys.argv[1] == "beehave":
    from beehave.ros.context import RosContext
    ctx = RosContext()
    ctx.start()
    node = ctx.create_node(sys.argv[2])
else:
    import rclpy
    rclpy.init()
    node = rclpy.create_node(sys.argv[2])


def done():
    if sys.argv[1] == "beehave":
        ctx.shutdown()
"""

# Prints the names of its process's threads.
THREADS = NODE + """
print(" ".join(sorted(open(f"/proc/self/task/{t}/comm").read().strip()
                      for t in os.listdir("/proc/self/task"))), flush=True)
done()
"""

# One side publishes nav_msgs/Odometry (a type the other process has not used before) for
# argv[3] seconds; the other listens until it has five or argv[3] seconds have passed.
TALKER = NODE + """
from nav_msgs.msg import Odometry
end = time.monotonic() + float(sys.argv[3])
pub = node.create_publisher(Odometry, "profile_check", 10)
while time.monotonic() < end:
    pub.publish(Odometry())
    time.sleep(0.05)
done()
"""
LISTENER = NODE + """
from nav_msgs.msg import Odometry
end = time.monotonic() + float(sys.argv[3])
got = []
node.create_subscription(Odometry, "profile_check", got.append, 10)
while time.monotonic() < end and len(got) < 5:
    if sys.argv[1] == "beehave":
        time.sleep(0.05)  # the context's executor thread takes the messages
    else:
        rclpy.spin_once(node, timeout_sec=0.05)
print("received", len(got), flush=True)
done()
"""


def _env_without_profile() -> dict[str, str]:
    """The suite's environment without its profile (conftest sets it for every process):
    what a plain rclpy program or a fresh RosContext starts with."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    env.pop(FASTDDS_PROFILE_ENV, None)
    env.pop(LEGACY_PROFILE_ENV, None)
    return env


def _threads(mode: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", THREADS, mode, "profile_probe"],
                         env=_env_without_profile(), capture_output=True, text=True,
                         timeout=wall_timeout(1.0), cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    return set(out.stdout.split())


def test_the_profile_turns_type_propagation_off_and_is_packaged() -> None:
    assert type_propagation(FASTDDS_PROFILE) == "disabled"
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "fastdds_profile.xml" in data["tool"]["setuptools"]["package-data"]["beehave"]


def test_a_ros_context_runs_without_the_typelookup_service() -> None:
    pytest.importorskip("rclpy")
    plain = _threads("plain")
    ours = _threads("beehave")
    # The control: Fast DDS's defaults start the service (else this test proves nothing).
    assert any(t.startswith(TYPELOOKUP_THREADS) for t in plain), plain
    assert not any(t.startswith(TYPELOOKUP_THREADS) for t in ours), ours
    assert any(t.startswith("dds.") for t in ours), ours  # a participant was made


@pytest.mark.parametrize("talker,listener", [("beehave", "plain"), ("plain", "beehave")])
def test_a_ros_context_and_a_plain_rclpy_program_with_the_defaults_hear_each_other(
        talker: str, listener: str) -> None:
    pytest.importorskip("rclpy")
    env = _env_without_profile()
    bound_s = wall_timeout(0.5)
    speaker = subprocess.Popen([sys.executable, "-c", TALKER, talker, "profile_talker",
                                str(bound_s)], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    try:
        heard = subprocess.run([sys.executable, "-c", LISTENER, listener, "profile_listener",
                                str(bound_s)],
                               env=env, cwd=ROOT, capture_output=True, text=True,
                               timeout=bound_s * 2)
    finally:
        speaker.terminate()
        try:
            said = speaker.communicate(timeout=wall_timeout(0.2))[0]
        except subprocess.TimeoutExpired:
            speaker.kill()
            said = speaker.communicate()[0]
    assert heard.returncode == 0, (heard.stderr[-2000:], said[-2000:])
    # (The executor thread of a RosContext may add one more before the loop looks.)
    count = int(heard.stdout.split()[-1]) if heard.stdout.startswith("received") else 0
    assert count >= 5, (heard.stdout, heard.stderr[-2000:], said[-2000:])


@pytest.fixture
def checked(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test sees its profiles checked afresh (the module warns once per file)."""
    monkeypatch.setattr(fastdds, "_checked", set())


def _default_profile(value: str | None, *, default: bool = True) -> str:
    prop = "" if value is None else (
        f"<propertiesPolicy><properties><property><name>fastdds.type_propagation</name>"
        f"<value>{value}</value></property></properties></propertiesPolicy>")
    flag = ' is_default_profile="true"' if default else ""
    return (f'<dds xmlns="http://www.eprosima.com"><profiles><participant profile_name="p"'
            f"{flag}><rtps>{prop}</rtps></participant></profiles></dds>")


def test_no_profile_of_the_users_gets_beehaves(checked: None) -> None:
    env: dict[str, str] = {}
    assert use_fastdds_profile(env) == FASTDDS_PROFILE
    assert env == {FASTDDS_PROFILE_ENV: str(FASTDDS_PROFILE)}


@pytest.mark.parametrize("variable", [FASTDDS_PROFILE_ENV, LEGACY_PROFILE_ENV])
@pytest.mark.parametrize("body,warned", [
    (_default_profile("disabled"), False),
    (_default_profile("registration_only"), False),
    (_default_profile(None), True),
    (_default_profile("enabled"), True),
    (_default_profile("disabled", default=False), True),  # not the default participant
    ("<dds><not closed", True),
])
def test_a_profile_of_the_users_own_is_kept_and_checked(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, checked: None, variable: str,
        body: str, warned: bool) -> None:
    own = tmp_path / "mine.xml"
    own.write_text(body)
    env = {variable: str(own)}
    with caplog.at_level(logging.WARNING, logger="beehave.fastdds"):
        assert use_fastdds_profile(env) == own
        use_fastdds_profile(env)  # said once per file
    assert env == {variable: str(own)}  # kept, and nothing added
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == int(warned), said
    if warned:
        assert str(own) in said[0]


def test_a_profile_in_the_working_directory_is_checked(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        checked: None) -> None:
    (tmp_path / "DEFAULT_FASTDDS_PROFILES.xml").write_text(_default_profile("enabled"))
    monkeypatch.chdir(tmp_path)
    with caplog.at_level(logging.WARNING, logger="beehave.fastdds"):
        use_fastdds_profile({"SKIP_DEFAULT_XML_FILE": "1"})  # Fast DDS skips it: so do we
        assert not caplog.records
        env: dict[str, str] = {}
        assert use_fastdds_profile(env) == FASTDDS_PROFILE
    assert env[FASTDDS_PROFILE_ENV] == str(FASTDDS_PROFILE)
    assert len(caplog.records) == 1 and "DEFAULT_FASTDDS_PROFILES.xml" in caplog.text
