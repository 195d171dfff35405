"""``beehave fleet``: the factory fleet of seed paper 000, every agent in its own process.

The simulation (``beehave sim factory --robots N``), every ATV's two managers (``beehave
run`` of a generated ``atvK.yaml``), every machine agent and every charging-station agent
run as separate processes over DDS; this process only watches (``/factory/state``,
``/fleet/orders``, the agent directory) and shows a live table. After ``--minutes`` of sim
time it stops them all (the sim last: it writes the facts it measured and the picture) and
checks, in the physics:

- no machine ran empty;
- no two robots charged at one station at once;
- no battery reached zero;
- no robot drove faster than a zone's limit by more than 5 %;
- every contract was awarded at most once: no order delivered twice, no award while an
  award stood (the mission controller's state machines), and the physical deliveries per
  machine match the orders the machine saw done (give or take the ones under way);
- work was done: at least one delivery, so that an idle fleet fails;
- no order was late: every order delivered before its machine would have fallen to its
  safety stock (20 % of its capacity; from its level and consumption when it ordered),
  none still open past that.

It prints, writes into the JSON report and draws beside the picture the figures a
logistics engineer reads: per order its lead time (placed → delivered, sim seconds) and
whether it was late; per ATV its utilisation (the share of the run it had an order: from
an award to its delivery or loss), distance driven and time charging; throughput
(deliveries per hour of sim time); per machine the time it starved (ran empty).

``--dispatch single`` turns coordination off (every machine calls atv1 alone): the
baseline the market is compared with, and a run whose checks fail.

Exit 0 when every check passed, 1 otherwise, 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from behaviours.demos.checks import Processes, checks_table, process_failures
from behaviours.fleet.mission import ORDERS_QOS, ORDERS_TOPIC
from behaviours.fleet.site import site
from robots.topics import FACTORY_STATE

#: The agents' directory lease. Above the 2 s default: at full simulation speed a 2-core
#: machine runs a dozen busy processes, and an announcement late by more than the lease
#: reads as a death (and costs a re-award).
LEASE_S = 3.0
#: The sim's /clock rate for a fleet (see run_fleet).
CLOCK_RATE_HZ = 50.0


ATV_TEMPLATE = Path(__file__).resolve().parents[2] / "robots" / "config" / "atv.yaml"


def atv_config(namespace: str, world: str) -> dict[str, Any]:
    """The robot YAML of one ATV: ``robots/config/atv.yaml`` with its namespace, agent name
    and world (written to ``OUT/fleet/<namespace>.yaml``)."""
    cfg: dict[str, Any] = yaml.safe_load(ATV_TEMPLATE.read_text())
    cfg["namespace"] = namespace
    cfg["agent"] = {**cfg.get("agent", {}), "name": namespace, "lease_s": LEASE_S}
    # The fleet starts the sim first and reports its death itself: on a loaded machine the
    # first /clock can take longer than the usual 30 s to be discovered (seen: 3 fleets on
    # 2 cores), and an ATV giving up then would be a false failure.
    cfg["sim_clock_timeout_s"] = max(float(cfg.get("sim_clock_timeout_s", 30.0)), 120.0)
    for section in ("behaviors", "logics"):
        for spec in cfg.get(section, {}).values():
            if "world" in spec.get("params", {}):
                spec["params"]["world"] = world
    return cfg


@dataclass
class Watch:
    """What the watcher heard (written by the ROS thread, read by the table)."""

    state: dict[str, Any] = field(default_factory=dict)
    orders: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Every order report, in the order they came (the figures read the award times).
    history: list[dict[str, Any]] = field(default_factory=list)
    violations: list[str] = field(default_factory=list)
    agents: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: The latest agent messages (copies from ``MESSAGES_TOPIC``), newest last: as many as
    #: the web view lists.
    messages: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=50))
    #: Messages that could not be read, by topic (shown in the summary, never silent).
    malformed: dict[str, int] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def _bad(self, topic: str) -> None:
        with self.lock:
            self.malformed[topic] = self.malformed.get(topic, 0) + 1

    def on_state(self, data: str) -> None:
        try:
            state = json.loads(data)
        except ValueError:
            self._bad(FACTORY_STATE)
            return
        with self.lock:
            self.state = state

    def on_order(self, data: str) -> None:
        try:
            report = json.loads(data)
            order = report["order"]
        except (ValueError, KeyError, TypeError):
            self._bad(ORDERS_TOPIC)
            return
        with self.lock:
            if report.get("violation"):
                self.violations.append(f"order {order}: {report['violation']}")
            previous = self.orders.get(order)
            if previous is not None and previous["state"] == "delivered" \
                    and report["state"] == "delivered":
                self.violations.append(f"order {order} delivered twice")
            self.orders[order] = report
            self.history.append(report)

    def on_directory(self, data: str) -> None:
        from beehave.agents.directory import DIRECTORY_TOPIC

        try:
            entry = json.loads(data)
            name = entry["agent"]
        except (ValueError, KeyError, TypeError):
            self._bad(DIRECTORY_TOPIC)
            return
        with self.lock:
            self.agents[name] = entry

    def on_message(self, data: str) -> None:
        """A copy of an agent message (see :data:`beehave.agents.agent.MESSAGES_TOPIC`)."""
        from beehave.agents.agent import MESSAGES_TOPIC
        from beehave.agents.message import Message

        try:
            message = Message.from_json(data)
        except ValueError:
            self._bad(MESSAGES_TOPIC)
            return
        content = json.dumps(message.content, separators=(",", ":"))
        row = {"sent": time.strftime("%H:%M:%S", time.localtime(message.sent_at)),
               "performative": message.performative.value, "from": message.sender,
               "to": ", ".join(message.receivers), "protocol": message.protocol or "",
               "conversation": message.conversation_id,
               "content": content if len(content) <= 80 else content[:79] + "…"}
        with self.lock:
            self.messages.append(row)


def announced_url(log: Path) -> Callable[[], str | None]:
    """The address ``beehave run --http`` announces in its log (``web view and API at
    URL``), once it has: what the fleet's web view forwards a robot's own view to."""
    found: list[str] = []

    def url() -> str | None:
        if not found:
            with contextlib.suppress(OSError):
                match = re.search(r"web view and API at (\S+)", log.read_text(errors="replace"))
                if match:
                    found.append(match.group(1))
        return found[0] if found else None

    return url


def fleet_view(watch: Watch) -> dict[str, list[dict[str, Any]]]:
    """What ``beehave fleet --http`` serves at ``GET /api/fleet`` (the web view draws each
    section as a live table): the ATVs in the physics, the orders and their contracts,
    every agent of the directory with what it offers, and the latest messages between
    them, newest first."""
    with watch.lock:
        state = dict(watch.state)
        orders = list(watch.orders.values())
        agents = dict(watch.agents)
        messages = list(reversed(watch.messages))
    robots = [{"atv": ns, "battery_pct": round(100 * r["battery_fraction"], 1),
               "load": r["load"], "zone": r["zone"], "speed_mps": round(r["speed_mps"], 2),
               "x_m": round(r["x_m"], 2), "y_m": round(r["y_m"], 2),
               "charging_at": r["charging_at"]}
              for ns, r in sorted(state.get("robots", {}).items())]
    contracts = [{"order": o["order"], "machine": o["machine"], "state": o["state"],
                  "atv": o["atv"], "awards": " → ".join(o["awards"]), "reason": o["reason"]}
                 for o in sorted(orders, key=lambda o: o["stamp"], reverse=True)[:50]]
    directory = [{"agent": name, "state": e.get("state"),
                  "services": ", ".join(f"{k} {v}" if v else k
                                        for k, v in e.get("services", {}).items())}
                 for name, e in sorted(agents.items())]
    machines = [{"machine": n, "level": round(m["level"], 1), "capacity": m["capacity"]}
                for n, m in sorted(state.get("machines", {}).items())]
    return {"robots": robots, "machines": machines, "contracts": contracts,
            "agents": directory, "messages": messages}


def _table(watch: Watch, started: float) -> Group:
    with watch.lock:
        state = dict(watch.state)
        orders = list(watch.orders.values())
        agents = dict(watch.agents)
    sim_s = float(state.get("time_s", 0.0))
    wall = time.monotonic() - started
    robots = Table(title=f"sim {sim_s:6.1f} s   wall {wall:5.0f} s   "
                         f"×{sim_s / wall if wall > 0 else 0:.2f}", title_justify="left")
    for col in ("ATV", "behaviour", "battery", "load", "zone", "speed", "charging"):
        robots.add_column(col)
    for ns, r in sorted(state.get("robots", {}).items()):
        entry = agents.get(ns, {})
        offers = ", ".join(entry.get("services", {})) if entry.get("state") == "alive" else "—"
        robots.add_row(ns, offers or "(charging)", f"{100 * r['battery_fraction']:.0f} %",
                       f"{r['load']:g}" if r["load"] else "", r["zone"] or "",
                       f"{r['speed_mps']:.2f}", r["charging_at"] or "")
    machines = Table(title="machines", title_justify="left")
    for col in ("machine", "level", "open order", "state", "ATV", "awards", "delivered",
                "late"):
        machines.add_column(col)
    # Only an order still open is "open": a delivered or failed one is counted instead.
    latest: dict[str, dict[str, Any]] = {}
    delivered: dict[str, int] = {}
    late: dict[str, list[str]] = {}
    for o in orders:
        if o["state"] in OPEN_STATES:
            latest[o["machine"]] = o
        elif o["state"] == "delivered":
            delivered[o["machine"]] = delivered.get(o["machine"], 0) + 1
        if is_late(o["state"], o.get("sim_s"), o.get("due_sim_s"), sim_s):
            late.setdefault(o["machine"], []).append(o["order"])
    for name, m in sorted(state.get("machines", {}).items()):
        o = latest.get(name, {})
        level = m["level"] / m["capacity"]
        machines.add_row(name, Text(f"{100 * level:3.0f} %",
                                    style="red" if level < 0.2 else "green"),
                         o.get("order", ""), o.get("state", ""), o.get("atv") or "",
                         " → ".join(o.get("awards", [])), str(delivered.get(name, 0)),
                         Text(", ".join(late.get(name, [])), style="red"))
    stations = Table(title="charging stations", title_justify="left")
    for col in ("agent", "station", "reserved by", "charging now"):
        stations.add_column(col)
    occupants = {k: v["occupants"] for k, v in state.get("stations", {}).items()}
    for name, entry in sorted(agents.items()):
        props = entry.get("services", {}).get("charging")
        if props is None or entry.get("state") != "alive":
            continue
        stations.add_row(name, props.get("station", ""), props.get("holder") or "",
                         ", ".join(occupants.get(props.get("station", ""), [])))
    return Group(robots, machines, stations)


def _watch(ros: Any, watch: Watch) -> None:
    from std_msgs.msg import String

    from beehave.agents.agent import DIRECTORY_READER_QOS, MESSAGES_QOS, MESSAGES_TOPIC
    from beehave.agents.directory import DIRECTORY_TOPIC
    from hal.factory import STATE_QOS

    node = ros.create_node("fleet_watch")
    node.create_subscription(String, FACTORY_STATE, lambda m: watch.on_state(m.data),
                             STATE_QOS)
    node.create_subscription(String, ORDERS_TOPIC, lambda m: watch.on_order(m.data),
                             ORDERS_QOS)
    node.create_subscription(String, DIRECTORY_TOPIC, lambda m: watch.on_directory(m.data),
                             DIRECTORY_READER_QOS)
    node.create_subscription(String, MESSAGES_TOPIC, lambda m: watch.on_message(m.data),
                             MESSAGES_QOS)


OPEN_STATES = ("created", "announced", "awarded")


def is_late(state: str, delivered_s: float | None, due_s: float | None,
            now_s: float) -> bool:
    """Whether an order in ``state`` is late at ``now_s`` (sim seconds): delivered after it
    was due, or still open past it. A failed order is failed, not late; one without a due
    time (its machine had no sim time yet) is never late. The one rule of the live table,
    :func:`figures` and the check."""
    if due_s is None:
        return False
    if state == "delivered":
        return delivered_s is not None and delivered_s > due_s
    return state in OPEN_STATES and now_s > due_s


def _union_s(spans: list[tuple[float, float]]) -> float:
    """The length of the union of ``spans`` ((start, end) pairs)."""
    total, reach = 0.0, -math.inf
    for start, end in sorted(spans):
        if end <= reach:
            continue
        total += end - max(start, reach)
        reach = end
    return total


def figures(report: dict[str, Any], history: list[dict[str, Any]],
            sim_s: float) -> dict[str, Any]:
    """What a logistics engineer reads of a run (all times in sim seconds): per order its
    lead time and lateness, per ATV its utilisation, distance and charging, throughput,
    per machine its starvation. ``report`` is the sim's facts, ``history`` every order
    report in the order they came (:attr:`Watch.history`), ``sim_s`` the run's end."""
    latest: dict[str, dict[str, Any]] = {}
    awarded_at: dict[str, tuple[str, float]] = {}  # order → (atv, since)
    spans: dict[str, list[tuple[float, float]]] = {}
    delivered_at: dict[str, float] = {}
    for r in history:
        order, at = r["order"], r.get("sim_s")
        latest[order] = r
        if at is None:
            continue
        held = awarded_at.pop(order, None)
        if held is not None:
            spans.setdefault(held[0], []).append((held[1], at))
        if r["state"] == "awarded" and r.get("atv"):
            awarded_at[order] = (r["atv"], at)
        elif r["state"] == "delivered":
            delivered_at.setdefault(order, at)
    for atv, since in awarded_at.values():  # still under way at the end
        spans.setdefault(atv, []).append((since, sim_s))
    orders = []
    for order, r in latest.items():
        placed, due = r.get("placed_sim_s"), r.get("due_sim_s")
        done = delivered_at.get(order)
        lead = None if done is None or placed is None else done - placed
        state = r["state"]
        late = is_late(state, done, due, sim_s)
        orders.append({"order": order, "machine": r["machine"], "state": state,
                       "atv": r.get("atv"), "awards": list(r.get("awards", [])),
                       "placed_s": None if placed is None else round(placed, 1),
                       "delivered_s": None if done is None else round(done, 1),
                       "due_s": None if due is None else round(due, 1),
                       "lead_time_s": None if lead is None else round(lead, 1),
                       "late": late})
    orders.sort(key=lambda o: (o["placed_s"] is None, o["placed_s"] or 0.0, o["order"]))
    leads = [o["lead_time_s"] for o in orders if o["lead_time_s"] is not None]
    robots = report.get("robots", {})
    atvs = {ns: {"utilisation": round(min(1.0, _union_s(spans.get(ns, [])) / sim_s), 3)
                 if sim_s > 0 else 0.0,
                 "busy_s": round(_union_s(spans.get(ns, [])), 1),
                 "deliveries": r.get("deliveries", 0),
                 "distance_m": round(r.get("distance_m", 0.0), 1),
                 "charging_s": round(r.get("charging_s", 0.0), 1)}
            for ns, r in sorted(robots.items(), key=lambda kv: (len(kv[0]), kv[0]))}
    machines = {n: {"starved_s": round(m["empty_s"], 1),
                    "first_empty_s": None if m.get("first_empty_at_s") is None
                    else round(m["first_empty_at_s"], 1),
                    "deliveries": m.get("deliveries", 0),
                    "lowest_level": round(m["min_level"], 1)}
                for n, m in sorted(report.get("machines", {}).items())}
    delivered = len(report.get("deliveries", []))
    return {
        "sim_s": round(sim_s, 1),
        "throughput_per_h": round(delivered / sim_s * 3600.0, 1) if sim_s > 0 else 0.0,
        "deliveries": delivered,
        "orders": {"placed": len(orders),
                   "delivered": sum(1 for o in orders if o["state"] == "delivered"),
                   "open": sum(1 for o in orders if o["state"] in OPEN_STATES),
                   "failed": sum(1 for o in orders if o["state"] == "failed"),
                   "late": sum(1 for o in orders if o["late"]),
                   "lead_time_mean_s": round(sum(leads) / len(leads), 1) if leads else None,
                   "lead_time_max_s": max(leads) if leads else None},
        "order_list": orders, "atvs": atvs, "machines": machines,
        "starved_s": round(sum(m["starved_s"] for m in machines.values()), 1),
    }


def figures_tables(figs: dict[str, Any]) -> Group:
    """:func:`figures` as the summary's tables: ATVs, machines, orders."""
    o = figs["orders"]
    atvs = Table(title=f"throughput {figs['throughput_per_h']:g} deliveries / h   orders: "
                       f"{o['placed']} placed, {o['delivered']} delivered, {o['open']} open, "
                       f"{o['late']} late   lead time mean "
                       f"{_num(o['lead_time_mean_s'])} s, max {_num(o['lead_time_max_s'])} s",
                 title_justify="left")
    for col in ("ATV", "utilisation", "deliveries", "distance", "charging"):
        atvs.add_column(col)
    for ns, a in figs["atvs"].items():
        atvs.add_row(ns, f"{100 * a['utilisation']:.0f} %", str(a["deliveries"]),
                     f"{a['distance_m']:.0f} m", f"{a['charging_s']:.0f} s")
    machines = Table(title="machines", title_justify="left")
    for col in ("machine", "starved", "deliveries", "lowest level"):
        machines.add_column(col)
    for name, m in figs["machines"].items():
        machines.add_row(name, Text(f"{m['starved_s']:.0f} s",
                                    style="red" if m["starved_s"] > 0 else "green"),
                         str(m["deliveries"]), f"{m['lowest_level']:g}")
    orders = Table(title="orders (sim seconds)", title_justify="left")
    for col in ("order", "ATV", "placed", "delivered", "lead time", "due", "state"):
        orders.add_column(col)
    for r in figs["order_list"]:
        orders.add_row(r["order"], " → ".join(r["awards"]), _num(r["placed_s"]),
                       _num(r["delivered_s"]), _num(r["lead_time_s"]), _num(r["due_s"]),
                       Text("late", style="red") if r["late"] else r["state"])
    return Group(atvs, machines, orders)


def _num(value: float | None) -> str:
    return "—" if value is None else f"{value:.0f}"


def draw_figures(picture: Path, figs: dict[str, Any]) -> None:
    """Add the figures to the sim's picture, in a panel on its right: utilisation bars per
    ATV with its distance, starvation per machine, each order's lead time against the time
    it had (late ones in red), throughput."""
    from PIL import Image, ImageDraw, ImageFont

    base = Image.open(picture).convert("RGB")
    panel_w = 460
    image = Image.new("RGB", (base.width + panel_w, base.height), (30, 30, 34))
    image.paste(base, (0, 0))
    draw = ImageDraw.Draw(image)
    draw.font = ImageFont.load_default(size=12)
    x0, y = base.width + 12, 8
    ink, dim, red, green = (235, 235, 235), (160, 160, 165), (220, 60, 60), (80, 180, 90)
    o = figs["orders"]
    for line in (f"throughput {figs['throughput_per_h']:g} deliveries/h "
                 f"over {figs['sim_s']:.0f} s",
                 f"orders {o['placed']} placed, {o['delivered']} delivered, "
                 f"{o['open']} open, {o['late']} late",
                 f"lead time mean {_num(o['lead_time_mean_s'])} s, "
                 f"max {_num(o['lead_time_max_s'])} s"):
        draw.text((x0, y), line, fill=ink)
        y += 16
    y += 6
    draw.text((x0, y), "ATV utilisation (busy share), distance", fill=dim)
    y += 16
    bar_w = 200
    for ns, a in figs["atvs"].items():
        draw.text((x0, y), ns, fill=ink)
        draw.rectangle([x0 + 50, y + 2, x0 + 50 + bar_w, y + 12], outline=dim)
        draw.rectangle([x0 + 50, y + 2, x0 + 50 + round(bar_w * a["utilisation"]), y + 12],
                       fill=green)
        draw.text((x0 + 58 + bar_w, y), f"{100 * a['utilisation']:.0f} %  "
                                         f"{a['distance_m']:.0f} m", fill=ink)
        y += 16
    y += 6
    draw.text((x0, y), "machines: time starved (empty)", fill=dim)
    y += 16
    for name, m in figs["machines"].items():
        draw.text((x0, y), f"{name}: {m['starved_s']:.0f} s", fill=red if m["starved_s"] > 0
                  else ink)
        y += 16
    y += 6
    draw.text((x0, y), "orders: lead time (bar) and time until due (|)", fill=dim)
    y += 16
    rows = [r for r in figs["order_list"] if r["placed_s"] is not None]
    longest = max([1.0, *(r["lead_time_s"] or 0.0 for r in rows),
                   *((r["due_s"] or 0.0) - (r["placed_s"] or 0.0) for r in rows)])
    scale = 260 / longest
    for r in rows:
        if y > image.height - 14:
            draw.text((x0, y), f"… {len(rows)} orders in all", fill=dim)
            break
        draw.text((x0, y), r["order"], fill=red if r["late"] else ink)
        lead = r["lead_time_s"]
        if lead is None:  # still open: how long it has waited
            lead = figs["sim_s"] - r["placed_s"]
            colour = red if r["late"] else dim
        else:
            colour = red if r["late"] else green
        left = x0 + 90
        draw.rectangle([left, y + 3, left + max(1, round(lead * scale)), y + 11], fill=colour)
        if r["due_s"] is not None:
            due_x = left + round((r["due_s"] - r["placed_s"]) * scale)
            draw.line([due_x, y, due_x, y + 13], fill=ink, width=2)
        y += 14
    image.save(picture, format="PNG", optimize=True)


def checks(report: dict[str, Any], watch: Watch,
           figs: dict[str, Any] | None = None) -> list[tuple[str, bool, str]]:
    """(check, passed, what was measured) — the physics from the sim's report, the
    contracts from the mission controllers' reports, lateness from :func:`figures`."""
    out: list[tuple[str, bool, str]] = []
    machines = report.get("machines", {})
    empty = [f"{n} {m['empty_s']:.0f} s" for n, m in machines.items() if m["empty_s"] > 0]
    lowest = min((m["min_level"] / m["capacity"] for m in machines.values()), default=0.0)
    out.append(("no machine ran empty", not empty and bool(machines),
                "; ".join(empty) or f"lowest level {lowest:.2f}"))
    stations = report.get("stations", {})
    most = max((s["max_charging"] for s in stations.values()), default=0)
    out.append(("at most one robot charging per station", most <= 1 and bool(stations),
                f"most at once: {most}"))
    robots = report.get("robots", {})
    low = min((r["min_battery_fraction"] for r in robots.values()), default=0.0)
    out.append(("no battery reached zero", low > 0 and bool(robots),
                f"lowest battery {100 * low:.1f} %"))
    zones = report.get("zones", {})
    worst = max((z["max_ratio"] for z in zones.values()), default=0.0)
    out.append(("zone limits kept (≤ +5 %)", worst <= 1.05,
                f"worst speed / limit {worst:.3f}"))
    with watch.lock:
        orders = list(watch.orders.values())
        violations = list(watch.violations)
    done: dict[str, int] = {}
    open_: dict[str, int] = {}
    for o in orders:
        bucket = done if o["state"] == "delivered" else open_ if o["state"] in (
            "announced", "awarded") else None
        if bucket is not None:
            bucket[o["machine"]] = bucket.get(o["machine"], 0) + 1
    physical: dict[str, int] = {}
    for d in report.get("deliveries", []):
        physical[d["machine"]] = physical.get(d["machine"], 0) + 1
    mismatch = [f"{m}: {physical.get(m, 0)} unloaded, {done.get(m, 0)} orders done"
                for m in set(physical) | set(done)
                if not done.get(m, 0) <= physical.get(m, 0) <= done.get(m, 0) + open_.get(m, 0)]
    out.append(("every contract awarded at most once", not violations and not mismatch,
                "; ".join(violations + mismatch)
                or f"{sum(done.values())} orders delivered, "
                   f"{sum(len(o['awards']) for o in orders)} awards"))
    total = len(report.get("deliveries", []))
    out.append(("deliveries made", total > 0, f"{total} in the physics"))
    if figs is not None:
        late = [r["order"] for r in figs["order_list"] if r["late"]]
        o = figs["orders"]
        out.append(("no order late (delivered before its machine fell to 20 %)",
                    not late, f"late: {', '.join(late)}" if late else
                    f"{o['delivered']} delivered in time, lead time max "
                    f"{_num(o['lead_time_max_s'])} s"))
    return out


def run_fleet(console: Console, *, world: str = "factory", robots: int = 4,
              minutes: float = 5.0, fast: bool = False, out_dir: Path = Path("out"),
              record: bool = False, http: tuple[str, int] | None = None,
              order_below: float = 0.6, dispatch: str = "market") -> int:
    places = site(world)
    fleet_dir = out_dir / "fleet"
    fleet_dir.mkdir(parents=True, exist_ok=True)
    report_path, picture = out_dir / "fleet_report.json", out_dir / "fleet.png"
    report_path.unlink(missing_ok=True)
    py = sys.executable
    procs = Processes(fleet_dir)
    watch = Watch()
    sim_s = minutes * 60.0
    from beehave.ros.context import RosContext

    try:
        # /clock at 50 Hz, not 100: every ATV process receives each one (lockstep holds
        # publish the held time anyway, so control loops keep their rate).
        procs.start("sim", [py, "-m", "beehave.cli", "sim", world, "--robots", str(robots),
                            "--clock-rate-hz", str(CLOCK_RATE_HZ),
                            *(["--fast"] if fast else []), "--report", str(report_path),
                            "--picture", str(picture)])
        for name in sorted(places.stations):
            procs.start(name, [py, "-m", "behaviours.fleet.station", name, "--world", world,
                               "--lease-s", str(LEASE_S)])
        for k in range(1, robots + 1):
            ns = f"atv{k}"
            cfg = fleet_dir / f"{ns}.yaml"
            cfg.write_text(yaml.safe_dump(atv_config(ns, world), sort_keys=False))
            recording = ["--record", str(fleet_dir / f"{ns}.mcap")] if record else []
            # With --http, each ATV serves its own view on a free loopback port; the
            # fleet's page forwards to it (docs/http.md, "robots of other processes").
            view = ["--http", "127.0.0.1:0"] if http is not None else []
            procs.start(ns, [py, "-m", "beehave.cli", "run", str(cfg), *recording, *view])
        for name in sorted(places.machines):
            procs.start(name, [py, "-m", "behaviours.fleet.machine", name, "--world", world,
                               "--lease-s", str(LEASE_S), "--below", str(order_below),
                               *(["--only", "atv1"] if dispatch == "single" else [])])
        with RosContext() as ros, contextlib.ExitStack() as web:
            _watch(ros, watch)
            if http is not None:
                from beehave.interfaces.http import serve

                server = serve({}, host=http[0], port=http[1],
                               world=yaml.safe_load(Path(places.world_path).read_text()),
                               fleet=lambda: fleet_view(watch),
                               remotes={f"atv{k}": announced_url(fleet_dir / f"atv{k}.log")
                                        for k in range(1, robots + 1)})
                web.callback(server.stop)
                console.print(f"fleet web view at {server.url}")
            started = time.monotonic()
            # Wall-time bound: a fleet far slower than real time is a failure too.
            wall_limit_s = 120.0 + sim_s * (1.0 if fast else 1.5)
            failed: dict[str, int] = {}
            with Live(_table(watch, started), console=console, refresh_per_second=2,
                      transient=not console.is_terminal) as live:
                while True:
                    time.sleep(0.5)
                    live.update(_table(watch, started))
                    with watch.lock:
                        now_s = float(watch.state.get("time_s", 0.0))
                    failed = procs.dead()
                    if failed or now_s >= sim_s or time.monotonic() - started > wall_limit_s:
                        break
            wall_s = time.monotonic() - started
            console.print(_table(watch, started))
        # The ATVs first: one that charges releases its station, one that delivers lets
        # its machine know, while both still listen; then the machines and stations; the
        # sim last (it writes the facts and the picture).
        atvs = [n for n in procs.procs if n.startswith("atv")]
        procs.stop(atvs)
        procs.stop([n for n in procs.procs if n != "sim" and n not in atvs])
        procs.stop(["sim"])
    finally:
        procs.kill_all()
    if not report_path.exists():
        console.print(f"[red]FAILED:[/] the simulation wrote no report ({report_path}); see "
                      f"{fleet_dir / 'sim.log'}")
        return 1
    report = json.loads(report_path.read_text())
    with watch.lock:
        history = list(watch.history)
    figs = figures(report, history, float(report.get("time_s", now_s)))
    results = checks(report, watch, figs)
    results += process_failures(failed, fleet_dir)
    if now_s < sim_s:
        results.append((f"{minutes:g} sim minutes run", False,
                        f"only {now_s:.0f} s in {wall_s:.0f} s wall"))
    console.print(figures_tables(figs))
    console.print(checks_table(f"fleet summary — {robots} ATVs ({dispatch}), {now_s:.0f} s "
                               f"sim in {wall_s:.0f} s wall (×{now_s / wall_s:.2f})", results))
    passed = all(ok for _, ok, _ in results)
    report["fleet"] = {"robots": robots, "dispatch": dispatch, "figures": figs,
                       "checks": [{"check": n, "passed": ok, "measured": m}
                                  for n, ok, m in results], "passed": passed}
    report_path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    if picture.exists():
        draw_figures(picture, figs)
    if watch.malformed:
        console.print(f"[yellow]unreadable messages:[/] {watch.malformed}")
    console.print(f"picture: {picture}   facts: {report_path}   logs"
                  f"{' and recordings' if record else ''}: {fleet_dir}/")
    print(json.dumps({"fleet": {"robots": robots, "sim_s": round(now_s, 1),
                                "wall_s": round(wall_s, 1),
                                "real_time_factor": round(now_s / wall_s, 3),
                                "dispatch": dispatch,
                                "throughput_per_h": figs["throughput_per_h"],
                                "orders": figs["orders"], "starved_s": figs["starved_s"],
                                "utilisation": {k: v["utilisation"]
                                                for k, v in figs["atvs"].items()},
                                "passed": passed}}), flush=True)
    return 0 if passed else 1


#: ``--scenario`` → what runs. ``follow``, ``handover`` and ``droid`` (both at once) are the
#: MAVLink Droid paper's: a rover follows a rover leading a tour; the quadrotor finishes the
#: mission a wall blocks (docs/mavlink.md).
SCENARIOS = ("factory", "droid", "follow", "handover", "serve")



def _http_address(text: str) -> tuple[str, int]:
    from beehave.interfaces.http.server import address_arg  # fastapi: only when asked

    return address_arg(text)

def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    pre = argparse.ArgumentParser(prog="beehave fleet", add_help=False)
    pre.add_argument("--scenario", choices=SCENARIOS, default="factory")
    known, rest = pre.parse_known_args(argv)
    if known.scenario == "serve":  # the ARCADE paper's SERVE task (docs/allocation.md)
        from behaviours.demos.serve import main as serve_main

        return serve_main(argv)
    if known.scenario != "factory":
        from behaviours.demos.droid import main as droid_main

        # The MAVLink scenario has one rover and one copter: the fleet's other options
        # mean nothing there, and are refused rather than ignored.
        droid = argparse.ArgumentParser(prog=f"beehave fleet --scenario {known.scenario}",
                                        description="a rover and a quadrotor over MAVLink "
                                                    "(docs/mavlink.md)")
        droid.add_argument("--out", default="out", metavar="FOLDER",
                           help=f"where {known.scenario}.png goes")
        droid.add_argument("--fast", action="store_true",
                           help="as fast as the machine goes (lockstep with the robots' "
                                "control loops), not at real time; the same checks")
        droid_args = droid.parse_args(rest)
        out = Path(droid_args.out)
        out.mkdir(parents=True, exist_ok=True)
        return droid_main(["--scenario", known.scenario,
                           "--picture", str(out / f"{known.scenario}.png"),
                           *(["--fast"] if droid_args.fast else [])])
    parser = argparse.ArgumentParser(prog="beehave fleet", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", choices=SCENARIOS, default="factory",
                        help="factory (default): the ROS-JADE factory; follow: over "
                             "MAVLink, a rover leads a tour and another follows; handover: "
                             "a rover meets a wall and the quadrotor finishes its mission; "
                             "droid: both at once (docs/mavlink.md); "
                             "serve: EMILI and Kobukis serve guests through a market with "
                             "coalitions (docs/allocation.md; --help with it for its options)")
    parser.add_argument("world", nargs="?", default="factory",
                        help="a world name or YAML path with machines, depots and charging "
                             "stations (default: factory)")
    parser.add_argument("--robots", type=int, default=4, metavar="N",
                        help="how many ATVs (default 4)")
    parser.add_argument("--minutes", type=float, default=5.0, metavar="M",
                        help="sim minutes to run (default 5)")
    parser.add_argument("--fast", action="store_true",
                        help="as fast as the machine goes (lockstep), not at real time")
    parser.add_argument("--out", default="out", metavar="FOLDER",
                        help="where fleet.png, fleet_report.json and the logs go")
    parser.add_argument("--http", type=_http_address, default=None, metavar="[HOST:]PORT",
                        help="serve the fleet's live tables and the map (docs/http.md) on "
                             "HOST:PORT (127.0.0.1 unless given; 0: a free port)")
    parser.add_argument("--order-below", type=float, default=0.6, metavar="FRACTION",
                        help="a machine orders material when its level falls below this "
                             "fraction of its capacity (default 0.6)")
    parser.add_argument("--dispatch", choices=("market", "single"), default="market",
                        help="market (default): every machine awards its orders by contract "
                             "net to the cheapest bid; single: no coordination, every order "
                             "goes to atv1 alone (the baseline; its checks fail)")
    parser.add_argument("--record", action="store_true",
                        help="record every ATV into FOLDER/fleet/atvK.mcap (one file per "
                             "robot; docs/recording.md: beehave inspect/plot/replay)")
    parser.add_argument("--signed", action="store_true",
                        help="every agent in signed mode, with a fleet authority and "
                             "certificates made in FOLDER/keys (docs/agents.md#trust-model)")
    args = parser.parse_args(argv)
    if not 1 <= args.robots <= 10:
        parser.error(f"--robots must be 1..10 (the parking row), got {args.robots}")
    if not 0 < args.order_below < 1:
        parser.error(f"--order-below must be a fraction in (0, 1), got {args.order_below}")
    if not 0 < args.minutes <= 24 * 60:
        parser.error(f"--minutes must be in (0, 1440], got {args.minutes}")
    try:
        places = site(args.world)
    except Exception as exc:
        parser.error(f"world {args.world!r}: {exc}")
    if not places.machines or not places.depots or not places.stations:
        parser.error(f"world {args.world!r} needs machines, a depot and charging stations "
                     f"(it has {len(places.machines)}, {len(places.depots)}, "
                     f"{len(places.stations)})")
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    if args.signed:  # the children take their keys from the environment
        from beehave.agents.trust import signed_environment

        os.environ.update(signed_environment(Path(args.out) / "keys", [
            *places.stations, *places.machines,
            *(f"atv{k}" for k in range(1, args.robots + 1))]))
    console = Console()
    console.rule(f"[bold]beehave fleet — {args.robots} ATVs in {args.world}")
    return run_fleet(console, world=args.world, robots=args.robots, minutes=args.minutes,
                     fast=args.fast, out_dir=Path(args.out), record=args.record,
                     http=args.http, order_below=args.order_below, dispatch=args.dispatch)


if __name__ == "__main__":
    raise SystemExit(main())
