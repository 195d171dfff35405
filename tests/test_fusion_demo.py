"""The Kobuki fusion demo's logics (behaviours/fusion_demo.py) without the simulation.

The sensor HALs are stand-ins registered under the Kobuki's HAL names; the test writes the
sensor keys itself and reads what the arbiter forwards (tests/test_fusion_sim.py does the
same with the physics).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from test_fusion import Recorder

from beehave import HAL, FusionInput, LowLevelBehaviorManager
from beehave.fusion import arbiter_name
from beehave.testing import wait_until
from behaviours.fusion_demo import FusionDemo

INPUTS = {"bumper": FusionInput(priority=100, max_age_s=0.3, safety=True),
          "joystick": FusionInput(priority=50, max_age_s=0.5),
          "wander": FusionInput(priority=10, max_age_s=0.5)}
CLEAR = {**{f"bumper/{s}": False for s in ("left", "center", "right")},
         **{f"cliff/{s}": False for s in ("left", "center", "right")},
         "wheel_drop/left": False, "wheel_drop/right": False}


class Bumpers(HAL):
    name = "kobuki_bumpers"


class Cliffs(HAL):
    name = "kobuki_cliffs"


@pytest.fixture
def ll() -> Iterator[LowLevelBehaviorManager]:
    Recorder.sent_by_all = []
    manager = LowLevelBehaviorManager(default="demo", stop_timeout_s=0.5)
    manager.hals.register(Recorder, name=arbiter_name("cmd_vel"), actuator="cmd_vel",
                          inputs=INPUTS, rate_hz=100.0)
    manager.hals.register(Bumpers)
    manager.hals.register(Cliffs)
    manager.register("demo", FusionDemo, speed_mps=0.3, backoff_s=0.2, turn_s=0.2)
    with manager:
        yield manager


def winner(ll: LowLevelBehaviorManager) -> dict[str, Any]:
    value = ll.blackboard.get("fusion/cmd_vel/winner")
    return value if isinstance(value, dict) else {}


def test_blind_sensors_hold_the_robot_then_wander_drives(ll: LowLevelBehaviorManager) -> None:
    # No bumper data yet: the safety source proposes to stand still, wander is overruled.
    assert wait_until(lambda: winner(ll) == {"source": "bumper", "value": (0.0, 0.0)})
    assert ll.blackboard.get("fusion/cmd_vel/wander") == (0.3, 0.0)
    for key, value in CLEAR.items():
        ll.blackboard.set(key, value)
    assert wait_until(lambda: winner(ll) == {"source": "wander", "value": (0.3, 0.0)})


def test_a_left_bump_backs_off_turns_right_then_hands_back(ll: LowLevelBehaviorManager) -> None:
    for key, value in CLEAR.items():
        ll.blackboard.set(key, value)
    assert wait_until(lambda: winner(ll).get("source") == "wander")
    ll.blackboard.set("bumper/left", True)
    assert wait_until(lambda: winner(ll) == {"source": "bumper", "value": (-0.1, 0.0)})
    ll.blackboard.set("bumper/left", False)
    assert wait_until(lambda: winner(ll) == {"source": "bumper", "value": (0.0, -1.0)})
    assert wait_until(lambda: winner(ll).get("source") == "wander")


def test_the_joystick_beats_wander_but_not_the_bumper(ll: LowLevelBehaviorManager) -> None:
    for key, value in CLEAR.items():
        ll.blackboard.set(key, value)
    ll.blackboard.set("joystick/cmd_vel", [0.1, 0.5])
    assert wait_until(lambda: winner(ll) == {"source": "joystick", "value": (0.1, 0.5)})
    ll.blackboard.set("cliff/center", True)
    assert wait_until(lambda: winner(ll) == {"source": "bumper", "value": (-0.1, 0.0)})
    ll.blackboard.set("cliff/center", False)
    ll.blackboard.set("joystick/cmd_vel", [0.2, 0.0])
    assert wait_until(lambda: winner(ll) == {"source": "joystick", "value": (0.2, 0.0)})
    # The teleop falls silent: after its max age, wander drives again.
    assert wait_until(lambda: winner(ll).get("source") == "wander")


def test_a_bad_joystick_value_is_refused_and_wander_goes_on(
        ll: LowLevelBehaviorManager, caplog: pytest.LogCaptureFixture) -> None:
    for key, value in CLEAR.items():
        ll.blackboard.set(key, value)
    ll.blackboard.set("joystick/cmd_vel", "forward!")
    assert wait_until(lambda: "'forward!' is not a pair of numbers" in caplog.text)
    assert wait_until(lambda: winner(ll).get("source") == "wander")
    assert ll.current == "demo"
