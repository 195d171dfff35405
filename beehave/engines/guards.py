"""Can a set of guards hold at once? The check behind the state machine's cycle rejection.

A state machine takes condition-only transitions (no ``on``) one after another without
waiting, so a cycle of them whose guards can all hold *for the same blackboard* never
stops: it re-enters its states, starting and safe-stating their actions, until the engine
gives up. :func:`can_hold_together` answers the question for one such cycle:

- ``KEY OP VALUE`` / ``KEY`` / ``not KEY`` conditions (:class:`BlackboardCondition`) are
  decided exactly: each reads one key, so the guards on one key are tried against every
  value that can make a difference (the constants they compare with, the values between
  and beyond them, a missing key, true, false) — the real condition objects are called,
  so the answer is what the engine would see.
- A network decision (``policy.condition("charge")``) cannot be two decisions at once.
- Any other callable is opaque: only "the same callable must hold and must not hold"
  is a contradiction. A cycle whose decidable guards can all hold and that has opaque
  guards left *may* loop: the caller warns instead of rejecting.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from beehave.engines.engine import BlackboardCondition, condition_label

__all__ = ["Guard", "Verdict", "can_hold_together"]


@dataclass(frozen=True)
class Guard:
    """``condition`` must hold (``holds=True``, a ``when``) or must not (an ``unless``)."""

    condition: Callable[..., Any]
    holds: bool = True


class Verdict(enum.Enum):
    """The answer of :func:`can_hold_together`."""

    NEVER = "never"
    """Some guards contradict each other: no blackboard makes them all hold."""
    POSSIBLE = "possible"
    """Every guard is decidable and some blackboard (``witness``) makes them all hold."""
    MAYBE = "maybe"
    """The decidable guards can hold together; opaque callables are left undecided."""


@dataclass
class Answer:
    verdict: Verdict
    #: For POSSIBLE / MAYBE: a blackboard (key → value) where the decidable guards
    #: hold; a missing key is shown as None.
    witness: dict[str, Any] = field(default_factory=dict)
    #: For MAYBE: labels of the guards that could not be decided.
    opaque: list[str] = field(default_factory=list)


class _Missing:
    def __repr__(self) -> str:
        return "<missing>"


_MISSING = _Missing()


def _candidates(conditions: Iterable[BlackboardCondition]) -> list[Any]:
    """Every value that can change the outcome of ``conditions`` on one key."""
    numbers: set[float] = set()
    others: list[Any] = []
    for cond in conditions:
        value = cond.value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            numbers.add(value)
        elif cond.op is not None and value not in others:
            others.append(value)
    ordered = sorted(numbers)
    # Plain numbers first, so that a reported witness reads naturally.
    values: list[Any] = [(low + high) / 2 for low, high in zip(ordered, ordered[1:],
                                                               strict=False)]
    if ordered:
        values += [ordered[0] - 1, ordered[-1] + 1]
    values += ordered
    for value in others:
        values.append(value)
        if isinstance(value, str):
            values.append(value + "\x00")  # just above it, for < and > on text
    values += [_MISSING, True, False, 0, "\x00any other text"]
    return values


def _holds(cond: BlackboardCondition, value: Any) -> bool:
    board = {} if value is _MISSING else {cond.key: value}
    return cond(board)


def can_hold_together(guards: Sequence[Guard]) -> Answer:
    """Whether some blackboard makes every guard come out as required."""
    by_key: dict[str, list[Guard]] = {}
    opaque: dict[int, tuple[Guard, bool]] = {}
    opaque_labels: list[str] = []
    policies: dict[int, Any] = {}
    decisions: dict[int, set[str]] = {}  # policy id → decisions that must be taken
    refused: dict[int, set[str]] = {}  # policy id → decisions that must not be taken
    for guard in guards:
        cond = guard.condition
        if isinstance(cond, BlackboardCondition):
            by_key.setdefault(cond.key, []).append(guard)
            continue
        policy = getattr(cond, "policy", None)
        decision = getattr(cond, "decision", None)
        if policy is not None and isinstance(decision, str) and hasattr(policy, "decisions"):
            policies[id(policy)] = policy
            bucket = decisions if guard.holds else refused
            bucket.setdefault(id(policy), set()).add(decision)
            continue
        seen = opaque.get(id(cond))
        if seen is not None and seen[1] != guard.holds:
            return Answer(Verdict.NEVER)
        if seen is None:
            opaque[id(cond)] = (guard, guard.holds)
            label = condition_label(cond)
            opaque_labels.append(label if guard.holds else f"not {label}")
    for policy_id, policy in policies.items():
        wanted, unwanted = decisions.get(policy_id, set()), refused.get(policy_id, set())
        # A network takes exactly one of its decisions.
        if len(wanted) > 1 or wanted & unwanted or unwanted >= set(policy.decisions):
            return Answer(Verdict.NEVER)
    if decisions or refused:
        opaque_labels += [f"nn: {d}" for ds in decisions.values() for d in sorted(ds)]
    witness: dict[str, Any] = {}
    for key, key_guards in by_key.items():
        conds = [g.condition for g in key_guards]
        assert all(isinstance(c, BlackboardCondition) for c in conds)
        for value in _candidates(conds):  # type: ignore[arg-type]
            if all(_holds(g.condition, value) == g.holds  # type: ignore[arg-type]
                   for g in key_guards):
                witness[key] = None if value is _MISSING else value
                break
        else:
            return Answer(Verdict.NEVER)
    if opaque_labels:
        return Answer(Verdict.MAYBE, witness, opaque_labels)
    return Answer(Verdict.POSSIBLE, witness)
