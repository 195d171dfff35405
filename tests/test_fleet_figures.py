"""``beehave fleet`` as a user runs it, judged from outside (issue 24, items 5-7): its
figures (lead times, utilisation, distance, throughput, starvation) in the summary, the
JSON report and the picture, and checks that fail when coordination is poor — every order
sent to one ATV (``--dispatch single``) while the other stands idle.

The run is real: the sim, two ATVs, five machines and three stations as processes over
DDS on this test's ROS_DOMAIN_ID, in lockstep (``--fast``). What it checks is read from
the files and the output the command leaves, with plain json and PIL.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("pybullet")
pytest.importorskip("rclpy")

from beehave.procs import dies_with_parent  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S  # noqa: E402

# One real fleet run of 3 sim minutes (11 processes) is set up by the first test: about
# 30 s on an idle machine, 1 min beside other work; past the suite's 120 s default at load.
pytestmark = pytest.mark.timeout(int(6 * WALL_TIMEOUT_S))  # one worker: its lane (conftest)

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def single(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One 3-sim-minute run of the default factory with coordination off: every machine
    calls atv1 alone; atv2 is there and could help. Machines order at 37.5 % (not 60 %):
    press1 and lathe1 order within a second or two of each other (about 91 s), leaving
    46 s and 67 s until they reach safety stock. One ATV each makes it (the market: both
    delivered at about 131 s, 8 s before press1's due time); one ATV for both does not,
    whichever it takes first (measured: the second delivered 4-5 s late when press1 went
    first, about 30 s late the other way round); a loaded machine only makes it later.
    """
    out = tmp_path_factory.mktemp("fleet_single")
    # Dies with this worker (a timeout ends it without cleanup), and takes its sim,
    # robots and agents with it.
    run = subprocess.run(
        [sys.executable, "-m", "beehave.cli", "fleet", "--robots", "2", "--minutes", "3",
         "--fast", "--dispatch", "single", "--order-below", "0.375", "--out", str(out)],
        cwd=ROOT, env={**os.environ, "COLUMNS": "200"}, capture_output=True, text=True,
        timeout=5 * WALL_TIMEOUT_S, preexec_fn=dies_with_parent)
    last = run.stdout.strip().splitlines()[-1] if run.stdout.strip() else "{}"
    return {"code": run.returncode, "stdout": run.stdout, "stderr": run.stderr,
            "line": json.loads(last).get("fleet", {}), "out": out,
            "report": json.loads((out / "fleet_report.json").read_text())
            if (out / "fleet_report.json").exists() else {}}


def _why(run: dict[str, Any]) -> str:
    return f"exit {run['code']}\n{run['stdout'][-4000:]}\n{run['stderr'][-2000:]}"


def test_one_atv_taking_every_order_fails_the_checks(single: dict[str, Any]) -> None:
    assert single["code"] == 1, _why(single)
    assert single["line"]["passed"] is False and single["line"]["dispatch"] == "single"
    checks = {c["check"]: c for c in single["report"]["fleet"]["checks"]}
    failed = sorted(name for name, c in checks.items() if not c["passed"])
    # The machines starve and orders come late: the coordination checks, not a crash.
    assert failed, _why(single)
    assert set(failed) <= {"no machine ran empty",
                           "no order late (delivered before its machine fell to 20 %)"}, failed
    assert not [n for n in failed if "process" in n or "sim minutes" in n], failed


def test_the_figures_are_in_the_summary_the_report_and_the_picture(
        single: dict[str, Any]) -> None:
    from PIL import Image

    figs = single["report"]["fleet"]["figures"]
    facts = single["report"]
    assert figs["sim_s"] >= 180
    # Throughput: the sim's deliveries per hour of sim time.
    assert figs["deliveries"] == len(facts["deliveries"]) > 0
    assert figs["throughput_per_h"] == pytest.approx(
        len(facts["deliveries"]) / facts["time_s"] * 3600, abs=0.2)
    # Per ATV: atv1 did all the work, atv2 stood idle (busy share 0, no distance). The
    # first orders come about half-way through: atv1 is busy from then on (0.58 measured;
    # 0.40 on a loaded machine, its first award later).
    atvs = figs["atvs"]
    assert atvs["atv1"]["utilisation"] > 0.25 and atvs["atv1"]["distance_m"] > 20
    assert atvs["atv2"]["utilisation"] == 0 and atvs["atv2"]["distance_m"] < 1
    assert atvs["atv1"]["deliveries"] == facts["robots"]["atv1"]["deliveries"]
    # Per order: delivered ones have a lead time = delivered - placed, in sim seconds.
    delivered = [o for o in figs["order_list"] if o["state"] == "delivered"]
    assert delivered
    for o in delivered:
        assert o["lead_time_s"] == pytest.approx(o["delivered_s"] - o["placed_s"], abs=0.2)
        assert 0 < o["lead_time_s"] < figs["sim_s"] and o["awards"][-1] == "atv1"
    assert figs["orders"]["late"] >= 1 or figs["starved_s"] > 0
    # Starvation per machine is the sim's time at level 0.
    for name, m in figs["machines"].items():
        assert m["starved_s"] == pytest.approx(facts["machines"][name]["empty_s"], abs=0.1)
    # The summary prints them.
    for words in ("throughput", "utilisation", "lead time", "starved", "late"):
        assert words in single["stdout"], words
    # The machines' logs carry the sim time of every order.
    log = (single["out"] / "fleet" / "press1.log").read_text()
    events = [json.loads(line) for line in log.splitlines() if line.startswith("{")]
    orders = [e for e in events if e["event"] in ("order", "delivered", "order_failed")]
    assert orders and all(isinstance(e["sim_s"], float) for e in orders)
    # The picture: the sim's top-down view with the figures' panel beside it.
    image = Image.open(single["out"] / "fleet.png")
    assert image.width >= (24 + 1) * 40 + 400 and image.height == (16 + 1) * 40


def test_the_live_table_ends_true(single: dict[str, Any]) -> None:
    """The last live table (printed before the summary): a machine's "open order" is an
    order still open, never a delivered one; late orders are listed."""
    figs = single["report"]["fleet"]["figures"]
    final = {o["order"]: o for o in figs["order_list"]}
    live = single["stdout"][:single["stdout"].index("throughput")]
    titles = re.findall(r"sim\s+([\d.]+) s\s+wall", live)
    assert titles, live[-3000:]
    shown_at_s = float(titles[-1])
    table = live.rsplit("machines", 1)[1].split("charging stations")[0]
    rows = [[c.strip() for c in line.strip("│").split("│")] for line in table.splitlines()
            if line.startswith("│")]
    rows = [cells for cells in rows if cells[0]]  # not a wrapped line's continuation
    assert len(rows) == 5, table
    for cells in rows:
        row, open_order = " | ".join(cells), cells[2]
        if open_order:
            assert final[open_order]["state"] in ("created", "announced", "awarded"), row
    # Late by the time the table was drawn: listed in its "late" column.
    late = [o["order"] for o in figs["order_list"] if o["late"] and o["due_s"] < shown_at_s
            and (o["delivered_s"] is None or o["delivered_s"] <= shown_at_s)]
    assert late or figs["starved_s"] > 0
    for order in late:
        assert order in table, (order, table)


def test_the_atvs_start_without_a_refused_speed_limit(single: dict[str, Any]) -> None:
    """Every ATV once warned at start-up that set_parameters refused max_speed_mps=inf
    (undeclared parameter): the zones logic set it before the work behaviour declared it."""
    for k in (1, 2):
        log = (single["out"] / "fleet" / f"atv{k}.log").read_text()
        assert "refused max_speed_mps" not in log and "undeclared" not in log, log[-3000:]


# ---- the figures from a scripted history (no run) -------------------------------------

def _report(order: str, state: str, sim_s: float, *, placed: float, due: float | None,
            atv: str | None = None) -> dict[str, Any]:
    """A ``/fleet/orders`` report as docs/fleet.md gives it."""
    return {"schema": "beehave.fleet.order/1", "order": order,
            "machine": order.rsplit("-", 1)[0], "depot": "depot", "state": state,
            "atv": atv, "attempt": 1, "awards": [atv] if atv else [], "reason": None,
            "violation": None, "stamp": 0.0, "sim_s": sim_s, "placed_sim_s": placed,
            "due_sim_s": due}


#: (order, placed, due, [(state, sim_s, atv)]) — in time, delivered late, open past its
#: due time, open in time, failed past its due time (failed, not late), no due time.
Steps = list[tuple[str, float, str | None]]
SCRIPT: list[tuple[str, float, float | None, Steps]] = [
    ("press1-1", 100.0, 200.0, [("awarded", 101.0, "atv1"), ("delivered", 150.0, "atv1")]),
    ("press1-2", 110.0, 180.0, [("awarded", 111.0, "atv1"), ("delivered", 190.0, "atv1")]),
    ("press2-1", 120.0, 250.0, [("awarded", 121.0, "atv2")]),
    ("press2-2", 130.0, 400.0, [("announced", 130.0, None)]),
    ("press1-3", 140.0, 150.0, [("failed", 160.0, None)]),
    ("mill-1", 145.0, None, [("announced", 145.0, None)])]
LATE = {"press1-2", "press2-1"}


def _scripted_history() -> list[dict[str, Any]]:
    history = []
    for order, placed, due, steps in SCRIPT:
        history.append(_report(order, "created", placed, placed=placed, due=due))
        history += [_report(order, state, at, placed=placed, due=due, atv=atv)
                    for state, at, atv in steps]
    return sorted(history, key=lambda r: r["sim_s"])


def test_a_failed_order_or_one_without_a_due_time_is_never_late() -> None:
    """Beside tests/test_fleet.py's figures test (busy time, lead times, late delivered and
    open orders): failed and undated orders, and starvation from the sim's facts."""
    from behaviours.demos.fleet import figures

    facts = {"time_s": 300.0, "deliveries": [{}, {}],
             "robots": {ns: {"deliveries": 1 if ns == "atv1" else 0, "distance_m": 3.0,
                             "charging_s": 0.0} for ns in ("atv1", "atv2", "atv3")},
             "machines": {"press1": {"empty_s": 12.0, "first_empty_at_s": 170.0,
                                     "deliveries": 2, "min_level": 0.0,
                                     "capacity": 100.0}}}
    figs = figures(facts, _scripted_history(), 300.0)
    by_order = {o["order"]: o for o in figs["order_list"]}
    assert {o for o, r in by_order.items() if r["late"]} == LATE
    assert by_order["press1-1"]["lead_time_s"] == 50.0
    assert by_order["press1-2"]["lead_time_s"] == 80.0
    assert by_order["press2-1"]["lead_time_s"] is None
    assert figs["orders"] == {"placed": 6, "delivered": 2, "open": 3, "failed": 1, "late": 2,
                              "lead_time_mean_s": 65.0, "lead_time_max_s": 80.0}
    assert figs["atvs"]["atv3"]["utilisation"] == 0.0
    assert figs["machines"]["press1"]["starved_s"] == 12.0 == figs["starved_s"]


def _watch_with(history: list[dict[str, Any]], time_s: float = 300.0) -> Any:
    from behaviours.demos.fleet import Watch

    watch = Watch(state={"time_s": time_s, "machines": {
        name: {"level": 50.0, "capacity": 100.0} for name in ("mill", "press1", "press2")}})
    for r in history:
        watch.orders[r["order"]] = r
    watch.history = list(history)
    return watch


def test_the_live_table_lists_the_late_orders_the_figures_count() -> None:
    import io
    import time

    from rich.console import Console

    from behaviours.demos.fleet import _table

    console = Console(file=io.StringIO(), width=220, color_system=None)
    console.print(_table(_watch_with(_scripted_history()), time.monotonic()))
    text = console.file.getvalue()  # type: ignore[attr-defined]
    table = text.split("machines", 1)[1].split("charging stations")[0]
    rows = {cells[0]: cells for cells in
            ([c.strip() for c in line.strip("│").split("│")] for line in table.splitlines()
             if line.startswith("│"))}
    assert rows["press1"][-1] == "press1-2" and rows["press1"][-2] == "2", rows["press1"]
    assert rows["press2"][-1] == "press2-1" and rows["press2"][2] == "press2-2", rows["press2"]
    assert rows["mill"][-1] == "", rows["mill"]
