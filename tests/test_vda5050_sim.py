"""VDA 5050 in the physics: ``beehave sim --fast`` and ``beehave run`` (EMILI with a
``vda5050:`` section) as real processes over DDS, a real mosquitto, and a test master.

One order over three nodes with a pick and a drop, released in two parts (a stale update
refused in between), is driven in pybullet; the sim's ground-truth odometry and lift
state are checked. A second order is cancelled mid-edge: EMILI stands still, the rest of
the order FAILED. Every message EMILI sent validates against the 2.1.0 schemas.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

pytest.importorskip("pybullet")
pytest.importorskip("rclpy")

from mqtt_broker import Broker, Master, action, edge, node  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from ros_probe import Probe  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

from beehave.testing import WALL_TIMEOUT_S, wall_timeout  # noqa: E402
from robots.world import load_world  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TOLERANCE_M = 0.15  # Navigation's, which OrderExecution uses


def _start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, *args], cwd=ROOT, env=dict(os.environ),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _status(state: dict[str, Any]) -> dict[str, str]:
    return {a["actionId"]: a["actionStatus"] for a in state["actionStates"]}


def test_emili_executes_a_vda5050_order_in_the_physics(tmp_path: Path) -> None:
    world = load_world("warehouse")
    dropoff = world.station("emili_dropoff")
    config = yaml.safe_load((ROOT / "robots/config/emili_vda5050.yaml").read_text())
    procs: list[subprocess.Popen[str]] = []
    probe = Probe()
    with Broker() as broker:
        config["vda5050"]["broker"]["port"] = broker.port
        path = tmp_path / "emili_vda5050.yaml"
        path.write_text(yaml.safe_dump(config))
        master = Master(broker.port, serial_number="emili1")
        try:
            odom = probe.record(Odometry, "/emili1/odom")
            lift = probe.record(Float64, "/emili1/lift/state")
            procs.append(_start("-m", "beehave.cli", "sim", "--fast"))
            procs.append(_start("-m", "beehave.cli", "run", str(path)))
            master.wait_for("connection", lambda m: m["connectionState"] == "ONLINE",
                            timeout_s=WALL_TIMEOUT_S)
            master.wait_state(lambda s: "agvPosition" in s, timeout_s=WALL_TIMEOUT_S)
            # The probe must hear the lift before it moves (discovery is slow on a loaded
            # machine): else the pick's rise is missed and the check reads only its end.
            assert probe.wait(lambda: bool(lift) and bool(odom)), "no lift/odom probe"
            # The base: EMILI's start, then 3 m on, where it picks; the drop-off station
            # is the horizon, released by an update.
            n0 = node("n0", 0, x=3.0, y=2.0)
            n1 = node("n1", 2, x=6.0, y=2.0, actions=[action("pick", "pick1", loadId="L1")])
            n2 = node("emili_dropoff", 4, actions=[action("drop", "drop1")])
            master.order("o1", 1, [n0, n1, {**n2, "released": False}],
                         [edge(n0, n1), {**edge(n1, n2), "released": False}])
            master.wait_state(lambda s: s["driving"], timeout_s=WALL_TIMEOUT_S)
            master.order("o1", 0, [n1, n2])  # stale: refused, the order goes on
            refused = master.wait_state(lambda s: any(
                e["errorType"] == "orderUpdateError" for e in s["errors"]),
                timeout_s=WALL_TIMEOUT_S)
            assert refused["orderUpdateId"] == 1
            master.order("o1", 2, [n1, n2], [edge(n1, n2)])  # stitched at n1
            done = master.wait_state(lambda s: s["lastNodeId"] == "emili_dropoff" and
                                     _status(s).get("drop1") == "FINISHED",
                                     timeout_s=WALL_TIMEOUT_S)
            assert _status(done) == {"pick1": "FINISHED", "drop1": "FINISHED"}
            assert done["errors"] == [] and done["loads"] == []
            # The physics: ground-truth pose in the drop-off station, the lift went up to
            # the pick height and is down again.
            # (The probe hears the sim over DDS: on a loaded machine its streams lag the
            # state the master got, so it waits until they have caught up.)
            def at_dropoff() -> bool:
                p = odom[-1].pose.pose.position
                return math.hypot(p.x - dropoff.center_m[0],
                                  p.y - dropoff.center_m[1]) <= TOLERANCE_M + 0.05

            assert probe.wait(at_dropoff), odom[-1].pose.pose.position
            assert probe.wait(lambda: lift[-1].data <= 0.005), [m.data for m in lift][-5:]
            assert max(m.data for m in lift) >= 0.195

            # A second order, cancelled mid-edge: EMILI stops and the rest FAILS.
            back = node("back", 6, x=4.0, y=2.0, actions=[action("pick", "pick2")])
            here = node("emili_dropoff", 4)
            first_o2 = len(odom)  # the odometry from here on is o2's drive
            master.order("o2", 0, [here, back], [edge(here, back)])
            master.wait_state(lambda s: s["orderId"] == "o2" and s["driving"],
                              timeout_s=WALL_TIMEOUT_S)
            assert probe.wait(lambda: abs(odom[-1].twist.twist.linear.x) > 0.05)
            master.instant(action("cancelOrder", "cancel1"))
            cancelled = master.wait_state(
                lambda s: _status(s).get("cancel1") == "FINISHED", timeout_s=WALL_TIMEOUT_S)
            assert _status(cancelled)["pick2"] == "FAILED"
            # 6.6.3 / 6.12: FINISHED (cancel) and RUNNING (a HARD pick) at a standstill.
            assert cancelled["driving"] is False, cancelled["velocity"]
            picking = next(s for s in list(master.received["state"])
                           if _status(s).get("pick1") == "RUNNING")
            assert picking["driving"] is False, picking["velocity"]
            assert cancelled["nodeStates"] == [] and cancelled["edgeStates"] == []
            count = len(odom)
            assert probe.wait(lambda: len(odom) > count + 30)
            still = odom[-1]
            assert abs(still.twist.twist.linear.x) < 0.01, still.twist.twist
            # The bound: the wheels stand within 0.5 s of sim time of when EMILI
            # first reported the cancel. That sim time is read from EMILI's own first state
            # that lists it: its agvPosition is the odometry EMILI had then, found again in
            # the sim's odometry. (Not the probe's last odometry when the master sends: on a
            # loaded machine the probe's stream and mosquitto lag sim seconds behind.)
            ack = next(s for s in list(master.received["state"]) if "cancel1" in _status(s))
            ax, ay = ack["agvPosition"]["x"], ack["agvPosition"]["y"]
            drive = list(odom)[first_o2:]
            match = min(drive, key=lambda m: math.hypot(m.pose.pose.position.x - ax,
                                                        m.pose.pose.position.y - ay))
            # (Should EMILI's state publisher be slower than the stop, the report shows the
            # standstill and this bound holds trivially; the checks above still hold it to
            # a standstill short of "back". Beside busy loops the report came 0.08-0.19 s of
            # sim time before the wheels stood, in 6 runs.)
            t_ack = _stamp_s(match)
            stopped = next(_stamp_s(m) for m in drive if _stamp_s(m) >= t_ack
                           and abs(m.twist.twist.linear.x) < 0.01)
            assert stopped - t_ack <= 0.5, (stopped - t_ack, ack["actionStates"])
            assert still.pose.pose.position.x > 4.0 + 0.5  # stopped short of "back"
            assert not master.invalid, master.invalid
        finally:
            master.close()
            for proc in procs:
                if proc.poll() is None:
                    proc.terminate()
            outputs = []
            for proc in procs:
                try:
                    outputs.append(proc.communicate(timeout=WALL_TIMEOUT_S)[0])
                except subprocess.TimeoutExpired:
                    proc.kill()
                    outputs.append(proc.communicate()[0])
            probe.close()
        assert "stopped cleanly" in outputs[1], outputs[1][-3000:]


def _stamp_s(msg: Odometry) -> float:
    return float(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def test_beehave_run_reports_an_unreachable_broker_and_keeps_retrying(
        tmp_path: Path) -> None:
    """No broker at the configured address: ``beehave run`` says so on stderr, retries
    (more than once, backing off), keeps the robot running and stops cleanly."""
    from mqtt_broker import free_port

    config = yaml.safe_load((ROOT / "robots/config/emili_vda5050.yaml").read_text())
    port = free_port()  # nobody listens there
    config["vda5050"]["broker"].update(port=port, reconnect_max_s=2.0)
    config["use_sim_time"] = False  # no simulation in this test
    path = tmp_path / "emili_vda5050.yaml"
    path.write_text(yaml.safe_dump(config))
    proc = subprocess.run([sys.executable, "-m", "beehave.cli", "run", str(path),
                           "--only", "high", "--duration-s", "6"], cwd=ROOT,
                          env=dict(os.environ), capture_output=True, text=True,
                          timeout=wall_timeout(1.5))
    reported = proc.stderr.count(f"no MQTT broker reachable at 127.0.0.1:{port}; retrying")
    assert reported >= 2, proc.stderr[-3000:]
    assert proc.returncode == 0 and "stopped cleanly" in proc.stdout, \
        (proc.returncode, proc.stdout[-2000:], proc.stderr[-2000:])


def test_beehave_demo_vda5050_checks_the_physics(tmp_path: Path) -> None:
    """``beehave demo --vda5050``: the scenario with its own broker, the timeline and the
    physics checks printed, the picture written, exit 0 because every check held."""
    proc = subprocess.run([sys.executable, "-m", "beehave.cli", "demo", "--vda5050",
                           "--fast", "--out", str(tmp_path)], cwd=ROOT, env=dict(os.environ),
                          capture_output=True, text=True,
                          timeout=wall_timeout(2.0))
    out = proc.stdout
    assert proc.returncode == 0, (out[-3000:], proc.stderr[-3000:])
    assert "order timeline" in out and "lastNodeId: emili_dropoff" in out, out[-3000:]
    assert "velocity 0 after cancelOrder" in out and "NO" not in out.split("physics")[-1]
    assert (tmp_path / "vda5050.png").stat().st_size > 10_000
