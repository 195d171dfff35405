"""The HAL contract, kept by the MAVLink HALs against a simulated vehicle."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Iterator
from typing import Any

import pytest
from hal_contract import HALContract

from hal.mavlink import MavlinkPositionHAL
from robots.mavlink_endpoint import MavlinkEndpoint
from robots.sim import Simulation
from robots.world import world_from_dict

# One pytest-xdist worker runs this module: its module-scoped rig is built once.
pytestmark = pytest.mark.xdist_group("test_mavlink_hal_contract")

_PORT: list[int] = []


@pytest.fixture(scope="module", autouse=True)
def vehicle() -> Iterator[None]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        _PORT.append(s.getsockname()[1])
    sim = Simulation(world_from_dict({"name": "contract", "floor": {"size_m": [6, 6]},
                                      "robots": [{"namespace": "rover", "kind": "kobuki",
                                                  "start": {"x_m": 1, "y_m": 1}}]}),
                     real_time_factor=1.0)
    endpoint = MavlinkEndpoint(sim, "rover", url=f"udpout:127.0.0.1:{_PORT[-1]}")
    sim.start()
    try:
        yield
    finally:
        endpoint.close()
        sim.close()


class TestMavlinkPositionHAL(HALContract):
    """One MAVLink HAL stands for all: they share their base class (link, staleness,
    unload); the others' keys are checked in test_mavlink.py."""

    hal_cls = MavlinkPositionHAL
    expected_keys = ("position/north_m", "position/east_m", "position/lat_deg")

    def hal_params(self) -> dict[str, Any]:
        return {"connection": f"udp:127.0.0.1:{_PORT[-1]}"}

    @staticmethod
    async def settle(turns: int = 20) -> None:
        # A new link takes the vehicle's messages once its first heartbeat (1 Hz) has
        # told it the system id.
        await asyncio.sleep(1.1)
