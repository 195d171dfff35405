"""A minimal VDA 5050 master control, and a local mosquitto broker, for the demo and tests.

:class:`Broker` starts ``/usr/sbin/mosquitto`` on a free port of 127.0.0.1 with a
configuration file of its own, and stops it by its PID (``kill`` / ``restart`` are for the
reconnect tests). :class:`Master` is the fleet-manager side: it sends orders and instant
actions and records every message the AGV publishes, each checked against the schema.
Not a fleet manager: one AGV, no traffic control.
"""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
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


class Broker:
    """mosquitto on ``127.0.0.1:port``; a context manager."""

    def __init__(self, port: int | None = None) -> None:
        self.port = port or free_port()
        self._dir = tempfile.TemporaryDirectory(prefix="beehave-mqtt-")
        self.config = Path(self._dir.name) / "mosquitto.conf"
        self.config.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\n"
                               "persistence false\n")
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
        raise RuntimeError(f"mosquitto did not listen on port {self.port}")

    def kill(self) -> None:
        """Stop the broker hard (SIGKILL): clients see their connection break."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=5)
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
                 interface_name: str = "uagv", host: str = "127.0.0.1") -> None:
        self.topics = Topics.of(interface_name, manufacturer, serial_number)
        self.manufacturer, self.serial_number = manufacturer, serial_number
        self.received: dict[str, list[dict[str, Any]]] = {t: [] for t in validation.TOPICS}
        self.invalid: list[str] = []
        self._cond = threading.Condition()
        self._header = 0
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2,
                                  client_id=f"master-{serial_number}-{id(self):x}")
        self.client.on_message = self._on_message
        self.client.on_connect = self._on_connect
        self.client.connect_async(host, port, keepalive=5)
        self.client.reconnect_delay_set(min_delay=1, max_delay=1)
        self.client.loop_start()

    def _on_connect(self, client: mqtt.Client, *_: Any) -> None:
        for topic in ("state", "visualization", "connection", "factsheet"):
            client.subscribe(self.topics[topic], qos=1)

    def _on_message(self, _c: mqtt.Client, _u: Any, message: mqtt.MQTTMessage) -> None:
        kind = message.topic.rsplit("/", 1)[-1]
        data = json.loads(message.payload)
        found = validation.problems(kind, data)  # type: ignore[arg-type]
        with self._cond:
            if found:
                self.invalid.append(f"{kind}: {found}")
            self.received[kind].append(data)
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
