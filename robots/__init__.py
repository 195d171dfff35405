"""Simulated robots (EMILI, Kobuki) and worlds in pybullet — see docs/simulation.md.

``from robots import Simulation, load_world``. The names load lazily, so importing the
package does not import pybullet (the ``sim`` extra) until a simulation is used.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Simulation": "robots.sim", "SimState": "robots.sim", "ROBOT_KINDS": "robots.sim",
    "SimRobot": "robots.robot", "Odometry": "robots.robot", "Pose2D": "robots.robot",
    "LaserScan": "robots.robot", "BatteryState": "robots.robot",
    "Emili": "robots.emili", "Kobuki": "robots.kobuki",
    "World": "robots.world", "load_world": "robots.world", "world_from_dict": "robots.world",
    "available_worlds": "robots.world",
    "Factory": "robots.factory", "FactoryFacts": "robots.factory",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'robots' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
