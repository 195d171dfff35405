"""HALs for the factory fleet's ATVs (docs/fleet.md).

HAL ``name``     what it does
``speed_limit``  sets the robot's ``max_speed_mps`` — the parameter of its high-level
                 node that every driving action obeys (:class:`behaviours.actions.SpeedLimit`)
                 — with a real ROS 2 parameter call, as ``ros2 param set`` would
"""

from __future__ import annotations

import math

from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters

from beehave.errors import HALError
from beehave.ros.hal import RosHAL

PARAM = "max_speed_mps"
SERVICE = "beehave_high_level/set_parameters"  # relative: the robot's namespace


class SpeedLimitHAL(RosHAL):
    """Sets ``max_speed_mps`` on the robot's high-level node (see the module docstring)."""

    name = "speed_limit"

    async def set_max_speed(self, mps: float, *, timeout_s: float = 2.0) -> None:
        """Limit the robot to ``mps`` (> 0; ``math.inf`` lifts the limit). Raises
        :class:`~beehave.errors.HALError` when the node refuses it or does not answer."""
        if isinstance(mps, bool) or not isinstance(mps, (int, float)) or not mps > 0:
            raise HALError(f"HAL {self.name!r}: max speed must be a number > 0 (m/s; inf: no "
                           f"limit), got {mps!r}")
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(mps))
        request = SetParameters.Request(parameters=[Parameter(name=PARAM, value=value)])
        response = await self.call(SetParameters, SERVICE, request, timeout_s=timeout_s)
        result = response.results[0]
        if not result.successful:
            raise HALError(f"HAL {self.name!r}: {SERVICE} refused {PARAM}="
                           f"{'inf' if math.isinf(mps) else mps}: {result.reason}")
