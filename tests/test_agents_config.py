"""The robot YAML's ``agent:`` section: validated with file and key path, and a Robot
that has one is an agent its behaviours reach."""

from __future__ import annotations

from typing import Any

import pytest

from beehave.config import parse_config
from beehave.errors import ConfigError
from beehave.testing import WALL_TIMEOUT_S, wait_until


def _config(agent: Any) -> dict[str, Any]:
    return {"namespace": "atv", "agent": agent}


@pytest.mark.parametrize(("agent", "message"), [
    ({"name": "has space"}, "agent.name: String should match pattern"),
    ({"name": "atv_1", "lease_s": 0}, "agent.lease_s: Input should be greater than 0"),
    ({"name": "atv_1", "lease": 2}, "agent.lease: unknown key; valid keys: name, services, "
                                    "lease_s"),
    ({"name": "atv_1", "services": {"transport": 3}}, "agent.services.transport: Input "
                                                       "should be a valid dictionary"),
    ({"services": {}}, "agent.name: Field required"),
])
def test_bad_agent_sections_name_file_and_key(agent: Any, message: str) -> None:
    with pytest.raises(ConfigError) as error:
        parse_config(_config(agent), source="atv.yaml")
    assert str(error.value).startswith("atv.yaml: ")
    assert message in str(error.value)


def test_agent_section_defaults() -> None:
    config = parse_config(_config({"name": "atv_1", "services": {"transport": {"kg": 5}}}))
    assert config.agent is not None
    assert (config.agent.name, config.agent.services, config.agent.lease_s) == \
        ("atv_1", {"transport": {"kg": 5}}, 2.0)
    assert parse_config({"namespace": "atv"}).agent is None


def test_a_robot_with_an_agent_section_is_found_and_reaches_its_behaviours() -> None:
    pytest.importorskip("rclpy")
    from beehave.agents import Agent, AgentBehavior
    from beehave.robot import Robot
    from beehave.ros.context import RosContext

    config = parse_config({
        "namespace": "cfg_atv", "stop_timeout_s": 0.5,
        "behaviors": {"who": {"class": "tests.test_agents_config:WhoAmI"}},
        "agent": {"name": "cfg_atv", "services": {"transport": {"zone": "north"}},
                  "lease_s": 1.0}}, source="cfg_atv.yaml")
    assert issubclass(WhoAmI, AgentBehavior)
    with RosContext() as ros, Agent("cfg_seeker", ros=ros) as seeker:
        with Robot(config) as robot:
            assert wait_until(lambda: bool(seeker.directory.search("transport",
                                                                   zone="north"))), \
                "the robot's agent never appeared"
            assert robot.high is not None
            who = robot.high.switch("who")
            assert who.wait(WALL_TIMEOUT_S)
            assert who.result == "cfg_atv"
        # It said goodbye when the robot stopped.
        assert wait_until(lambda: not seeker.directory.alive("cfg_atv")), \
            "the robot's agent stayed in the directory"


try:
    from beehave.agents import AgentBehavior as _Base
except ImportError:  # pragma: no cover - without rclpy the robot test is skipped
    _Base = object  # type: ignore[assignment,misc]


class WhoAmI(_Base):  # type: ignore[valid-type,misc]
    def run(self) -> str:
        return str(self.agent.name)
