"""Robot configuration files: every mistake is refused with the file, the key path and the
valid choices, before anything starts (no ROS 2 needed: the robot is only built)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from beehave.config import RobotConfig, load_config
from beehave.errors import ConfigError
from beehave.robot import Robot

ROOT = Path(__file__).resolve().parent.parent

HEADER = "namespace: emili\nstop_timeout_s: 0.3\n"


def write(tmp_path: Path, body: str, *, header: str = HEADER) -> Path:
    path = tmp_path / "emili.yaml"
    path.write_text(header + body)
    return path


@pytest.fixture
def build(tmp_path: Path) -> Iterator[object]:
    """Load ``body`` as emili.yaml and build the robot from it (nothing is started)."""
    robots: list[Robot] = []

    def _build(body: str, *, header: str = HEADER) -> Robot:
        robot = Robot(load_config(write(tmp_path, body, header=header)))
        robots.append(robot)
        return robot

    yield _build
    for robot in robots:
        robot.shutdown()


# ---- item 4: durations and rates must be finite -----------------------------------------

NON_FINITE = [
    ("stop_timeout_s: .inf", "stop_timeout_s"),
    ("stop_timeout_s: .nan", "stop_timeout_s"),
    ("stop_timeout_s: -.inf", "stop_timeout_s"),
    ("stop_timeout_s: 'inf'", "stop_timeout_s"),
    ("ros: {blackboard_rate_hz: .inf}", "ros.blackboard_rate_hz"),
    ("ros: {snapshot_period_s: .nan}", "ros.snapshot_period_s"),
    ("ros: {state_period_s: .inf}", "ros.state_period_s"),
    ("sim: {real_time_factor: .inf}", "sim.real_time_factor"),
    ("sim: {real_time_factor: .nan}", "sim.real_time_factor"),
]


@pytest.mark.parametrize(("line", "key"), NON_FINITE)
def test_non_finite_durations_and_rates_are_refused(tmp_path: Path, line: str,
                                                    key: str) -> None:
    path = write(tmp_path, line + "\n", header="namespace: emili\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    message = str(err.value)
    assert message.startswith(f"{path}: {key}: "), message
    assert "finite number" in message or "greater than 0" in message, message


@pytest.mark.parametrize(("line", "key"), [
    ("stop_timeout_s: 0", "stop_timeout_s"),
    ("ros: {blackboard_rate_hz: -5}", "ros.blackboard_rate_hz"),
    ("sim: {real_time_factor: 0}", "sim.real_time_factor"),
])
def test_non_positive_durations_and_rates_are_refused(tmp_path: Path, line: str,
                                                      key: str) -> None:
    path = write(tmp_path, line + "\n", header="namespace: emili\n")
    with pytest.raises(ConfigError, match=rf"{re.escape(str(path))}: {re.escape(key)}: "
                                          r"Input should be greater than 0"):
        load_config(path)


def test_finite_values_and_null_real_time_factor_are_kept(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, "ros: {blackboard_rate_hz: 50, state_period_s: 0.2}\n"
                                         "sim: {real_time_factor: null}\n"))
    assert config.stop_timeout_s == 0.3
    assert config.ros.blackboard_rate_hz == 50.0 and config.ros.state_period_s == 0.2
    assert config.sim is not None and config.sim.real_time_factor is None


# ---- item 21: file and key path for parameters, HAL names, idle ------------------------

def test_redefining_idle_names_the_key(tmp_path: Path) -> None:
    path = write(tmp_path, "behaviors:\n  idle: {class: 'config_fixtures:Waits'}\n")
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}: behaviors\.idle: "
                                          r"'idle' is built in .* cannot be redefined"):
        load_config(path)


def test_bad_behavior_parameters_name_file_and_key(build) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError) as err:
        build("behaviors:\n  tour: {class: 'config_fixtures:Waits', "
              "params: {speed: 0.3}}\n")
    message = str(err.value)
    assert re.match(r"^.*emili\.yaml: behaviors\.tour\.params: ", message), message
    assert "'speed'" in message and "speed_mps" in message, message  # bad one, valid ones


def test_bad_logic_parameters_name_file_and_key(build) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError, match=r"emili\.yaml: logics\.uses\.params: .*'mode'"):
        build("logics:\n  uses: {class: 'config_fixtures:UsesBroken', "
              "params: {mode: fast}}\n")


def test_unknown_hal_name_names_the_entry_and_the_choices(build) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError) as err:
        build("hals: [debug, lazer]\n")
    message = str(err.value)
    assert re.match(r"^.*emili\.yaml: hals\.1: unknown HAL 'lazer'; registered: ", message), \
        message
    assert "'laser'" in message and "'debug'" in message, message


def test_bad_hal_parameters_name_file_and_key(build) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError, match=r"emili\.yaml: hals\.0\.params: .*'port'"):
        build("hals:\n  - {class: 'config_fixtures:BrokenHAL', params: {port: /dev/x}}\n")


def test_a_hal_listed_twice_is_refused(build) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError, match=r"emili\.yaml: hals\.1: HAL 'broken' is already "
                                          r"given by hals\.0"):
        build("hals:\n  - {class: 'config_fixtures:BrokenHAL'}\n"
              "  - {class: 'config_fixtures:BrokenHAL', name: broken}\n")


@pytest.mark.parametrize(("body", "expected"), [
    ("hals: [3]\n", r"hals\.0: expected a HAL name \(str\) or a mapping"),
    ("hals:\n  - {name: base}\n", r"hals\.0\.class: Field required"),
    ("hals:\n  - {class: 'a:B', nme: x}\n", r"hals\.0\.nme: unknown key; valid keys: class, "
                                            r"params, name"),
    ("ros: {rate_hz: 5}\n", r"ros\.rate_hz: unknown key; valid keys: blackboard_rate_hz, "
                            r"snapshot_period_s, state_period_s"),
    ("sim: {wrld: x}\n", r"sim\.wrld: unknown key; valid keys: simulator, world, "
                         r"real_time_factor"),
    ("behaviors:\n  t: {class: 'a:B', param: {}}\n", r"behaviors\.t\.param: unknown key; "
                                                      r"valid keys: class, params"),
])
def test_shape_errors_say_what_fits(tmp_path: Path, body: str, expected: str) -> None:
    path = write(tmp_path, body)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    message = str(err.value)
    assert re.match(rf"^{re.escape(str(path))}: {expected}", message), message
    assert "HALSpec" not in message and ".str" not in message, message  # no pydantic noise


@pytest.mark.parametrize("path", [
    ROOT / "tests" / "data" / "rosbot.yaml",
    ROOT / "robots" / "config" / "emili.yaml",
    ROOT / "robots" / "config" / "kobuki.yaml",
], ids=lambda p: p.name)
def test_shipped_configurations_still_build(path: Path) -> None:
    pytest.importorskip("rclpy")  # their behaviours talk ROS 2
    robot = Robot(load_config(path))
    robot.shutdown()
    assert isinstance(robot.config, RobotConfig)


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"robot configuration '.*missing\.yaml' does not "
                                          r"exist"):
        load_config(tmp_path / "missing.yaml")


def test_hal_names_are_what_beehave_run_registers(tmp_path: Path) -> None:
    from beehave.config import hal_names, load_config

    path = tmp_path / "r.yaml"
    path.write_text("namespace: r\nhals:\n  - debug\n"
                    "  - {class: 'hal.debug:DebugHAL', name: dbg2}\n"
                    "  - {class: 'hal.mobile_base:OdometryHAL'}\n")
    assert hal_names(load_config(path)) == ["debug", "dbg2", "odometry"]
