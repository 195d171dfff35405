"""VDA 5050 2.1 over MQTT: schemas, the order rules, and the interface on a real broker.

The protocol tests run the real interface, a real :class:`HighLevelBehaviorManager`, the
real control plane and a real mosquitto (its own config file, a free port, killed by PID);
only the robot is replaced by :class:`FakeDrive`, a behaviour that "drives" each edge in
``EDGE_S`` seconds, so the rules can be checked in a fraction of a second each. The same
interface drives EMILI in the physics in ``test_vda5050_sim.py``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from typing import Any

import pytest
from mqtt_broker import Broker, Master, TlsFiles, action, broker, edge, make_tls_files, node

from beehave import HighLevelBehaviorManager
from beehave.config import parse_config
from beehave.errors import ConfigError, Vda5050ValidationError
from beehave.highlevel import ManagerState
from beehave.interfaces import ControlPlane
from beehave.interfaces.vda5050 import (
    ActionStatus,
    AgvOrders,
    OrderRejected,
    Vda5050Interface,
    check,
    problems,
)
from beehave.interfaces.vda5050.order import ActionState, Drive, Point
from beehave.interfaces.vda5050.validation import TOPICS, validator
from beehave.testing import WALL_TIMEOUT_S
from behaviours.vda5050 import OrderLoop

__all__ = ["broker"]  # the fixture, imported for pytest

SERIAL = "agv7"
EDGE_S = 0.3
# A negative check (no connection comes about) runs to its end: short on purpose; a loaded
# machine can only make it miss a wrong connection, never fail a right refusal.
UNCONNECTED_S = 1.5


# ---- a map and a robot stand-in ---------------------------------------------------------

class LineMap:
    """A 20 x 12 m map called ``warehouse``; stations ``a`` and ``dock`` (charging);
    anything with x in 9–11 and y > 6 is a wall no route passes."""

    STATIONS = {"a": (2.0, 2.0), "dock": (1.0, 1.0)}

    def __init__(self, world: str) -> None:
        self.world = world

    def locate(self, node_id: str, position: dict[str, Any] | None) -> Point:
        if position is None:
            if node_id in self.STATIONS:
                return self.STATIONS[node_id]
            raise OrderRejected("validationError", f"no station {node_id!r}")
        if position["mapId"] != "warehouse":
            raise OrderRejected("validationError", f"mapId {position['mapId']!r}; valid: "
                                "'warehouse'")
        return (float(position["x"]), float(position["y"]))

    def check_route(self, points: Sequence[tuple[str, Point]]) -> None:
        for node_id, (x, y) in points:
            if 9 <= x <= 11 and y > 6:
                raise OrderRejected("noRouteError", f"no path to {node_id!r}",
                                    references={"nodeId": node_id})

    def charging_station_at(self, point: Point) -> str | None:
        return "dock" if abs(point[0] - 1.0) < 0.5 and abs(point[1] - 1.0) < 0.5 else None


class FakeDrive(OrderLoop):
    """Executes orders with ``OrderExecution``'s loop, without a robot: an edge takes
    ``EDGE_S`` (interruptible), an action ``EDGE_S / 3``; ``where`` is the fake position."""

    node_map = LineMap
    idle_wait_s = 0.02
    where: Point = (0.0, 0.0)
    done: list[str] = []  # noqa: RUF012 - shared log of the test's executions

    def __init__(self, *, orders: AgvOrders, **_options: Any) -> None:
        self.orders = orders

    def drive(self, task: Drive) -> None:
        if self.sleep(EDGE_S):
            FakeDrive.where = task.node.position
            FakeDrive.done.append(task.node.node_id)
            self.orders.node_reached(task.node)

    def execute(self, action: ActionState) -> None:
        self.orders.set_action(action.action_id, ActionStatus.RUNNING)
        if self.sleep(EDGE_S / 3):
            FakeDrive.done.append(action.action_id)
            self.orders.set_action(action.action_id, ActionStatus.FINISHED)


def options(port: int, **more: Any) -> Any:
    config = parse_config({"namespace": "t", "vda5050": {
        "broker": {"host": "127.0.0.1", "port": port, "reconnect_max_s": 1.0},
        "serial_number": SERIAL, "executor": "test_vda5050:FakeDrive",
        "visualization_rate_hz": 5.0, **more}})
    assert config.vda5050 is not None
    return config.vda5050


class Agv:
    """The interface on a manager and a control plane, with a master on the broker."""

    def __init__(self, broker: Broker, **more: Any) -> None:
        FakeDrive.where, FakeDrive.done = (0.0, 0.0), []
        self.hl = HighLevelBehaviorManager(stop_timeout_s=WALL_TIMEOUT_S)
        self.interface = Vda5050Interface(options(broker.port, **more), high=self.hl,
                                          executor=FakeDrive)
        self.interface._position = lambda: FakeDrive.where  # type: ignore[method-assign]
        self.interface.orders._position = lambda: FakeDrive.where
        self.hl.start()
        self.plane = ControlPlane(self.hl, name="t")
        self.master = Master(broker.port, serial_number=SERIAL)
        self.interface.start(control=self.plane)

    def close(self) -> None:
        self.hl.shutdown()
        self.interface.close()
        self.plane.close()
        self.master.close()


@pytest.fixture
def agv(broker: Broker) -> Iterator[Agv]:
    made = Agv(broker)
    try:
        made.master.wait_for("connection", lambda m: m["connectionState"] == "ONLINE",
                             timeout_s=WALL_TIMEOUT_S)
        yield made
    finally:
        made.close()
    assert not made.master.invalid, made.master.invalid


def three_nodes(pick: str = "p1", drop: str = "d1") -> list[dict[str, Any]]:
    return [node("n0", 0, x=0.0, y=0.0),
            node("n1", 2, x=3.0, y=0.0, actions=[action("pick", pick, loadId="L1")]),
            node("n2", 4, x=6.0, y=0.0, actions=[action("drop", drop)])]


def errors_of(state: dict[str, Any], error_type: str) -> list[dict[str, Any]]:
    return [e for e in state["errors"] if e["errorType"] == error_type]


def refs(error: dict[str, Any]) -> dict[str, str]:
    return {r["referenceKey"]: r["referenceValue"] for r in error["errorReferences"]}


# ---- the schemas ------------------------------------------------------------------------

def test_every_schema_ships_with_its_licence_and_compiles() -> None:
    from importlib import resources

    folder = resources.files("beehave.interfaces.vda5050").joinpath("schemas")
    assert "Verband der Automobilindustrie" in folder.joinpath("LICENSE.txt").read_text()
    assert "MIT" in folder.joinpath("NOTICE.md").read_text()
    for topic in TOPICS:
        assert validator(topic).schema["$schema"].endswith("2020-12/schema")


def test_a_schema_violation_names_the_field() -> None:
    order = {"headerId": 1, "timestamp": "2024-01-01T00:00:00Z", "version": "2.1.0",
             "manufacturer": "m", "serialNumber": "s", "orderId": "o", "orderUpdateId": 0,
             "nodes": [{"nodeId": "n0", "sequenceId": 0, "actions": []},
                       {"nodeId": "n1", "sequenceId": "two", "released": True,
                        "actions": []}],
             "edges": []}
    fields = [p.field for p in problems("order", order)]
    assert fields == ["nodes[0].released", "nodes[1].sequenceId"]
    with pytest.raises(Vda5050ValidationError, match=r"nodes\[1\]\.sequenceId"):
        check("order", order)


# ---- the order rules (no broker) --------------------------------------------------------

def book() -> AgvOrders:
    return AgvOrders(locate=LineMap("warehouse").locate,
                     check_route=LineMap("warehouse").check_route)


def order(order_id: str, update_id: int, nodes: list[dict[str, Any]],
          edges: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    return {"orderId": order_id, "orderUpdateId": update_id, "nodes": nodes,
            "edges": edges if edges is not None else
            [edge(a, b) for a, b in zip(nodes, nodes[1:], strict=False)]}


def drive_all(orders: AgvOrders) -> None:
    while (task := orders.next_task()) is not None:
        if isinstance(task, Drive):
            orders.node_reached(task.node)
        else:
            orders.set_action(task.action.action_id, ActionStatus.FINISHED)


def test_update_is_stitched_at_the_last_base_node_and_replaces_the_horizon() -> None:
    orders = book()
    p1 = action("pick", "p1")
    assert orders.accept(order("o", 0, [node("n0", 0, x=0, y=0),
                                        node("n1", 2, x=1, y=0, actions=[p1]),
                                        node("h", 4, x=9, y=1, released=False,
                                             actions=[action("pick", "gone")])]))
    # The stitching node comes again with its actions (as masters send it): known, kept.
    assert orders.accept(order("o", 1, [node("n1", 2, x=1, y=0, actions=[p1]),
                                        node("n2", 4, x=2, y=0), node("n3", 6, x=3, y=0,
                                        actions=[action("pick", "gone")])]))
    fields = orders.state_fields()
    assert [n["nodeId"] for n in fields["nodeStates"]] == ["n0", "n1", "n2", "n3"]
    assert [e["sequenceId"] for e in fields["edgeStates"]] == [1, 3, 5]
    # The horizon's action came again on a released node: one entry, WAITING.
    assert [(a["actionId"], a["actionStatus"]) for a in fields["actionStates"]] == [
        ("p1", "WAITING"), ("gone", "WAITING")]
    drive_all(orders)
    assert (orders.last_node_id, orders.last_node_sequence_id) == ("n3", 6)
    assert not orders.active()


@pytest.mark.parametrize(("update_id", "first", "what"), [
    (0, ("n1", 2), None),                              # a resend: ignored, no error
    (1, ("n1", 4), "current base ends at 'n1'"),       # out of sequence (sequenceId)
    (2, ("n0", 0), "current base ends at 'n1'"),       # out of sequence (node)
])
def test_updates_that_do_not_continue_the_base_are_refused(
        update_id: int, first: tuple[str, int], what: str | None) -> None:
    orders = book()
    orders.accept(order("o", 1 if update_id == 0 else 0,
                        [node("n0", 0, x=0, y=0), node("n1", 2, x=1, y=0)]))
    before = orders.state_fields()
    update = order("o", 1 if update_id == 0 else update_id,
                   [node(first[0], first[1], x=1, y=0), node("n9", first[1] + 2, x=2, y=0)])
    if what is None:
        assert orders.accept(update) is False
    else:
        with pytest.raises(OrderRejected, match=what) as info:
            orders.accept(update)
        assert info.value.entry["errorType"] == "orderUpdateError"
    assert orders.state_fields() == before


def test_a_stale_update_is_refused_and_the_order_goes_on() -> None:
    orders = book()
    orders.accept(order("o", 3, [node("n0", 0, x=0, y=0), node("n1", 2, x=1, y=0)]))
    with pytest.raises(OrderRejected, match="older than the current 3") as info:
        orders.accept(order("o", 2, [node("n1", 2, x=1, y=0), node("n2", 4, x=2, y=0)]))
    assert info.value.entry["errorType"] == "orderUpdateError"
    assert orders.order_update_id == 3 and orders.active()


def test_a_new_order_waits_until_the_current_one_is_done() -> None:
    orders = book()
    orders.accept(order("o1", 0, [node("n0", 0, x=0, y=0), node("n1", 2, x=1, y=0)]))
    with pytest.raises(OrderRejected, match="still executing order 'o1'"):
        orders.accept(order("o2", 0, [node("n1", 2, x=1, y=0)]))
    drive_all(orders)
    assert orders.accept(order("o2", 0, [node("n1", 0, x=1, y=0)]))
    assert orders.order_id == "o2"


@pytest.mark.parametrize(("nodes", "edges", "error_type", "field"), [
    ([node("n0", 0, x=0, y=0, released=False)], [], "validationError", "nodes[0].released"),
    ([node("n0", 0, x=0, y=0), node("n1", 2, x=1, y=0, released=False),
      node("n2", 4, x=2, y=0)], None, "validationError", "nodes[2].released"),
    ([node("n0", 0, x=0, y=0, actions=[action("dance", "x")])], [], "orderError",
     "nodes[0].actions[0].actionType"),
    ([node("n0", 0, x=0, y=0, map_id="moon")], [], "validationError",
     "nodes[0].nodePosition"),
    ([node("nowhere", 0)], [], "validationError", "nodes[0].nodePosition"),
    ([node("n0", 0, x=0, y=0), node("n1", 2, x=1, y=0)], [], "validationError", "edges"),
    ([node("n0", 0, x=0, y=0), node("n1", 2, x=10, y=8)], None, "noRouteError", None),
])
def test_bad_orders_are_refused_naming_the_field(
        nodes: list[dict[str, Any]], edges: list[dict[str, Any]] | None, error_type: str,
        field: str | None) -> None:
    orders = book()
    with pytest.raises(OrderRejected) as info:
        orders.accept(order("o", 0, nodes, edges))
    entry = info.value.entry
    assert entry["errorType"] == error_type
    if field is not None:
        assert refs(entry)["field"] == field, entry
    else:
        assert refs(entry)["nodeId"] == "n1"
    assert orders.order_id == "" and not orders.active()


# ---- the interface on a real broker -----------------------------------------------------

def test_connection_online_then_factsheet_and_state_validate(agv: Agv) -> None:
    sheet = agv.master.wait_for("factsheet", lambda m: True, timeout_s=WALL_TIMEOUT_S)
    actions = {a["actionType"]: a["actionScopes"]
               for a in sheet["protocolFeatures"]["agvActions"]}
    assert actions["pick"] == ["NODE", "EDGE"] and actions["cancelOrder"] == ["INSTANT"]
    state = agv.master.wait_state(lambda s: True, timeout_s=WALL_TIMEOUT_S)
    assert state["orderId"] == "" and state["errors"] == []
    agv.master.wait_for("visualization", lambda m: True, timeout_s=WALL_TIMEOUT_S)


def test_state_is_repeated_without_changes_and_never_less_often_than_every_30_s(
        broker: Broker) -> None:
    """Nothing happens, yet states keep coming every ``state_period_s`` (the master sees
    the AGV alive); a longer configured period is cut to the standard's 30 s."""
    made = Agv(broker, state_period_s=0.2, visualization_rate_hz=1.0)
    try:
        first = made.master.wait_state(lambda s: True, timeout_s=WALL_TIMEOUT_S)
        # Three more states with nothing changed (the header counts them).
        made.master.wait_state(lambda s: s["headerId"] >= first["headerId"] + 3,
                               timeout_s=WALL_TIMEOUT_S)
    finally:
        made.close()
    hl = HighLevelBehaviorManager(stop_timeout_s=WALL_TIMEOUT_S)
    lazy = Vda5050Interface(options(broker.port, state_period_s=120.0), high=hl,
                            executor=FakeDrive)
    assert lazy.state_period_s == 30.0
    assert lazy.factsheet()["protocolLimits"]["timing"]["defaultStateInterval"] == 30.0


def test_order_is_executed_node_by_node_with_its_actions(agv: Agv) -> None:
    agv.master.order("o1", 0, three_nodes())
    done = agv.master.wait_state(
        lambda s: s["lastNodeId"] == "n2" and all(
            a["actionStatus"] == "FINISHED" for a in s["actionStates"]), timeout_s=WALL_TIMEOUT_S)
    assert done["nodeStates"] == [] and done["edgeStates"] == []
    assert FakeDrive.done == ["n0", "n1", "p1", "n2", "d1"]
    # Every step was reported as it happened: n1 reached while p1 still waited.
    agv.master.wait_state(lambda s: s["lastNodeId"] == "n1" and any(
        a["actionId"] == "d1" and a["actionStatus"] == "WAITING" for a in s["actionStates"]),
        timeout_s=WALL_TIMEOUT_S)


def test_stale_update_is_refused_in_the_state_while_the_order_runs_on(agv: Agv) -> None:
    nodes = three_nodes()
    agv.master.order("o1", 2, nodes)
    agv.master.order("o1", 1, [nodes[2], node("n3", 6, x=7.0, y=0.0)])
    state = agv.master.wait_state(lambda s: bool(errors_of(s, "orderUpdateError")),
                                  timeout_s=WALL_TIMEOUT_S)
    error = errors_of(state, "orderUpdateError")[0]
    assert refs(error)["orderUpdateId"] == "1" and "older than the current 2" in \
        error["errorDescription"]
    done = agv.master.wait_state(lambda s: s["lastNodeId"] == "n2" and all(
        a["actionStatus"] == "FINISHED" for a in s["actionStates"]), timeout_s=WALL_TIMEOUT_S)
    assert done["orderUpdateId"] == 2
    assert FakeDrive.done == ["n0", "n1", "p1", "n2", "d1"]


def test_update_stitched_while_driving(agv: Agv) -> None:
    base = [node("n0", 0, x=0.0, y=0.0), node("n1", 2, x=1.0, y=0.0),
            node("h2", 4, x=2.0, y=0.0, released=False)]
    agv.master.order("o1", 0, base)
    agv.master.wait_state(lambda s: s["newBaseRequest"] is True or s["lastNodeId"] == "n1",
                          timeout_s=WALL_TIMEOUT_S)
    agv.master.order("o1", 1, [node("n1", 2, x=1.0, y=0.0), node("n2", 4, x=2.0, y=0.0)])
    done = agv.master.wait_state(lambda s: s["lastNodeId"] == "n2", timeout_s=WALL_TIMEOUT_S)
    assert done["orderUpdateId"] == 1 and done["errors"] == []
    assert FakeDrive.done == ["n0", "n1", "n2"]


@pytest.mark.parametrize(("payload", "field"), [
    (b"{not json", None),
    ({"headerId": 1}, "timestamp"),
])
def test_invalid_messages_become_validation_errors(agv: Agv, payload: Any,
                                                   field: str | None) -> None:
    agv.master.send("order", payload)
    state = agv.master.wait_state(lambda s: bool(errors_of(s, "validationError")),
                                  timeout_s=WALL_TIMEOUT_S)
    error = errors_of(state, "validationError")[0]
    assert refs(error)["topic"] == "order"  # the topic name (7.1), not the MQTT topic
    if field is None:
        assert "not valid JSON" in error["errorDescription"]
    else:
        assert refs(error)["field"] == field, error
    assert agv.hl.current == "idle"  # nothing started, nothing crashed


def test_an_order_for_another_serial_number_is_refused(agv: Agv) -> None:
    message = {**agv.master.header(), "serialNumber": "someone_else", "orderId": "o",
               "orderUpdateId": 0, "nodes": [node("n0", 0, x=0.0, y=0.0)], "edges": []}
    agv.master.send("order", message)
    state = agv.master.wait_state(lambda s: bool(errors_of(s, "validationError")),
                                  timeout_s=WALL_TIMEOUT_S)
    assert refs(errors_of(state, "validationError")[0])["field"] == "serialNumber"
    assert state["orderId"] == ""


def test_unknown_instant_action_is_refused_in_the_state(agv: Agv) -> None:
    agv.master.instant(action("teleport", "i1"))
    state = agv.master.wait_state(lambda s: bool(errors_of(s, "validationError")),
                                  timeout_s=WALL_TIMEOUT_S)
    assert refs(errors_of(state, "validationError")[0])["field"] == "actions[0].actionType"
    assert {"actionId": "i1", "actionType": "teleport", "actionStatus": "FAILED"}.items() <= \
        next(a for a in state["actionStates"] if a["actionId"] == "i1").items()


def test_cancel_order_mid_edge_stops_and_fails_the_rest(agv: Agv) -> None:
    agv.master.order("o1", 0, three_nodes())
    agv.master.wait_state(lambda s: s["lastNodeId"] == "n0", timeout_s=WALL_TIMEOUT_S)
    agv.master.instant(action("cancelOrder", "c1"))
    state = agv.master.wait_state(lambda s: any(
        a["actionId"] == "c1" and a["actionStatus"] == "FINISHED"
        for a in s["actionStates"]), timeout_s=WALL_TIMEOUT_S)
    status = {a["actionId"]: a["actionStatus"] for a in state["actionStates"]}
    assert status == {"p1": "FAILED", "d1": "FAILED", "c1": "FINISHED"}
    assert state["nodeStates"] == [] and state["edgeStates"] == []
    assert state["lastNodeId"] == "n0" and state["orderId"] == "o1"
    assert agv.hl.current == "idle" or agv.hl.requested == "idle"
    assert "n1" not in FakeDrive.done
    # Nothing left to cancel: the standard's error.
    agv.master.instant(action("cancelOrder", "c2"))
    agv.master.wait_state(lambda s: bool(errors_of(s, "noOrderToCancel")), timeout_s=WALL_TIMEOUT_S)
    # And a new order is taken after the cancel.
    agv.master.order("o2", 0, [node("n0", 0, x=0.0, y=0.0)])
    agv.master.wait_state(lambda s: s["orderId"] == "o2" and s["lastNodeId"] == "n0",
                          timeout_s=WALL_TIMEOUT_S)


def test_pause_and_resume(agv: Agv) -> None:
    agv.master.order("o1", 0, three_nodes())
    agv.master.wait_state(lambda s: s["lastNodeId"] == "n0", timeout_s=WALL_TIMEOUT_S)
    agv.master.instant(action("startPause", "s1"))
    paused = agv.master.wait_state(lambda s: s["paused"] is True, timeout_s=WALL_TIMEOUT_S)
    reached = paused["lastNodeId"]
    agv.master.wait_state(lambda s: any(a["actionId"] == "s1" and a["actionStatus"] ==
                                        "FINISHED" for a in s["actionStates"]),
                          timeout_s=WALL_TIMEOUT_S)
    done_when_paused = list(FakeDrive.done)
    time.sleep(2 * EDGE_S)  # long enough to reach the next node, had the pause not held
    agv.master.instant(action("stateRequest", "r1"))
    still = agv.master.wait_state(lambda s: any(a["actionId"] == "r1"
                                                for a in s["actionStates"]),
                                  timeout_s=WALL_TIMEOUT_S)
    assert still["lastNodeId"] == reached and still["paused"] is True
    assert FakeDrive.done == done_when_paused
    agv.master.instant(action("stopPause", "s2"))
    done = agv.master.wait_state(lambda s: s["lastNodeId"] == "n2" and not s["paused"],
                                 timeout_s=WALL_TIMEOUT_S)
    assert {a["actionId"]: a["actionStatus"] for a in done["actionStates"]}["d1"] in (
        "RUNNING", "FINISHED", "WAITING")
    assert FakeDrive.done.count("n2") == 1


def test_a_pause_from_elsewhere_shows_on_the_state_and_holds_the_order(agv: Agv) -> None:
    """A pause through ROS 2 or the web page (here the core call they make) is the same
    pause: the master sees ``paused`` and no node is reached until the resume."""
    agv.master.order("o1", 0, three_nodes())
    agv.master.wait_state(lambda s: s["lastNodeId"] == "n0", timeout_s=WALL_TIMEOUT_S)
    agv.hl.pause()
    paused = agv.master.wait_state(lambda s: s["paused"] is True, timeout_s=WALL_TIMEOUT_S)
    done_when_paused = list(FakeDrive.done)
    time.sleep(2 * EDGE_S)  # long enough to reach the next node, had the pause not held
    # The pause may come after n1 (the master hears of n0 through the broker, late on a
    # loaded host); either way the state says the last node reached, and no other comes.
    assert FakeDrive.done == done_when_paused
    assert paused["lastNodeId"] == [n for n in done_when_paused if n in ("n0", "n1")][-1]
    agv.hl.resume()
    agv.master.wait_state(lambda s: s["lastNodeId"] == "n2" and not s["paused"],
                          timeout_s=WALL_TIMEOUT_S)


def test_broker_killed_and_restarted(broker: Broker) -> None:
    made = Agv(broker)
    try:
        master = made.master
        master.wait_for("connection", lambda m: m["connectionState"] == "ONLINE",
                        timeout_s=WALL_TIMEOUT_S)
        master.order("o1", 0, three_nodes())
        master.wait_state(lambda s: s["lastNodeId"] == "n0", timeout_s=WALL_TIMEOUT_S)
        # A second master on the broker sees the AGV's last will when the AGV's link
        # breaks; kill the broker, restart it, and the AGV reconnects on its own.
        broker.restart()
        master.wait_for("connection", lambda m: m["connectionState"] == "ONLINE"
                        and m["headerId"] >= 2, timeout_s=WALL_TIMEOUT_S)
        assert made.interface.connects >= 2
        # The master resends the order it is not sure arrived: not executed twice.
        master.order("o1", 0, three_nodes())
        master.wait_state(lambda s: s["lastNodeId"] == "n2", timeout_s=WALL_TIMEOUT_S)
        assert FakeDrive.done.count("n1") == 1 and FakeDrive.done.count("p1") == 1
    finally:
        made.close()
    assert not made.master.invalid


def test_a_resend_is_answered_with_a_state(broker: Broker) -> None:
    """A master that missed the states (QoS 0) while it was away resends the order: the
    AGV does not execute it again but answers with its state (the race CI once lost)."""
    made = Agv(broker)
    late = None
    try:
        made.master.wait_for("connection", lambda m: m["connectionState"] == "ONLINE",
                             timeout_s=WALL_TIMEOUT_S)
        made.master.order("o1", 0, three_nodes())
        made.master.wait_state(lambda s: s["lastNodeId"] == "n2" and not s["driving"]
                               and all(a["actionStatus"] == "FINISHED"
                                       for a in s["actionStates"]), timeout_s=WALL_TIMEOUT_S)
        late = Master(broker.port, serial_number=SERIAL)
        late.wait_for("connection", lambda m: m["connectionState"] == "ONLINE",
                      timeout_s=WALL_TIMEOUT_S)
        late._header = made.master._header  # the same master's headerIds, continued
        late.order("o1", 0, three_nodes())
        state = late.wait_state(lambda s: s["lastNodeId"] == "n2", timeout_s=WALL_TIMEOUT_S)
        assert state["orderId"] == "o1" and state["errors"] == []
        assert FakeDrive.done.count("n1") == 1 and FakeDrive.done.count("d1") == 1
    finally:
        made.close()
        if late is not None:
            late.close()
    assert late is not None and not late.invalid


def test_the_last_will_says_connection_broken(broker: Broker) -> None:
    watcher = Master(broker.port, serial_number=SERIAL)
    made = Agv(broker)
    try:
        watcher.wait_for("connection", lambda m: m["connectionState"] == "ONLINE",
                         timeout_s=WALL_TIMEOUT_S)
        # Cut the AGV's link without a DISCONNECT (as a crash or a cable would): the
        # broker publishes the will.
        assert made.interface._client is not None
        made.interface._client._sock_close()  # type: ignore[attr-defined]
        watcher.wait_for("connection", lambda m: m["connectionState"] == "CONNECTIONBROKEN",
                         timeout_s=WALL_TIMEOUT_S)
        last = watcher.wait_for("connection", lambda m: m["connectionState"] == "ONLINE"
                                and m["headerId"] >= 2, timeout_s=WALL_TIMEOUT_S)
        assert last["serialNumber"] == SERIAL
    finally:
        made.close()
        watcher.wait_for("connection", lambda m: m["connectionState"] == "OFFLINE",
                         timeout_s=WALL_TIMEOUT_S)
        watcher.close()
    assert not watcher.invalid


def test_config_errors_name_the_key() -> None:
    with pytest.raises(ConfigError, match=r"vda5050\.serial_number: String should match"):
        parse_config({"namespace": "t", "vda5050": {"serial_number": "a/b"}})
    with pytest.raises(ConfigError, match=r"vda5050\.broker\.hots: unknown key; valid keys: "
                                          r"host, port"):
        parse_config({"namespace": "t", "vda5050": {"serial_number": "a",
                                                     "broker": {"hots": "x"}}})


def test_username_from_a_missing_environment_variable_is_refused(broker: Broker) -> None:
    hl = HighLevelBehaviorManager(stop_timeout_s=WALL_TIMEOUT_S)
    interface = Vda5050Interface(options(broker.port, broker={
        "port": broker.port, "username_env": "BEEHAVE_TEST_NO_SUCH_VAR"}),
        high=hl, executor=FakeDrive)
    with pytest.raises(ConfigError, match="BEEHAVE_TEST_NO_SUCH_VAR"):
        interface.start(control=ControlPlane(hl, name="t"))
    interface.close()
    hl.shutdown()


@pytest.fixture(scope="module")
def tls_files(tmp_path_factory: pytest.TempPathFactory) -> TlsFiles:
    return make_tls_files(tmp_path_factory.mktemp("tls"))


def _start_unconnected(port: int, broker_options: dict[str, Any],
                       caplog: pytest.LogCaptureFixture) -> None:
    """Start an AGV with ``broker_options``; it must not connect within 1.5 s (its
    warnings land in ``caplog``). Closed again either way."""
    hl = HighLevelBehaviorManager(stop_timeout_s=WALL_TIMEOUT_S)
    interface = Vda5050Interface(options(port, broker=broker_options), high=hl,
                                 executor=FakeDrive)
    plane = ControlPlane(hl, name="t")
    try:
        with caplog.at_level("WARNING", logger="beehave.interfaces.vda5050.agv"):
            interface.start(control=plane)
            assert not interface.connected.wait(UNCONNECTED_S)
    finally:
        interface.close()
        plane.close()
        hl.shutdown()


def test_username_password_from_the_environment_over_tls(
        tls_files: TlsFiles, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """A broker that wants TLS and a password (mosquitto: password_file, allow_anonymous
    false, a certificate of a CA of our own): the AGV connects with the credentials of the
    environment variables its YAML names and the CA of ``ca_file``; a wrong password is
    reported as refused and nothing is exchanged."""
    monkeypatch.setenv("BEEHAVE_TEST_VDA_USER", "agv")
    monkeypatch.setenv("BEEHAVE_TEST_VDA_PASSWORD", "s3cret")
    with Broker(users={"agv": "s3cret", "fm": "fleet"}, tls=tls_files) as secure:
        broker_options = {"port": secure.port, "username_env": "BEEHAVE_TEST_VDA_USER",
                          "password_env": "BEEHAVE_TEST_VDA_PASSWORD", "tls": True,
                          "ca_file": str(tls_files.cafile), "reconnect_max_s": 1.0}
        hl = HighLevelBehaviorManager(stop_timeout_s=WALL_TIMEOUT_S)
        interface = Vda5050Interface(options(secure.port, broker=broker_options), high=hl,
                                     executor=FakeDrive)
        hl.start()
        plane = ControlPlane(hl, name="t")
        master = Master(secure.port, serial_number=SERIAL, username="fm", password="fleet",
                        ca_file=tls_files.cafile)
        try:
            interface.start(control=plane)
            master.wait_for("connection", lambda m: m["connectionState"] == "ONLINE",
                            timeout_s=WALL_TIMEOUT_S)
            master.order("o1", 0, three_nodes())
            master.wait_state(lambda s: s["lastNodeId"] == "n2", timeout_s=WALL_TIMEOUT_S)
        finally:
            hl.shutdown()
            interface.close()
            plane.close()
            master.close()
        assert not master.invalid, master.invalid

        monkeypatch.setenv("BEEHAVE_TEST_VDA_PASSWORD", "wrong")
        _start_unconnected(secure.port, broker_options, caplog)
        assert f"broker 127.0.0.1:{secure.port} refused the connection" in caplog.text


def test_tls_without_the_brokers_ca_does_not_connect(
        tls_files: TlsFiles, caplog: pytest.LogCaptureFixture) -> None:
    """The broker's certificate is checked: without its CA (the system CAs by default)
    the AGV does not talk to it, and says so."""
    with Broker(tls=tls_files) as secure:
        _start_unconnected(secure.port, {"port": secure.port, "tls": True,
                                         "reconnect_max_s": 1.0}, caplog)
        assert f"no MQTT broker reachable at 127.0.0.1:{secure.port}" in caplog.text


def test_no_broker_is_reported_and_retried_until_one_appears(
        caplog: pytest.LogCaptureFixture) -> None:
    late = Broker()
    made_hl = HighLevelBehaviorManager(stop_timeout_s=WALL_TIMEOUT_S)
    interface = Vda5050Interface(options(late.port), high=made_hl, executor=FakeDrive)
    made_hl.start()
    plane = ControlPlane(made_hl, name="t")
    try:
        with caplog.at_level("WARNING", logger="beehave.interfaces.vda5050.agv"):
            interface.start(control=plane)
            assert not interface.connected.wait(UNCONNECTED_S)
        assert f"no MQTT broker reachable at 127.0.0.1:{late.port}" in caplog.text
        with late:
            assert interface.connected.wait(WALL_TIMEOUT_S), \
                "did not connect once the broker was up"
    finally:
        made_hl.shutdown()
        interface.close()
        plane.close()


def test_beehave_broker_serves_until_sigterm() -> None:
    import subprocess
    import sys

    import paho.mqtt.client as mqtt
    from mqtt_broker import free_port
    from paho.mqtt.enums import CallbackAPIVersion

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "beehave.cli", "broker", "--port",
                             str(port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert f"MQTT broker on 127.0.0.1:{port}" in line, line
        client = mqtt.Client(CallbackAPIVersion.VERSION2)
        assert client.connect("127.0.0.1", port) == mqtt.MQTT_ERR_SUCCESS
        client.disconnect()
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=WALL_TIMEOUT_S)
    assert proc.returncode == 0 and "broker stopped" in out, out


def test_periodic_messages_keep_their_cadence_when_woken_late() -> None:
    from beehave.interfaces.vda5050.agv import _next_tick

    # Woken 8 ms late for a 50 ms period: the next one stays on the schedule.
    assert _next_tick(1.000, 0.05, 1.008, restart=False) == pytest.approx(1.050)
    # A state sent on a change restarts the period from now.
    assert _next_tick(1.000, 0.05, 1.020, restart=True) == pytest.approx(1.070)
    # A stall longer than a period: no burst of catch-up messages.
    assert _next_tick(1.000, 0.05, 1.300, restart=False) == pytest.approx(1.350)


def test_benchmark_closes_the_agvs_it_started_when_one_fails(
        broker: Broker, monkeypatch: pytest.MonkeyPatch) -> None:
    """``python -m benchmarks vda5050`` starts ten AGVs: when the third fails to start,
    the two already running are closed (their threads and MQTT links ended) before the
    error propagates, instead of being left running in the benchmark process."""
    from benchmarks import bench_vda5050

    real_agv = bench_vda5050._agv
    started: list[Any] = []

    def third_fails(port: int, serial: str, **more: Any) -> Any:
        if len(started) == 2:
            raise RuntimeError("third AGV failed to start")
        made = real_agv(port, serial, **more)
        started.append(made)
        return made

    monkeypatch.setattr(bench_vda5050, "_agv", third_fails)
    with pytest.raises(RuntimeError, match="third AGV"):
        bench_vda5050._fleet(broker.port, 10, state_period_s=0.05)
    assert len(started) == 2
    for hl, interface, _plane in started:
        assert interface._client is None and not interface._threads
        assert hl._state is ManagerState.STOPPED, hl._state


@pytest.mark.parametrize(("args", "message"), [
    (["--broker", "127.0.0.1:1883"], "--broker is for the VDA 5050 demo"),
    (["--vda5050", "--console"], "--console and --vda5050 are different demos"),
    (["--vda5050", "--broker", "host:notaport"], "expected HOST:PORT"),
])
def test_demo_vda5050_refuses_options_it_cannot_honour(
        args: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    from beehave.cli import main

    try:
        status = main(["demo", *args])
    except SystemExit as exc:  # argparse's own error
        status = exc.code  # type: ignore[assignment]
    assert status == 2
    assert message in capsys.readouterr().err


def test_charging_and_factsheet_instant_actions(agv: Agv) -> None:
    """startCharging only on a charging station (chargingError elsewhere), stopCharging,
    and factsheetRequest publishes the factsheet again."""
    sheets = len(agv.master.received["factsheet"])
    agv.master.instant(action("startCharging", "c-away"), action("factsheetRequest", "f1"))
    state = agv.master.wait_state(lambda s: {"c-away", "f1"} <= {
        a["actionId"] for a in s["actionStates"] if a["actionStatus"] in ("FINISHED",
                                                                        "FAILED")},
        timeout_s=WALL_TIMEOUT_S)
    status = {a["actionId"]: a["actionStatus"] for a in state["actionStates"]}
    assert status["c-away"] == "FAILED" and status["f1"] == "FINISHED"
    assert errors_of(state, "chargingError")
    agv.master.wait_for("factsheet", lambda m: len(agv.master.received["factsheet"]) >
                        sheets, timeout_s=WALL_TIMEOUT_S)
    FakeDrive.where = LineMap.STATIONS["dock"]
    agv.master.instant(action("startCharging", "c-dock"), action("stopCharging", "c-off"))
    agv.master.wait_state(lambda s: {"c-dock", "c-off"} <= {
        a["actionId"] for a in s["actionStates"] if a["actionStatus"] == "FINISHED"},
        timeout_s=WALL_TIMEOUT_S)


def test_malformed_messages_during_an_order_do_not_disturb_it(agv: Agv) -> None:
    agv.master.order("o1", 0, three_nodes())
    agv.master.wait_state(lambda s: s["lastNodeId"] == "n0", timeout_s=WALL_TIMEOUT_S)
    agv.master.send("order", b"{broken")
    agv.master.send("order", {**agv.master.header(), "orderId": "o1", "orderUpdateId": 1,
                              "nodes": "not a list", "edges": []})
    agv.master.send("instantActions", {**agv.master.header(), "actions": [{"x": 1}]})
    done = agv.master.wait_state(lambda s: s["lastNodeId"] == "n2" and all(
        a["actionStatus"] == "FINISHED" for a in s["actionStates"]), timeout_s=WALL_TIMEOUT_S)
    assert done["orderUpdateId"] == 0 and len(errors_of(done, "validationError")) == 3
    assert FakeDrive.done == ["n0", "n1", "p1", "n2", "d1"]


def test_the_compiled_check_agrees_with_jsonschema_and_still_names_the_field() -> None:
    # The fast validator decides "valid"; jsonschema (the reference) names what is wrong.
    # Both must give one verdict on the corner cases where JSON Schema drafts differ.
    from beehave.interfaces.vda5050 import validation

    header = {"headerId": 1, "timestamp": "2026-01-01T00:00:00.000Z", "version": "2.1.0",
              "manufacturer": "b", "serialNumber": "s"}
    order = {**header, "orderId": "o", "orderUpdateId": 0,
             "nodes": [node("n0", 0, x=1.0, y=1.0, map_id="flat")], "edges": []}
    first = order["nodes"][0]
    cases = {
        "valid": order,
        "integer as 1.0": {**order, "orderUpdateId": 1.0},
        "integer as 1.5": {**order, "orderUpdateId": 1.5},
        "bool as integer": {**order, "orderUpdateId": True},
        "below minimum": {**order, "orderUpdateId": -1},
        "missing required": {k: v for k, v in order.items() if k != "orderId"},
        "unknown key": {**order, "extra": 1},
        "timestamp not a date": {**order, "timestamp": "yesterday"},
        "bad enum": {**order, "nodes": [{**first, "actions": [
            {"actionType": "pick", "actionId": "a", "blockingType": "MAYBE"}]}]},
        "string as number": {**order, "nodes": [{**first, "nodePosition": {
            **first["nodePosition"], "x": "1"}}]},
    }
    for name, message in cases.items():
        reference = validator("order").is_valid(message)
        assert validation.fast_validator("order")(message) is reference, name
        assert (validation.problems("order", message) == []) is reference, name
    assert [p.field for p in validation.problems("order", cases["string as number"])] == [
        "nodes[0].nodePosition.x"]
    state = {**header, "orderId": "o", "orderUpdateId": 0, "lastNodeId": "",
             "lastNodeSequenceId": 0, "nodeStates": [], "edgeStates": [],
             "actionStates": [], "driving": False, "operatingMode": "AUTOMATIC",
             "errors": [], "batteryState": {"batteryCharge": 50.0, "charging": False},
             "safetyState": {"eStop": "NONE", "fieldViolation": False}}
    validation.check("state", state)
    with pytest.raises(Vda5050ValidationError, match=r"nodeStates\[0\]"):
        validation.check("state", {**state, "nodeStates": [{"nodeId": 7}]})
    with pytest.raises(Vda5050ValidationError, match="driving"):
        validation.check("state", {**state, "driving": "yes"})
