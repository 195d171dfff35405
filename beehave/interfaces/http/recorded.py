"""The read-only API of ``beehave view FILE.mcap``: a recording behind the live page.

The page asks ``GET /api/robots`` as it does of a live robot; a ``"recording"`` there
tells it to play a timeline instead of opening the stream. It then reads each moment with
``GET /api/recording/at?t=T`` (every robot's snapshot, blackboard, events and trail at T,
from :class:`~beehave.recording.timeline.RecordingTimeline`: bisections, no replay) and
the plots with ``GET /api/robots/{robot}/series?keys=…``. The live read endpoints answer
too, with ``?t=`` (default: the end), and ``GET /api/robots/{robot}/structure`` gives the
recorded structures of the robot's decision engines, so the page draws the same graphs.
Commands are refused with 405: a recording cannot be switched, stopped, paused, or given
breakpoints.
"""

from collections.abc import Callable
from typing import Annotated, Any, TypeVar

from fastapi import FastAPI, Query

from beehave.breakpoints import KINDS as BREAKPOINT_KINDS
from beehave.errors import RecordingError
from beehave.recording.timeline import RecordingTimeline

_T = TypeVar("_T")

#: The most keys one ``GET …/series`` reads (each is a pass over the recording; the page
#: asks a few at a time).
MAX_SERIES_KEYS = 100

#: The commands of a live robot, refused on a recording.
COMMANDS = ("switch", "stop", "pause", "resume", "breakpoints", "breakpoints/remove",
            "continue")


def add_recording_routes(app: FastAPI, timeline: RecordingTimeline, read: Any,
                         http_error: type[Exception]) -> None:
    """Add the recording's routes to ``app`` ahead of the live ones (the first route that
    matches answers). ``read``: the read-access dependency; ``http_error(status, error,
    detail)``: the app's error."""
    names = list(timeline.robots)

    def robot_of(robot: str) -> str:
        if robot not in timeline.robots:
            raise http_error(404, "UnknownRobot", f"unknown robot {robot!r}; recorded: "
                             f"{', '.join(repr(n) for n in names) or 'none'}")
        return robot

    def moment(t: float | None) -> float:
        return timeline.duration_s if t is None else t

    def answer(call: Callable[[], _T]) -> _T:
        try:
            return call()
        except RecordingError as exc:
            raise http_error(422, "BadRecordingQuery", str(exc)) from None

    T = Annotated[float | None, Query(description="seconds since the start of the "
                                                  "recording (default: its end)")]

    @app.get("/api/recording", summary="The recording served: duration, robots, files")
    def recording(_: read) -> dict[str, Any]:
        return describe(timeline)

    @app.get("/api/recording/at", summary="Every robot at time t: snapshot, blackboard, "
                                          "events, trail")
    def at(_: read, t: Annotated[float, Query(description="seconds since the start")]
           ) -> dict[str, Any]:
        return answer(lambda: {"t_s": t, "robots": {n: timeline.state_at(n, t)
                                                    for n in names}})

    @app.get("/api/robots", summary="The robots recorded")
    def robots(_: read) -> dict[str, Any]:
        return {"robots": [{"name": n, "behavior": None, "logic": None} for n in names],
                "auth": {}, "world": False, "fleet": False, "recording": describe(timeline)}

    @app.get("/api/robots/{robot}/series", summary="Blackboard values over the recording")
    def series(_: read, robot: str,
               keys: Annotated[str, Query(description="comma-separated keys")] = ""
               ) -> dict[str, Any]:
        name = robot_of(robot)
        wanted = list(dict.fromkeys(k for k in keys.split(",") if k))  # each key read once
        if len(wanted) > MAX_SERIES_KEYS:
            raise http_error(422, "BadRecordingQuery", f"{len(wanted)} keys asked: at most "
                             f"{MAX_SERIES_KEYS} a request")
        return answer(lambda: {"keys": timeline.keys(name),
                               "series": timeline.series(name, wanted)})

    @app.get("/api/robots/{robot}/snapshot", summary="What ran at t")
    def snapshot(_: read, robot: str, t: T = None) -> dict[str, Any]:
        name = robot_of(robot)
        return answer(lambda: timeline.snapshot_at(name, moment(t)))

    @app.get("/api/robots/{robot}/status", summary="What ran at t")
    def status(_: read, robot: str, t: T = None) -> dict[str, Any]:
        return snapshot(None, robot, t)

    @app.get("/api/robots/{robot}/blackboard", summary="The blackboard at t")
    def blackboard(_: read, robot: str, t: T = None) -> dict[str, Any]:
        name = robot_of(robot)
        return answer(lambda: timeline.blackboard_at(name, moment(t)))

    @app.get("/api/robots/{robot}/events", summary="The events up to t")
    def events(_: read, robot: str, t: T = None) -> list[dict[str, Any]]:
        name = robot_of(robot)
        return answer(lambda: timeline.events_at(name, moment(t)))

    @app.get("/api/robots/{robot}/structure",
             summary="The recorded structures of the robot's decision engines (every one, "
                     "or with ?t= those running at t)")
    def structure(_: read, robot: str, t: T = None) -> dict[str, Any]:
        name = robot_of(robot)
        return answer(lambda: {"engines": timeline.structures(name, t)})

    @app.get("/api/robots/{robot}/breakpoints",
             summary="None: a recording cannot be paused")
    def breakpoints(_: read, robot: str) -> dict[str, Any]:
        robot_of(robot)
        return {"breakpoints": {}, "hit": None, "paused": False,
                "choices": {kind: [] for kind in BREAKPOINT_KINDS}}

    @app.get("/api/robots/{robot}/behaviors", summary="None: a recording runs nothing")
    def behaviors(_: read, robot: str) -> list[dict[str, Any]]:
        robot_of(robot)
        return []

    @app.get("/api/robots/{robot}/logics", summary="None: a recording runs nothing")
    def logics(_: read, robot: str) -> list[dict[str, Any]]:
        robot_of(robot)
        return []

    def refuser(command: str) -> Any:
        def refuse(robot: str) -> None:
            robot_of(robot)  # an unknown robot is named as such, not as a recording
            raise http_error(405, "RecordingReadOnly", f"{robot!r} is a recording, served "
                             f"read-only by `beehave view`: {command} needs a live robot "
                             "(`beehave run ROBOT.yaml --http`)")
        return refuse

    for command in COMMANDS:
        app.add_api_route(f"/api/robots/{{robot}}/{command}", refuser(command),
                          methods=["POST"], include_in_schema=False)


def describe(timeline: RecordingTimeline) -> dict[str, Any]:
    rec = timeline.recording
    return {"files": [str(f) for f in rec.files], "duration_s": round(timeline.duration_s, 6),
            "start_stamp": timeline.start_ns / 1e9, "robots": list(timeline.robots),
            "truncated": rec.truncated, "damaged": rec.describe_damage()}


__all__ = ["COMMANDS", "MAX_SERIES_KEYS", "add_recording_routes", "describe"]
