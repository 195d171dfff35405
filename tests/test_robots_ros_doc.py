"""docs/robots_ros.md tells the truth about the robot interface: every topic of its tables
exists on the sim node with the documented message type and direction, and every topic the
sim node has is documented."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("pybullet")

from beehave.ros.context import RosContext  # noqa: E402
from robots.node import SimNode  # noqa: E402
from robots.sim import Simulation  # noqa: E402
from robots.world import world_from_dict  # noqa: E402

DOC = Path(__file__).resolve().parent.parent / "docs" / "robots_ros.md"

Entry = tuple[str, str, str]  # (topic, type, "pub" | "sub")


def documented() -> dict[str, set[Entry]]:
    """The interface tables, by heading line ("Every robot:", "EMILI:", "Kobuki …")."""
    text = DOC.read_text()
    section = text[text.index("## The robot interface"):]
    section = section[:section.index("\n## ", 1)]
    tables: dict[str, set[Entry]] = {}
    current = ""
    for line in section.splitlines():
        if line and not line.startswith("|") and line.split()[0] in ("Every", "EMILI:", "Kobuki"):
            current = line.split()[0].rstrip(":")
            tables[current] = set()
        elif line.startswith("| `") and current:
            cells = [c.strip() for c in line.strip("|").split("|")]
            direction = "sub" if cells[2] in ("to robot", "to simulation") else "pub"
            msg_type = cells[1].strip("`")
            for topic in re.findall(r"`([^`]+)`", cells[0].split("(")[0]):
                tables[current].add((topic, msg_type, direction))
    return tables


def type_name(msg_type: Any) -> str:
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


def actual(node: Any, namespace: str) -> set[Entry]:
    def rel(topic: str) -> str:
        return topic.removeprefix(f"/{namespace}/") if namespace else topic

    infrastructure = ("/rosout", "/parameter_events")  # every rclpy node has them
    return ({(rel(p.topic_name), type_name(p.msg_type), "pub") for p in node.publishers
             if p.topic_name not in infrastructure} |
            {(rel(s.topic_name), type_name(s.msg_type), "sub") for s in node.subscriptions
             if s.topic_name not in infrastructure})


@pytest.fixture
def sim_node() -> Iterator[SimNode]:
    world = world_from_dict({
        "name": "doc_check", "floor": {"size_m": [6, 6]},
        "robots": [{"namespace": "doc_emili", "kind": "emili", "start": {"x_m": 2, "y_m": 2}},
                   {"namespace": "doc_kobuki", "kind": "kobuki",
                    "start": {"x_m": 4, "y_m": 4}}],
    })
    sim = Simulation(world, real_time_factor=None)
    ros = RosContext()
    node = SimNode(sim, ros)
    try:
        yield node
    finally:
        node.destroy()
        ros.shutdown()
        sim.close()


def test_the_documented_topics_are_the_sim_nodes(sim_node: SimNode) -> None:
    docs = documented()
    assert set(docs) == {"Every", "EMILI", "Kobuki"}, docs.keys()
    common = {e for e in docs["Every"] if not e[0].startswith("/")}
    clock = {e for e in docs["Every"] if e[0].startswith("/")}
    assert actual(sim_node.ports["doc_emili"].node, "doc_emili") == common | docs["EMILI"]
    assert actual(sim_node.ports["doc_kobuki"].node, "doc_kobuki") == common | docs["Kobuki"]
    clock_node = next(n for n in sim_node.nodes if n.get_namespace() == "/")
    assert actual(clock_node, "") == clock
