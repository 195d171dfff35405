"""A minimal VDA 5050 master control, and a local mosquitto broker, for the demo and tests.

:class:`Broker` starts ``/usr/sbin/mosquitto`` on a free port of 127.0.0.1 with a
configuration file of its own, and stops it by its PID (``kill`` / ``restart`` are for the
reconnect tests). :class:`Master` is the fleet-manager side: it sends orders and instant
actions and records every message the AGV publishes, each checked against the schema.
Not a fleet manager: one AGV, no traffic control.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any, Self

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from beehave.interfaces.vda5050 import validation
from beehave.interfaces.vda5050.agv import QOS, Topics, timestamp

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@dataclass(frozen=True)
class TlsFiles:
    """A broker's TLS files (PEM): the CA that signed ``certfile``, and its key."""

    cafile: Path
    certfile: Path
    keyfile: Path


def make_tls_files(folder: Path, *, host: str = "127.0.0.1") -> TlsFiles:
    """A self-signed CA and a server certificate for ``host`` (an IP address, as its
    subjectAltName), made with ``openssl`` in ``folder``: enough for a TLS broker in tests
    or on a lab network; a real deployment uses its own CA."""
    openssl = shutil.which("openssl")
    if openssl is None:
        raise RuntimeError("openssl not found: it makes the test certificates")
    files = TlsFiles(folder / "ca.pem", folder / "server.pem", folder / "server.key")
    ca_key, csr = folder / "ca.key", folder / "server.csr"

    def run(*args: str) -> None:
        subprocess.run([openssl, *args], check=True, capture_output=True)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj",
        "/CN=beehave test CA", "-keyout", str(ca_key), "-out", str(files.cafile))
    run("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={host}", "-keyout",
        str(files.keyfile), "-out", str(csr))
    ext = folder / "san.ext"
    ext.write_text(f"subjectAltName=IP:{host}\n")
    run("x509", "-req", "-in", str(csr), "-CA", str(files.cafile), "-CAkey", str(ca_key),
        "-CAcreateserial", "-days", "2", "-extfile", str(ext), "-out", str(files.certfile))
    return files


class Broker:
    """mosquitto on ``127.0.0.1:port``; a context manager.

    ``users`` (name → password) switches anonymous access off and writes a password file
    (``mosquitto_passwd``); ``tls`` makes the listener TLS only."""

    def __init__(self, port: int | None = None, *, users: dict[str, str] | None = None,
                 tls: TlsFiles | None = None) -> None:
        self.port = port or free_port()
        self.tls = tls
        self._dir = tempfile.TemporaryDirectory(prefix="beehave-mqtt-")
        self.config = Path(self._dir.name) / "mosquitto.conf"
        # Only errors and warnings reach stderr: it is a pipe read only when mosquitto
        # exits at once, and a connection log line per client would fill it and block
        # the broker in a long run.
        lines = [f"listener {self.port} 127.0.0.1", "persistence false", "log_type error",
                 "log_type warning"]
        if os.geteuid() == 0:
            # Started by root, mosquitto would switch to the user "mosquitto", who cannot
            # read the password and key files in this private folder.
            lines.append("user root")
        if users:
            passwd = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"
            password_file = Path(self._dir.name) / "passwd"
            password_file.touch(mode=0o600)
            for user, password in users.items():
                subprocess.run([passwd, "-b", str(password_file), user, password],
                               check=True, capture_output=True)
            lines += ["allow_anonymous false", f"password_file {password_file}"]
        else:
            lines.append("allow_anonymous true")
        if tls is not None:
            lines += [f"cafile {tls.cafile}", f"certfile {tls.certfile}",
                      f"keyfile {tls.keyfile}"]
        self.config.write_text("\n".join(lines) + "\n")
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.config)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                err = self.proc.stderr.read().decode() if self.proc.stderr else ""
                raise RuntimeError(f"mosquitto exited at once: {err}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return
            except OSError:
                time.sleep(0.02)
        self.kill()  # whoever started it cannot stop it once this raised
        raise RuntimeError(f"mosquitto did not listen on port {self.port}")

    def kill(self) -> None:
        """Stop the broker hard (SIGKILL): clients see their connection break."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=5)
        if self.proc is not None and self.proc.stderr is not None:
            self.proc.stderr.close()
        self.proc = None

    def restart(self) -> None:
        self.kill()
        self.start()

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc is not None and self.proc.stderr is not None:
            self.proc.stderr.close()
        self._dir.cleanup()


class Master:
    """A minimal VDA 5050 master control for one AGV (tests and the demo)."""

    def __init__(self, port: int, *, manufacturer: str = "beehave", serial_number: str,
                 interface_name: str = "uagv", host: str = "127.0.0.1",
                 clock: Callable[[], float] | None = None,
                 username: str | None = None, password: str | None = None,
                 ca_file: Path | str | None = None) -> None:
        self.topics = Topics.of(interface_name, manufacturer, serial_number)
        self.manufacturer, self.serial_number = manufacturer, serial_number
        self.received: dict[str, list[dict[str, Any]]] = {t: [] for t in validation.TOPICS}
        self.invalid: list[str] = []
        #: ``(clock(), state)`` for every state received, when a ``clock`` was given.
        self.stamped: list[tuple[float, dict[str, Any]]] = []
        #: ``time.perf_counter()`` when each state of ``received["state"]`` arrived.
        self.state_arrived: list[float] = []
        self._clock = clock
        self._cond = threading.Condition()
        #: Set once the master is on the broker.
        self.connected = threading.Event()
        self._header = 0
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2,
                                  client_id=f"master-{serial_number}-{id(self):x}")
        self.client.on_message = self._on_message
        self.client.on_connect = self._on_connect
        if username is not None:
            self.client.username_pw_set(username, password)
        if ca_file is not None:
            self.client.tls_set(ca_certs=str(ca_file))
        self.client.connect_async(host, port, keepalive=5)
        self.client.reconnect_delay_set(min_delay=1, max_delay=1)
        self.client.loop_start()

    def _on_connect(self, client: mqtt.Client, _userdata: Any, _flags: Any, reason: Any,
                    _props: Any) -> None:
        if reason.is_failure:
            return
        for topic in ("state", "visualization", "connection", "factsheet"):
            client.subscribe(self.topics[topic], qos=1)
        self.connected.set()

    def _on_message(self, _c: mqtt.Client, _u: Any, message: mqtt.MQTTMessage) -> None:
        arrived = time.perf_counter()
        kind = message.topic.rsplit("/", 1)[-1]
        data = json.loads(message.payload)
        found = validation.problems(kind, data)  # type: ignore[arg-type]
        with self._cond:
            if found:
                self.invalid.append(f"{kind}: {found}")
            self.received[kind].append(data)
            if kind == "state":
                self.state_arrived.append(arrived)
                if self._clock is not None:
                    self.stamped.append((self._clock(), data))
            self._cond.notify_all()

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()

    # ---- sending ------------------------------------------------------------------------

    def header(self) -> dict[str, Any]:
        self._header += 1
        return {"headerId": self._header, "timestamp": timestamp(), "version": "2.1.0",
                "manufacturer": self.manufacturer, "serialNumber": self.serial_number}

    def send(self, topic: str, message: dict[str, Any] | str | bytes) -> None:
        payload = message if isinstance(message, str | bytes) else json.dumps(message)
        self.client.publish(self.topics[topic], payload, qos=QOS[topic]).wait_for_publish(5)

    def order(self, order_id: str, update_id: int, nodes: list[dict[str, Any]],
              edges: list[dict[str, Any]] | None = None) -> dict[str, Any]:
        """Send an order; edges default to straight ones between consecutive nodes."""
        if edges is None:
            edges = [edge(a, b) for a, b in zip(nodes, nodes[1:], strict=False)]
        message = {**self.header(), "orderId": order_id, "orderUpdateId": update_id,
                   "nodes": nodes, "edges": edges}
        self.send("order", message)
        return message

    def instant(self, *actions: dict[str, Any]) -> dict[str, Any]:
        message = {**self.header(), "actions": list(actions)}
        self.send("instantActions", message)
        return message

    # ---- waiting ------------------------------------------------------------------------

    def wait_for(self, topic: str, predicate: Callable[[dict[str, Any]], bool], *,
                 timeout_s: float) -> dict[str, Any]:
        """The first message on ``topic`` (received so far or later) that matches."""
        seen = 0
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                messages = self.received[topic]
                for message in messages[seen:]:
                    if predicate(message):
                        return message
                seen = len(messages)
                left = deadline - time.monotonic()
                if left <= 0:
                    last = messages[-1] if messages else None
                    raise AssertionError(f"no matching {topic} message within {timeout_s} s; "
                                         f"last: {json.dumps(last)[:1500]}")
                self._cond.wait(left)

    def wait_state(self, predicate: Callable[[dict[str, Any]], bool], *,
                   timeout_s: float) -> dict[str, Any]:
        return self.wait_for("state", predicate, timeout_s=timeout_s)

    def last_state(self) -> dict[str, Any]:
        with self._cond:
            return self.received["state"][-1]


def node(node_id: str, seq: int, *, x: float | None = None, y: float | None = None,
         map_id: str = "warehouse", released: bool = True,
         actions: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"nodeId": node_id, "sequenceId": seq, "released": released,
                           "actions": actions or []}
    if x is not None and y is not None:
        out["nodePosition"] = {"x": x, "y": y, "mapId": map_id}
    return out


def edge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    return {"edgeId": f"{a['nodeId']}-{b['nodeId']}", "sequenceId": a["sequenceId"] + 1,
            "released": b["released"], "startNodeId": a["nodeId"],
            "endNodeId": b["nodeId"], "actions": []}


def action(action_type: str, action_id: str, **params: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"actionType": action_type, "actionId": action_id,
                           "blockingType": "HARD"}
    if params:
        out["actionParameters"] = [{"key": k, "value": v} for k, v in params.items()]
    return out


# ---- the scenario: ``python -m behaviours.demos.vda5050_master`` ----------------------

VIA_M = (6.0, 2.0)
"""A node without actions between the start and the pick-up (on the free aisle y = 2)."""
VIA_DEVIATION_M = 0.15
EDGE_MPS = 0.6
"""The edges' speed: ``speed_mps`` of robots/config/emili_vda5050.yaml (no maxSpeed)."""

@dataclass
class Timeline:
    """What the master saw, stamped with the simulation's time."""

    rows: list[tuple[float, str]] = dataclass_field(default_factory=list)
    _last: dict[str, str] = dataclass_field(default_factory=dict)

    def follow(self, sim_s: float, state: dict[str, Any]) -> None:
        seen = {"lastNodeId": state["lastNodeId"], "driving": str(state["driving"]),
                **{f"action {a['actionId']}": a["actionStatus"]
                   for a in state["actionStates"]},
                **{f"error {e['errorType']}": e.get("errorDescription", "")
                   for e in state["errors"]}}
        for key, value in seen.items():
            if self._last.get(key) != value:
                self._last[key] = value
                self.rows.append((sim_s, f"{key}: {value}"))


def run_scenario(*, out: Path, real_time_factor: float | None = None,
                 console: Any = None, figures: dict[str, float] | None = None,
                 broker: tuple[str, int] | None = None) -> list[str]:
    """EMILI takes a VDA 5050 order over a local broker: pick at ``emili_pickup``, drop at
    ``emili_dropoff``; a second order to the charging station is cancelled mid-edge.
    Returns the problems (empty: the physics matched). ``figures``, when given, gets the
    latencies measured on the way (the benchmark reads them): ``order_to_wheels_<id>_ms``
    (wall time from the master publishing an order to the first physics step with a
    non-zero wheel command), ``cancel_to_stop_sim_s`` and ``cancel_to_stop_wall_ms``
    (cancelOrder published → EMILI's measured velocity below 0.01 m/s),
    ``cancel_to_standstill_state_sim_s`` and ``..._wall_ms`` (cancelOrder published → the
    first state at the master saying ``driving: false``).
    ``broker``: ``(host, port)`` of a running broker to use instead of a local mosquitto
    of the scenario's own (anonymous access)."""
    import math as _math

    from rich.console import Console
    from rich.table import Table

    from beehave.config import load_config, parse_config
    from beehave.robot import Robot
    from beehave.ros.context import RosContext
    from robots.node import SimNode
    from robots.sim import Simulation
    from robots.world import load_world

    console = console or Console()
    world = load_world("warehouse")
    pickup, dropoff = world.station("emili_pickup"), world.station("emili_dropoff")
    problems: list[str] = []
    checks: list[tuple[str, str, str, bool]] = []
    timeline = Timeline()
    root = Path(__file__).resolve().parents[2]
    with Broker() if broker is None else contextlib.nullcontext() as local:
        host, port = (("127.0.0.1", local.port) if isinstance(local, Broker)
                      else broker or ("127.0.0.1", 1883))
        data = load_config(root / "robots/config/emili_vda5050.yaml").model_dump(
            by_alias=True, exclude={"source"})
        data["vda5050"]["broker"].update(host=host, port=port)
        config = parse_config(data, source="emili_vda5050.yaml")
        sim = Simulation(world, real_time_factor=real_time_factor)
        ros = RosContext()
        sim_node = SimNode(sim, ros)
        robot = Robot(config)
        master = Master(port, host=host, serial_number="emili1", clock=lambda: sim.time_s)
        emili = sim.emili("emili1")
        lift_max = [0.0]
        trace: list[tuple[float, float, float]] = []  # the body's x, y, forward speed

        def on_step(_t: float) -> None:
            lift_max[0] = max(lift_max[0], emili.lift_height())
            odom = emili.odometry()
            trace.append((odom.x_m, odom.y_m, odom.linear_mps))

        remove = sim.on_step(on_step)

        latencies: dict[str, float] = {} if figures is None else figures

        def send_order(order_id: str, nodes: list[dict[str, Any]]) -> None:
            """Send an order and note when the physics first gets a wheel command."""
            commanded: list[float] = []

            def on_step(_t: float) -> None:
                if not commanded and emili.cmd_vel() != (0.0, 0.0):
                    commanded.append(time.perf_counter())
                    latencies[f"order_to_wheels_{order_id}_ms"] = (commanded[0] - sent) * 1e3
            sent = time.perf_counter()
            watches.append(sim.on_step(on_step))
            master.order(order_id, 0, nodes)

        watches: list[Callable[[], None]] = []

        def wait(predicate: Callable[[dict[str, Any]], bool], timeout_s: float
                 ) -> dict[str, Any] | None:
            try:
                return master.wait_state(predicate, timeout_s=timeout_s)
            except AssertionError as exc:
                problems.append(str(exc)[:300])
                return None

        try:
            ros.start()
            sim.start()
            robot.start()
            if not master.connected.wait(30):
                # The robot logs the same and keeps retrying; the scenario cannot wait.
                raise RuntimeError(f"no MQTT broker reachable at {host}:{port} within 30 s")
            master.wait_for("connection", lambda m: m["connectionState"] == "ONLINE",
                            timeout_s=30)
            wait(lambda s: "agvPosition" in s, 30)
            start = node("start", 0, x=3.0, y=2.0)
            # A node without actions on the way: EMILI drives on through it (6.6.3).
            via = node("via", 2, x=VIA_M[0], y=VIA_M[1])
            via["nodePosition"]["allowedDeviationXY"] = VIA_DEVIATION_M
            take = node("emili_pickup", 4, actions=[action("pick", "pick-1", loadId="box-1")])
            put = node("emili_dropoff", 6, actions=[action("drop", "drop-1")])
            console.print("master → order o1: start → via → emili_pickup (pick) → "
                          "emili_dropoff (drop)")
            send_order("o1", [start, via, take, put])
            picked = wait(lambda s: s["lastNodeId"] == "emili_pickup" and any(
                a["actionId"] == "pick-1" and a["actionStatus"] == "FINISHED"
                for a in s["actionStates"]), 120)
            pick_pose = emili.pose()
            pick_lift = emili.lift_height()
            done = wait(lambda s: s["lastNodeId"] == "emili_dropoff" and any(
                a["actionId"] == "drop-1" and a["actionStatus"] == "FINISHED"
                for a in s["actionStates"]), 120)
            drop_pose = emili.pose()
            drop_lift = emili.lift_height()
            near_via = [v for x, y, v in list(trace)
                        if _math.hypot(x - VIA_M[0], y - VIA_M[1]) <= VIA_DEVIATION_M]
            slowest = min(near_via) if near_via else _math.nan
            # The slowest the body went within the node's deviation: above half the edge's.
            checks.append(("drove through 'via'", f"{slowest:.3f} m/s",
                           f"> {0.5 * EDGE_MPS:.2f} m/s", bool(near_via)
                           and slowest > 0.5 * EDGE_MPS))
            if picked and done:
                e_pick = _math.hypot(pick_pose.x_m - pickup.center_m[0],
                                     pick_pose.y_m - pickup.center_m[1])
                e_drop = _math.hypot(drop_pose.x_m - dropoff.center_m[0],
                                     drop_pose.y_m - dropoff.center_m[1])
                checks += [
                    ("pick-up reached", f"{e_pick:.3f} m from centre", "≤ 0.20 m",
                     e_pick <= 0.20),
                    ("lift at the pick", f"{pick_lift:.3f} m", "≥ 0.19 m", pick_lift >= 0.19),
                    ("drop-off reached", f"{e_drop:.3f} m from centre", "≤ 0.20 m",
                     e_drop <= 0.20),
                    ("lift after the drop", f"{drop_lift:.3f} m", "≤ 0.01 m",
                     drop_lift <= 0.01)]
            # Order 2, to the charging station, cancelled mid-edge.
            here = node("emili_dropoff", 0)
            charge = node("emili_charging", 2, actions=[action("startCharging", "charge-1")])
            console.print("master → order o2: emili_dropoff → emili_charging; cancelOrder "
                          "mid-edge")
            send_order("o2", [here, charge])
            wait(lambda s: s["orderId"] == "o2" and s["driving"], 60)
            t_drive = sim.time_s
            while sim.time_s < t_drive + 3.0:
                time.sleep(0.01)
            stopped: list[float] = []
            stopped_wall: list[float] = []

            def on_stop(t: float) -> None:
                if not stopped and abs(emili.odometry().linear_mps) < 0.01:
                    stopped_wall.append(time.perf_counter())
                    stopped.append(t)
            watch = sim.on_step(on_stop)
            with master._cond:
                before = len(master.received["state"])
                t_cancel = sim.time_s
                wall_cancel = time.perf_counter()
            master.instant(action("cancelOrder", "cancel-1"))
            cancelled = wait(lambda s: any(a["actionId"] == "cancel-1" and
                                           a["actionStatus"] == "FINISHED"
                                           for a in s["actionStates"]), 30)
            deadline = time.monotonic() + 10
            while not stopped and time.monotonic() < deadline:
                time.sleep(0.01)
            watch()
            stop_s = stopped[0] - t_cancel if stopped else _math.inf
            latencies["cancel_to_stop_sim_s"] = stop_s
            latencies["cancel_to_stop_wall_ms"] = (
                (stopped_wall[0] - wall_cancel) * 1e3 if stopped_wall else _math.inf)
            checks.append(("velocity 0 after cancelOrder", f"{stop_s:.3f} s sim",
                           "≤ 0.5 s sim", stop_s <= 0.5))
            # The first state after the cancel that says driving false: when the master
            # learns the AGV stands (and the simulation must agree that it does).
            with master._cond:
                after = list(zip(master.stamped[before:],
                                 master.state_arrived[before:], strict=False))
            standing = next(((t, wall) for (t, st), wall in after if not st["driving"]),
                            None)
            if standing is not None:
                latencies["cancel_to_standstill_state_sim_s"] = standing[0] - t_cancel
                latencies["cancel_to_standstill_state_wall_ms"] = (
                    standing[1] - wall_cancel) * 1e3
                still = bool(stopped) and stopped[0] <= standing[0]
                checks.append(("driving false: stands still",
                               f"{standing[0] - t_cancel:.3f} s sim",
                               f"≥ stop {stop_s:.3f} s", still))
            else:
                problems.append("no state with driving false after the cancelOrder")
            # VDA 5050 2.1 (6.6.3, 6.12): cancelOrder is FINISHED, and a HARD action
            # RUNNING, only once the AGV stands still: the state that says so must not
            # say driving.
            running = next((st for st in list(master.received["state"]) if any(
                a["actionId"] == "pick-1" and a["actionStatus"] == "RUNNING"
                for a in st["actionStates"])), None)
            if running is not None:
                checks.append(("pick RUNNING: stands still",
                               f"{abs(running['velocity']['vx']):.3f} m/s",
                               "not driving", running["driving"] is False))
            if cancelled is not None:
                checks.append(("cancel FINISHED: stands still",
                               f"{abs(cancelled['velocity']['vx']):.3f} m/s",
                               "not driving", cancelled["driving"] is False))
                failed = {a["actionId"]: a["actionStatus"] for a in cancelled["actionStates"]}
                checks.append(("order o2's action after the cancel",
                               failed.get("charge-1", "?"), "FAILED",
                               failed.get("charge-1") == "FAILED"))
            checks.append(("every message validated", f"{len(master.invalid)} invalid",
                           "0", not master.invalid))
        finally:
            remove()
            for remove_watch in watches:
                remove_watch()
            out.parent.mkdir(parents=True, exist_ok=True)
            try:
                sim.render_topdown(out)
            except Exception as exc:  # the picture is a by-product; report it
                problems.append(f"could not render {out}: {exc!r}")
            master.close()
            # Every step runs whatever an earlier one raised; the robot first (its safe
            # states), the sim node before the simulation, ROS last.
            with contextlib.ExitStack() as stack:
                for step in (ros.shutdown, sim.close, sim_node.destroy, robot.shutdown):
                    stack.callback(step)
    for stamp, state in master.stamped:
        timeline.follow(stamp, state)
    timeline_table = Table(title="order timeline (sim time the master received it)")
    timeline_table.add_column("t [s]", justify="right")
    timeline_table.add_column("state change")
    for t, what in timeline.rows:
        timeline_table.add_row(f"{t:7.2f}", what)
    console.print(timeline_table)
    table = Table(title="physics checks")
    for col in ("check", "measured", "target", "ok"):
        table.add_column(col)
    for name, measured, target, ok in checks:
        table.add_row(name, measured, target, "[green]yes[/]" if ok else "[red]NO[/]")
        if not ok:
            problems.append(f"{name}: {measured} (target {target})")
    console.print(table)
    if latencies:
        console.print("latencies: " + ", ".join(
            f"{k} {v:.3f}" for k, v in sorted(latencies.items())))
    console.print(f"picture: {out}")
    return problems


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m behaviours.demos.vda5050_master",
        description="EMILI as a VDA 5050 AGV: a local mosquitto, the simulated warehouse and "
                    "a master that sends an order (pick, drop) and cancels a second one; "
                    "exit 0 only if the physics matched.")
    parser.add_argument("--out", default="docs/img/vda5050.png", metavar="FILE.png")
    parser.add_argument("--real-time-factor", type=float, default=None, metavar="X",
                        help="default: as fast as possible")
    parser.add_argument("--broker", type=broker_address, default=None, metavar="HOST:PORT",
                        help="a running MQTT broker to use (default: a local mosquitto of "
                             "the scenario's own on a free port)")
    args = parser.parse_args(argv)
    return scenario_exit(out=Path(args.out), real_time_factor=args.real_time_factor,
                         broker=args.broker)


def broker_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (or ``HOST``, port 1883) for ``--broker``."""
    host, _, port = text.rpartition(":") if ":" in text else (text, "", "1883")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


def scenario_exit(*, out: Path, real_time_factor: float | None,
                  broker: tuple[str, int] | None = None) -> int:
    """Run the scenario, print its problems; the exit status (0: the physics matched)."""
    try:
        problems = run_scenario(out=out, real_time_factor=real_time_factor, broker=broker)
    except RuntimeError as exc:
        problems = [str(exc)]
    for problem in problems:
        print(f"FAILED: {problem}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
