"""What a recording holds: channel names, their JSON schemas, ROS 2 message definitions.

Every beehave channel is JSON with a JSON Schema (MCAP ``json`` encoding), so Foxglove
shows and plots it as it is. Channels of one robot share a prefix (its namespace)::

    /<robot>/beehave/blackboard     every stored blackboard change
    /<robot>/beehave/events/high    high-level lifecycle events (behaviours, actions …)
    /<robot>/beehave/events/low     low-level events (logic switches, HAL loads …)
    /<robot>/beehave/outputs        HAL commands the logics gave (set_color, show …)
    /<robot>/beehave/clock          sim time beside wall time (robots on sim time)
    /<robot>/beehave/engines/structure  each decision engine's structure, once per id
    /<robot>/beehave/engines/state  each engine's state whenever it changes
    /<robot>/<topic>                ROS 2 topics, ros2msg/CDR (odom, scan, cmd_vel …):
                                    those of the configuration, and every topic a
                                    behaviour subscribes to (lift/state, orders …)
    /<topic>                        a global topic a behaviour subscribes to
    /beehave/recorder               the recorder's own counts (written, dropped)

A recording without a prefix (a bare blackboard in a test) uses ``/beehave/...``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from beehave.errors import RecordingError

BLACKBOARD = "beehave/blackboard"
EVENTS_HIGH = "beehave/events/high"
EVENTS_LOW = "beehave/events/low"
OUTPUTS = "beehave/outputs"
CLOCK = "beehave/clock"
LOG = "beehave/log"
TF = "beehave/tf"
ENGINE_STRUCTURE = "beehave/engines/structure"
ENGINE_STATE = "beehave/engines/state"
RECORDER = "/beehave/recorder"

PROFILE = ""
"""The MCAP profile: none. The ``ros2`` profile requires every channel to be CDR with
``offered_qos_profiles`` metadata, and beehave's own channels are JSON; readers (Foxglove,
``mcap-ros2-support``) decode each channel by its schema's encoding, profile or not."""

_TIME = {"type": "number", "description": "time.time() when it happened (s)"}


_FOXGLOVE_TIME = {"type": "object", "title": "time",
                  "properties": {"sec": {"type": "integer", "minimum": 0},
                                 "nsec": {"type": "integer", "minimum": 0}}}
"""Foxglove's time: seconds and nanoseconds (``foxglove.Log``, ``foxglove.FrameTransform``)."""


def _object(title: str, description: str, properties: dict[str, Any],
            required: list[str]) -> dict[str, Any]:
    """The JSON Schema of a JSON object (each beehave channel's message is one)."""
    return {"title": title, "description": description, "type": "object",
            "properties": properties, "required": required}


SCHEMAS: dict[str, dict[str, Any]] = {s["title"]: s for s in (
    _object("beehave.BlackboardChange",
            "One stored blackboard change (beehave.blackboard.Change).",
            {"key": {"type": "string"},
             "value": {"description": "strict JSON; non-finite floats as {\"$float\": \"inf\"}"},
             "stamp": _TIME,
             "writer": {"type": ["string", "null"],
                        "description": "hal:<name>, logic:<path>, ros:<bridge> or null"},
             "stale": {"type": "boolean"},
             "batch": {"type": "integer",
                       "description": "changes with one batch were stored between the "
                                      "same two looks of the logics at the blackboard: "
                                      "a replay feeds them together (absent: blackboard "
                                      "not bound to a loop, or an older recording)"}},
            ["key", "value", "stamp", "writer", "stale"]),
    _object("beehave.Event", "One lifecycle event (beehave.events.Event); a high-level "
            "switch_requested has detail.source: 'external' or the path of the behaviour "
            "that asked (absent in recordings older than it: a replay takes them all as "
            "external).",
            {"kind": {"type": "string"}, "subject": {"type": "string"},
             "status": {"type": ["string", "null"]}, "error": {"type": ["string", "null"]},
             "detail": {"type": "object"}, "stamp": _TIME},
            ["kind", "subject", "status", "error", "detail", "stamp"]),
    _object("beehave.HalCommand",
            "A HAL method a logic (or a safe state) called to drive hardware.",
            {"hal": {"type": "string"}, "method": {"type": "string"},
             "args": {"type": "array"}, "kwargs": {"type": "object"}, "stamp": _TIME},
            ["hal", "method", "args", "kwargs", "stamp"]),
    _object("foxglove.Log",
            "Each event of both levels once more, as Foxglove's Log panel reads it (the "
            "schema foxglove.Log): level 2 INFO, 3 WARNING (STUCK, a safe state that "
            "failed …), 4 ERROR (something that FAILED); name: <robot>/high or /low.",
            {"timestamp": _FOXGLOVE_TIME,
             "level": {"type": "integer", "enum": [0, 1, 2, 3, 4, 5]},
             "message": {"type": "string"}, "name": {"type": "string"},
             "file": {"type": "string"}, "line": {"type": "integer", "minimum": 0}},
            ["timestamp", "level", "message", "name", "file", "line"]),
    _object("foxglove.FrameTransform",
            "The robot's pose from its odometry, as Foxglove's 3D panel reads frames: "
            "parent_frame_id (map) to child_frame_id (<robot>/base_link, the frame of "
            "the laser scans).",
            {"timestamp": _FOXGLOVE_TIME,
             "parent_frame_id": {"type": "string"}, "child_frame_id": {"type": "string"},
             "translation": {"type": "object", "properties": {
                 "x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}},
             "rotation": {"type": "object", "properties": {
                 "x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"},
                 "w": {"type": "number"}}}},
            ["timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"]),
    _object("beehave.ClockSample", "The robot's sim time at a wall time: replay paces by it.",
            {"sim_time_s": {"type": "number"}, "stamp": _TIME},
            ["sim_time_s", "stamp"]),
    _object("beehave.EngineStructure",
            "What a running behaviour's decision engine is made of (what the web view "
            "draws as a graph: DecisionEngine.structure()), recorded once per structure_id "
            "(a hash of it) when an engine with that id is first seen.",
            {"path": {"type": "string", "description": "the behaviour the engine drives"},
             "structure_id": {"type": "string"},
             "structure": {"type": "object", "description": "DecisionEngine.structure(): "
                           "kind, states and transitions or tree nodes"},
             "stamp": _TIME},
            ["path", "structure_id", "structure", "stamp"]),
    _object("beehave.EngineState",
            "Where a running behaviour's decision engine is (DecisionEngine.describe(): a "
            "state machine's state and last_transition, a tree's node statuses, with its "
            "structure_id), recorded whenever it changes (a tree's tick count alone is no "
            "change); engine null: the behaviour no longer runs an engine.",
            {"path": {"type": "string"},
             "engine": {"type": ["object", "null"]}, "stamp": _TIME},
            ["path", "engine", "stamp"]),
    _object("beehave.RecorderStats",
            "How many messages the recorder wrote and dropped so far.",
            {"written": {"type": "integer"}, "dropped": {"type": "integer"},
             "dropped_by_channel": {"type": "object"}, "stamp": _TIME},
            ["written", "dropped", "stamp"]),
)}


CHANNEL_SCHEMA = {BLACKBOARD: "beehave.BlackboardChange", EVENTS_HIGH: "beehave.Event",
                  EVENTS_LOW: "beehave.Event", OUTPUTS: "beehave.HalCommand",
                  CLOCK: "beehave.ClockSample", LOG: "foxglove.Log",
                  TF: "foxglove.FrameTransform", ENGINE_STRUCTURE: "beehave.EngineStructure",
                  ENGINE_STATE: "beehave.EngineState"}


def schema_bytes(name: str) -> bytes:
    return json.dumps(SCHEMAS[name], sort_keys=True).encode()


def topic(prefix: str, channel: str) -> str:
    """The MCAP topic of ``channel`` for the robot ``prefix`` (``""``: no robot)."""
    prefix = prefix.strip("/")
    return f"/{prefix}/{channel}" if prefix else f"/{channel}"


# ---- ROS 2 message definitions (the ros2msg schema of a ROS channel) ---------------------

def ros_type_name(msg_type: type) -> str:
    """``nav_msgs/msg/Odometry`` for the Python class of that message."""
    module = msg_type.__module__.split(".")  # nav_msgs.msg._odometry
    return f"{module[0]}/msg/{msg_type.__name__}"


def _msg_file(package: str, name: str) -> Path:
    try:
        from ament_index_python.packages import get_package_share_directory

        share = Path(get_package_share_directory(package))
    except Exception:  # no ament index (a bare wheel install): next to the interpreter
        import sys

        share = Path(sys.prefix) / "share" / package
    return share / "msg" / f"{name}.msg"


def _nested(field_type: str) -> str | None:
    """``geometry_msgs/Pose`` out of ``sequence<geometry_msgs/Pose, 5>`` or ``x/Y[3]``."""
    inner = field_type
    if inner.startswith("sequence<"):
        inner = inner[len("sequence<"):].rstrip(">").split(",")[0].strip()
    inner = inner.split("[")[0]
    return inner if "/" in inner else None


def ros_msgdef(msg_type: type) -> str:
    """The ``ros2msg`` definition of ``msg_type``: its ``.msg`` text followed by those of
    the types it uses, each after a ``===`` line and ``MSG: pkg/Type`` (what rosbag2
    writes, so Foxglove and ``mcap-ros2-support`` decode the CDR data)."""
    seen: list[str] = []
    texts: dict[str, str] = {}

    def visit(cls: type) -> None:
        package = cls.__module__.split(".")[0]
        full = f"{package}/{cls.__name__}"
        if full in texts:
            return
        path = _msg_file(package, cls.__name__)
        try:
            texts[full] = path.read_text()
        except OSError as exc:
            raise RecordingError(f"no message definition for {full} at {path}: {exc}; "
                                 "its package's share/ folder must be installed") from exc
        seen.append(full)
        for field_type in cls.get_fields_and_field_types().values():  # type: ignore[attr-defined]
            nested = _nested(field_type)
            if nested is None:
                continue
            pkg, name = nested.split("/")
            import importlib

            module = importlib.import_module(f"{pkg}.msg")
            visit(getattr(module, name))

    visit(msg_type)
    first, *rest = seen
    parts = [texts[first].rstrip("\n")]
    for full in rest:
        parts.append("=" * 80 + f"\nMSG: {full}\n" + texts[full].rstrip("\n"))
    return "\n".join(parts) + "\n"
