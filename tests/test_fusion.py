"""Priority fusion (beehave.fusion): which proposal the arbiter forwards, cycle by cycle.

Most tests drive :meth:`Arbiter.cycle` by hand on a blackboard with a fake clock, so a
table of (time, proposals) → forwarded value reads like the rules in the module docstring.
The last ones run the arbiter as a HAL in a real LowLevelBehaviorManager.
"""

from __future__ import annotations

import asyncio
import logging
import math
import random
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from beehave import (
    Arbiter,
    BadProposal,
    Blackboard,
    ConfigError,
    FusionInput,
    FusionLock,
    Logic,
    LowLevelBehaviorManager,
    UnknownFusionSource,
)
from beehave.clock import VirtualClock
from beehave.events import Event, EventBus, EventKind
from beehave.fusion import arbiter_name, check_twist, lock_key, make_inputs, proposal_key
from beehave.testing import wait_until

log = logging.getLogger(__name__)

STOP = (0.0, 0.0)
INPUTS = {"bumper": FusionInput(priority=100, max_age_s=0.3, safety=True),
          "joystick": FusionInput(priority=50, max_age_s=0.5),
          "wander": FusionInput(priority=10, max_age_s=0.5)}


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class Recorder(Arbiter):
    """A cmd_vel arbiter that records what it forwards instead of publishing it."""

    name = "fusion_cmd_vel"
    default_safe_value = STOP
    expected = "(linear_mps, angular_rps)"
    sent_by_all: list[tuple[float, float]] = []  # across instances (the manager builds one)

    def __init__(self, **params: Any) -> None:
        super().__init__(**params)
        self.sent: list[tuple[float, float]] = []

    def check(self, value: Any) -> tuple[float, float]:
        return check_twist(value)

    def forward(self, value: tuple[float, float]) -> None:
        self.sent.append(value)
        Recorder.sent_by_all.append(value)


class Rig:
    """An arbiter on an unbound blackboard (callbacks run in the writer's thread)."""

    def __init__(self, inputs: dict[str, FusionInput] = INPUTS,
                 locks: dict[str, FusionLock] | None = None) -> None:
        self.clock = FakeClock()
        self.board = Blackboard(clock=self.clock)
        self.arb = Recorder(actuator="cmd_vel", inputs=inputs, locks=locks)
        self.arb.blackboard = self.board.client("hal:fusion_cmd_vel")
        self.events: list[Event] = []
        self.arb.events = EventBus(log)
        self.arb.events.subscribe(self.events.append)
        asyncio.run(self.arb.on_load())

    def at(self, t: float) -> Rig:
        self.clock.t = 1000.0 + t
        return self

    def cycle(self) -> tuple[float, float] | None:
        """What this cycle forwarded (None: nothing)."""
        before = len(self.arb.sent)
        self.arb.cycle()
        return self.arb.sent[-1] if len(self.arb.sent) > before else None


@pytest.fixture
def rig() -> Rig:
    return Rig()


# ---- the rules, as tables of cycles --------------------------------------------------------

def test_the_higher_priority_wins_while_it_is_fresh(rig: Rig) -> None:
    rig.arb.propose("wander", (0.2, 0.0))
    assert rig.at(0.0).cycle() == (0.2, 0.0)
    rig.arb.propose("joystick", (0.5, 0.3))
    assert rig.at(0.1).cycle() == (0.5, 0.3)
    rig.arb.propose("wander", (0.25, 0.0))  # a lower priority changing its mind changes nothing
    assert rig.at(0.2).cycle() == (0.5, 0.3)
    assert rig.arb.winner == "joystick"
    assert rig.board.get("fusion/cmd_vel/winner") == {"source": "joystick", "value": (0.5, 0.3)}


def test_a_stale_proposal_expires_and_the_safe_value_is_sent_once(rig: Rig) -> None:
    rig.arb.propose("wander", (0.2, 0.0))
    table = [(0.0, (0.2, 0.0)), (0.25, (0.2, 0.0)), (0.5, (0.2, 0.0)),  # max age 0.5 s
             (0.51, STOP),  # expired: the safe value, once ...
             (0.6, None), (5.0, None)]  # ... and then silence, never the old command again
    assert [(t, rig.at(t).cycle()) for t, _ in table] == table
    assert rig.board.get("fusion/cmd_vel/winner") == {"source": None, "value": STOP}
    assert rig.board.is_stale(proposal_key("cmd_vel", "wander"))


def test_proposing_the_same_value_again_keeps_it_fresh(rig: Rig) -> None:
    # The blackboard wakes nobody for an equal value; freshness must come from the entry.
    for step in range(10):
        rig.at(step * 0.3)
        rig.arb.propose("wander", (0.2, 0.0))
        assert rig.cycle() == (0.2, 0.0), f"cycle {step}"


def test_safety_wins_over_any_priority() -> None:
    rig = Rig({"bumper": FusionInput(priority=1, max_age_s=0.3, safety=True),
               "joystick": FusionInput(priority=1000, max_age_s=0.5)})
    rig.arb.propose("joystick", (0.5, 0.0))
    rig.arb.propose("bumper", (-0.1, 0.0))
    assert rig.at(0.0).cycle() == (-0.1, 0.0)
    rig.arb.propose("joystick", (0.6, 0.0))
    assert rig.at(0.1).cycle() == (-0.1, 0.0)
    assert rig.arb.winner == "bumper"


def test_hand_over_to_the_lower_priority_when_the_higher_goes_stale(rig: Rig) -> None:
    rig.arb.propose("wander", (0.2, 0.0))
    rig.arb.propose("bumper", (-0.1, 0.0))
    cycles = []
    for t in (0.0, 0.2, 0.3, 0.31, 0.4):
        rig.at(t)
        rig.arb.propose("wander", (0.2, 0.0))  # wander keeps proposing; bumper fell silent
        cycles.append((t, rig.cycle(), rig.arb.winner))
    assert cycles == [(0.0, (-0.1, 0.0), "bumper"), (0.2, (-0.1, 0.0), "bumper"),
                      (0.3, (-0.1, 0.0), "bumper"), (0.31, (0.2, 0.0), "wander"),
                      (0.4, (0.2, 0.0), "wander")]


def test_withdraw_hands_over_at_the_next_cycle(rig: Rig) -> None:
    rig.arb.propose("wander", (0.2, 0.0))
    rig.arb.propose("joystick", (0.5, 0.0))
    assert rig.at(0.0).cycle() == (0.5, 0.0)
    rig.arb.withdraw("joystick")
    assert rig.at(0.01).cycle() == (0.2, 0.0)
    rig.arb.propose("joystick", (0.4, 0.0))  # fresh again
    assert rig.at(0.02).cycle() == (0.4, 0.0)


def test_nothing_proposed_yet_commands_the_safe_value_once(rig: Rig) -> None:
    assert [rig.at(t).cycle() for t in (0.0, 0.1, 0.2)] == [STOP, None, None]


def test_safe_state_sends_the_safe_value(rig: Rig) -> None:
    rig.arb.propose("joystick", (0.5, 0.0))
    rig.at(0.0).cycle()
    rig.arb.safe_state()
    assert rig.arb.sent[-1] == STOP


# ---- locks ---------------------------------------------------------------------------------

def test_a_lock_mutes_the_sources_up_to_its_priority_but_never_safety() -> None:
    rig = Rig(locks={"pause": FusionLock(priority=50)})
    rig.arb.propose("wander", (0.2, 0.0))
    assert rig.at(0.0).cycle() == (0.2, 0.0)  # never written: a plain lock is released
    rig.arb.set_lock("pause", True)
    rig.arb.propose("joystick", (0.5, 0.0))  # priority 50: muted too
    assert (rig.at(0.1).cycle(), rig.arb.locked) == (STOP, ("pause",))
    assert rig.board.get("fusion/cmd_vel/locked") == ["pause"]
    rig.arb.propose("bumper", (-0.1, 0.0))  # safety passes any lock
    assert rig.at(0.2).cycle() == (-0.1, 0.0)
    rig.arb.withdraw("bumper")
    assert rig.at(0.25).cycle() == STOP
    rig.arb.set_lock("pause", False)
    rig.arb.propose("joystick", (0.5, 0.0))
    assert (rig.at(0.3).cycle(), rig.arb.locked) == ((0.5, 0.0), ())


def test_a_heartbeat_lock_engages_while_it_is_silent() -> None:
    rig = Rig(locks={"estop": FusionLock(priority=1000, max_age_s=0.2)})
    rig.arb.propose("joystick", (0.5, 0.0))
    assert rig.at(0.0).cycle() == STOP  # never heard from the e-stop: locked
    rig.arb.set_lock("estop", False)  # the heartbeat: "not pressed"
    rig.arb.propose("joystick", (0.5, 0.0))
    assert rig.at(0.1).cycle() == (0.5, 0.0)
    rig.arb.propose("joystick", (0.5, 0.0))
    assert rig.at(0.35).cycle() == STOP  # the e-stop fell silent: locked again
    assert rig.arb.locked == ("estop",)


def test_a_lock_holding_garbage_is_engaged_and_reported() -> None:
    rig = Rig(locks={"pause": FusionLock(priority=50)})
    rig.arb.propose("wander", (0.2, 0.0))
    rig.board.set(lock_key("cmd_vel", "pause"), "off", writer="teleop")
    assert rig.at(0.0).cycle() == STOP
    assert rig.at(0.1).cycle() is None
    assert rig.arb.rejected == 1  # once, not per cycle
    assert "lock 'pause' must hold True or False, got 'off'" in rig.board.get(
        "fusion/cmd_vel/rejected")["reason"]
    rig.board.set(lock_key("cmd_vel", "pause"), False, writer="teleop")
    assert rig.at(0.2).cycle() == (0.2, 0.0)


def test_bad_locks_are_refused() -> None:
    rig = Rig(locks={"pause": FusionLock(priority=50)})
    with pytest.raises(UnknownFusionSource, match="unknown lock 'paws'; registered: 'pause'"):
        rig.arb.set_lock("paws", True)
    with pytest.raises(BadProposal, match="lock 'pause' must be set to True or False"):
        rig.arb.set_lock("pause", 1)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="lock priority must be an int"):
        FusionLock(priority=0.5)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="lock max_age_s must be finite seconds"):
        FusionLock(priority=1, max_age_s=math.inf)
    with pytest.raises(ConfigError, match="lock 'x': unknown key.*valid keys: priority"):
        Recorder(actuator="cmd_vel", inputs=INPUTS, locks={"x": {"priority": 1, "when": 2}})


# ---- bad input -----------------------------------------------------------------------------

def test_propose_refuses_an_unknown_source_and_lists_the_valid_ones(rig: Rig) -> None:
    with pytest.raises(UnknownFusionSource) as err:
        rig.arb.propose("wandr", (0.2, 0.0))
    msg = str(err.value)
    assert "'cmd_vel'" in msg and "'wandr'" in msg
    assert "'bumper', 'joystick', 'wander'" in msg
    assert err.value.choices == ["bumper", "joystick", "wander"]
    with pytest.raises(UnknownFusionSource):
        rig.arb.withdraw("nobody")
    assert "fusion/cmd_vel/wandr" not in rig.board


@pytest.mark.parametrize("value", [(0.2,), "fast", None, (math.nan, 0.0), (0.1, math.inf),
                                   (True, 0.0), {"linear": 1}])
def test_propose_refuses_a_value_of_the_wrong_type(rig: Rig, value: Any) -> None:
    with pytest.raises(BadProposal, match=r"arbiter 'cmd_vel': proposal of source 'wander'"
                                          r".*expected \(linear_mps, angular_rps\)"):
        rig.arb.propose("wander", value)
    assert proposal_key("cmd_vel", "wander") not in rig.board


def test_a_bad_proposal_on_the_blackboard_is_rejected_and_reported_not_forwarded(
        rig: Rig) -> None:
    rig.arb.propose("wander", (0.2, 0.0))
    rig.board.set("fusion/cmd_vel/joystick", "full speed", writer="teleop")
    rig.board.set("fusion/cmd_vel/typo", (1.0, 0.0), writer="teleop")
    assert rig.arb.rejected == 2
    assert rig.at(0.0).cycle() == (0.2, 0.0)  # the valid lower priority still drives
    assert rig.at(0.1).cycle() == (0.2, 0.0)
    assert rig.arb.rejected == 2  # reported once, not once per cycle
    subjects = [(e.kind, e.subject, e.status) for e in rig.events]
    assert subjects == [(EventKind.ENDED, "fusion:cmd_vel:joystick", "FAILED"),
                        (EventKind.ENDED, "fusion:cmd_vel:typo", "FAILED")]
    assert isinstance(rig.events[0].error, BadProposal)
    assert isinstance(rig.events[1].error, UnknownFusionSource)
    rejected = rig.board.get("fusion/cmd_vel/rejected")
    assert rejected["source"] == "typo" and "registered: 'bumper'" in rejected["reason"]
    # A good value replaces the bad one: forwarded again.
    rig.board.set("fusion/cmd_vel/joystick", [0.4, 0.1], writer="teleop")  # JSON: a list
    assert rig.at(0.2).cycle() == (0.4, 0.1)


@pytest.mark.parametrize(("spec", "problem"), [
    ({"priority": 1.5, "max_age_s": 0.5}, "priority must be an int"),
    ({"priority": True, "max_age_s": 0.5}, "priority must be an int"),
    ({"priority": "1", "max_age_s": 0.5}, "priority must be an int"),
    ({"priority": 1, "max_age_s": math.inf}, "max_age_s must be finite seconds"),
    ({"priority": 1, "max_age_s": math.nan}, "max_age_s must be finite seconds"),
    ({"priority": 1, "max_age_s": 0}, "max_age_s must be finite seconds"),
    ({"priority": 1, "max_age_s": "0.5"}, "max_age_s must be finite seconds"),
    ({"priority": 1, "max_age_s": 0.5, "safety": "yes"}, "safety must be true or false"),
    ({"priority": 1}, "priority and max_age_s are required"),
    ({"priority": 1, "max_age_s": 0.5, "timeout": 1}, "unknown key.*timeout.*valid keys"),
])
def test_bad_inputs_name_the_actuator_the_source_and_the_problem(spec: dict[str, Any],
                                                                 problem: str) -> None:
    with pytest.raises(ConfigError, match=rf"arbiter 'cmd_vel': input 'wander': .*{problem}"):
        make_inputs("cmd_vel", {"wander": spec})


@pytest.mark.parametrize(("inputs", "problem"), [
    ({}, "inputs must be a non-empty mapping"),
    ({"winner": {"priority": 1, "max_age_s": 1}}, "'winner' is reserved"),
    ({"a b": {"priority": 1, "max_age_s": 1}}, "source name 'a b' must be a name"),
    ({"a": {"priority": 1, "max_age_s": 1}, "b": {"priority": 1, "max_age_s": 2}},
     "'a' and 'b' are both non-safety with priority 1"),
])
def test_bad_input_sets_are_refused(inputs: dict[str, Any], problem: str) -> None:
    with pytest.raises(ConfigError, match=problem):
        make_inputs("cmd_vel", inputs)


def test_bad_arbiter_parameters_are_refused() -> None:
    with pytest.raises(ConfigError, match="rate_hz must be a finite number"):
        Recorder(actuator="cmd_vel", inputs=INPUTS, rate_hz=math.inf)
    with pytest.raises(ConfigError, match="arbiter actuator 'cmd/vel' must be a name"):
        Recorder(actuator="cmd/vel", inputs=INPUTS)
    with pytest.raises(ConfigError, match=r"safe_value \(1.0,\) is not valid.*expected"):
        Recorder(actuator="cmd_vel", inputs=INPUTS, safe_value=(1.0,))

    class NoDefault(Arbiter):
        def forward(self, value: Any) -> None: ...

    with pytest.raises(ConfigError, match="safe_value is required"):
        NoDefault(actuator="lift", inputs=INPUTS)


# ---- stress --------------------------------------------------------------------------------

def test_stress_the_forwarded_command_is_always_the_highest_fresh_proposal() -> None:
    """20 sources (4 safety) proposing, re-proposing, withdrawing and writing garbage at
    random for 5000 cycles; a reference model says, for every cycle, which source must
    win. Invariant: the arbiter forwards exactly that source's value (or the safe value
    once when none is fresh, then nothing)."""
    rnd = random.Random(11)
    names = [f"s{i}" for i in range(20)]
    inputs = {n: FusionInput(priority=rnd.randrange(1000) * 20 + i,
                             max_age_s=rnd.choice([0.05, 0.1, 0.3]), safety=i < 4)
              for i, n in enumerate(names)}
    rig = Rig(inputs)
    rank = sorted(names, key=lambda n: (not inputs[n].safety, -inputs[n].priority))
    model: dict[str, tuple[float, tuple[float, float]]] = {}  # source → (stamp, value)
    t = 0.0
    safe_sent = False
    winners = set()
    for cycle in range(5000):
        rig.at(t)
        now = rig.clock()  # the model reads ages on the arbiter's clock, rounding included
        for _ in range(rnd.randrange(4)):
            src = rnd.choice(names)
            roll = rnd.random()
            if roll < 0.7:
                value = (round(rnd.uniform(-1, 1), 2), float(names.index(src)))
                rig.arb.propose(src, value)
                model[src] = (now, value)
            elif roll < 0.85:
                rig.arb.withdraw(src)
                model.pop(src, None)
            else:  # garbage over the blackboard: rejected, the entry now holds no proposal
                rig.board.set(proposal_key("cmd_vel", src), "garbage", writer="fuzz")
                model.pop(src, None)
        fresh = [n for n in rank if n in model and now - model[n][0] <= inputs[n].max_age_s]
        sent = rig.cycle()
        if fresh:
            assert (sent, rig.arb.winner) == (model[fresh[0]][1], fresh[0]), f"cycle {cycle}"
            winners.add(fresh[0])
            safe_sent = False
        else:
            assert sent == (None if safe_sent else STOP), f"cycle {cycle}"
            assert rig.arb.winner is None
            safe_sent = True
        t += rnd.choice([0.0, 0.01, 0.02, 0.05])
    assert len(winners) >= 15  # the run really switched between many sources
    assert rig.arb.rejected > 100


def test_stress_proposers_in_threads_never_break_the_cycle() -> None:
    """Eight threads propose (and write garbage) concurrently while the loop cycles; every
    forwarded value must be the winner's own (values carry their source's index) and no
    cycle may raise."""
    names = [f"s{i}" for i in range(8)]
    inputs = {n: FusionInput(priority=i, max_age_s=0.05, safety=i == 0)
              for i, n in enumerate(names)}
    mismatches: list[tuple[str | None, Any]] = []

    class Checking(Recorder):
        def forward(self, value: tuple[float, float]) -> None:
            src = self.winner
            if src is not None and value[1] != float(names.index(src)):
                mismatches.append((src, value))
            super().forward(value)

    ll = LowLevelBehaviorManager(default="hold", stop_timeout_s=0.5)
    ll.hals.register(Checking, actuator="cmd_vel", inputs=inputs, rate_hz=500.0)
    ll.register("hold", Holder)
    Holder.seen = None
    stop = threading.Event()
    with ll:
        assert wait_until(lambda: Holder.seen is not None)
        arb = Holder.seen
        assert arb is not None

        def proposer(i: int) -> None:
            rnd = random.Random(i)
            while not stop.is_set():
                if rnd.random() < 0.1:
                    ll.blackboard.set(proposal_key("cmd_vel", names[i]), "garbage")
                else:
                    arb.propose(names[i], (rnd.random(), float(i)))

        threads = [threading.Thread(target=proposer, args=(i,)) for i in range(len(names))]
        for th in threads:
            th.start()
        assert wait_until(lambda: arb.cycles > 300)
        stop.set()
        for th in threads:
            th.join()
        assert arb.status.name == "RUNNING" and arb.restarts == 0
    assert not mismatches
    assert arb.rejected > 0


# ---- as a HAL in a running low level -------------------------------------------------------

class Holder(Logic):
    """Holds the arbiter loaded (as proposers do) and hands it to the test."""

    seen: Recorder | None = None

    async def run(self) -> None:
        Holder.seen = await self.hal(arbiter_name("cmd_vel"), Recorder)
        await asyncio.Event().wait()


class Wander(Logic):
    """Proposes driving forward every 20 ms, for ever."""

    async def run(self) -> None:
        drive = await self.hal(arbiter_name("cmd_vel"), Arbiter)
        while True:
            drive.propose("wander", (0.2, 0.0))
            await asyncio.sleep(0.02)


@pytest.fixture
def low_level(clock: VirtualClock) -> Iterator[LowLevelBehaviorManager]:
    """On the test kit's virtual clock: the arbiter's cycles and the proposals' ages are
    exact, on a loaded machine too."""
    Recorder.sent_by_all = []
    ll = LowLevelBehaviorManager(default="wander", stop_timeout_s=0.5, hal_handover_s=0.05,
                                 clock=clock)
    ll.hals.register(Recorder, actuator="cmd_vel", inputs=INPUTS, rate_hz=100.0)
    ll.register("wander", Wander)
    ll.register("other", Holder)
    ll.register("none", _Idle)
    with ll:
        yield ll


class _Idle(Logic):
    async def run(self) -> None:
        await asyncio.Event().wait()


def test_the_arbiter_cycles_at_its_rate_and_stops_the_actuator_at_unload(
        low_level: LowLevelBehaviorManager, clock: VirtualClock) -> None:
    clock.advance(1.0)
    # 100 Hz for one second, exactly: cycles at 0.00, 0.01, …, 1.00 s; the first comes
    # before wander's first proposal (the safe value), then wander wins every cycle.
    assert Recorder.sent_by_all == [STOP] + [(0.2, 0.0)] * 100
    assert low_level.blackboard.get("fusion/cmd_vel/winner") == {"source": "wander",
                                                                  "value": (0.2, 0.0)}
    low_level.switch("none")  # nobody holds the arbiter any more: unloaded, safe state
    assert clock.run_until(lambda: arbiter_name("cmd_vel") not in low_level.hals.loaded,
                           timeout_s=1.0)
    # The manager lists it as gone before its safe state has run (the unload finishes in
    # a task of its own): wait for the stop, then check nothing is sent after it.
    assert clock.run_until(lambda: Recorder.sent_by_all[-1] == STOP, timeout_s=1.0)
    sent = len(Recorder.sent_by_all)
    clock.advance(0.1)  # ten of its cycles
    assert len(Recorder.sent_by_all) == sent and Recorder.sent_by_all[-1] == STOP
    # Its blackboard subscription ended with it.
    assert not [s for s in low_level.blackboard._subs if s.pattern == "fusion/cmd_vel/*"]


def test_a_garbage_proposal_does_not_crash_the_running_arbiter(
        low_level: LowLevelBehaviorManager, clock: VirtualClock) -> None:
    events: list[Event] = []
    low_level.events.subscribe(events.append)
    assert clock.run_until(lambda: Recorder.sent_by_all.count((0.2, 0.0)) >= 2, timeout_s=1.0)
    low_level.blackboard.set("fusion/cmd_vel/joystick", {"v": 1}, writer="teleop")
    assert clock.run_until(lambda: any(e.subject == "fusion:cmd_vel:joystick"
                                       for e in events), timeout_s=1.0)
    count = len(Recorder.sent_by_all)
    clock.advance(0.05)
    assert len(Recorder.sent_by_all) == count + 5
    assert set(Recorder.sent_by_all[count:]) == {(0.2, 0.0)}
    hal = low_level.hals.loaded[arbiter_name("cmd_vel")]
    assert hal.restarts == 0 and hal.status.name == "RUNNING"


# ---- the robot file ------------------------------------------------------------------------

FUSION_YAML = {"cmd_vel": {"class": "test_fusion:Recorder", "rate_hz": 20.0,
                           "inputs": {"bumper": {"priority": 100, "max_age_s": 0.3,
                                                 "safety": True},
                                      "wander": {"priority": 10, "max_age_s": 0.5}}}}


def _robot_file(fusion: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {"namespace": "k", "fusion": fusion, **extra}


def test_the_kobuki_fusion_file_registers_its_arbiter() -> None:
    pytest.importorskip("rclpy")
    from beehave.config import load_config
    from beehave.robot import Robot
    from hal.drive import CmdVelArbiter

    robot = Robot(load_config("robots/config/kobuki_fusion.yaml"), only="low")
    assert robot.low is not None
    cls, params = robot.low.hals.resolve("fusion_cmd_vel")
    assert cls is CmdVelArbiter
    arbiter = cls(**params)
    assert isinstance(arbiter, CmdVelArbiter)
    assert arbiter.safe_value == STOP
    assert [(n, s.safety) for n, s in arbiter.sources.items()] == [
        ("bumper", True), ("joystick", False), ("wander", False)]
    assert arbiter.locks == {"pause": FusionLock(priority=50)}


@pytest.mark.parametrize(("change", "problem"), [
    ({"inputs": {"wander": {"priority": 1.5, "max_age_s": 0.5}}},
     "fusion.cmd_vel.inputs.wander.priority: Input should be a valid integer"),
    ({"inputs": {"wander": {"priority": 1, "max_age_s": float("inf")}}},
     "fusion.cmd_vel.inputs.wander.max_age_s: Input should be a finite number"),
    ({"inputs": {"wander": {"priority": 1, "max_age": 0.5}}},
     "fusion.cmd_vel.inputs.wander.max_age: unknown key; valid keys: priority, max_age_s, "
     "safety"),
    ({"locks": {"stop": {"priority": 1, "max_age": 1}}},
     "fusion.cmd_vel.locks.stop.max_age: unknown key; valid keys: priority, max_age_s"),
    ({"locks": {"stop": {"priority": 1.0}}},
     "fusion.cmd_vel.locks.stop.priority: Input should be a valid integer"),
    ({"rate": 5}, "fusion.cmd_vel.rate: unknown key; valid keys: class, rate_hz, safe_value, "
                  "inputs"),
    ({"inputs": {"a": {"priority": 1, "max_age_s": 1}, "b": {"priority": 1, "max_age_s": 1}}},
     "fusion.cmd_vel: arbiter 'cmd_vel': inputs 'a' and 'b' are both non-safety"),
    ({"inputs": {"winner": {"priority": 1, "max_age_s": 1}}},
     "fusion.cmd_vel: arbiter 'cmd_vel': source name 'winner' is reserved"),
])
def test_a_bad_fusion_section_names_the_file_and_the_key_path(change: dict[str, Any],
                                                               problem: str) -> None:
    from beehave.config import parse_config

    spec = {**FUSION_YAML["cmd_vel"], **change}
    with pytest.raises(ConfigError) as err:
        parse_config(_robot_file({"cmd_vel": spec}), source="k.yaml")
    assert str(err.value).startswith("k.yaml: ")
    assert problem in str(err.value)


def test_bad_arbiter_values_fail_when_the_robot_is_built_not_at_the_first_load() -> None:
    from beehave.config import parse_config
    from beehave.errors import NotASubclass
    from beehave.robot import Robot

    bad_safe = {"cmd_vel": {**FUSION_YAML["cmd_vel"], "safe_value": [0.0]}}
    with pytest.raises(ConfigError, match=r"k.yaml: fusion.cmd_vel: arbiter 'cmd_vel': "
                                          r"safe_value \[0.0\] is not valid"):
        Robot(parse_config(_robot_file(bad_safe), source="k.yaml"), only="low")
    not_arbiter = {"cmd_vel": {**FUSION_YAML["cmd_vel"], "class": "test_fusion:Wander"}}
    with pytest.raises(NotASubclass, match="k.yaml: fusion.cmd_vel.class: .* not a Arbiter"):
        Robot(parse_config(_robot_file(not_arbiter), source="k.yaml"), only="low")
    bad_name = {"cmd/vel": FUSION_YAML["cmd_vel"]}
    with pytest.raises(ConfigError, match=r"k.yaml: fusion.cmd/vel: actuator 'cmd/vel' must"):
        parse_config(_robot_file(bad_name), source="k.yaml")
    twice = _robot_file(FUSION_YAML, hals=[{"class": "test_fusion:Recorder",
                                            "name": "fusion_cmd_vel",
                                            "params": {"actuator": "x", "inputs": INPUTS}}])
    with pytest.raises(ConfigError, match="arbiter HAL 'fusion_cmd_vel' is already given by "
                                          "hals.0"):
        Robot(parse_config(twice, source="k.yaml"), only="low")
