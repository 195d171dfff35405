"""Tutorial example (docs/tutorial.md, section 1): a patrol that can be switched to
charging at runtime. The tutorial's code blocks, one after the other, are this file.

Run it: ``.venv/bin/python examples/patrol.py``
"""

from __future__ import annotations

import time

from beehave import Action, ActionTypeBusy, Behavior, HighLevelBehaviorManager


class Robot:
    """Stands in for real hardware: a position on a line and a speed."""

    def __init__(self) -> None:
        self.x_m = 0.0
        self.speed_mps = 0.0


class DriveTo(Action):
    action_type = "driving"  # only one driving action at a time, in any behaviour

    def __init__(self, robot: Robot, goal_m: float) -> None:
        self.robot, self.goal_m = robot, goal_m

    def run(self) -> float:
        while abs(self.goal_m - self.robot.x_m) > 0.05:
            if self.interrupted:  # cooperative: stop soon after being asked
                return self.robot.x_m
            self.robot.speed_mps = 0.5 if self.goal_m > self.robot.x_m else -0.5
            self.robot.x_m += self.robot.speed_mps * 0.02
            self.sleep(0.02)  # returns early when interrupted
        self.robot.speed_mps = 0.0
        return self.robot.x_m

    def safe_state(self) -> None:
        # Called once whenever the action ends without success: leave the wheels still.
        self.robot.speed_mps = 0.0


class Patrol(Behavior):
    def __init__(self, robot: Robot, waypoints_m: list[float]) -> None:
        self.robot, self.waypoints_m = robot, waypoints_m

    def run(self) -> None:
        while not self.interrupted:
            for goal in self.waypoints_m:
                drive = self.start_action(DriveTo(self.robot, goal))
                drive.wait()  # wakes when the drive ends, also when we are interrupted
                if self.interrupted:
                    return


class Charge(Behavior):
    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        self.speed_at_start_mps: float | None = None
        self.refused: ActionTypeBusy | None = None

    def run(self) -> str:
        # A switch starts us only after the old behaviour and its actions have ended.
        self.speed_at_start_mps = self.robot.speed_mps
        dock = self.start_action(DriveTo(self.robot, 0.0))
        try:
            self.start_action(DriveTo(self.robot, 5.0))  # "driving" is taken by `dock`
        except ActionTypeBusy as busy:
            self.refused = busy
        dock.wait()
        return "docked"


def main() -> None:
    robot = Robot()
    with HighLevelBehaviorManager(stop_timeout_s=1.0) as hl:
        hl.register("patrol", Patrol, robot=robot, waypoints_m=[1.0, 0.5])
        hl.register("charge", Charge, robot=robot)
        hl.switch("patrol")
        time.sleep(1.0)
        print("patrolling at x =", round(robot.x_m, 2), "speed", robot.speed_mps)
        charge = hl.switch("charge")  # returns once patrol and its drive have ended
        charge.wait(10)
        print("switched; speed right after the switch:", charge.speed_at_start_mps)
        print("refused:", charge.refused)
        print("charge:", charge.status.name, charge.result)
        # When a top-level behaviour ends on its own, the manager runs "idle" again.
        for record in hl.history:
            print(f"  {record['name']:>7} {record['status']:<12} {record['elapsed_s']:.2f} s")


if __name__ == "__main__":
    main()
