"""Errors of the simulated robots and worlds, under beehave's root :class:`BeehaveError`.

Messages name the thing (world file and key, robot namespace, station name) and, for a bad
name, what exists.
"""

from __future__ import annotations

from beehave.errors import BeehaveError, ConfigError, UnknownNameError


class WorldError(ConfigError):
    """A world file that cannot be read or does not validate.

    ``.path`` is the file (or ``"<dict>"``), ``.problems`` one line per problem, each naming
    the key path (``robots.1.start.x_m``), what was expected and what was found.
    """

    def __init__(self, path: str, problems: list[str]) -> None:
        self.path = path
        self.problems = problems
        lines = "\n  ".join(problems)
        super().__init__(f"invalid world {path}:\n  {lines}")


class UnknownWorld(UnknownNameError):
    kind = "world"


class UnknownStation(UnknownNameError):
    kind = "station"


class UnknownMachine(UnknownNameError):
    kind = "machine"


class UnknownZone(UnknownNameError):
    kind = "speed zone"


class UnknownRobot(UnknownNameError):
    kind = "robot namespace"


class SimulationError(BeehaveError):
    """The simulation was used in a way it cannot serve (stepped by hand while its thread
    runs, used after ``stop()``), or an ``on_step`` callback raised (``__cause__``)."""


class CommandOutOfRange(BeehaveError, ValueError):
    """A robot command outside the robot's limits (lift height, LED colour, button index)."""
