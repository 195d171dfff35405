"""Replay determinism on the main demo: record `beehave demo --fast --record` once, replay
each robot's logics *and behaviours* on the recording at `--speed max`, and get the same
LED colours, display texts, logic switches, behaviour switches and behaviour/action
lifecycles as live -- with nothing sent to ROS. A behaviour changed on purpose is caught at
its first divergence; a recording without a channel the behaviours read is refused naming
it. Also checks what `beehave inspect` and `beehave plot` make of the recording."""

from __future__ import annotations

import io
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("pybullet")
pytest.importorskip("rclpy")

import yaml  # noqa: E402
from rich.console import Console  # noqa: E402

from beehave.cli import main  # noqa: E402
from beehave.config import RobotConfig, load_config, parse_config  # noqa: E402
from beehave.errors import RecordingError  # noqa: E402
from beehave.recording import Recording, read_recording  # noqa: E402
from beehave.recording.replay import HIGH_SWITCH, replay  # noqa: E402
from beehave.testing import beehave_threads, wait_until  # noqa: E402
from behaviours.demos.warehouse import CONFIG_DIR, run_sim_demo  # noqa: E402
from behaviours.emili import Commanded  # noqa: E402
from behaviours.logics import LIGHT_BLUE  # noqa: E402

# One pytest-xdist worker runs this module (its lane, tests/conftest.py): its module-scoped
# rig is built once.
# A replay of the whole demo takes 5-25 s depending on the host's load, and some tests here
# run several (a diverging one waits out its catch-up bounds): 300 s, not the suite's 120 s
# (a run beside 16 other busy processes hit 120 s).
pytestmark = pytest.mark.timeout(300)

DEMO_SWITCHES = ["idle", "tour", "commanded", "maintenance"]
# Negative checks on DDS (nothing more arrives) run to their end: short on purpose; a loaded
# machine can only make them miss a late message, never fail a right replay.
QUIET_S = 0.3


# Session scope, in the one worker of this module's group: with module scope pytest-xdist
# interleaved other modules' tests and the demo was recorded four times per run (100 s).
@pytest.fixture(scope="session")
def demo(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest
         ) -> Iterator[Path]:
    """One recorded demo run (about 20 s) shared by the tests of this file. It is also the
    test of the demo itself, run as ``beehave demo --fast`` does (as fast as possible, as
    the README advertises): every goal is checked in the physics, the picture is drawn,
    and no thread is left. Lockstep keeps fast mode correct: the controllers hold the
    physics at each of their steps, so a reaction time measured in sim time does not grow
    with the speed-up."""
    folder = tmp_path_factory.mktemp("demo")
    path = folder / "demo.mcap"
    out = io.StringIO()
    before = set(beehave_threads())
    capture = request.config.pluginmanager.getplugin("capturemanager")
    with capture.global_and_fixture_disabled():  # rclpy's executor wants the real stdout
        problems = run_sim_demo(Console(file=out, width=120), real_time_factor=None,
                                out_dir=folder, live_display=False, record=path)
    assert problems == [], out.getvalue()
    assert f"into {path}" in out.getvalue()
    picture = folder / "demo.png"
    assert picture.exists() and picture.stat().st_size > 5000
    assert wait_until(lambda: not [t for t in beehave_threads() if t not in before])
    yield path


@pytest.fixture(scope="session")
def emili_replayed(demo: Path) -> dict[str, Any]:
    """EMILI replayed once through the API, asked to go 100 s beyond the recording's end,
    while a ROS probe listens on what EMILI commands and every rclpy node made in this
    process is counted (a replay of the whole demo is several seconds of the suite: three
    tests read this one). ``result``: the replay's; ``made``: the names of the nodes the
    replay made; ``heard``: what the probe received per topic after the replay."""
    import rclpy.node
    from geometry_msgs.msg import Twist
    from std_msgs.msg import Float64, String

    from tests.ros_probe import Probe

    probe = Probe()
    try:
        heard = {topic: probe.record(t, topic) for topic, t in (
            ("/emili1/cmd_vel", Twist), ("/emili1/sound", String),
            ("/emili1/lift/command", Float64), ("/emili1/orders/progress", String))}
        # The probe does hear a robot that publishes: its silence below means something.
        talker = probe.ros.create_node("talker")
        pub = talker.create_publisher(Twist, "/emili1/cmd_vel", 10)
        assert probe.wait(lambda: (pub.publish(Twist()), bool(heard["/emili1/cmd_vel"]))[1])
        probe.ros.destroy_node(talker)
        probe.wait(lambda: False, timeout_s=QUIET_S)  # the talker's last messages arrive
        heard["/emili1/cmd_vel"].clear()

        made: list[str] = []
        init = rclpy.node.Node.__init__
        lock = threading.Lock()

        def spy(self: Any, name: str, *args: Any, **kwargs: Any) -> None:
            with lock:
                made.append(name)
            init(self, name, *args, **kwargs)

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(rclpy.node.Node, "__init__", spy)
            result = replay(demo, _emili(), speed=None, to_s=_replayed_end(demo) + 100.0)
        probe.wait(lambda: False, timeout_s=QUIET_S)  # anything sent would have arrived
        found = {"result": result, "made": made,
                 "heard": {topic: list(got) for topic, got in heard.items()}}
    finally:  # not kept for the session: it would hear every later test's emili1
        probe.ros.shutdown()
    return found


def test_the_fast_demo_reaches_every_goal_in_the_physics(demo: Path) -> None:
    """The checks are the fixture's (see :func:`demo`); here the recording is complete."""
    assert demo.stat().st_size > 0


def _emili(commanded: str | None = None) -> RobotConfig:
    """EMILI's configuration, with another class for its `commanded` behaviour."""
    source = CONFIG_DIR / "emili.yaml"
    if commanded is None:
        return load_config(source)
    data = yaml.safe_load(source.read_text())
    data["behaviors"]["commanded"]["class"] = commanded
    return parse_config(data, source=f"{source} (variant)")


def test_demo_recording_replays_to_the_same_decisions(
        demo: Path, emili_replayed: dict[str, Any], capsys: pytest.CaptureFixture[str]
        ) -> None:
    rec = read_recording(demo)
    assert rec.prefixes == ["emili1", "kobuki1"] and rec.dropped() == 0
    for robot in ("emili1", "kobuki1"):
        for channel in ("beehave/blackboard", "beehave/events/high", "beehave/events/low",
                        "beehave/outputs", "beehave/clock", "odom", "scan", "cmd_vel",
                        "battery_state"):
            assert rec.channels[f"/{robot}/{channel}"].count > 0, (robot, channel)
    # What the behaviours read beyond the configured topics was recorded too: the lift's
    # state (Lift), the other agent's order (Commanded), the bumpers (Wander).
    for channel in ("/emili1/lift/state", "/emili1/orders", "/kobuki1/bumpers"):
        assert rec.channels[channel].count > 0, channel
    commands = [m.data for m in rec.of("/emili1/beehave/outputs")]
    assert {"hal": "emili_leds", "method": "set_color", "args": list(LIGHT_BLUE)}.items() \
        <= next(c for c in commands if c["args"] == list(LIGHT_BLUE)).items()
    requested = [m.data for m in rec.of("/emili1/beehave/events/high")
                 if m.data["kind"] == "switch_requested"]
    assert [r["subject"] for r in requested] == DEMO_SWITCHES
    assert {r["detail"]["source"] for r in requested} == {"external"}
    # The proof that the interrupted drive left the robot stopped: its safe state ran.
    ran = [m.data for m in rec.of("/emili1/beehave/events/high")
           if m.data["kind"] == "safe_state_ran"]
    assert {"subject": "tour/Navigation→emili_pickup", "status": "INTERRUPTED"}.items() \
        <= next(r for r in ran if r["subject"] == "tour/Navigation→emili_pickup").items()

    # The command line replays kobuki1; EMILI is replayed through the API (emili_replayed).
    capsys.readouterr()
    code = main(["replay", str(demo), "--robot", str(CONFIG_DIR / "kobuki.yaml"),
                 "--speed", "max"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "deterministic" in printed and "behaviours and actions" in printed, printed
    assert "(sim time)" in printed and "/cmd_vel x" in printed, printed

    # The behaviour switch sequence itself, from the replay (not only "no divergence").
    result = emili_replayed["result"]
    assert result.divergence is None, result.divergence
    switches = [o.value for o in result.outputs if o.key == HIGH_SWITCH]
    assert [v[1] for v in switches if v[0] == "completed"] == DEMO_SWITCHES
    assert [v[1] for v in switches if v[0] == "requested"] == DEMO_SWITCHES
    ended = {o.key: o.value for o in result.outputs if o.value[0] == "ended"}
    assert ended["high:tour/Navigation→emili_dropoff"][1] == "SUCCEEDED"
    assert ended["high:tour/Navigation→emili_pickup"][1] == "INTERRUPTED"
    assert ended["high:commanded/Navigation→emili_charging"][1] == "SUCCEEDED"
    assert ended["high:maintenance/Lift→0m"][1] == "SUCCEEDED"

    assert main(["inspect", str(demo), "--limit", "500"]) == 0
    shown = capsys.readouterr().out
    assert "/emili1/odom" in shown and "switch_completed  maintenance" in shown

    picture = demo.parent / "timeline.png"
    assert main(["plot", str(demo), "-o", str(picture)]) == 0
    assert picture.stat().st_size > 20_000


class ImpatientCommanded(Commanded):
    """`commanded`, changed: once it has reached an order it switches the robot to `idle`
    by itself -- the recorded one waited for the operator's next switch."""

    def report(self, order_id: str, status: str, detail: str = "", **extra: Any) -> None:
        super().report(order_id, status, detail, **extra)
        if status == "reached":
            self.manager.switch("idle")


def test_a_behaviour_that_switches_differently_is_the_first_divergence(demo: Path) -> None:
    rec = read_recording(demo)
    result = replay(rec, _emili("tests.test_replay_demo:ImpatientCommanded"), speed=None)
    div = result.divergence
    assert div is not None
    # The recording's next switch was the operator's `maintenance`; the changed behaviour
    # asked for `idle` as soon as the order was reached.
    assert div.key == HIGH_SWITCH, str(div)
    assert (div.expected, div.got) == (["requested", "maintenance"], ["requested", "idle"])
    reached = next(o for o in result.expected
                   if o.key == "high:commanded/Navigation→emili_charging"
                   and o.value[0] == "ended")
    assert div.t_s == pytest.approx(reached.t_s, abs=0.5)  # when it switched, not later
    assert f"t={div.t_s:.3f} s" in str(div) and "'high:switch'" in str(div)
    # Everything before it was the same: the tour, the order, the drive.
    assert all(o.t_s >= div.t_s for o in result.expected
               if o.key == HIGH_SWITCH and o.value[1] == "maintenance")


def test_a_recording_without_what_a_behaviour_reads_is_refused_naming_it(demo: Path) -> None:
    rec = read_recording(demo)

    def without(*topics: str) -> Recording:
        return Recording(rec.files, [m for m in rec.messages if m.topic not in topics],
                         {t: c for t, c in rec.channels.items() if t not in topics},
                         rec.truncated, rec.metadata, rec.schemas)

    with pytest.raises(RecordingError) as err:
        replay(without("/emili1/lift/state"), _emili(), speed=None)
    text = str(err.value)
    assert "channel(s) /emili1/lift/state missing" in text, text
    assert "tour/Lift→0.2m subscribed to /emili1/lift/state (Float64)" in text, text
    assert "/emili1/odom" in text.split("has:")[1]  # what the recording does have

    with pytest.raises(RecordingError, match="/emili1/beehave/events/high missing"):
        replay(without("/emili1/beehave/events/high"), _emili(), speed=None)
    # The low level alone still replays without the behaviours' channels.
    low = replay(without("/emili1/lift/state", "/emili1/beehave/events/high"), _emili(),
                 speed=None, high=False)
    assert low.divergence is None and not low.high


def test_nothing_reaches_ros_during_a_replay(emili_replayed: dict[str, Any]) -> None:
    # (Whether it diverges is test_demo_recording_replays_to_the_same_decisions's
    # question; here: what it sends.)
    result = emili_replayed["result"]
    assert emili_replayed["made"] == []  # the replay made no ROS node
    captured = {c.topic for c in result.commands}
    assert {"/emili1/cmd_vel", "/emili1/sound", "/emili1/lift/command",
            "/emili1/orders/progress"} <= captured
    assert "/lockstep" not in captured  # pacing, not a command
    lift = [c.value["data"] for c in result.commands if c.topic == "/emili1/lift/command"]
    assert lift[:2] == [0.2, 0.0]  # the tour's lift up and down, as commanded live
    moving = [c for c in result.commands if c.topic == "/emili1/cmd_vel"
              and c.value["linear"]["x"] > 0.1]
    assert moving  # the navigation drove (captured): it is not a silent no-op
    heard = emili_replayed["heard"]
    assert {topic: len(got) for topic, got in heard.items()} == dict.fromkeys(heard, 0)


# ---- recordings users bring: cut off, damaged, asked beyond their end (issue 23) --------

def _cut_copy(demo: Path, fraction: float) -> Path:
    """What a killed recorder leaves: the file up to some byte, no summary, no footer."""
    data = demo.read_bytes()
    out = demo.parent / f"cut{int(fraction * 100)}.mcap"
    out.write_bytes(data[:int(len(data) * fraction)])
    return out


def _damaged_copy(demo: Path) -> tuple[Path, int]:
    """2,000 random bytes written into the middle of a chunk in the middle of the file."""
    import random

    from mcap.reader import make_reader

    with open(demo, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    chunk = chunks[len(chunks) // 2]
    at = chunk.chunk_start_offset + chunk.chunk_length // 2 - 1000
    data = bytearray(demo.read_bytes())
    data[at:at + 2000] = random.Random(23).randbytes(2000)
    out = demo.parent / "damaged.mcap"
    out.write_bytes(bytes(data))
    return out, at


def test_a_cut_off_recording_replays_up_to_where_it_ends_and_says_so(
        demo: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = _cut_copy(demo, 0.6)
    rec = read_recording(cut)
    assert rec.truncated and not rec.damaged
    capsys.readouterr()
    for config in ("emili.yaml", "kobuki.yaml"):
        code = main(["replay", str(cut), "--robot", str(CONFIG_DIR / config),
                     "--speed", "max"])
        printed = capsys.readouterr().out
        # Not the replay's own shutdown at the end of the data as a divergence.
        assert code == 0, printed
        assert "was cut off at t=" in printed and "compared up to there" in printed, printed
        assert "deterministic:" in printed and "as recorded up to t=" in printed, printed
    assert main(["inspect", str(cut), "--limit", "0"]) == 0
    assert "truncated" in capsys.readouterr().out
    assert main(["plot", str(cut), "-o", str(cut.with_suffix(".png"))]) == 0
    assert "truncated" in capsys.readouterr().out


def test_a_damaged_recording_names_the_damage_and_exits_2(
        demo: Path, capsys: pytest.CaptureFixture[str]) -> None:
    damaged, at = _damaged_copy(demo)
    rec = read_recording(damaged)
    [damage] = rec.damaged
    assert damage.start_byte <= at < damage.end_byte, (damage, at)
    assert not rec.truncated  # a finished file, damaged inside: not a crash
    whole = read_recording(demo)
    # Every message read is a recorded one: no garbage times, none invented.
    assert whole.start_ns <= rec.start_ns and rec.end_ns <= whole.end_ns
    assert len(rec.messages) < len(whole.messages)
    capsys.readouterr()
    assert main(["inspect", str(damaged), "--limit", "0"]) == 2
    shown = capsys.readouterr().out
    assert "DAMAGED" in shown and f"bytes {damage.start_byte}-{damage.end_byte}" in \
        shown.replace("\n", ""), shown
    code = main(["replay", str(damaged), "--robot", str(CONFIG_DIR / "emili.yaml"),
                 "--speed", "max"])
    printed = capsys.readouterr().out
    assert code == 2, printed
    assert "DAMAGED" in printed and "INCOMPLETE" in printed and "deterministic" not in printed
    assert main(["plot", str(damaged), "-o", str(damaged.with_suffix(".png"))]) == 2
    assert "DAMAGED" in capsys.readouterr().out


def test_to_beyond_the_end_replays_to_the_end_without_a_false_divergence(
        emili_replayed: dict[str, Any]) -> None:
    result = emili_replayed["result"]  # asked for 100 s beyond the end
    assert result.divergence is None, result.divergence
    assert any("beyond the recording's end" in w for w in result.warnings), result.warnings


def _replayed_end(demo: Path) -> float:
    from beehave.recording.replay import _Timeline

    rec = read_recording(demo)
    return _Timeline(rec, "emili1")(rec.end_ns)


def test_plot_names_what_it_cannot_draw(demo: Path, capsys: pytest.CaptureFixture[str]
                                        ) -> None:
    out = str(demo.parent / "refused.png")
    capsys.readouterr()
    assert main(["plot", str(demo), "--series", "leds/color", "-o", out]) == 2
    err = capsys.readouterr().err
    assert "'leds/color' has no numbers to plot" in err and "[0.35" in err, err
    assert "keys with numbers:" in err and "odom/linear_mps" in err, err
    assert main(["plot", str(demo), "--robot", "nobody", "-o", out]) == 2
    err = capsys.readouterr().err
    assert "no robot 'nobody'" in err and "'emili1', 'kobuki1'" in err, err


def test_the_declared_mcap_profile_holds(demo: Path) -> None:
    """Read with the plain `mcap` reader (issue 23, item 6): a file that declares the
    `ros2` profile must have only CDR channels with `offered_qos_profiles` metadata (the
    MCAP spec); the demo's has JSON channels too, so it must declare none."""
    from mcap.reader import make_reader

    with open(demo, "rb") as f:
        reader = make_reader(f)
        profile = reader.get_header().profile
        summary = reader.get_summary()
    assert summary is not None
    channels = list(summary.channels.values())
    encodings = {c.message_encoding for c in channels}
    assert encodings == {"json", "cdr"}
    if profile == "ros2":
        assert encodings == {"cdr"} and all("offered_qos_profiles" in c.metadata
                                            for c in channels)
    else:
        assert profile == ""


def test_events_are_written_for_foxglove_log_panel(demo: Path) -> None:
    """Read with the plain `mcap` reader: each robot's events also go out as `foxglove.Log`
    (JSON), the schema Foxglove's Log panel shows (issue 23, item 6)."""
    import json as _json

    from mcap.reader import make_reader

    with open(demo, "rb") as f:
        logs = [(schema, channel, _json.loads(message.data)) for schema, channel, message
                in make_reader(f).iter_messages(topics=["/emili1/beehave/log"])]
    assert logs
    schema, channel, _ = logs[0]
    assert schema is not None and schema.name == "foxglove.Log"
    assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
    for _, _, log in logs:
        assert set(log) == {"timestamp", "level", "message", "name", "file", "line"}
        assert set(log["timestamp"]) == {"sec", "nsec"} and 0 <= log["timestamp"]["nsec"] < 1e9
        assert log["level"] in (1, 2, 3, 4, 5) and log["name"] in ("emili1/high", "emili1/low")
    messages = [log["message"] for _, _, log in logs]
    assert "safe_state_ran tour/Navigation→emili_pickup INTERRUPTED" in messages
    assert "switch_completed commanded" in messages


def test_scans_can_be_placed_on_the_map(demo: Path) -> None:
    """Read with the plain `mcap` + `mcap-ros2-support` readers: each robot's pose goes out
    as `foxglove.FrameTransform` from the scans' frame's parent, `map` (issue 23, item 6)."""
    import json as _json

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(demo, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        transforms = [(s, _json.loads(m.data)) for s, _, m
                      in reader.iter_messages(topics=["/emili1/beehave/tf"])]
    with open(demo, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        scan = next(d for _, _, _, d in reader.iter_decoded_messages(topics=["/emili1/scan"]))
    assert transforms and transforms[0][0].name == "foxglove.FrameTransform"
    frames = {(t["parent_frame_id"], t["child_frame_id"]) for _, t in transforms}
    assert frames == {("map", scan.header.frame_id)}, (frames, scan.header.frame_id)
    # The pose moves: EMILI drove its tour (it starts at (3, 2) in the warehouse).
    xs = [t["translation"]["x"] for _, t in transforms]
    assert min(xs) < 3.5 < max(xs)
