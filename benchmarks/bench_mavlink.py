"""MAVLink: how fast the HALs and the protocols are, with the bare UDP round trip as floor.

``python -m benchmarks mavlink`` prints, as JSON lines:

- ``mavlink_udp_round_trip`` (floor): a bare pymavlink COMMAND_LONG → COMMAND_ACK between
  two sockets of this process, answered by a thread that does nothing else;
- ``mavlink_command_ack``: :meth:`hal.mavlink.MavlinkLink.command` against a simulated
  vehicle (:mod:`robots.mavlink_endpoint`) — p50 and p99; ``mavlink_command_ack_signed``
  the same on a signed link (MAVLink 2 signing on both sides: what signing costs);
- ``mavlink_hal_latency``: from a vehicle sending LOCAL_POSITION_NED (a bare pymavlink
  socket, so the send time is exact) to ``position/north_m`` changing on the blackboard,
  through :class:`hal.mavlink.MavlinkPositionHAL` in a HAL manager — median and p99;
- ``mavlink_mission_upload_20``: the full upload protocol for 20 waypoints against the
  simulated vehicle — median;
- ``fleet_state_age_10hz``: the age of another process's fleet state (published at
  10 Hz, :class:`beehave.agents.fleet.Fleet`) as a reader sees it at arbitrary moments —
  half a period plus the transit, ideally about 50 ms (p50) and 100 ms (p99).
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks._util import median, percentile, report


def _port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _floor(n: int) -> list[float]:
    from hal.mavlink import mavutil

    port = _port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1)
    stop = threading.Event()

    def echo() -> None:
        while not stop.is_set():
            msg = vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=0.05)
            if msg is not None:
                vehicle.mav.command_ack_send(msg.command, 0)

    vehicle.mav.heartbeat_send(10, 3, 0, 0, 3)  # the listening side learns the address
    gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=2.0)
    thread = threading.Thread(target=echo, daemon=True)
    thread.start()
    samples = []
    try:
        for _ in range(n):
            start = time.perf_counter()
            gcs.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
            if gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=1.0) is not None:
                samples.append(time.perf_counter() - start)
    finally:
        stop.set()
        thread.join()
        gcs.close()
        vehicle.close()
    return samples


def _hal_latency(n: int) -> list[float]:
    from beehave.blackboard import Blackboard, Change
    from beehave.hal import HALManager
    from hal.mavlink import MavlinkPositionHAL, close_all_links, mavutil

    port = _port()
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1,
                                         source_component=1)
    samples: list[float] = []

    async def body() -> None:
        board = Blackboard()
        manager = HALManager(board)
        manager.register(MavlinkPositionHAL, connection=f"udp:127.0.0.1:{port}")
        await manager.load("mavlink_position")
        arrived: dict[float, float] = {}

        def seen(change: Change) -> None:
            arrived[change.value] = time.perf_counter()

        board.subscribe("position/north_m", seen)
        vehicle.mav.heartbeat_send(10, 3, 0, 0, 3)
        await asyncio.sleep(0.3)
        for i in range(n):
            value = float(i + 1)
            sent = time.perf_counter()
            vehicle.mav.local_position_ned_send(i, value, 0.0, 0.0, 0.0, 0.0, 0.0)
            while value not in arrived and time.perf_counter() - sent < 1.0:
                await asyncio.sleep(0.0002)
            if value in arrived:
                samples.append(arrived[value] - sent)
            if i % 20 == 0:
                vehicle.mav.heartbeat_send(10, 3, 0, 0, 3)
        await manager.close()

    try:
        asyncio.run(body())
    finally:
        close_all_links()
        vehicle.close()
    return samples


def _against_the_sim(commands: int, uploads: int, *, signed: bool = False
                     ) -> tuple[list[float], list[float]]:
    import hashlib
    import tempfile

    from hal.mavlink import Waypoint, close_all_links, mavlink, open_link
    from robots.mavlink_endpoint import MavlinkEndpoint
    from robots.sim import Simulation
    from robots.world import world_from_dict

    world = world_from_dict({"name": "bench", "floor": {"size_m": [10, 10]},
                             "robots": [{"namespace": "rover", "kind": "kobuki",
                                         "start": {"x_m": 2, "y_m": 2}}]})
    sim = Simulation(world, real_time_factor=1.0)
    port = _port()
    passphrase = "bench"
    endpoint = MavlinkEndpoint(sim, "rover", url=f"udpout:127.0.0.1:{port}",
                               signing_key=hashlib.sha256(passphrase.encode()).digest()
                               if signed else None)
    sim.start()
    acks: list[float] = []
    upload_s: list[float] = []
    key_file = tempfile.NamedTemporaryFile("w", suffix=".key", delete=False)  # noqa: SIM115
    key_file.write(passphrase)
    key_file.close()
    try:
        link = open_link(f"udp:127.0.0.1:{port}",
                         signing_key_file=key_file.name if signed else None)
        link.wait_heartbeat(timeout_s=5.0)
        for _ in range(commands):
            start = time.perf_counter()
            link.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                         4, what="set mode HOLD")
            acks.append(time.perf_counter() - start)
        # Inside the fence (the floor, 0.3 m in from its edges).
        items = link.mission_items([Waypoint(1.0 + i * 0.1, 1.0) for i in range(20)])
        for _ in range(uploads):
            start = time.perf_counter()
            link.upload_mission(items)
            upload_s.append(time.perf_counter() - start)
    finally:
        close_all_links()
        endpoint.close()
        sim.close()
        Path(key_file.name).unlink()
    return acks, upload_s


_PEER = """
import sys, time
from beehave.agents import Agent
from beehave.agents.fleet import Fleet
sys.setswitchinterval(0.001)
with Agent("bench_fleet_peer", probe_s=0.3) as agent:
    fleet = Fleet(agent, state=lambda: {"battery_pct": 50.0}, rate_hz=10.0)
    time.sleep(float(sys.argv[1]))
    fleet.close()
"""


def _fleet_age(seconds: float) -> list[float]:
    """Ages of a peer's state (another process, 10 Hz) as read at arbitrary moments."""
    import subprocess
    import sys

    from beehave.agents import Agent
    from beehave.agents.fleet import Fleet

    peer = subprocess.Popen([sys.executable, "-c", _PEER, str(seconds + 6.0)])
    ages: list[float] = []
    try:
        with Agent("bench_fleet_reader", probe_s=0.3) as agent:
            fleet = Fleet(agent, rate_hz=10.0)
            deadline = time.monotonic() + 15.0
            while fleet.get("bench_fleet_peer") is None and time.monotonic() < deadline:
                time.sleep(0.05)
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                state = fleet.get("bench_fleet_peer")
                if state is not None:
                    ages.append(state.age_s)
                time.sleep(0.037)  # not a multiple of the period: reads fall anywhere in it
            fleet.close()
    finally:
        peer.terminate()
        peer.wait()
    return ages


def main() -> list[dict[str, Any]]:
    rows = []
    floor = _floor(300)
    rows.append(report("mavlink_udp_round_trip_p50", median(floor) * 1e3, "ms",
                       p99_ms=round(percentile(floor, 99) * 1e3, 3)))
    acks, uploads = _against_the_sim(200, 10)
    p50 = median(acks) * 1e3
    rows.append(report("mavlink_command_ack_p50", p50, "ms", "<= 5 ms", p50 <= 5.0,
                       p99_ms=round(percentile(acks, 99) * 1e3, 3),
                       floor_ratio=round(p50 / (median(floor) * 1e3), 1)))
    signed, _ = _against_the_sim(200, 0, signed=True)
    signed_p50 = median(signed) * 1e3
    rows.append(report("mavlink_command_ack_signed_p50", signed_p50, "ms", "<= 5 ms",
                       signed_p50 <= 5.0, p99_ms=round(percentile(signed, 99) * 1e3, 3),
                       unsigned_ratio=round(signed_p50 / p50, 2)))
    hal = _hal_latency(300)
    hal_ms = median(hal) * 1e3
    rows.append(report("mavlink_hal_latency_p50", hal_ms, "ms", "<= 2 ms", hal_ms <= 2.0,
                       p99_ms=round(percentile(hal, 99) * 1e3, 3), samples=len(hal)))
    up = median(uploads) * 1e3
    rows.append(report("mavlink_mission_upload_20_p50", up, "ms", "<= 200 ms", up <= 200.0,
                       max_ms=round(max(uploads) * 1e3, 3)))
    ages = _fleet_age(5.0)
    if ages:
        age = median(ages) * 1e3
        rows.append(report("fleet_state_age_10hz_p50", age, "ms", "<= 100 ms", age <= 100.0,
                           p99_ms=round(percentile(ages, 99) * 1e3, 3), reads=len(ages)))
    else:  # the peer's state never arrived: say so rather than drop the figure
        rows.append(report("fleet_state_age_10hz_p50", float("nan"), "ms", "<= 100 ms", False,
                           reads=0))
    return rows


if __name__ == "__main__":
    main()
