"""The replay's stand-ins for ROS and time: a node that captures what is published and
hands recorded messages to subscriptions, a clock that knows who waits on it; and the
hooks a replay relies on (who asked for a switch, who subscribes to what)."""

from __future__ import annotations

import json
import threading
from typing import Any

import pytest

pytest.importorskip("rclpy")

from geometry_msgs.msg import Twist  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from beehave import Behavior, HighLevelBehaviorManager  # noqa: E402
from beehave.errors import RecordingError  # noqa: E402
from beehave.recording.inputs import input_channel  # noqa: E402
from beehave.recording.replay_node import ReplayClock, ReplayNode  # noqa: E402
from beehave.ros.io import RosIO, watch_subscriptions  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402


def _node(now: list[float] | None = None) -> ReplayNode:
    clock = now if now is not None else [0.0]
    return ReplayNode("emili1", now_s=lambda: clock[0])


def test_published_messages_are_captured_with_their_topic_and_time() -> None:
    now = [1.5]
    node = _node(now)
    io = RosIO(node, owner="tour/Drive")  # type: ignore[arg-type]
    cmd = io.publisher(Twist, "cmd_vel")
    msg = Twist()
    msg.linear.x = 0.4
    cmd.publish(msg)
    now[0] = 2.0
    io.publisher(String, "/sound").publish(String(data="chime"))
    got = [(c.topic, c.type_name, c.t_s) for c in node.captured]
    assert got == [("/emili1/cmd_vel", "geometry_msgs/Twist", 1.5),
                   ("/sound", "std_msgs/String", 2.0)]
    assert node.captured[0].value["linear"] == {"x": 0.4, "y": 0.0, "z": 0.0}
    assert node.captured[1].value == {"data": "chime"}
    io.destroy_all()  # flushing a captured publisher waits for nobody


def test_lockstep_announcements_hold_the_clock_and_are_not_captured() -> None:
    node = _node()
    pub = node.create_publisher(String, "/lockstep")
    pub.publish(String(data=json.dumps({"participant": "nav", "until_s": 3.05})))
    assert node.holds() == {"nav": 3.05} and node.captured == []
    pub.publish(String(data=json.dumps({"participant": "nav", "until_s": None})))
    assert node.holds() == {}


def test_subscriptions_get_what_the_feed_hands_them_and_timers_follow_its_clock() -> None:
    node = _node()
    io = RosIO(node, owner="tour/Navigation")  # type: ignore[arg-type]
    odom = io.latest(Odometry, "odom")
    subs = node.subscriptions("/emili1/odom")
    assert [s.topic for s in subs] == ["/emili1/odom"]
    fed = Odometry()
    fed.pose.pose.position.x = 4.0
    for sub in subs:
        sub.callback(fed)
    assert odom.get() is fed and odom.count == 1
    ticks: list[int] = []
    io.timer(0.5, lambda: ticks.append(1))
    node.fire_timers(0.4)
    assert ticks == []
    node.fire_timers(1.0)  # due at 0.5; next at 1.0
    node.fire_timers(1.0)
    assert len(ticks) == 2
    io.destroy_all()
    assert node.subscriptions("/emili1/odom") == [] and node.topics == []


def test_services_and_actions_are_refused_naming_them() -> None:
    io = RosIO(_node(), owner="dock")  # type: ignore[arg-type]
    with pytest.raises(RecordingError, match=r"service '/emili1/dock' \(Trigger\) cannot "
                                             r"be called in a replay"):
        io.call(Trigger, "dock", Trigger.Request())
    with pytest.raises(RecordingError, match="action server '/emili1/navigate'"):
        io.action_client(Trigger, "navigate")


def test_the_clock_knows_who_is_due_to_run() -> None:
    clock = ReplayClock()
    cond = threading.Condition()
    woke = threading.Event()

    def sleeper() -> None:
        with cond:
            clock.wait(cond, lambda: False, 1.0)
        woke.set()

    thread = threading.Thread(target=sleeper)
    thread.start()
    assert wait_until(lambda: bool(clock.parked()))
    assert not clock.ready()
    clock._now = 1.0  # moved without notifying: the sleeper is due, not yet running
    assert clock.ready()
    clock.set_time(1.0)
    assert woke.wait(WALL_TIMEOUT_S)
    thread.join(WALL_TIMEOUT_S)
    assert clock.parked() == set() and not clock.ready()


def test_held_wakes_let_time_pass_and_end_no_wait_until_released() -> None:
    """What a replay does once its behaviours have done all the recording shows before a
    switch: time moves on, but a sleep due later than that moment does not end (live,
    the switch came first) until the switch is fed."""
    clock = ReplayClock()
    clock.set_time(10.0)
    cond = threading.Condition()
    woke = threading.Event()

    def sleeper() -> None:
        with cond:
            clock.wait(cond, lambda: False, 0.5)  # due at 10.5
        woke.set()

    thread = threading.Thread(target=sleeper)
    thread.start()
    assert wait_until(lambda: bool(clock.parked()))
    clock.hold_wakes(10.2)
    clock.set_time(11.0)
    assert clock.now() == 11.0
    assert not woke.wait(0.05) and not clock.ready() and clock.next_deadline() is None
    clock.release_wakes()
    assert woke.wait(WALL_TIMEOUT_S)
    thread.join(WALL_TIMEOUT_S)
    # A wait due before the hold's start still ends at once.
    clock.hold_wakes(12.0)
    with cond:
        assert clock.wait(cond, lambda: False, 0.0) is False  # due now: returns at once
    clock.release_wakes()


def test_a_subscription_is_announced_before_it_is_made() -> None:
    node = _node()
    seen: list[tuple[type, str, list[str]]] = []
    stop = watch_subscriptions(node, lambda t, topic: seen.append((t, topic, node.topics)))
    io = RosIO(node, owner="lift")  # type: ignore[arg-type]
    io.latest(String, "lift/state")
    stop()
    io.latest(String, "orders")
    # Announced with its resolved name while nobody subscribed yet (a recorder that
    # subscribes there misses nothing); no announcement once unwatched.
    assert seen == [(String, "/emili1/lift/state", [])]
    assert input_channel("emili1", "/emili1", "/emili1/lift/state") == "/emili1/lift/state"
    assert input_channel("emili1", "/emili1", "/orders") == "/orders"


class _Asker(Behavior):
    def run(self) -> None:
        self.manager.switch("other")


class _Other(Behavior):
    def run(self) -> None:
        while self.sleep(1.0):
            pass


def test_switch_requests_say_who_asked() -> None:
    events: list[Any] = []
    with HighLevelBehaviorManager(stop_timeout_s=0.3) as hl:
        hl.register("asker", _Asker)
        hl.register("other", _Other)
        hl.subscribe(lambda e: events.append(e) if e.kind.value == "switch_requested"
                     else None)
        hl.switch("asker")
        assert wait_until(lambda: hl.current == "other")
    sources = [(e.subject, e.detail["source"]) for e in events]
    assert sources == [("asker", "external"), ("other", "asker")]
