"""The package's layers import one way: no import cycle between modules of beehave/,
behaviours/, hal/ and robots/ — lazy imports inside functions included, since they only
hide a cycle from the interpreter (only imports under ``if TYPE_CHECKING:`` are left out)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("beehave", "behaviours", "hal", "robots")


def _modules(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    modules = {}
    for package in packages:
        for file in (root / package).rglob("*.py"):
            parts = list(file.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = file
    return modules


def _imports(module: str, file: Path, modules: dict[str, Path]) -> set[str]:
    """The modules of ours that ``module`` imports (the longest module prefix of each
    imported name)."""
    def ours(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    tree = ast.parse(file.read_text(encoding="utf-8"))
    typing_only = {id(n) for node in ast.walk(tree)
                   if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
                   for stmt in node.body for n in ast.walk(stmt)}
    package = module.split(".") if file.name == "__init__.py" else module.split(".")[:-1]
    found: set[str | None] = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            found.update(ours(alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            # `from pkg import mod` imports the module pkg.mod; `from mod import name`, mod.
            found.update(ours(f"{target}.{alias.name}") if f"{target}.{alias.name}" in modules
                         else ours(target) for alias in node.names)
    found.discard(module)
    found.discard(None)
    return {m for m in found if m is not None}


def import_cycles(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> list[list[str]]:
    """Groups of modules that import each other (strongly connected components > 1)."""
    modules = _modules(root, packages)
    graph = {m: _imports(m, f, modules) for m, f in modules.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan; the import graph is shallow enough for recursion
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                cycles.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(cycles)


def test_no_module_imports_one_that_imports_it_back() -> None:
    cycles = import_cycles()
    assert cycles == [], "import cycles (move what both sides need one layer down): " + "; ".join(
        " ↔ ".join(group) for group in cycles)


def test_the_check_finds_a_lazy_cycle_and_leaves_typing_only_imports_out(tmp_path: Path) -> None:
    """The check itself: a cycle closed by an import inside a function is one; an import
    under ``if TYPE_CHECKING:`` is not (else the test above could pass finding nothing)."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "low.py").write_text("def f():\n    from pkg.high import g\n    return g\n")
    (package / "high.py").write_text("from pkg import low\n\ndef g():\n    return low\n")
    (package / "typed.py").write_text(
        "from typing import TYPE_CHECKING\nfrom pkg.high import g\n"
        "if TYPE_CHECKING:\n    from pkg.typed_back import T\n")
    (package / "typed_back.py").write_text("from pkg import typed\nT = int\n")
    (package / "rel.py").write_text("from . import rel_back\n")
    (package / "rel_back.py").write_text("from .rel import x\n")
    assert import_cycles(tmp_path, ("pkg",)) == [["pkg.high", "pkg.low"],
                                                  ["pkg.rel", "pkg.rel_back"]]
