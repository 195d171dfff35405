"""Simulation plugins: how ``beehave run`` (``sim:``) and ``beehave sim`` find a simulator.

The framework knows no simulator. A package offers one through the entry-point group
``beehave.simulations`` — as HAL plugins are found through ``beehave.hals`` — naming an
object with two callables::

    [project.entry-points."beehave.simulations"]
    pybullet = "robots.node:PYBULLET"

- ``start(world, *, real_time_factor, ros)`` builds the world, puts its robots on ROS 2
  through ``ros`` (a :class:`~beehave.ros.context.RosContext`), starts stepping and returns
  a :class:`RunningSimulation`;
- ``main(argv)`` is the ``beehave sim`` command line; it returns the exit code;
- optionally ``world_data(world)``: the world named ``world`` (a name the simulator ships
  or a file) as JSON data, for the web view's map (``beehave run --http --world NAME``);
  it raises a :class:`~beehave.errors.BeehaveError` naming the worlds it knows.
"""

from __future__ import annotations

import importlib.metadata
from typing import TYPE_CHECKING, Any, Protocol

from beehave.errors import ConfigError

if TYPE_CHECKING:
    from beehave.ros.context import RosContext

ENTRY_POINT_GROUP = "beehave.simulations"
DEFAULT = "pybullet"


class RunningSimulation(Protocol):
    """What ``start`` returns: the simulation (for checks and pictures) and its end."""

    @property
    def sim(self) -> Any:
        """The simulator's own object (for pybullet: :class:`robots.sim.Simulation`)."""

    def close(self) -> None:
        """Stop stepping, take the robots off ROS 2 and free the simulator."""


class Simulator(Protocol):
    def start(self, world: str, *, real_time_factor: float | None,
              ros: RosContext) -> RunningSimulation: ...

    def main(self, argv: list[str]) -> int: ...


def load_simulator(name: str = DEFAULT) -> Simulator:
    """The simulator installed as ``name``; an unknown name lists the installed ones."""
    eps = {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
    ep = eps.get(name)
    if ep is None:
        raise ConfigError(f"no simulator {name!r} is installed (entry-point group "
                          f"{ENTRY_POINT_GROUP!r}); installed: {', '.join(sorted(eps)) or 'none'}")
    try:
        simulator: Simulator = ep.load()
    except Exception as exc:
        raise ConfigError(f"simulator {name!r}: cannot import {ep.value!r}: {exc!r}") from exc
    return simulator
