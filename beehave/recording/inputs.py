"""Recording what the high level reads: the ROS 2 topics its behaviours subscribe to.

A replay runs the robot's behaviours again (:mod:`beehave.recording.replay`); they read
the robot through ``self.ros`` subscriptions (odometry, the laser, the lift's state, the
orders of another agent …). :func:`attach_behavior_inputs` watches the high level's node:
the first time a behaviour or action subscribes to a topic, the recorder subscribes to it
too (raw CDR, as :meth:`~beehave.recording.recorder.Recorder.attach_topic` records any
topic) and keeps recording it until the end. A topic recorded already (the configuration's
``recording.topics``) is not recorded twice. Topics in the robot's namespace go to
``/<robot>/<topic>``; a global one keeps its name (``/orders``) and is recorded once.

Why subscribe on first use, not up front: which topics a behaviour reads is known only when
it runs; the configuration names its behaviours' classes, not their topics.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

from beehave.errors import RecordingError
from beehave.recording import schema

if TYPE_CHECKING:
    from beehave.recording.recorder import Recorder
    from beehave.robot import Robot

log = logging.getLogger(__name__)

__all__ = ["attach_behavior_inputs", "input_channel"]


def input_channel(prefix: str, namespace: str, topic: str) -> str:
    """The MCAP topic of the fully resolved ROS ``topic`` a robot's behaviour read:
    ``/emili1/lift/state`` for ``/emili1/lift/state`` (namespace ``emili1``, prefix
    ``emili1``); a global topic keeps its name (``/orders``), shared by the robots."""
    relative = _relative(namespace, topic)
    return schema.topic(prefix, relative) if relative is not None else "/" + topic.strip("/")


def _relative(namespace: str, topic: str) -> str | None:
    ns = namespace.strip("/")
    if ns and topic.startswith(f"/{ns}/"):
        return topic[len(ns) + 2:]
    return None


def attach_behavior_inputs(recorder: Recorder, robot: Robot, *,
                           prefix: str | None = None) -> None:
    """Record every topic ``robot``'s behaviours and actions subscribe to from now on (see
    the module docstring). Call it after ``robot.start()`` (its high-level node exists
    then), in the process that runs the high level; a robot without one is left alone."""
    from beehave.ros.io import watch_subscriptions

    high = robot.high
    node = high.node if high is not None else None
    if node is None:
        return
    prefix = robot.config.namespace if prefix is None else prefix
    namespace = node.get_namespace()
    lock = threading.Lock()

    def on_subscribe(msg_type: type, topic: str) -> None:  # in the subscribing thread
        relative = _relative(namespace, topic)
        channel = input_channel(prefix, namespace, topic)
        with lock:
            if channel in recorder._topics:
                return  # recorded already (recording.topics, or an earlier subscription)
            try:
                if relative is not None:
                    recorder.attach_topic(node, relative, msg_type, prefix=prefix)
                else:
                    recorder.attach_topic(node, topic, msg_type, prefix="")
            except RecordingError as exc:  # a closed recorder must not fail a behaviour
                log.warning("recorder: not recording %s for %r: %s", topic, prefix, exc)
            except Exception as exc:  # no message definition installed, …
                log.warning("recorder: cannot record %s (%s) for %r: %r", topic,
                            msg_type.__name__, prefix, exc)

    recorder._detach.append(watch_subscriptions(node, on_subscribe))
