"""Neural network engine over ``torch``: blackboard features in, one of N decisions out.

A :class:`NeuralPolicy` holds a ``torch.nn.Module`` that maps a feature vector (read from
blackboard keys, scaled) to scores for N named decisions. It learns online from labelled
examples (:meth:`NeuralPolicy.add_example`) or rewards (:meth:`NeuralPolicy.add_reward`):
a background thread trains on a replay buffer and publishes a fresh copy of the weights
after training steps. A decision only reads the latest published copy — it never waits
for training, and training never sees a half-made decision.

:class:`NeuralEngine` drives a behaviour with it: at ``rate_hz`` (and whenever what it
started ends) it decides, and when the decision changes it interrupts what the previous
decision started and starts what the new one maps to. A decision also serves elsewhere as a
condition: ``policy.condition("charge")`` is a tree condition or a state-machine guard.

torch is imported when a policy is built, not when this module is imported; without it
you get :class:`~beehave.engines.errors.MissingExtra` naming ``beehave-robotics[nn]``.
Everything runs on the CPU.
"""

from __future__ import annotations

import collections
import copy
import math
import random
import threading
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from beehave.engines.engine import (
    DecisionEngine,
    EngineContext,
    Readable,
    Starter,
    as_starter,
    require,
)
from beehave.engines.errors import DecisionFailed, EngineBusy, EngineConfigError
from beehave.runnable import Runnable
from beehave.status import Status

if TYPE_CHECKING:
    import graphviz
    import torch

__all__ = ["DecisionCondition", "Feature", "NeuralEngine", "NeuralPolicy", "Trainer"]

StartLike = Starter | Callable[[], Runnable] | type[Runnable]


def _torch() -> Any:
    return require("torch", extra="nn")


@dataclass(frozen=True)
class Feature:
    """One input: ``(blackboard[key] - offset) * scale``; ``default`` when the key is
    missing or not a number; booleans count as 0/1."""

    key: str
    scale: float = 1.0
    offset: float = 0.0
    default: float = 0.0

    def read(self, blackboard: Readable) -> float:
        value = blackboard.get(self.key)
        if isinstance(value, bool):
            value = float(value)
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            return self.default
        return (float(value) - self.offset) * self.scale


class DecisionCondition:
    """``policy.decide(blackboard) == decision``: a network decision as a condition."""

    def __init__(self, policy: NeuralPolicy, decision: str) -> None:
        if decision not in policy.decisions:
            raise EngineConfigError(f"unknown decision {decision!r}; the network decides "
                                    f"between {', '.join(map(repr, policy.decisions))}")
        self.policy, self.decision = policy, decision
        self.label = f"nn: {decision}"

    def __call__(self, blackboard: Readable) -> bool:
        return self.policy.decide(blackboard) == self.decision

    def __repr__(self) -> str:
        return f"DecisionCondition({self.decision!r})"


class Trainer:
    """The background training thread of a policy; whoever started it stops it.

    Returned by :meth:`NeuralPolicy.start_training`. :meth:`stop` wakes the thread and
    joins it (no polling); it is idempotent.
    """

    def __init__(self, policy: NeuralPolicy, name: str) -> None:
        self.policy = policy
        self._stopping = False
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._main, name=name, daemon=True)

    def _main(self) -> None:
        policy = self.policy
        try:
            while True:
                with policy._cond:
                    while not self._stopping and policy._untrained == 0:
                        policy._cond.wait()
                    if self._stopping:
                        return
                    steps = policy._untrained * policy.steps_per_example
                    policy._untrained = 0
                for _ in range(steps):
                    if self._stopping:
                        return
                    policy.train_step()
        except BaseException as exc:  # recorded here and raised by stop()
            self.error = exc

    def stop(self, timeout_s: float | None = 5.0) -> None:
        """Stop training and join the thread; re-raises an error the thread hit."""
        with self.policy._cond:
            self._stopping = True
            self.policy._cond.notify_all()
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(timeout_s)
        with self.policy._cond:
            if self.policy._trainer is self:
                self.policy._trainer = None
        if self.error is not None:
            error, self.error = self.error, None
            raise error


class NeuralPolicy:
    """A small network that picks one of ``decisions`` from ``features``, learning online.

    ``features``: blackboard keys or :class:`Feature` (scaled keys). ``decisions``: the
    names of the outputs. ``model``: your own ``torch.nn.Module`` taking a float tensor of
    shape ``(batch, len(features))`` and returning ``(batch, len(decisions))`` scores;
    default an MLP with ``hidden`` tanh layers. ``seed`` makes initialisation and replay
    sampling reproducible. ``weights`` loads a file written by :meth:`save`.
    """

    def __init__(self, features: Sequence[str | Feature], decisions: Sequence[str], *,
                 hidden: Sequence[int] = (16,), model: torch.nn.Module | None = None,
                 learning_rate: float = 0.01, batch_size: int = 32, buffer_size: int = 5000,
                 steps_per_example: int = 1, seed: int = 0,
                 weights: str | Path | None = None) -> None:
        tm = _torch()
        self.features = tuple(f if isinstance(f, Feature) else Feature(f) for f in features)
        self.decisions = tuple(decisions)
        if not self.features:
            raise EngineConfigError("a NeuralPolicy needs at least one feature")
        if len(self.decisions) < 2 or len(set(self.decisions)) != len(self.decisions):
            raise EngineConfigError(f"a NeuralPolicy needs two or more distinct decisions, "
                                    f"got {list(self.decisions)}")
        self.hidden = tuple(int(h) for h in hidden)
        self.batch_size = batch_size
        self.steps_per_example = steps_per_example
        self._index = {d: i for i, d in enumerate(self.decisions)}
        with tm.random.fork_rng(devices=[]):
            tm.manual_seed(seed)
            built: torch.nn.Module = model if model is not None else self._mlp(tm)
        self.model = built
        self.model.train()
        params = [p for p in self.model.parameters() if p.requires_grad]
        # A fixed model (no parameters) decides but cannot learn.
        self._optimizer = (tm.optim.Adam(params, lr=learning_rate, foreach=False)
                           if params else None)
        # Decisions read a published copy of the weights: a ring of three inference
        # copies, each with a generation counter (a seqlock). Publishing writes into the
        # copy that is neither current nor previous, then points decisions at it; a
        # decision that was lapped by two publishes in the middle of its forward pass
        # notices the changed generation and decides again. Nobody waits for anybody.
        self._ring: list[torch.nn.Module] = [self._snapshot() for _ in range(3)]
        self._generation = [0, 0, 0]
        self._current = 0
        source = [*self.model.parameters(), *self.model.buffers()]
        self._pairs = [list(zip([*m.parameters(), *m.buffers()], source, strict=True))
                       for m in self._ring]
        self._rng = random.Random(seed)
        self._buffer: collections.deque[tuple[list[float], int, float]] = collections.deque(
            maxlen=buffer_size)
        self._cond = threading.Condition()
        self._train_lock = threading.Lock()
        self._untrained = 0
        self._trainer: Trainer | None = None
        #: Training steps taken, examples and rewards received (for reports).
        self.steps = 0
        self.examples = 0
        self.last_loss: float | None = None
        if weights is not None:
            self.load(weights)

    def _mlp(self, tm: Any) -> torch.nn.Module:
        layers: list[Any] = []
        width = len(self.features)
        for h in self.hidden:
            layers += [tm.nn.Linear(width, h), tm.nn.Tanh()]
            width = h
        layers.append(tm.nn.Linear(width, len(self.decisions)))
        module: torch.nn.Module = tm.nn.Sequential(*layers)
        return module

    def _snapshot(self) -> torch.nn.Module:
        snapshot: torch.nn.Module = copy.deepcopy(self.model)
        snapshot.eval()
        for param in snapshot.parameters():
            param.requires_grad_(False)
        return snapshot

    def _publish(self) -> None:
        """Copy the trained weights into a free inference copy and make it current.
        Called with ``_train_lock`` held."""
        torch = _torch()
        slot = (self._current + 1) % 3
        self._generation[slot] += 1  # odd: being written
        with torch.no_grad():
            for dst, src in self._pairs[slot]:
                dst.copy_(src)
        self._generation[slot] += 1  # even: stable
        self._current = slot

    def _forward(self, features: Sequence[float]) -> Any:
        torch = _torch()
        x = torch.tensor([list(features)], dtype=torch.float32)
        for _ in range(100):
            slot = self._current
            generation = self._generation[slot]
            if generation % 2:
                continue  # lapped while being written: take the new current copy
            out = self._ring[slot](x)
            if self._generation[slot] == generation:
                return out
        raise EngineConfigError("network weights changed during 100 decisions in a row")

    # -- deciding ------------------------------------------------------------------------
    def featurize(self, blackboard: Readable) -> list[float]:
        """The feature vector the network sees for the current blackboard."""
        return [f.read(blackboard) for f in self.features]

    def scores(self, features: Sequence[float]) -> list[float]:
        """The network's raw score per decision (same order as ``decisions``)."""
        return list(self._forward(features)[0].tolist())

    def decide_features(self, features: Sequence[float]) -> str:
        """The decision for an explicit feature vector."""
        return self.decisions[int(self._forward(features).argmax())]

    def decide(self, blackboard: Readable) -> str:
        """The decision for the current blackboard. Never waits for training."""
        return self.decide_features(self.featurize(blackboard))

    def condition(self, decision: str) -> DecisionCondition:
        """A condition that holds when the network decides ``decision``."""
        return DecisionCondition(self, decision)

    # -- learning ------------------------------------------------------------------------
    def add_example(self, features: Sequence[float], decision: str) -> None:
        """Learn that ``features`` should lead to ``decision``. Returns at once; the
        training thread (if one runs) takes a step for it."""
        self._add(features, decision, 1.0)

    def add_reward(self, features: Sequence[float], decision: str, reward: float) -> None:
        """Reinforce (reward > 0) or discourage (reward < 0) taking ``decision`` for
        ``features``: a policy-gradient step weighted by the reward, clipped to [-1, 1]."""
        self._add(features, decision, max(-1.0, min(1.0, float(reward))))

    def _add(self, features: Sequence[float], decision: str, weight: float) -> None:
        if decision not in self._index:
            raise EngineConfigError(f"unknown decision {decision!r}; the network decides "
                                    f"between {', '.join(map(repr, self.decisions))}")
        if len(features) != len(self.features):
            raise EngineConfigError(f"expected {len(self.features)} features "
                                    f"({', '.join(f.key for f in self.features)}), "
                                    f"got {len(features)}")
        with self._cond:
            self._buffer.append(([float(v) for v in features], self._index[decision], weight))
            self.examples += 1
            self._untrained += 1
            self._cond.notify_all()

    def train_step(self) -> float | None:
        """One optimisation step on a minibatch from the replay buffer, then publish the
        weights for decisions. Returns the loss (None while the buffer is empty).

        The training thread calls it; call it yourself to train synchronously (tests,
        benchmarks). Steps never run concurrently.
        """
        torch = _torch()
        if self._optimizer is None:
            raise EngineConfigError("this policy's model has no trainable parameters")
        with self._cond:
            if not self._buffer:
                return None
            n = min(self.batch_size, len(self._buffer))
            batch = self._rng.choices(self._buffer, k=n)  # with replacement: cheap
        with self._train_lock:
            x = torch.tensor([b[0] for b in batch], dtype=torch.float32)
            y = torch.tensor([b[1] for b in batch], dtype=torch.long)
            w = torch.tensor([b[2] for b in batch], dtype=torch.float32)
            logits = self.model(x)
            loss = (w * torch.nn.functional.cross_entropy(logits, y, reduction="none")).mean()
            self._optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self._optimizer.step()
            self._publish()
            self.steps += 1
            self.last_loss = float(loss.detach())
        return self.last_loss

    def start_training(self, *, name: str = "beehave:nn-train") -> Trainer:
        """Start the background training thread and return it; the caller owns it and
        must :meth:`Trainer.stop` it. Its name should start with ``beehave`` so that leak
        checks see it. Raises :class:`EngineBusy` if one already runs."""
        with self._cond:
            if self._trainer is not None:
                raise EngineBusy(f"this policy is already being trained by thread "
                                 f"{self._trainer.thread.name!r}")
            trainer = self._trainer = Trainer(self, name)
        trainer.thread.start()
        return trainer

    # -- persistence ---------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write the weights with the feature and decision names (``torch.save``)."""
        torch = _torch()
        with self._train_lock:
            state = {k: v.clone() for k, v in self.model.state_dict().items()}
        torch.save({"state_dict": state, "features": [f.key for f in self.features],
                    "decisions": list(self.decisions), "hidden": list(self.hidden)},
                   str(path))

    def load(self, path: str | Path) -> None:
        """Load weights written by :meth:`save`; the features and decisions must match."""
        torch = _torch()
        try:
            data = torch.load(str(path), map_location="cpu", weights_only=True)
        except (OSError, RuntimeError, EOFError) as exc:
            raise EngineConfigError(f"{path}: cannot load network weights: {exc}") from exc
        keys = [f.key for f in self.features]
        if data.get("features") != keys or data.get("decisions") != list(self.decisions):
            raise EngineConfigError(
                f"{path}: weights are for features {data.get('features')} → decisions "
                f"{data.get('decisions')}, this policy has {keys} → {list(self.decisions)}")
        with self._train_lock:
            self.model.load_state_dict(data["state_dict"])
            self._publish()


class NeuralEngine(DecisionEngine):
    """Decides with a :class:`NeuralPolicy` and starts what each decision maps to.

    ``starts`` maps decisions to what they start (None: start nothing). ``finish`` lists
    decisions that end the behaviour (the result is the decision). When what a decision
    started succeeds, ``on_success="decide"`` decides again (and restarts it if the
    decision stays), ``"return"`` ends the behaviour with its result. A failure fails the
    behaviour with :class:`DecisionFailed`.

    With ``train=True`` the engine owns the policy's training thread while it runs (named
    ``beehave:nn-train:<behaviour path>``); ``teacher(blackboard) -> decision`` labels every
    decision online, so the network learns to imitate the teacher while it decides.
    """

    kind = "neural"

    def __init__(self, policy: NeuralPolicy, starts: Mapping[str, StartLike | None], *,
                 rate_hz: float = 10.0, finish: Collection[str] = (),
                 on_success: str = "decide", train: bool = False,
                 teacher: Callable[[Readable], str] | None = None) -> None:
        unknown = sorted((set(starts) | set(finish)) - set(policy.decisions))
        if unknown:
            raise EngineConfigError(f"unknown decision(s) {unknown}; the network decides "
                                    f"between {', '.join(map(repr, policy.decisions))}")
        if on_success not in ("decide", "return"):
            raise EngineConfigError(f"on_success must be 'decide' or 'return', "
                                    f"not {on_success!r}")
        if not rate_hz > 0:
            raise EngineConfigError(f"rate_hz must be positive, got {rate_hz!r}")
        self.policy = policy
        self.starts = {d: None if s is None else as_starter(s, label=d)
                       for d, s in starts.items()}
        self.finish = frozenset(finish)
        self.on_success = on_success
        self.rate_hz = float(rate_hz)
        self.poll_s = 1.0 / self.rate_hz
        self.train = train
        self.teacher = teacher
        self.decision: str | None = None
        #: The last decision taken (kept when ``decision`` is cleared to decide afresh).
        self.last_decision: str | None = None
        self.decisions_made = 0
        self._trainer: Trainer | None = None
        self._current: Runnable | None = None

    def describe(self) -> dict[str, Any]:
        """The network's last decision and what it runs, JSON-serialisable:
        ``{"kind": "neural_network", "last_decision": …, "running": …, "decisions": […],
        "decisions_made": n, "training": bool, "training_steps": n, "examples": n,
        "last_loss": …}``. Safe from any thread: it only reads."""
        current = self._current
        policy = self.policy
        return {
            "kind": "neural_network",
            "last_decision": self.last_decision,
            "running": None if current is None else current.name,
            "decisions": list(policy.decisions),
            "decisions_made": self.decisions_made,
            "training": self._trainer is not None,
            "training_steps": policy.steps,
            "examples": policy.examples,
            "last_loss": policy.last_loss,
        }

    def on_start(self, context: EngineContext) -> None:
        self.decision = None
        self.last_decision = None
        if self.train or self.teacher is not None:
            self._trainer = self.policy.start_training(
                name=f"beehave:nn-train:{context.behavior.path}")

    def run(self, context: EngineContext) -> Any:
        blackboard = context.blackboard
        while not context.interrupted:
            current = self._current
            if current is not None and current.status.finished:
                current.wait(0)  # seen: no ChildFailed later
                context.forget(current)
                self._current = None
                if context.interrupted:
                    return None
                if current.status is Status.FAILED:
                    raise DecisionFailed(
                        f"decision {self.decision!r}: {type(current).__name__} "
                        f"{current.name!r} failed: {current.error!r}",
                        decision=self.decision or "?") from current.error
                if current.status is Status.SUCCEEDED and self.on_success == "return":
                    return current.result
                self.decision = None  # decide afresh; the same decision restarts it
            features = self.policy.featurize(blackboard)
            decision = self.policy.decide_features(features)
            self.last_decision = decision
            self.decisions_made += 1
            if self.teacher is not None:
                self.policy.add_example(features, self.teacher(blackboard))
            if decision in self.finish:
                self.decision = decision
                return decision
            if decision != self.decision:
                if self._current is not None:
                    context.stop([self._current])
                    self._current = None
                self.decision = decision
                starter = self.starts.get(decision)
                if starter is not None:
                    self._current = context.start(starter)
            context.wait(self.poll_s)
        return None

    def on_stop(self, context: EngineContext) -> None:
        try:
            if self._current is not None:
                context.stop([self._current])
                self._current = None
        finally:
            trainer, self._trainer = self._trainer, None
            if trainer is not None:
                trainer.stop()

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *,
                  resolve_start: Callable[[Any, str], Starter], where: str = "",
                  base_dir: Path | None = None) -> NeuralEngine:
        """Build from the dict / YAML form::

            features: [battery/percentage, {key: dock/distance_m, scale: 0.1}]
            decisions: {patrol: patrol, charge: charge, wait: null}
            hidden: [16]
            weights: charging.pt        # optional, relative to the YAML file
            rate_hz: 10
            train: false
        """
        prefix = f"{where}." if where else ""
        allowed = {"features", "decisions", "hidden", "weights", "rate_hz", "train",
                   "finish", "on_success", "learning_rate", "seed"}
        extra = sorted(set(data) - allowed)
        if extra:
            raise EngineConfigError(f"{where or '<top>'}: unknown key(s) {extra}; valid: "
                                    f"{', '.join(sorted(allowed))}")
        raw_features = data.get("features")
        if not isinstance(raw_features, list) or not raw_features:
            raise EngineConfigError(f"{prefix}features: expected a non-empty list of "
                                    f"blackboard keys, got {raw_features!r}")
        features: list[Feature] = []
        for i, f in enumerate(raw_features):
            if isinstance(f, str):
                features.append(Feature(f))
            elif isinstance(f, Mapping) and isinstance(f.get("key"), str):
                try:
                    features.append(Feature(**f))
                except TypeError as exc:
                    raise EngineConfigError(f"{prefix}features[{i}]: {exc}; expected key, "
                                            "scale, offset, default") from None
            else:
                raise EngineConfigError(f"{prefix}features[{i}]: expected a key or "
                                        f"{{key: …, scale: …}}, got {f!r}")
        decisions = data.get("decisions")
        if not isinstance(decisions, Mapping) or len(decisions) < 2:
            raise EngineConfigError(f"{prefix}decisions: expected a mapping of two or more "
                                    f"decisions to what they start, got {decisions!r}")
        starts = {str(d): None if s is None else resolve_start(s, f"{prefix}decisions.{d}")
                  for d, s in decisions.items()}
        weights = data.get("weights")
        if weights is not None and base_dir is not None:
            weights = base_dir / str(weights)
        policy = NeuralPolicy(features, list(starts), hidden=data.get("hidden", (16,)),
                              learning_rate=float(data.get("learning_rate", 0.01)),
                              seed=int(data.get("seed", 0)), weights=weights)
        return cls(policy, starts, rate_hz=float(data.get("rate_hz", 10.0)),
                   finish=data.get("finish", ()), train=bool(data.get("train", False)),
                   on_success=str(data.get("on_success", "decide")))

    def to_graph(self) -> graphviz.Digraph:
        graphviz_mod = require("graphviz", extra="engines")
        graph = graphviz_mod.Digraph("neural", graph_attr={"rankdir": "LR"},
                                     node_attr={"fontname": "Helvetica"})
        graph.node("net", f"network\n{len(self.policy.features)}→"
                   f"{'→'.join(map(str, self.policy.hidden))}→{len(self.policy.decisions)}",
                   shape="box3d")
        for f in self.policy.features:
            graph.node(f"f:{f.key}", f.key, shape="note")
            graph.edge(f"f:{f.key}", "net")
        for d in self.policy.decisions:
            starter = self.starts.get(d)
            label = d + ("" if starter is None else f"\n▶ {starter.name}")
            graph.node(f"d:{d}", label, shape="doublecircle" if d in self.finish else "box",
                       style="rounded")
            graph.edge("net", f"d:{d}")
        return graph
