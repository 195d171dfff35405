"""``beehave plot``: a recording as a picture -- a Gantt chart of what ran, series below.

For each robot: one row per behaviour, action and top-level logic, a bar for each time it
ran, coloured by how it ended (succeeded, failed, interrupted, stuck, still running when
the recording ended), switches marked; under it the chosen blackboard series (speed,
battery, distances). The time axis is seconds since the recording's start, sim time when
the robot ran on it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from beehave.blackboard import from_json
from beehave.errors import RecordingError
from beehave.recording import schema
from beehave.recording.reader import Recording

DEFAULT_SERIES = ("odom/linear_mps", "battery/percentage", "laser/front_m", "lift/height_m")
"""Drawn under each robot's chart when recorded (on its blackboard or as a ROS topic)."""

COLOURS = {"SUCCEEDED": "#2e9e44", "FAILED": "#d62728", "INTERRUPTED": "#ff9f1c",
           "STUCK": "#8c1c8c", "RUNNING": "#7f7f7f"}


@dataclass(frozen=True)
class Bar:
    row: str
    start_s: float
    end_s: float
    status: str


def _timeline(recording: Recording, prefix: str) -> Any:
    sim = recording.sim_time(prefix)
    start = recording.start_ns
    if sim is None:
        return lambda t_ns: (t_ns - start) / 1e9
    sim0 = sim(start)
    return lambda t_ns: sim(t_ns) - sim0


def bars(recording: Recording, prefix: str) -> tuple[list[Bar], list[tuple[float, str]]]:
    """The Gantt bars of robot ``prefix`` (behaviours and actions from the high-level
    events, top-level logics from the low-level ones) and its switches (time, name)."""
    at = _timeline(recording, prefix)
    end = at(recording.end_ns)
    out: list[Bar] = []
    switches: list[tuple[float, str]] = []
    for level in (schema.EVENTS_HIGH, schema.EVENTS_LOW):
        open_: dict[str, float] = {}
        for m in recording.of(schema.topic(prefix, level)):
            kind, subject = m.data["kind"], m.data["subject"]
            if subject.startswith(("hal:", "blackboard:")):
                continue
            if level == schema.EVENTS_LOW and "/" in subject:
                continue  # sub-logics: the top-level logic's row says enough
            t = at(m.log_time_ns)
            row = subject if level == schema.EVENTS_HIGH else f"logic: {subject}"
            if kind == "started":
                open_[row] = t
            elif kind in ("ended", "stuck") and row in open_:
                status = "STUCK" if kind == "stuck" else (m.data["status"] or "SUCCEEDED")
                out.append(Bar(row, open_.pop(row), t, status))
            elif kind == "switch_completed" and level == schema.EVENTS_HIGH:
                switches.append((t, subject))
        out += [Bar(row, t0, end, "RUNNING") for row, t0 in open_.items()]
    return out, switches


def _front_m(scan: Any) -> float:
    n = len(scan.ranges)
    hits = [r for i, r in enumerate(scan.ranges)
            if abs(scan.angle_min + i * scan.angle_increment) <= math.pi / 4
            and scan.range_min <= r <= scan.range_max]
    return min(hits) if n and hits else math.nan


ROS_SERIES: dict[str, tuple[str, Any]] = {
    "odom/linear_mps": ("odom", lambda m: m.twist.twist.linear.x),
    "odom/angular_rps": ("odom", lambda m: m.twist.twist.angular.z),
    "battery/percentage": ("battery_state", lambda m: m.percentage * 100.0),
    "laser/front_m": ("scan", _front_m),
    "cmd_vel/linear_mps": ("cmd_vel", lambda m: m.linear.x),
}
"""Series a plot can take from a recorded ROS 2 topic when no HAL put them on the
blackboard (the same keys and units as the mobile-base HALs)."""


def _ros_series(recording: Recording, prefix: str, key: str
                ) -> tuple[list[float], list[float]] | None:
    source = ROS_SERIES.get(key)
    if source is None:
        return None
    messages = recording.of(schema.topic(prefix, source[0]))
    if not messages:
        return None
    at = _timeline(recording, prefix)
    step = max(1, len(messages) // 1000)  # a picture needs no more points than pixels
    picked = messages[::step]
    decode = _decoder(recording, picked[0].schema_name)
    return ([at(m.log_time_ns) for m in picked],
            [float(source[1](decode(m.data))) for m in picked])


def _decoder(recording: Recording, schema_name: str) -> Any:
    """rclpy's deserializer (C, fast) when ROS 2 is installed, else mcap_ros2's."""
    try:
        from rclpy.serialization import deserialize_message

        from beehave.recording.recorder import message_type

        msg_type = message_type(schema_name, where="plot")
        return lambda data: deserialize_message(data, msg_type)
    except (ImportError, RecordingError):
        from beehave.recording.reader import ros_decoder

        return ros_decoder(recording, schema_name)


def available(recording: Recording, prefix: str) -> set[str]:
    """The series :func:`series` can draw for robot ``prefix``."""
    keys = {m.data["key"] for m in recording.of(schema.topic(prefix, schema.BLACKBOARD))}
    keys |= {k for k, (topic, _) in ROS_SERIES.items()
             if schema.topic(prefix, topic) in recording.channels}
    return keys


def series(recording: Recording, prefix: str, key: str) -> tuple[list[float], list[float]]:
    """The numeric values of blackboard ``key`` over time (stale and non-numbers left
    out); from the recorded ROS topic (:data:`ROS_SERIES`) when the blackboard lacks it."""
    at = _timeline(recording, prefix)
    ts: list[float] = []
    vs: list[float] = []
    for m in recording.of(schema.topic(prefix, schema.BLACKBOARD)):
        if m.data["key"] != key or m.data["stale"]:
            continue
        value = from_json(m.data["value"])
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        ts.append(at(m.log_time_ns))
        vs.append(float(value) if math.isfinite(value) else math.nan)
    if not ts:
        from_ros = _ros_series(recording, prefix, key)
        if from_ros is not None:
            return from_ros
    return ts, vs


def _short(value: Any) -> Any:
    """``value`` with its floats to 4 significant digits (float32 colours print long)."""
    if isinstance(value, float):
        return float(f"{value:.4g}")
    if isinstance(value, (list, tuple)):
        return [_short(v) for v in value]
    if isinstance(value, dict):
        return {k: _short(v) for k, v in value.items()}
    return value


def _values_of(recording: Recording, prefix: str, key: str, limit: int = 5) -> str:
    seen: list[str] = []
    for m in recording.of(schema.topic(prefix, schema.BLACKBOARD)):
        if m.data["key"] == key:
            text = repr(_short(from_json(m.data["value"])))
            if text not in seen:
                seen.append(text)
            if len(seen) > limit:
                break
    more = ", …" if len(seen) > limit else ""
    return ", ".join(seen[:limit]) + more if seen else "none recorded"


def _numeric(recording: Recording, prefix: str) -> list[str]:
    return sorted(k for k in available(recording, prefix) if series(recording, prefix, k)[0])


def plot(recording: Recording, out: str | Path, *, robots: Sequence[str] | None = None,
         keys: Sequence[str] | None = None, title: str | None = None) -> Path:
    """Draw ``recording`` into the picture ``out`` (PNG, SVG or PDF by its suffix) and
    return its path. ``robots``: the prefixes to show (default all); ``keys``: the
    blackboard series (default: those of :data:`DEFAULT_SERIES` that were recorded)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    shown = list(robots) if robots else recording.prefixes
    unknown = [r for r in shown if r not in recording.prefixes]
    if unknown or not shown:
        what = (f"no robot {', '.join(map(repr, unknown))} in it" if unknown
                else "no robot recorded in it")
        raise RecordingError(f"{recording.files[0]}: nothing to plot: {what}; robots "
                             f"recorded: {', '.join(map(repr, recording.prefixes)) or 'none'}")
    panels: list[tuple[str, str, Any]] = []  # (robot, "gantt" | key, data)
    for prefix in shown:
        panels.append((prefix, "gantt", bars(recording, prefix)))
        present = available(recording, prefix)
        wanted = list(keys) if keys else [k for k in DEFAULT_SERIES if k in present]
        missing = [k for k in wanted if k not in present]
        if keys and missing and len(missing) == len(wanted):
            raise RecordingError(f"{recording.files[0]}: robot {prefix!r} has no blackboard "
                                 f"key {missing}; recorded keys include: "
                                 f"{', '.join(sorted(present)[:20])}")
        for key in wanted:
            if key in present:
                data = series(recording, prefix, key)
                if keys and not data[0]:
                    raise RecordingError(
                        f"{recording.files[0]}: robot {prefix!r}: blackboard key {key!r} has "
                        f"no numbers to plot; its values: {_values_of(recording, prefix, key)}"
                        f"; keys with numbers: {', '.join(_numeric(recording, prefix)[:20])}")
                panels.append((prefix, key, data))
    heights = []
    for _, kind, data in panels:
        heights.append(max(1.5, 0.35 * len({b.row for b in data[0]}) + 0.8)
                       if kind == "gantt" else 1.3)
    fig, axes = plt.subplots(len(panels), 1, figsize=(12, sum(heights) + 0.8), sharex=True,
                             gridspec_kw={"height_ratios": heights}, squeeze=False)
    for ax, (prefix, kind, data) in zip(axes[:, 0], panels, strict=True):
        if kind == "gantt":
            found, switches = data
            rows = list(dict.fromkeys(b.row for b in sorted(found, key=lambda b: b.start_s)))
            for b in found:
                y = rows.index(b.row)
                colour = COLOURS.get(b.status, "#1f77b4")
                ax.broken_barh([(b.start_s, max(b.end_s - b.start_s, 1e-3))], (y - 0.38, 0.76),
                               facecolors=colour, edgecolor="black", linewidth=0.3)
                if b.end_s - b.start_s < 0.05 and b.status != "RUNNING":
                    # Too short for a bar: a mark in its colour, not a blank running row.
                    ax.plot([b.start_s], [y], marker="D", markersize=4, color=colour,
                            markeredgecolor="black", markeredgewidth=0.3)
            for t, name in switches:
                ax.axvline(t, color="black", linestyle=":", linewidth=0.8)
                ax.text(t, len(rows) - 0.4, f" → {name}", fontsize=7, va="bottom")
            ax.set_yticks(range(len(rows)), rows, fontsize=7)
            ax.set_ylim(-0.7, len(rows) + 0.2)
            ax.invert_yaxis()
            ax.set_title(f"{prefix or 'robot'}: behaviours, actions and logics", fontsize=9,
                         loc="left")
            ax.grid(axis="x", alpha=0.3)
        else:
            ts, vs = data
            ax.step(ts, vs, where="post", linewidth=1.0)
            ax.set_ylabel(kind, fontsize=7, rotation=0, ha="right", va="center")
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time since the start of the recording (s)"
                           + (", sim time" if recording.sim_time(shown[0]) else ""))
    fig.legend(handles=[Patch(color=c, label=s.lower()) for s, c in COLOURS.items()],
               loc="upper right", ncol=len(COLOURS), fontsize=7, frameon=False)
    # The title's span on the same axis as the plot (sim time when the robot ran on it).
    at = _timeline(recording, shown[0])
    span = at(recording.end_ns) - at(recording.start_ns)
    clock = ", sim time" if recording.sim_time(shown[0]) else ""
    notes = (" (truncated)" if recording.truncated else "") + \
        (" (DAMAGED)" if recording.damaged else "")
    fig.suptitle(title or f"{recording.files[0].name}: {span:.1f} s{clock}{notes}",
                 fontsize=10, x=0.01, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
