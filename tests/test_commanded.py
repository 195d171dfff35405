"""CommandedBehavior: commands from a queue; malformed ones are refused and recorded."""

from __future__ import annotations

import pytest

from beehave import HighLevelBehaviorManager, Status
from beehave.testing import ScriptedAction, wait_until
from behaviours.behaviors import CommandedBehavior, CommandError, CommandQueue


def scripted(duration_s: float = 0.0, fail: bool = False, kind: str = "driving"
             ) -> ScriptedAction:
    return ScriptedAction(kind, duration_s=duration_s,
                          raises=RuntimeError("wheel slip") if fail else None, result="ok")


def started(hl: HighLevelBehaviorManager) -> tuple[CommandQueue, CommandedBehavior]:
    queue = CommandQueue({"drive": scripted, "beep": lambda: ScriptedAction("sound")})
    hl.register("commanded", CommandedBehavior, queue=queue)
    behavior = hl.switch("commanded")
    assert isinstance(behavior, CommandedBehavior)
    return queue, behavior


def test_a_command_starts_its_action_and_its_outcome_is_recorded(
        hl: HighLevelBehaviorManager) -> None:
    queue, behavior = started(hl)
    queue.feed_json('{"action": "drive", "params": {"duration_s": 0.01}, "id": "c1"}')
    assert wait_until(lambda: len(queue.outcomes) == 1)
    (outcome,) = queue.outcomes
    assert (outcome.id, outcome.action, outcome.status, outcome.detail) == (
        "c1", "drive", "SUCCEEDED", "ok")
    assert behavior.status is Status.RUNNING


@pytest.mark.parametrize(("text", "expected"), [
    ('{"action": "drive"', "malformed JSON command"),
    ('["drive"]', "a command is a JSON object"),
    ('{"action": "fly"}', "unknown action 'fly'; known: 'beep', 'drive'"),
    ('{"action": "drive", "params": {"speed": 1}}', "action 'drive' rejects params"),
    ('{"action": "drive", "cancel": "all"}', "exactly one of 'action'"),
    ('{"action": "drive", "params": 3}', "params: Input should be a valid dictionary"),
])
def test_malformed_commands_raise_and_are_recorded(text: str, expected: str) -> None:
    queue = CommandQueue({"drive": scripted, "beep": lambda: ScriptedAction("sound")})
    with pytest.raises(CommandError, match=expected.replace("(", r"\(")):
        queue.feed_json(text)
    (rejected,) = queue.rejected
    assert rejected.received == text and expected in rejected.reason
    assert len(queue) == 0


def test_cancel_interrupts_the_running_command(hl: HighLevelBehaviorManager) -> None:
    queue, _ = started(hl)
    queue.put({"action": "drive", "params": {"duration_s": 30}, "id": "long"})
    assert wait_until(lambda: "long" in _running(hl))
    queue.put({"cancel": "long"})
    assert wait_until(lambda: len(queue.outcomes) == 1)
    assert queue.outcomes[0].status == "INTERRUPTED"


def test_a_busy_type_is_reported_and_preempt_takes_it(hl: HighLevelBehaviorManager) -> None:
    queue, _ = started(hl)
    queue.put({"action": "drive", "params": {"duration_s": 30}, "id": "first"})
    assert wait_until(lambda: "first" in _running(hl))
    queue.put({"action": "drive", "params": {"duration_s": 30}, "id": "second"})
    assert wait_until(lambda: any(o.id == "second" for o in queue.outcomes))
    assert [o.status for o in queue.outcomes if o.id == "second"] == ["BUSY"]
    queue.put({"action": "drive", "params": {"duration_s": 30}, "preempt": True, "id": "third"})
    assert wait_until(lambda: any(o.id == "first" for o in queue.outcomes))
    assert [o.status for o in queue.outcomes if o.id == "first"] == ["INTERRUPTED"]


def test_a_failing_command_is_recorded_without_ending_the_behaviour(
        hl: HighLevelBehaviorManager) -> None:
    queue, behavior = started(hl)
    queue.put({"action": "drive", "params": {"fail": True}, "id": "bad"})
    assert wait_until(lambda: len(queue.outcomes) == 1)
    assert queue.outcomes[0].status == "FAILED" and "wheel slip" in queue.outcomes[0].detail
    queue.put({"action": "beep", "id": "after"})
    assert wait_until(lambda: len(queue.outcomes) == 2)
    assert behavior.status is Status.RUNNING


def test_switching_away_interrupts_running_commands(hl: HighLevelBehaviorManager) -> None:
    queue, behavior = started(hl)
    queue.put({"action": "drive", "params": {"duration_s": 30}, "id": "long"})
    assert wait_until(lambda: "long" in _running(hl))
    hl.switch("idle")
    assert behavior.status is Status.INTERRUPTED
    assert [o.status for o in queue.outcomes] == ["INTERRUPTED"]


def _running(hl: HighLevelBehaviorManager) -> dict[str, object]:
    top = hl.top
    return dict(getattr(top, "running", {}))
