"""The serve scenario (issue 11, the ARCADE paper's SERVE task; docs/allocation.md):

- the world: EMILI has no path into the narrow shelf aisle, a Kobuki has;
- the market: EMILI's broker refuses the aisle's roles, so the auctioneer's choice for the
  cake from the narrow shelf is the coalition (a Kobuki fetches, EMILI serves);
- the physics of the items (``ServeFloor``): a hand-over happens only with both robots at
  the meeting point and EMILI's lift up; a serve records the display;
- the checks fail when the behaviour is wrong (broken variants of a passing run);
- the whole scenario, every robot and the order source in its own process over DDS, in
  real pybullet: every order completed and every check held.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("pybullet")
pytest.importorskip("rclpy")

from beehave.agents.market import Job, Task, choose  # noqa: E402
from beehave.errors import NoPath  # noqa: E402
from beehave.procs import dies_with_parent  # noqa: E402
from beehave.testing import WALL_TIMEOUT_S  # noqa: E402
from behaviours.actions import world_planner  # noqa: E402
from behaviours.demos.serve import AISLE, ServeFloor, checks  # noqa: E402
from behaviours.market.cafe import cafe_orders  # noqa: E402
from behaviours.market.serving import ServeBroker, held_item, parse_steps  # noqa: E402
from robots.world import load_world, world_from_dict  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
EMILI = {"capabilities": ("carry", "serve"), "robot_radius_m": 0.55, "clearance_m": 0.1,
         "has_lift": True, "has_display": True}  # as robots/config/serve_emili.yaml
KOBUKI = {"capabilities": ("carry",), "robot_radius_m": 0.2, "clearance_m": 0.1}


# ---- the world and the market (pure logic) -------------------------------------------------

def test_emili_finds_no_path_into_the_narrow_aisle_and_a_kobuki_does() -> None:
    world = load_world("serve")
    aisle = world.zone(AISLE)
    emili, kobuki = world_planner("serve", 0.55, 0.1), world_planner("serve", 0.2, 0.1)
    start = (10.5, 4.5)
    inside = [(x / 10, y / 100) for x in range(3, 50, 2) for y in range(625, 710, 10)
              if aisle.contains(x / 10, y / 100)]
    assert len(inside) > 50
    for point in inside:  # anywhere in the aisle, not only at the shelf
        with pytest.raises(NoPath):
            emili.plan(start, point, goal_tolerance_m=0.05)
    shelf = world.station("shelf_narrow").center_m
    assert kobuki.plan(start, shelf, goal_tolerance_m=0.05).length_m < 15.0
    for name in ("shelf_open", "meeting", "table1", "table2", "table3"):  # EMILI's places
        emili.plan(start, world.station(name).center_m, goal_tolerance_m=0.15)


class Standing(ServeBroker):
    """A broker at a fixed pose with a full battery (no robot needed to bid)."""

    def __init__(self, at: tuple[float, float], **options: Any) -> None:
        super().__init__("serve", **options)
        self.at = at

    def pose(self) -> tuple[float, float] | None:
        return self.at

    def battery_pct(self) -> float | None:
        return 90.0


def _bids(task: Task, brokers: dict[str, Standing]) -> tuple[dict[str, dict[str, list[str]]],
                                                              dict[Any, dict[str, float]],
                                                              dict[tuple[str, str], str]]:
    open_roles = {task.id: {p.name: [r.name for r in p.roles] for p in task.plans}}
    bids: dict[Any, dict[str, float]] = {}
    refused: dict[tuple[str, str], str] = {}
    for name, broker in brokers.items():
        for plan in task.plans:
            for role in plan.roles:
                job = Job(task, plan.name, role.name, conversation_id="c", initiator="o")
                if role.capability not in broker.capabilities:
                    continue
                offer = broker.cost(job, [])
                if isinstance(offer, float):
                    bids.setdefault((task.id, plan.name, role.name), {})[name] = offer
                else:
                    refused[(name, f"{plan.name}/{role.name}")] = str(offer)
    return open_roles, bids, refused


def test_the_narrow_shelf_is_served_by_a_coalition_and_the_open_one_by_emili_alone() -> None:
    tea, cake, napkins = cafe_orders("serve")
    brokers = {"emili1": Standing((10.5, 4.5), **EMILI),
               "kobuki1": Standing((3.1, 4.6), **KOBUKI)}
    open_roles, bids, refused = _bids(cake, brokers)
    # EMILI refuses everything in the aisle, saying why; it bids for serving at the meeting.
    assert refused[("emili1", "alone/serve")].startswith("no path")
    assert refused[("emili1", "coalition/fetch")].startswith("no path")
    assert "emili1" in bids[("cake", "coalition", "serve")]
    chosen = choose(open_roles, bids)["cake"]
    assert (chosen.plan, chosen.members) == ("coalition", {"fetch": "kobuki1",
                                                           "serve": "emili1"})
    open_roles, bids, _ = _bids(tea, brokers)
    assert choose(open_roles, bids)["tea"].members == {"serve": "emili1"}
    open_roles, bids, refused = _bids(napkins, brokers)
    assert refused[("emili1", "main/carry")].startswith("no path")
    assert choose(open_roles, bids)["napkins"].members == {"carry": "kobuki1"}


def test_malformed_steps_are_refused_naming_the_step_and_the_valid_ops() -> None:
    with pytest.raises(ValueError, match=r"params.steps\[1\] = \['fly', 'x', \[1, 2\]\].*"
                                         r"'pick', 'give', 'take', 'serve'"):
        parse_steps({"steps": [["pick", "s", [1, 2]], ["fly", "x", [1, 2]]]})
    with pytest.raises(ValueError, match="non-empty list"):
        parse_steps({})
    task = Task.make("serve", id="bad", location=(1, 1), roles=["carry"])
    job = Job(task, "main", "carry", conversation_id="c", initiator="o")
    reason = Standing((4.5, 4.3), **KOBUKI).cost(job, [])
    assert isinstance(reason, str) and reason.startswith("task 'bad', role 'carry': "
                                                         "params.steps must be")


# ---- an item left on a robot by a dissolved round (issue 11, CI) -----------------------------

def _job(task: Task, plan: str, role: str) -> Job:
    return Job(task, plan, role, conversation_id=f"c-{task.id}", initiator="orders")


def test_the_physics_word_on_a_held_item_is_unknown_until_it_names_the_robot() -> None:
    from std_msgs.msg import String

    state = String(data=json.dumps({"robots": {"kobuki1": {"item": "shelf_open#1"},
                                               "emili1": {"item": None}}}))
    assert held_item(state, "kobuki1") == (True, "shelf_open#1")
    assert held_item(state, "emili1") == (True, None)
    assert held_item(state, "kobuki2") == (False, None)  # not in the message
    assert held_item(String(data="not json"), "kobuki1") == (False, None)
    assert held_item(None, "kobuki1") == (False, None)


def test_a_robot_carrying_another_orders_item_refuses_to_take_or_pick_until_it_is_put_down(
        ) -> None:
    """CI: the tea's first round was dissolved after EMILI picked its item; re-awarded the
    cake's serve role first, EMILI stood at the meeting point with the tea on its plate,
    read it as the cake's hand-over, and waited for ``fetch:handed`` until its rendezvous
    timed out (the physics hands nothing onto a full plate). Now its bid says why not."""
    tea, cake, _ = cafe_orders("serve")
    emili = Standing((9.0, 6.3), **EMILI)
    emili.hold.set("shelf_open#1", "tea")
    take = _job(cake, "coalition", "serve")
    reason = emili.cost(take, [])
    assert isinstance(reason, str), f"bid {reason} for a take with the tea on the plate"
    assert "shelf_open#1" in reason and "'tea'" in reason and "cake/serve" in reason
    # With the tea's role queued ahead, the plate is free by then: it bids.
    tea_role = _job(tea, "main", "serve")
    assert isinstance(emili.cost(take, [tea_role]), float)
    # A robot that carries nothing bids for it at once.
    assert isinstance(Standing((9.0, 6.3), **EMILI).cost(take, []), float)
    # An item of no known order (never recorded) blocks too, naming it.
    emili.hold.sync("shelf_open#7")
    blocked = emili.cost(take, [])
    assert isinstance(blocked, str) and "shelf_open#7 of no known order" in blocked


def test_the_robot_that_holds_an_orders_item_carries_on_with_it_and_bids_less() -> None:
    """A re-awarded round: the robot holding the order's item skips the pick (no second
    item from the shelf, so "every item picked was served" can hold) — its bid leaves out
    the drive to the shelf, so it is the cheaper one for the order."""
    tea, cake, _ = cafe_orders("serve")
    role = _job(tea, "main", "serve")
    empty, carrying = Standing((7.0, 4.5), **EMILI), Standing((7.0, 4.5), **EMILI)
    carrying.hold.set("shelf_open#1", "tea")
    assert [xy for xy in carrying.stops(role)] == [parse_steps(role.role.params)[1][2]]
    with_item, without = carrying.cost(role, []), empty.cost(role, [])
    assert isinstance(with_item, float) and isinstance(without, float)
    assert with_item < without
    # A Kobuki that picked the cake's item for a dissolved round: its fetch goes straight
    # to the meeting point; the napkins (a pick of another order) wait until it is given.
    kobuki = Standing((1.3, 6.65), **KOBUKI)
    kobuki.hold.set("shelf_narrow#1", "cake")
    fetch = _job(cake, "coalition", "fetch")
    assert kobuki.stops(fetch) == [parse_steps(fetch.role.params)[1][2]]
    _, _, napkins = cafe_orders("serve")
    assert isinstance(kobuki.cost(_job(napkins, "main", "carry"), []), str)
    assert isinstance(kobuki.cost(_job(napkins, "main", "carry"), [fetch]), float)


def test_a_role_never_reads_another_orders_item_as_its_hand_over() -> None:
    """The runtime side: a take or pick that finds the robot carrying another order's item
    fails at once, naming it (not after a 60 s rendezvous timeout); its own order's item
    is carried on with."""
    from beehave.errors import BeehaveError
    from behaviours.market.serving import Hold, ServeError, ServeRole

    _, cake, _ = cafe_orders("serve")
    hold = Hold()
    hold.set("shelf_open#1", "tea")
    role = ServeRole(_job(cake, "coalition", "serve"), hold=hold, world="serve")
    role._me = "emili1"
    with pytest.raises(ServeError, match=r"cannot take at meeting: it carries shelf_open#1 "
                                         r"of order 'tea'"):
        role._carried("take", "meeting")
    assert issubclass(ServeError, BeehaveError)
    hold.set("shelf_narrow#1", "cake")
    assert role._carried("take", "meeting") == "shelf_narrow#1"
    hold.set(None, None)
    assert role._carried("take", "meeting") is None


# ---- the physics of the items ---------------------------------------------------------------

def _cafe(kobuki_at: tuple[float, float]) -> Any:
    """A 6 x 4 m room: EMILI stands in a table's spot 0.6 m east of the meeting point, the
    Kobuki in a shelf station at ``kobuki_at``."""
    return world_from_dict({
        "name": "cafe_test", "floor": {"size_m": [6, 4]},
        "stations": [
            {"name": "shelf_k", "kind": "pickup", "center_m": list(kobuki_at),
             "size_m": [0.6, 0.6]},
            {"name": "meeting", "kind": "dropoff", "center_m": [2.4, 2.0]},
            {"name": "table1", "kind": "dropoff", "center_m": [3.0, 2.0],
             "size_m": [0.6, 0.6]}],
        "robots": [
            {"namespace": "emili1", "kind": "emili", "start": {"x_m": 3.0, "y_m": 2.0}},
            {"namespace": "kobuki1", "kind": "kobuki",
             "start": {"x_m": kobuki_at[0], "y_m": kobuki_at[1]}}]})


def test_a_hand_over_needs_both_at_the_meeting_point_and_the_lift_up() -> None:
    from robots.sim import Simulation

    sim = Simulation(_cafe((1.8, 2.0)), real_time_factor=None)
    try:
        floor = ServeFloor(sim)
        sim.emili("emili1").set_display("cake: for table1")
        sim.run_for(3.0)
        facts = floor.facts()
        assert [p["robot"] for p in facts["picks"]] == ["kobuki1"]  # stood in the shelf
        floor.offer("kobuki1", "emili1", for_s=60.0)
        sim.run_for(2.0)
        assert floor.facts()["hand_overs"] == []  # offered, both there, the lift is down
        sim.emili("emili1").set_lift(0.2)
        sim.run_for(6.0)  # 2 s to raise it, 1 s to hand over, 1.5 s for the guest
        facts = floor.facts()
        h = facts["hand_overs"][0]  # (the Kobuki, still in its shelf, then picks again)
        assert (h["giver"], h["taker"], h["item"]) == ("kobuki1", "emili1", "shelf_k#1")
        assert h["giver_to_meeting_m"] < 0.7 and h["taker_lift_m"] >= 0.15
        d = facts["deliveries"][0]  # EMILI stands at table1: the guest takes it
        assert (d["item"], d["robot"], d["table"], d["display"]) == (
            "shelf_k#1", "emili1", "table1", "cake: for table1")
        assert d["time_s"] >= h["time_s"] + 1.5
    finally:
        sim.close()


@pytest.mark.parametrize("kobuki_at, offered", [
    ((0.6, 0.6), True),    # offered, but 2 m from the meeting point
    ((1.8, 2.0), False),   # at the meeting point, lift up, but never offered: passing by
])
def test_no_hand_over_away_from_the_meeting_point_or_without_an_offer(
        kobuki_at: tuple[float, float], offered: bool) -> None:
    from robots.sim import Simulation

    sim = Simulation(_cafe(kobuki_at), real_time_factor=None)
    try:
        floor = ServeFloor(sim)
        sim.emili("emili1").set_lift(0.2)
        if offered:
            floor.offer("kobuki1", "emili1", for_s=60.0)
        sim.run_for(6.0)
        facts = floor.facts()
        assert len(facts["picks"]) == 1 and facts["hand_overs"] == []
        assert floor.state()["robots"]["kobuki1"]["item"] == "shelf_k#1"
    finally:
        sim.close()


# ---- the checks fail when the behaviour is wrong ----------------------------------------------

OUTCOMES = {
    "tea": {"task": "tea", "kind": "serve", "table": "table3", "state": "completed",
            "plan": "main", "members": {"serve": "emili1"}},
    "cake": {"task": "cake", "kind": "serve", "table": "table1", "state": "completed",
             "plan": "coalition", "members": {"fetch": "kobuki2", "serve": "emili1"}},
    "napkins": {"task": "napkins", "kind": "deliver", "table": "table2",
                "state": "completed", "plan": "main", "members": {"carry": "kobuki1"}},
}
FACTS = {
    "world": "serve", "time_s": 110.0, "meeting": {"meeting": [6.05, 6.65]},
    "tables": {"table1": [2.5, 2.95], "table2": [6.0, 2.95], "table3": [9.5, 2.95]},
    "picks": [
        {"item": "shelf_open#1", "shelf": "shelf_open", "robot": "emili1", "time_s": 29.0,
         "x_m": 9.0, "y_m": 6.3},
        {"item": "shelf_narrow#1", "shelf": "shelf_narrow", "robot": "kobuki2",
         "time_s": 45.0, "x_m": 1.3, "y_m": 6.65},
        {"item": "shelf_narrow#2", "shelf": "shelf_narrow", "robot": "kobuki1",
         "time_s": 60.0, "x_m": 1.3, "y_m": 6.65}],
    "hand_overs": [
        {"item": "shelf_narrow#1", "giver": "kobuki2", "taker": "emili1",
         "meeting": "meeting", "time_s": 66.0, "giver_xy": [5.33, 6.65],
         "taker_xy": [6.73, 6.65], "giver_to_meeting_m": 0.72, "taker_to_meeting_m": 0.68,
         "taker_lift_m": 0.2}],
    "deliveries": [
        {"item": "shelf_open#1", "table": "table3", "robot": "emili1", "kind": "emili",
         "time_s": 42.0, "x_m": 9.5, "y_m": 3.07, "display": "tea: tea for table3",
         "lift_m": 0.0},
        {"item": "shelf_narrow#2", "table": "table2", "robot": "kobuki1", "kind": "kobuki",
         "time_s": 80.0, "x_m": 6.0, "y_m": 3.05, "display": None, "lift_m": None},
        {"item": "shelf_narrow#1", "table": "table1", "robot": "emili1", "kind": "emili",
         "time_s": 95.0, "x_m": 2.5, "y_m": 3.07, "display": "cake: cake for table1",
         "lift_m": 0.2}],
    "robots": {"emili1": {"kind": "emili", "item": None, "in_aisle_s": 0.0,
                          "first_in_aisle_at_s": None},
               "kobuki1": {"kind": "kobuki", "item": None, "in_aisle_s": 20.0,
                           "first_in_aisle_at_s": 30.0},
               "kobuki2": {"kind": "kobuki", "item": None, "in_aisle_s": 20.0,
                           "first_in_aisle_at_s": 20.0}},
    "zones": {AISLE: {"max_speed_mps": 0.25, "max_ratio": 0.94, "robot": "kobuki2",
                      "at_s": 40.0, "most_inside": 1, "most_inside_at_s": 20.0,
                      "most_inside_robots": ["kobuki2"]}},
}


def _failed(facts: dict[str, Any], outcomes: dict[str, Any] = OUTCOMES) -> list[str]:
    return [name for name, ok, _ in checks(facts, outcomes, expected=list(OUTCOMES))
            if not ok]


def _broken(change: Any) -> dict[str, Any]:
    facts = copy.deepcopy(FACTS)
    change(facts)
    return facts


def test_the_checks_pass_on_a_good_run() -> None:
    assert _failed(FACTS) == []


@pytest.mark.parametrize("change, fails", [
    # The Kobuki handed over 2 m from the meeting point.
    (lambda f: f["hand_overs"][0].update(giver_to_meeting_m=2.0),
     "cake: handed over kobuki2 -> emili1"),
    # EMILI took the item with its lift down.
    (lambda f: f["hand_overs"][0].update(taker_lift_m=0.0), "cake: handed over"),
    # The served cake was never handed over (EMILI fetched it some other way).
    (lambda f: f["hand_overs"].clear(), "cake: handed over"),
    # EMILI drove into the narrow aisle.
    (lambda f: f["robots"]["emili1"].update(in_aisle_s=3.0, first_in_aisle_at_s=50.0),
     "EMILI never in the narrow aisle"),
    # EMILI served the cake without showing the order.
    (lambda f: f["deliveries"][2].update(display=""), "cake: the order on emili1's display"),
    # The napkins went to another table.
    (lambda f: f["deliveries"][1].update(table="table3"), "napkins: served at table2"),
    # An item was picked and never served.
    (lambda f: f["picks"].append({**f["picks"][0], "item": "shelf_open#2"}),
     "every item picked was served"),
    # Two Kobukis in the one-lane aisle at once (the zone keeper let both in).
    (lambda f: f["zones"][AISLE].update(most_inside=2, most_inside_robots=["kobuki1",
                                                                          "kobuki2"]),
     "at most one robot in the aisle at once"),
    # A Kobuki raced through the aisle.
    (lambda f: f["zones"][AISLE].update(max_ratio=1.3), "aisle limit"),
])
def test_the_checks_fail_when_the_behaviour_is_wrong(change: Any, fails: str) -> None:
    failed = _failed(_broken(change))
    assert any(name.startswith(fails) for name in failed), failed


def test_an_order_the_market_did_not_complete_fails_its_check() -> None:
    outcomes = copy.deepcopy(OUTCOMES)
    outcomes["cake"].update(state="failed", reason="5 rounds without completion")
    assert _failed(FACTS, outcomes) == ["order 'cake' completed"]
    del outcomes["cake"]
    assert "order 'cake' completed" in _failed(FACTS, outcomes)


# ---- options --------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, says", [
    (["--robots", "0"], "--robots (the number of Kobukis) must be 1..4, got 0"),
    (["--robots", "9"], "must be 1..4, got 9"),
    (["--minutes", "-1"], "--minutes must be in (0, 60], got -1.0"),
    (["factory"], "world 'factory': "),
    (["nowhere.yaml"], "world 'nowhere.yaml': "),
])
def test_bad_serve_arguments_exit_2_naming_the_problem(
        argv: list[str], says: str, capsys: pytest.CaptureFixture[str]) -> None:
    from behaviours.demos.fleet import main as fleet_main

    with pytest.raises(SystemExit) as exc:
        fleet_main(["--scenario", "serve", *argv])
    assert exc.value.code == 2
    assert says in capsys.readouterr().err


# ---- the whole scenario: real processes over DDS, real pybullet ---------------------------------

# Real processes: slow on a loaded machine. The run's own bound stays below the test's.
@pytest.mark.timeout(int(5 * WALL_TIMEOUT_S))
def test_the_serve_scenario_completes_every_order_and_every_check_holds(
        tmp_path: Path) -> None:
    out = tmp_path / "out"

    def logs() -> str:
        return "".join(f"--- {log.name}\n{log.read_text(errors='replace')[-1500:]}\n"
                       for log in sorted((out / "serve").glob("*.log")))

    try:
        # --signed: every agent signs and takes only what the fleet signed (docs/agents.md).
        proc = subprocess.run([sys.executable, "-m", "beehave.cli", "fleet", "--scenario",
                               "serve", "--fast", "--signed", "--out", str(out)], cwd=ROOT,
                              env=dict(os.environ), capture_output=True, text=True,
                              timeout=4.7 * WALL_TIMEOUT_S,
                              preexec_fn=dies_with_parent)  # a worker's timeout: no orphans
    except subprocess.TimeoutExpired as exc:  # say where each process was
        shown = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) \
            else (exc.stdout or "")
        pytest.fail(f"timed out after {exc.timeout:.0f} s\n{shown[-6000:]}\n{logs()}")
    tail = proc.stdout[-6000:] + proc.stderr[-3000:] + logs()
    lines = [line for line in proc.stdout.splitlines() if line.startswith('{"serve"')]
    assert lines, f"no result line:\n{tail}"
    result = json.loads(lines[-1])["serve"]
    failed = [name for name, ok in result["checks"] if not ok]
    assert proc.returncode == 0 and result["passed"] and not failed, f"{failed}\n{tail}"
    cake = result["outcomes"]["cake"]
    assert cake["plan"] == "coalition" and cake["members"]["serve"] == "emili1"
    assert cake["members"]["fetch"].startswith("kobuki")
    assert result["outcomes"]["tea"]["members"] == {"serve": "emili1"}
    facts = json.loads((out / "serve_report.json").read_text())
    [hand_over] = facts["hand_overs"]  # measured in the physics, not told by the robots
    assert (hand_over["giver"], hand_over["taker"]) == (cake["members"]["fetch"], "emili1")
    assert facts["robots"]["emili1"]["in_aisle_s"] == 0.0
    assert len(facts["deliveries"]) == 3 and (out / "serve.png").stat().st_size > 10_000
    assert (out / "keys" / "emili1.cert").exists()
    assert not [log.name for log in (out / "serve").glob("*.log")
                if "OPEN mode" in log.read_text(errors="replace")]


def test_the_serve_watcher_counts_what_it_cannot_read() -> None:
    from behaviours.demos.serve import Watch

    watch = Watch()
    watch.on_order("not json")
    watch.on_order(json.dumps({"step": "finished"}))  # no detail
    watch.on_state("{")
    watch.on_order(json.dumps({"step": "finished", "detail": {"outcomes": {}}}))
    assert watch.malformed == 3 and watch.finished == {"outcomes": {}}
