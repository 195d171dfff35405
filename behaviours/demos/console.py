"""The console demo of the high-level manager (``beehave demo``).

A point robot on a line drives, beeps and lifts under two top-level behaviours. The demo
shows actions of two types side by side, a type-lock rejection, a preemption and a switch
mid-drive, then checks that what it showed really happened (the robot stood still after
the switch, the lock was refused and then preempted).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from beehave import Action, ActionTypeBusy, Behavior, Event, EventKind, HighLevelBehaviorManager

TICK_S = 0.05


@dataclass
class PointRobot:
    """A robot on a line: position, commanded speed, lift height, what it says."""

    x_m: float = 0.0
    speed_mps: float = 0.0
    lift_m: float = 0.0
    sounds: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def step(self, dt_s: float) -> None:
        with self.lock:
            self.x_m += self.speed_mps * dt_s


class Drive(Action):
    """Drive to ``goal_m`` at up to ``speed_mps``; safe state: zero speed."""

    action_type = "driving"

    def __init__(self, robot: PointRobot, goal_m: float, speed_mps: float = 1.0) -> None:
        self.robot, self.goal_m, self.speed_mps = robot, goal_m, speed_mps
        self.name = f"drive→{goal_m:g}m"

    def run(self) -> float:
        while not self.interrupted:
            error = self.goal_m - self.robot.x_m
            if abs(error) < 0.02:
                break
            self.robot.speed_mps = max(-self.speed_mps, min(self.speed_mps, 2.0 * error))
            self.robot.step(TICK_S)
            self.sleep(TICK_S)
        self.robot.speed_mps = 0.0
        return self.robot.x_m

    def safe_state(self) -> None:
        self.robot.speed_mps = 0.0


class Beep(Action):
    action_type = "sound"

    def __init__(self, robot: PointRobot, tune: str, times: int = 6) -> None:
        self.robot, self.tune, self.times = robot, tune, times
        self.name = f"sound:{tune}"

    def run(self) -> None:
        for _ in range(self.times):
            self.robot.sounds.append(self.tune)
            if not self.sleep(0.3):
                return


class Lift(Action):
    action_type = "lifting"

    def __init__(self, robot: PointRobot, height_m: float) -> None:
        self.robot, self.height_m = robot, height_m
        self.name = f"lift→{height_m:g}m"

    def run(self) -> float:
        while abs(self.robot.lift_m - self.height_m) > 1e-3 and self.sleep(TICK_S):
            step = max(-0.02, min(0.02, self.height_m - self.robot.lift_m))
            self.robot.lift_m += step
        return self.robot.lift_m


class Delivery(Behavior):
    """Drives to the drop-off while playing a tune; tries a second drive (refused), then
    preempts the drive with a closer goal."""

    def __init__(self, robot: PointRobot, findings: dict[str, object]) -> None:
        self.robot, self.findings = robot, findings

    def run(self) -> None:
        self.start_action(Drive(self.robot, goal_m=8.0))
        self.start_action(Beep(self.robot, "la-li-lu"))
        self.sleep(0.8)
        try:
            self.start_action(Drive(self.robot, goal_m=-3.0))
        except ActionTypeBusy as busy:
            self.findings["rejected"] = str(busy)
        self.sleep(0.4)
        self.start_action(Drive(self.robot, goal_m=12.0, speed_mps=1.5), preempt=True)
        self.findings["preempted"] = True
        while self.sleep(1.0):
            pass


class Maintenance(Behavior):
    """Stands still and lowers the lift."""

    def __init__(self, robot: PointRobot) -> None:
        self.robot = robot

    def run(self) -> None:
        self.start_action(Lift(self.robot, 0.0)).wait()
        self.start_action(Beep(self.robot, "maintenance", times=2)).wait()
        while self.sleep(1.0):
            pass


def _tree(snapshot: dict[str, Any], robot: PointRobot, log: list[str]) -> Group:
    table = Table(title=f"top-level: {snapshot['current']}", expand=False)
    for column in ("path", "status", "type", "elapsed"):
        table.add_column(column)

    def add(node: dict[str, Any], depth: int = 0) -> None:
        elapsed = node.get("elapsed_s") or 0.0
        status = str(node["status"])
        colour = {"RUNNING": "green", "INTERRUPTED": "yellow", "FAILED": "red",
                  "STUCK": "magenta"}.get(status, "white")
        table.add_row("  " * depth + str(node["name"]), Text(status, style=colour),
                      str(node.get("action_type", "")), f"{float(elapsed):.2f} s")
        for child in node.get("children", []):
            add(child, depth + 1)

    if snapshot["top"]:
        add(snapshot["top"])
    locks = ", ".join(f"{k}→{v['holder']}" for k, v in snapshot["locks"].items())
    state = Text(f"robot x={robot.x_m:5.2f} m  v={robot.speed_mps:4.2f} m/s  "
                 f"lift={robot.lift_m:4.2f} m   locks: {locks or '-'}")
    return Group(table, state, Text("\n".join(log[-8:]), style="dim"))


def run_highlevel_demo(console: Console) -> list[str]:
    """Run the scenario; return the list of problems (empty when everything happened)."""
    robot = PointRobot(lift_m=0.2)
    findings: dict[str, object] = {}
    log: list[str] = []

    def on_event(event: Event) -> None:
        if event.kind in (EventKind.STARTED, EventKind.ENDED, EventKind.LOCK_REJECTED,
                          EventKind.LOCK_PREEMPTED, EventKind.SWITCH_COMPLETED):
            log.append(f"{event.kind.value:>16}  {event.subject}  {event.status or ''}")

    problems: list[str] = []
    with HighLevelBehaviorManager(stop_timeout_s=1.0) as hl:
        hl.subscribe(on_event)
        hl.register("delivery", Delivery, robot=robot, findings=findings)
        hl.register("maintenance", Maintenance, robot=robot)
        with Live(console=console, refresh_per_second=10, transient=False) as live:
            hl.switch("delivery")
            deadline = time.monotonic() + 2.5
            while time.monotonic() < deadline:
                live.update(_tree(hl.snapshot(), robot, log))
                time.sleep(0.1)
            moving_before = robot.speed_mps
            x_at_switch = robot.x_m
            t0 = time.monotonic()
            hl.switch("maintenance")  # mid-drive
            switch_s = time.monotonic() - t0
            speed_after = robot.speed_mps
            x_after = robot.x_m
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                live.update(_tree(hl.snapshot(), robot, log))
                time.sleep(0.1)
            live.update(_tree(hl.snapshot(), robot, log))
        console.print()
        console.print(f"switch delivery → maintenance took {switch_s * 1e3:.1f} ms "
                      f"(robot was moving at {moving_before:.2f} m/s)")
        if "rejected" not in findings:
            problems.append("the second driving action was not refused")
        else:
            console.print(f"[bold]type lock refused:[/] {findings['rejected']}")
        if not findings.get("preempted"):
            problems.append("the preemption did not happen")
        if moving_before == 0.0:
            problems.append("the robot was not driving when the switch came")
        if speed_after != 0.0 or abs(robot.x_m - x_after) > 1e-9:
            problems.append(f"the robot kept moving after the switch "
                            f"(v={speed_after}, x {x_after:.3f} → {robot.x_m:.3f})")
        if abs(robot.lift_m) > 1e-3:
            problems.append(f"maintenance did not lower the lift ({robot.lift_m:.3f} m)")
        if "maintenance" not in robot.sounds:
            problems.append("maintenance did not beep")
        console.print(f"robot stopped at x={x_at_switch:.2f}…{robot.x_m:.2f} m, "
                      f"lift {robot.lift_m:.2f} m, sounds: {robot.sounds}")
    return problems
