"""``beehave fleet --fast``: the real-time factor of the whole factory fleet, every agent
in its own process (the sim, each ATV's two managers, each machine and station), with 4 and
10 ATVs, and the largest fleet that still runs at real time or faster. The sim alone (no
controllers, same run) is the baseline: the ratio says what the agents cost.

Beside the real-time factor, what one ATV process costs: its CPU seconds per second of sim
time (user + system, from ``/proc/PID/stat``, over the run after start-up, averaged over
the ATVs). CPU time does not depend on how busy the rest of the host is the way wall time
does, so it is the figure to compare before and after a change on a shared machine.

Targets (issue 24, item 8): ≥ 1.5× at 10 ATVs; the largest fleet at ≥ 1× reported (the
aim: 25 ATVs on 2 cores). The search stops where ``beehave fleet`` refuses the size (the
factory world parks 10 ATVs today).

    python -m benchmarks fleet            # about 12 minutes
    python -m benchmarks.bench_fleet 4    # one fleet size only (2 sim minutes)
    python -m benchmarks.bench_fleet search   # only the largest fleet at >= 1x
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks._util import report

SIM_MINUTES = 2.0
#: Fleet sizes tried, in order, for the largest one at ≥ 1× real time (short runs).
SEARCH_ROBOTS = (10, 15, 20, 25)
SEARCH_MINUTES = 1.0
#: Sim seconds of start-up left out of the CPU figure (imports, discovery, first /clock).
SETTLE_SIM_S = 10.0
_CLK_TCK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` so far; None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / _CLK_TCK  # utime, stime


def _descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        try:
            children = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:
            continue
        out += [int(c) for c in children]
        todo += [int(c) for c in children]
    return out


def _role(argv: list[bytes]) -> str | None:
    """What a process of the fleet is: ``atvK``, ``sim`` or ``agent`` (a machine or a
    charging station); None for anything else."""
    args = [a.decode(errors="replace") for a in argv]
    if "run" in args:
        for arg in args:
            if arg.endswith(".yaml") and Path(arg).stem.startswith("atv"):
                return Path(arg).stem
    if "sim" in args:
        return "sim"
    if any(a in ("behaviours.fleet.machine", "behaviours.fleet.station") for a in args):
        return "agent"
    return None


def _fleet_pids(root: int) -> dict[str, int]:
    """The processes under ``root`` by name: ``atvK``, ``sim``, ``agentN``, and ``fleet``
    (the watcher, ``root`` itself)."""
    found = {"fleet": root}
    agents = 0
    for pid in _descendants(root):
        try:
            role = _role(Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0"))
        except OSError:
            continue
        if role == "agent":
            agents += 1
            role = f"agent{agents}"
        if role is not None:
            found[role] = pid
    return found


class _CpuWatch:
    """Samples the ATVs' CPU time against the sim time of ``/factory/state`` (5 Hz)."""

    def __init__(self, root: int, *, until_sim_s: float) -> None:
        from std_msgs.msg import String

        from beehave.ros.context import RosContext
        from hal.factory import STATE_QOS
        from robots.topics import FACTORY_STATE

        self.root = root
        # The fleet stops its ATVs once the sim reached the run's length; the sim runs on
        # meanwhile, faster without them: that part is no cost of theirs.
        self.until_sim_s = until_sim_s
        self.sim_s = 0.0
        self.first: tuple[float, dict[str, float]] | None = None
        self.last: tuple[float, dict[str, float]] | None = None
        self.wall: list[float] = []  # time.monotonic() of the first and the last sample
        self._stop = threading.Event()
        self._ros = RosContext()
        node = self._ros.create_node("bench_fleet_cpu")
        node.create_subscription(String, FACTORY_STATE, self._on_state, STATE_QOS)
        self._ros.start()
        self._thread = threading.Thread(target=self._sample, name="bench_fleet_cpu")
        self._thread.start()

    def _on_state(self, msg: Any) -> None:
        self.sim_s = float(json.loads(msg.data).get("time_s", 0.0))

    def _sample(self) -> None:
        pids: dict[str, int] = {}
        while not self._stop.wait(0.5):
            sim_s = self.sim_s
            if sim_s < SETTLE_SIM_S:
                continue
            if sim_s > self.until_sim_s:
                break
            if not any(k.startswith("atv") for k in pids):
                pids = _fleet_pids(self.root)
            cpu = {name: _cpu_s(pid) for name, pid in pids.items()}
            if len(cpu) < 2 or any(v is None for v in cpu.values()):
                if self.first is not None:
                    break  # the ATVs are being stopped
                pids = {}
                continue
            sample = (sim_s, {k: v for k, v in cpu.items() if v is not None})
            if self.first is None:
                self.first = sample
                self.wall = [time.monotonic()]
            self.last = sample
            self.wall[1:] = [time.monotonic()]

    def close(self) -> dict[str, Any]:
        self._stop.set()
        self._thread.join()
        self._ros.shutdown()
        if self.first is None or self.last is None or self.last[0] <= self.first[0]:
            return {}
        sim_s = self.last[0] - self.first[0]
        per = {k: (self.last[1][k] - self.first[1][k]) / sim_s
               for k in self.first[1] if k in self.last[1]}
        atvs = [v for k, v in per.items() if k.startswith("atv")]
        agents = [v for k, v in per.items() if k.startswith("agent")]
        if not atvs:
            return {}
        return {"atv_cpu_s_per_sim_s": round(sum(atvs) / len(atvs), 4),
                "atv_cpu_max": round(max(atvs), 4),
                "sim_cpu_s_per_sim_s": round(per.get("sim", math.nan), 4),
                "agent_cpu_s_per_sim_s": round(sum(agents) / max(len(agents), 1), 4),
                "watcher_cpu_s_per_sim_s": round(per.get("fleet", math.nan), 4),
                "total_cpu_s_per_sim_s": round(sum(per.values()), 3),
                "cpu_window_sim_s": round(sim_s, 1),
                # Sim seconds per wall second once every process runs (the run's own
                # factor counts the ATVs' start-up too, a large part of a short run).
                "steady_real_time_factor": round(sim_s / (self.wall[-1] - self.wall[0]), 3)}


def _fleet(robots: int, out: Path, minutes: float = SIM_MINUTES) -> dict[str, Any]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "beehave.cli", "fleet", "--robots", str(robots), "--minutes",
         str(minutes), "--fast", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watch = _CpuWatch(proc.pid, until_sim_s=minutes * 60.0)
    try:
        stdout, stderr = proc.communicate(timeout=1800)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        cpu = watch.close()
    for line in stdout.splitlines():
        if line.startswith('{"fleet"'):
            result: dict[str, Any] = json.loads(line)["fleet"]
            return {**result, **cpu}
    raise RuntimeError(f"beehave fleet printed no result (exit {proc.returncode}):\n"
                       f"{stdout[-2000:]}\n{stderr[-2000:]}")


def _sim_alone(robots: int) -> float:
    """Sim seconds per wall second of ``beehave sim factory --fast`` without controllers."""
    wall_s = 20.0
    with tempfile.TemporaryDirectory() as tmp:
        report_path = Path(tmp) / "r.json"
        started = time.monotonic()
        subprocess.run([sys.executable, "-m", "beehave.cli", "sim", "factory", "--robots",
                        str(robots), "--fast", "--no-lockstep", "--duration-s", str(wall_s),
                        "--report", str(report_path)], capture_output=True, timeout=300)
        took = time.monotonic() - started
        return float(json.loads(report_path.read_text())["time_s"]) / max(took, 1e-9)


def _processes(robots: int) -> int:
    """The sim, the ATVs, and one agent per machine and charging station."""
    from behaviours.fleet.site import site

    places = site("factory")
    return 1 + robots + len(places.machines) + len(places.stations)


def _row(robots: int, result: dict[str, Any], alone: float | None,
         minutes: float) -> dict[str, Any]:
    rtf = result["real_time_factor"]
    target = ">= 1.5x" if robots == 10 else None
    extra: dict[str, Any] = {}
    if alone is not None:
        extra = {"sim_alone_x": round(alone, 2), "ratio_to_sim_alone": round(rtf / alone, 3)}
    return report(f"fleet_real_time_factor_{robots}_atvs", rtf, "x", target=target,
                  ok=rtf >= 1.5 if robots == 10 else None, **extra,
                  sim_minutes=minutes, checks_passed=result["passed"],
                  steady_x=result.get("steady_real_time_factor"),
                  atv_cpu_s_per_sim_s=result.get("atv_cpu_s_per_sim_s"),
                  processes=_processes(robots), load_1min=round(os.getloadavg()[0], 1))


def main(sizes: tuple[int, ...] = (4, 10), search: bool = True) -> list[dict[str, Any]]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for robots in sizes:
            alone = _sim_alone(robots)
            result = _fleet(robots, Path(tmp) / f"fleet{robots}")
            rows.append(_row(robots, result, alone, SIM_MINUTES))
            if result.get("atv_cpu_s_per_sim_s") is not None:
                rows.append(report(
                    f"fleet_atv_cpu_per_sim_s_{robots}_atvs", result["atv_cpu_s_per_sim_s"],
                    "cpu s / sim s", atv_cpu_max=result.get("atv_cpu_max"),
                    sim=result.get("sim_cpu_s_per_sim_s"),
                    per_agent=result.get("agent_cpu_s_per_sim_s"),
                    watcher=result.get("watcher_cpu_s_per_sim_s"),
                    whole_fleet=result.get("total_cpu_s_per_sim_s"),
                    window_sim_s=result.get("cpu_window_sim_s")))
        if search:
            # Short runs, growing, until one falls below real time: the last that held.
            largest = 0
            refused = None
            for robots in SEARCH_ROBOTS:
                try:
                    result = _fleet(robots, Path(tmp) / f"search{robots}", SEARCH_MINUTES)
                except RuntimeError as exc:
                    if "--robots must be" not in str(exc):
                        raise
                    refused = robots  # the world has no room for more (its parking row)
                    break
                _row(robots, result, None, SEARCH_MINUTES)
                if result.get("steady_real_time_factor", result["real_time_factor"]) < 1.0:
                    break
                largest = robots
            rows.append(report("fleet_largest_at_real_time", largest, "ATVs",
                               target=">= 10 (aim: 25)", ok=largest >= 10,
                               criterion="steady real-time factor >= 1 (after start-up)",
                               refused_by_world=refused,
                               tried=list(SEARCH_ROBOTS), sim_minutes=SEARCH_MINUTES))
    return rows


if __name__ == "__main__":
    if len(sys.argv) > 1:  # fleet sizes, and "search" for the search too
        main(tuple(int(a) for a in sys.argv[1:] if a != "search"),
             search="search" in sys.argv[1:])
    else:
        main()
