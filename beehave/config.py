"""Robot configuration files (YAML) for ``beehave run``.

::

    namespace: emili                     # the robot's ROS namespace
    stop_timeout_s: 2.0
    use_sim_time: false                  # sleep/timeouts follow /clock when true
    sim_clock_timeout_s: 30.0            # with use_sim_time: how long to wait for /clock
    behaviors:                           # top-level behaviours, by import path
      tour:
        class: behaviours.demos.console:Delivery
        params: {goal_m: 3.0}
    default_behavior: idle
    logics:
      leds: {class: "behaviours.logics:LedLogic", params: {threshold: 20}}
    default_logic: leds
    hals:                                # a name (entry point) or a class with params
      - debug
      - {class: "hal.emili:EmiliBaseHAL", name: base, params: {}}
    ros:
      blackboard_rate_hz: 2000.0
      snapshot_period_s: 1.0
      state_period_s: 1.0
      second_goal: reject                # beehave/execute_behavior: reject | preempt
    agent:                               # optional: the robot is an agent (docs/agents.md)
      name: atv_1                        # unique in the DDS domain
      services: {transport: {payload_kg: 50}}
      lease_s: 2.0
      mode: signed                       # open (default) | signed: docs/agents.md#trust-model
      keys: keys/                        # from `beehave keys`: fleet.pub, atv_1.key, .cert
    fusion:                              # optional: priority fusion (docs/fusion.md)
      cmd_vel:                           # the actuator; its arbiter is HAL fusion_cmd_vel
        class: "hal.drive:CmdVelArbiter"
        rate_hz: 20.0
        inputs:                          # source: {priority (int), max_age_s, safety}
          bumper: {priority: 100, max_age_s: 0.3, safety: true}
          wander: {priority: 10, max_age_s: 0.5}
        locks:                           # lock: {priority, max_age_s (heartbeat)}
          pause: {priority: 50}
    sim:                                 # optional: run the simulation in this process
      simulator: pybullet                # entry point (group beehave.simulations)
      world: warehouse                   # (the one that runs the low level)
      real_time_factor: 1.0              # null: as fast as possible
    vda5050:                             # optional: a VDA 5050 AGV over MQTT (docs/vda5050.md)
      broker: {host: 127.0.0.1, port: 1883}
      interface_name: uagv
      manufacturer: beehave
      serial_number: emili1
      world: warehouse                   # node positions and station names are its map
    recording:                           # optional: what `--record` adds (docs/recording.md)
      topics: [odom, scan, cmd_vel, battery_state, {name: lift/state, type: std_msgs/msg/Float64}]
      queue_size: 100000                 # per channel; beyond it, drops are counted
      max_file_mb: null                  # roll over into run_001.mcap … at this size
    substitutes:                         # tests: scripted stand-ins by name (docs/testing.md)
      "tour/Navigate*": {duration_s: 30.0, result: true}

Errors name the file, the key path and what was expected.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from beehave import simulation
from beehave.errors import ConfigError, NotASubclass

Seconds = Annotated[float, Field(gt=0, allow_inf_nan=False)]
"""A duration in seconds: positive and finite. An infinite stop timeout overflows the
lock waits and a NaN one makes every comparison false (every action STUCK at once), so
both are refused where they are read, with the key path."""

Hertz = Annotated[float, Field(gt=0, allow_inf_nan=False)]
"""A rate per second: positive and finite (``inf`` would make its period 0, NaN never
compares)."""

Factor = Annotated[float, Field(gt=0, allow_inf_nan=False)]
"""A positive, finite multiplier (``real_time_factor``); "as fast as possible" is ``null``,
not ``.inf``."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class ClassSpec(_Strict):
    class_: str = Field(alias="class", description="import path, `package.module:Class`")
    params: dict[str, Any] = Field(default_factory=dict)

    @field_validator("class_")
    @classmethod
    def _import_path(cls, value: str) -> str:
        if ":" not in value or value.startswith(":") or value.endswith(":"):
            raise ValueError(f"expected 'package.module:Class', got {value!r}")
        return value


class HALSpec(ClassSpec):
    name: str | None = None


class RosOptions(_Strict):
    blackboard_rate_hz: Hertz = 2000.0
    snapshot_period_s: Seconds = 1.0
    state_period_s: Seconds = 1.0
    second_goal: Literal["reject", "preempt"] = Field(
        "reject", description="beehave/execute_behavior: a goal that arrives while another "
        "executes is refused (ABORTED at once, naming the running goal), or preempts it")


class SimOptions(_Strict):
    """Start the simulation (and its ROS 2 node) inside ``beehave run``."""

    simulator: str = Field(simulation.DEFAULT,
                           description="an entry point of group beehave.simulations")
    world: str = "warehouse"
    real_time_factor: Factor | None = 1.0


class AgentOptions(_Strict):
    """The robot's agent (``beehave.agents``): its name, what it offers, its lease."""

    # The pattern of beehave.agents.message.NAME_PATTERN (not imported: that needs rclpy).
    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]{0,62}$")
    services: dict[str, dict[str, Any]] = Field(default_factory=dict)
    lease_s: Seconds = 2.0
    mode: Literal["open", "signed"] | None = Field(
        None, description="open (nothing checked) or signed (docs/agents.md#trust-model); "
                          "default: BEEHAVE_AGENT_MODE, else open")
    keys: str | None = Field(None, description="the folder `beehave keys` wrote: fleet.pub, "
                                                "NAME.key, NAME.cert (relative to this file)")
    fleet_public_key: str | None = None
    key: str | None = None
    certificate: str | None = None


# ---- vda5050: a VDA 5050 AGV over MQTT (beehave.interfaces.vda5050) ---------------------

_TOPIC_LEVEL = r"^[A-Za-z0-9_.-]+$"
"""One MQTT topic level of a VDA 5050 topic: no ``/``, ``+``, ``#`` or spaces."""


class BrokerOptions(_Strict):
    """Where the MQTT broker is. ``username_env``/``password_env`` name environment
    variables (a password never sits in the YAML); ``tls`` switches TLS on, ``ca_file``
    picks the CA bundle (default: the system's)."""

    host: str = "127.0.0.1"
    port: int = Field(1883, ge=1, le=65535)
    username_env: str | None = None
    password_env: str | None = None
    tls: bool = False
    ca_file: str | None = None
    keepalive_s: int = Field(10, ge=1, le=3600)
    reconnect_max_s: Seconds = 10.0


class Vda5050Options(_Strict):
    """The robot as a VDA 5050 2.1 AGV (``docs/vda5050.md``)."""

    broker: BrokerOptions = Field(default_factory=lambda: BrokerOptions())
    interface_name: str = Field("uagv", pattern=_TOPIC_LEVEL)
    manufacturer: str = Field("beehave", pattern=_TOPIC_LEVEL)
    serial_number: str = Field(pattern=_TOPIC_LEVEL)
    world: str = "warehouse"
    behavior: str = Field("vda5050", description="the name the order behaviour is "
                                                 "registered under")
    executor: str = Field("behaviours.vda5050:OrderExecution",
                          description="the Behavior class that executes orders")
    factsheet: dict[str, Any] = Field(default_factory=dict,
                                      description="factsheet sections to override")
    state_period_s: Seconds = 30.0
    visualization_rate_hz: Hertz = 2.0
    speed_mps: Annotated[float, Field(gt=0, le=2.0)] = 0.6
    lift_pick_m: Annotated[float, Field(ge=0, le=0.3)] = 0.2
    lift_drop_m: Annotated[float, Field(ge=0, le=0.3)] = 0.0


class RecordedTopic(_Strict):
    """A robot topic to record with its ROS 2 type (``recording.topics``)."""

    name: str
    type: str = Field(pattern=r"^[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+$",
                      description="e.g. std_msgs/msg/Float64")


class RecordingOptions(_Strict):
    """What ``beehave run --record`` writes besides the blackboard, the events and the HAL
    commands (docs/recording.md): the robot topics (a standard name -- odom, scan,
    cmd_vel, battery_state -- or ``{name, type}``), the queue bound and the roll-over size."""

    topics: list[str | RecordedTopic] = Field(
        default_factory=lambda: list[str | RecordedTopic](
            ["odom", "scan", "cmd_vel", "battery_state"]))
    queue_size: int = Field(100_000, ge=1)
    max_file_mb: float | None = Field(None, gt=0, allow_inf_nan=False)


class FusionInputOptions(_Strict):
    """One source of an arbiter (:class:`beehave.fusion.FusionInput`)."""

    priority: int = Field(strict=True, description="higher wins; an int")
    max_age_s: Seconds
    safety: bool = Field(False, strict=True)


class FusionLockOptions(_Strict):
    """One lock of an arbiter (:class:`beehave.fusion.FusionLock`)."""

    priority: int = Field(strict=True, description="mutes sources up to this priority")
    max_age_s: Seconds | None = None


class FusionOptions(_Strict):
    """The arbiter of one actuator (:class:`beehave.fusion.Arbiter`)."""

    class_: str = Field(alias="class", description="import path of an Arbiter subclass")
    rate_hz: Hertz = 20.0
    safe_value: Any = None
    inputs: dict[str, FusionInputOptions] = Field(min_length=1)
    locks: dict[str, FusionLockOptions] = Field(default_factory=dict)

    @field_validator("class_")
    @classmethod
    def _import_path(cls, value: str) -> str:
        return ClassSpec._import_path(value)

    def arbiter_params(self, actuator: str) -> dict[str, Any]:
        """The keyword arguments of the arbiter's constructor."""
        params: dict[str, Any] = {
            "actuator": actuator, "rate_hz": self.rate_hz,
            "inputs": {n: i.model_dump() for n, i in self.inputs.items()},
            "locks": {n: lock.model_dump() for n, lock in self.locks.items()}}
        if self.safe_value is not None:
            params["safe_value"] = self.safe_value
        return params


class SubstituteOptions(_Strict):
    """A scripted stand-in (:class:`beehave.testing.Scripted`) for the actions, behaviours
    and logics whose path, name or class matches the key."""

    duration_s: Annotated[float, Field(ge=0)] = 0.0
    result: Any = None
    fail: str | None = Field(None, description="fail with RuntimeError(fail) instead")


class RobotConfig(_Strict):
    namespace: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$")
    stop_timeout_s: Seconds = 2.0
    use_sim_time: bool = False
    sim_clock_timeout_s: Seconds = Field(
        30.0, description="with use_sim_time, how long start() waits for the first /clock")
    behaviors: dict[str, ClassSpec] = Field(default_factory=dict)
    default_behavior: str = "idle"
    logics: dict[str, ClassSpec] = Field(default_factory=dict)
    default_logic: str | None = None
    hals: list[str | HALSpec] = Field(default_factory=list)
    ros: RosOptions = Field(default_factory=lambda: RosOptions())
    agent: AgentOptions | None = None
    fusion: dict[str, FusionOptions] = Field(default_factory=dict)
    sim: SimOptions | None = None
    vda5050: Vda5050Options | None = None
    recording: RecordingOptions = Field(default_factory=lambda: RecordingOptions())
    substitutes: dict[str, SubstituteOptions] = Field(default_factory=dict)
    source: str = Field("<dict>", exclude=True)


def load_config(path: str | Path) -> RobotConfig:
    """Read and validate a robot configuration file.

    Its directory becomes a place where its ``class:`` import paths are found: they are
    looked up as any Python import (installed packages, and the current directory under
    ``beehave``), then in the configuration file's directory — so a ``mybots`` package
    beside ``robot.yaml`` imports from any working directory. The directory is appended to
    ``sys.path`` (last: it never shadows an installed package) and stays there, since the
    classes it provides may import more of their package later."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"robot configuration {str(path)!r} does not exist") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    config = parse_config(data, source=str(path))
    add_import_dir(path.resolve().parent)
    return config


def add_import_dir(directory: Path) -> None:
    """Let ``class:`` import paths be found in ``directory`` (after everything else)."""
    entry = str(directory)
    if entry not in sys.path:
        sys.path.append(entry)
        importlib.invalidate_caches()


def parse_config(data: Any, *, source: str = "<dict>") -> RobotConfig:
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level, got "
                          f"{type(data).__name__}")
    try:
        config = RobotConfig.model_validate({**data, "source": source})
    except ValidationError as exc:
        problems = "; ".join(d for d in dict.fromkeys(_describe(e) for e in exc.errors()) if d)
        raise ConfigError(f"{source}: {problems}") from None
    if "idle" in config.behaviors:
        raise ConfigError(f"{source}: behaviors.idle: 'idle' is built in (the safe behaviour "
                          "that runs when nothing else does) and cannot be redefined; give "
                          "yours another name and make it default_behavior")
    names = {"idle", *config.behaviors}
    if config.default_behavior not in names:
        raise ConfigError(f"{source}: default_behavior: {config.default_behavior!r} is not "
                          f"one of the behaviors ({', '.join(sorted(names))})")
    if config.default_logic is not None and config.default_logic not in config.logics:
        raise ConfigError(f"{source}: default_logic: {config.default_logic!r} is not one of "
                          f"the logics ({', '.join(sorted(config.logics)) or 'none'})")
    _check_fusion(config)
    return config


def _check_fusion(config: RobotConfig) -> None:
    """The ``fusion:`` section: names and priorities the schema cannot check (the same
    rules as :func:`beehave.fusion.make_inputs`, reported with the file and key path)."""
    from beehave.fusion import check_name, make_inputs, make_locks

    for actuator, spec in config.fusion.items():
        try:
            check_name("actuator", actuator)
            params = spec.arbiter_params(actuator)
            make_inputs(actuator, params["inputs"])
            make_locks(actuator, params["locks"])
        except ConfigError as exc:
            raise ConfigError(f"{config.source}: fusion.{actuator}: {exc}") from None


_HAL_ENTRY = "a HAL name (str) or a mapping {class: 'package.module:Class', name: …, params: {…}}"


def _describe(err: Any) -> str:
    parts = list(err["loc"])
    if len(parts) >= 3 and parts[0] == "hals" and parts[2] in ("str", "HALSpec"):
        # pydantic tries each member of `str | HALSpec` and reports both; say what fits.
        if len(parts) > 3:  # inside a mapping: the HALSpec branch has the real problem
            del parts[2]
        elif isinstance(err["input"], dict):
            return "" if parts[2] == "str" else f"hals.{parts[1]}: {err['msg']}"
        else:
            return f"hals.{parts[1]}: expected {_HAL_ENTRY} (got {err['input']!r:.60})"
    loc = ".".join(str(p) for p in parts) or "<top>"
    if err["type"] == "extra_forbidden":
        return f"{loc}: unknown key; valid keys: {', '.join(_valid_keys(parts))}"
    return f"{loc}: {err['msg']} (got {err['input']!r:.60})"


def _valid_keys(loc: list[Any]) -> list[str]:
    """The keys allowed beside the unknown one at ``loc`` (its last element)."""
    nested: dict[str, type[BaseModel]] = {"behaviors": ClassSpec, "logics": ClassSpec,
                                          "hals": HALSpec, "ros": RosOptions,
                                          "sim": SimOptions, "agent": AgentOptions,
                                          "vda5050": Vda5050Options,
                                          "recording": RecordingOptions}
    model = nested.get(str(loc[0]), RobotConfig) if len(loc) > 1 else RobotConfig
    if len(loc) > 2 and loc[0] == "vda5050" and loc[1] == "broker":
        model = BrokerOptions
    if loc[0] == "fusion" and len(loc) > 2:  # fusion.<actuator>[.inputs.<source>].<key>
        model = FusionOptions if len(loc) <= 4 else (
            FusionLockOptions if loc[2] == "locks" else FusionInputOptions)
    return [field.alias or name for name, field in model.model_fields.items()
            if name != "source"]


def hal_names(config: RobotConfig) -> list[str]:
    """The names of the HALs ``config`` gives, in order: a string entry is its name, a
    ``{class: …}`` entry its ``name`` or else its class's (what ``beehave run`` registers)."""
    from beehave.hal import HAL

    return [spec if isinstance(spec, str) else spec.name or import_class(
        spec.class_, base=HAL, where=f"{config.source}: hals.{i}.class").name
        for i, spec in enumerate(config.hals)]


def import_class(path: str, *, where: str, base: type[Any]) -> type[Any]:
    """``package.module:Class`` → the class, which must derive from ``base``; errors name
    ``where`` (file and key path)."""
    module_name, _, attr = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{where}: cannot import module {module_name!r}: {exc} (import "
                          f"paths are looked up in the installed packages, the current "
                          f"directory under `beehave`, then the configuration file's "
                          f"directory)") from exc
    try:
        obj = module
        for part in attr.split("."):
            obj = getattr(obj, part)
    except AttributeError:
        public = sorted(n for n in vars(module) if not n.startswith("_")
                        and isinstance(getattr(module, n), type))
        raise ConfigError(f"{where}: module {module_name!r} has no {attr!r}; classes there: "
                          f"{', '.join(public) or 'none'}") from None
    if not isinstance(obj, type):
        raise ConfigError(f"{where}: {path!r} is not a class")
    if not issubclass(obj, base):
        raise NotASubclass(f"{where}: {path!r} is not a {base.__name__} subclass")
    return obj
