"""The agent layer: a directory (yellow pages), FIPA-ACL messages over DDS, and interaction
protocols written as Behaviors (FIPA request, contract net). See ``docs/agents.md``.

Robot-agnostic: anything with a ROS 2 node can be an agent (a robot, a machine, a
charging station, an order source)."""

from beehave.agents.agent import (
    Agent,
    AgentAction,
    AgentBehavior,
    Conversation,
    Mailbox,
    agent_of,
)
from beehave.agents.directory import AgentInfo, Change, Directory, DirectoryEvent
from beehave.agents.market import (
    Auctioneer,
    Broker,
    Job,
    Outcome,
    Plan,
    Role,
    Task,
    TaskState,
    auction,
)
from beehave.agents.message import SCHEMA, Message, Performative
from beehave.agents.trust import Mode, Trust
from beehave.errors import (
    AgentError,
    AgentNameTaken,
    AgentUnreachable,
    InvalidTask,
    NoReply,
    ProtocolFailed,
    RendezvousTimeout,
    TaskFailed,
    UnknownCapability,
)

__all__ = [
    "SCHEMA", "Agent", "AgentAction", "AgentBehavior", "AgentError", "AgentInfo",
    "AgentNameTaken", "AgentUnreachable", "Change", "Conversation", "Directory",
    "DirectoryEvent", "Mailbox", "Message", "NoReply", "Performative", "ProtocolFailed",
    "agent_of",
    # signed agents (beehave.agents.trust; docs/agents.md#trust-model)
    "Mode", "Trust",
    # market-based allocation (beehave.agents.market)
    "Auctioneer", "Broker", "InvalidTask", "Job", "Outcome", "Plan", "RendezvousTimeout",
    "Role", "Task", "TaskFailed", "TaskState", "UnknownCapability", "auction",
]
