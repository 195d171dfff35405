"""The control-plane core: one validation and one state for ROS 2, HTTP and VDA 5050."""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from config_fixtures import Drive, Explodes

from beehave import (
    ConstructorFailed,
    HighLevelBehaviorManager,
    InvalidParameters,
    Logic,
    LowLevelBehaviorManager,
    ManagerShutdown,
    UnknownBehavior,
)
from beehave.errors import BadRequest, BlackboardError, UnknownKey
from beehave.interfaces import STATE_SCHEMA, ControlPlane
from beehave.testing import wait_until


class Quiet(Logic):
    async def run(self) -> None:
        import asyncio

        await asyncio.sleep(3600)


@pytest.fixture
def plane(hl: HighLevelBehaviorManager) -> Iterator[ControlPlane]:
    hl.register("drive", Drive, station="dock")
    hl.register("broken_later", Drive)  # station must come with the switch
    core = ControlPlane(hl, name="emili")
    yield core
    core.close()


def strict_json(data: Any) -> Any:
    """What a network interface sends: strict JSON, no NaN/inf."""
    return json.loads(json.dumps(data, allow_nan=False))


def test_behaviors_list_names_classes_first_doc_paragraph_and_parameters(
        plane: ControlPlane) -> None:
    listed = {b["name"]: b for b in plane.behaviors()}
    assert list(listed) == ["broken_later", "drive", "idle"]
    drive = listed["drive"]
    assert drive["class"] == f"{Drive.__module__}.Drive"
    assert drive["doc"] == "Drives to a station and waits there."
    assert drive["parameters"] == [
        # given at registration: shown as the default, not required any more
        {"name": "station", "type": "str", "default": "dock", "required": False},
        {"name": "speed_mps", "type": "float", "default": 0.5, "required": False}]
    assert listed["broken_later"]["parameters"][0] == {
        "name": "station", "type": "str", "default": None, "required": True}
    assert listed["idle"]["current"] and not drive["current"]
    assert plane.logics() == []  # no low level
    assert strict_json(plane.behaviors()) == plane.behaviors()


@pytest.mark.parametrize(("name", "params", "error", "message"), [
    ("patrol", None, UnknownBehavior, "'patrol'; registered: 'broken_later', 'drive', 'idle'"),
    # A name from outside is cut in the message: the registered names still fit in what
    # an interface shows (ROS 2 result, HTTP detail), however long the name.
    ("x" * 10_000, None, UnknownBehavior,
     "'x{100}… [^']*10000 characters, cut[^']*'; registered: 'broken_later', 'drive', 'idle'$"),
    (42, None, BadRequest, "must be a string, got int 42; registered: broken_later, drive"),
    ("drive", ["dock"], InvalidParameters, "must be a mapping of parameter names"),
    ("drive", {"station": object()}, InvalidParameters, "parameter 'station' must be a JSON"),
    ("drive", {"speed_mps": math.nan}, InvalidParameters, "'speed_mps' must be a JSON value"),
    ("drive", {"not an id": 1}, InvalidParameters, "'not an id' is not a valid identifier"),
    ("drive", {"colour": "red"}, InvalidParameters, "it accepts: station, speed_mps"),
    ("broken_later", {}, InvalidParameters, "missing a required argument: 'station'"),
])
def test_a_refused_switch_names_the_problem_and_stops_nothing(
        plane: ControlPlane, hl: HighLevelBehaviorManager, name: Any, params: Any,
        error: type[Exception], message: str) -> None:
    plane.switch("drive")
    # Done switching: running, and its request no longer in flight (current is set a
    # moment before the request is let go).
    assert wait_until(lambda: hl.current == "drive" and hl.requested is None
                      and "driving" in plane.status()["locks"])
    with pytest.raises(error, match=message.replace("(", r"\(")):
        plane.switch(name, params)
    assert hl.current == "drive" and hl.requested is None  # still driving, nothing queued


def test_a_constructor_that_raises_is_reported_as_its_own_fault(hl: HighLevelBehaviorManager
                                                                 ) -> None:
    hl.register("broken", Explodes)
    core = ControlPlane(hl)
    try:
        with pytest.raises(ConstructorFailed, match="motor controller not found"):
            core.switch("broken")
        assert hl.current == "idle"
    finally:
        core.close()


def test_switch_returns_at_once_and_the_behaviour_runs_with_its_parameters(
        plane: ControlPlane, hl: HighLevelBehaviorManager) -> None:
    answer = plane.switch("drive", {"station": "shelf_a", "speed_mps": 1})
    assert answer == {"requested": "drive", "params": {"station": "shelf_a", "speed_mps": 1}}
    assert wait_until(lambda: hl.current == "drive")
    top = hl.top
    assert isinstance(top, Drive) and (top.station, top.speed_mps) == ("shelf_a", 1)
    assert {b["name"]: b["current"] for b in plane.behaviors()}["drive"]


def test_stop_puts_every_action_in_its_safe_state(plane: ControlPlane,
                                                  hl: HighLevelBehaviorManager) -> None:
    plane.switch("drive")
    assert wait_until(lambda: "driving" in plane.status()["locks"])
    top = hl.top
    assert isinstance(top, Drive)
    assert plane.stop() == {"requested": "idle", "params": {}}
    assert wait_until(lambda: hl.current == "idle")
    assert top.action.safe_state_calls == 1 and plane.status()["locks"] == {}


def test_status_is_the_ros_state_message(plane: ControlPlane) -> None:
    plane.switch("drive")
    assert wait_until(lambda: len(plane.status()["running"]) == 2)
    status = plane.status()
    assert status["schema"] == STATE_SCHEMA and status["behavior"] == "drive"
    assert status["running"] == [
        {"path": "drive", "kind": "behavior", "class": "Drive", "status": "RUNNING",
         "action_type": None},
        {"path": "drive/to_station", "kind": "action", "class": "ScriptedAction",
         "status": "RUNNING", "action_type": "driving"}]
    assert status["locks"] == {"driving": "drive/to_station"} and status["stuck"] == []
    assert status["engines"] == [] and status["logic"] is None
    assert strict_json(status) == status


def test_snapshot_holds_the_tree_and_the_low_level_in_strict_json() -> None:
    ll = LowLevelBehaviorManager(default="quiet", stop_timeout_s=0.3)
    ll.register("quiet", Quiet)
    with HighLevelBehaviorManager(stop_timeout_s=0.3) as hl, ll:
        hl.register("drive", Drive, station="dock")
        core = ControlPlane(hl, low=ll, blackboard=ll.blackboard, name="kobuki")
        try:
            core.switch("drive")
            # (An action holds its lock a moment before it joins the behaviour's children.)
            assert wait_until(lambda: "driving" in core.status()["locks"]
                              and core.snapshot()["tree"].get("children"))
            snap = core.snapshot()
            assert strict_json(snap) == snap
            assert snap["robot"] == "kobuki" and snap["behavior"] == "drive"
            assert snap["tree"]["name"] == "drive"
            assert [c["name"] for c in snap["tree"]["children"]] == ["to_station"]
            assert snap["lock_details"]["driving"]["holder"] == "drive/to_station"
            assert snap["low"]["current"] == "quiet" and "blackboard" not in snap["low"]
            assert [(lg["name"], lg["current"]) for lg in core.logics()] == [("quiet", True)]
        finally:
            core.close()


def test_blackboard_by_key_and_pattern_with_age_staleness_and_strict_json(
        plane: ControlPlane, hl: HighLevelBehaviorManager) -> None:
    board = hl.blackboard
    board.set("battery/percentage", 54.0, writer="hal:debug")
    board.set("scan/front_m", math.inf, writer="hal:laser")
    board.set("odom/pose", (1.0, 2.0, 0.5), writer="hal:odom", stale=True)
    one = plane.blackboard(key="battery/percentage")
    assert list(one) == ["battery/percentage"]
    entry = one["battery/percentage"]
    assert entry["value"] == 54.0 and entry["writer"] == "hal:debug"
    assert entry["age_s"] >= 0 and entry["stale"] is False and entry["stamp"] > 0
    every = plane.blackboard()
    assert strict_json(every) == every
    assert every["scan/front_m"]["value"] == {"$float": "inf"}
    assert every["odom/pose"] == {**every["odom/pose"], "value": [1.0, 2.0, 0.5], "stale": True}
    assert list(plane.blackboard(pattern="*/front_m")) == ["scan/front_m"]
    assert plane.blackboard(pattern="nothing/*") == {}


def test_an_unknown_key_names_close_matches(plane: ControlPlane,
                                            hl: HighLevelBehaviorManager) -> None:
    hl.blackboard.set("battery/percentage", 54.0)
    with pytest.raises(UnknownKey, match=r"emili: blackboard key 'battery/percent' holds no "
                                         r"value; did you mean 'battery/percentage'\?"):
        plane.blackboard(key="battery/percent")
    with pytest.raises(UnknownKey, match="1 keys hold a value"):
        plane.blackboard(key="zzz")
    with pytest.raises(BlackboardError):
        plane.blackboard(key="bad key")
    with pytest.raises(BlackboardError):
        plane.blackboard(pattern="a//b")


def test_events_are_numbered_kept_in_a_ring_and_read_on_from_a_seq(
        hl: HighLevelBehaviorManager) -> None:
    hl.register("drive", Drive, station="dock")
    core = ControlPlane(hl, events_kept=5)
    try:
        for _ in range(3):
            core.switch("drive")
            assert wait_until(lambda: hl.current == "drive" and hl.requested is None)
            core.stop()
            assert wait_until(lambda: hl.current == "idle" and hl.requested is None)
        kept = core.events(limit=100)
        assert len(kept) == 5  # the ring keeps the newest
        seqs = [e["seq"] for e in kept]
        assert seqs == list(range(seqs[0], seqs[0] + 5)) and seqs[0] > 1
        assert core.events(after_seq=seqs[2]) == kept[3:]
        assert core.events(limit=2) == kept[3:]
        assert core.events(after_seq=seqs[-1]) == []
        assert all(e["source"] == "high" for e in kept)
        assert strict_json(kept) == kept
        with pytest.raises(BadRequest, match="limit must be an int >= 0, got -1"):
            core.events(limit=-1)
    finally:
        core.close()


def test_subscribers_get_every_event_and_one_that_raises_breaks_nothing(
        plane: ControlPlane, hl: HighLevelBehaviorManager,
        caplog: pytest.LogCaptureFixture) -> None:
    got: list[dict[str, Any]] = []
    lock = threading.Lock()

    def record(event: dict[str, Any]) -> None:
        with lock:
            got.append(event)

    def broken(event: dict[str, Any]) -> None:
        raise RuntimeError("observer bug")

    unsubscribe_broken = plane.subscribe(broken)
    unsubscribe = plane.subscribe(record)
    plane.switch("drive")
    # Up to the action's start and the switch's end, whichever comes last (the switching
    # thread may report its end after the behaviour started the action: a stress run): no
    # event of this switch is still on its way to `record`.
    assert wait_until(lambda: any(e["kind"] == "started" and e["subject"] == "drive/to_station"
                                  for e in list(got))
                      and any(e["kind"] == "switch_completed" and e["subject"] == "drive"
                              for e in list(got)))
    assert hl.current == "drive"
    unsubscribe()
    unsubscribe_broken()
    with lock:
        seen = len(got)
    plane.stop()
    assert wait_until(lambda: hl.current == "idle")
    assert len(got) == seen
    ring = plane.events(limit=1000)
    assert [e["seq"] for e in ring][-1] >= seen  # the ring kept recording
    requested = next(e for e in ring if e["kind"] == "switch_requested"
                     and e["subject"] == "drive")
    assert requested["detail"] == {"params": {}, "source": "external"}
    # The broken listener's exception was reported, not dropped silently.
    assert any("event listener" in r.getMessage() and r.exc_info is not None
               and "observer bug" in str(r.exc_info[1]) for r in caplog.records)


def test_close_stops_recording_and_a_shut_down_manager_refuses_switches() -> None:
    hl = HighLevelBehaviorManager(stop_timeout_s=0.3)
    hl.start()
    core = ControlPlane(hl)
    core.close()
    core.close()  # idempotent
    hl.shutdown()
    assert core.events() == []
    with pytest.raises(ManagerShutdown):
        core.switch("idle")


def test_the_low_level_part_is_read_again_after_each_low_level_event() -> None:
    ll = LowLevelBehaviorManager(default="quiet", stop_timeout_s=0.3)
    ll.register("quiet", Quiet)
    ll.register("other", Quiet)
    with HighLevelBehaviorManager(stop_timeout_s=0.3) as hl, ll:
        # Without events the cached part would stay an hour: only the event refreshes it.
        core = ControlPlane(hl, low=ll, low_refresh_s=3600.0)
        try:
            assert wait_until(lambda: core.snapshot()["low"]["current"] == "quiet")
            ll.switch("other")
            assert wait_until(lambda: core.snapshot()["low"]["current"] == "other")
            assert [lg["name"] for lg in core.logics() if lg["current"]] == ["other"]
        finally:
            core.close()
