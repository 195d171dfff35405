"""Run the benchmarks: ``python -m benchmarks`` (all) or ``python -m benchmarks NAME``.

Each module ``benchmarks/bench_<name>.py`` has ``main() -> list[dict]``. Exit status is 0
even when a target is missed: the JSON lines say so (``"ok": false``); CI does not gate on
timing because these machines are noisy.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys

import benchmarks


def main(argv: list[str]) -> int:
    names = sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules(benchmarks.__path__)
                   if m.name.startswith("bench_"))
    wanted = argv or names
    unknown = [w for w in wanted if w not in names]
    if unknown:
        print(f"unknown benchmark(s) {unknown}; available: {names}", file=sys.stderr)
        return 2
    missed = 0
    for name in wanted:
        print(f"# {name}", file=sys.stderr, flush=True)
        rows = importlib.import_module(f"benchmarks.bench_{name}").main()
        missed += sum(1 for r in rows if r.get("ok") is False)
    print(f"# {missed} target(s) missed", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
