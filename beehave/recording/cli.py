"""``beehave replay``, ``beehave inspect``, ``beehave plot``, and ``--record`` for ``run``.

Exit status as for every ``beehave`` command: 0 ok, 1 a failure while running (for
``replay``: the replay diverged from the recording), 2 bad arguments, configuration or
recording (missing, not MCAP, lacking the channels a replay needs) -- also a damaged
recording: each tool does what it can with the intact part, names the damaged parts and
exits 2.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

from beehave.errors import BeehaveError, RecordingError

if TYPE_CHECKING:
    from beehave.recording.recorder import Recorder
    from beehave.recording.replay import ReplayResult
    from beehave.robot import Robot


def _fail(command: str, exc: BaseException | str) -> int:
    print(f"beehave {command}: {exc}", file=sys.stderr, flush=True)
    return 2


def speed_arg(text: str) -> float | None:
    """``1``, ``N`` (times real time) or ``max`` (as fast as the logics keep up: None)."""
    if text.strip().lower() == "max":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 1, a factor N or 'max', got {text!r}") \
            from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite factor > 0 or 'max', got "
                                         f"{text!r}")
    return value


def _time_arg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds since the start of the "
                                         f"recording, got {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


# ---- beehave run --record / beehave demo --record ----------------------------------------

def start_recording(path: str | Path, robots: list[Robot]) -> Recorder:
    """A started :class:`Recorder` into ``path`` with ``robots`` attached (each under its
    namespace), sized by the first robot's ``recording:`` options. Call it before the
    robots start, and :func:`robots_started` once they run."""
    from beehave.recording.recorder import Recorder

    options = robots[0].config.recording if robots else None
    recorder = Recorder(path, queue_size=options.queue_size if options else 100_000,
                        max_file_mb=options.max_file_mb if options else None)
    recorder.start()
    try:
        for robot in robots:
            recorder.attach_robot(robot)
    except BaseException:
        recorder.close()
        raise
    return recorder


def robots_started(recorder: Recorder, robots: list[Robot]) -> None:
    """Record the ROS 2 topics of the ``robots`` (their nodes exist now): those of their
    configurations, and every topic their behaviours subscribe to from now on (what a
    replay of the high level feeds them, :mod:`beehave.recording.inputs`)."""
    from beehave.recording.inputs import attach_behavior_inputs

    for robot in robots:
        if robot.low is not None and robot.low.hals.node is not None:
            recorder.attach_ros_topics(robot)  # the behaviours' inputs too
        else:
            attach_behavior_inputs(recorder, robot)


def finish_recording(recorder: Recorder) -> str:
    """Close ``recorder``; one line saying what was written (and lost)."""
    stats = recorder.close()
    files = ", ".join(str(f) for f in stats.files)
    lost = f"; {stats.dropped} DROPPED (disk too slow)" if stats.dropped else ""
    return f"recorded {stats.written} messages into {files}{lost}"


# ---- beehave replay ---------------------------------------------------------------------

def replay_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="beehave replay",
        description="Run a robot's logics and behaviours on a recording: its HALs replaced "
                    "by a replay source writing the recorded values into the blackboard, its "
                    "behaviours fed the recorded topics and switch requests, at the recorded "
                    "times (sim time when recorded on it); HAL commands and published "
                    "messages captured, not sent, and no ROS node made. Compares the logics' "
                    "outputs and switches and the behaviours' switches, starts and ends with "
                    "the recording and reports the first divergence (exit 1). "
                    "docs/recording.md")
    parser.add_argument("recording", metavar="FILE.mcap")
    parser.add_argument("--robot", required=True, metavar="ROBOT.yaml",
                        help="the robot's configuration (its logics and HALs)")
    parser.add_argument("--prefix", default=None, metavar="NAME",
                        help="the robot in the recording (default: the configuration's "
                             "namespace)")
    parser.add_argument("--speed", type=speed_arg, default=1.0, metavar="1|N|max",
                        help="1: real time (default), N: N times faster, max: as fast as "
                             "the logics keep up")
    parser.add_argument("--from", dest="from_s", type=_time_arg, default=None, metavar="T",
                        help="start at T seconds into the recording")
    parser.add_argument("--to", dest="to_s", type=_time_arg, default=None, metavar="T",
                        help="stop at T seconds into the recording")
    parser.add_argument("--low-only", action="store_true",
                        help="replay the logics alone, not the behaviours")
    args = parser.parse_args(argv)
    if args.from_s is not None and args.to_s is not None and args.to_s <= args.from_s:
        return _fail("replay", f"--to ({args.to_s}) must be after --from ({args.from_s})")
    from beehave.config import load_config
    from beehave.recording.replay import replay

    try:
        config = load_config(args.robot)
        result = replay(args.recording, config, prefix=args.prefix, speed=args.speed,
                        from_s=args.from_s, to_s=args.to_s,
                        high=False if args.low_only else None)
    except BeehaveError as exc:
        return _fail("replay", exc)
    print(describe_replay(result), flush=True)
    if result.divergence is not None:
        return 1
    return 2 if result.damaged else 0


def describe_replay(result: ReplayResult) -> str:
    clock = "sim time" if result.sim_time else "wall time"
    levels = "logics and behaviours" if result.high else "logics"
    lines = [f"replayed {levels}: {result.span_s:.2f} s ({clock}) in {result.wall_s:.2f} s "
             f"(x{result.speedup:.1f}): {result.fed} inputs, {len(result.outputs)} outputs "
             f"(recorded: {len(result.expected)})"]
    if result.high:
        counts = Counter(c.topic for c in result.commands)
        shown = ", ".join(f"{topic} x{n}" for topic, n in sorted(counts.items())) or "none"
        lines.append(f"captured, not sent: {len(result.commands)} message(s): {shown}")
    lines += [f"warning: {w}" for w in result.warnings]
    if result.divergence is None:
        what = ("logic outputs, logic and behaviour switches, behaviours and actions"
                if result.high else "logic outputs and switches")
        upto = f" up to t={result.cut_s:.3f} s" if result.cut_s is not None else ""
        if result.damaged:
            lines.append(f"INCOMPLETE: the same {what} as recorded{upto}, but the "
                         "recording is damaged after it (exit 2)")
        else:
            lines.append(f"deterministic: the same {what} as recorded{upto}")
    else:
        lines.append(f"DIVERGED: {result.divergence}")
    return "\n".join(lines)


# ---- beehave inspect --------------------------------------------------------------------

def _recording_parser(prog: str, description: str, *,
                      robot_help: str) -> argparse.ArgumentParser:
    """The arguments ``inspect`` and ``plot`` share: the recording and ``--robot``."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("recording", metavar="FILE.mcap")
    parser.add_argument("--robot", action="append", default=None, metavar="NAME",
                        help=robot_help)
    return parser


_TIMELINE_KINDS = {"started", "ended", "stuck", "switch_requested", "switch_completed",
                   "switch_rejected", "fallback", "lock_rejected", "lock_preempted",
                   "safe_state_ran", "safe_state_failed", "restarted", "loop_blocked"}


def inspect_main(argv: list[str]) -> int:
    parser = _recording_parser(
        "beehave inspect",
        "What a recording holds: its channels with their message counts, its duration, "
        "losses, and the event timeline (behaviours, actions, logic switches, locks, STUCK).",
        robot_help="only this robot's events (repeatable)")
    parser.add_argument("--limit", type=int, default=200, metavar="N",
                        help="show at most N timeline lines (default 200; 0: none)")
    parser.add_argument("--at", dest="at_s", type=_time_arg, default=None, metavar="T",
                        help="instead: what each robot ran, held and knew at T seconds "
                             "(wall time since the start): behaviour, logic, running items, "
                             "type locks, blackboard (what `beehave view` shows at T)")
    args = parser.parse_args(argv)
    if args.at_s is not None:
        return _inspect_at(args.recording, args.at_s, args.robot)
    from rich.console import Console
    from rich.table import Table

    from beehave.recording import schema
    from beehave.recording.reader import read_recording

    try:
        rec = read_recording(args.recording)
        unknown = [r for r in args.robot or [] if r not in rec.prefixes]
        if unknown:
            raise RecordingError(f"no robot {unknown} in {args.recording}; robots recorded: "
                                 f"{', '.join(map(repr, rec.prefixes)) or 'none'}")
    except BeehaveError as exc:
        return _fail("inspect", exc)
    console = Console(width=max(100, Console().width))
    files = ", ".join(str(f) for f in rec.files)
    console.print(f"[bold]{files}[/]: {len(rec.messages)} messages, {rec.duration_s:.2f} s, "
                  f"robots: {', '.join(rec.prefixes) or '-'}")
    if rec.truncated:
        console.print("[yellow]truncated[/]: the recording process died; read up to its "
                      "last complete chunk")
    for damage in rec.describe_damage():
        console.print(f"[red]DAMAGED[/]: {damage}", highlight=False)
    if rec.dropped():
        console.print(f"[red]{rec.dropped()} message(s) dropped[/] while recording (disk "
                      "slower than the robot)")
    table = Table(title="channels")
    for col in ("topic", "encoding", "schema", "messages", "per s"):
        table.add_column(col, justify="right" if col in ("messages", "per s") else "left")
    for topic, info in sorted(rec.channels.items()):
        rate = info.count / rec.duration_s if rec.duration_s > 0 else 0.0
        table.add_row(topic, info.encoding, info.schema_name, str(info.count), f"{rate:.1f}")
    console.print(table)
    status = 2 if rec.damaged else 0  # what is shown is all there is, but not all there was
    if args.limit <= 0:
        return status
    robots = args.robot or rec.prefixes
    topics = {schema.topic(p, c): p for p in robots
              for c in (schema.EVENTS_HIGH, schema.EVENTS_LOW)}
    shown = 0
    console.rule("event timeline (wall seconds since the start of the recording)")
    events = [m for m in rec.messages if m.topic in topics]
    for m in events:
        data = m.data
        if data["kind"] not in _TIMELINE_KINDS or data["subject"].startswith("blackboard:"):
            continue
        if shown >= args.limit:
            console.print(f"… {len(events) - shown} more (--limit)")
            break
        level = "high" if m.topic.endswith("high") else "low "
        t = (m.log_time_ns - rec.start_ns) / 1e9
        state = f" {data['status']}" if data["status"] else ""
        error = f"  [red]{data['error']}[/]" if data["error"] else ""
        source = data["detail"].get("source") if data["kind"] == "switch_requested" else None
        asked = f" (asked by {source})" if source not in (None, "external") else ""
        console.print(f"{t:9.3f}  {topics[m.topic]:<10} {level} {data['kind']:<17} "
                      f"{data['subject']}{state}{error}{asked}", highlight=False)
        shown += 1
    return status


def _inspect_at(path: str, at_s: float, robots: list[str] | None) -> int:
    from beehave.recording.reader import read_recording
    from beehave.recording.timeline import RecordingTimeline

    try:
        rec = read_recording(path)
        timeline = RecordingTimeline(rec)
        for name in robots or []:
            timeline.robot(name)
        lines = timeline.describe_at(at_s, robots)
    except BeehaveError as exc:
        return _fail("inspect", exc)
    print("\n".join(lines), flush=True)
    # What is missing, on stderr (stdout stays one fact per line): exit 2 says it too.
    intact_s = (rec.intact_until_ns - rec.start_ns) / 1e9
    if rec.truncated:
        print(f"beehave inspect: truncated: the recording process died; read up to its last "
              f"complete chunk, nothing missing before t={intact_s:.3f} s", file=sys.stderr)
    for damage in rec.describe_damage():
        print(f"beehave inspect: DAMAGED: {damage}", file=sys.stderr)
    if (rec.damaged or rec.truncated) and at_s >= intact_s:
        print(f"beehave inspect: t={at_s:g} s is after t={intact_s:.3f} s: what is shown "
              f"may lack what the lost part held", file=sys.stderr, flush=True)
    return 2 if rec.damaged else 0


# ---- beehave view -----------------------------------------------------------------------

def view_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="beehave view",
        description="Serve a recording with the live web view's page: play, pause, speed, "
                    "scrub, the same panels and plots, for each robot recorded. Read-only: "
                    "switch, stop, pause and resume are refused (405). docs/http.md")
    parser.add_argument("recording", metavar="FILE.mcap")
    parser.add_argument("--host", default="127.0.0.1",
                        help="the address to listen on (default 127.0.0.1: this machine "
                             "only; any other needs the token, printed at start)")
    parser.add_argument("--port", type=int, default=8080,
                        help="the port (default 8080; 0 picks a free one)")
    args = parser.parse_args(argv)
    import gc
    import signal
    import threading

    from beehave.interfaces.http import HttpServer
    from beehave.recording.reader import read_recording
    from beehave.recording.timeline import RecordingTimeline

    try:
        rec = read_recording(args.recording)
        timeline = RecordingTimeline(rec)
        # The recording's objects live as long as the server: out of the collector's way
        # (a full collection over a 30-minute recording's messages paused a scrub step
        # for half a second).
        gc.collect()
        gc.freeze()
        server = HttpServer({}, host=args.host, port=args.port, recording=timeline)
        server.start()
    except BeehaveError as exc:
        return _fail("view", exc)
    robots = ", ".join(timeline.robots) or "-"
    print(f"beehave: recording {args.recording} ({timeline.duration_s:.1f} s, robots: "
          f"{robots}) at {server.url}", flush=True)
    for damage in rec.describe_damage():
        print(f"DAMAGED: {damage}", flush=True)
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    try:
        done.wait()
    finally:
        server.stop()
    print("beehave view: stopped", flush=True)
    return 0


# ---- beehave plot -----------------------------------------------------------------------

def plot_main(argv: list[str]) -> int:
    parser = _recording_parser(
        "beehave plot",
        "A recording as a picture: a Gantt chart of the behaviours, actions and logics of "
        "each robot (coloured by outcome, switches marked) with blackboard series underneath.",
        robot_help="only this robot (repeatable; default: every robot)")
    parser.add_argument("-o", "--out", required=True, metavar="OUT.png",
                        help="the picture to write (.png, .svg or .pdf)")
    parser.add_argument("--series", action="append", default=None, metavar="KEY",
                        help="a blackboard key to plot under the chart (repeatable; default: "
                             "speed, battery, front distance, lift height where recorded)")
    args = parser.parse_args(argv)
    if Path(args.out).suffix.lower() not in (".png", ".svg", ".pdf"):
        return _fail("plot", f"-o {args.out!r}: the picture must end in .png, .svg or .pdf")
    from beehave.recording.plot import plot
    from beehave.recording.reader import read_recording

    try:
        rec = read_recording(args.recording)
        out = plot(rec, args.out, robots=args.robot, keys=args.series)
    except BeehaveError as exc:
        return _fail("plot", exc)
    print(f"wrote {out}", flush=True)
    if rec.truncated:
        print("truncated: the recording process died; drawn up to its last complete chunk",
              flush=True)
    for damage in rec.describe_damage():
        print(f"DAMAGED: {damage}", flush=True)
    return 2 if rec.damaged else 0
