"""``beehave fleet --scenario serve``: the ARCADE paper's SERVE task in the physics.

A café (``robots/worlds/serve.yaml``): EMILI (lift, display: it can hand over to a guest;
wide) and ``--robots`` Kobukis (faster, no lift; narrow), an open shelf, a shelf in an
aisle only a Kobuki fits into, a meeting point and three guest tables. Every agent runs in
its own process over DDS, as the factory fleet does:

- the simulation (``python -m behaviours.demos.serve sim``): pybullet with the sim node
  (topics, ``/clock``, lockstep) and :class:`ServeFloor`, the physics of the items, which
  publishes ``/serve/state`` and measures the facts the checks are made of;
- each robot: ``beehave run`` of ``robots/config/serve_emili.yaml`` /
  ``serve_kobuki.yaml`` (namespace and agent name per robot): a
  :class:`~behaviours.market.serving.ServeBroker` that bids planned travel times and
  performs the roles it wins, and the speed zone of the aisle on the low level;
- the order source (``python -m behaviours.market.cafe``): auctions the three orders
  (:func:`~behaviours.market.cafe.cafe_orders`) with the market's auctioneer.

This process only watches (``/serve/orders``, ``/serve/state``), prints a live table,
stops everything when the orders are settled (or after ``--minutes`` of sim time), and
checks what the simulation measured:

- every order completed (the auctioneer's outcome) and served in the physics: an item
  put down at the order's table by the robot of its last role, standing there;
- a ``serve`` order: the server showed the order on its display while the guest took it;
- every hand-over: from the coalition's ``fetch`` robot to its ``serve`` robot, both
  standing within ``HAND_OVER_RADIUS_M`` of the meeting point, the taker's lift raised;
- EMILI never inside the narrow aisle; at most one robot in it at once (a zone keeper
  agent, ``python -m behaviours.market.serving shelf_aisle``, lets them in one by one);
  no robot faster than the aisle's limit + 5 %;
- nothing lost: every item picked was served.

Exit 0 only if every check held, 1 otherwise, 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

if TYPE_CHECKING:
    from rich.console import Console, Group

    from behaviours.demos.checks import Check
    from robots.sim import Simulation

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = {"emili": ROOT / "robots" / "config" / "serve_emili.yaml",
           "kobuki": ROOT / "robots" / "config" / "serve_kobuki.yaml"}
WORLD = "serve"
MAX_KOBUKIS = 4
#: The agents' directory lease: above the fleet's 3 s, since a robot that misses it (a busy
#: 2-core host) counts as dead and dissolves its coalition.
LEASE_S = 5.0
CLOCK_RATE_HZ = 50.0
HAND_OVER_RADIUS_M = 1.0
"""How close to the meeting point's centre both robots must stand for a hand-over."""
AISLE = "shelf_aisle"
"""The speed zone that is the narrow aisle: EMILI must never be inside it."""


# ---- the physics of the items (sim process) ----------------------------------------------

@dataclass
class _Robot:
    ns: str
    kind: str
    item: str | None = None
    body: int | None = None
    dwell: Any = None
    since_s: float = 0.0
    speeds: deque[float] = field(default_factory=lambda: deque(maxlen=4))
    inside_s: float = 0.0
    first_inside_s: float | None = None


class ServeFloor:
    """The serve scenario's physics, hooked into a :class:`~robots.sim.Simulation`'s step
    at ``rate_hz`` (sim time). Shelves, the meeting point and tables are the world's
    stations named ``shelf*``, ``meeting*`` and ``table*``. The rules:

    - **pick**: a robot holding nothing that stands still (``|v| < still_speed_mps``)
      inside a shelf station for ``pick_s`` gets an item (``<shelf>#<n>``);
    - **hand-over**: while a robot holding an item offers it to an EMILI holding none
      (:meth:`offer`: the giver's ``/serve/hand_over`` message, valid ``for_s``), both
      standing still within ``hand_over_radius_m`` of a meeting station's centre, EMILI's
      lift at ``lift_min_m`` or higher, for ``hand_over_s``: the item moves onto EMILI's
      plate. Without an offer nothing moves (a loaded robot that passes a waiting EMILI
      keeps its item);
    - **serve**: a robot holding an item that stands still inside a table station for
      ``serve_s``: the guest takes it; recorded with the robot's display text and lift.

    Items show as boxes on the robot that holds them (visual only). The time each robot
    spends inside the aisle zone and the fastest speed there (averaged over 4 updates)
    are measured too. :meth:`facts` is the report; :meth:`state` the ``/serve/state``
    message; listeners (:meth:`on_event`) run in the stepping thread after an event."""

    def __init__(self, sim: Simulation, *, rate_hz: float = 20.0,
                 still_speed_mps: float = 0.05, pick_s: float = 1.5,
                 hand_over_s: float = 1.0, serve_s: float = 1.5,
                 hand_over_radius_m: float = HAND_OVER_RADIUS_M,
                 lift_min_m: float = 0.15) -> None:
        from robots.emili import Emili

        self.sim, self.world = sim, sim.world
        self.still_speed_mps, self.pick_s = still_speed_mps, pick_s
        self.hand_over_s, self.serve_s = hand_over_s, serve_s
        self.hand_over_radius_m, self.lift_min_m = hand_over_radius_m, lift_min_m
        stations = self.world.stations
        self.shelves = [s for s in stations if s.name.startswith("shelf")]
        self.meetings = [s for s in stations if s.name.startswith("meeting")]
        self.tables = [s for s in stations if s.name.startswith("table")]
        self.zones = list(self.world.zones)
        self._emilis = {ns for ns, r in sim.robots.items() if isinstance(r, Emili)}
        self._robots = {ns: _Robot(ns, r.kind) for ns, r in sim.robots.items()}
        self._lock = threading.Lock()
        self._count: dict[str, int] = {}
        self.picks: list[dict[str, Any]] = []
        self.hand_overs: list[dict[str, Any]] = []
        self.deliveries: list[dict[str, Any]] = []
        self.zone_max: dict[str, dict[str, Any]] = {
            z.name: {"max_speed_mps": z.max_speed_mps, "max_ratio": 0.0, "robot": None,
                     "at_s": None, "most_inside": 0, "most_inside_at_s": None,
                     "most_inside_robots": []} for z in self.zones}
        self._offers: dict[str, tuple[str, float]] = {}  # giver -> (taker, until sim s)
        self._pair: tuple[str, str] | None = None
        self._pair_since_s = 0.0
        self._listeners: list[Callable[[], None]] = []
        self._last_s = sim.time_s
        self._remove = sim.on_step(self._update, rate_hz=rate_hz)

    def offer(self, giver: str, taker: str, *, for_s: float = 1.0) -> None:
        """``giver`` offers its item to ``taker`` for the next ``for_s`` sim seconds (any
        thread). Unknown robots are ignored: the physics decides, not the message."""
        if giver in self._robots and taker in self._robots:
            with self._lock:
                self._offers[giver] = (taker, self._last_s + for_s)

    def on_event(self, callback: Callable[[], None]) -> None:
        self._listeners.append(callback)

    def close(self) -> None:
        self._remove()

    # ---- readings ---------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        from behaviours.market.serving import STATE_SCHEMA

        with self._lock:
            robots = {}
            for ns, r in self._robots.items():
                robot = self.sim.robot(ns)
                pose = robot.pose()
                lift = getattr(robot, "lift_height", None)
                robots[ns] = {"kind": r.kind, "item": r.item, "x_m": round(pose.x_m, 3),
                              "y_m": round(pose.y_m, 3),
                              "lift_m": round(lift(), 3) if lift is not None else None}
            return {"schema": STATE_SCHEMA, "time_s": round(self._last_s, 3),
                    "robots": robots, "picks": len(self.picks),
                    "hand_overs": len(self.hand_overs), "deliveries": len(self.deliveries)}

    def facts(self) -> dict[str, Any]:
        """Everything measured: picks, hand-overs, deliveries (in order), per robot the
        time inside each zone, per zone the largest speed / limit ratio."""
        with self._lock:
            return {"world": self.world.name, "time_s": round(self._last_s, 3),
                    "meeting": {m.name: list(m.center_m) for m in self.meetings},
                    "tables": {t.name: list(t.center_m) for t in self.tables},
                    "picks": list(self.picks), "hand_overs": list(self.hand_overs),
                    "deliveries": list(self.deliveries),
                    "robots": {ns: {"kind": r.kind, "item": r.item,
                                    "in_aisle_s": round(r.inside_s, 3),
                                    "first_in_aisle_at_s": r.first_inside_s}
                               for ns, r in self._robots.items()},
                    "zones": dict(self.zone_max)}

    # ---- sim thread -------------------------------------------------------------------

    def _update(self, time_s: float) -> None:
        fired = False
        with self._lock:
            dt = time_s - self._last_s
            self._last_s = time_s
            odoms = {ns: self.sim.robot(ns).odometry() for ns in self._robots}
            still = {}
            for zone in self.zones:  # how many robots at once (the aisle is one lane)
                inside = sorted(ns for ns, o in odoms.items() if zone.contains(o.x_m, o.y_m))
                entry = self.zone_max[zone.name]
                if len(inside) > entry["most_inside"]:
                    entry.update(most_inside=len(inside), most_inside_at_s=round(time_s, 3),
                                 most_inside_robots=inside)
            for ns, r in self._robots.items():
                o = odoms[ns]
                r.speeds.append(abs(o.linear_mps))
                still[ns] = abs(o.linear_mps) < self.still_speed_mps
                fired |= self._zones(r, o.x_m, o.y_m, time_s, dt)
                fired |= self._pick_or_serve(r, o.x_m, o.y_m, still[ns], time_s)
            fired |= self._hand_over(odoms, still, time_s)
            for r in self._robots.values():
                if r.body is not None:
                    self._move_item(r, odoms[r.ns])
        if fired:
            for callback in list(self._listeners):
                callback()

    def _zones(self, r: _Robot, x: float, y: float, time_s: float, dt: float) -> bool:
        for zone in self.zones:
            if not zone.contains(x, y):
                continue
            if zone.name == AISLE:
                r.inside_s += dt
                if r.first_inside_s is None:
                    r.first_inside_s = round(time_s, 3)
            speed = sum(r.speeds) / len(r.speeds)
            entry = self.zone_max[zone.name]
            if speed / zone.max_speed_mps > entry["max_ratio"]:
                entry.update(max_ratio=round(speed / zone.max_speed_mps, 4), robot=r.ns,
                             at_s=round(time_s, 3))
        return False

    def _pick_or_serve(self, r: _Robot, x: float, y: float, still: bool,
                       time_s: float) -> bool:
        place = None
        if still:
            spots = self.shelves if r.item is None else self.tables
            place = next((s for s in spots if s.contains(x, y)), None)
        if place is not r.dwell:
            r.dwell, r.since_s = place, time_s
            return False
        if place is None:
            return False
        if r.item is None and time_s - r.since_s + 1e-9 >= self.pick_s:
            n = self._count[place.name] = self._count.get(place.name, 0) + 1
            r.item = f"{place.name}#{n}"
            self.picks.append({"item": r.item, "shelf": place.name, "robot": r.ns,
                               "time_s": round(time_s, 3), "x_m": round(x, 3),
                               "y_m": round(y, 3)})
            self._show(r)
            r.dwell = None
            return True
        if r.item is not None and time_s - r.since_s + 1e-9 >= self.serve_s:
            robot = self.sim.robot(r.ns)
            display = getattr(robot, "display", None)
            lift = getattr(robot, "lift_height", None)
            self.deliveries.append({
                "item": r.item, "table": place.name, "robot": r.ns, "kind": r.kind,
                "time_s": round(time_s, 3), "x_m": round(x, 3), "y_m": round(y, 3),
                "display": display() if display is not None else None,
                "lift_m": round(lift(), 3) if lift is not None else None})
            r.item = None
            self._show(r)
            r.dwell = None
            return True
        return False

    def _hand_over(self, odoms: dict[str, Any], still: dict[str, bool],
                   time_s: float) -> bool:
        pair = None
        for giver, (taker, until_s) in sorted(self._offers.items()):
            if until_s < time_s:
                del self._offers[giver]
                continue
            g, t = self._robots[giver], self._robots[taker]
            if g.item is None or t.item is not None or taker not in self._emilis \
                    or self.sim.emili(taker).lift_height() < self.lift_min_m \
                    or not (still[giver] and still[taker]):
                continue
            for meeting in self.meetings:
                mx, my = meeting.center_m
                if all(math.hypot(odoms[ns].x_m - mx, odoms[ns].y_m - my)
                       <= self.hand_over_radius_m for ns in (giver, taker)):
                    pair = (giver, taker, meeting)
                    break
            if pair is not None:
                break
        if pair is None or pair[:2] != self._pair:
            self._pair = None if pair is None else pair[:2]
            self._pair_since_s = time_s
            return False
        if time_s - self._pair_since_s + 1e-9 < self.hand_over_s:
            return False
        giver, taker, meeting = pair
        g, t = self._robots[giver], self._robots[taker]
        mx, my = meeting.center_m
        go, to = odoms[giver], odoms[taker]
        self.hand_overs.append({
            "item": g.item, "giver": giver, "taker": taker, "meeting": meeting.name,
            "time_s": round(time_s, 3),
            "giver_xy": [round(go.x_m, 3), round(go.y_m, 3)],
            "taker_xy": [round(to.x_m, 3), round(to.y_m, 3)],
            "giver_to_meeting_m": round(math.hypot(go.x_m - mx, go.y_m - my), 3),
            "taker_to_meeting_m": round(math.hypot(to.x_m - mx, to.y_m - my), 3),
            "taker_lift_m": round(self.sim.emili(taker).lift_height(), 3)})
        t.item, g.item = g.item, None
        self._offers.pop(giver, None)
        self._show(g)
        self._show(t)
        self._pair = None
        return True

    # ---- the item's box in pybullet (sim thread) ---------------------------------------

    def _show(self, r: _Robot) -> None:
        if r.item is None and r.body is not None:
            body, r.body = r.body, None
            self.sim.call(lambda c: c.removeBody(body))
        elif r.item is not None and r.body is None:
            def create(c: Any) -> int:
                shape = c.createVisualShape(c.GEOM_BOX, halfExtents=[0.08, 0.08, 0.06],
                                            rgbaColor=[0.95, 0.85, 0.2, 1.0])
                body: int = c.createMultiBody(0.0, -1, shape, [0.0, 0.0, 0.4])
                return body

            r.body = self.sim.call(create)

    def _move_item(self, r: _Robot, o: Any) -> None:
        robot = self.sim.robot(r.ns)
        lift = getattr(robot, "lift_height", None)
        # On EMILI's plate (0.35 m + the lift); on a Kobuki's top plate.
        z = 0.42 + lift() if lift is not None else 0.2
        body, quat = r.body, (0.0, 0.0, math.sin(o.yaw_rad / 2), math.cos(o.yaw_rad / 2))
        self.sim.call(lambda c: c.resetBasePositionAndOrientation(body, [o.x_m, o.y_m, z],
                                                                  quat))


def serve_world(world: str | Path, kobukis: int) -> Any:
    """``world`` with its EMILIs and its first ``kobukis`` Kobukis (WorldError when it has
    fewer, naming how many it has)."""
    from robots.errors import WorldError
    from robots.world import load_world

    w = load_world(world)
    emilis = [r for r in w.robots if r.kind == "emili"]
    koboks = [r for r in w.robots if r.kind == "kobuki"]
    if not emilis or kobukis > len(koboks):
        raise WorldError(w.name, [f"robots: the serve scenario needs an EMILI and "
                                  f"{kobukis} Kobuki(s); this world has {len(emilis)} "
                                  f"EMILI(s) and {len(koboks)} Kobuki(s)"])
    return w.model_copy(update={"robots": emilis[:1] + koboks[:kobukis]})


def sim_main(argv: list[str]) -> int:
    """``python -m behaviours.demos.serve sim [WORLD] --robots N [--fast] --report FILE
    --picture FILE``: the sim node and :class:`ServeFloor` until SIGINT/SIGTERM; then the
    facts and the picture (trajectories)."""
    parser = argparse.ArgumentParser(prog="python -m behaviours.demos.serve sim")
    parser.add_argument("world", nargs="?", default=WORLD)
    parser.add_argument("--robots", type=int, default=2)
    parser.add_argument("--fast", action="store_true")
    parser.add_argument("--report", type=Path, required=True)
    parser.add_argument("--picture", type=Path, default=None)
    args = parser.parse_args(argv)
    from std_msgs.msg import String

    from beehave.ros.context import RosContext
    from behaviours.market.serving import HAND_OVER_TOPIC, SERVE_STATE, STATE_QOS
    from robots.node import SimNode
    from robots.sim import SimState, Simulation

    sim = Simulation(serve_world(args.world, args.robots),
                     real_time_factor=None if args.fast else 1.0)
    floor = ServeFloor(sim)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    ros = RosContext()
    node = SimNode(sim, ros, clock_rate_hz=CLOCK_RATE_HZ)
    pub_node = ros.create_node("serve_floor")
    pub = pub_node.create_publisher(String, SERVE_STATE, STATE_QOS)

    def on_offer(msg: String) -> None:
        try:
            data = json.loads(msg.data)
            floor.offer(str(data["giver"]), str(data["taker"]))
        except (ValueError, KeyError, TypeError) as exc:
            print(json.dumps({"event": "bad_offer", "data": msg.data[:200],
                              "error": str(exc)}), flush=True)

    pub_node.create_subscription(String, HAND_OVER_TOPIC, on_offer, 10)
    lock = threading.Lock()

    def publish(_time_s: float = 0.0) -> None:
        with lock:  # an event and the periodic tick may come from one step
            pub.publish(String(data=json.dumps(floor.state())))

    remove = sim.on_step(publish, rate_hz=5.0)
    floor.on_event(publish)
    code = 0
    try:
        ros.start()
        publish()
        sim.start()
        print(json.dumps({"event": "ready", "robots": list(sim.robots)}), flush=True)
        while not stop.wait(0.5):
            if sim.state is SimState.FAILED:
                code = 1
                break
    finally:
        try:
            sim.stop()
        finally:
            remove()
            floor.close()
            node.destroy()
            ros.shutdown()
            args.report.parent.mkdir(parents=True, exist_ok=True)
            args.report.write_text(json.dumps(floor.facts(), indent=2) + "\n")
            if args.picture is not None:
                sim.render_topdown(args.picture, scale_px_per_m=60.0,
                                   title=f"serve  t = {sim.time_s:.0f} s")
            sim.close()
    return code


# ---- the checks (launcher) ---------------------------------------------------------------

def _last_role(outcome: dict[str, Any]) -> str | None:
    """The role that serves the table: ``serve`` in a coalition, else the only one."""
    members = outcome.get("members") or {}
    return "serve" if "serve" in members else next(iter(members), None)


def item_trail(facts: dict[str, Any], outcome: dict[str, Any]) -> dict[str, Any]:
    """Follow the item an order was served with back through the physics: the delivery at
    the order's table by the robot of its serving role, the hand-over of that item (if
    any) and its pick. ``{"delivery", "hand_over", "pick"}``, each None when missing."""
    server = (outcome.get("members") or {}).get(_last_role(outcome) or "")
    delivery = next((d for d in facts.get("deliveries", [])
                     if d["table"] == outcome.get("table") and d["robot"] == server), None)
    item = None if delivery is None else delivery["item"]
    return {"delivery": delivery,
            "hand_over": next((h for h in facts.get("hand_overs", [])
                               if h["item"] == item), None),
            "pick": next((p for p in facts.get("picks", []) if p["item"] == item), None)}


def role_steps(facts: dict[str, Any], outcome: dict[str, Any]) -> dict[str, list[str]]:
    """role -> what its robot did with the order's item, in the physics (for the
    summary and the picture)."""
    trail = item_trail(facts, outcome)
    out: dict[str, list[str]] = {}
    for role, robot in (outcome.get("members") or {}).items():
        did = []
        p, h, d = trail["pick"], trail["hand_over"], trail["delivery"]
        if p is not None and p["robot"] == robot:
            did.append(f"picked {p['item']} at {p['time_s']:.0f} s")
        if h is not None and robot in (h["giver"], h["taker"]):
            other = h["taker"] if h["giver"] == robot else h["giver"]
            did.append(f"{'handed it to' if h['giver'] == robot else 'took it from'} "
                       f"{other} at {h['time_s']:.0f} s")
        if d is not None and d["robot"] == robot:
            did.append(f"served it at {d['table']} at {d['time_s']:.0f} s")
        out[role] = did
    return out


def checks(facts: dict[str, Any], outcomes: dict[str, dict[str, Any]], *,
           expected: list[str]) -> list[Check]:
    """(check, passed, what was measured): the auction's outcomes against the facts the
    simulation measured (:meth:`ServeFloor.facts`). ``expected``: the order ids."""
    out: list[Check] = []
    deliveries = list(facts.get("deliveries", []))
    tables = facts.get("tables", {})
    for tid in expected:
        o = outcomes.get(tid)
        if o is None:
            out.append((f"order {tid!r} completed", False, "never settled"))
            continue
        members = o.get("members") or {}
        who = ", ".join(f"{r}={b}" for r, b in members.items())
        out.append((f"order {tid!r} completed", o.get("state") == "completed",
                    f"{o.get('state')} with plan {o.get('plan')} ({who})"
                    + (f": {o.get('reason')}" if o.get("state") != "completed" else "")))
        server = members.get(_last_role(o) or "")
        table = o.get("table")
        trail = item_trail(facts, o)
        d = trail["delivery"]
        where = tables.get(table)
        measured = "no item put down there by it"
        off = math.inf
        if d is not None and where is not None:
            off = math.hypot(d["x_m"] - where[0], d["y_m"] - where[1])
            measured = (f"{d['item']} by {server} at {d['time_s']:.1f} s, {off:.2f} m from "
                        f"the table's spot")
        out.append((f"{tid}: served at {table} by {server}", off <= 0.6, measured))
        if d is not None and o.get("kind") == "serve":
            shown = str(d.get("display") or "")
            out.append((f"{tid}: the order on {server}'s display when served",
                        shown.startswith(f"{tid}:"), repr(shown)))
        if "fetch" in members and "serve" in members:
            h = trail["hand_over"]
            name = (f"{tid}: handed over {members['fetch']} -> {members['serve']} at the "
                    f"meeting point (both <= {HAND_OVER_RADIUS_M:g} m, lift up)")
            if h is None:
                out.append((name, False, "no hand-over of the served item in the physics"))
            else:
                near = max(h["giver_to_meeting_m"], h["taker_to_meeting_m"])
                out.append((name, h["giver"] == members["fetch"]
                            and h["taker"] == members["serve"] and near <= HAND_OVER_RADIUS_M
                            and h["taker_lift_m"] >= 0.15,
                            f"{h['item']} at {h['time_s']:.1f} s: {h['giver']} "
                            f"{h['giver_to_meeting_m']:.2f} m, {h['taker']} "
                            f"{h['taker_to_meeting_m']:.2f} m away, lift "
                            f"{h['taker_lift_m']:.2f} m"))
    robots = facts.get("robots", {})
    emilis = {ns: r for ns, r in robots.items() if r["kind"] == "emili"}
    inside = {ns: r["in_aisle_s"] for ns, r in emilis.items() if r["in_aisle_s"] > 0}
    out.append(("EMILI never in the narrow aisle", bool(emilis) and not inside,
                "; ".join(f"{ns} {s:.1f} s inside from {emilis[ns]['first_in_aisle_at_s']} s"
                          for ns, s in inside.items()) or "0.0 s inside"))
    zone = facts.get("zones", {}).get(AISLE)
    if zone is not None:
        out.append(("at most one robot in the aisle at once", zone["most_inside"] <= 1,
                    f"most at once: {zone['most_inside']}"
                    + (f" ({', '.join(zone['most_inside_robots'])} at "
                       f"{zone['most_inside_at_s']:.1f} s)" if zone["most_inside"] > 1
                       else "")))
        out.append((f"aisle limit {zone['max_speed_mps']:g} m/s kept (<= +5 %)",
                    zone["max_ratio"] <= 1.05,
                    f"worst speed / limit {zone['max_ratio']:.3f}"
                    + (f" ({zone['robot']})" if zone["robot"] else "")))
    picks = facts.get("picks", [])
    served_items = {d["item"] for d in deliveries}
    lost = [p["item"] for p in picks if p["item"] not in served_items]
    out.append(("every item picked was served", bool(picks) and not lost,
                f"{len(picks)} picked, {len(deliveries)} served"
                + (f"; not served: {lost}" if lost else "")))
    return out


# ---- the launcher ----------------------------------------------------------------------

@dataclass
class Watch:
    """What the launcher heard (ROS thread writes, the table reads)."""

    steps: list[dict[str, Any]] = field(default_factory=list)
    state: dict[str, Any] = field(default_factory=dict)
    finished: dict[str, Any] | None = None
    brokers: list[str] = field(default_factory=list)
    malformed: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_order(self, data: str) -> None:
        try:
            msg = json.loads(data)
            step, detail = msg["step"], msg["detail"]
        except (ValueError, KeyError, TypeError):
            with self.lock:
                self.malformed += 1
            return
        with self.lock:
            self.steps.append(msg)
            if step == "finished":
                self.finished = detail
            elif step == "brokers":
                self.brokers = list(detail.get("brokers", []))

    def on_state(self, data: str) -> None:
        try:
            state = json.loads(data)
        except ValueError:
            with self.lock:
                self.malformed += 1
            return
        with self.lock:
            self.state = state


def robot_config(kind: str, namespace: str, world: str) -> dict[str, Any]:
    """The robot YAML of one robot of the scenario: its kind's template with its
    namespace, agent name and world."""
    cfg: dict[str, Any] = yaml.safe_load(CONFIGS[kind].read_text())
    cfg["namespace"] = namespace
    cfg["agent"] = {**cfg.get("agent", {}), "name": namespace, "lease_s": LEASE_S}
    for section in ("behaviors", "logics"):
        for spec in cfg.get(section, {}).values():
            if "world" in spec.get("params", {}):
                spec["params"]["world"] = world
    return cfg


def _progress(watch: Watch, started: float) -> Group:
    from rich.console import Group
    from rich.table import Table

    with watch.lock:
        state = dict(watch.state)
        steps = list(watch.steps)
    sim_s = float(state.get("time_s", 0.0))
    wall = time.monotonic() - started
    robots = Table(title=f"sim {sim_s:6.1f} s   wall {wall:5.0f} s", title_justify="left")
    for col in ("robot", "holds", "x", "y", "lift"):
        robots.add_column(col)
    for ns, r in sorted(state.get("robots", {}).items()):
        robots.add_row(ns, r.get("item") or "", f"{r['x_m']:.2f}", f"{r['y_m']:.2f}",
                       "" if r.get("lift_m") is None else f"{r['lift_m']:.2f}")
    orders = Table(title="orders", title_justify="left")
    for col in ("order", "last step", "detail"):
        orders.add_column(col)
    last: dict[str, tuple[str, str]] = {}
    for s in steps:
        d = s["detail"]
        tid = d.get("task")
        if isinstance(tid, str):
            info = d.get("members") or d.get("event") or d.get("reason") or ""
            last[tid] = (s["step"], json.dumps(info) if not isinstance(info, str) else info)
    for tid, (step, info) in sorted(last.items()):
        orders.add_row(tid, step, info[:70])
    return Group(robots, orders)


def _summary(outcomes: dict[str, dict[str, Any]], facts: dict[str, Any]) -> Any:
    from rich.table import Table

    table = Table(title="who did which role")
    for col in ("order", "kind", "table", "plan", "role", "robot", "in the physics"):
        table.add_column(col)
    for tid, o in outcomes.items():
        steps = role_steps(facts, o)
        for role, robot in (o.get("members") or {}).items():
            table.add_row(tid, o.get("kind", ""), o.get("table") or "", o.get("plan") or "",
                          role, robot, "; ".join(steps.get(role, [])) or "-")
    return table


def annotate(picture: Path, facts: dict[str, Any], outcomes: dict[str, dict[str, Any]],
             *, world: str | Path, scale_px_per_m: float = 60.0, margin_m: float = 0.5
             ) -> None:
    """Draw on the sim's picture who did which role: the meeting radius, each hand-over
    and delivery where it happened, and a legend of the orders' roles under the map."""
    from PIL import Image, ImageDraw, ImageFont

    from robots.world import load_world

    depth = load_world(world).floor.size_m[1]

    def px(x: float, y: float) -> tuple[float, float]:
        return ((x + margin_m) * scale_px_per_m, (depth + margin_m - y) * scale_px_per_m)

    base = Image.open(picture).convert("RGB")
    legend = []
    for tid, o in outcomes.items():
        steps = role_steps(facts, o)
        legend.append(f"{tid} ({o.get('kind')} to {o.get('table')}): {o.get('state')}, "
                      f"plan {o.get('plan')}")
        legend += [f"    {r} = {b}: {', '.join(steps.get(r, [])) or 'nothing'}"
                   for r, b in (o.get("members") or {}).items()]
    font = ImageFont.load_default(size=13)
    img = Image.new("RGB", (base.width, base.height + 17 * (len(legend) + 1) + 10),
                    (30, 30, 30))
    img.paste(base, (0, 0))
    draw = ImageDraw.Draw(img)
    for name, (mx, my) in facts.get("meeting", {}).items():
        cx, cy = px(mx, my)
        r = HAND_OVER_RADIUS_M * scale_px_per_m
        draw.ellipse((cx - r, cy - r, cx + r, cy + r), outline=(60, 160, 255), width=2)
        draw.text((cx - r, cy + r + 2), f"{name}: hand-over radius {HAND_OVER_RADIUS_M:g} m",
                  fill=(20, 60, 160), font=font)
    for h in facts.get("hand_overs", []):
        for key in ("giver_xy", "taker_xy"):
            x, y = px(*h[key])
            draw.ellipse((x - 6, y - 6, x + 6, y + 6), outline=(60, 160, 255), width=3)
        gx, gy = px(*h["giver_xy"])
        tx, ty = px(*h["taker_xy"])
        draw.line((gx, gy, tx, ty), fill=(60, 160, 255), width=3)
        draw.text((gx - 20, gy + 12), f"{h['giver']} -> {h['taker']} {h['time_s']:.0f} s",
                  fill=(20, 60, 160), font=font)
    for d in facts.get("deliveries", []):
        x, y = px(d["x_m"], d["y_m"])
        draw.rectangle((x - 6, y - 6, x + 6, y + 6), outline=(0, 150, 0), width=3)
        task = next((t for t, o in outcomes.items() if o.get("table") == d["table"]), "?")
        draw.text((x - 40, y + 12), f"{task}: {d['robot']} {d['time_s']:.0f} s",
                  fill=(0, 90, 0), font=font)
    y0 = base.height + 6
    draw.text((8, y0), "who did which role (blue: hand-overs, green: where served)",
              fill=(235, 235, 235), font=font)
    for i, line in enumerate(legend, start=1):
        draw.text((8, y0 + 17 * i), line, fill=(235, 235, 235), font=font)
    img.save(picture)


def run_serve(console: Console, *, world: str = WORLD, kobukis: int = 2,
              minutes: float = 5.0, fast: bool = False, out_dir: Path = Path("out")
              ) -> int:
    """Run the scenario (see the module docstring); 0 when every check held."""
    from rich.live import Live
    from std_msgs.msg import String

    from beehave.ros.context import RosContext
    from behaviours.demos.checks import Processes, checks_table, process_failures
    from behaviours.market.cafe import ORDERS_QOS, ORDERS_TOPIC, cafe_orders
    from behaviours.market.serving import SERVE_STATE, STATE_QOS

    log_dir = out_dir / "serve"
    log_dir.mkdir(parents=True, exist_ok=True)
    report_path, picture = out_dir / "serve_report.json", out_dir / "serve.png"
    result_path = log_dir / "outcomes.json"
    for stale in (report_path, result_path):
        stale.unlink(missing_ok=True)
    expected = [t.id for t in cafe_orders(world)]
    py = sys.executable
    procs = Processes(log_dir, cwd=ROOT)
    watch = Watch()
    sim_limit_s = minutes * 60.0
    now_s, wall_s, failed = 0.0, 0.0, {}
    try:
        procs.start("sim", [py, "-m", "behaviours.demos.serve", "sim", world, "--robots",
                            str(kobukis), *(["--fast"] if fast else []), "--report",
                            str(report_path), "--picture", str(picture)])
        names = [("emili", "emili1")] + [("kobuki", f"kobuki{k}")
                                          for k in range(1, kobukis + 1)]
        for kind, ns in names:
            cfg = log_dir / f"{ns}.yaml"
            cfg.write_text(yaml.safe_dump(robot_config(kind, ns, world), sort_keys=False))
            procs.start(ns, [py, "-m", "beehave.cli", "run", str(cfg)])
        procs.start("keeper", [py, "-m", "behaviours.market.serving", AISLE, "--world", world,
                               "--lease-s", str(LEASE_S)])
        procs.start("orders", [py, "-m", "behaviours.market.cafe", "orders", "--world", world,
                               "--brokers", str(len(names)), "--keepers", "1",
                               "--lease-s", str(LEASE_S), "--result", str(result_path)])
        with RosContext() as ros:
            node = ros.create_node("serve_watch")
            node.create_subscription(String, ORDERS_TOPIC, lambda m: watch.on_order(m.data),
                                     ORDERS_QOS)
            node.create_subscription(String, SERVE_STATE, lambda m: watch.on_state(m.data),
                                     STATE_QOS)
            started = time.monotonic()
            wall_limit_s = 120.0 + sim_limit_s * (1.0 if fast else 1.5)
            with Live(_progress(watch, started), console=console, refresh_per_second=2,
                      transient=not console.is_terminal) as live:
                while True:
                    time.sleep(0.5)
                    live.update(_progress(watch, started))
                    with watch.lock:
                        now_s = float(watch.state.get("time_s", 0.0))
                        finished = watch.finished is not None or result_path.exists()
                    failed = procs.dead()
                    if failed or finished or now_s >= sim_limit_s \
                            or time.monotonic() - started > wall_limit_s:
                        break
            wall_s = time.monotonic() - started
        procs.stop([n for n in procs.procs if n != "sim"])
        procs.stop(["sim"])
    finally:
        procs.kill_all()
    if not report_path.exists():
        console.print(f"[red]FAILED:[/] the simulation wrote no report ({report_path}); see "
                      f"{log_dir / 'sim.log'}")
        return 1
    facts = json.loads(report_path.read_text())
    # The order source's own record decides; the topic is for the live view.
    final = json.loads(result_path.read_text()) if result_path.exists() else None
    with watch.lock:
        final = final or watch.finished
    outcomes = dict((final or {}).get("outcomes", {}))
    results = checks(facts, outcomes, expected=expected)
    results += process_failures(failed, log_dir)
    if final is None:
        results.append(("orders settled in time", False,
                        f"not within {minutes:g} sim minutes ({now_s:.0f} s sim, "
                        f"{wall_s:.0f} s wall)"))
    console.print(_summary(outcomes, facts))
    console.print(checks_table(f"serve summary — EMILI + {kobukis} Kobukis, "
                               f"{facts['time_s']:.0f} s sim in {wall_s:.0f} s wall", results))
    if watch.malformed:  # counted by the watcher: shown, never silent (as the fleet does)
        console.print(f"[yellow]unreadable messages:[/] {watch.malformed}")
    with watch.lock, open(log_dir / "orders.jsonl", "w") as steps:
        steps.writelines(json.dumps(s) + "\n" for s in watch.steps)  # every auction step
    if picture.exists():
        annotate(picture, facts, outcomes, world=world)
    console.print(f"picture: {picture}   facts: {report_path}   logs: {log_dir}/")
    passed = all(ok for _, ok, _ in results)
    print(json.dumps({"serve": {"kobukis": kobukis, "sim_s": facts["time_s"],
                                "wall_s": round(wall_s, 1), "passed": passed,
                                "outcomes": {t: {"plan": o.get("plan"),
                                                 "members": o.get("members"),
                                                 "state": o.get("state")}
                                             for t, o in outcomes.items()},
                                "checks": [[n, ok] for n, ok, _ in results]}}), flush=True)
    return 0 if passed else 1


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["sim"]:
        return sim_main(argv[1:])
    parser = argparse.ArgumentParser(prog="beehave fleet --scenario serve", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", choices=["serve"], default="serve")
    parser.add_argument("world", nargs="?", default=WORLD,
                        help="a world name or YAML path with the serve scenario's stations "
                             "(shelf_open, shelf_narrow, meeting, table1..3), an EMILI and "
                             "Kobukis (default: serve)")
    parser.add_argument("--robots", type=int, default=2, metavar="N",
                        help=f"how many Kobukis besides EMILI (1..{MAX_KOBUKIS}, default 2)")
    parser.add_argument("--minutes", type=float, default=5.0, metavar="M",
                        help="at most this many sim minutes (default 5)")
    parser.add_argument("--fast", action="store_true",
                        help="as fast as the machine goes (lockstep), not at real time")
    parser.add_argument("--out", default="out", metavar="FOLDER",
                        help="where serve.png, serve_report.json and the logs go")
    parser.add_argument("--signed", action="store_true",
                        help="every agent in signed mode, with a fleet authority and "
                             "certificates made in FOLDER/keys (docs/agents.md#trust-model)")
    args = parser.parse_args(argv)
    if not 1 <= args.robots <= MAX_KOBUKIS:
        parser.error(f"--robots (the number of Kobukis) must be 1..{MAX_KOBUKIS}, "
                     f"got {args.robots}")
    if not (math.isfinite(args.minutes) and 0 < args.minutes <= 60):
        parser.error(f"--minutes must be in (0, 60], got {args.minutes}")
    try:
        serve_world(args.world, args.robots)
        from behaviours.market.cafe import cafe_orders

        cafe_orders(args.world)
    except Exception as exc:  # a bad world: name it, with what was wrong
        parser.error(f"world {args.world!r}: {exc}")
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.signed:  # the children take their keys from the environment
        from beehave.agents.trust import signed_environment

        os.environ.update(signed_environment(Path(args.out) / "keys", [
            "emili1", *(f"kobuki{k}" for k in range(1, args.robots + 1)),
            f"keeper_{AISLE}", "orders"]))
    from rich.console import Console

    console = Console()
    console.rule(f"[bold]beehave fleet --scenario serve — EMILI + {args.robots} Kobukis "
                 f"in {args.world}")
    return run_serve(console, world=args.world, kobukis=args.robots, minutes=args.minutes,
                     fast=args.fast, out_dir=Path(args.out))


if __name__ == "__main__":
    raise SystemExit(main())
