"""Behaviour tree engine over ``py_trees``.

Build the tree from ordinary py_trees composites and decorators, with two beehave leaves:

- :class:`StartLeaf` starts an Action or sub-Behavior when first ticked and maps its
  Status: running → RUNNING, SUCCEEDED → SUCCESS, anything else → FAILURE. When the tree
  abandons it (a higher-priority branch took over, or the tree stops) it interrupts what it
  started and waits for it, safe states applied.
- :class:`BlackboardCheck` is SUCCESS when a condition over the behaviour's blackboard
  (the manager's blackboard, or its ROS 2 mirror) holds, FAILURE otherwise.

::

    root = py_trees.composites.Selector("root", memory=False, children=[
        py_trees.composites.Sequence("charge?", memory=True, children=[
            BlackboardCheck("battery low", "battery/percentage < 20"),
            StartLeaf("charge", lambda: Charge(robot)),
        ]),
        StartLeaf("patrol", lambda: Patrol(robot)),
    ])
    hl.register("patrol", EngineBehavior, engine=TreeEngine(root, rate_hz=20))

The engine ticks the tree at ``rate_hz`` in the behaviour's thread. The root's SUCCESS ends
the behaviour (result: the ``result`` of the last leaf that succeeded); FAILURE fails it with
:class:`~beehave.engines.errors.TreeFailed` naming the leaf. An interrupt stops the tree.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from beehave import breakpoints
from beehave.engines.engine import (
    Condition,
    DecisionEngine,
    EngineContext,
    Starter,
    as_starter,
    condition_label,
    parse_condition,
    require,
)

require("py_trees", extra="engines")

import py_trees  # noqa: E402
from py_trees.common import Status as TreeStatus  # noqa: E402

from beehave.engines.errors import EngineConfigError, TreeFailed  # noqa: E402
from beehave.errors import ActionTypeBusy  # noqa: E402
from beehave.runnable import Runnable  # noqa: E402
from beehave.status import Status  # noqa: E402

if TYPE_CHECKING:
    import graphviz

__all__ = ["BlackboardCheck", "StartLeaf", "TreeEngine"]

StartLike = Starter | Callable[[], Runnable] | type[Runnable]
StartResolver = Callable[[Any, str], Starter]


class _EngineLeaf(py_trees.behaviour.Behaviour):
    """A leaf that needs the running engine's context (set by the engine at start)."""

    context: EngineContext | None = None
    #: The behaviour's blackboard, cached at start (a tick should not walk up to it).
    board: Any = None

    def _context(self) -> EngineContext:
        if self.context is None:
            raise EngineConfigError(f"tree leaf {self.name!r} ticked outside a TreeEngine run")
        return self.context


class StartLeaf(_EngineLeaf):
    """Starts ``start`` (a factory, a class or a Starter) and reports its outcome.

    ``on_busy`` decides what happens when the action type is held: ``"running"`` (the
    default: retry on the next tick) or ``"failure"`` (the tree may choose another branch).
    Retrying is what lets a higher-priority branch take over the type from a running
    lower-priority sibling: the leaf reports RUNNING, so the selector stops the sibling
    (interrupted, safe state applied), and the next tick starts the leaf's action.
    """

    def __init__(self, name: str, start: StartLike, *, on_busy: str = "running") -> None:
        super().__init__(name)
        if on_busy not in ("failure", "running"):
            raise EngineConfigError(f"leaf {name!r}: on_busy must be 'failure' or "
                                    f"'running', not {on_busy!r}")
        self.starter = as_starter(start, label=name)
        self.on_busy = on_busy
        self.handle: Runnable | None = None
        #: The last handle that ended (for results and failure reports).
        self.last: Runnable | None = None

    def initialise(self) -> None:
        """py_trees calls this before the first tick after the leaf was not RUNNING."""
        self.handle = None

    def update(self) -> TreeStatus:
        context = self._context()
        if self.handle is None:
            try:
                self.handle = context.start(self.starter)
            except ActionTypeBusy as busy:
                self.feedback_message = str(busy)
                return TreeStatus.RUNNING if self.on_busy == "running" else TreeStatus.FAILURE
            self.feedback_message = f"started {self.handle.name}"
        handle = self.handle
        if not handle.status.finished:
            return TreeStatus.RUNNING
        handle.wait(0)  # the outcome is seen here: no ChildFailed later
        context.forget(handle)
        self.last, self.handle = handle, None
        self.feedback_message = f"{handle.name}: {handle.status.name}"
        return TreeStatus.SUCCESS if handle.status is Status.SUCCEEDED else TreeStatus.FAILURE

    def terminate(self, new_status: TreeStatus) -> None:
        """py_trees calls this when the leaf ends or is abandoned (``INVALID``): stop
        what it still runs."""
        handle = self.handle
        if handle is not None and not handle.status.finished and self.context is not None:
            self.context.stop([handle])
            self.last = handle
        self.handle = None


class BlackboardCheck(_EngineLeaf):
    """SUCCESS when ``condition(blackboard)`` holds, FAILURE otherwise; never RUNNING.

    ``condition`` is a callable or a ``"KEY OP VALUE"`` string (see
    :func:`~beehave.engines.engine.parse_condition`), or a network decision
    (``policy.condition("charge")``).
    """

    def __init__(self, name: str, condition: Condition | str) -> None:
        super().__init__(name)
        self.condition: Condition = (parse_condition(condition, where=f"condition {name!r}")
                                     if isinstance(condition, str) else condition)

    def update(self) -> TreeStatus:
        board = self.board
        if board is None:
            board = self.board = self._context().blackboard
        holds = self.condition(board)
        return TreeStatus.SUCCESS if holds else TreeStatus.FAILURE


class TreeEngine(DecisionEngine):
    """Ticks a py_trees tree at ``rate_hz`` in the behaviour's thread."""

    kind = "tree"

    def __init__(self, root: py_trees.behaviour.Behaviour, *, rate_hz: float = 20.0) -> None:
        if not isinstance(root, py_trees.behaviour.Behaviour):
            raise EngineConfigError(f"TreeEngine needs a py_trees behaviour as root, "
                                    f"got {root!r}")
        if not rate_hz > 0:
            raise EngineConfigError(f"rate_hz must be positive, got {rate_hz!r}")
        self.root = root
        self.rate_hz = float(rate_hz)
        self.poll_s = min(0.05, 1.0 / self.rate_hz)
        self.tree = py_trees.trees.BehaviourTree(root)
        self.ticks = 0
        # (tick, layout, statuses) after the last complete tick of a run, for describe().
        self._seen: tuple[int, list[tuple[py_trees.behaviour.Behaviour, str]],
                          tuple[str, ...]] | None = None

    @property
    def leaves(self) -> list[_EngineLeaf]:
        return [n for n in self.root.iterate() if isinstance(n, _EngineLeaf)]

    def _layout(self) -> list[tuple[py_trees.behaviour.Behaviour, str]]:
        """Every node in pre-order with its path: names from the root joined by ``/``,
        ``[i]`` telling same-named siblings apart."""
        out: list[tuple[py_trees.behaviour.Behaviour, str]] = []

        def visit(node: py_trees.behaviour.Behaviour, path: str) -> None:
            out.append((node, path))
            names = [c.name for c in node.children]
            for i, child in enumerate(node.children):
                part = child.name if names.count(child.name) == 1 else f"{child.name}[{i}]"
                visit(child, f"{path}/{part}")

        visit(self.root, self.root.name)
        return out

    def describe(self) -> dict[str, Any]:
        """Every node of the tree in pre-order with its py_trees status, JSON-serialisable:
        ``{"kind": "behaviour_tree", "tick": n, "nodes": [{"name", "path", "status"}, …]}``.
        ``path`` joins the names from the root with ``/`` (``[i]`` tells same-named
        siblings apart); ``status`` is ``RUNNING``, ``SUCCESS``, ``FAILURE`` or
        ``INVALID`` (not ticked, or abandoned).

        Safe from any thread: while the tree runs it shows the statuses as the last
        complete tick left them (never a tick half-way), recorded by :meth:`run`."""
        seen = self._seen
        if seen is not None:
            tick, layout, statuses = seen
        else:
            layout = self._layout()
            tick, statuses = self.ticks, tuple(node.status.name for node, _ in layout)
        nodes = [{"name": node.name, "path": path, "status": status}
                 for (node, path), status in zip(layout, statuses, strict=True)]
        return {"kind": "behaviour_tree", "tick": tick, "nodes": nodes,
                "structure_id": self.structure_id()}

    def structure(self) -> dict[str, Any]:
        """The tree as a graph, JSON-serialisable: ``{"kind": "behaviour_tree", "nodes":
        [{"name", "path", "parent", "type", "memory", "starts", "action_type"}, …]}`` in
        the pre-order of :meth:`describe` (its statuses line up by index); ``parent`` is
        the index of the parent node (None for the root), ``type`` the py_trees class
        (``Sequence``, ``Selector``, ``Parallel``, a decorator, ``StartLeaf`` …),
        ``memory`` a composite's memory flag (else None), ``starts`` what a StartLeaf
        starts and ``action_type`` its type where the starter is an Action class."""
        layout = self._layout()
        index = {id(node): i for i, (node, _) in enumerate(layout)}
        nodes = []
        for node, path in layout:
            parent = node.parent
            entry: dict[str, Any] = {
                "name": node.name, "path": path,
                "parent": None if node is self.root or parent is None
                else index.get(id(parent)),
                "type": type(node).__name__,
                "memory": getattr(node, "memory", None)}
            if isinstance(node, StartLeaf):
                factory = node.starter.factory
                action_type = getattr(factory, "action_type", None) \
                    if isinstance(factory, type) else None
                entry["starts"] = node.starter.name
                entry["action_type"] = action_type if isinstance(action_type, str) else None
            nodes.append(entry)
        return {"kind": "behaviour_tree", "nodes": nodes}

    # -- the driver ----------------------------------------------------------------------
    def on_start(self, context: EngineContext) -> None:
        board = context.blackboard
        for leaf in self.leaves:
            leaf.context, leaf.board = context, board
        self.tree.setup()

    def tick(self) -> TreeStatus:
        """Tick the tree once and return the root's status. Called by :meth:`run` at
        ``rate_hz``; call it yourself only from a custom ``run``."""
        self.tree.tick()
        self.ticks += 1
        return self.root.status

    def run(self, context: EngineContext) -> Any:
        period_s = 1.0 / self.rate_hz
        next_tick = context.now()
        layout = self._layout()
        self.structure_changed()  # the tree may have been rebuilt since the last run
        before: tuple[str, ...] = ("INVALID",) * len(layout)
        behavior = context.behavior
        while not context.interrupted:
            status = self.tick()
            # One tuple, swapped in whole: describe() never sees half a tick.
            statuses = tuple(node.status.name for node, _ in layout)
            self._seen = (self.ticks, layout, statuses)
            if breakpoints.wanted(behavior, "node"):
                for (node, path), new, was in zip(layout, statuses, before, strict=True):
                    # Entered: ticked into a new status from one that was not RUNNING.
                    if new != was and new != "INVALID" and was != "RUNNING":
                        breakpoints.entered(behavior, "node", path, also=node.name)
            before = statuses
            if context.interrupted:  # leaves saw their actions interrupted: not a failure
                return None
            if status == TreeStatus.SUCCESS:
                return self._result()
            if status == TreeStatus.FAILURE:
                self._fail()
            next_tick += period_s
            now = context.now()
            if next_tick < now:  # overran: do not try to catch up with a burst of ticks
                next_tick = now
            while (remaining := next_tick - context.now()) > 0:
                if not context.wait(remaining):
                    return None
        return None

    def _result(self) -> Any:
        done = [leaf.last for leaf in self.leaves if isinstance(leaf, StartLeaf)
                and leaf.last is not None and leaf.last.status is Status.SUCCEEDED]
        last = max(done, key=lambda h: h.ended_at or 0.0, default=None)
        return None if last is None else last.result

    def _fail(self) -> None:
        failed = [n for n in self.root.iterate()
                  if n.status == TreeStatus.FAILURE and not n.children]
        leaf = failed[-1] if failed else self.root
        cause = None
        if isinstance(leaf, StartLeaf) and leaf.last is not None:
            cause = leaf.last.error
        detail = f": {leaf.feedback_message}" if leaf.feedback_message else ""
        raise TreeFailed(f"tree {self.root.name!r} failed at leaf {leaf.name!r}{detail}",
                         node=leaf.name) from cause

    def on_stop(self, context: EngineContext) -> None:
        self._seen = None
        # Stopping the root calls terminate(INVALID) on every running node: StartLeaf
        # interrupts and waits for what it started.
        try:
            if self.root.status != TreeStatus.INVALID:
                self.root.stop(TreeStatus.INVALID)
            self.tree.shutdown()
        finally:
            for leaf in self.leaves:
                leaf.context, leaf.board = None, None

    # -- dict / YAML form ----------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, resolve_start: StartResolver,
                  where: str = "", rate_hz: float = 20.0) -> TreeEngine:
        """Build from the dict / YAML form: one node, each node a one-key mapping::

            selector:            # also: sequence, parallel (policy: all|one), inverter
              memory: false      # optional (sequence: true, selector: false)
              children:
                - sequence:
                    children:
                      - condition: "battery/percentage < 20"
                      - action: charge          # a start entry, resolved by resolve_start
                - behavior: {use: patrol}       # same as action, for sub-behaviours

        Errors name the key path (``tree.selector.children[0]…``) prefixed with ``where``.
        """
        return cls(_build_node(data, where or "tree", resolve_start), rate_hz=rate_hz)

    # -- drawing -------------------------------------------------------------------------
    def to_graph(self) -> graphviz.Digraph:
        graphviz_mod = require("graphviz", extra="engines")
        graph = graphviz_mod.Digraph("tree", graph_attr={"rankdir": "TB", "ordering": "out"},
                                     node_attr={"fontname": "Helvetica"})
        counter = iter(range(1_000_000))

        def add(node: py_trees.behaviour.Behaviour) -> str:
            ident = f"n{next(counter)}"
            if isinstance(node, py_trees.composites.Sequence):
                graph.node(ident, f"→ {node.name}", shape="box", style="filled",
                           fillcolor="#ffd38a")
            elif isinstance(node, py_trees.composites.Selector):
                graph.node(ident, f"? {node.name}", shape="octagon", style="filled",
                           fillcolor="#8ad3ff")
            elif isinstance(node, py_trees.composites.Parallel):
                graph.node(ident, f"⇉ {node.name}", shape="parallelogram", style="filled",
                           fillcolor="#d3a8ff")
            elif isinstance(node, py_trees.decorators.Decorator):
                graph.node(ident, node.name, shape="diamond")
            elif isinstance(node, BlackboardCheck):
                graph.node(ident, f"{node.name}\n[{condition_label(node.condition)}]",
                           shape="ellipse", style="filled", fillcolor="#e0e0e0")
            elif isinstance(node, StartLeaf):
                graph.node(ident, f"▶ {node.name}", shape="ellipse", style="filled",
                           fillcolor="#b5f0b5")
            else:
                graph.node(ident, node.name, shape="ellipse")
            for child in node.children:
                graph.edge(ident, add(child))
            return ident

        add(self.root)
        return graph


_COMPOSITES = ("sequence", "selector", "fallback", "parallel")
_LEAVES = ("condition", "action", "behavior", "start")
_KINDS = (*_COMPOSITES, "inverter", *_LEAVES)


def _build_node(data: Any, where: str, resolve: StartResolver) -> py_trees.behaviour.Behaviour:
    if not isinstance(data, Mapping) or len(data) != 1:
        raise EngineConfigError(f"{where}: expected a mapping with exactly one node kind "
                                f"({', '.join(_KINDS)}), got {data!r}")
    ((kind, body),) = data.items()
    path = f"{where}.{kind}"
    if kind not in _KINDS:
        raise EngineConfigError(f"{where}: unknown node kind {kind!r}; valid: "
                                f"{', '.join(_KINDS)}")
    if kind in ("condition",):
        if isinstance(body, str):
            name, text = body, body
        elif isinstance(body, Mapping) and isinstance(body.get("check"), str):
            _only(body, {"check", "name"}, path)
            text = body["check"]
            name = str(body.get("name", text))
        else:
            raise EngineConfigError(f"{path}: expected 'KEY OP VALUE' or "
                                    f"{{check: 'KEY OP VALUE', name: …}}, got {body!r}")
        return BlackboardCheck(name, parse_condition(text, where=path))
    if kind in ("action", "behavior", "start"):
        on_busy = "running"
        if isinstance(body, Mapping) and "on_busy" in body:
            body = dict(body)
            on_busy = body.pop("on_busy")
        starter = resolve(body, path)
        return StartLeaf(starter.name, starter, on_busy=on_busy)
    if not isinstance(body, Mapping):
        raise EngineConfigError(f"{path}: expected a mapping (name, children …), got {body!r}")
    name = str(body.get("name", kind))
    if kind == "inverter":
        _only(body, {"name", "child"}, path)
        if "child" not in body:
            raise EngineConfigError(f"{path}.child: missing; an inverter needs one child")
        return py_trees.decorators.Inverter(name, _build_node(body["child"], f"{path}.child",
                                                              resolve))
    _only(body, {"name", "children", "memory", "policy"}, path)
    children_raw = body.get("children")
    if not isinstance(children_raw, list) or not children_raw:
        raise EngineConfigError(f"{path}.children: expected a non-empty list of nodes, "
                                f"got {children_raw!r}")
    children = [_build_node(c, f"{path}.children[{i}]", resolve)
                for i, c in enumerate(children_raw)]
    memory = body.get("memory", kind == "sequence")
    if not isinstance(memory, bool):
        raise EngineConfigError(f"{path}.memory: expected true or false, got {memory!r}")
    if kind == "sequence":
        return py_trees.composites.Sequence(name, memory=memory, children=children)
    if kind in ("selector", "fallback"):
        return py_trees.composites.Selector(name, memory=memory, children=children)
    policy_name = body.get("policy", "all")
    policies = {"all": py_trees.common.ParallelPolicy.SuccessOnAll,
                "one": py_trees.common.ParallelPolicy.SuccessOnOne}
    if policy_name not in policies:
        raise EngineConfigError(f"{path}.policy: expected 'all' or 'one', got {policy_name!r}")
    return py_trees.composites.Parallel(name, policy=policies[policy_name](),
                                        children=children)


def _only(body: Mapping[str, Any], allowed: set[str], path: str) -> None:
    extra = sorted(set(body) - allowed)
    if extra:
        raise EngineConfigError(f"{path}: unknown key(s) {', '.join(map(repr, extra))}; "
                                f"valid: {', '.join(sorted(allowed))}")


