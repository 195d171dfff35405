"""``beehave fleet --fast``: the real-time factor of the whole factory fleet, every agent
in its own process (the sim, each ATV's two managers, each machine and station), with 4 and
10 ATVs. The sim alone (no controllers, same run) is the baseline: the ratio says what the
agents cost. Target: ≥ 1× at 10 ATVs (issue 10).

    python -m benchmarks fleet            # about 6 minutes
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks._util import report

SIM_MINUTES = 2.0


def _fleet(robots: int, out: Path) -> dict[str, Any]:
    proc = subprocess.run(
        [sys.executable, "-m", "beehave.cli", "fleet", "--robots", str(robots), "--minutes",
         str(SIM_MINUTES), "--fast", "--out", str(out)],
        capture_output=True, text=True, timeout=1800)
    for line in proc.stdout.splitlines():
        if line.startswith('{"fleet"'):
            result: dict[str, Any] = json.loads(line)["fleet"]
            return result
    raise RuntimeError(f"beehave fleet printed no result (exit {proc.returncode}):\n"
                       f"{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")


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


def main() -> list[dict[str, Any]]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for robots in (4, 10):
            alone = _sim_alone(robots)
            result = _fleet(robots, Path(tmp) / f"fleet{robots}")
            rtf = result["real_time_factor"]
            rows.append(report(f"fleet_real_time_factor_{robots}_atvs", rtf, "x",
                               target=">= 1x" if robots == 10 else None,
                               ok=rtf >= 1.0 if robots == 10 else None,
                               sim_alone_x=round(alone, 2),
                               ratio_to_sim_alone=round(rtf / alone, 3),
                               checks_passed=result["passed"],
                               processes=_processes(robots)))
    return rows


if __name__ == "__main__":
    main()
