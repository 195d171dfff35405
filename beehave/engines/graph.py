"""``beehave graph SPEC -o out.png``: draw a behaviour's state machine, tree or network.

``SPEC`` is a YAML behaviour file, or ``module:attr`` where ``attr`` is a DecisionEngine,
an EngineBehavior (class or object), or a function returning either (called with the
``--param KEY=VALUE`` arguments; values are read as JSON, else taken as strings). Needs no
ROS setup and no running manager: nothing is started.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import logging
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from beehave.engines.engine import DecisionEngine, EngineBehavior, require
from beehave.engines.errors import NotRenderable
from beehave.errors import BeehaveError

__all__ = ["graph_main", "load_spec", "render_engine"]

_FORMATS = ("png", "svg", "pdf", "dot")


def render_engine(engine: DecisionEngine, output: str | Path) -> Path:
    """Render ``engine.to_graph()`` to ``output``; the suffix picks the format (``.png``,
    ``.svg``, ``.pdf``, or ``.dot`` for the graphviz source, which needs no ``dot``)."""
    out = Path(output)
    fmt = out.suffix.lstrip(".").lower() or "png"
    if fmt not in _FORMATS:
        raise NotRenderable(f"{out}: unknown format {fmt!r}; use one of {', '.join(_FORMATS)}")
    graph = engine.to_graph()
    out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "dot":
        out.write_text(graph.source, encoding="utf-8")
        return out
    graphviz_mod = require("graphviz", extra="engines")
    try:
        graph.render(outfile=str(out), format=fmt, cleanup=True)
    except graphviz_mod.ExecutableNotFound:
        raise NotRenderable("graphviz's 'dot' program is not installed (apt-get install "
                            "graphviz); write a .dot file instead") from None
    return out


def _signature_text(obj: Any) -> str:
    try:
        parameters = inspect.signature(obj).parameters.values()
    except (TypeError, ValueError):
        return "?"
    return ", ".join(str(p.replace(annotation=p.empty)) for p in parameters) or "nothing"


def _engine_of(obj: Any, params: Mapping[str, Any], spec: str) -> DecisionEngine:
    if isinstance(obj, DecisionEngine):
        return obj
    if isinstance(obj, EngineBehavior):
        return obj.engine
    if callable(obj):
        try:
            signature = inspect.signature(obj)
        except (TypeError, ValueError):  # no signature to check: the call will tell
            signature = None
        if signature is not None:
            try:
                signature.bind(**params)
            except TypeError as exc:
                given = " ".join(f"-p {k}=…" for k in params) or "no -p"
                missing = [n for n, p in signature.parameters.items()
                           if p.default is p.empty and n not in params
                           and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
                example = f" (e.g. -p {missing[0]}=null)" if missing else ""
                raise NotRenderable(
                    f"{spec}: cannot call it with {given}: {exc}; give its arguments with "
                    f"-p KEY=VALUE, values as JSON{example}; it takes: "
                    f"{_signature_text(obj)}") from None
        built = obj(**params)
        if isinstance(built, DecisionEngine):
            return built
        engine = getattr(built, "engine", None)
        if isinstance(engine, DecisionEngine):
            return engine
        raise NotRenderable(f"{spec} built {built!r}, which has no decision engine "
                            "(expected a DecisionEngine or an EngineBehavior)")
    raise NotRenderable(f"{spec} is {obj!r}: not a DecisionEngine, an EngineBehavior, or a "
                        "function returning one")


def load_spec(spec: str, params: Mapping[str, Any] | None = None,
              registry: Mapping[str, Any] | None = None) -> DecisionEngine:
    """The engine named by ``spec`` (a YAML file or ``module:attr``), built, not started."""
    path = Path(spec)
    if path.suffix in (".yaml", ".yml"):
        from behaviours.yaml_schema import load_engine

        # Drawing starts nothing: actions may lack their robot argument here.
        return load_engine(path, registry=registry, inject=params, strict_params=False)
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise NotRenderable(f"{spec!r}: expected a YAML file (.yaml) or 'module:attr'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise NotRenderable(f"{spec!r}: cannot import {module_name!r}: {exc}") from None
    obj = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise NotRenderable(f"{spec!r}: {module_name!r} has no {attr!r}")
        obj = getattr(obj, part)
    return _engine_of(obj, params or {}, spec)


def _param(text: str) -> tuple[str, Any]:
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(raw)
    except ValueError:
        return key, raw


def graph_main(argv: list[str]) -> int:
    """``beehave graph``: parse ``argv`` (without the program and command names), render,
    print the output path. Returns 0, or 2 with a message on stderr."""
    parser = argparse.ArgumentParser(
        prog="beehave graph", description="Render a behaviour's state machine, tree or "
        "network (a YAML file or module:attr) with graphviz.")
    parser.add_argument("spec", help="behaviour YAML file, or module:attr")
    parser.add_argument("-o", "--output", help="output file; the suffix picks the format "
                        "(.png default, .svg, .pdf, .dot)")
    parser.add_argument("-p", "--param", action="append", type=_param, default=[],
                        metavar="KEY=VALUE", help="parameter for a module:attr function, or "
                        "an injected action argument for a YAML file (JSON value)")
    parser.add_argument("--registry", metavar="MODULE:ATTR",
                        help="a mapping of action names for a YAML file's actions")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="log what loading finds (e.g. unreachable states) in detail")
    args = parser.parse_args(argv)
    if args.verbose and not logging.getLogger().handlers:
        logging.basicConfig(level=logging.DEBUG,
                            format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        registry = _registry(args.registry) if args.registry else None
        engine = load_spec(args.spec, dict(args.param), registry)
        output = args.output or f"{Path(args.spec.split(':')[-1]).stem}.png"
        out = render_engine(engine, output)
    except (BeehaveError, ImportError, AttributeError, TypeError) as exc:
        print(f"beehave graph: {exc}{_hint(exc, args)}", file=sys.stderr)
        return 2
    print(out)
    return 0


def _registry(text: str) -> Mapping[str, Any]:
    module_name, sep, attr = text.partition(":")
    if not sep or not module_name or not attr:
        raise NotRenderable(f"--registry {text!r}: expected MODULE:ATTR (a mapping of action "
                            "names to classes)")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise NotRenderable(f"--registry {text!r}: cannot import {module_name!r}: {exc}"
                            ) from None
    registry = getattr(module, attr, None)
    if not isinstance(registry, Mapping):
        raise NotRenderable(f"--registry {text!r}: {module_name!r} has no mapping {attr!r} "
                            f"(got {registry!r})")
    return registry


def _hint(exc: BaseException, args: argparse.Namespace) -> str:
    """What to try next, for the failures a first use runs into."""
    text = str(exc)
    if "unknown action" in text and not args.registry:
        return ("\nhint: name the file's actions with --registry MODULE:ATTR (a dict of "
                "names to Action classes), or use import paths 'module:Class' in the file")
    return ""


if __name__ == "__main__":
    raise SystemExit(graph_main(sys.argv[1:]))
