"""RosContext: one rclpy context, its nodes, and the executor thread that serves them."""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.experimental.events_executor import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from beehave.lifecycle import Running

log = logging.getLogger(__name__)

_executor_thread = threading.local()


def in_executor_thread() -> bool:
    """Whether the calling code runs in a :class:`RosContext`'s executor thread (a ROS
    callback): waiting there for something that needs another ROS callback — a service
    response, a message — blocks until the wait times out, as nothing else is served."""
    return bool(getattr(_executor_thread, "active", False))


class RosContext(Running):
    """Owns an rclpy :class:`~rclpy.context.Context`, the nodes created through it, and one
    ``EventsExecutor`` spun by a framework thread.

    Why this shape: on rclpy 9.1.2 ``MultiThreadedExecutor`` delivers ~200 msg/s and starves
    other threads, while ``EventsExecutor`` handles ~40k msg/s — but its ``spin()`` in a
    non-main thread hangs the process. So the thread calls ``spin_once(timeout_sec=…)`` in a
    loop, and :meth:`shutdown` stops and joins it before the nodes are destroyed (an unjoined
    executor thread aborts the interpreter at exit). Each context is independent, so tests
    and multi-robot programs can hold several.
    """

    def __init__(self, *, args: Sequence[str] | None = None, spin_timeout_s: float = 0.05) -> None:
        self.context = Context()
        rclpy.init(args=list(args) if args is not None else None, context=self.context)
        self.executor = EventsExecutor(context=self.context)
        self.spin_timeout_s = spin_timeout_s
        self._nodes: list[Node] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    def create_node(self, name: str, *, namespace: str = "", use_sim_time: bool = False,
                    parameters: dict[str, Any] | None = None) -> Node:
        """A node served by this context's executor; destroyed by :meth:`shutdown`."""
        overrides = [Parameter("use_sim_time", value=use_sim_time)]
        overrides += [Parameter(k, value=v) for k, v in (parameters or {}).items()]
        node = rclpy.create_node(name, namespace=namespace, context=self.context,
                                 parameter_overrides=overrides,
                                 automatically_declare_parameters_from_overrides=True)
        with self._lock:
            self._nodes.append(node)
        self.executor.add_node(node)
        return node

    def destroy_node(self, node: Node) -> None:
        """Take ``node`` off the executor and destroy it (before :meth:`shutdown`)."""
        with self._lock:
            if node not in self._nodes:
                return
            self._nodes.remove(node)
        self.executor.remove_node(node)
        node.destroy_node()

    def start(self) -> None:
        """Start the executor thread (idempotent)."""
        with self._lock:
            if self._thread is not None:
                return
            self._thread = threading.Thread(target=self._spin, name="beehave:ros-executor",
                                            daemon=True)
            self._thread.start()

    def _spin(self) -> None:
        _executor_thread.active = True
        while not self._stop.is_set() and self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=self.spin_timeout_s)
            except Exception:  # a callback's bug must not stop every other callback
                log.exception("a ROS callback raised; the executor goes on")

    def shutdown(self) -> None:
        """Stop and join the executor thread, destroy the nodes, shut the context down."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            thread, nodes = self._thread, list(self._nodes)
        self._stop.set()
        if thread is not None and thread is not threading.current_thread():
            thread.join()
        self.executor.shutdown()
        for node in nodes:
            node.destroy_node()
        if self.context.ok():
            rclpy.shutdown(context=self.context)

