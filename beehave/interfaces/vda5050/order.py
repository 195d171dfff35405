"""The AGV's order state: what the fleet manager asked for and how far it has got.

:class:`AgvOrders` holds the current order (its remaining nodes and edges, base and
horizon), the action states, the errors, the last node reached and the pause flag — the
part of the VDA 5050 ``state`` message that belongs to orders. It checks every order
against the standard's rules before it touches anything (:meth:`AgvOrders.accept`), so
an invalid update never disturbs a running order:

- a new ``orderId`` is taken only when the previous order is done (every released node
  reached, every action ended) — otherwise ``orderUpdateError``;
- the same ``orderId`` with the same ``orderUpdateId`` is a resend and ignored; a lower
  one is stale — ``orderUpdateError``;
- a higher ``orderUpdateId`` is stitched: its first node must be the current base's last
  node (same ``nodeId`` and ``sequenceId``), otherwise the update is out of sequence —
  ``orderUpdateError``; the old horizon is dropped and the update's nodes and edges are
  appended;
- nodes and edges must alternate with increasing ``sequenceId`` and connect
  (``startNodeId``/``endNodeId``), the base (``released``) must come before the horizon,
  every node must be placed on the map (``nodePosition`` with the world's ``mapId``, or a
  ``nodeId`` that names a station) and every action must be one the AGV supports —
  ``validationError`` naming the field;
- the first node of a new order must be where the AGV is (standing on it, or within its
  ``allowedDeviationXY``, then it counts as traversed) — ``orderError`` naming the node;
- the released base must be drivable on the map — ``noRouteError`` naming the node.

The behaviour that executes orders (:class:`behaviours.vda5050.OrderExecution`) asks
:meth:`AgvOrders.next_task` what to do next and reports back with :meth:`node_reached`
and :meth:`set_action`. Everything here is thread-safe (one lock); ``on_change`` is called
after every change that the ``state`` topic must report, outside the lock.
"""

from __future__ import annotations

import enum
import math
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Literal

from beehave.errors import Vda5050Error

Point = tuple[float, float]

NODE_ACTIONS = ("pick", "drop", "startCharging", "stopCharging")
"""Action types an order may carry on its nodes and edges."""
INSTANT_ACTIONS = ("cancelOrder", "startPause", "stopPause", "factsheetRequest",
                   "stateRequest", "startCharging", "stopCharging")
"""Action types of the ``instantActions`` topic."""

ORDER_ERROR_TYPES = ("validationError", "orderError", "orderUpdateError", "noRouteError",
                     "noOrderToCancel")
"""Errors about orders (and a cancel that found none); the next accepted order clears
them."""

FIRST_NODE_TOLERANCE_M = 0.5
"""How far (m) the first node of a new order may be from the AGV when the node gives no
``allowedDeviationXY`` (or 0): the manufacturer's tolerance for "trivially reachable"
(VDA 5050 2.1, 6.6.1)."""

STANDSTILL_TIMEOUT_S = 5.0
"""How long a ``startPause``, a ``cancelOrder`` or a HARD blocking action waits for the
AGV to stand still (measured by the odometry) before it reports anyway, with an error."""

MAX_ERRORS = 20
"""Errors kept in the state at most (the oldest go first), so a master that keeps
sending bad messages cannot grow the state without bound."""


class ActionStatus(enum.Enum):
    """The ``actionStatus`` of an action in the state (VDA 5050 2.1, 6.11)."""

    WAITING = "WAITING"
    """Received, not started yet (its node not reached)."""
    INITIALIZING = "INITIALIZING"
    """Being prepared (not used by beehave's actions, which start at once)."""
    RUNNING = "RUNNING"
    """Being executed."""
    PAUSED = "PAUSED"
    """Not sent by beehave: the 2.1.0 state schema does not allow it (VDA5050/VDA5050#356).
    A paused AGV says so with the state's ``paused`` flag; its action stays RUNNING."""
    FINISHED = "FINISHED"
    """Done."""
    FAILED = "FAILED"
    """Could not be done, or cancelled; ``resultDescription`` says why."""

    @property
    def ended(self) -> bool:
        return self in (ActionStatus.FINISHED, ActionStatus.FAILED)


class OrderRejected(Vda5050Error):
    """An order (or update) the AGV refuses; ``.entry`` is the ``errors`` entry the state
    reports (``errorType``, ``errorReferences``, ``errorDescription``)."""

    def __init__(self, error_type: str, description: str, *,
                 references: Mapping[str, str] | None = None, hint: str | None = None
                 ) -> None:
        super().__init__(f"{error_type}: {description}")
        self.entry = error_entry(error_type, description, references=references, hint=hint)


def error_entry(error_type: str, description: str, *,
                references: Mapping[str, str] | None = None, hint: str | None = None,
                level: Literal["WARNING", "FATAL"] = "WARNING") -> dict[str, Any]:
    """One ``errors`` entry of the state, as the schema wants it."""
    entry: dict[str, Any] = {
        "errorType": error_type, "errorLevel": level, "errorDescription": description,
        "errorReferences": [{"referenceKey": k, "referenceValue": str(v)}
                            for k, v in (references or {}).items()]}
    if hint:
        entry["errorHint"] = hint
    return entry


@dataclass
class Node:
    node_id: str
    sequence_id: int
    released: bool
    position: Point
    theta: float | None
    actions: list[str]          # action ids, in order
    description: str = ""
    raw_position: dict[str, Any] | None = None
    route: Any = None
    """The node map's plan of the leg that ends here (from the AGV's position or the
    previous released node), made when the order was checked; the order behaviour hands
    it to the drive so the first command does not wait for the same plan again."""


@dataclass
class Edge:
    edge_id: str
    sequence_id: int
    released: bool
    start_node_id: str
    end_node_id: str
    actions: list[str]
    max_speed_mps: float | None = None


@dataclass
class ActionState:
    action_id: str
    action_type: str
    parameters: dict[str, Any]
    status: ActionStatus = ActionStatus.WAITING
    result: str = ""
    description: str = ""
    blocking_type: str = "HARD"
    """``NONE`` (may run while driving), ``SOFT`` or ``HARD`` (only at a standstill)."""

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"actionId": self.action_id, "actionType": self.action_type,
                               "actionStatus": self.status.value}
        if self.result:
            out["resultDescription"] = self.result
        if self.description:
            out["actionDescription"] = self.description
        return out


@dataclass(frozen=True)
class Drive:
    """Drive to ``node`` (along ``edge``, None for an order's first node), and on through
    ``then`` without stopping."""

    node: Node
    edge: Edge | None
    then: tuple[tuple[Node, Edge], ...] = ()
    """The released nodes after ``node`` (each with the edge that leads to it) that the
    AGV drives on to: it passes ``node`` and all of them but the last without stopping,
    since none of those has an action and no edge among them has one (VDA 5050 2.1: the
    AGV stops only where an action or the end of the base needs it). Empty: stop at
    ``node``. Report each with ``node_reached`` as it is passed."""

    @property
    def stop(self) -> Node:
        """The node the AGV stops at: the last of ``then``, else ``node``."""
        return self.then[-1][0] if self.then else self.node


@dataclass(frozen=True)
class RunAction:
    """Execute ``action`` (its node is reached, or its edge is about to be driven)."""

    action: ActionState


Task = Drive | RunAction


@dataclass
class _Order:
    order_id: str = ""
    update_id: int = 0
    nodes: list[Node] = field(default_factory=list)   # not reached yet, base then horizon
    edges: list[Edge] = field(default_factory=list)   # not finished yet
    todo: list[str] = field(default_factory=list)     # action ids due now, in order


class AgvOrders:
    """The order state of one AGV (see the module docstring for the rules).

    ``locate(node_id, position)`` maps a node to world coordinates: the ``nodePosition``
    dict (None when the order gave none) → ``(x_m, y_m)``, raising ``OrderRejected`` with
    the reason. ``check_route(points)`` raises ``OrderRejected`` (``noRouteError``) when
    the polyline through ``points`` cannot be driven; it may return the plan of each leg
    (one per pair of points), which become the end nodes' :attr:`Node.route`.
    ``position()`` is where the robot is now (None before the first odometry).
    """

    def __init__(self, *, locate: Callable[[str, dict[str, Any] | None], Point],
                 check_route: Callable[[Sequence[tuple[str, Point]]], Sequence[Any] | None]
                 | None = None,
                 position: Callable[[], Point | None] = lambda: None,
                 standing_still: Callable[[], bool] = lambda: True,
                 on_change: Callable[[], None] = lambda: None) -> None:
        self._locate = locate
        self._check_route = check_route
        self._position = position
        self._standing_still = standing_still
        self._on_change = on_change
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._order = _Order()
        self._actions: dict[str, ActionState] = {}
        self._errors: list[dict[str, Any]] = []
        self.last_node_id = ""
        self.last_node_sequence_id = 0
        self.paused = False
        self.executing = False
        self.loads: list[dict[str, Any]] = []

    # ---- reading ------------------------------------------------------------------------

    @contextmanager
    def _changing(self) -> Iterator[None]:
        with self._cond:
            yield
            self._cond.notify_all()
        self._on_change()

    @property
    def order_id(self) -> str:
        with self._lock:
            return self._order.order_id

    @property
    def order_update_id(self) -> int:
        with self._lock:
            return self._order.update_id

    def active(self) -> bool:
        """Whether the order still has work: a released node to reach or an action that
        has not ended."""
        with self._lock:
            return self._active()

    def _active(self) -> bool:
        if any(n.released for n in self._order.nodes):
            return True
        ids = self._order.todo + [a for n in self._order.nodes for a in n.actions] + \
            [a for e in self._order.edges for a in e.actions]
        return any(not self._actions[a].status.ended for a in ids if a in self._actions)

    def action(self, action_id: str) -> ActionState:
        with self._lock:
            return self._actions[action_id]

    def errors(self) -> list[dict[str, Any]]:
        with self._lock:
            return [dict(e) for e in self._errors]

    def state_fields(self) -> dict[str, Any]:
        """The order part of the ``state`` message."""
        with self._lock:
            order = self._order
            return {
                "orderId": order.order_id,
                "orderUpdateId": order.update_id,
                "lastNodeId": self.last_node_id,
                "lastNodeSequenceId": self.last_node_sequence_id,
                "nodeStates": [self._node_state(n) for n in order.nodes],
                "edgeStates": [{"edgeId": e.edge_id, "sequenceId": e.sequence_id,
                                "released": e.released} for e in order.edges],
                "actionStates": [a.as_dict() for a in self._actions.values()],
                "errors": [dict(e) for e in self._errors],
                "paused": self.paused,
                "newBaseRequest": bool(order.nodes) and not any(
                    n.released for n in order.nodes),
                "loads": [dict(load) for load in self.loads],
            }

    @staticmethod
    def _node_state(node: Node) -> dict[str, Any]:
        out: dict[str, Any] = {"nodeId": node.node_id, "sequenceId": node.sequence_id,
                               "released": node.released}
        if node.raw_position is not None:
            out["nodePosition"] = node.raw_position
        if node.description:
            out["nodeDescription"] = node.description
        return out

    # ---- errors -------------------------------------------------------------------------

    def add_error(self, entry: dict[str, Any]) -> None:
        with self._changing():
            self._errors.append(entry)
            del self._errors[:-MAX_ERRORS]

    def clear_errors(self, types: Sequence[str]) -> None:
        with self._changing():
            self._errors = [e for e in self._errors if e["errorType"] not in types]

    # ---- orders -------------------------------------------------------------------------

    def accept(self, order: Mapping[str, Any]) -> bool:
        """Take a schema-valid order or order update. Returns False for a resend (same
        ``orderId`` and ``orderUpdateId``: nothing to do), True when accepted; raises
        :class:`OrderRejected` (nothing changed) otherwise."""
        with self._lock:
            current = self._order
            order_id = str(order["orderId"])
            update_id = int(order["orderUpdateId"])
            refs = {"orderId": order_id, "orderUpdateId": str(update_id)}
            if order_id == current.order_id:
                if update_id == current.update_id:
                    return False
                if update_id < current.update_id:
                    raise OrderRejected(
                        "orderUpdateError",
                        f"order {order_id!r}: orderUpdateId {update_id} is older than the "
                        f"current {current.update_id}; the update is ignored",
                        references=refs, hint="send updates with increasing orderUpdateId")
                nodes, edges, actions = self._parse(order, update=True)
                stitch = self._stitch_node()
                first = nodes[0]
                if (first.node_id, first.sequence_id) != stitch:
                    raise OrderRejected(
                        "orderUpdateError",
                        f"order {order_id!r} update {update_id}: its first node is "
                        f"{first.node_id!r} (sequenceId {first.sequence_id}) but the "
                        f"current base ends at {stitch[0]!r} (sequenceId {stitch[1]}); an "
                        "update must start at the last released node",
                        references={**refs, "nodeId": first.node_id})
                self._route([first, *nodes[1:]], from_robot=False)
                with self._changing():
                    kept = [n for n in current.nodes if n.released]
                    kept_edges = [e for e in current.edges if e.released]
                    # Actions of the horizon that is replaced are dropped from the state.
                    for gone in [n for n in current.nodes if not n.released] + \
                            [e for e in current.edges if not e.released]:
                        for a in gone.actions:
                            self._actions.pop(a, None)
                    current.nodes = kept + nodes[1:]
                    current.edges = kept_edges + edges
                    current.update_id = update_id
                    self._actions.update(actions)
                    self._errors = [e for e in self._errors
                                    if e["errorType"] not in ORDER_ERROR_TYPES]
                return True
            if self._active():
                raise OrderRejected(
                    "orderUpdateError",
                    f"order {order_id!r} refused: the AGV is still executing order "
                    f"{current.order_id!r}", references=refs,
                    hint="cancel the running order (instant action cancelOrder) or wait "
                         "until it is done")
            nodes, edges, actions = self._parse(order)
            traversed = self._first_node_reachable(order_id, nodes[0], refs)
            self._route(nodes, from_robot=True)
            with self._changing():
                self._order = _Order(order_id, update_id, nodes, edges)
                # Ended actions of the old order go; the new ones are listed WAITING.
                self._actions = {k: v for k, v in self._actions.items()
                                 if not v.status.ended} | actions
                self._errors = [e for e in self._errors
                                if e["errorType"] not in ORDER_ERROR_TYPES]
                if traversed:
                    self.node_reached(nodes[0])
            return True

    def _first_node_reachable(self, order_id: str, first: Node,
                              refs: Mapping[str, str]) -> bool:
        """A new order starts where the AGV is (VDA 5050 2.1, 6.6.1): "the AGV is already
        standing on the node, or [...] in the node's deviation range". Else the order is
        refused (Figure 8, step 4) — the AGV never drives off the graph — as an
        ``orderError`` naming the field (6.6.4.2: an order with fields the AGV cannot use;
        the standard names no other error type for it). Returns True when the AGV is
        within the node's own ``allowedDeviationXY``: the node then counts as traversed
        (6.6.3.1) and is not driven to. "Standing on the node" is within
        :data:`FIRST_NODE_TOLERANCE_M` when the node gives no deviation (or 0)."""
        here = self._position()
        if here is None:
            return False
        deviation = float((first.raw_position or {}).get("allowedDeviationXY") or 0.0)
        allowed = deviation or FIRST_NODE_TOLERANCE_M
        away = distance_m(here, first.position)
        if away > allowed:
            raise OrderRejected(
                "orderError",
                f"order {order_id!r}: its first node {first.node_id!r} is {away:.2f} m from "
                f"the AGV (allowed {allowed:.2f} m): a new order must start where the AGV "
                "is", references={**refs, "field": "nodes[0].nodePosition",
                                  "nodeId": first.node_id},
                hint="start the order at the AGV's position, or at its last node with an "
                     "allowedDeviationXY that reaches the AGV")
        return deviation > 0 and away <= deviation

    def _stitch_node(self) -> tuple[str, int]:
        released = [n for n in self._order.nodes if n.released]
        if released:
            return released[-1].node_id, released[-1].sequence_id
        return self.last_node_id, self.last_node_sequence_id

    def _parse(self, order: Mapping[str, Any], *, update: bool = False
               ) -> tuple[list[Node], list[Edge], dict[str, ActionState]]:
        """The order's nodes, edges and actions, checked for structure (validationError
        naming the field) and placed on the map. In an ``update`` the first node is the
        stitching node, already known with its actions: they are not taken again."""
        raw_nodes = list(order["nodes"])
        raw_edges = list(order["edges"])

        def bad(where: str, what: str, **more: str) -> OrderRejected:
            return OrderRejected("validationError", f"order {order['orderId']!r}: {where}: "
                                 f"{what}", references={"field": where, **more})

        if not raw_nodes:
            raise bad("nodes", "an order needs at least one node")
        if len(raw_edges) != len(raw_nodes) - 1:
            raise bad("edges", f"{len(raw_nodes)} node(s) need {len(raw_nodes) - 1} "
                               f"edge(s) between them, got {len(raw_edges)}")
        raw_nodes.sort(key=lambda n: n["sequenceId"])
        raw_edges.sort(key=lambda e: e["sequenceId"])
        actions: dict[str, ActionState] = {}
        # An update replaces the horizon, so the horizon's actions may come again.
        parts: list[Node | Edge] = [*self._order.nodes, *self._order.edges]
        horizon_ids = {a for part in parts if not part.released
                       for a in part.actions} if update else set()

        def take_actions(where: str, raw: list[dict[str, Any]]) -> list[str]:
            ids = []
            for j, a in enumerate(raw):
                here = f"{where}.actions[{j}]"
                if a["actionType"] not in NODE_ACTIONS:
                    # Valid VDA 5050, but not this AGV's: an orderError (6.6.4.2).
                    raise OrderRejected(
                        "orderError", f"order {order['orderId']!r}: {here}.actionType: action "
                        f"type {a['actionType']!r} is not supported; supported: "
                        f"{', '.join(NODE_ACTIONS)}",
                        references={"field": f"{here}.actionType",
                                    "actionId": str(a["actionId"])})
                known = self._actions.get(a["actionId"])
                if a["actionId"] in actions or known is not None and \
                        not known.status.ended and a["actionId"] not in horizon_ids:
                    raise bad(f"{here}.actionId", f"actionId {a['actionId']!r} is used "
                              "twice", actionId=str(a["actionId"]))
                params = {p["key"]: p["value"] for p in a.get("actionParameters", [])}
                actions[a["actionId"]] = ActionState(
                    a["actionId"], a["actionType"], params,
                    description=a.get("actionDescription", ""),
                    blocking_type=str(a.get("blockingType", "HARD")))
                ids.append(a["actionId"])
            return ids

        nodes: list[Node] = []
        horizon = False
        for i, n in enumerate(raw_nodes):
            where = f"nodes[{i}]"
            if i and n["sequenceId"] <= raw_nodes[i - 1]["sequenceId"]:
                raise bad(f"{where}.sequenceId", "sequenceIds must increase",
                          nodeId=n["nodeId"])
            if i == 0 and not n["released"]:
                raise bad(f"{where}.released", "the first node must be released (base)",
                          nodeId=n["nodeId"])
            if horizon and n["released"]:
                raise bad(f"{where}.released", "a released node after an unreleased one: "
                          "the base must come before the horizon", nodeId=n["nodeId"])
            horizon = horizon or not n["released"]
            try:
                x, y = self._locate(n["nodeId"], n.get("nodePosition"))
            except OrderRejected as exc:
                raise bad(f"{where}.nodePosition", str(exc.entry["errorDescription"]),
                          nodeId=n["nodeId"]) from None
            pos = n.get("nodePosition")
            nodes.append(Node(n["nodeId"], n["sequenceId"], n["released"], (x, y),
                              None if pos is None else pos.get("theta"),
                              [] if update and i == 0 else take_actions(where, n["actions"]),
                              n.get("nodeDescription", ""), pos))
        edges: list[Edge] = []
        for i, e in enumerate(raw_edges):
            where = f"edges[{i}]"
            a, b = raw_nodes[i], raw_nodes[i + 1]
            if (e["startNodeId"], e["endNodeId"]) != (a["nodeId"], b["nodeId"]):
                raise bad(where, f"edge {e['edgeId']!r} goes {e['startNodeId']!r} → "
                          f"{e['endNodeId']!r}, but it lies between nodes {a['nodeId']!r} "
                          f"and {b['nodeId']!r}", edgeId=e["edgeId"])
            if not a["sequenceId"] < e["sequenceId"] < b["sequenceId"]:
                raise bad(f"{where}.sequenceId", f"{e['sequenceId']} is not between its "
                          f"nodes' ({a['sequenceId']} and {b['sequenceId']})",
                          edgeId=e["edgeId"])
            if e["released"] != b["released"]:
                raise bad(f"{where}.released", "an edge is released exactly when its end "
                          "node is", edgeId=e["edgeId"])
            edges.append(Edge(e["edgeId"], e["sequenceId"], e["released"], e["startNodeId"],
                              e["endNodeId"], take_actions(where, e["actions"]),
                              e.get("maxSpeed")))
        return nodes, edges, actions

    def _route(self, nodes: list[Node], *, from_robot: bool) -> None:
        if self._check_route is None:
            return
        released = [n for n in nodes if n.released]
        points = [(n.node_id, n.position) for n in released]
        here = self._position() if from_robot else None
        if here is not None:
            points.insert(0, ("(the AGV)", here))
        if len(points) < 2:
            return
        routes = self._check_route(points)
        # Leg i ends at points[i + 1]: that node of ``released``.
        ends = released if here is not None else released[1:]
        if routes is not None and len(routes) == len(ends):
            for node, route in zip(ends, routes, strict=True):
                node.route = route

    # ---- instant actions and execution --------------------------------------------------

    def add_instant(self, action: Mapping[str, Any]) -> ActionState:
        state = ActionState(str(action["actionId"]), str(action["actionType"]),
                            {p["key"]: p["value"] for p in action.get("actionParameters", [])},
                            description=str(action.get("actionDescription", "")))
        with self._changing():
            self._actions[state.action_id] = state
        return state

    def set_action(self, action_id: str, status: ActionStatus, result: str = "") -> None:
        with self._changing():
            state = self._actions.get(action_id)
            if state is not None:
                state.status = status
                state.result = result or state.result

    def cancel(self, reason: str) -> list[str]:
        """Drop the order's remaining nodes and edges; every action that has not ended
        FAILS with ``reason``. Returns the failed action ids. The order id stays (VDA 5050:
        the cancelled order is still the AGV's last one)."""
        with self._changing():
            order = self._order
            failed = [a for a, s in self._actions.items()
                      if not s.status.ended and s.action_type != "cancelOrder"]
            for a in failed:
                self._actions[a].status = ActionStatus.FAILED
                self._actions[a].result = reason
            order.nodes.clear()
            order.edges.clear()
            order.todo.clear()
        return failed

    def position(self) -> Point | None:
        """Where the AGV is now (None before its first odometry)."""
        return self._position()

    def set_loads(self, loads: list[dict[str, Any]]) -> None:
        with self._changing():
            self.loads = loads

    def set_paused(self, paused: bool) -> None:
        with self._changing():
            self.paused = paused

    def set_executing(self, executing: bool) -> None:
        with self._changing():
            self.executing = executing

    def wait_not_executing(self, *, timeout_s: float) -> bool:
        """Wait until the executing behaviour has ended; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self.executing, timeout=timeout_s)

    def next_task(self) -> Task | None:
        """What the executing behaviour must do next: an action due now, else the drive
        to the next released node; None when there is nothing (order done or waiting for
        its horizon to be released)."""
        with self._lock:
            order = self._order
            while order.todo:
                state = self._actions.get(order.todo[0])
                if state is not None and not state.status.ended:
                    return RunAction(state)
                order.todo.pop(0)
            if not order.nodes or not order.nodes[0].released:
                return None
            node = order.nodes[0]
            edge = next((e for e in order.edges if e.end_node_id == node.node_id
                         and e.sequence_id == node.sequence_id - 1), None)
            if edge is not None:
                # Edge actions run when the edge starts, before the drive (docs: limits).
                pending = [a for a in edge.actions if not self._actions[a].status.ended]
                if pending:
                    order.todo.extend(pending)
                    return RunAction(self._actions[pending[0]])
            return Drive(node, edge, self._drive_on(node))

    def _drive_on(self, node: Node) -> tuple[tuple[Node, Edge], ...]:
        """The released nodes after ``node`` the AGV may drive on to without stopping
        (see :attr:`Drive.then`); called with the lock held."""
        order = self._order
        then: list[tuple[Node, Edge]] = []
        if node.actions or len(order.nodes) < 2 or not order.nodes[1].released:
            return ()
        edges = {e.sequence_id: e for e in order.edges if e.released}
        last = node
        for following in order.nodes[1:]:
            if last.actions or not following.released:
                break
            edge = edges.get(following.sequence_id - 1)
            if edge is None or edge.end_node_id != following.node_id or edge.actions:
                break
            then.append((following, edge))
            last = following
        return tuple(then)

    def node_reached(self, node: Node) -> None:
        """The AGV stands on ``node``: it becomes the last node, leaves the node states
        with the edge that led to it, and its actions are due."""
        with self._changing():
            order = self._order
            if not order.nodes or order.nodes[0] is not node:
                return  # cancelled or replaced meanwhile
            order.nodes.pop(0)
            order.edges = [e for e in order.edges if e.sequence_id > node.sequence_id]
            self.last_node_id = node.node_id
            self.last_node_sequence_id = node.sequence_id
            order.todo.extend(node.actions)

    def wait_standstill(self, *, timeout_s: float) -> bool:
        """Wait until the AGV stands still (measured: ``standing_still()``, re-checked
        whenever :meth:`notify` is called, as the interface does when the odometry starts
        or stops); False when it still moves after ``timeout_s``."""
        with self._cond:
            return self._cond.wait_for(self._standing_still, timeout=timeout_s)

    def wait_change(self, *, timeout_s: float) -> None:
        """Block until something changes (or ``timeout_s``)."""
        with self._cond:
            self._cond.wait(timeout=timeout_s)

    def notify(self) -> None:
        with self._cond:
            self._cond.notify_all()


def distance_m(a: Point, b: Point) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])
