"""beehave: high- and low-level multi-task robot behaviour.

Subclass :class:`Behavior` and :class:`Action` for deliberate decisions (threads, type
locks, runtime switching with :class:`HighLevelBehaviorManager`), :class:`Logic` and
:class:`HAL` for reactions over a :class:`Blackboard` (asyncio,
:class:`LowLevelBehaviorManager`).
"""

from beehave.action import Action
from beehave.behavior import Behavior, Idle
from beehave.blackboard import Blackboard, BlackboardClient, Change
from beehave.errors import (
                            ActionTypeBusy,
                            AgentError,
                            AgentNameTaken,
                            AgentUnreachable,
                            AlreadyStarted,
                            BadProposal,
                            BadRequest,
                            BeehaveError,
                            ChildFailed,
                            ConfigError,
                            ConstructorFailed,
                            GoalFailed,
                            Interrupted,
                            InvalidParameters,
                            LoopBlocked,
                            ManagerShutdown,
                            NoPath,
                            NoReply,
                            NotASubclass,
                            ProtocolFailed,
                            RecordingError,
                            ReservedAttribute,
                            SwitchSuperseded,
                            UnknownBehavior,
                            UnknownFusionSource,
                            UnknownHAL,
                            UnknownKey,
                            UnknownLogic,
                            UnknownNameError,
)
from beehave.events import Event, EventKind
from beehave.fusion import Arbiter, FusionInput, FusionLock
from beehave.hal import HAL, HALManager
from beehave.highlevel import HighLevelBehaviorManager
from beehave.logic import Logic
from beehave.lowlevel import LowLevelBehaviorManager
from beehave.status import Status

__version__ = "0.1.0"

__all__ = [
    "HAL", "Action", "ActionTypeBusy", "AgentError", "AgentNameTaken", "AgentUnreachable",
    "AlreadyStarted", "BadRequest", "BeehaveError", "Behavior",
    "Blackboard", "BlackboardClient", "Change", "ChildFailed", "ConfigError",
    "ConstructorFailed", "Event", "EventKind", "GoalFailed", "HALManager",
    "HighLevelBehaviorManager", "Idle", "Interrupted", "InvalidParameters", "Logic",
    "LoopBlocked", "LowLevelBehaviorManager", "ManagerShutdown", "NoPath", "NoReply",
    "NotASubclass", "ProtocolFailed", "RecordingError", "ReservedAttribute",
    "Status", "SwitchSuperseded", "UnknownBehavior", "UnknownHAL", "UnknownKey", "UnknownLogic",
    "UnknownNameError",
    # priority fusion (beehave.fusion)
    "Arbiter", "BadProposal", "FusionInput", "FusionLock", "UnknownFusionSource",
]
