"""The two managers as ROS 2 nodes, over real DDS (localhost, a domain of our own).

Observed the way any ROS 2 tool would: a plain rclpy node sets parameters, calls services
and listens to topics.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import Twist  # noqa: E402
from ros_probe import Probe, last_json  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from beehave import Action, Behavior, Logic  # noqa: E402
from beehave.config import load_config, parse_config  # noqa: E402
from beehave.errors import ConfigError, Interrupted  # noqa: E402
from beehave.robot import Robot  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, beehave_threads, wait_until, wall_timeout  # noqa: E402

HERE = Path(__file__).resolve().parent
CONFIG = HERE / "data" / "rosbot.yaml"
HIGH = "/rosbot/beehave_high_level"
LOW = "/rosbot/beehave_low_level"


@pytest.fixture
def probe() -> Iterator[Probe]:
    p = Probe()
    yield p
    p.close()


@pytest.fixture
def robot() -> Iterator[Robot]:
    before = set(beehave_threads())
    with Robot(load_config(CONFIG)) as r:
        yield r
    assert wait_until(lambda: not [t for t in beehave_threads() if t not in before]), \
        [t.name for t in beehave_threads() if t not in before]


def observe_switch(probe: Probe) -> dict[str, Any]:
    """Switch to patrol by parameter and collect what happens on the robot's topics."""
    cmd = probe.record(Twist, "/rosbot/cmd_vel")
    board = probe.record(String, "/rosbot/beehave/blackboard", latched=True)
    state = probe.record(String, "/rosbot/beehave/high_level/state", latched=True)
    assert probe.wait(lambda: bool(board) and bool(state)), "no latched state arrived"
    result = probe.set_param(HIGH, "behavior", "patrol")
    assert result.successful, result.reason
    assert probe.wait(lambda: any(m.linear.x == pytest.approx(0.3) for m in cmd))
    assert probe.wait(lambda: (last_json(state) or {}).get("behavior") == "patrol")

    def mode_is_driving() -> bool:
        return any(json.loads(m.data)["entries"].get("mode", {}).get("value") == "driving"
                   for m in list(board))

    assert probe.wait(mode_is_driving), "the low level did not follow Patrol.logic"
    stop = probe.trigger("/rosbot/beehave/stop")
    assert stop.success, stop.message
    assert probe.wait(lambda: (last_json(state) or {}).get("behavior") == "idle")
    assert probe.wait(lambda: bool(cmd) and cmd[-1].linear.x == 0.0), "no zero velocity"
    # The Cruise action's publisher is destroyed with the action.
    assert probe.wait(lambda: probe.publishers("/rosbot/cmd_vel") == 0)
    return {"state": last_json(state), "param": probe.get_param(HIGH, "behavior")}


def test_parameter_switch_state_blackboard_and_stop(robot: Robot, probe: Probe) -> None:
    seen = observe_switch(probe)
    assert seen["param"] == "idle"  # the parameter follows the running behaviour
    assert robot.high is not None and robot.high.current == "idle"
    # The high level's read-only mirror holds the low level's blackboard …
    assert wait_until(lambda: robot.high.blackboard.get("mode") == "driving")
    assert robot.high.blackboard.get("battery/percentage") is not None  # from the debug HAL
    # … and the low level knows what the high level does.
    assert robot.low is not None
    assert wait_until(lambda: robot.low.blackboard.get("high_level/behavior") == "idle")


def test_pause_and_resume_services_stop_the_wheels_and_drive_on(robot: Robot,
                                                                probe: Probe) -> None:
    cmd = probe.record(Twist, "/rosbot/cmd_vel")
    state = probe.record(String, "/rosbot/beehave/high_level/state", latched=True)
    assert probe.set_param(HIGH, "behavior", "patrol").successful
    assert probe.wait(lambda: any(m.linear.x == pytest.approx(0.3) for m in cmd))

    paused = probe.trigger("/rosbot/beehave/pause")
    assert paused.success and paused.message == "pausing", paused.message
    assert probe.wait(lambda: (last_json(state) or {}).get("paused") is True)
    assert last_json(state)["behavior"] == "patrol"  # the behaviour stays
    assert probe.wait(lambda: cmd[-1].linear.x == 0.0), "no zero velocity on pause"
    zero_at = len(cmd) - 1
    assert probe.trigger("/rosbot/beehave/pause").message == "already paused"
    # The low level sees it (a logic may show it) ...
    assert robot.low is not None
    assert wait_until(lambda: robot.low.blackboard.get("high_level/paused") is True)
    # ... and nothing drives while paused: every command after the zero is a zero.
    probe.wait(lambda: False, timeout_s=0.5)
    assert all(m.linear.x == 0.0 for m in list(cmd)[zero_at:])

    resumed = probe.trigger("/rosbot/beehave/resume")
    assert resumed.success and resumed.message == "resumed", resumed.message
    assert probe.wait(lambda: cmd[-1].linear.x == pytest.approx(0.3)), "did not drive on"
    assert probe.wait(lambda: (last_json(state) or {}).get("paused") is False)
    assert probe.trigger("/rosbot/beehave/resume").message == "was not paused"
    assert wait_until(lambda: robot.low.blackboard.get("high_level/paused") is False)


def test_unknown_or_mistyped_names_are_rejected_with_reasons(robot: Robot, probe: Probe) -> None:
    result = probe.set_param(HIGH, "behavior", "patroll")
    assert not result.successful
    assert "'patroll'" in result.reason and "idle, parked, patrol" in result.reason
    result = probe.set_param(HIGH, "behavior", 3)
    assert not result.successful and "must be a string" in result.reason
    result = probe.set_param(LOW, "logic", "disco")
    assert not result.successful and "driving, parked" in result.reason
    assert robot.high is not None and robot.high.current == "parked"


def test_logic_parameter_switches_the_low_level(robot: Robot, probe: Probe) -> None:
    assert robot.low is not None
    assert wait_until(lambda: robot.low.current == "parked")
    result = probe.set_param(LOW, "logic", "driving")
    assert result.successful, result.reason
    assert wait_until(lambda: robot.low.blackboard.get("mode") == "driving")
    assert wait_until(lambda: probe.get_param(LOW, "logic") == "driving")


def test_late_joiner_gets_the_blackboard(robot: Robot, probe: Probe) -> None:
    assert robot.low is not None
    assert wait_until(lambda: robot.low.blackboard.get("mode") == "parked")
    assert robot.high is not None
    assert wait_until(lambda: robot.high.blackboard.get("mode") == "parked")
    late = probe.record(String, "/rosbot/beehave/blackboard", latched=True)
    assert probe.wait(lambda: bool(late))
    assert json.loads(late[0].data)["schema"] == "beehave/blackboard/2"
    # The last message arrives at once (transient-local); a full snapshot follows within
    # snapshot_period_s (0.5 s here) even while the debug HAL keeps changing entries.
    snapshots = lambda: [json.loads(m.data) for m in list(late)  # noqa: E731
                         if json.loads(m.data)["kind"] == "snapshot"]
    # A late joiner gets the last BLACKBOARD_DEPTH messages, in order: the first snapshot
    # among them may be older than "mode"; one made after it must come.
    assert probe.wait(lambda: any(snap["entries"].get("mode", {}).get("value") == "parked"
                                  for snap in snapshots()))


def test_action_io_helpers_and_interrupted_wait(robot: Robot, probe: Probe) -> None:
    assert robot.high is not None
    waiting = threading.Event()
    outcome: list[Any] = []

    class WaitForGo(Action):
        action_type = "listening"

        def run(self) -> str:
            go = self.ros.latest(String, "go")
            waiting.set()
            msg = go.wait_for(lambda m: m.data == "go", timeout_s=30.0)
            return msg.data

    class Listener(Behavior):
        def run(self) -> None:
            first = self.start_action(WaitForGo())
            first.wait()
            outcome.append(first.result)
            second = self.start_action(WaitForGo())
            outcome.append(second)
            while self.sleep(1.0):
                pass

    robot.high.register("listener", Listener)
    robot.high.switch("listener")
    assert waiting.wait(WALL_TIMEOUT_S)
    pub = probe.node.create_publisher(String, "/rosbot/go", 10)
    assert probe.wait(lambda: pub.get_subscription_count() >= 1)
    pub.publish(String(data="wait"))
    pub.publish(String(data="go"))
    assert wait_until(lambda: len(outcome) == 2)
    assert outcome[0] == "go"
    second = outcome[1]
    robot.high.switch("parked")  # interrupts the second wait, which would take 30 s
    assert isinstance(second.error, Interrupted) or second.status.name == "INTERRUPTED"
    assert probe.wait(lambda: pub.get_subscription_count() == 0)  # its subscription is gone


def test_config_errors_name_file_and_key() -> None:
    with pytest.raises(ConfigError, match=r"namespace"):
        parse_config({"namespace": "9bad"}, source="r.yaml")
    with pytest.raises(ConfigError, match=r"default_behavior: 'tour' is not one of"):
        parse_config({"namespace": "r", "default_behavior": "tour"}, source="r.yaml")
    with pytest.raises(ConfigError, match=r"behaviors.x.class: cannot import module 'nope'"):
        Robot(parse_config({"namespace": "r",
                            "behaviors": {"x": {"class": "nope:X"}}}, source="r.yaml"))
    with pytest.raises(ConfigError, match=r"r.yaml: behaviors.x.class.*has no 'Nope'"):
        Robot(parse_config({"namespace": "r",
                            "behaviors": {"x": {"class": "rosbot:Nope"}}}, source="r.yaml"))
    with pytest.raises(ConfigError, match=r"behaviours: unknown key; valid keys: namespace"):
        parse_config({"namespace": "r", "behaviours": {}}, source="r.yaml")


def _spawn(*args: str) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(HERE)}
    return subprocess.Popen([sys.executable, "-m", "beehave.cli", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _ended(proc: subprocess.Popen[str]) -> str:
    """The output of ``proc`` (sent SIGTERM) once it ended. One that does not end within
    half the suite's bound is sent SIGABRT (its threads' stacks go to its output: the
    suite's PYTHONFAULTHANDLER), then SIGKILL: never left running (seen beside busy
    loops: one outlived a 20 s wait and the test)."""
    try:
        return proc.communicate(timeout=wall_timeout(0.5))[0]
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
    try:
        out = proc.communicate(timeout=wall_timeout(0.1))[0]
    except subprocess.TimeoutExpired:
        proc.kill()
        out = proc.communicate()[0]
    return f"(still running {wall_timeout(0.5):g} s after SIGTERM: aborted)\n{out}"


def test_two_processes_behave_like_one(probe: Probe) -> None:
    low = _spawn("run", str(CONFIG), "--only", "low")
    high = _spawn("run", str(CONFIG), "--only", "high")
    try:
        seen = observe_switch(probe)
        assert seen["param"] == "idle"
    finally:
        for proc in (high, low):
            proc.send_signal(signal.SIGTERM)
        outputs = [_ended(proc) for proc in (high, low)]
    for proc, out in zip((high, low), outputs, strict=True):
        assert proc.returncode == 0, out
        assert "stopped cleanly" in out, out


def test_plain_rclpy_client_process(robot: Robot) -> None:
    """A separate process, knowing nothing of beehave, switches and reads the blackboard."""
    script = HERE / "data" / "plain_client.py"
    proc = subprocess.run([sys.executable, str(script), "/rosbot"], capture_output=True,
                          text=True, timeout=60, env=dict(os.environ))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["set_behavior"] is True
    assert report["mode"] == "driving"
    assert robot.high is not None and robot.high.current == "patrol"


@pytest.mark.parametrize("payload", [
    "not json", "[1]", '{"schema": "beehave/blackboard/2"}',
    '{"schema": "beehave/blackboard/2", "kind": "changes", "seq": "x", "stamp": 1, '
    '"entries": {"a": {"value": 1}}}',
    '{"schema": "beehave/blackboard/2", "kind": "changes", "seq": 1, "stamp": 1, '
    '"entries": {"bad key/": {"value": 1}}}',
    '{"schema": "beehave/blackboard/2", "kind": "changes", "seq": 1, "stamp": 1, '
    '"entries": {"a": 5}}',
])
def test_malformed_blackboard_messages_are_refused_whole(robot: Robot, probe: Probe,
                                                         payload: str) -> None:
    assert robot.high is not None
    events: list[Any] = []
    robot.high.subscribe(events.append)
    from beehave.ros.bridge import LATCHED

    pub = probe.node.create_publisher(String, "/rosbot/beehave/blackboard", LATCHED)
    assert probe.wait(lambda: pub.get_subscription_count() >= 1)
    pub.publish(String(data=payload))
    assert wait_until(lambda: any(e.subject == "ros:beehave/blackboard" for e in events))
    assert robot.high.blackboard.get("a") is None  # nothing of it was applied


def test_service_call_from_an_action_is_interruptible(robot: Robot, probe: Probe) -> None:
    from std_srvs.srv import Trigger

    assert robot.high is not None
    calling = threading.Event()

    class CallsTheVoid(Action):
        action_type = "service"

        def run(self) -> Any:
            calling.set()
            return self.ros.call(Trigger, "nobody_serves_this", Trigger.Request(),
                                 timeout_s=30.0)

    class Caller(Behavior):
        def run(self) -> None:
            self.action = self.start_action(CallsTheVoid())
            while self.sleep(1.0):
                pass

    robot.high.register("caller", Caller)
    caller = robot.high.switch("caller")
    assert calling.wait(WALL_TIMEOUT_S)
    robot.high.switch("parked")  # well before the 30 s timeout
    action = caller.action  # type: ignore[attr-defined]
    assert action.status.name == "INTERRUPTED", (action.status, action.error)


def test_commanded_behavior_takes_commands_from_a_ros_topic(robot: Robot, probe: Probe) -> None:
    from rosbot import Cruise

    from behaviours.behaviors import CommandedBehavior, CommandQueue

    assert robot.high is not None
    queue = CommandQueue({"cruise": Cruise})
    robot.high.register("commanded", CommandedBehavior, queue=queue, topic="commands")
    robot.high.switch("commanded")
    cmd = probe.record(Twist, "/rosbot/cmd_vel")
    status = probe.record(String, "/rosbot/commands/status")
    pub = probe.node.create_publisher(String, "/rosbot/commands", 10)
    assert probe.wait(lambda: pub.get_subscription_count() >= 1)
    pub.publish(String(data='{"action": "cruise", "params": {"speed_mps": 0.1}, "id": "c1"}'))
    assert probe.wait(lambda: any(m.linear.x == pytest.approx(0.1) for m in cmd))
    pub.publish(String(data='{"action": "fly"}'))
    pub.publish(String(data='{"cancel": "all"}'))
    reports = lambda: [json.loads(m.data) for m in list(status)]  # noqa: E731
    assert probe.wait(lambda: any(r.get("id") == "c1" and r["status"] == "INTERRUPTED"
                                  for r in reports()))
    assert any(r["status"] == "REJECTED" and "unknown action 'fly'" in r["detail"]
               and "'cruise'" in r["detail"] for r in reports())
    assert probe.wait(lambda: cmd[-1].linear.x == 0.0)  # Cruise's safe state
    assert [r.received for r in queue.rejected] == ['{"action": "fly"}']


def test_non_finite_numbers_reach_the_mirror_as_numbers(robot: Robot, probe: Probe) -> None:
    """A laser that sees nothing in range says inf: `front_m < 0.5` must work on the mirror."""
    assert robot.low is not None and robot.high is not None
    board = probe.record(String, "/rosbot/beehave/blackboard", latched=True)
    robot.low.blackboard.set("laser/front_m", float("inf"))
    robot.low.blackboard.set("laser/ranges", [0.4, float("-inf"), float("nan")])
    mirror = robot.high.blackboard
    assert wait_until(lambda: mirror.get("laser/ranges") is not None)
    assert wait_until(lambda: mirror.get("laser/front_m") is not None)
    front = mirror.get("laser/front_m")
    assert isinstance(front, float) and not front < 0.5 and front == float("inf")
    ranges = mirror.get("laser/ranges")
    assert ranges[:2] == [0.4, float("-inf")] and ranges[2] != ranges[2]
    # On the wire it is strict JSON that any ROS 2 tool can parse.
    assert probe.wait(lambda: any("laser/front_m" in m.data for m in list(board)))
    for msg in list(board):
        json.loads(msg.data, parse_constant=lambda c: pytest.fail(f"non-JSON {c} sent"))


def test_repeated_service_calls_reuse_one_client_destroyed_with_the_owner(
        robot: Robot, probe: Probe) -> None:
    from std_srvs.srv import Trigger

    assert robot.high is not None
    node = robot.high.node
    served: list[int] = []

    def count(_req: Any, response: Any) -> Any:
        served.append(1)
        response.success = True
        return response

    probe.node.create_service(Trigger, "/rosbot/count", count)
    before = len(list(node.clients))

    class CallsOften(Action):
        action_type = "service"

        def run(self) -> int:
            for _ in range(100):
                assert self.ros.call(Trigger, "count", Trigger.Request(), timeout_s=10.0).success
            return len(list(node.clients)) - before

    class Caller(Behavior):
        def run(self) -> None:
            self.action = self.start_action(CallsOften())
            self.action.wait()
            while self.sleep(1.0):
                pass

    robot.high.register("caller", Caller)
    caller = robot.high.switch("caller")
    assert wait_until(lambda: hasattr(caller, "action"))
    action = caller.action  # type: ignore[attr-defined]
    assert wait_until(lambda: action.status.name == "SUCCEEDED"), action.error
    assert len(served) == 100
    assert action.result == 1
    assert len(list(node.clients)) == before  # destroyed when the action ended


def test_behavior_parameter_back_to_the_running_name_overrides_a_queued_switch(
        robot: Robot, probe: Probe) -> None:
    """patrol runs, `parked` is still queued, then the operator sets `patrol` again: the
    latest request wins, although it names the behaviour that runs right now."""
    from beehave import EventKind

    assert robot.high is not None
    hl = robot.high
    gate, held = threading.Event(), threading.Event()
    seen: list[Any] = []

    def hold_the_switch(event: Any) -> None:
        # Holds the switch thread after patrol started: later requests queue up behind it.
        seen.append(event)
        if (event.kind is EventKind.SWITCH_COMPLETED and event.subject == "patrol"
                and not held.is_set()):
            held.set()
            gate.wait(10)

    unsubscribe = hl.subscribe(hold_the_switch)
    try:
        assert probe.set_param(HIGH, "behavior", "patrol").successful
        assert held.wait(WALL_TIMEOUT_S) and hl.current == "patrol"
        assert probe.set_param(HIGH, "behavior", "parked").successful  # queued
        assert probe.set_param(HIGH, "behavior", "patrol").successful  # the latest
        released_at = len(seen)
    finally:
        gate.set()
    try:
        # Once a switch completed after the release, the last one must be to patrol
        # (the bug: the second request was skipped and parked stayed).
        assert wait_until(lambda: any(e.kind is EventKind.SWITCH_COMPLETED
                                      for e in list(seen)[released_at:])
                          and hl.current == "patrol"), hl.current
    finally:
        unsubscribe()
    assert wait_until(lambda: probe.get_param(HIGH, "behavior") == "patrol")


# -- the logic parameter (issue 9, items 11 and 14) --------------------------------------------

class _Forever(Logic):
    async def run(self) -> None:
        import asyncio

        await asyncio.sleep(3600)


class _Brief(Logic):
    """Ends on its own: the low level falls back to its default logic."""

    async def run(self) -> None:
        import asyncio

        await asyncio.sleep(0.05)


class _HoldsTheLoop(Logic):
    """The mistake issue 9 describes: a blocking wait inside a coroutine. It blocks until
    the test releases it (10 s at most), so a slow host cannot let it go too early."""

    blocking = threading.Event()
    release = threading.Event()

    async def run(self) -> None:
        import asyncio

        await asyncio.sleep(0)
        _HoldsTheLoop.blocking.set()
        _HoldsTheLoop.release.wait(10.0)
        await asyncio.sleep(3600)


@pytest.fixture
def low_node(probe: Probe) -> Iterator[tuple[Any, Any]]:
    """A low level on a node of its own (namespace /llp), with a short switch bound."""
    from beehave.lowlevel import LowLevelBehaviorManager
    from beehave.ros.bridge import LowLevelBridge
    from beehave.ros.context import RosContext

    ros = RosContext()
    node = ros.create_node("beehave_low_level", namespace="llp")
    ll = LowLevelBehaviorManager(default="parked", stop_timeout_s=0.3)
    for name, cls in (("parked", _Forever), ("driving", _Forever), ("brief", _Brief),
                      ("hog", _HoldsTheLoop)):
        ll.register(name, cls)
    ros.start()
    with ll:
        bridge = LowLevelBridge(ll, node, switch_timeout_s=0.5)
        try:
            yield ll, bridge
        finally:
            bridge.destroy()
    ros.shutdown()


LLP = "/llp/beehave_low_level"


def test_logic_parameter_shows_the_default_after_a_logic_ends_on_its_own(
        low_node: tuple[Any, Any], probe: Probe) -> None:
    ll, _ = low_node
    result = probe.set_param(LLP, "logic", "brief")
    assert result.successful, result.reason
    assert wait_until(lambda: ll.current == "parked" and ll.history
                      and ll.history[-1].name == "brief")
    assert wait_until(lambda: probe.get_param(LLP, "logic") == "parked"), \
        probe.get_param(LLP, "logic")


def test_logic_parameter_fails_with_a_reason_when_the_loop_is_blocked(
        low_node: tuple[Any, Any], probe: Probe) -> None:
    ll, _ = low_node
    _HoldsTheLoop.blocking.clear()
    _HoldsTheLoop.release.clear()
    try:
        assert probe.set_param(LLP, "logic", "hog").successful
        assert _HoldsTheLoop.blocking.wait(WALL_TIMEOUT_S)
        result = probe.set_param(LLP, "logic", "driving")  # the hog holds the loop
    finally:
        _HoldsTheLoop.release.set()
    assert not result.successful
    assert "'driving'" in result.reason and "block" in result.reason, result.reason
    # Nothing was switched behind the caller's back once the loop is free again.
    assert wait_until(lambda: not ll.snapshot()["loop_blocked"])
    assert ll.call(_noop()) is None
    assert ll.current == "hog"
    assert probe.get_param(LLP, "logic") == "hog"


async def _noop() -> None:
    return None


# -- engine state on the state topic (issue 9, "Also wanted") ----------------------------------

class _Docking(Behavior):
    """Stands in for a behaviour driven by a state machine: its snapshot has an engine."""

    def run(self) -> None:
        self.start_behavior(_Ticking())
        while self.sleep(1.0):
            pass

    def _snapshot(self) -> dict[str, Any]:
        snap = super()._snapshot()
        snap["engine"] = {"kind": "state_machine", "state": "approach",
                          "states": ["approach", "dock"], "since_s": float("inf")}
        return snap


class _Ticking(Behavior):
    def run(self) -> None:
        while self.sleep(1.0):
            pass

    def _snapshot(self) -> dict[str, Any]:
        snap = super()._snapshot()
        snap["engine"] = {"kind": "behaviour_tree",
                          "nodes": [{"name": "root", "status": "RUNNING"}]}
        return snap


def test_state_topic_carries_the_engines_of_the_running_tree(robot: Robot,
                                                             probe: Probe) -> None:
    assert robot.high is not None and robot.low is not None
    state = probe.record(String, "/rosbot/beehave/high_level/state", latched=True)
    robot.high.register("docking", _Docking)
    robot.high.switch("docking")

    def engines() -> list[dict[str, Any]]:
        last = last_json(state) or {}
        return last.get("engines", []) if last.get("behavior") == "docking" else []

    assert probe.wait(lambda: len(engines()) == 2), last_json(state)
    assert (last_json(state) or {})["schema"] == "beehave/high_level/state/2"
    by_path = {e["path"]: e for e in engines()}
    assert by_path["docking"]["kind"] == "state_machine"
    assert by_path["docking"]["state"] == "approach"
    assert by_path["docking"]["since_s"] == {"$float": "inf"}  # strict JSON
    assert by_path["docking/_Ticking"]["nodes"] == [{"name": "root", "status": "RUNNING"}]
    # The low level accepts the new schema and shows it to logics.
    assert wait_until(lambda: len(robot.low.blackboard.get("high_level/engines") or []) == 2)
    robot.high.switch("parked")
    assert probe.wait(lambda: (last_json(state) or {}).get("behavior") == "parked"
                      and last_json(state)["engines"] == [])  # type: ignore[index]


def test_earlier_schemas_are_still_read() -> None:
    from beehave.ros.bridge import BlackboardMessage, StateMessage

    old_state = StateMessage.model_validate_json(
        '{"schema": "beehave/high_level/state/1", "stamp": 1, "behavior": "idle"}')
    assert old_state.engines == []
    old_board = BlackboardMessage.model_validate_json(
        '{"schema": "beehave/blackboard/1", "kind": "changes", "seq": 1, "stamp": 1, '
        '"entries": {"a": {"value": 1}}}')
    assert old_board.entries["a"].value == 1


# -- the mirror loses nothing (issue 9, mirror latency work) -----------------------------------

def test_the_mirror_receives_every_change_message_in_order() -> None:
    """`changes` messages are deltas: none may be replaced in a queue before the mirror
    took it (with depth 1, about a third were at 1 kHz and the mirror kept old values)."""
    import asyncio

    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.lowlevel import LowLevelBehaviorManager
    from beehave.ros.bridge import HighLevelBridge, LowLevelBridge
    from beehave.ros.context import RosContext

    high_ros, low_ros = RosContext(), RosContext()
    hl = HighLevelBehaviorManager()
    high = HighLevelBridge(hl, high_ros.create_node("beehave_high_level", namespace="mirr"))
    seen: list[int] = []
    hl.blackboard.subscribe("count", lambda c: seen.append(c.value))
    low_node = low_ros.create_node("beehave_low_level", namespace="mirr")
    high_ros.start()
    low_ros.start()
    try:
        with LowLevelBehaviorManager() as ll:
            low = LowLevelBridge(ll, low_node)
            try:
                ll.blackboard.set("count", -1)
                assert wait_until(lambda: hl.blackboard.get("count") == -1)
                seen.clear()

                async def count() -> None:
                    for i in range(500):  # one message each: 1 kHz against a 2 kHz cap
                        ll.blackboard.set("count", i)
                        await asyncio.sleep(0.001)

                ll.call(count())
                assert wait_until(lambda: hl.blackboard.get("count") == 499)
            finally:
                low.destroy()
        assert seen == list(range(500)), f"{500 - len(seen)} changes lost"
        assert high.missed_messages == 0
    finally:
        high.destroy()
        hl.shutdown()
        low_ros.shutdown()
        high_ros.shutdown()


def test_an_engine_state_change_is_published_without_a_lifecycle_event(probe: Probe) -> None:
    """A state machine's transition starts or ends nothing: it must still reach the topic
    (here the heartbeat is a minute away)."""
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.ros.bridge import HighLevelBridge
    from beehave.ros.context import RosContext

    class Machine(Behavior):
        state = "approach"

        def run(self) -> None:
            while self.sleep(1.0):
                pass

        def _snapshot(self) -> dict[str, Any]:
            snap = super()._snapshot()
            snap["engine"] = {"kind": "state_machine", "state": self.state}
            return snap

    ros = RosContext()
    node = ros.create_node("beehave_high_level", namespace="engst")
    hl = HighLevelBehaviorManager(node=node, stop_timeout_s=0.3)
    bridge = HighLevelBridge(hl, node, state_period_s=60.0)
    ros.start()
    try:
        hl.register("machine", Machine)
        hl.start()
        machine = hl.switch("machine")
        state = probe.record(String, "/engst/beehave/high_level/state", latched=True)

        def engine_state() -> str | None:
            engines = (last_json(state) or {}).get("engines") or [{}]
            return engines[0].get("state")

        assert probe.wait(lambda: engine_state() == "approach")
        machine.state = "dock"  # type: ignore[attr-defined]
        assert probe.wait(lambda: engine_state() == "dock")
    finally:
        bridge.destroy()
        hl.shutdown()
        ros.shutdown()


def test_logic_parameter_set_inside_the_loop_is_refused_not_blocking(
        low_node: tuple[Any, Any]) -> None:
    from rclpy.parameter import Parameter

    ll, bridge = low_node

    async def set_from_a_logic() -> Any:
        return bridge.node.set_parameters([Parameter("logic", value="driving")])[0]

    result = ll.call(set_from_a_logic())
    assert not result.successful and "switch_async('driving')" in result.reason
    assert ll.current == "parked"


# -- review of issue 9 -------------------------------------------------------------------------

def _board_message(seq: int, kind: str, entries: dict[str, Any]) -> String:
    return String(data=json.dumps({"schema": "beehave/blackboard/2", "kind": kind, "seq": seq,
                                   "stamp": 1.0, "entries": entries, "removed": []}))


def test_mirror_stale_or_nan_entries_are_no_change_at_every_snapshot() -> None:
    """A stale entry never reads as fresh on the mirror (it was set, then marked stale,
    at each snapshot), and an unchanged NaN is not notified again."""
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.ros.bridge import HighLevelBridge
    from beehave.ros.context import RosContext

    ros = RosContext()
    hl = HighLevelBehaviorManager()
    bridge = HighLevelBridge(hl, ros.create_node("beehave_high_level", namespace="mstale"))
    try:
        seen: list[tuple[str, Any, bool]] = []
        hl.blackboard.subscribe("**", lambda c: seen.append((c.key, c.value, c.stale)))
        battery = {"value": 54.0, "stale": True, "writer": "hal:battery"}
        laser = {"value": {"$float": "nan"}, "writer": "hal:laser"}
        for seq in (1, 2, 3):
            bridge._on_blackboard(_board_message(seq, "snapshot", {
                "battery/percentage": battery, "laser/front_m": laser}))
        assert [(k, s) for k, _, s in seen] == [("battery/percentage", True),
                                                ("laser/front_m", False)], seen
        assert hl.blackboard.is_stale("battery/percentage")
    finally:
        bridge.destroy()
        hl.shutdown()
        ros.shutdown()


class _Loops(Behavior):
    def run(self) -> None:
        while self.sleep(0.05):
            pass


class _Broken(Behavior):
    def __init__(self) -> None:
        raise RuntimeError("typo in the constructor")

    def run(self) -> None:  # pragma: no cover - never constructed
        pass


def test_behavior_parameter_latest_request_wins_after_a_rejected_one() -> None:
    """patrol runs, parked is queued, `broken` is refused by its constructor, then patrol
    is set again: patrol must win (the rejection used to make the bridge forget that
    parked was queued, so the last set was skipped as "already running")."""
    from rclpy.parameter import Parameter

    from beehave import EventKind
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.ros.bridge import HighLevelBridge
    from beehave.ros.context import RosContext

    ros = RosContext()
    node = ros.create_node("beehave_high_level", namespace="rejw")
    ros.start()
    hl = HighLevelBehaviorManager(node=node, stop_timeout_s=0.3)
    hl.register("patrol", _Loops)
    hl.register("parked", _Loops)
    hl.register("broken", _Broken)
    hl.start()
    bridge = HighLevelBridge(hl, node)
    gate, held = threading.Event(), threading.Event()
    ended: list[str] = []

    def hold(event: Any) -> None:
        if event.kind is EventKind.SWITCH_REJECTED or (
                event.kind is EventKind.SWITCH_COMPLETED and event.subject != "patrol"):
            ended.append(event.kind.name)
        if (event.kind is EventKind.SWITCH_COMPLETED and event.subject == "patrol"
                and not held.is_set()):
            held.set()
            gate.wait(10)  # later requests queue up behind this one

    unsubscribe = hl.subscribe(hold)

    def set_behavior(name: str) -> Any:
        return node.set_parameters([Parameter("behavior", value=name)])[0]

    try:
        assert set_behavior("patrol").successful
        assert held.wait(WALL_TIMEOUT_S)
        assert set_behavior("parked").successful
        set_behavior("broken")  # refused: now or when processed
        assert set_behavior("patrol").successful
        assert hl.requested == "patrol"
        gate.set()
        assert wait_until(lambda: hl.requested is None)
        assert hl.current == "patrol", (hl.current, ended)
    finally:
        gate.set()
        unsubscribe()
        bridge.destroy()
        hl.shutdown()
        ros.shutdown()


def test_destroyed_bridges_leave_no_parameter_behind_and_a_new_bridge_fits() -> None:
    """destroy() removes "all of it": setting `behavior` / `logic` on the node afterwards
    switches nothing, and another bridge can be put on the same node."""
    from rclpy.exceptions import ParameterNotDeclaredException
    from rclpy.parameter import Parameter

    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.lowlevel import LowLevelBehaviorManager
    from beehave.ros.bridge import HighLevelBridge, LowLevelBridge
    from beehave.ros.context import RosContext

    ros = RosContext()
    high_node = ros.create_node("beehave_high_level", namespace="dparm")
    low_node = ros.create_node("beehave_low_level", namespace="dparm")
    ros.start()
    hl = HighLevelBehaviorManager(stop_timeout_s=0.3)
    hl.register("patrol", _Loops)
    hl.start()
    ll = LowLevelBehaviorManager(default="parked", stop_timeout_s=0.3)
    ll.register("parked", _Forever)
    ll.register("driving", _Forever)
    try:
        with ll:
            HighLevelBridge(hl, high_node).destroy()
            LowLevelBridge(ll, low_node, switch_timeout_s=0.5).destroy()
            assert hl.node is None
            for node, name, value in ((high_node, "behavior", "patrol"),
                                      (low_node, "logic", "driving")):
                with pytest.raises(ParameterNotDeclaredException):
                    node.set_parameters([Parameter(name, value=value)])
            assert hl.current == "idle" and ll.current == "parked"
            again = HighLevelBridge(hl, high_node)
            try:
                assert high_node.set_parameters(
                    [Parameter("behavior", value="patrol")])[0].successful
                assert wait_until(lambda: hl.current == "patrol")
            finally:
                again.destroy()
    finally:
        hl.shutdown()
        ros.shutdown()


def test_an_engine_that_appears_after_the_start_is_published() -> None:
    """A behaviour that prepares (builds its machine, loads a map) before driving its
    engine is published with no engines at its start; its engine must still follow."""
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.ros.bridge import HighLevelBridge
    from beehave.ros.context import RosContext

    ready = threading.Event()

    class Preparing(Behavior):
        def run(self) -> None:
            while self.sleep(1.0):
                pass

        def _snapshot(self) -> dict[str, Any]:
            snap = super()._snapshot()
            if ready.is_set():
                snap["engine"] = {"kind": "state_machine", "state": "approach"}
            return snap

    ros = RosContext()
    node = ros.create_node("beehave_high_level", namespace="engla")
    hl = HighLevelBehaviorManager(node=node, stop_timeout_s=0.3)
    bridge = HighLevelBridge(hl, node, state_period_s=60.0)
    ros.start()
    probe = Probe()
    try:
        hl.register("preparing", Preparing)
        hl.start()
        state = probe.record(String, "/engla/beehave/high_level/state", latched=True)
        hl.switch("preparing")
        assert probe.wait(lambda: (last_json(state) or {}).get("behavior") == "preparing")
        assert (last_json(state) or {}).get("engines") == []
        ready.set()
        assert probe.wait(lambda: [e.get("state") for e in
                                   (last_json(state) or {}).get("engines", [])] == ["approach"]
                          ), last_json(state)
    finally:
        probe.close()
        bridge.destroy()
        hl.shutdown()
        ros.shutdown()


class _StopsMotors(Logic):
    """Asks a ROS service to stop the motors when it ends: its stop needs a ROS callback."""

    stop_acked: bool | None = None

    async def run(self) -> None:
        import asyncio

        from std_srvs.srv import Trigger

        base = await self.hal("base")
        try:
            await asyncio.sleep(3600)
        finally:
            response = await base.call(Trigger, "stop_motors", Trigger.Request(), timeout_s=3.0)
            type(self).stop_acked = response.success


def test_logic_parameter_switch_whose_stop_needs_a_ros_callback(probe: Probe) -> None:
    """A remote `ros2 param set logic` is served in the executor thread; waiting there for
    the whole switch starved the old logic's service call in its `finally` (it timed out,
    the logic went STUCK, the set was refused)."""
    from std_srvs.srv import Trigger

    from beehave.lowlevel import LowLevelBehaviorManager
    from beehave.ros.bridge import LowLevelBridge
    from beehave.ros.context import RosContext
    from beehave.ros.hal import RosHAL

    class Base(RosHAL):
        name = "base"

    def stop_motors(_request: Any, response: Any) -> Any:
        response.success = True
        return response

    probe.node.create_service(Trigger, "/llsvc/stop_motors", stop_motors)
    ros = RosContext()
    node = ros.create_node("beehave_low_level", namespace="llsvc")
    ll = LowLevelBehaviorManager(default="parked", stop_timeout_s=0.5)
    ll.hals.node = node
    ll.hals.register(Base)
    ll.register("parked", _Forever)
    ll.register("drive", _StopsMotors)
    stuck: list[Any] = []
    ll.subscribe(lambda e: stuck.append(e) if e.kind.name == "STUCK" else None)
    ros.start()
    try:
        with ll:
            bridge = LowLevelBridge(ll, node, switch_timeout_s=2.0)
            try:
                ll.switch("drive")
                result = probe.set_param("/llsvc/beehave_low_level", "logic", "parked")
                assert result.successful, result.reason
                assert wait_until(lambda: ll.current == "parked")
                assert _StopsMotors.stop_acked is True
                assert stuck == []
                assert wait_until(lambda: probe.get_param("/llsvc/beehave_low_level",
                                                          "logic") == "parked")
            finally:
                bridge.destroy()
    finally:
        ros.shutdown()


@pytest.mark.parametrize("bridge, option, value", [
    ("high", "state_rate_hz", 0), ("high", "engine_rate_hz", float("nan")),
    ("high", "state_period_s", -1.0), ("low", "blackboard_rate_hz", 0.0),
    ("low", "snapshot_period_s", float("inf")), ("low", "settle_s", float("nan"))])
def test_bridges_refuse_rates_and_periods_that_are_not_positive_numbers(
        bridge: str, option: str, value: float) -> None:
    from beehave.highlevel import HighLevelBehaviorManager
    from beehave.lowlevel import LowLevelBehaviorManager
    from beehave.ros.bridge import HighLevelBridge, LowLevelBridge
    from beehave.ros.context import RosContext

    ros = RosContext()
    node = ros.create_node("bad_rates")
    try:
        with pytest.raises(ConfigError, match=rf"{option} must be .* got {value!r}"):
            if bridge == "high":
                HighLevelBridge(HighLevelBehaviorManager(), node, **{option: value})
            else:
                LowLevelBridge(LowLevelBehaviorManager(), node, **{option: value})
        assert not node.has_parameter("behavior") and not node.has_parameter("logic")
    finally:
        ros.shutdown()


LEFT_RUNNING = """
import time
from std_msgs.msg import String
from beehave.ros.context import RosContext
ros = RosContext()
node = ros.create_node("left_running")
ros.start()
node.create_subscription(String, "left_running", lambda msg: None, 10)
publisher = node.create_publisher(String, "left_running", 10)
for _ in range(50):
    publisher.publish(String(data="still talking"))
    time.sleep(0.001)
print("end of script", flush=True)
"""


def test_a_context_left_running_at_exit_is_shut_down_not_aborted() -> None:
    """A script that never called ``shutdown()`` ended with SIGABRT (6 of 6 here): its
    executor thread, back from rclpy's wait during the interpreter's finalization, was ended
    by pthread_exit, whose unwinding through rclpy's C++ frames called std::terminate."""
    done = subprocess.run([sys.executable, "-c", LEFT_RUNNING], capture_output=True,
                          text=True, timeout=WALL_TIMEOUT_S, stdin=subprocess.DEVNULL)
    assert done.returncode == 0, (done.returncode, done.stderr[-3000:])
    assert "end of script" in done.stdout


STUCK_AT_EXIT = """
import threading
from std_msgs.msg import String
from beehave.ros.context import RosContext
ros = RosContext()
node = ros.create_node("stuck_at_exit")
ros.start()
entered = threading.Event()

def blocks_for_ever(msg):
    entered.set()
    threading.Event().wait()

node.create_subscription(String, "stuck_at_exit", blocks_for_ever, 10)
publisher = node.create_publisher(String, "stuck_at_exit", 10)
while not entered.is_set():
    publisher.publish(String(data="block"))
    entered.wait(0.05)
print("end of script", flush=True)
"""


def test_a_context_left_in_a_callback_that_never_returns_does_not_hang_the_exit() -> None:
    """The exit's shutdown waits EXIT_JOIN_S for the executor thread, not for ever, and
    says where it is stuck."""
    done = subprocess.run([sys.executable, "-c", STUCK_AT_EXIT], capture_output=True,
                          text=True, timeout=WALL_TIMEOUT_S, stdin=subprocess.DEVNULL)
    assert "end of script" in done.stdout, done.stderr[-3000:]
    assert "still in a callback" in done.stderr and "blocks_for_ever" in done.stderr, \
        done.stderr[-3000:]
