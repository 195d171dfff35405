"""The ``beehave`` command line: ``beehave demo``."""

from __future__ import annotations

import argparse
import logging
import sys


def _demo(_: argparse.Namespace) -> int:
    from rich.console import Console

    # The demos live with the ready-made behaviours, not in the framework.
    from behaviours.demo import run_highlevel_demo

    console = Console()
    console.rule("[bold]beehave — high level: behaviours, actions, type locks, switching")
    problems = run_highlevel_demo(console)
    try:
        from behaviours.lowlevel_demo import run_lowlevel_demo
    except ImportError as exc:  # pragma: no cover - shipped together
        problems.append(f"low-level demo missing: {exc}")
    else:
        if not run_lowlevel_demo(console):
            problems.append("the low-level demo did not show what it should")
    if problems:
        for problem in problems:
            console.print(f"[red]FAILED:[/] {problem}")
        return 1
    console.print("[green]demo OK[/]: every step was checked")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="beehave", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log beehave events")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="run the console demo of both managers")
    demo.set_defaults(func=_demo)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    code: int = args.func(args)
    return code


if __name__ == "__main__":
    sys.exit(main())
