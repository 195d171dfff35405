"""A recording as a timeline (beehave.recording.timeline): what each robot ran, held and
knew at any moment, read as ``beehave view`` and ``beehave inspect --at`` read it. The
rules as a table: after each recorded event, the behaviour, the running items, the type
locks, STUCK items and the pause."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from beehave.blackboard import Blackboard
from beehave.errors import RecordingError
from beehave.events import Event, EventBus, EventKind
from beehave.recording import Recorder, read_recording
from beehave.recording.timeline import RecordingTimeline
from beehave.testing import WALL_TIMEOUT_S

ROOT = Path(__file__).resolve().parent.parent

# (event, behaviour, running paths, locks, stuck, paused) after each high-level event
HIGH: list[tuple[tuple[Any, ...], str | None, list[str], dict[str, str], list[str], bool]] = [
    ((EventKind.SWITCH_COMPLETED, "tour", None, {}), "tour", [], {}, [], False),
    ((EventKind.STARTED, "tour", "RUNNING", {}), "tour", ["tour"], {}, [], False),
    ((EventKind.STARTED, "tour/drive", "RUNNING", {"action_type": "driving"}), "tour",
     ["tour", "tour/drive"], {"driving": "tour/drive"}, [], False),
    ((EventKind.STARTED, "tour/sub", "RUNNING", {}), "tour",
     ["tour", "tour/drive", "tour/sub"], {"driving": "tour/drive"}, [], False),
    ((EventKind.STARTED, "tour/sub/lift", "RUNNING", {"action_type": "lifting"}), "tour",
     ["tour", "tour/drive", "tour/sub", "tour/sub/lift"],
     {"driving": "tour/drive", "lifting": "tour/sub/lift"}, [], False),
    ((EventKind.PAUSED, "tour", None, {}), "tour",
     ["tour", "tour/drive", "tour/sub", "tour/sub/lift"],
     {"driving": "tour/drive", "lifting": "tour/sub/lift"}, [], True),
    ((EventKind.STUCK, "tour/sub/lift", "STUCK", {}), "tour",
     ["tour", "tour/drive", "tour/sub", "tour/sub/lift"],
     {"driving": "tour/drive", "lifting": "tour/sub/lift"}, ["tour/sub/lift"], True),
    ((EventKind.RESUMED, "tour", None, {}), "tour",
     ["tour", "tour/drive", "tour/sub", "tour/sub/lift"],
     {"driving": "tour/drive", "lifting": "tour/sub/lift"}, ["tour/sub/lift"], False),
    # the parent ends; its STUCK action holds its lock until its thread ends
    ((EventKind.ENDED, "tour/sub", "INTERRUPTED", {}), "tour",
     ["tour", "tour/drive", "tour/sub/lift"],
     {"driving": "tour/drive", "lifting": "tour/sub/lift"}, ["tour/sub/lift"], False),
    ((EventKind.STUCK_RELEASED, "tour/sub/lift", None, {}), "tour",
     ["tour", "tour/drive"], {"driving": "tour/drive"}, [], False),
    ((EventKind.ENDED, "tour", "INTERRUPTED", {}), "tour", [], {}, [], False),
    ((EventKind.SWITCH_COMPLETED, "idle", None, {}), "idle", [], {}, [], False),
    ((EventKind.STARTED, "idle", "RUNNING", {}), "idle", ["idle"], {}, [], False),
]


@pytest.fixture
def recorded(tmp_path: Path) -> Path:
    path = tmp_path / "timeline.mcap"
    high, low, board = EventBus(), EventBus(), Blackboard()
    with Recorder(path, flush_period_s=0.05) as recorder:
        recorder.attach_events(high, prefix="r1", level="high")
        recorder.attach_events(low, prefix="r1", level="low")
        recorder.attach_blackboard(board, prefix="r1")
        board.set("speed_mps", 0.5, writer="hal:odometry")
        board.set("mode", "auto", writer="test")
        for (kind, subject, status, detail), *_ in HIGH:
            high.emit(Event(kind, subject, status, detail=detail))
        board.set("speed_mps", 0.0, writer="hal:odometry")
        board.mark_stale(pattern="mode")
        low.emit(Event(EventKind.STARTED, "hal:odometry", "RUNNING"))
        low.emit(Event(EventKind.SWITCH_COMPLETED, "leds"))
        low.emit(Event(EventKind.STARTED, "leds", "RUNNING"))
    return path


def _at(timeline: RecordingTimeline, t_ns: int) -> float:
    return (t_ns - timeline.start_ns) / 1e9


def test_after_each_event_the_timeline_says_what_ran_held_and_was_paused(
        recorded: Path) -> None:
    rec = read_recording(recorded)
    timeline = RecordingTimeline(rec)
    times = [m.log_time_ns for m in rec.of("/r1/beehave/events/high")]
    assert len(times) == len(HIGH)
    for t_ns in times:
        # Two events recorded in the same nanosecond: the moment is after both.
        last = max(j for j, t in enumerate(times) if t == t_ns)
        event, behaviour, running, locks, stuck, paused = HIGH[last]
        snap = timeline.snapshot_at("r1", _at(timeline, t_ns))
        got = (snap["behavior"], [r["path"] for r in snap["running"]], snap["locks"],
               snap["stuck"], snap["paused"])
        assert got == (behaviour, running, locks, stuck, paused), event
    # The tree is drawn from its root: a STUCK orphan is in the locks, not the tree.
    t = _at(timeline, times[8])
    tree = timeline.snapshot_at("r1", t)["tree"]
    assert [c["path"] for c in tree["children"]] == ["tour/drive"]
    assert tree["children"][0]["action_type"] == "driving"
    assert len(timeline.events_at("r1", t)) == 9


def test_the_blackboard_and_the_low_level_at_a_moment(recorded: Path) -> None:
    rec = read_recording(recorded)
    timeline = RecordingTimeline(rec)
    changes = rec.of("/r1/beehave/blackboard")
    first = _at(timeline, changes[0].log_time_ns)
    assert list(timeline.blackboard_at("r1", first)) == ["speed_mps"]
    end = timeline.duration_s
    board = timeline.blackboard_at("r1", end)
    assert board["speed_mps"]["value"] == 0.0 and board["speed_mps"]["writer"] == "hal:odometry"
    assert board["mode"]["stale"] is True and board["mode"]["value"] == "auto"
    low = timeline.snapshot_at("r1", end)
    assert low["logic"] == "leds" and low["low"]["logic"]["path"] == "leds"
    assert low["low"]["hals"]["loaded"] == {"odometry": {}}
    assert timeline.keys("r1") == ["speed_mps"]
    assert timeline.series("r1", ["speed_mps"])["speed_mps"]["v"] == [0.5, 0.0]


def test_the_end_asked_to_the_microsecond_is_the_end(recorded: Path) -> None:
    """The page plays to the end and asks for ``duration.toFixed(6)``, which may round up
    past it: that is the end, not "outside the recording" (a play stopped on that error)."""
    import math

    timeline = RecordingTimeline(read_recording(recorded))
    end = timeline.duration_s
    rounded_up = math.ceil(end * 1e6) / 1e6
    at_end, asked = timeline.state_at("r1", end), timeline.state_at("r1", rounded_up)
    asked["snapshot"].pop("t_s")  # the moment as asked
    at_end["snapshot"].pop("t_s")
    assert asked == at_end
    assert timeline.blackboard_at("r1", rounded_up) == timeline.blackboard_at("r1", end)
    with pytest.raises(RecordingError, match=r"outside the recording: 0 to"):
        timeline.state_at("r1", end + 2e-6)


def test_bad_questions_name_what_is_wrong_and_what_exists(recorded: Path) -> None:
    timeline = RecordingTimeline(read_recording(recorded))
    with pytest.raises(RecordingError, match=r"outside the recording: 0 to"):
        timeline.state_at("r1", timeline.duration_s + 5)
    with pytest.raises(RecordingError, match="finite"):
        timeline.state_at("r1", float("nan"))
    with pytest.raises(RecordingError, match="robots recorded: 'r1'"):
        timeline.state_at("r9", 0.0)
    with pytest.raises(RecordingError, match="numeric keys: speed_mps"):
        timeline.series("r1", ["mode/nope"])


def test_inspect_at_prints_the_moment_and_refuses_a_time_outside(recorded: Path) -> None:
    def inspect(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "beehave.cli", "inspect", str(recorded),
                               *args], cwd=ROOT, capture_output=True, text=True,
                              timeout=WALL_TIMEOUT_S)

    done = inspect("--at", "0")
    assert done.returncode == 0, done.stderr
    assert "r1 blackboard: speed_mps = 0.5 (writer hal:odometry)" in done.stdout
    bad = inspect("--at", "9999")
    assert bad.returncode == 2 and "t=9999 s is outside the recording: 0 to " in bad.stderr
    missing = subprocess.run([sys.executable, "-m", "beehave.cli", "view",
                              str(recorded.with_name("none.mcap")), "--port", "0"],
                             cwd=ROOT, capture_output=True, text=True,
                             timeout=WALL_TIMEOUT_S)
    assert missing.returncode == 2 and "does not exist" in missing.stderr



@pytest.mark.parametrize("text", ["nan", "inf", "-inf", "-1", "soon", "1e400", ""])
def test_inspect_at_refuses_a_time_that_is_no_moment_of_a_recording(
        recorded: Path, text: str, capsys: pytest.CaptureFixture[str]) -> None:
    from beehave.recording.cli import inspect_main

    with pytest.raises(SystemExit) as exited:
        inspect_main([str(recorded), f"--at={text}"])  # "--at -inf" reads as an option
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert "argument --at:" in err and repr(text) in err, err
    assert "seconds" in err, err


def test_inspect_at_on_a_cut_or_damaged_recording_says_what_is_missing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """stdout keeps one fact per line; stderr says the file was cut off or where it is
    damaged, and whether T lies after what was lost (exit 2 for damage, as ``inspect``)."""
    import random

    from mcap.reader import make_reader

    from beehave.recording.cli import inspect_main

    path = tmp_path / "blobs.mcap"
    board, rnd = Blackboard(), random.Random(5)
    with Recorder(path, flush_period_s=0.05) as recorder:
        recorder.attach_blackboard(board, prefix="r1")
        for i in range(8):  # incompressible: three chunks of 512 kB
            board.set("blob", rnd.randbytes(100_000).hex(), writer="test")
            board.set("n", i, writer="test")
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        f.seek(0)
        last_n = max(m.log_time for _, c, m in make_reader(f).iter_messages()
                     if c.topic.endswith("blackboard"))
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    # Damage the chunk before the one that holds n = 7 (the writer's timing decides the
    # layout: the recorder's closing messages may get a chunk of their own), never the
    # first: before the damage the file is complete, after it n = 7 is still there.
    holder = next(k for k, c in enumerate(chunks)
                  if c.message_start_time <= last_n <= c.message_end_time)
    assert holder >= 2, [(c.message_start_time, c.message_end_time) for c in chunks]
    data = bytearray(path.read_bytes())
    middle = chunks[holder - 1]
    at = middle.chunk_start_offset + middle.chunk_length // 2
    data[at:at + 2000] = random.Random(1).randbytes(2000)
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    last = chunks[-1]
    cut = tmp_path / "cut.mcap"  # the last chunk whole, no summary, no footer
    cut.write_bytes(path.read_bytes()[:last.chunk_start_offset + last.chunk_length])
    capsys.readouterr()

    assert inspect_main([str(damaged), "--at", "0"]) == 2
    out, err = capsys.readouterr()
    assert out.startswith("at 0.000 s") and "DAMAGED" not in out
    assert "beehave inspect: DAMAGED:" in err and "are lost" in err, err
    assert "may lack" not in err, err  # before the damage: complete
    end = repr(read_recording(damaged).duration_s)
    assert inspect_main([str(damaged), "--at", end]) == 2
    out, err = capsys.readouterr()
    assert "r1 blackboard: n = 7 (writer test)" in out
    assert "DAMAGED" in err and "may lack what the lost part held" in err, err

    assert read_recording(cut).truncated
    assert inspect_main([str(cut), "--at", "0"]) == 0
    out, err = capsys.readouterr()
    assert "r1 blackboard: blob = " in out
    assert "truncated: the recording process died" in err, err

# ---- decision engines: structure once, state on change ------------------------------------

def test_a_state_machine_changing_state_at_20_hz_is_recorded_with_its_structure_once(
        tmp_path: Path) -> None:
    """Read as an outside tool reads the file (the plain ``mcap`` reader, each message
    checked against the JSON Schema the file carries), then through the timeline."""
    import json

    import jsonschema
    from mcap.reader import make_reader

    from beehave import Action, HighLevelBehaviorManager
    from beehave.engines import EngineBehavior, State, StateMachineEngine, Transition
    from beehave.testing import wait_until

    class Step(Action):
        action_type = "driving"

        def run(self) -> None:
            self.sleep(0.05)  # 20 state changes a second
            board = self.manager.blackboard
            board.set("steps", board.get("steps", 0) + 1, writer="test")

    machine = StateMachineEngine(
        [State("a", start=Step), State("b", start=Step)],
        [Transition("a", "b", on="succeeded"), Transition("b", "a", on="succeeded")],
        initial="a")
    path = tmp_path / "sm.mcap"
    with HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
        hl.register("flip", EngineBehavior, engine=machine)
        with Recorder(path, flush_period_s=0.05) as recorder:
            recorder.attach_events(hl.events, prefix="r1", level="high")
            recorder.attach_engines(hl, prefix="r1")
            hl.switch("flip")
            assert wait_until(lambda: hl.blackboard.get("steps", 0) >= 20)
            hl.switch("idle")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {ch.topic: json.loads(summary.schemas[ch.schema_id].data)
                   for ch in summary.channels.values()}
        messages = [(ch.topic, json.loads(m.data)) for _, ch, m in
                    reader.iter_messages(log_time_order=True)]
    for topic, data in messages:
        if topic.startswith("/r1/beehave/engines/"):
            jsonschema.validate(data, schemas[topic])
    structures = [d for t, d in messages if t == "/r1/beehave/engines/structure"]
    states = [d for t, d in messages if t == "/r1/beehave/engines/state"]
    assert len(structures) == 1 and structures[0]["path"] == "flip"
    assert {s["name"] for s in structures[0]["structure"]["states"]} == {"a", "b"}
    assert states[-1]["engine"] is None  # the behaviour ended: no engine
    seen = {s["engine"]["state"] for s in states[:-1]}
    assert seen - {None} == {"a", "b"}  # None: the machine built, no state entered yet
    assert all(s["engine"]["structure_id"] == structures[0]["structure_id"]
               for s in states[:-1])
    # Recorded on change only: no two equal states in a row (a lap's last_transition
    # differs), and not more often than the machine changed.
    descs = [json.dumps(s["engine"], sort_keys=True) for s in states[:-1]]
    assert all(x != y for x, y in zip(descs, descs[1:], strict=False))
    steps = sum(1 for t, d in messages if t == "/r1/beehave/events/high"
                and d["kind"] == "started" and d["subject"].startswith("flip/Step"))
    assert len(states) - 1 <= steps + 1

    timeline = RecordingTimeline(read_recording(path))
    first = next(i for i, s in enumerate(states) if s["engine"]["state"] is not None)
    t_first = (timeline.robots["r1"].engine_times[first] - timeline.start_ns) / 1e9
    engines = timeline.engines_at("r1", t_first)
    assert [(e["path"], e["kind"], e["state"]) for e in engines] == [
        ("flip", "state_machine", states[first]["engine"]["state"])]
    assert timeline.snapshot_at("r1", t_first)["engines"] == engines
    assert [s["structure_id"] for s in timeline.structures("r1", t_first)] == \
        [structures[0]["structure_id"]]
    assert timeline.engines_at("r1", timeline.duration_s) == []
    line = f"r1 engine: flip (state_machine) state {states[first]['engine']['state']}"
    assert any(x.startswith(line) for x in timeline.describe_at(t_first))


def test_a_recording_without_engine_channels_has_no_engines(recorded: Path) -> None:
    timeline = RecordingTimeline(read_recording(recorded))
    assert timeline.engines_at("r1", timeline.duration_s) == []
    assert timeline.structures("r1") == []
    assert not any(" engine: " in line for line in timeline.describe_at(0.0))


def test_an_engine_that_cannot_describe_itself_does_not_hide_the_others(
        tmp_path: Path) -> None:
    """A user engine raising in ``describe()`` is skipped and named in
    ``Recorder.engine_errors``; the engine of the behaviour under it is still recorded."""
    from types import SimpleNamespace
    from typing import cast

    from beehave import HighLevelBehaviorManager

    class Broken:
        def describe(self) -> dict[str, Any]:
            raise ValueError("no state yet")

    class Steady:
        def describe(self) -> dict[str, Any]:
            return {"kind": "state_machine", "state": "s", "structure_id": "sid1"}

        def structure(self) -> dict[str, Any]:
            return {"kind": "state_machine", "states": [{"name": "s"}]}

    inner = SimpleNamespace(path="outer/inner", _engine=Steady(), children=[])
    high = SimpleNamespace(top=SimpleNamespace(path="outer", _engine=Broken(),
                                               children=[inner]))
    path = tmp_path / "broken.mcap"
    with Recorder(path, flush_period_s=0.05) as recorder:
        recorder.attach_engines(cast(HighLevelBehaviorManager, high), prefix="r1")
    errors = recorder.engine_errors
    assert list(errors) == ["outer"] and isinstance(errors["outer"], ValueError)
    rec = read_recording(path)
    states = [m.data for m in rec.of("/r1/beehave/engines/state")]
    assert states and all(s["path"] == "outer/inner" for s in states)
    assert states[0]["engine"]["state"] == "s"
    [structure] = [m.data for m in rec.of("/r1/beehave/engines/structure")]
    assert structure["structure_id"] == "sid1"


def test_the_engine_schemas_are_in_the_package_and_refuse_what_they_do_not_describe(
) -> None:
    """The JSON Schemas each engine channel carries (``beehave.recording.schema``) are
    valid JSON Schema, accept a tree's state and ``engine: null`` too, and refuse a message
    without its behaviour path or with an engine that is no object."""
    import jsonschema

    from beehave.recording import schema

    structure = schema.SCHEMAS[schema.CHANNEL_SCHEMA[schema.ENGINE_STRUCTURE]]
    state = schema.SCHEMAS[schema.CHANNEL_SCHEMA[schema.ENGINE_STATE]]
    for s in (structure, state):
        jsonschema.Draft202012Validator.check_schema(s)
    stamp = 1.7e9
    tree = {"kind": "behaviour_tree", "structure_id": "t1", "tick": 42,
            "nodes": [{"path": "root", "status": "RUNNING"}]}
    jsonschema.validate({"path": "patrol", "engine": tree, "stamp": stamp}, state)
    jsonschema.validate({"path": "patrol", "engine": None, "stamp": stamp}, state)
    jsonschema.validate({"path": "patrol", "structure_id": "t1", "stamp": stamp,
                         "structure": {"kind": "behaviour_tree", "nodes": []}}, structure)
    for bad in ({"engine": tree, "stamp": stamp}, {"path": "p", "engine": [], "stamp": stamp},
                {"path": "p", "engine": tree, "stamp": "now"}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, state)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"path": "p", "structure_id": "t1", "stamp": stamp,
                             "structure": "a tree"}, structure)


def test_a_message_without_its_schemas_fields_is_refused_naming_channel_and_field(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A file written by another tool (the plain ``mcap`` writer, the channels' beehave
    schemas) whose engine state lacks ``path``: ``inspect --at`` says which channel, when
    and what is missing, exit 2 (it was a KeyError traceback)."""
    import json

    from mcap.writer import Writer

    from beehave.recording import schema
    from beehave.recording.cli import inspect_main

    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start()
        ids = {}
        for channel in (schema.EVENTS_HIGH, schema.ENGINE_STATE):
            name = schema.CHANNEL_SCHEMA[channel]
            sid = writer.register_schema(name, "jsonschema", schema.schema_bytes(name))
            ids[channel] = writer.register_channel(schema.topic("r1", channel), "json", sid)
        event = {"kind": "started", "subject": "tour", "status": "RUNNING", "error": None,
                 "detail": {}, "stamp": 1.0}
        state = {"engine": {"kind": "state_machine", "state": "a"}, "stamp": 1.5}
        for t_ns, channel, data in ((10**9, schema.EVENTS_HIGH, event),
                                    (2 * 10**9, schema.ENGINE_STATE, state)):
            writer.add_message(ids[channel], log_time=t_ns, publish_time=t_ns,
                               data=json.dumps(data).encode())
        writer.finish()
    with pytest.raises(RecordingError, match=r"/r1/beehave/engines/state at t=1\.000 s: "
                       r"not a beehave\.EngineState message .*\(missing 'path'\)"):
        RecordingTimeline(read_recording(path))
    capsys.readouterr()
    assert inspect_main([str(path), "--at", "0"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and "beehave inspect: /r1/beehave/engines/state at t=1.000 s" in err
