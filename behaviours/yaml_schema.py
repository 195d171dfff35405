"""The YAML behaviour format: a pydantic schema, the loader that turns a file into an
engine, and :class:`YamlBehavior`, which runs a file (see ``docs/yaml_behaviors.md``; it is
offered with the other ready-made behaviours as ``behaviours.behaviors.YamlBehavior``).

A file names its engine and describes the states (or the tree, or the network) and the
actions they start::

    name: patrol_and_charge
    engine: state_machine
    actions:                        # aliases: a class (registry name or module:Class) + params
      to_dock: {use: "behaviours.demos.console:Drive", params: {goal_m: 0.0}}
      patrol:  {use: "behaviours.demos.console:Drive", params: {goal_m: 8.0, speed_mps: 0.5}}
    initial: patrol
    states:
      - {name: patrol, start: patrol}
      - {name: charge, start: [to_dock, {use: beep, params: {tune: charging}}]}
      - {name: done, final: true}
    transitions:
      - {source: patrol, dest: charge, when: "battery/percentage < 20"}
      - {source: charge, dest: patrol, on: succeeded}

Every error names the file, the key path and what was expected.
"""

from __future__ import annotations

import importlib
import inspect
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from beehave.action import Action
from beehave.behavior import Behavior
from beehave.engines.engine import (
    DecisionEngine,
    EngineBehavior,
    Starter,
    format_validation_error,
)
from beehave.engines.errors import EngineConfigError
from beehave.errors import ConfigError
from beehave.runnable import Runnable

__all__ = ["ActionRef", "BehaviorDoc", "YamlBehavior", "YamlBehaviorError", "build_engine",
           "load_engine"]

#: What a registry maps names to: an Action/Behavior class or a factory taking the params.
Factory = Callable[..., Runnable]


class YamlBehaviorError(ConfigError):
    """A YAML behaviour file that is not valid. ``.file`` and ``.key_path`` say where."""

    def __init__(self, file: str, key_path: str, message: str) -> None:
        self.file = file
        self.key_path = key_path
        where = f"{file}: {key_path}: " if key_path else f"{file}: "
        super().__init__(where + message)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ActionRef(_Strict):
    """``use``: an alias from ``actions``, a registry name or ``module:Class``;
    ``params`` go to its constructor; ``preempt`` to ``start_action``."""

    use: str = Field(min_length=1)
    params: dict[str, Any] = Field(default_factory=dict)
    preempt: bool = False


class BehaviorDoc(_Strict):
    """A whole behaviour file (or an inline ``behavior:`` inside one)."""

    name: str | None = None
    engine: Literal["state_machine", "tree", "neural"]
    actions: dict[str, ActionRef] = Field(default_factory=dict)
    # state machine
    initial: str | None = None
    states: list[dict[str, Any]] | None = None
    transitions: list[dict[str, Any]] | None = None
    events: list[str] | None = None
    # tree
    tree: dict[str, Any] | None = None
    rate_hz: float = Field(default=20.0, gt=0)
    # neural network
    neural: dict[str, Any] | None = None

    @model_validator(mode="after")
    def _engine_keys(self) -> BehaviorDoc:
        needs = {"state_machine": ("states", "initial"), "tree": ("tree",),
                 "neural": ("neural",)}[self.engine]
        missing = [k for k in needs if getattr(self, k) is None]
        if missing:
            raise ValueError(f"engine {self.engine!r} needs key(s) {', '.join(missing)}")
        foreign = {"state_machine": ("tree", "neural"),
                   "tree": ("states", "transitions", "initial", "events", "neural"),
                   "neural": ("states", "transitions", "initial", "events", "tree")
                   }[self.engine]
        present = [k for k in foreign if getattr(self, k) is not None]
        if present:
            raise ValueError(f"key(s) {', '.join(present)} do not belong to engine "
                             f"{self.engine!r}")
        return self


class _Loader:
    """Resolves start entries of one document (and its inline sub-behaviours)."""

    def __init__(self, file: Path, registry: Mapping[str, Factory],
                 inject: Mapping[str, Any], strict_params: bool = True,
                 chain: tuple[Path, ...] = ()) -> None:
        self.file = file
        self.strict_params = strict_params
        self.registry = registry
        self.inject = inject
        #: The files that include this one, outermost first (to refuse include cycles).
        self.chain = chain
        #: Inline documents being built (a YAML alias can make one contain itself).
        self._building: list[int] = []

    def error(self, key_path: str, message: str) -> YamlBehaviorError:
        return YamlBehaviorError(str(self.file), key_path, message)

    def build(self, data: Any, where: str = "",
              aliases: Mapping[str, ActionRef] | None = None) -> DecisionEngine:
        if id(data) in self._building:
            raise self.error(where, "this inline behaviour contains itself (through a YAML "
                                    "alias); a behaviour cannot start itself")
        self._building.append(id(data))
        try:
            return self._build(data, where, aliases)
        finally:
            self._building.pop()

    def _build(self, data: Any, where: str,
               aliases: Mapping[str, ActionRef] | None) -> DecisionEngine:
        try:
            doc = BehaviorDoc.model_validate(data)
        except ValidationError as exc:
            prefix = f"{where}." if where else ""
            raise YamlBehaviorError(str(self.file), "", format_validation_error(exc, prefix)
                                    ) from None
        scope = {**(aliases or {}), **doc.actions}
        for alias, ref in doc.actions.items():  # fail early on bad aliases
            self._factory(ref.use, f"{where + '.' if where else ''}actions.{alias}.use", {})

        def resolve(entry: Any, path: str) -> Starter:
            return self.starter(entry, path, scope)

        prefix = f"{where}." if where else ""
        try:
            if doc.engine == "state_machine":
                from beehave.engines.state_machine import StateMachineEngine
                return StateMachineEngine.from_dict(
                    {"states": doc.states, "transitions": doc.transitions or [],
                     "initial": doc.initial, "events": doc.events or []},
                    resolve_start=resolve, where=where, origin=str(self.file))
            if doc.engine == "tree":
                from beehave.engines.tree import TreeEngine
                assert doc.tree is not None
                return TreeEngine.from_dict(doc.tree, resolve_start=resolve,
                                            where=f"{prefix}tree", rate_hz=doc.rate_hz)
            from beehave.engines.neural import NeuralEngine
            assert doc.neural is not None
            return NeuralEngine.from_dict(doc.neural, resolve_start=resolve,
                                          where=f"{prefix}neural", base_dir=self.file.parent)
        except YamlBehaviorError:
            raise
        except EngineConfigError as exc:
            raise YamlBehaviorError(str(self.file), "", str(exc)) from None

    def starter(self, entry: Any, path: str, scope: Mapping[str, ActionRef]) -> Starter:
        if isinstance(entry, str):
            ref = ActionRef(use=entry)
        elif isinstance(entry, Mapping) and "behavior" in entry:
            extra = sorted(set(entry) - {"behavior"})
            if extra:
                raise self.error(path, f"unknown key(s) {extra} beside 'behavior'")
            return self._sub_behavior(entry["behavior"], f"{path}.behavior", scope)
        elif isinstance(entry, Mapping):
            try:
                ref = ActionRef.model_validate(entry)
            except ValidationError as exc:
                raise YamlBehaviorError(str(self.file), "",
                                        format_validation_error(exc, f"{path}.")) from None
        else:
            raise self.error(path, f"expected an action name, {{use: NAME, params: {{…}}}} or "
                                   f"{{behavior: …}}, got {entry!r}")
        base = scope.get(ref.use)
        if base is not None:  # an alias: its params, overridden by the entry's
            params = {**base.params, **ref.params}
            factory = self._factory(base.use, path, params)
            preempt = ref.preempt or base.preempt
        else:
            params = dict(ref.params)
            factory = self._factory(ref.use, path, params, aliases=scope)
            preempt = ref.preempt
        kwargs = self._bind(factory, ref.use, path, params)
        return Starter(lambda: factory(**kwargs), preempt, ref.use)

    def _sub_behavior(self, body: Any, path: str, scope: Mapping[str, ActionRef]) -> Starter:
        if isinstance(body, str):
            sub_file = (self.file.parent / body).resolve()
            registry, inject = self.registry, self.inject
            chain = (*self.chain, self.file.resolve())
            if sub_file in chain:
                cycle = " → ".join(str(f) for f in (*chain[chain.index(sub_file):], sub_file))
                raise self.error(path, f"behaviour files start each other in a cycle: "
                                       f"{cycle}; a behaviour cannot start itself")
            try:  # validate now, with the files that include it
                _load(sub_file, registry=registry, inject=inject,
                      strict_params=self.strict_params, chain=chain)
            except YamlBehaviorError as exc:
                raise self.error(path, str(exc)) from None

            def make_file() -> Runnable:
                return YamlBehavior(sub_file, registry=registry, inject=inject)
            return Starter(make_file, False, Path(body).stem)
        if not isinstance(body, Mapping):
            raise self.error(path, f"expected a file name or an inline behaviour "
                                   f"({{engine: …}}), got {body!r}")
        self.build(body, path, scope)  # validate now; a fresh engine per start
        label = str(body.get("name") or f"{body.get('engine')} behaviour")

        def make_inline() -> Runnable:
            behavior = EngineBehavior(self.build(body, path, scope), name=label)
            return behavior
        return Starter(make_inline, False, label)

    def _factory(self, use: str, path: str, params: Mapping[str, Any],
                 aliases: Mapping[str, ActionRef] | None = None) -> Factory:
        if use in self.registry:
            target = self.registry[use]
            if isinstance(target, type):
                self._check_class(target, use, path, "registry entry")
            elif not callable(target):
                raise self.error(path, f"registry entry {use!r} is {target!r}: not an Action "
                                       "or Behavior class, nor a factory returning one")
            return target
        if ":" in use:
            module_name, _, attr = use.partition(":")
            try:
                module = importlib.import_module(module_name)
            except ImportError as exc:
                raise self.error(path, f"cannot import module {module_name!r} for {use!r}: "
                                       f"{exc}") from None
            found: Any = getattr(module, attr, None)
            if found is None:
                raise self.error(path, f"module {module_name!r} has no {attr!r}")
            if not isinstance(found, type):
                what = "a function" if inspect.isroutine(found) else repr(found)
                raise self.error(path, f"{use!r} is {what}, not an Action or Behavior class; "
                                       "an import path names a class (put a factory in the "
                                       "registry instead)")
            self._check_class(found, use, path, "import path")
            return found
        known = sorted({*(aliases or {}), *self.registry})
        listed = ", ".join(map(repr, known)) or "none"
        raise self.error(path, f"unknown action {use!r}; known: {listed}; or give an "
                               "import path 'module:Class'")

    def _check_class(self, target: type, use: str, path: str, what: str) -> None:
        if not issubclass(target, (Action, Behavior)):
            raise self.error(path, f"{what} {use!r} is the class {target.__module__}."
                                   f"{target.__qualname__}, which is not an Action or "
                                   "Behavior subclass; only actions and behaviours can be "
                                   "started")

    def _bind(self, factory: Factory, use: str, path: str,
              params: Mapping[str, Any]) -> dict[str, Any]:
        try:
            signature = inspect.signature(factory)
        except (TypeError, ValueError):
            return dict(params)
        accepted = signature.parameters
        takes_any = any(p.kind is p.VAR_KEYWORD for p in accepted.values())
        kwargs = {k: v for k, v in self.inject.items()
                  if (k in accepted or takes_any) and k not in params}
        kwargs.update(params)
        try:
            (signature.bind if self.strict_params else signature.bind_partial)(**kwargs)
        except TypeError as exc:
            names = [n for n, p in accepted.items()
                     if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
            raise self.error(f"{path}.params", f"{use!r} rejects {sorted(params)}: {exc}; it "
                                               f"accepts: {', '.join(names) or 'nothing'}"
                                               ) from None
        return kwargs


class _YamlLoader(yaml.SafeLoader):  # type: ignore[misc]
    """YAML 1.2 booleans: only true/false. YAML 1.1 would read a transition's ``on:`` key
    (and ``yes``/``no``/``off``) as a boolean."""


_YamlLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
    list("tTfF"))


def _read(file: Path) -> Any:
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as exc:
        raise YamlBehaviorError(str(file), "", f"cannot read: {exc.strerror or exc}") from None
    try:
        return yaml.load(text, Loader=_YamlLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        raise YamlBehaviorError(str(file), "", f"{where}not valid YAML: "
                                               f"{getattr(exc, 'problem', exc)}") from None


def build_engine(data: Any, *, file: str | Path = "<dict>",
                 registry: Mapping[str, Factory] | None = None,
                 inject: Mapping[str, Any] | None = None,
                 strict_params: bool = True) -> DecisionEngine:
    """Validate a behaviour document (already parsed) and build its engine.

    ``registry`` maps action names to Action/Behavior classes or factories; ``inject``
    supplies constructor arguments by name to every action that takes them (the robot
    object, for instance), unless the file gives them. ``strict_params=False`` accepts
    missing constructor arguments (to draw a file without its robot).
    """
    return _build(data, file=Path(file), registry=registry, inject=inject,
                  strict_params=strict_params, chain=())


def _build(data: Any, *, file: Path, registry: Mapping[str, Factory] | None,
           inject: Mapping[str, Any] | None, strict_params: bool,
           chain: tuple[Path, ...]) -> DecisionEngine:
    if not isinstance(data, Mapping):
        raise YamlBehaviorError(str(file), "", f"expected a mapping with 'engine' at the top, "
                                               f"got {type(data).__name__}")
    loader = _Loader(file, registry or {}, inject or {}, strict_params, chain)
    try:
        return loader.build(data)
    except RecursionError:  # a last resort: the checks above name the usual causes
        raise YamlBehaviorError(str(file), "", "nested too deeply (does a behaviour start "
                                               "itself?)") from None


def load_engine(file: str | Path, *, registry: Mapping[str, Factory] | None = None,
                inject: Mapping[str, Any] | None = None,
                strict_params: bool = True) -> DecisionEngine:
    """Read, validate and build the engine of a YAML behaviour file (see :func:`build_engine`)."""
    return _load(Path(file), registry=registry, inject=inject, strict_params=strict_params,
                 chain=())


def _load(file: Path, *, registry: Mapping[str, Factory] | None,
          inject: Mapping[str, Any] | None, strict_params: bool,
          chain: tuple[Path, ...]) -> DecisionEngine:
    return _build(_read(file), file=file, registry=registry, inject=inject,
                  strict_params=strict_params, chain=chain)


def document_name(file: str | Path) -> str:
    """The ``name`` of a behaviour file, or its stem."""
    data = _read(Path(file))
    name = data.get("name") if isinstance(data, Mapping) else None
    return str(name) if name else Path(file).stem


class YamlBehavior(EngineBehavior):
    """A behaviour described entirely in a YAML file.

    The file is read and validated when the behaviour is constructed — at ``hl.switch``
    time, so a broken file is refused (``InvalidParameters`` naming the file, key path and
    what was expected) before the running behaviour is stopped::

        hl.register("patrol", YamlBehavior, file="behaviours/patrol.yaml",
                    registry={"drive": Drive}, inject={"robot": robot})

    ``registry`` maps action names used in the file to Action/Behavior classes or
    factories (a file may also name ``module:Class`` directly); ``inject`` gives
    constructor arguments by name to every action that takes them (the robot object).
    """

    def __init__(self, file: str | Path, *, registry: Mapping[str, Factory] | None = None,
                 inject: Mapping[str, Any] | None = None, name: str | None = None) -> None:
        self.file = Path(file)
        engine = load_engine(self.file, registry=registry, inject=inject)
        super().__init__(engine, name=name or document_name(self.file))

    def _snapshot(self) -> dict[str, Any]:
        snap = super()._snapshot()
        snap["file"] = str(self.file)  # which file is running, beside where its engine is
        return snap


EngineKind = Literal["state_machine", "tree", "neural"]
