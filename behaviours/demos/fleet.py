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
- and work was done: at least one delivery, so that an idle fleet fails.

Exit 0 when every check passed, 1 otherwise, 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import contextlib
import json
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
    for col in ("machine", "level", "open order", "state", "ATV", "awards"):
        machines.add_column(col)
    latest: dict[str, dict[str, Any]] = {}
    for o in orders:
        latest[o["machine"]] = o
    for name, m in sorted(state.get("machines", {}).items()):
        o = latest.get(name, {})
        level = m["level"] / m["capacity"]
        machines.add_row(name, Text(f"{100 * level:3.0f} %",
                                    style="red" if level < 0.2 else "green"),
                         o.get("order", ""), o.get("state", ""), o.get("atv") or "",
                         " → ".join(o.get("awards", [])))
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


def checks(report: dict[str, Any], watch: Watch) -> list[tuple[str, bool, str]]:
    """(check, passed, what was measured) — the physics from the sim's report, the
    contracts from the mission controllers' reports."""
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
    return out


def run_fleet(console: Console, *, world: str = "factory", robots: int = 4,
              minutes: float = 5.0, fast: bool = False, out_dir: Path = Path("out"),
              record: bool = False, http: tuple[str, int] | None = None,
              order_below: float = 0.6) -> int:
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
                               "--lease-s", str(LEASE_S), "--below", str(order_below)])
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
        agents = [n for n in procs.procs if n != "sim"]
        procs.stop(agents)
        procs.stop(["sim"])
    finally:
        procs.kill_all()
    if not report_path.exists():
        console.print(f"[red]FAILED:[/] the simulation wrote no report ({report_path}); see "
                      f"{fleet_dir / 'sim.log'}")
        return 1
    report = json.loads(report_path.read_text())
    results = checks(report, watch)
    results += process_failures(failed, fleet_dir)
    if now_s < sim_s:
        results.append((f"{minutes:g} sim minutes run", False,
                        f"only {now_s:.0f} s in {wall_s:.0f} s wall"))
    console.print(checks_table(f"fleet summary — {robots} ATVs, {now_s:.0f} s sim in "
                               f"{wall_s:.0f} s wall (×{now_s / wall_s:.2f})", results))
    if watch.malformed:
        console.print(f"[yellow]unreadable messages:[/] {watch.malformed}")
    console.print(f"picture: {picture}   facts: {report_path}   logs"
                  f"{' and recordings' if record else ''}: {fleet_dir}/")
    print(json.dumps({"fleet": {"robots": robots, "sim_s": round(now_s, 1),
                                "wall_s": round(wall_s, 1),
                                "real_time_factor": round(now_s / wall_s, 3),
                                "passed": all(ok for _, ok, _ in results)}}), flush=True)
    return 0 if all(ok for _, ok, _ in results) else 1


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
                     http=args.http, order_below=args.order_below)


if __name__ == "__main__":
    raise SystemExit(main())
