"""VDA 5050 2.1 conformance, seen from a master control written by someone else.

The master here is plain paho-mqtt 2 and ``jsonschema`` on the official 2.1.0 schemas
(``/work/shared/vda5050/2.1.0``, or ``VDA5050_SCHEMAS``): it does not use beehave to
build what it sends or to check what it receives. Every message the AGV publishes must
validate; every test below names the section of the standard it checks. The AGV side is
beehave's interface on a real mosquitto with the fake drive of ``test_vda5050.py``, whose
velocity is fed to the interface as odometry would (so "driving" and "stands still" are
measured, and a node counts as reached while the AGV still brakes, as in the physics).
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from jsonschema import Draft202012Validator
from mqtt_broker import Broker, broker
from paho.mqtt.enums import CallbackAPIVersion
from test_vda5050 import EDGE_S, FakeDrive, options

from beehave import Action, HighLevelBehaviorManager, Status
from beehave.interfaces import ControlPlane
from beehave.interfaces.vda5050 import ActionStatus, Vda5050Interface
from beehave.interfaces.vda5050.order import ActionState, Drive
from beehave.testing import WALL_TIMEOUT_S

__all__ = ["broker"]  # the fixture, imported for pytest

SCHEMAS = Path(os.environ.get("VDA5050_SCHEMAS", "/work/shared/vda5050/2.1.0"))
SERIAL = "agv7"
PREFIX = f"uagv/v2/beehave/{SERIAL}"
BRAKING_S = 0.4
"""How long the fake AGV keeps moving after it counts a node reached or is stopped."""


# ---- the master: plain paho-mqtt + the official schemas ---------------------------------

class PlainMaster:
    """A master control: sends orders and instant actions, keeps every message the AGV
    publishes (with the time it arrived) and the ones that break their schema."""

    def __init__(self, port: int) -> None:
        self.validators = {
            t: Draft202012Validator(json.loads((SCHEMAS / f"{t}.schema").read_text()))
            for t in ("order", "instantActions", "state", "visualization", "connection",
                      "factsheet")}
        self.cond = threading.Condition()
        self.received: list[tuple[str, dict[str, Any], float]] = []
        self.invalid: list[str] = []
        self.ids = itertools.count()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="plain-master")
        self.client.on_message = self._on_message
        self.client.connect("127.0.0.1", port)
        for topic in ("state", "visualization", "connection", "factsheet"):
            self.client.subscribe(f"{PREFIX}/{topic}", qos=1)
        self.client.loop_start()

    def _on_message(self, _c: Any, _u: Any, msg: mqtt.MQTTMessage) -> None:
        topic = msg.topic.rsplit("/", 1)[-1]
        body = json.loads(msg.payload)
        errors = [e.message for e in self.validators[topic].iter_errors(body)]
        with self.cond:
            if errors:
                self.invalid.append(f"{topic}: {errors[:3]}")
            self.received.append((topic, body, time.monotonic()))
            self.cond.notify_all()

    def send(self, topic: str, body: dict[str, Any], *, valid: bool = True) -> None:
        message = {"headerId": next(self.ids),
                   "timestamp": datetime.now(UTC).isoformat(timespec="milliseconds")
                   .replace("+00:00", "Z"),
                   "version": "2.1.0", "manufacturer": "beehave", "serialNumber": SERIAL,
                   **body}
        assert self.validators[topic].is_valid(message) is valid
        self.client.publish(f"{PREFIX}/{topic}", json.dumps(message), qos=0)

    def order(self, order_id: str, update_id: int, nodes: list[dict[str, Any]],
              **header: Any) -> None:
        edges = [{"edgeId": f"e{a['nodeId']}{b['nodeId']}", "sequenceId": a["sequenceId"] + 1,
                  "released": b["released"], "startNodeId": a["nodeId"],
                  "endNodeId": b["nodeId"], "actions": []}
                 for a, b in itertools.pairwise(nodes)]
        self.send("order", {"orderId": order_id, "orderUpdateId": update_id,
                            "nodes": nodes, "edges": edges, **header})

    def instant(self, kind: str, action_id: str) -> None:
        self.send("instantActions", {"actions": [
            {"actionType": kind, "actionId": action_id, "blockingType": "HARD"}]})

    def states(self) -> list[dict[str, Any]]:
        with self.cond:
            return [body for topic, body, _ in self.received if topic == "state"]

    def wait_state(self, predicate: Callable[[dict[str, Any]], bool], *,
                   after: int = 0) -> dict[str, Any]:
        """The first state (from the ``after``-th on) for which ``predicate`` holds."""
        deadline = time.monotonic() + WALL_TIMEOUT_S
        with self.cond:
            while True:
                found = [b for t, b, _ in self.received if t == "state"][after:]
                hit = next((s for s in found if predicate(s)), None)
                if hit is not None:
                    return hit
                left = deadline - time.monotonic()
                assert left > 0, f"no such state; last: {found[-1:] or None}"
                self.cond.wait(timeout=left)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def node(node_id: str, seq: int, x: float, y: float = 0.0, *,
         actions: list[dict[str, Any]] | None = None, **position: Any) -> dict[str, Any]:
    return {"nodeId": node_id, "sequenceId": seq, "released": True,
            "nodePosition": {"x": x, "y": y, "mapId": "warehouse", **position},
            "actions": actions or []}


def pick(action_id: str, blocking: str = "HARD", kind: str = "pick") -> dict[str, Any]:
    return {"actionType": kind, "actionId": action_id, "blockingType": blocking}


def status(state: dict[str, Any], action_id: str) -> str | None:
    return next((a["actionStatus"] for a in state["actionStates"]
                 if a["actionId"] == action_id), None)


def refs(error: dict[str, Any]) -> dict[str, str]:
    return {r["referenceKey"]: r["referenceValue"] for r in error["errorReferences"]}


# ---- the AGV: a fake drive whose velocity is measured -----------------------------------

class _Edge(Action):
    """Drives one edge at 0.6 m/s for ``EDGE_S``; brakes when it ends, however."""

    action_type = "driving"

    def __init__(self, brake: Callable[[], None]) -> None:
        self.brake = brake

    def run(self) -> bool:
        BrakingDrive.interface.update_velocity(0.6, 0.0)
        try:
            return self.sleep(EDGE_S)
        finally:
            self.brake()


class BrakingDrive(FakeDrive):
    """FakeDrive that moves at 0.6 m/s while it drives and brakes for ``BRAKING_S`` after
    it reaches a node or is stopped (the velocity goes to the interface as odometry
    would); its actions take ``action_s``."""

    interface: Vda5050Interface
    action_s = EDGE_S / 3

    def _brake(self) -> None:
        timer = threading.Timer(BRAKING_S, BrakingDrive.interface.update_velocity,
                                args=(0.0, 0.0))
        timer.daemon = True
        timer.start()

    def drive(self, task: Drive) -> None:
        if FakeDrive.where == task.node.position:
            self.orders.node_reached(task.node)
            return
        # The wheels are an action's, as in OrderExecution: a pause stops them (the edge
        # then runs again from its start after the resume).
        edge = self.start_action(_Edge(self._brake))
        edge.wait()
        if edge.status is Status.SUCCEEDED and edge.result:
            FakeDrive.where = task.node.position
            FakeDrive.done.append(task.node.node_id)
            self.orders.node_reached(task.node)

    def execute(self, action: ActionState) -> None:
        self.orders.set_action(action.action_id, ActionStatus.RUNNING)
        if self.sleep(self.action_s):
            FakeDrive.done.append(action.action_id)
            self.orders.set_action(action.action_id, ActionStatus.FINISHED)


class Agv:
    def __init__(self, broker: Broker, **more: Any) -> None:
        FakeDrive.where, FakeDrive.done = (0.0, 0.0), []
        self.hl = HighLevelBehaviorManager(stop_timeout_s=0.5)
        opts = options(broker.port, **more)
        self.interface = Vda5050Interface(opts, high=self.hl, executor=BrakingDrive)
        BrakingDrive.interface = self.interface
        self.interface._position = lambda: FakeDrive.where  # type: ignore[method-assign]
        self.interface.orders._position = lambda: FakeDrive.where
        self.hl.start()
        self.plane = ControlPlane(self.hl, name="t")
        self.master = PlainMaster(broker.port)
        self.interface.start(control=self.plane)
        self.master.wait_state(lambda s: True)

    def close(self) -> None:
        self.hl.shutdown()
        self.interface.close()
        self.plane.close()
        self.master.close()


@pytest.fixture
def agv(broker: Broker) -> Iterator[Agv]:
    made = Agv(broker, state_period_s=1.0)
    try:
        yield made
    finally:
        made.close()
    assert not made.master.invalid, made.master.invalid


def on_n0(*more: dict[str, Any]) -> list[dict[str, Any]]:
    return [node("n0", 0, 0.0), *more]


# ---- 1: a pause during a running action (6.10, 6.8.2) -----------------------------------

def test_a_pause_during_a_running_action_keeps_valid_states_flowing(agv: Agv) -> None:
    BrakingDrive.action_s = 30.0
    try:
        agv.master.order("o1", 0, on_n0(node("n1", 2, 3.0, actions=[pick("p1")])))
        agv.master.wait_state(lambda s: status(s, "p1") == "RUNNING")
        agv.master.instant("startPause", "s1")
        paused = agv.master.wait_state(lambda s: status(s, "s1") == "FINISHED")
        assert paused["paused"] is True
        # 6.8.2: the action is not PAUSED in 2.1.0's schema; the flag says the AGV is.
        assert status(paused, "p1") == "RUNNING"
        seen = len(agv.master.states())
        agv.master.instant("stateRequest", "r1")
        asked = agv.master.wait_state(lambda s: status(s, "r1") == "FINISHED", after=seen)
        assert asked["paused"] is True
        # States keep coming every state_period_s (1 s here) while paused.
        periodic = len(agv.master.states())
        agv.master.wait_state(lambda s: True, after=periodic + 1)
        ids = [s["headerId"] for s in agv.master.states()]
        assert ids == list(range(ids[0], ids[0] + len(ids))), "a gap in headerId"
    finally:
        BrakingDrive.action_s = EDGE_S / 3


def test_a_state_that_breaks_the_schema_is_replaced_not_dropped(
        agv: Agv, caplog: pytest.LogCaptureFixture) -> None:
    seen = len(agv.master.states())
    with caplog.at_level(logging.ERROR, logger="beehave.interfaces.vda5050.agv"):
        agv.interface.orders.set_loads([{"loadId": 42}])  # a bug: loadId must be a string
        state = agv.master.wait_state(lambda s: any(
            e["errorType"] == "internalError" for e in s["errors"]), after=seen)
    assert "loads" not in state or all(isinstance(x.get("loadId", ""), str)
                                       for x in state["loads"])
    assert any(r.levelno == logging.ERROR for r in caplog.records)


# ---- 4: rejections a master can read (6.6.4.2, 7.1) -------------------------------------

def test_an_unsupported_action_type_is_an_order_error_naming_the_order(agv: Agv) -> None:
    agv.master.order("o1", 3, on_n0(node("n1", 2, 3.0, actions=[pick("w1", kind="weld")])))
    state = agv.master.wait_state(lambda s: bool(s["errors"]))
    (error,) = state["errors"]
    assert error["errorType"] == "orderError"
    assert refs(error)["topic"] == "order"
    assert refs(error)["orderId"] == "o1" and refs(error)["orderUpdateId"] == "3"
    assert state["orderId"] == ""


def test_a_refused_order_names_topic_order_and_its_ids(agv: Agv) -> None:
    # A released node after an unreleased one: not a valid order.
    nodes = on_n0({**node("n1", 2, 1.0), "released": False}, node("n2", 4, 2.0))
    agv.master.order("o9", 1, nodes)
    error = agv.master.wait_state(lambda s: bool(s["errors"]))["errors"][0]
    assert error["errorType"] == "validationError"
    assert refs(error)["topic"] == "order"
    assert (refs(error)["orderId"], refs(error)["orderUpdateId"]) == ("o9", "1")


def test_a_schema_invalid_order_names_topic_order_not_the_mqtt_topic(agv: Agv) -> None:
    agv.master.send("order", {"orderId": "o5", "orderUpdateId": 0, "nodes": "none",
                              "edges": []}, valid=False)
    error = agv.master.wait_state(lambda s: bool(s["errors"]))["errors"][0]
    assert error["errorType"] == "validationError"
    assert refs(error)["topic"] == "order"
    assert refs(error)["orderId"] == "o5"


# ---- 6: noOrderToCancel clears; another major version is refused ------------------------

def test_no_order_to_cancel_clears_with_the_next_accepted_order(agv: Agv) -> None:
    agv.master.instant("cancelOrder", "c1")
    agv.master.wait_state(lambda s: any(e["errorType"] == "noOrderToCancel"
                                        for e in s["errors"]))
    agv.master.order("o1", 0, on_n0())
    state = agv.master.wait_state(lambda s: s["orderId"] == "o1")
    assert not any(e["errorType"] == "noOrderToCancel" for e in state["errors"])


def test_an_order_of_another_major_version_is_refused(agv: Agv) -> None:
    agv.master.order("o1", 0, on_n0(), version="3.0.0")
    state = agv.master.wait_state(lambda s: bool(s["errors"]))
    (error,) = state["errors"]
    assert error["errorType"] == "validationError"
    assert refs(error)["field"] == "version" and refs(error)["orderId"] == "o1"
    assert state["orderId"] == ""


# ---- 2: FINISHED only at a standstill (6.6.3, 6.8.2) ------------------------------------

@pytest.mark.parametrize("kind", ["cancelOrder", "startPause"])
def test_cancel_and_pause_finish_only_once_the_agv_stands_still(agv: Agv,
                                                                 kind: str) -> None:
    agv.master.order("o1", 0, on_n0(node("n1", 2, 3.0), node("n2", 4, 6.0)))
    agv.master.wait_state(lambda s: s["lastNodeId"] == "n0" and s["driving"])
    agv.master.instant(kind, "i1")
    done = agv.master.wait_state(lambda s: status(s, "i1") == "FINISHED")
    assert done["driving"] is False
    assert done["velocity"]["vx"] == 0.0


# ---- 3: HARD blocking actions start at a standstill (6.12) -------------------------------

@pytest.mark.parametrize("blocking", ["HARD", "SOFT"])
def test_a_blocking_action_starts_only_once_the_agv_stands_still(agv: Agv,
                                                                 blocking: str) -> None:
    agv.master.order("o1", 0, on_n0(node("n1", 2, 3.0, actions=[pick("p1", blocking)])))
    running = agv.master.wait_state(lambda s: status(s, "p1") in ("RUNNING", "FINISHED"))
    assert status(running, "p1") == "RUNNING"
    assert running["driving"] is False


# ---- 5: a new order starts where the AGV is (6.6.1) -------------------------------------

def test_a_new_order_whose_first_node_is_far_away_is_refused(agv: Agv) -> None:
    # 6.6.1 / Figure 8 step 4: refused. 2.1 names no error type for it; an order with a
    # field the AGV cannot use is an orderError naming that field (6.6.4.2).
    agv.master.order("far", 0, [node("n9", 0, 4.0), node("n10", 2, 5.0)])
    state = agv.master.wait_state(lambda s: bool(s["errors"]))
    (error,) = state["errors"]
    assert error["errorType"] == "orderError" and error["errorLevel"] == "WARNING"
    assert refs(error)["field"] == "nodes[0].nodePosition"
    assert refs(error)["nodeId"] == "n9" and refs(error)["orderId"] == "far"
    assert refs(error)["topic"] == "order"
    assert state["orderId"] == "" and state["nodeStates"] == []
    assert FakeDrive.done == []
    # Reported until an order is accepted (6.6.4.2, 3.).
    agv.master.order("o1", 0, on_n0())
    state = agv.master.wait_state(lambda s: s["orderId"] == "o1")
    assert state["errors"] == []


def test_a_first_node_within_its_allowed_deviation_counts_as_traversed(agv: Agv) -> None:
    # 6.6.3.1: "the first node is the last traversed node [...] but set the deviation
    # range so large that the AGV is within this range. Thus, the AGV shall realize that
    # this node shall be counted as traversed" - not driven back to.
    agv.master.order("near", 0, [node("n9", 0, 0.8, allowedDeviationXY=1.0),
                                 node("n10", 2, 2.0)])
    state = agv.master.wait_state(lambda s: s["lastNodeId"] == "n10")
    assert state["orderId"] == "near" and not state["errors"]
    assert FakeDrive.done == ["n10"]
