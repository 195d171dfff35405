"""``beehave/execute_behavior``: behaviours run as goals, from a plain rclpy client.

The client below is what any ROS 2 program would write from docs/ros.md ("Behaviours as
goals"): its own rclpy context and executor, std_msgs/String with the documented JSON, the
standard action_msgs/srv/CancelGoal; nothing of beehave on the wire. The robots are real:
both managers as ROS 2 nodes over DDS, the Debug HAL under the low level.
"""

from __future__ import annotations

import json
import threading
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

pytest.importorskip("rclpy")

import rclpy  # noqa: E402
from action_msgs.srv import CancelGoal  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from beehave import Behavior  # noqa: E402
from beehave.config import parse_config  # noqa: E402
from beehave.robot import Robot  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_ros_execute_behavior")

GOAL_SCHEMA = "beehave/execute_behavior/goal/1"
TERMINAL = ("SUCCEEDED", "CANCELED", "ABORTED", "REJECTED")


class Countdown(Behavior):
    """Counts ``steps`` short sleeps and returns how many it counted."""

    def __init__(self, steps: int = 3) -> None:
        self.steps = steps

    def run(self) -> dict[str, int]:
        for _ in range(self.steps):
            self.sleep(0.02)
        return {"counted": self.steps}


class Broken(Behavior):
    def run(self) -> None:
        raise RuntimeError("wheel jammed")


def _config(namespace: str, second_goal: str | None) -> dict[str, Any]:
    ros: dict[str, Any] = {"state_period_s": 0.5}
    if second_goal is not None:
        ros["second_goal"] = second_goal
    return {
        "namespace": namespace, "stop_timeout_s": 1.0,
        "behaviors": {"patrol": {"class": "rosbot:Patrol", "params": {"speed_mps": 0.3}},
                      "parked": {"class": "rosbot:Parked"},
                      "countdown": {"class": "test_ros_execute_behavior:Countdown"},
                      "broken": {"class": "test_ros_execute_behavior:Broken"}},
        "default_behavior": "parked",
        "logics": {"parked": {"class": "rosbot:Announce", "params": {"mode": "parked"}},
                   "driving": {"class": "rosbot:Announce", "params": {"mode": "driving"}}},
        "default_logic": "parked", "hals": ["debug"], "ros": ros}


class GoalClient:
    """A plain rclpy client of one robot's ``beehave/execute_behavior``."""

    def __init__(self, namespace: str) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"goal_client_{namespace}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        self.statuses: list[dict[str, Any]] = []
        self.feedback: list[dict[str, Any]] = []
        latched = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        base = f"/{namespace}/beehave/execute_behavior"
        self.status_sub = self.node.create_subscription(
            String, f"{base}/status", lambda m: self._keep(self.statuses, m), latched)
        self.feedback_sub = self.node.create_subscription(
            String, f"{base}/feedback", lambda m: self._keep(self.feedback, m), 10)
        self.goal_pub = self.node.create_publisher(String, f"{base}/goal", 10)
        self.cancel_client = self.node.create_client(CancelGoal, f"{base}/cancel")
        self.stop_client = self.node.create_client(Trigger, f"/{namespace}/beehave/stop")
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()
        assert wait_until(lambda: self.goal_pub.get_subscription_count() > 0
                          and self.status_sub.get_publisher_count() > 0), "no server"

    def _spin(self) -> None:
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # the context went away under us: done
                return

    def _keep(self, box: list[dict[str, Any]], msg: String) -> None:
        with self.lock:
            box.append(json.loads(msg.data))

    def send(self, behavior: Any, params: Any = None, **extra: Any) -> str:
        goal_id = str(uuid.uuid4())
        goal = {"schema": GOAL_SCHEMA, "goal_id": goal_id, "behavior": behavior, **extra}
        if params is not None:
            goal["params"] = params
        self.send_raw(json.dumps(goal))
        return goal_id

    def send_raw(self, text: str) -> None:
        self.goal_pub.publish(String(data=text))

    def of(self, goal_id: str) -> list[dict[str, Any]]:
        with self.lock:
            return [s for s in self.statuses if s["goal_id"] == goal_id]

    def wait_status(self, goal_id: str, *wanted: str) -> dict[str, Any]:
        found: list[dict[str, Any]] = []

        def seen() -> bool:
            found[:] = [s for s in self.of(goal_id) if s["status"] in wanted]
            return bool(found)

        assert wait_until(seen), f"goal {goal_id}: no {wanted}; got {self.of(goal_id)}"
        return found[0]

    def wait_end(self, goal_id: str) -> dict[str, Any]:
        return self.wait_status(goal_id, *TERMINAL)

    def _call(self, client: Any, request: Any) -> Any:
        assert client.wait_for_service(timeout_sec=WALL_TIMEOUT_S)
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        assert done.wait(WALL_TIMEOUT_S), "no answer"
        return future.result()

    def cancel(self, goal_id: str | None) -> Any:
        """CancelGoal for ``goal_id`` (None: every goal, the zero UUID)."""
        request = CancelGoal.Request()
        raw = uuid.UUID(int=0) if goal_id is None else uuid.UUID(goal_id)
        request.goal_info.goal_id.uuid = list(raw.bytes)
        return self._call(self.cancel_client, request)

    def stop(self) -> Any:
        return self._call(self.stop_client, Trigger.Request())

    def close(self) -> None:
        self.context.try_shutdown()
        self.thread.join(WALL_TIMEOUT_S)
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture(scope="module")
def robots() -> Iterator[dict[str, tuple[Robot, GoalClient]]]:
    out: dict[str, tuple[Robot, GoalClient]] = {}
    try:
        for name, policy in (("exec_reject", None), ("exec_preempt", "preempt")):
            robot = Robot(parse_config(_config(name, policy), source=f"{name}.yaml"))
            robot.start()
            out[name] = (robot, GoalClient(name))
        yield out
    finally:
        for robot, client in out.values():
            client.close()
            robot.shutdown()


@pytest.fixture
def reject(robots: dict[str, tuple[Robot, GoalClient]]) -> Iterator[tuple[Robot, GoalClient]]:
    yield robots["exec_reject"]
    _settle(*robots["exec_reject"])


@pytest.fixture
def preempt(robots: dict[str, tuple[Robot, GoalClient]]) -> Iterator[tuple[Robot, GoalClient]]:
    yield robots["exec_preempt"]
    _settle(*robots["exec_preempt"])


def _settle(robot: Robot, client: GoalClient) -> None:
    """Leave the robot with no goal executing, for the next test."""
    client.stop()
    assert robot.high is not None
    assert wait_until(lambda: robot.high is not None and robot.high.current == "idle")
    last = {s["goal_id"]: s["status"] for s in list(client.statuses) if s["goal_id"]}
    assert wait_until(lambda: all(
        any(s["status"] in TERMINAL for s in client.of(gid)) for gid in last))


def test_goal_executes_with_feedback_and_cancel_switches_to_idle(reject: Any) -> None:
    robot, client = reject
    gid = client.send("patrol", {"speed_mps": 0.4})
    accepted = client.wait_status(gid, "ACCEPTED")
    assert accepted["behavior"] == "patrol"
    client.wait_status(gid, "EXECUTING")
    # Feedback: the engine state and the running actions, as the state topic has them.
    assert wait_until(lambda: any(
        f["goal_id"] == gid and any(r["path"] == "patrol/Cruise"
                                    and r["action_type"] == "driving"
                                    for r in f["state"]["running"])
        for f in list(client.feedback)))
    fb = next(f for f in list(client.feedback) if f["goal_id"] == gid)
    assert fb["behavior"] == "patrol" and fb["state"]["behavior"] == "patrol"
    assert fb["state"]["locks"] == {} or "driving" in fb["state"]["locks"]
    assert robot.high.top.speed_mps == 0.4  # the goal's parameters reached the behaviour

    answer = client.cancel(gid)
    assert answer.return_code == CancelGoal.Response.ERROR_NONE
    assert [bytes(g.goal_id.uuid) for g in answer.goals_canceling] == [uuid.UUID(gid).bytes]
    client.wait_status(gid, "CANCELING")
    end = client.wait_end(gid)
    assert end["status"] == "CANCELED", end
    assert end["result"]["status"] == "INTERRUPTED"
    assert wait_until(lambda: robot.high.current == "idle")
    # A terminated goal cannot be cancelled again; an unknown one is unknown.
    assert client.cancel(gid).return_code == CancelGoal.Response.ERROR_GOAL_TERMINATED
    assert client.cancel(str(uuid.uuid4())).return_code == \
        CancelGoal.Response.ERROR_UNKNOWN_GOAL_ID


def test_result_is_how_the_behaviour_ended(reject: Any) -> None:
    _, client = reject
    gid = client.send("countdown", {"steps": 4})
    end = client.wait_end(gid)
    assert end["status"] == "SUCCEEDED", end
    assert end["result"]["status"] == "SUCCEEDED"
    assert end["result"]["value"] == {"counted": 4}
    assert end["result"]["error"] is None

    gid = client.send("broken")
    end = client.wait_end(gid)
    assert end["status"] == "ABORTED", end
    assert end["result"]["status"] == "FAILED"
    assert "wheel jammed" in end["result"]["error"]
    assert "wheel jammed" in end["message"]


def test_bad_goals_are_rejected_naming_the_valid_choices(reject: Any) -> None:
    robot, client = reject
    before = robot.high.current
    gid = client.send("patroll")
    end = client.wait_end(gid)
    assert end["status"] == "REJECTED"
    for name in ("broken", "countdown", "idle", "parked", "patrol"):
        assert repr(name) in end["message"], end["message"]

    gid = client.send("patrol", {"speed_mps": "fast"})
    end = client.wait_end(gid)
    assert end["status"] == "REJECTED"
    assert "speed_mps" in end["message"] and "float" in end["message"], end["message"]

    gid = client.send("patrol", ["not", "a", "mapping"])
    assert client.wait_end(gid)["status"] == "REJECTED"

    # Malformed: not a UUID, an unknown key, not JSON at all.
    client.send_raw(json.dumps({"schema": GOAL_SCHEMA, "goal_id": "g-1", "behavior": "patrol"}))
    end = client.wait_end("g-1")
    assert end["status"] == "REJECTED" and "goal_id" in end["message"], end
    gid = client.send("patrol", priority=3)
    end = client.wait_end(gid)
    assert end["status"] == "REJECTED" and "priority" in end["message"], end
    client.send_raw("{not json")
    assert wait_until(lambda: any(s["goal_id"] is None and s["status"] == "REJECTED"
                                  for s in list(client.statuses)))
    assert robot.high.current == before  # nothing was switched by a refused goal


def test_second_goal_rejected_under_reject_policy(reject: Any) -> None:
    robot, client = reject
    first = client.send("patrol")
    client.wait_status(first, "EXECUTING")
    second = client.send("countdown")
    end = client.wait_end(second)
    assert end["status"] == "REJECTED"
    assert first in end["message"] and "reject" in end["message"], end["message"]
    assert robot.high.current == "patrol"
    assert not any(s["status"] in TERMINAL for s in client.of(first))
    client.cancel(None)  # the zero UUID: every goal
    assert client.wait_end(first)["status"] == "CANCELED"


def test_second_goal_preempts_under_preempt_policy(preempt: Any) -> None:
    robot, client = preempt
    first = client.send("patrol")
    client.wait_status(first, "EXECUTING")
    second = client.send("patrol", {"speed_mps": 0.1})
    end = client.wait_end(first)
    assert end["status"] == "ABORTED"
    assert f"preempted by goal {second}" in end["message"]
    client.wait_status(second, "EXECUTING")
    assert robot.high.current == "patrol" and robot.high.top.speed_mps == 0.1
    assert not any(s["status"] in TERMINAL for s in client.of(second))
    assert client.cancel(second).return_code == CancelGoal.Response.ERROR_NONE
    assert client.wait_end(second)["status"] == "CANCELED"


def test_a_switch_made_elsewhere_aborts_the_goal(reject: Any) -> None:
    robot, client = reject
    gid = client.send("patrol")
    client.wait_status(gid, "EXECUTING")
    assert client.stop().success  # beehave/stop: a switch to idle, not this goal's cancel
    end = client.wait_end(gid)
    assert end["status"] == "ABORTED", end
    assert "'idle'" in end["message"], end["message"]
    assert end["result"]["status"] == "INTERRUPTED"


def test_a_goal_overtaken_by_another_switch_is_aborted(reject: Any) -> None:
    """A switch right after the goal, before or after its behaviour started: the client
    learns it either way (never started, or interrupted), naming the switch."""
    robot, client = reject
    hl = robot.high
    assert hl is not None
    gid = client.send("countdown", {"steps": 1000})
    client.wait_status(gid, "ACCEPTED", *TERMINAL)
    hl.request_switch("parked")
    end = client.wait_end(gid)
    assert end["status"] == "ABORTED", end
    assert "'parked'" in end["message"], end["message"]


def test_second_goal_policy_is_checked_in_the_yaml() -> None:
    from beehave.errors import ConfigError

    with pytest.raises(ConfigError, match=r"ros.second_goal: .*'reject' or 'preempt'"):
        parse_config(_config("exec_bad", "sometimes"), source="r.yaml")


def test_a_robot_that_shuts_down_aborts_its_goal() -> None:
    robot = Robot(parse_config(_config("exec_down", None), source="exec_down.yaml"))
    robot.start()
    client = None
    try:
        client = GoalClient("exec_down")
        gid = client.send("patrol")
        client.wait_status(gid, "EXECUTING")
        robot.shutdown()
        end = client.wait_end(gid)
        assert end["status"] == "ABORTED", end
        assert "shuts down" in end["message"], end["message"]
    finally:
        if client is not None:
            client.close()
        robot.shutdown()
