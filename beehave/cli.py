"""The ``beehave`` command line: ``demo``, ``run``, ``broker``, ``sim``, ``graph``, ``fleet``,
``keys`` (the fleet authority of signed agents), and for recordings ``replay``,
``inspect``, ``plot``.

Exit status: 0 when everything went as asked, 1 when something failed while running
(a simulation, a robot, its shutdown), 2 for bad arguments or a bad configuration; the
message on stderr starts with ``beehave <command>:``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from beehave.recording.recorder import Recorder
    from beehave.robot import Robot

log = logging.getLogger("beehave.cli")

DESCRIPTION = """\
beehave: run robot behaviour (high level: behaviours and actions; low level: logics,
blackboard and HALs) on ROS 2, and try it on simulated EMILI and Kobuki robots.
"""

EPILOG = """\
exit status: 0 ok, 1 a failure while running, 2 bad arguments or configuration.
`beehave graph -h` and `beehave sim -h` describe their own options.
"""

#: Image suffixes that show a picture file was meant where ``--out`` wants a folder.
_PICTURE_SUFFIXES = (".png", ".svg", ".pdf", ".jpg", ".jpeg")


# ---- argument types: refuse what would crash or hang later ------------------------------

def seconds_arg(text: str) -> float:
    """An argparse ``type`` for a duration: finite, not negative and at most
    :data:`beehave.hal.MAX_DURATION_S` (checked by :func:`beehave.hal.check_duration_s`).
    ``inf`` or a huge value would overflow the wait and NaN never compares; "until Ctrl-C"
    is said by leaving the option out. Simulators' own parsers may use it too."""
    from beehave.errors import ConfigError
    from beehave.hal import MAX_DURATION_S, check_duration_s

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") \
            from None
    try:
        return check_duration_s("N", value, allow_zero=True)
    except ConfigError:
        raise argparse.ArgumentTypeError(
            f"expected a finite number of seconds >= 0 and at most {MAX_DURATION_S:g}, got "
            f"{text!r}; leave the option out to run until Ctrl-C or SIGTERM") from None


def factor_arg(text: str) -> float:
    """An argparse ``type`` for a real-time factor: positive and finite; "no pacing" is
    ``--fast``."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(
            f"expected a finite number > 0, got {text!r}; use --fast for no pacing")
    return value


def settle_heap() -> None:
    """A robot process, once started: collect the start-up garbage, then keep what is left
    (modules, schemas, configuration: tens of thousands of objects that live as long as
    the process) out of the collector's full passes (``gc.freeze``). A full collection
    otherwise walks all of it, 40-75 ms every few seconds of work — the tail of a VDA 5050
    order's acceptance (docs/benchmarks.md)."""
    import gc

    gc.collect()
    gc.freeze()


# ---- beehave demo -----------------------------------------------------------------------

def _demo(args: argparse.Namespace) -> int:
    from rich.console import Console

    console = Console()
    if args.broker is not None and not args.vda5050:
        print("beehave demo: --broker is for the VDA 5050 demo (--vda5050)", file=sys.stderr)
        return 2
    if args.console and args.vda5050:
        print("beehave demo: --console and --vda5050 are different demos; pick one",
              file=sys.stderr)
        return 2
    if args.console and args.http is not None:
        print("beehave demo: --http serves the simulated demo's robots; the console demo "
              "(--console) has none", file=sys.stderr)
        return 2
    if not args.console:
        out = Path(args.out)
        if out.suffix.lower() in _PICTURE_SUFFIXES:
            print(f"beehave demo: --out is a folder (the picture is written to "
                  f"FOLDER/demo.png), got the file name {args.out!r}", file=sys.stderr)
            return 2
        if args.vda5050:
            return _demo_vda5050(args, out)
        # The demos live with the ready-made behaviours, not in the framework.
        from behaviours.demos.warehouse import run_sim_demo

        console.rule("[bold]beehave — EMILI and Kobuki in the simulated warehouse")
        speed = None if args.fast else args.real_time_factor
        record = None if args.record is None else Path(args.record or out / "demo.mcap")
        if record is not None and record.suffix != ".mcap":
            print(f"beehave demo: --record {args.record!r}: a recording is an MCAP file, "
                  "name it *.mcap", file=sys.stderr)
            return 2
        sim_problems = run_sim_demo(console, real_time_factor=speed, out_dir=out,
                                    record=record, http=args.http)
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


def _demo_vda5050(args: argparse.Namespace, out: Path) -> int:
    """EMILI as a VDA 5050 AGV driven by a master over MQTT (docs/vda5050.md)."""
    if args.http is not None or args.record is not None:
        print("beehave demo: --vda5050 takes neither --http nor --record", file=sys.stderr)
        return 2
    from behaviours.demos.vda5050_master import scenario_exit

    return scenario_exit(out=out / "vda5050.png",
                         real_time_factor=None if args.fast else args.real_time_factor,
                         broker=args.broker)


# ---- beehave run ------------------------------------------------------------------------

def _is_config_error(exc: BaseException) -> bool:
    """Errors that mean "fix the configuration" (exit 2) rather than "it failed while
    running" (exit 1): a bad value, name, class or parameter, also when only found at
    start (an unknown world, a default behaviour whose constructor raises)."""
    from beehave.errors import ConfigError, InvalidParameters, NotASubclass, UnknownNameError

    return isinstance(exc, ConfigError | UnknownNameError | InvalidParameters | NotASubclass)


def _keys(args: argparse.Namespace) -> int:
    from beehave.agents import trust
    from beehave.errors import ConfigError

    try:
        if args.keys_command == "init":
            paths = trust.init_fleet(args.dir, force=args.force)
        else:
            paths = trust.issue(args.dir, args.name, days=args.days)
    except ConfigError as exc:
        print(f"beehave keys: {exc}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0


def _report(command: str, exc: BaseException, *, verbose: bool) -> None:
    """One message on stderr, notes included; the traceback only with ``-v`` (an error of
    beehave names what to fix; anything else is a bug whose traceback helps)."""
    from beehave.errors import BeehaveError

    text = str(exc) if isinstance(exc, BeehaveError) else f"{type(exc).__name__}: {exc}"
    for note in getattr(exc, "__notes__", ()):
        text += f"\n  {note}"
    print(f"beehave {command}: {text}", file=sys.stderr, flush=True)
    if verbose:
        log.error("traceback", exc_info=exc)
    elif not isinstance(exc, BeehaveError):
        print(f"beehave {command}: (run `beehave -v {command} …` for the traceback)",
              file=sys.stderr, flush=True)


def _run(args: argparse.Namespace) -> int:
    from beehave.config import load_config
    from beehave.errors import BeehaveError
    from beehave.robot import Robot

    stop = threading.Event()
    stopping = threading.Event()
    recorder: Recorder | None = None
    recording_failed = 0

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        if stopping.is_set():
            # A second Ctrl-C while the robot shuts down: the user wants out now. The
            # shutdown is bounded, but a blocked logic or hardware may still hold it.
            os.write(2, b"beehave run: second signal during shutdown: exiting at once; "
                        b"safe states may not all have run\n")
            os._exit(1)
        log.info("signal %d: shutting down", signum)
        stop.set()

    # Installed before the robot is built, so a Ctrl-C at any time ends in a clean stop.
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    phase = "start"
    try:
        try:
            config = load_config(args.config)
            _check_http_options(args, config.sim.simulator if config.sim else None)
            robot = Robot(config, only=args.only)
            recorder = _recording(args.record, robot)
        except BeehaveError as exc:  # nothing has started yet
            _report("run", exc, verbose=args.verbose)
            return 2
        with robot:
            phase = "run"
            if recorder is not None:
                from beehave.recording.cli import robots_started

                robots_started(recorder, [robot])
            parts = "high and low level" if args.only is None else f"{args.only} level only"
            settle_heap()
            print(f"beehave: robot {config.namespace!r} running ({parts}); Ctrl-C to stop",
                  flush=True)
            with _http_for_run(args, robot):
                stop.wait(args.duration_s)
                phase = "shutdown"
                stopping.set()
    except Exception as exc:  # the robot has been shut down (Robot.start/__exit__ do it)
        if phase == "shutdown":
            exc.add_note("(raised while shutting the robot down; everything else was "
                         "stopped)")
        _report("run", exc, verbose=args.verbose)
        return 2 if phase == "start" and _is_config_error(exc) else 1
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if recorder is not None:  # after the robot: its safe states are recorded too
            recording_failed = _close_recording(recorder, verbose=args.verbose)
    if recording_failed:
        return 1
    print("beehave: stopped cleanly", flush=True)
    return 0


# ---- beehave broker ---------------------------------------------------------------------

def _broker_address(text: str) -> tuple[str, int]:
    from behaviours.demos.vda5050_master import broker_address

    try:
        return broker_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def _broker(args: argparse.Namespace) -> int:
    """A local mosquitto on 127.0.0.1 with a generated configuration, for VDA 5050
    (docs/vda5050.md), until Ctrl-C or SIGTERM."""
    import subprocess

    from behaviours.demos.vda5050_master import MOSQUITTO, Broker

    if not Path(MOSQUITTO).is_file():
        print(f"beehave broker: mosquitto not found ({MOSQUITTO}); install it "
              "(`make setup`, Debian package mosquitto)", file=sys.stderr)
        return 2
    broker = Broker(args.port)
    try:
        broker.start()
    except RuntimeError as exc:
        print(f"beehave broker: {exc}", file=sys.stderr)
        broker.__exit__()
        return 1
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    print(f"beehave: MQTT broker on 127.0.0.1:{broker.port} (configuration "
          f"{broker.config}); Ctrl-C to stop", flush=True)
    try:
        assert broker.proc is not None
        while not stop.is_set():
            try:
                broker.proc.wait(timeout=0.2)
            except subprocess.TimeoutExpired:
                continue
            print(f"beehave broker: mosquitto exited ({broker.proc.returncode})",
                  file=sys.stderr)
            return 1
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        broker.__exit__()
    print("beehave: broker stopped", flush=True)
    return 0


def _recording(path: str | None, robot: Robot) -> Recorder | None:
    """``--record``: a started recorder with ``robot`` attached, or None."""
    if path is None:
        return None
    from beehave.recording.cli import start_recording

    return start_recording(path, [robot])


def _close_recording(recorder: Recorder, *, verbose: bool) -> int:
    from beehave.errors import BeehaveError
    from beehave.recording.cli import finish_recording

    try:
        print(f"beehave: {finish_recording(recorder)}", flush=True)
    except BeehaveError as exc:
        _report("run", exc, verbose=verbose)
        return 1
    return 0


# ---- --http: the HTTP/WebSocket interface and web view (docs/http.md) -------------------

def http_address_arg(text: str) -> tuple[str, int]:
    """An argparse ``type`` for ``[HOST:]PORT`` (imported when used: the server needs
    fastapi)."""
    from beehave.interfaces.http.server import address_arg

    return address_arg(text)


def _add_http_options(parser: argparse.ArgumentParser, *, world: bool) -> None:
    parser.add_argument(
        "--http", type=http_address_arg, default=None, metavar="[HOST:]PORT",
        help="serve the HTTP/WebSocket API and the live web view (docs/http.md) on "
             "HOST:PORT (default host 127.0.0.1; port 0 picks a free one). Another host "
             "needs a token: BEEHAVE_HTTP_TOKEN, else one is generated and printed")
    if world:
        parser.add_argument(
            "--world", default=None, metavar="WORLD",
            help="the world the web view draws: a world name as `beehave sim` and `sim: "
                 "world:` take it (warehouse), or a world YAML file (default: the "
                 "simulation's, when `sim:` runs it in this process)")


def _check_http_options(args: argparse.Namespace, simulator: str | None = None) -> None:
    """Refuse ``--http``/``--world`` combinations that cannot work, before anything starts
    (a :class:`~beehave.errors.ConfigError`: exit 2). ``simulator``: the configuration's
    (``sim: simulator:``), which knows the world names."""
    from beehave.errors import ConfigError

    if args.http is None:
        if args.world is not None:
            raise ConfigError("--world is the map of the web view: give --http too")
        return
    if args.only == "low":
        raise ConfigError("--http serves the high level's control plane: it cannot run "
                          "with --only low (serve it from the process that runs the high "
                          "level)")
    if args.world is not None:
        args.world_data = _read_world(args.world, simulator)


def _read_world(world_file: str, simulator: str | None = None) -> dict[str, Any]:
    """A world as plain data (the web view draws it; the simulator validates it): a YAML
    file, or a name that is no file (``warehouse``), which the simulator resolves as
    ``beehave sim`` and ``sim: world:`` do."""
    import yaml

    from beehave.errors import BeehaveError, ConfigError
    from beehave.simulation import DEFAULT, load_simulator

    path = Path(world_file)
    if not path.is_file() and "/" not in world_file and path.suffix not in (".yaml", ".yml"):
        name = simulator or DEFAULT
        loader = getattr(load_simulator(name), "world_data", None)
        if loader is None:
            raise ConfigError(f"--world {world_file}: no such file, and simulator {name!r} "
                              f"resolves no world names; give a world YAML file")
        try:
            data: dict[str, Any] = loader(world_file)
        except BeehaveError as exc:
            raise ConfigError(f"--world {world_file}: {exc}") from exc
        return data
    try:
        data = yaml.safe_load(Path(world_file).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"--world {world_file}: cannot read it: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get("floor"), dict):
        raise ConfigError(f"--world {world_file}: not a world (a mapping with 'floor', "
                          f"'walls', 'stations' …; see robots/worlds/warehouse.yaml)")
    return data


def _world_provider(robot: Robot, args: argparse.Namespace) -> dict[str, Any] | None:
    """The web view's map: ``--world``'s file, or the in-process simulation's world (any
    object with a pydantic ``model_dump``). The framework imports no simulator for it."""
    data: dict[str, Any] | None = getattr(args, "world_data", None)
    if data is not None:
        return data
    world = getattr(robot.sim, "world", None)
    dump = getattr(world, "model_dump", None)
    data = dump(mode="json") if callable(dump) else None
    return data if isinstance(data, dict) else None


@contextlib.contextmanager
def _http_for_run(args: argparse.Namespace, robot: Robot) -> Iterator[None]:
    """Serve ``robot`` over HTTP while the block runs, when ``--http`` was given."""
    if args.http is None:
        yield
        return
    from beehave.config import hal_names
    from beehave.errors import ConfigError
    from beehave.interfaces.http import HttpServer
    from beehave.interfaces.http.server import VIEW_HALS, hold_hals

    plane = robot.plane
    if plane is None:
        raise ConfigError("--http needs the high level in this process (not --only low)")
    host, port = args.http
    server = HttpServer(plane, host=host, port=port,
                        world=_world_provider(robot, args))
    server.start()
    with contextlib.ExitStack() as stack:
        stack.callback(server.stop)
        low = robot.low
        if low is not None:  # the map needs the pose even when no logic asks for it
            configured = set(hal_names(robot.config))
            stack.callback(hold_hals(low, [n for n in VIEW_HALS if n in configured]))
        _announce(server)
        yield


def _announce(server: object) -> None:
    url = getattr(server, "url", "")
    print(f"beehave: web view and API at {url} (OpenAPI schema: "
          f"{url.split('#')[0]}openapi.json)", flush=True)
    if getattr(server, "token_source", None) == "generated":
        print(f"beehave: token {getattr(server, 'token', '')} (send 'Authorization: Bearer "
              f"TOKEN'; set BEEHAVE_HTTP_TOKEN to choose one)", flush=True)


# ---- the parser -------------------------------------------------------------------------

def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="beehave", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="log at DEBUG level: switches, ends of behaviours and actions, "
                             "HAL loads, ROS 2 (put it before the command)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser(
        "demo", help="EMILI and Kobuki in the simulated warehouse, checking each step "
                     "(--console: the two managers alone, no simulation)",
        description="EMILI and Kobuki in the simulated warehouse: every step is checked, "
                    "a top-down picture is written to FOLDER/demo.png; exit 1 when a check "
                    "fails.")
    speed = demo.add_mutually_exclusive_group()
    speed.add_argument("--real-time-factor", type=factor_arg, default=1.0, metavar="X",
                       help="simulated seconds per wall-clock second (default: 1.0)")
    speed.add_argument("--fast", action="store_true",
                       help="simulate as fast as the machine goes (no pacing)")
    demo.add_argument("--out", default="out", metavar="FOLDER",
                      help="folder to write the top-down picture demo.png into "
                           "(created if needed; default: out)")
    demo.add_argument("--console", action="store_true",
                      help="the console demo of the two managers instead: no simulation, "
                           "no ROS 2")
    demo.add_argument("--record", nargs="?", const="", default=None, metavar="FILE.mcap",
                      help="record both robots into an MCAP file (default FOLDER/demo.mcap); "
                           "replay it with `beehave replay`")
    demo.add_argument("--vda5050", action="store_true",
                      help="EMILI takes VDA 5050 orders from a master over MQTT (pick, drop, "
                           "a cancelled order); picture FOLDER/vda5050.png (docs/vda5050.md)")
    demo.add_argument("--broker", type=_broker_address, default=None, metavar="HOST:PORT",
                      help="with --vda5050: a running MQTT broker (default: a local "
                           "mosquitto of the demo's own)")
    _add_http_options(demo, world=False)
    demo.set_defaults(func=_demo)
    run = sub.add_parser(
        "run", help="run a robot from its configuration file (ROS 2)",
        description="Run a robot's two managers as ROS 2 nodes from its configuration "
                    "file (docs/ros.md) until Ctrl-C or SIGTERM; prints `stopped cleanly` "
                    "once everything is shut down. A second Ctrl-C while it shuts down "
                    "exits at once (exit 1).")
    run.add_argument("config", metavar="CONFIG.yaml", help="the robot configuration (YAML)")
    run.add_argument("--only", choices=["high", "low"], default=None,
                     help="run one manager only (the other runs in another process)")
    run.add_argument("--duration-s", type=seconds_arg, default=None, metavar="N",
                     help="stop after N wall-clock seconds (default: until Ctrl-C/SIGTERM)")
    run.add_argument("--record", default=None, metavar="FILE.mcap",
                     help="record the blackboard, events, HAL commands and robot topics "
                          "into an MCAP file (docs/recording.md)")
    _add_http_options(run, world=True)
    run.set_defaults(func=_run)
    broker = sub.add_parser(
        "broker", help="a local MQTT broker (mosquitto) for VDA 5050 (docs/vda5050.md)",
        description="Start mosquitto on 127.0.0.1 with a generated configuration until "
                    "Ctrl-C or SIGTERM; robots with a vda5050: section connect to it.")
    broker.add_argument("--port", type=int, default=1883, metavar="N",
                        help="the port to listen on (default: 1883)")
    broker.set_defaults(func=_broker)
    keys = sub.add_parser(
        "keys", help="keys of signed agents: `keys init` makes the fleet authority, "
                     "`keys issue NAME` an agent's key and certificate (docs/agents.md)",
        description="The fleet authority of signed agents (docs/agents.md#trust-model): "
                    "`init` writes DIR/fleet.key (keep it off the robots) and DIR/fleet.pub "
                    "(every agent needs it); `issue NAME` writes DIR/NAME.key and "
                    "DIR/NAME.cert, signed by DIR/fleet.key.")
    keys_sub = keys.add_subparsers(dest="keys_command", required=True, metavar="init|issue")
    init = keys_sub.add_parser("init", help="create the fleet authority key pair")
    init.add_argument("--force", action="store_true",
                      help="replace an existing fleet.key (voids every certificate it issued)")
    issue = keys_sub.add_parser("issue", help="a key and certificate for agent NAME")
    issue.add_argument("name", metavar="NAME", help="the agent name the certificate binds")
    issue.add_argument("--days", type=seconds_arg, default=365.0, metavar="N",
                       help="the certificate's validity in days (default: 365)")
    for p in (init, issue):
        p.add_argument("--dir", default="keys", metavar="DIR",
                       help="the folder of the fleet's keys (default: keys)")
    keys.set_defaults(func=_keys)
    # graph and sim parse their own arguments (see main); these entries are for -h.
    sub.add_parser("graph", add_help=False,
                   help="render a behaviour's state machine, tree or network to a picture "
                        "(beehave graph -h)")
    sub.add_parser("sim", add_help=False,
                   help="run a simulated world and put its robots on ROS 2 (beehave sim -h)")
    sub.add_parser("fleet", add_help=False,
                   help="multi-robot scenarios, every agent in its own process, checked in "
                        "the physics: the factory fleet (default), --scenario serve (a "
                        "market with coalitions), --scenario follow|handover|droid (MAVLink) "
                        "(beehave fleet -h)")
    for name, text in _RECORDING_COMMANDS.items():
        sub.add_parser(name, add_help=False, help=text)
    return parser


def _split(argv: Sequence[str]) -> int | None:
    """Index of the command in ``argv``: the first word that is not a global option.
    The global options are flags without a value, so nothing else can come between."""
    for i, arg in enumerate(argv):
        if arg == "--":
            return i + 1 if i + 1 < len(argv) else None
        if not arg.startswith("-"):
            return i
    return None


def _graph(argv: list[str]) -> int:
    from beehave.engines.graph import graph_main

    return graph_main(argv)


def _sim(argv: list[str]) -> int:
    from beehave.errors import BeehaveError
    from beehave.simulation import load_simulator

    try:
        simulator = load_simulator()
    except BeehaveError as exc:
        print(f"beehave sim: {exc}", file=sys.stderr)
        return 2
    return simulator.main(argv)


def _fleet(argv: list[str]) -> int:
    # The scenario lives with the ready-made behaviours, not in the framework.
    from behaviours.demos.fleet import main as fleet_main

    return fleet_main(argv)


# ---- recordings: beehave replay | inspect | plot (beehave/recording/cli.py) -----------------

def _recording_command(name: str) -> Callable[[list[str]], int]:
    """``beehave replay|inspect|plot``: ``beehave.recording.cli.<name>_main``, imported only
    when the command runs (it needs the ``record`` extra)."""
    def command(argv: list[str]) -> int:
        import importlib

        main: Callable[[list[str]], int] = getattr(
            importlib.import_module("beehave.recording.cli"), f"{name}_main")
        return main(argv)

    return command


_RECORDING_COMMANDS: dict[str, str] = {
    "replay": "run a robot's logics and behaviours again on a recording and check they "
              "decide the same (beehave replay -h)",
    "inspect": "a recording's channels, counts, duration and event timeline",
    "view": "serve a recording with the web view: play, pause, scrub, plots "
            "(beehave view -h)",
    "plot": "a recording as a Gantt chart of behaviours and actions with blackboard series "
            "(beehave plot -h)",
}


#: Commands that parse their own arguments (with their own ``-h``).
_OWN_PARSERS: dict[str, Callable[[list[str]], int]] = {
    "graph": _graph, "sim": _sim, "fleet": _fleet,
    **{name: _recording_command(name) for name in _RECORDING_COMMANDS}}


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # Import paths in configuration files and specs are looked up from the current
    # directory too, as `python -m` does.
    if "" not in sys.path and "." not in sys.path:
        sys.path.insert(0, "")
    at = _split(argv)
    command = argv[at] if at is not None else None
    if command in _OWN_PARSERS:
        assert at is not None and command is not None
        # Global options first (-v, -h), then everything after the command goes to the
        # command's own parser untouched.
        args = parser.parse_args([*argv[:at], command])
        _configure_logging(verbose=args.verbose)
        return _OWN_PARSERS[command](argv[at + 1:])
    args = parser.parse_args(argv)
    _configure_logging(verbose=args.verbose)
    code: int = args.func(args)
    return code


def _configure_logging(*, verbose: bool) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")


if __name__ == "__main__":
    sys.exit(main())
