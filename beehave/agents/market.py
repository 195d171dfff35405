"""Market-based task allocation with coalitions (the ARCADE paper's auctioneer and brokers).

A :class:`Task` has a kind, a place (``location`` or ``route``), an optional deadline and
one or more alternative :class:`Plan` s; a plan has one or more :class:`Role` s, each
naming the *capability* it needs (``lift``, ``transport``, ``display`` …). Every robot may
run a :class:`Broker` (it registers the directory service ``broker`` with its
capabilities, bids its own cost per role it can fill, refuses the others, and performs
the roles it is awarded, queued behind its earlier work) and an auctioneer
(:func:`auction`, or the :class:`Auctioneer` Behavior for many tasks).

One auction *round* is one conversation of the protocol ``beehave-auction``::

    auctioneer                                   brokers
      cfp {"tasks": [{task, open roles, done, reached}]}  ──►  every broker
      ◄── propose {"bids": [{task, plan, role, cost}], "refused": [...]}  (or refuse)
      accept-proposal {task, plan, role, members, done, reached}  ──►  each member
      reject-proposal  ──►  the others
      ◄── agree; inform {"event": "<role>:started"}; inform {"event": "<role>:<name>"} …
      inform {"event": …}  ──►  the other members of the task (rendezvous)
      ◄── inform {"result": …}  (the role is done)  or  failure

The auctioneer chooses, over all plans, the cheapest assignment of the open roles to
*distinct* brokers (a single robot, or a coalition), and never gives one broker two roles
in one round, so no robot holds two roles of one task. It then monitors the members: one
that fails, leaves the directory (its process died), neither agrees (it queued the role)
nor starts within ``start_timeout_s`` (a broker that bid but never starts), or then
stays silent for ``done_timeout_s`` dissolves the coalition — the other members get
``cancel`` — and the
task is auctioned again in a new round, keeping what was done: roles that finished stay
finished (their results and events are handed to the new members) and, once a role has
finished, the plan stays the one it belongs to.

Several tasks: :class:`Auctioneer` auctions them one at a time (a round is announced once
the previous one has awarded, so every bid sees the queues the earlier awards made), or,
with ``batch=True``, all waiting tasks in one round, assigned jointly (every broker gets
at most one role per round, and a task is awarded only if that gives it its cheapest
brokers; what is left waits for the next round, whose bids are re-planned on the new
queues).

Robot-agnostic: what a role costs and how it is performed is the broker's business
(``Broker.cost`` and ``Broker.perform_role``). See ``docs/allocation.md``.
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
import uuid
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, TypeVar

from beehave.action import Action
from beehave.agents.agent import Agent, AgentBehavior, Conversation, current_waiter
from beehave.agents.message import Message, Performative, jsonable
from beehave.agents.protocols import REFUSALS, Responder, ResponderTask, cancel_quietly
from beehave.errors import (
    AgentError,
    Interrupted,
    InvalidTask,
    NoReply,
    RendezvousTimeout,
    TaskFailed,
    UnknownCapability,
)
from beehave.runnable import Runnable

log = logging.getLogger(__name__)

AUCTION = "beehave-auction"
"""The protocol name of every auction message."""
BROKER_SERVICE = "broker"
"""The directory service a :class:`Broker` registers, with ``{"capabilities": [...]}``."""
MAX_ROLES = 12
"""Roles per plan: the exact assignment is exponential in it."""

Point = tuple[float, float]


# ---------------------------------------------------------------------- tasks
def _bad(where: str, what: str) -> InvalidTask:
    return InvalidTask(f"{where}: {what}")


def _name(value: Any, where: str) -> str:
    if not isinstance(value, str) or not value or len(value) > 100 or ":" in value:
        raise _bad(where, f"must be a non-empty str of at most 100 characters without ':', "
                          f"got {value!r}")
    return value


def _point(value: Any, where: str) -> Point:
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                       and math.isfinite(v) for v in value)):
        raise _bad(where, f"must be [x, y] in metres (two finite numbers), got {value!r}")
    return (float(value[0]), float(value[1]))


def _keys(data: Any, where: str, required: set[str], optional: set[str]) -> dict[str, Any]:
    if not isinstance(data, Mapping):
        raise _bad(where, f"must be a mapping with the keys {sorted(required | optional)}, "
                          f"got {type(data).__name__}")
    unknown = sorted(set(data) - required - optional)
    if unknown:
        raise _bad(where, f"unknown key(s) {unknown}; valid: {sorted(required | optional)}")
    missing = sorted(required - set(data))
    if missing:
        raise _bad(where, f"missing key(s) {missing}")
    return dict(data)


@dataclass(frozen=True)
class Role:
    """One part of a plan, filled by one robot that has ``capability``.

    ``waits_for`` names the events of other roles of the same plan this role waits for
    (``"fetch:at_meeting"``: a rendezvous); it documents the coordination and is checked
    against the plan's roles. ``params`` is free JSON for the broker (a meeting point…)."""

    name: str
    capability: str
    waits_for: tuple[str, ...] = ()
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "capability": self.capability,
                "waits_for": list(self.waits_for), "params": self.params}


@dataclass(frozen=True)
class Plan:
    """One way to do a task: its roles, each for a distinct robot."""

    name: str
    roles: tuple[Role, ...]

    def role(self, name: str) -> Role:
        for role in self.roles:
            if role.name == name:
                return role
        raise KeyError(f"plan {self.name!r} has no role {name!r}; its roles: "
                       f"{[r.name for r in self.roles]}")

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "roles": [r.to_dict() for r in self.roles]}


@dataclass(frozen=True)
class Task:
    """A job for the market. Build it with :meth:`make` (Python) or :meth:`from_dict`
    (JSON/YAML); both check it and raise :class:`~beehave.errors.InvalidTask` naming the
    key path and what is valid.

    ``deadline`` is a Unix time: brokers see it (bid accordingly), and the auctioneer
    fails the task when it passes before the task is done."""

    id: str
    kind: str
    plans: tuple[Plan, ...]
    location: Point | None = None
    route: tuple[Point, ...] = ()
    deadline: float | None = None
    params: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def make(cls, kind: str, *, roles: Iterable[Role | str] | None = None,
             plans: Mapping[str, Iterable[Role | str]] | None = None,
             id: str | None = None, location: Sequence[float] | None = None,
             route: Iterable[Sequence[float]] = (), deadline: float | None = None,
             params: Mapping[str, Any] | None = None) -> Task:
        """``roles`` for a task with one plan (``"main"``), or ``plans`` (name → roles)
        for alternatives. A role given as a str is a role of that capability named
        after it: ``Task.make("deliver", roles=["transport"])``."""
        if (roles is None) == (plans is None):
            raise InvalidTask(f"task {kind!r}: give exactly one of roles= (one plan) or "
                              f"plans= (alternatives)")
        named = {"main": roles} if roles is not None else dict(plans or {})
        data = {"id": id or f"{kind}-{uuid.uuid4().hex[:8]}", "kind": kind,
                "location": None if location is None else list(location),
                "route": [list(p) for p in route], "deadline": deadline,
                "params": dict(params or {}),
                "plans": [{"name": name, "roles": [
                    {"name": r, "capability": r} if isinstance(r, str) else r.to_dict()
                    for r in rs]} for name, rs in named.items()]}
        return cls.from_dict(data)

    @classmethod
    def from_dict(cls, data: Any, *, source: str = "task") -> Task:
        """Check and build a task from its JSON form (what :meth:`to_dict` gives)."""
        d = _keys(data, source, {"kind", "plans"},
                  {"id", "location", "route", "deadline", "params"})
        kind = _name(d["kind"], f"{source}.kind")
        tid = _name(d.get("id") or f"{kind}-{uuid.uuid4().hex[:8]}", f"{source}.id")
        where = f"task {tid!r}"
        location = None if d.get("location") is None else _point(d["location"],
                                                                 f"{where}: location")
        route_in = d.get("route") or []
        if not isinstance(route_in, list):
            raise _bad(f"{where}: route", f"must be a list of [x, y], got {route_in!r}")
        route = tuple(_point(p, f"{where}: route[{i}]") for i, p in enumerate(route_in))
        deadline = d.get("deadline")
        if deadline is not None and (isinstance(deadline, bool)
                                     or not isinstance(deadline, (int, float))
                                     or not math.isfinite(deadline)):
            raise _bad(f"{where}: deadline", f"must be a Unix time in seconds, got "
                                             f"{deadline!r}")
        params = d.get("params") or {}
        if not isinstance(params, dict):
            raise _bad(f"{where}: params", f"must be a mapping, got {params!r}")
        plans_in = d["plans"]
        if not isinstance(plans_in, list) or not plans_in:
            raise _bad(f"{where}: plans", f"must be a non-empty list of plans, got "
                                          f"{plans_in!r}")
        plans: list[Plan] = []
        for i, p in enumerate(plans_in):
            pw = f"{where}: plans[{i}]"
            pd = _keys(p, pw, {"roles"}, {"name"})
            pname = _name(pd.get("name") or f"plan{i}", f"{pw}.name")
            if any(q.name == pname for q in plans):
                raise _bad(f"{pw}.name", f"{pname!r} names two plans; plan names are unique")
            roles_in = pd["roles"]
            if not isinstance(roles_in, list) or not roles_in or len(roles_in) > MAX_ROLES:
                raise _bad(f"{pw}.roles", f"must be a list of 1 to {MAX_ROLES} roles, got "
                                          f"{roles_in!r:.200}")
            roles: list[Role] = []
            for j, r in enumerate(roles_in):
                rw = f"{pw}.roles[{j}]"
                rd = _keys(r, rw, {"capability"}, {"name", "waits_for", "params"})
                cap = _name(rd["capability"], f"{rw}.capability")
                rname = _name(rd.get("name") or cap, f"{rw}.name")
                if any(q.name == rname for q in roles):
                    raise _bad(f"{rw}.name", f"{rname!r} names two roles of plan {pname!r}; "
                                             f"give each role a name")
                waits = rd.get("waits_for") or []
                rparams = rd.get("params") or {}
                if not isinstance(waits, list) or not isinstance(rparams, dict):
                    raise _bad(rw, "waits_for must be a list of 'role:event', params a "
                                   "mapping")
                roles.append(Role(rname, cap, tuple(waits), dict(rparams)))
            names = [r.name for r in roles]
            for j, role in enumerate(roles):
                for k, event in enumerate(role.waits_for):
                    other, _, ev = event.partition(":") if isinstance(event, str) else ("", "", "")
                    if other not in names or other == role.name or not ev:
                        raise _bad(f"{pw}.roles[{j}].waits_for[{k}]",
                                   f"{event!r} is not '<role>:<event>' of another role of "
                                   f"this plan; its roles: {names}")
            plans.append(Plan(pname, tuple(roles)))
        return cls(tid, kind, tuple(plans), location, route,
                   None if deadline is None else float(deadline), dict(params))

    def plan(self, name: str) -> Plan:
        for plan in self.plans:
            if plan.name == name:
                return plan
        raise KeyError(f"task {self.id!r} has no plan {name!r}; its plans: "
                       f"{[p.name for p in self.plans]}")

    @property
    def capabilities(self) -> set[str]:
        return {r.capability for p in self.plans for r in p.roles}

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "kind": self.kind, "plans": [p.to_dict() for p in self.plans],
                "location": None if self.location is None else list(self.location),
                "route": [list(p) for p in self.route], "deadline": self.deadline,
                "params": self.params}


def check_capabilities(task: Task, offered: Collection[str], *,
                       vocabulary: bool = False) -> None:
    """Raise :class:`~beehave.errors.UnknownCapability` when ``task`` cannot be matched
    against ``offered``: with ``vocabulary`` (a fixed list of valid capabilities) any role
    outside it; otherwise only when no plan is fully covered (an alternative plan may
    need a robot that is simply not running)."""
    for plan in task.plans:
        missing = [r for r in plan.roles if r.capability not in offered]
        if vocabulary and missing:
            raise UnknownCapability(missing[0].capability, offered,
                                    where=f"task {task.id!r}, plan {plan.name!r}, role "
                                          f"{missing[0].name!r}: ")
        if not missing:
            return
    first = next(r for p in task.plans for r in p.roles if r.capability not in offered)
    raise UnknownCapability(first.capability, offered,
                            where=f"task {task.id!r}: no plan can be staffed (every plan "
                                  f"needs a capability nobody offers); ")


# ---------------------------------------------------------------------- assignment
Bids = dict[tuple[str, str, str], dict[str, float]]
"""(task id, plan, role) → {broker: cost}."""


def best_assignment(roles: Sequence[str], bids: Mapping[str, Mapping[str, float]]
                    ) -> tuple[float, dict[str, str]] | None:
    """The cheapest assignment of ``roles`` to distinct bidders (``bids``: role →
    {bidder: cost}), exactly, by dynamic programming over the subsets of roles; None
    when the roles cannot all be filled by distinct bidders. Ties go to the bidder whose
    name sorts first."""
    k = len(roles)
    bidders = sorted({b for r in roles for b in bids.get(r, {})})
    full = (1 << k) - 1
    inf = math.inf
    best: list[float] = [0.0] + [inf] * full
    choice: list[list[tuple[int, int] | None]] = []
    for b in bidders:
        step: list[tuple[int, int] | None] = [None] * (full + 1)
        new = list(best)
        for mask in range(full + 1):
            if best[mask] == inf:
                continue
            for i, role in enumerate(roles):
                if mask >> i & 1:
                    continue
                cost = bids.get(role, {}).get(b)
                if cost is None:
                    continue
                m2 = mask | 1 << i
                if best[mask] + cost < new[m2]:
                    new[m2] = best[mask] + cost
                    step[m2] = (mask, i)
        best = new
        choice.append(step)
    if best[full] == inf:
        return None
    out: dict[str, str] = {}
    mask = full
    for idx in range(len(bidders) - 1, -1, -1):
        picked = choice[idx][mask]
        if picked is None:
            continue  # this bidder got nothing
        prev, i = picked
        out[roles[i]] = bidders[idx]
        mask = prev
    return best[full], out


def hungarian(cost: Sequence[Sequence[float]]) -> list[int]:
    """Minimum-cost assignment of a rectangular matrix (rows ≤ columns): the column of
    each row. Classic O(n²m) shortest augmenting paths with potentials."""
    n = len(cost)
    m = len(cost[0]) if n else 0
    if n > m:
        raise ValueError("hungarian: more rows than columns")
    u = [0.0] * (n + 1)
    v = [0.0] * (m + 1)
    p = [0] * (m + 1)
    way = [0] * (m + 1)
    for i in range(1, n + 1):
        p[0] = i
        j0 = 0
        minv = [math.inf] * (m + 1)
        used = [False] * (m + 1)
        while True:
            used[j0] = True
            i0, delta, j1 = p[j0], math.inf, 0
            for j in range(1, m + 1):
                if not used[j]:
                    cur = cost[i0 - 1][j - 1] - u[i0] - v[j]
                    if cur < minv[j]:
                        minv[j], way[j] = cur, j0
                    if minv[j] < delta:
                        delta, j1 = minv[j], j
            for j in range(m + 1):
                if used[j]:
                    u[p[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if p[j0] == 0:
                break
        while True:
            j1 = way[j0]
            p[j0] = p[j1]
            j0 = j1
            if not j0:
                break
    row_col = [-1] * n
    for j in range(1, m + 1):
        if p[j]:
            row_col[p[j] - 1] = j - 1
    return row_col


@dataclass
class Choice:
    """What the auctioneer chose for one task in a round."""

    task: str
    plan: str
    members: dict[str, str]  # role → broker
    cost: float


def choose(open_roles: Mapping[str, Mapping[str, Sequence[str]]], bids: Bids, *,
           batch: bool = False) -> dict[str, Choice]:
    """The awards of one round. ``open_roles``: task id → plan → the roles still to fill
    (plans that cannot be used any more are left out).

    Single task (or ``batch=False`` with several: one after another, greedily): the
    cheapest plan with its cheapest assignment to distinct brokers. ``batch``: every
    task's cheapest plan on its own, then one joint minimum-cost assignment in which a
    broker fills at most one role (a bid is priced on the broker's queue as it is: a
    second role in the same round would make it stale). A task is awarded only when the
    joint assignment gives it its cheapest assignment; a task that would have to settle
    for dearer brokers (its cheapest went to other tasks), or does not get all its roles,
    waits for the next round, whose bids are re-planned on the queues this one left —
    forcing it on a second choice now is what makes one-shot joint rounds worse than
    sequential auctions when brokers queue work. When no task gets its cheapest
    assignment, the task whose cheapest assignment is cheapest is awarded alone, so
    every round that can award something does."""
    chosen: dict[str, Choice] = {}
    taken: set[str] = set()
    solo: dict[str, Choice] = {}
    for tid, plans in open_roles.items():
        best: Choice | None = None
        for plan, roles in plans.items():
            table = {r: {b: c for b, c in bids.get((tid, plan, r), {}).items()
                         if batch or b not in taken} for r in roles}
            found = best_assignment(list(roles), table)
            if found is not None and (best is None or found[0] < best.cost):
                best = Choice(tid, plan, found[1], found[0])
        if best is None:
            continue
        if batch:
            solo[tid] = best
        else:
            chosen[tid] = best
            taken.update(best.members.values())
    if not batch or not solo:
        return chosen
    rows = [(tid, c.plan, r) for tid, c in solo.items()
            for r in open_roles[tid][c.plan]]
    brokers = sorted({b for row in rows for b in bids.get(row, {})})
    big = 1.0 + 2.0 * sum(max(bids.get(row, {}).values(), default=0.0) for row in rows)
    # A column per broker, and one "not now" column per row so that every row can be left
    # unfilled (at a price above any real assignment).
    matrix = [[bids.get(row, {}).get(b, math.inf) for b in brokers]
              + [big] * len(rows) for row in rows]
    matrix = [[big * 4 if c == math.inf else c for c in line] for line in matrix]
    cols = hungarian(matrix)
    got: dict[str, dict[str, str]] = {}
    for i, ((tid, _plan, role), col) in enumerate(zip(rows, cols, strict=True)):
        if col < len(brokers) and matrix[i][col] < big:
            got.setdefault(tid, {})[role] = brokers[col]
    for tid, c in solo.items():
        members = got.get(tid, {})
        if len(members) != len(open_roles[tid][c.plan]):
            continue  # half staffed: it waits
        cost = sum(bids[(tid, c.plan, r)][b] for r, b in members.items())
        if cost <= c.cost + 1e-9 * max(1.0, abs(c.cost)):
            chosen[tid] = Choice(tid, c.plan, members, cost)
    if not chosen:
        first = min(solo.values(), key=lambda c: (c.cost, c.task))
        chosen[first.task] = first
    return chosen


# ---------------------------------------------------------------------- broker side
_J = TypeVar("_J")


def cheapest_insertion(new: _J, queue: Sequence[_J],
                       queue_cost: Callable[[list[_J]], float | str | None], *,
                       fixed: int = 0) -> tuple[float, int] | str:
    """Where ``new`` costs least in ``queue``, and what it adds: ``(marginal cost,
    position)``, or the reason it fits nowhere.

    ``queue_cost(order)`` is the cost, in the market's global metric, of doing ``order``
    in that order (a float), or a reason (str) / None when that order is not feasible.
    The marginal cost of a position is ``queue_cost(with new there) -
    queue_cost(queue)``: the new role's own cost *and* the delay it puts on the roles it
    goes before. The first ``fixed`` entries (roles already running) keep their place.
    Ties go to the later position (the earlier roles are not delayed for nothing).

    A market whose brokers bid this way minimises the sum of the queues' costs: the sum
    of the winning bids is exactly what the accepted roles add to it. Bidding the new
    role's own completion time at the end of the queue instead ignores the roles queued
    behind it and that one a short role could go before a long one."""
    base = queue_cost(list(queue))
    if base is None or isinstance(base, str):
        return f"the queue as it is: {base or 'not feasible'}"
    best: tuple[float, int] | None = None
    why: str | None = None
    for i in range(max(0, min(fixed, len(queue))), len(queue) + 1):
        order = [*queue[:i], new, *queue[i:]]
        cost = queue_cost(order)
        if cost is None or isinstance(cost, str):
            why = why or cost or "not feasible"
            continue
        if best is None or cost - base <= best[0]:
            best = (cost - base, i)
    if best is None:
        return why or "not feasible"
    return best


class Job:
    """One role a broker was awarded, as :meth:`Broker.cost` and
    :meth:`Broker.perform_role` see it; the rendezvous API for the action that performs
    it (pass the job to your action).

    Events are named ``"<role>:<event>"``; :meth:`signal` sends one of this role's,
    :meth:`wait_for` waits for another role's."""

    def __init__(self, task: Task, plan: str, role: str, *, conversation_id: str,
                 initiator: str, members: Mapping[str, str] | None = None,
                 done: Mapping[str, Any] | None = None, reached: Iterable[str] = (),
                 agent: Agent | None = None) -> None:
        self.task = task
        self.plan = task.plan(plan)
        self.role = self.plan.role(role)
        self.conversation_id = conversation_id
        self.initiator = initiator
        #: role → broker of the coalition (empty while bidding).
        self.members = dict(members or {})
        #: role → result of the roles that finished (in earlier rounds too).
        self.done = dict(done or {})
        self._agent = agent
        self._lock = threading.Lock()
        self._reached: set[str] = set(reached)
        self._conds: set[threading.Condition] = set()

    @property
    def reached(self) -> set[str]:
        """The events of this task's roles that happened (this job's own included)."""
        with self._lock:
            return set(self._reached)

    def signal(self, event: str, data: Any = None) -> None:
        """Tell the coalition that this role reached ``event`` (``"at_meeting"``); the
        auctioneer relays it to the other members."""
        name = f"{self.role.name}:{_name(event, 'event')}"
        self._deliver(name)
        if self._agent is None:
            raise AgentError(f"job {self.role.name!r} of task {self.task.id!r} is not "
                             f"awarded: it cannot signal {name!r}")
        self._agent.send(Message(performative=Performative.INFORM, sender=self._agent.name,
                                 receivers=[self.initiator],
                                 conversation_id=self.conversation_id, protocol=AUCTION,
                                 content={"event": name, "data": jsonable(data)}))

    def wait_for(self, event: str, *, timeout_s: float) -> None:
        """Wait until another role's ``event`` (``"fetch:at_meeting"``) happened.

        Raises :class:`~beehave.errors.RendezvousTimeout` after ``timeout_s`` and
        :class:`~beehave.errors.Interrupted` as soon as the calling action is interrupted
        (a cancel from the auctioneer: the coalition was dissolved)."""
        role, _, ev = event.partition(":")
        names = [r.name for r in self.plan.roles]
        if role not in names or not ev:
            raise InvalidTask(f"task {self.task.id!r}, role {self.role.name!r}: cannot wait "
                              f"for {event!r}: events are '<role>:<event>' with a role of "
                              f"plan {self.plan.name!r}: {names}")
        cond, interrupted, who = current_waiter()
        cond = cond or threading.Condition()
        with self._lock:
            self._conds.add(cond)
        try:
            with cond:
                cond.wait_for(lambda: event in self._reached or interrupted(), timeout_s)
        finally:
            with self._lock:
                self._conds.discard(cond)
        if event in self.reached:
            return
        if interrupted():
            raise Interrupted(f"{who}: interrupted while task {self.task.id!r}, role "
                              f"{self.role.name!r} waited for {event!r}")
        raise RendezvousTimeout(f"task {self.task.id!r}, role {self.role.name!r}: no "
                                f"{event!r} within {timeout_s} s (reached: "
                                f"{sorted(self.reached) or 'nothing'})")

    def meet(self, mine: str, theirs: str, *, timeout_s: float) -> None:
        """A rendezvous: signal ``mine``, then wait for ``theirs`` (both at the meeting
        point: the hand-over can start)."""
        self.signal(mine)
        self.wait_for(theirs, timeout_s=timeout_s)

    def _deliver(self, event: str) -> None:
        with self._lock:
            self._reached.add(event)
            conds = list(self._conds)
        for cond in conds:
            with cond:
                cond.notify_all()

    def __repr__(self) -> str:
        return f"<Job {self.task.id}/{self.plan.name}/{self.role.name}>"


class Broker(Responder):
    """Bids for the roles of auctioned tasks and performs the roles it wins.

    Subclass it and write how a role is priced — either :meth:`queue_cost` (the cost of
    doing a whole queue of roles in a given order, in the market's one global metric:
    the broker then bids the *marginal* cost of the cheapest place for the new role in its
    queue, and puts an awarded role there) or :meth:`cost` (the bid for one role appended
    after the queue) — and :meth:`perform_role` (the :class:`~beehave.Action` that does
    the role). Set :attr:`capabilities`: they are registered in the directory (service
    ``broker``) while the broker runs, and the broker bids only for roles whose capability
    is among them.

    Awarded roles queue behind each other (:attr:`queue_tasks`); every bid is computed on
    the queue as it is at that moment, and an award is priced (and placed) again when it
    arrives (the queue may have changed since the bid): a role it can no longer fill is
    answered with ``failure``, and the auctioneer re-auctions it."""

    protocol = AUCTION
    service = BROKER_SERVICE
    queue_tasks = True
    capabilities: tuple[str, ...] = ()

    def cost(self, job: Job, queue: list[Job]) -> float | str | None:
        """The bid for ``job`` (a role not awarded yet), given the roles already accepted
        and not finished (``queue``, in the order they will run: this one would come
        after them). Return the cost (lower is better), or a reason (str) / None to refuse.
        Called in this broker's thread for every role it has the capability for.

        Not called when the broker writes :meth:`queue_cost` instead."""
        raise NotImplementedError(f"{type(self).__name__} must override cost() or "
                                  f"queue_cost()")

    def queue_cost(self, queue: list[Job]) -> float | str | None:
        """Optional hook, instead of :meth:`cost`: the cost of doing ``queue`` in this
        order, in the market's global metric — e.g. the sum of the roles' completion
        times (seconds from now until each is done, driving from stop to stop), so that a
        role that makes the others wait pays for their waiting. Return a reason (str) or
        None when this order is not feasible (a deadline missed, the battery too low).

        When you write it, the broker bids for a role the least it adds to this cost at
        any place in its queue after the roles already running
        (:func:`cheapest_insertion`), and an awarded role takes the place that is
        cheapest when the award arrives. Called several times per bid (once per place):
        keep it short."""
        raise NotImplementedError(f"{type(self).__name__} must override cost() or "
                                  f"queue_cost()")

    def perform_role(self, job: Job) -> Action | Any:
        """Do the awarded role: return the :class:`~beehave.Action` that does it (give it
        the job: its rendezvous API), or the result itself when it is done at once. Raise
        to refuse the award (the auctioneer re-auctions the role)."""
        raise NotImplementedError(f"{type(self).__name__} must override perform_role()")

    def service_properties(self) -> dict[str, Any]:
        return {"capabilities": sorted(self.capabilities)}

    def run(self) -> None:
        #: The awarded roles not finished, by conversation (their rendezvous events go
        #: there).
        self._jobs: dict[str, Job] = {}
        #: Where the award being started goes: (conversation id, index among waiting).
        self._place: tuple[str, int] | None = None
        super().run()

    @property
    def inserts(self) -> bool:
        """Whether this broker bids marginal insertion costs (it writes
        :meth:`queue_cost`)."""
        return type(self).queue_cost is not Broker.queue_cost

    def _running(self) -> list[Job]:
        jobs = self._jobs
        return [jobs[c] for c, t in self.tasks.items()
                if c in jobs and t.action is not None and not t.action.status.finished]

    @property
    def offered(self) -> list[str]:
        """The capabilities of this broker's directory registration."""
        props = self.agent.services.get(BROKER_SERVICE, {})
        caps = props.get("capabilities", [])
        return list(caps) if isinstance(caps, list) else []

    def queue(self) -> list[Job]:
        """The roles accepted and not finished, in the order they run."""
        jobs = self._jobs
        return self._running() + [jobs[t.request.conversation_id] for t in self.waiting
                                  if t.request.conversation_id in jobs]

    def _price(self, job: Job) -> tuple[float | str, int | None]:
        """The bid for ``job`` and, for an inserting broker, its place among the waiting
        roles."""
        if job.role.capability not in self.offered:
            return (f"lacks capability {job.role.capability!r} (it offers: "
                    f"{', '.join(self.offered) or 'nothing'})"), None
        place: int | None = None
        if self.inserts:
            running = len(self._running())
            found = cheapest_insertion(job, self.queue(), self._queue_cost, fixed=running)
            if isinstance(found, str):
                return found, None
            offer: float | str | None = found[0]
            place = found[1] - running
        else:
            offer = self.cost(job, self.queue())
        if offer is None or isinstance(offer, str):
            return offer or "no bid", None
        return self._finite("cost", offer), place

    def _finite(self, hook: str, value: object) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not math.isfinite(value):
            raise TypeError(f"{self.path}: {hook}() must return a finite number, a reason "
                            f"(str) or None, got {value!r}")
        return float(value)

    def _queue_cost(self, queue: list[Job]) -> float | str | None:
        cost = self.queue_cost(queue)
        return cost if cost is None or isinstance(cost, str) else \
            self._finite("queue_cost", cost)

    def _handle(self, message: Message) -> None:
        kind = message.performative
        if kind is Performative.CFP:
            self._answer_cfp(message)
        elif kind is Performative.INFORM and isinstance(message.content, dict) \
                and "event" in message.content:
            job = self._jobs.get(message.conversation_id)
            if job is not None:
                job._deliver(str(message.content["event"]))
        elif kind is Performative.REJECT_PROPOSAL:
            # An auction never takes back a rejection: a task auctioned again gets a new
            # round (a new conversation and cfp). Kept, every bid of a busy market would
            # stay for proposal_valid_s — thousands of messages to scan and to collect.
            self.proposals.pop(message.conversation_id, None)
        else:
            if kind is Performative.CANCEL:
                self._jobs.pop(message.conversation_id, None)
            super()._handle(message)

    def _answer_cfp(self, cfp: Message) -> None:
        self._expire_proposals()
        bids: list[dict[str, Any]] = []
        refused: list[dict[str, Any]] = []
        try:
            entries = cfp.content["tasks"]
            for entry in entries:
                task = Task.from_dict(entry["task"])
                for plan, role in entry["open"]:
                    job = Job(task, plan, role, conversation_id=cfp.conversation_id,
                              initiator=cfp.sender, done=entry.get("done"),
                              reached=entry.get("reached", ()))
                    offer = self._price(job)[0]
                    row = {"task": task.id, "plan": plan, "role": role}
                    if isinstance(offer, str):
                        refused.append({**row, "reason": offer})
                    else:
                        bids.append({**row, "cost": offer})
        except Exception as exc:  # a malformed cfp, or a cost() that raised
            log.warning("%s: cannot bid on %s: %r", self.path, cfp.conversation_id, exc)
            self._reply(cfp, Performative.FAILURE, {"reason": repr(exc)})
            return
        if not bids:
            self._reply(cfp, Performative.REFUSE, {"reason": "no role it can fill",
                                                   "refused": refused})
        elif self._reply(cfp, Performative.PROPOSE, {"bids": bids, "refused": refused}):
            self._propose(cfp.conversation_id, cfp)

    def perform(self, task: Message) -> Any:
        c = task.content
        job = Job(Task.from_dict(c["task"]), c["plan"], c["role"],
                  conversation_id=task.conversation_id, initiator=task.sender,
                  members=c.get("members"), done=c.get("done"),
                  reached=c.get("reached", ()), agent=self.agent)
        # Re-planned: the queue may have changed since the bid.
        offer, place = self._price(job)
        if isinstance(offer, str):
            raise AgentError(f"{self.agent.name!r} cannot take role {job.role.name!r} of "
                             f"task {job.task.id!r} any more: {offer}")
        outcome = self.perform_role(job)
        self._jobs[task.conversation_id] = job
        self._place = None if place is None else (task.conversation_id, place)
        self._reply(task, Performative.AGREE, {"cost": offer, "queued": len(self.queue())})
        return outcome

    def _start(self, message: Message) -> None:
        self._place = None
        super()._start(message)
        place, self._place = self._place, None
        if place is None:
            return
        # Responder queues an award last; an inserting broker moves it to the place its
        # bid was computed for (re-planned in perform()).
        cid, index = place
        mine = next((t for t in self.waiting if t.request.conversation_id == cid), None)
        if mine is not None:
            self.waiting.remove(mine)
            self.waiting.insert(max(0, min(index, len(self.waiting))), mine)

    def _launch(self, task: ResponderTask, *, queue: bool) -> bool:
        started = super()._launch(task, queue=queue)
        if started:
            job = self._jobs.get(task.request.conversation_id)
            if job is not None:
                try:
                    job.signal("started")
                except AgentError as exc:
                    log.warning("%s: could not report the start of %r: %s", self.path,
                                job, exc)
        return started

    def _reap_ended(self) -> None:
        jobs = self._jobs
        for cid in [c for c, t in self.tasks.items()
                    if t.action is not None and t.action.status.finished]:
            jobs.pop(cid, None)
        super()._reap_ended()


# ---------------------------------------------------------------------- auctioneer side
class TaskState(Enum):
    """Where a task stands in the market."""

    WAITING = "waiting"
    """Not awarded (yet, or again after its coalition was dissolved)."""
    AWARDED = "awarded"
    """Its roles are being performed."""
    COMPLETED = "completed"
    """Every role of one plan finished."""
    FAILED = "failed"
    """Given up: no broker could fill it, the deadline passed, or ``max_rounds`` ran out."""


@dataclass
class Outcome:
    """What became of one task: who did which role, and every round it took."""

    task: Task
    state: TaskState = TaskState.WAITING
    plan: str | None = None
    #: role → broker, for the roles that finished (and, while awarded, the current ones).
    members: dict[str, str] = field(default_factory=dict)
    results: dict[str, Any] = field(default_factory=dict)
    #: events reached by roles that count (finished roles, and the current members').
    reached: list[str] = field(default_factory=list)
    #: one entry per round: ``{"round", "plan", "members", "cost", "ended"}``.
    rounds: list[dict[str, Any]] = field(default_factory=list)
    reason: str = ""
    #: brokers that failed this task: not asked again for it.
    excluded: set[str] = field(default_factory=set)
    #: Seconds from the cfp to the accept-proposals, per round.
    award_latency_s: list[float] = field(default_factory=list)
    #: Seconds from detecting a member's failure to the next award.
    reaward_s: list[float] = field(default_factory=list)
    _failed_at: float | None = field(default=None, repr=False)
    #: A batch round deferred it (it bids again at once; the round does not count).
    _deferred: bool = field(default=False, repr=False)

    @property
    def done(self) -> bool:
        return self.state in (TaskState.COMPLETED, TaskState.FAILED)

    def open_roles(self) -> dict[str, list[str]]:
        """plan → roles to fill: once a role finished, only its plan."""
        if self.results:
            assert self.plan is not None
            plan = self.task.plan(self.plan)
            return {plan.name: [r.name for r in plan.roles if r.name not in self.results]}
        return {p.name: [r.name for r in p.roles] for p in self.task.plans}


Observer = Callable[[str, dict[str, Any]], None]


@dataclass
class _Member:
    task: str
    role: str
    awarded_at: float
    agreed_at: float | None = None
    started_at: float | None = None


class _Round:
    """One auction round: announce, collect, choose, award, monitor (one conversation)."""

    def __init__(self, agent: Agent, outcomes: list[Outcome], *, batch: bool,
                 reply_by_s: float, start_timeout_s: float, done_timeout_s: float,
                 tell: Callable[..., None], on_awarded: Callable[[], None],
                 on_settled: Callable[[Outcome], None]) -> None:
        self.agent = agent
        self.outcomes = {o.task.id: o for o in outcomes}
        self.batch = batch
        self.reply_by_s = reply_by_s
        self.start_timeout_s = start_timeout_s
        self.done_timeout_s = done_timeout_s
        self.tell = tell
        self.on_awarded = on_awarded
        self.on_settled = on_settled
        self.members: dict[str, _Member] = {}

    def run(self) -> None:
        with self.agent.conversation(protocol=AUCTION) as conv:
            undecided: set[str] = set()
            unanswered: set[str] = set()
            try:
                self._run(conv, undecided, unanswered)
            except Interrupted:
                why = {"reason": "the auctioneer was interrupted"}
                cancel_quietly(conv, sorted(self.members), Performative.CANCEL, why)
                cancel_quietly(conv, sorted(undecided), Performative.REJECT_PROPOSAL, why)
                cancel_quietly(conv, sorted(unanswered), Performative.CANCEL, why)
                raise

    def _run(self, conv: Conversation, undecided: set[str], unanswered: set[str]) -> None:
        started = time.monotonic()
        cid = conv.conversation_id
        brokers = {info.name: info for info in self.agent.directory.search(BROKER_SERVICE)
                   if info.name != self.agent.name}
        offered = {c for info in brokers.values()
                   for c in info.properties(BROKER_SERVICE).get("capabilities", [])}
        # A task no plan of which the brokers present can staff is not announced: this
        # round leaves it unassigned, saying which capability is missing (the broker
        # that has it may not have joined yet: the next round asks again).
        unstaffable: dict[str, str] = {}
        for o in self.outcomes.values():
            try:
                check_capabilities(o.task, offered)
            except UnknownCapability as exc:
                unstaffable[o.task.id] = str(exc)
        entries: list[dict[str, Any]] = [
            {"task": o.task.to_dict(),
             "open": [[p, r] for p, rs in o.open_roles().items() for r in rs],
             "done": o.results, "reached": o.reached}
            for o in self.outcomes.values() if not o.done and o.task.id not in unstaffable]
        names = sorted(brokers) if entries else []
        self.tell("cfp", conversation_id=cid, tasks=[e["task"]["id"] for e in entries],
                  candidates=names)
        bids: Bids = {}
        #: (task, plan, role) → {broker: its reason for not bidding}: what a task that
        #: is left unassigned says.
        refusals: dict[tuple[str, str, str], dict[str, str]] = {}
        if names:
            unanswered.update(names)
            try:
                conv.send(Performative.CFP, names, {"tasks": entries},
                          reply_by_s=self.reply_by_s)
            except AgentError as exc:  # some were not reachable: go on without them
                unanswered.difference_update(getattr(exc, "unreachable", ()))
            deadline = time.monotonic() + self.reply_by_s
            while unanswered:
                try:
                    reply = conv.receive(timeout_s=max(0.0, deadline - time.monotonic()))
                except NoReply:
                    break
                if reply.sender not in unanswered:
                    continue
                unanswered.discard(reply.sender)
                if reply.performative is Performative.PROPOSE:
                    undecided.add(reply.sender)
                    self._read_bids(reply, bids)
                self._read_refusals(reply, refusals)
            if unanswered:
                late = sorted(unanswered)
                unanswered.clear()
                cancel_quietly(conv, late, Performative.CANCEL,
                                {"reason": "no proposal before reply_by"})
        open_roles = {tid: o.open_roles() for tid, o in self.outcomes.items() if not o.done}
        chosen = self._choose_avoiding_excluded(open_roles, bids)
        lost: list[tuple[str, str]] = []
        for tid, choice in chosen.items():
            o = self.outcomes[tid]
            o.plan = choice.plan
            o.state = TaskState.AWARDED
            o.members = {r: b for r, b in o.members.items() if r in o.results}
            o.members.update(choice.members)
            o.rounds.append({"round": cid, "plan": choice.plan, "members": choice.members,
                             "cost": choice.cost, "ended": "running"})
            for role, broker in choice.members.items():
                undecided.discard(broker)
                self.members[broker] = _Member(tid, role, time.monotonic())
                conv.watch(broker)
                try:
                    conv.send(Performative.ACCEPT_PROPOSAL, [broker],
                              {"task": o.task.to_dict(), "plan": choice.plan, "role": role,
                               "members": o.members, "done": o.results,
                               "reached": o.reached})
                except AgentError as exc:  # it died since its bid
                    lost.append((broker, f"award not deliverable: {exc}"))
            o.award_latency_s.append(time.monotonic() - started)
            if o._failed_at is not None:
                o.reaward_s.append(time.monotonic() - o._failed_at)
                o._failed_at = None
            self.tell("awarded", conversation_id=cid, task=tid, plan=choice.plan,
                      members=choice.members, cost=choice.cost)
        if undecided:
            losers = sorted(undecided)
            undecided.clear()
            cancel_quietly(conv, losers, Performative.REJECT_PROPOSAL,
                            {"reason": "not chosen in this round"})
        unassigned = [o for tid, o in self.outcomes.items() if not o.done and tid not in chosen]
        # Batch: a task whose cheapest brokers went to other tasks of this round is
        # deferred — asked again at once, on re-planned bids; not a failed round.
        deferred = [o for o in unassigned if self.batch and choose(
            {o.task.id: open_roles[o.task.id]}, bids)]
        for o in deferred:
            unassigned.remove(o)
            o.state = TaskState.WAITING
            o.reason = ("deferred: its cheapest brokers were given to other tasks of this "
                        "round; it is auctioned again on their new queues")
            o._deferred = True
            self.tell("deferred", conversation_id=cid, task=o.task.id, reason=o.reason)
        for o in unassigned:
            o.state = TaskState.WAITING
            o.reason = unstaffable.get(o.task.id) or self._why_not(o, bids, names,
                                                                  refusals)
            o.rounds.append({"round": cid, "plan": None, "members": {}, "cost": None,
                             "ended": f"unassigned: {o.reason}"})
            self.tell("unassigned", conversation_id=cid, task=o.task.id, reason=o.reason)
        for broker, why in lost:
            if broker in self.members:
                self._dissolve(conv, broker, why)
        for o in deferred:  # before on_awarded: the next round must include them
            self.on_settled(o)
        self.on_awarded()
        for o in unassigned:
            self.on_settled(o)  # back to the auctioneer: again later, or given up
        self._monitor(conv)

    def _read_bids(self, reply: Message, bids: Bids) -> None:
        content = reply.content if isinstance(reply.content, dict) else {}
        for bid in content.get("bids", []) if isinstance(content.get("bids"), list) else []:
            try:
                key = (str(bid["task"]), str(bid["plan"]), str(bid["role"]))
                cost = bid["cost"]
            except (KeyError, TypeError):
                key, cost = None, None
            # A cost is a finite number >= 0: a bool (JSON true read as 1), a string, a
            # negative cost (which would win every auction) or NaN/inf is no bid.
            if key is None or isinstance(cost, bool) or not isinstance(cost, (int, float)) \
                    or not math.isfinite(cost) or cost < 0:
                log.warning("agent %r: bid from %r ignored: the cost must be a finite "
                            "number >= 0, got %r", self.agent.name, reply.sender, bid)
                continue
            o = self.outcomes.get(key[0])
            if o is None or key[2] not in o.open_roles().get(key[1], []):
                continue
            bids.setdefault(key, {})[reply.sender] = float(cost)

    @staticmethod
    def _read_refusals(reply: Message,
                       refusals: dict[tuple[str, str, str], dict[str, str]]) -> None:
        """Keep the reasons a broker gave for the roles it did not bid for (a
        ``propose``'s or a ``refuse``'s ``refused`` list)."""
        content = reply.content if isinstance(reply.content, dict) else {}
        rows = content.get("refused")
        for row in rows if isinstance(rows, list) else []:
            if isinstance(row, dict) and all(k in row for k in ("task", "plan", "role")):
                key = (str(row["task"]), str(row["plan"]), str(row["role"]))
                refusals.setdefault(key, {})[reply.sender] = f"{row.get('reason')!s:.200}"
        if reply.performative is not Performative.PROPOSE and not rows:
            refusals.setdefault(("*", "*", "*"), {})[reply.sender] = \
                f"{content.get('reason', reply.content)!s:.200}"

    def _why_not(self, o: Outcome, bids: Bids, names: list[str],
                 refusals: Mapping[tuple[str, str, str], Mapping[str, str]]
                 | None = None) -> str:
        parts = []
        refusals = refusals or {}
        for plan, roles in o.open_roles().items():
            filled = {r: sorted(bids.get((o.task.id, plan, r), {})) for r in roles}
            said = {r: dict(sorted(refusals.get((o.task.id, plan, r), {}).items()))
                    for r in roles}
            said = {r: why for r, why in said.items() if why}
            parts.append(f"plan {plan!r}: bidders per role {filled}"
                         + (f", refusals per role {said}" if said else ""))
        general = refusals.get(("*", "*", "*"))
        if general:
            parts.append(f"refused outright: {dict(sorted(general.items()))}")
        return (f"no assignment of distinct brokers in this round (brokers asked: "
                f"{names or 'none'}; excluded: {sorted(o.excluded) or 'none'}); "
                + "; ".join(parts))

    def _monitor(self, conv: Conversation) -> None:
        while self.members:
            now = time.monotonic()
            # (when, member or None, task, why): the first limit to pass ends the wait.
            limits: list[tuple[float, str | None, str, str]] = []
            for name, m in self.members.items():
                if m.started_at is None and m.agreed_at is None:
                    limits.append((m.awarded_at + self.start_timeout_s, name, m.task,
                                   f"did not start within {self.start_timeout_s} s"))
                else:  # working, or queued behind its earlier roles (it agreed)
                    since = m.started_at if m.started_at is not None else m.agreed_at
                    assert since is not None
                    limits.append((since + self.done_timeout_s, name, m.task,
                                   f"silent for {self.done_timeout_s} s"))
            for tid in {m.task for m in self.members.values()}:
                deadline = self.outcomes[tid].task.deadline
                if deadline is not None:
                    limits.append((now + deadline - time.time(), None, tid,
                                   "its deadline passed"))
            when, who, tid, why = min(limits, key=lambda x: x[0])
            try:
                reply = conv.receive(timeout_s=max(0.0, when - now))
            except NoReply:
                if who is not None:
                    self._dissolve(conv, who, why)
                else:
                    self._end_task(conv, self.outcomes[tid], TaskState.FAILED, why)
                continue
            member = self.members.get(reply.sender)
            if member is None:
                continue  # a late bid, or a report of a member already let go
            m = member
            content = reply.content if isinstance(reply.content, dict) else {}
            o = self.outcomes[m.task]
            if reply.performative is Performative.INFORM and "event" in content:
                self._event(conv, reply.sender, m, str(content["event"]), content)
            elif reply.performative is Performative.INFORM:
                self._role_done(conv, reply.sender, m, content.get("result"))
            elif reply.performative in (Performative.FAILURE, *REFUSALS):
                why = content.get("reason", reply.content)
                self._dissolve(conv, reply.sender, f"{reply.performative.value}: {why}",
                               exclude=not content.get("departed"))
            elif reply.performative is Performative.AGREE:
                m.agreed_at = time.monotonic()
                self.tell("agreed", conversation_id=conv.conversation_id, task=o.task.id,
                          role=m.role, broker=reply.sender)

    def _choose_avoiding_excluded(self, open_roles: dict[str, dict[str, list[str]]],
                                  bids: Bids) -> dict[str, Choice]:
        """:func:`choose`, without the brokers that failed a task before -- unless only
        they can fill it: a member that failed (a rendezvous that timed out on a busy
        host, say) may well succeed the next time, and the task's ``max_rounds`` bounds
        the retries, where leaving it out would fail the task for certain."""
        avoided: Bids = {}
        for key, table in bids.items():
            for name in self.outcomes[key[0]].excluded:
                if name in table:
                    avoided.setdefault(key, {})[name] = table.pop(name)
        chosen = choose(open_roles, bids, batch=self.batch)
        stuck = {tid: roles for tid, roles in open_roles.items()
                 if tid not in chosen and any(key[0] == tid for key in avoided)}
        if stuck:
            taken = {b for c in chosen.values() for b in c.members.values()}
            again = {key: {b: c for b, c in {**bids.get(key, {}), **avoided.get(key, {})}.items()
                           if b not in taken}
                     for key in {*bids, *avoided} if key[0] in stuck}
            chosen.update(choose(stuck, again, batch=self.batch))
        return chosen

    def _event(self, conv: Conversation, sender: str, m: _Member, event: str,
               content: dict[str, Any]) -> None:
        o = self.outcomes[m.task]
        if event == f"{m.role}:started":
            m.started_at = time.monotonic()
        if event not in o.reached:
            o.reached.append(event)
        self.tell("event", conversation_id=conv.conversation_id, task=o.task.id,
                  role=m.role, broker=sender, event=event, data=content.get("data"))
        others = sorted(n for n, x in self.members.items() if x.task == m.task and n != sender)
        if others:
            cancel_quietly(conv, others, Performative.INFORM,
                            {"event": event, "data": content.get("data")})

    def _role_done(self, conv: Conversation, sender: str, m: _Member, result: Any) -> None:
        o = self.outcomes[m.task]
        del self.members[sender]
        conv.unwatch(sender)
        o.results[m.role] = result
        self.tell("role_done", conversation_id=conv.conversation_id, task=o.task.id,
                  role=m.role, broker=sender, result=result)
        assert o.plan is not None
        if all(r.name in o.results for r in o.task.plan(o.plan).roles):
            self._end_task(conv, o, TaskState.COMPLETED, "")

    def _end_task(self, conv: Conversation, o: Outcome, state: TaskState, why: str) -> None:
        mine = sorted(n for n, x in self.members.items() if x.task == o.task.id)
        for name in mine:
            del self.members[name]
            conv.unwatch(name)
        cancel_quietly(conv, mine, Performative.CANCEL, {"reason": why or "task ended"})
        if o.rounds:
            o.rounds[-1]["ended"] = state.value if not why else f"{state.value}: {why}"
        o.state = state
        o.reason = why
        self.tell("completed" if state is TaskState.COMPLETED else "failed",
                  conversation_id=conv.conversation_id, task=o.task.id, reason=why,
                  members=o.members, results=o.results)
        self.on_settled(o)

    def _dissolve(self, conv: Conversation, culprit: str, why: str, *,
                  exclude: bool = True) -> None:
        """A member failed: cancel the others of its task (and the culprit: a silent one
        must never also do it), keep what finished, and hand the task back."""
        m = self.members[culprit]
        o = self.outcomes[m.task]
        mine = sorted(n for n, x in self.members.items() if x.task == m.task)
        for name in mine:
            del self.members[name]
            conv.unwatch(name)
        cancel_quietly(conv, mine, Performative.CANCEL,
                        {"reason": f"coalition dissolved: {culprit!r} ({m.role}) {why}"})
        if exclude:
            o.excluded.add(culprit)
        kept = set(o.results)
        o.reached = [e for e in o.reached if e.partition(":")[0] in kept]
        o.members = {r: b for r, b in o.members.items() if r in kept}
        o.state = TaskState.WAITING
        o.reason = f"{culprit!r} ({m.role}): {why}"
        o._failed_at = time.monotonic()
        if o.rounds:
            o.rounds[-1]["ended"] = f"dissolved: {o.reason}"
        self.tell("dissolved", conversation_id=conv.conversation_id, task=o.task.id,
                  broker=culprit, role=m.role, reason=why, kept=sorted(kept))
        self.on_settled(o)


def _tell_with(observer: Observer | None) -> Callable[..., None]:
    def tell(step: str, **detail: Any) -> None:
        if observer is None:
            return
        try:
            observer(step, detail)
        except Exception:
            log.exception("auction observer raised on %r", step)
    return tell


def auction(agent: Agent, task: Task, *, reply_by_s: float = 0.5,
            start_timeout_s: float = 5.0, done_timeout_s: float = 300.0,
            max_rounds: int = 5, retry_s: float = 1.0,
            capabilities: Collection[str] | None = None,
            observer: Observer | None = None) -> Outcome:
    """Auction ``task``, award it to a broker or a coalition, and monitor it to its end.

    Returns the :class:`Outcome` when the task is completed; raises
    :class:`~beehave.errors.TaskFailed` (``.outcome`` holds it) when it failed: no
    assignment after ``max_rounds`` rounds (an unassigned round is retried after
    ``retry_s``), the deadline passed, or no plan's capabilities are offered.
    ``capabilities``: the valid capability names, checked before anything is sent.
    ``observer(step, detail)`` hears ``cfp``, ``awarded``, ``unassigned`` (``deferred``
    too, from a batch :class:`Auctioneer`), ``agreed``,
    ``event``, ``role_done``, ``dissolved``, ``completed`` and ``failed``.

    Interrupted (called from a Behavior that is switched away): every member gets
    ``cancel``, every bid not decided a ``reject-proposal``; then
    :class:`~beehave.errors.Interrupted`."""
    if capabilities is not None:
        check_capabilities(task, capabilities, vocabulary=True)
    outcome = Outcome(task)
    tell = _tell_with(observer)
    cond, interrupted, who = current_waiter()
    cond = cond or threading.Condition()
    for n in itertools.count(1):
        _Round(agent, [outcome], batch=False, reply_by_s=reply_by_s,
               start_timeout_s=start_timeout_s, done_timeout_s=done_timeout_s, tell=tell,
               on_awarded=lambda: None, on_settled=lambda o: None).run()
        if outcome.state is TaskState.COMPLETED:
            return outcome
        if outcome.state is TaskState.WAITING and n < max_rounds:
            if outcome.rounds and outcome.rounds[-1]["ended"].startswith("unassigned"):
                with cond:  # unassigned: give the market time to change
                    cond.wait_for(interrupted, retry_s)
                if interrupted():
                    raise Interrupted(f"{who}: interrupted between auction rounds of "
                                      f"task {task.id!r}")
            continue
        if outcome.state is TaskState.WAITING:
            outcome.state = TaskState.FAILED
            outcome.reason = f"{max_rounds} rounds without completion; last: {outcome.reason}"
        raise TaskFailed(f"agent {agent.name!r}: task {task.id!r} failed: {outcome.reason}",
                         outcome=outcome)
    raise AssertionError("unreachable")


class Auctioneer(AgentBehavior):
    """Allocates tasks to brokers and monitors them until each is completed or failed;
    its result is ``{task id: Outcome}``.

    ``batch=None`` (default): a task that waits alone is auctioned on its own, several
    that wait are assigned jointly, as with ``batch=True``. ``batch=False``: sequential,
    one round per task in arrival order, the next announced once the previous has
    awarded (so the next bids see the queues the award made); rounds run in parallel
    while their coalitions work. ``batch=True``: every waiting task in one round, jointly
    assigned (see :func:`choose`); a task deferred because its cheapest brokers went to
    other tasks of the round is in the next round at once, and a deferral does not count
    against ``max_rounds``. A dissolved coalition's task goes to the front of the queue.
    Give tasks to
    the constructor, or hand them over while it runs with :meth:`submit`; with
    ``keep_running`` it waits for more after the last one."""

    def __init__(self, tasks: Iterable[Task] = (), *, batch: bool | None = None,
                 reply_by_s: float = 0.5, start_timeout_s: float = 5.0,
                 done_timeout_s: float = 300.0, max_rounds: int = 5, retry_s: float = 1.0,
                 capabilities: Collection[str] | None = None, keep_running: bool = False,
                 observer: Observer | None = None) -> None:
        self.capabilities = None if capabilities is None else set(capabilities)
        self.batch = batch
        self.options = {"reply_by_s": reply_by_s, "start_timeout_s": start_timeout_s,
                        "done_timeout_s": done_timeout_s}
        self.max_rounds = max_rounds
        self.retry_s = retry_s
        self.keep_running = keep_running
        self.observer = observer
        self._lock = threading.Lock()
        self.outcomes: dict[str, Outcome] = {}
        self._pending: list[Outcome] = []
        self._awarding = 0
        self._retry_at: dict[str, float] = {}
        self._news = False
        for task in tasks:
            self.submit(task)

    def submit(self, task: Task) -> Outcome:
        """Queue ``task`` (thread-safe); its :class:`Outcome` fills in as it goes."""
        if self.capabilities is not None:
            check_capabilities(task, self.capabilities, vocabulary=True)
        with self._lock:
            if task.id in self.outcomes:
                raise InvalidTask(f"task id {task.id!r} was submitted already")
            outcome = self.outcomes[task.id] = Outcome(task)
            self._pending.append(outcome)
        self._wake()
        return outcome

    def _wake(self) -> None:
        cond = getattr(self, "_cond", None)
        if cond is not None:
            with cond:
                self._news = True
                cond.notify_all()

    def _awarded(self) -> None:
        with self._lock:
            self._awarding -= 1
        self._wake()

    def _settled(self, outcome: Outcome) -> None:
        """A round handed ``outcome`` back (its round's thread): completed, failed, or
        waiting again (unassigned: retried after ``retry_s``; dissolved: at once)."""
        if outcome.state is TaskState.WAITING and outcome._deferred:
            outcome._deferred = False
            with self._lock:
                self._retry_at[outcome.task.id] = 0.0
                self._pending.insert(0, outcome)
        elif outcome.state is TaskState.WAITING:
            if len(outcome.rounds) >= self.max_rounds:
                outcome.state = TaskState.FAILED
                outcome.reason = (f"{self.max_rounds} rounds without completion; last: "
                                  f"{outcome.reason}")
                _tell_with(self.observer)("failed", task=outcome.task.id,
                                          reason=outcome.reason)
            else:
                unassigned = bool(outcome.rounds) and \
                    outcome.rounds[-1]["ended"].startswith("unassigned")
                with self._lock:
                    self._retry_at[outcome.task.id] = (
                        time.monotonic() + self.retry_s if unassigned else 0.0)
                    self._pending.insert(0, outcome)
        self._wake()

    def on_child_ended(self, child: Runnable) -> None:
        self._wake()

    def run(self) -> dict[str, Outcome]:
        tell = _tell_with(self.observer)
        while True:
            with self._lock:
                now = time.monotonic()
                ready = [o for o in self._pending
                         if self._retry_at.get(o.task.id, 0.0) <= now]
                busy = self._awarding > 0
                unsettled = [o for o in self.outcomes.values() if not o.done]
                later = [self._retry_at.get(o.task.id, 0.0) - now for o in self._pending]
            if not unsettled and not self.keep_running:
                return dict(self.outcomes)
            if ready and not busy:
                # Default (None): jointly when several tasks wait -- one at a time in
                # arrival order pins each robot's first role to whichever task came
                # first (issue 24: 1.22 x the optimum against 1.01-1.05 jointly).
                batch = self.batch if self.batch is not None else len(ready) > 1
                take = ready if batch else ready[:1]
                with self._lock:
                    for o in take:
                        self._pending.remove(o)
                    self._awarding += 1
                rnd = _Round(self.agent, take, batch=batch, tell=tell,
                             on_awarded=self._awarded, on_settled=self._settled,
                             **self.options)
                self.start_behavior(_RoundBehavior(rnd))
                continue
            # Woken by submit(), a round that awarded or handed a task back, a child
            # that ended (a failed round raises ChildFailed here), or an interrupt.
            timeout_s = min([t for t in later if t > 0], default=1.0)
            with self._cond:
                self._cond.wait_for(lambda: self._interrupt_requested or self._news,
                                    timeout_s)
                self._news = False
                self._raise_pending()
            if self._interrupt_requested:
                raise Interrupted(f"{self.path}: interrupted with "
                                  f"{len(unsettled)} task(s) unsettled")


class _RoundBehavior(AgentBehavior):
    """Runs one :class:`_Round` in its own thread (its coalitions work in parallel with
    the next rounds)."""

    def __init__(self, rnd: _Round) -> None:
        self.rnd = rnd

    def run(self) -> None:
        self.rnd.run()
