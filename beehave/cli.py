"""The ``beehave`` command line: ``demo``, ``run``, ``sim``, ``graph``."""

from __future__ import annotations

import argparse
import logging
import sys


def _demo(args: argparse.Namespace) -> int:
    from pathlib import Path

    from rich.console import Console

    console = Console()
    if not args.console:
        # The demos live with the ready-made behaviours, not in the framework.
        from behaviours.demos.warehouse import run_sim_demo

        console.rule("[bold]beehave — EMILI and Kobuki in the simulated warehouse")
        speed = None if args.fast else args.real_time_factor
        sim_problems = run_sim_demo(console, real_time_factor=speed, out_dir=Path(args.out))
        for problem in sim_problems:
            console.print(f"[red]FAILED:[/] {problem}")
        if sim_problems:
            return 1
        console.print("[green]demo OK[/]: every goal was reached in the physics")
        return 0

    from behaviours.demos.console import run_highlevel_demo

    console.rule("[bold]beehave — high level: behaviours, actions, type locks, switching")
    problems = run_highlevel_demo(console)
    try:
        from behaviours.demos.lowlevel import run_lowlevel_demo
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


def _run(args: argparse.Namespace) -> int:
    import signal
    import threading

    from beehave.config import load_config
    from beehave.errors import BeehaveError
    from beehave.robot import Robot

    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        logging.getLogger("beehave").info("signal %d: shutting down", signum)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        config = load_config(args.config)
        robot = Robot(config, only=args.only)
    except BeehaveError as exc:
        print(f"beehave run: {exc}", file=sys.stderr)
        return 2
    with robot:
        parts = "high and low level" if args.only is None else f"{args.only} level only"
        print(f"beehave: robot {config.namespace!r} running ({parts}); Ctrl-C to stop",
              flush=True)
        stop.wait(args.duration_s)
    print("beehave: stopped cleanly", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="beehave", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log beehave events")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="EMILI and Kobuki in the simulated warehouse "
                                       "(--console: the managers alone, no simulation)")
    demo.add_argument("--real-time-factor", type=float, default=1.0,
                      help="simulation speed (1 = real time)")
    demo.add_argument("--fast", action="store_true", help="simulate as fast as possible")
    demo.add_argument("--out", default="out", help="where to write the picture")
    demo.add_argument("--console", action="store_true",
                      help="the console demo of the two managers, without simulation")
    demo.set_defaults(func=_demo)
    run = sub.add_parser("run", help="run a robot from its configuration file (ROS 2)")
    run.add_argument("config", help="the robot configuration (YAML)")
    run.add_argument("--only", choices=["high", "low"], default=None,
                     help="run one manager only (the other runs elsewhere)")
    run.add_argument("--duration-s", type=float, default=None,
                     help="stop after this many seconds (default: until Ctrl-C/SIGTERM)")
    run.set_defaults(func=_run)
    graph = sub.add_parser("graph", add_help=False,
                           help="render a behaviour's state machine or tree (see graph -h)")
    graph.set_defaults(func=None)
    sim = sub.add_parser("sim", add_help=False,
                         help="run the simulation and its ROS 2 node (see sim -h)")
    sim.set_defaults(func=None)
    argv = sys.argv[1:] if argv is None else argv
    # Import paths in configuration files and specs are looked up from the current
    # directory too, as `python -m` does.
    if "" not in sys.path and "." not in sys.path:
        sys.path.insert(0, "")
    if argv and argv[0] == "graph":  # its own parser, with its own --help
        from beehave.engines.graph import graph_main

        return graph_main(argv[1:])
    if argv and argv[0] == "sim":
        from beehave.errors import BeehaveError
        from beehave.simulation import load_simulator

        try:
            simulator = load_simulator()
        except BeehaveError as exc:
            print(f"beehave sim: {exc}", file=sys.stderr)
            return 2
        return simulator.main(argv[1:])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    code: int = args.func(args)
    return code


if __name__ == "__main__":
    sys.exit(main())
