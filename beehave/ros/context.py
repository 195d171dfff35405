"""RosContext: one rclpy context, its nodes, and the executor thread that serves them."""

from __future__ import annotations

import atexit
import fcntl
import logging
import os
import re
import sys
import threading
import time
import traceback
import weakref
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import rclpy
from rclpy.clock_type import ClockType
from rclpy.context import Context
from rclpy.experimental.events_executor import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from beehave.fastdds import use_fastdds_profile
from beehave.lifecycle import Running
from beehave.ros.io import destroy_node_action_clients

log = logging.getLogger(__name__)

_executor_thread = threading.local()

CLOCK_TOPIC = "/clock"
#: Reliable, depth 10 (rclpy's default): a lockstep hold publishes the held time once, and
#: the actions waiting on it must not miss it (rclpy's own TimeSource is best effort).
CLOCK_QOS = 10

#: rclpy context → the RosContext that owns it (:meth:`RosContext.of`).
_owners: weakref.WeakValueDictionary[int, RosContext] = weakref.WeakValueDictionary()


#: Where Fast DDS keeps its shared-memory transport's ports (``fastdds_port<N>``, each
#: with a named semaphore ``sem.fastdds_port<N>_mutex``), and how long a port may stay
#: unfinished before it counts as left behind (a live creator finishes it within
#: milliseconds).
SHM_DIR = Path("/dev/shm")
DEAD_PORT_AGE_S = 10.0
#: How often a starting context looks again at an unfinished port of its domain (see
#: :func:`await_unfinished_shm_ports`).
DEAD_PORT_POLL_S = 0.1
_PORT = re.compile(r"fastdds_port\d+")
_SEGMENT_LOCK = re.compile(r"fastdds_[0-9a-f]{16}_el")
#: The first word of a port's segment (Boost.Interprocess' managed_open_or_create_impl):
#: 2 once the segment is set up; 0 (created) or 1 (being set up) before; 3 corrupted.
_SEGMENT_READY = 2
_SEGMENT_CORRUPTED = 3


def clear_dead_shm_ports(shm_dir: Path = SHM_DIR, *, min_age_s: float = DEAD_PORT_AGE_S
                         ) -> list[str]:
    """Release and remove the Fast DDS shared-memory ports that a killed process left
    unfinished, with their mutexes; returns the ports' names.

    A process killed while it sets up a port (``/dev/shm/fastdds_port<N>``) leaves the
    segment marked "being set up", and may leave the port's mutex
    (``sem.fastdds_port<N>_mutex``) locked. A process of that domain that opens port N
    (in ``rcl_node_init``, creating its participant) waits for the segment to be ready for
    ever, deaf to SIGTERM; a locked mutex alone costs it 2 s. The files outlive every
    process, so every later start on that port hangs the same way (eProsima/Fast-DDS#3878;
    seen in our stress runs, the native stack read with gdb). With
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` the ROS 2 middleware always adds the
    shared-memory transport, whatever ``FASTDDS_BUILTIN_TRANSPORTS`` says.

    A port still unfinished after ``min_age_s`` has no live creator. It is first marked
    corrupted, in place: a process already waiting on it then gives up waiting and goes
    on (Fast DDS carries on without that port; removing the file alone does not free a
    process that has it mapped). Then the file and its mutex are removed, so the next
    process makes the port anew. Ports that are set up, and their mutexes, are never
    touched. A port is removed only if it is still the file that was marked (same inode)
    just before: that narrows the race with a process that replaces it at that moment to
    microseconds, without closing it (Fast DDS replaces an unfinished port only when its
    creator has been gone or stopped for 10 s)."""
    removed: list[str] = []
    now = time.time()
    for name in _port_names(shm_dir):
        path = shm_dir / name
        try:
            fd = os.open(path, os.O_RDWR)
        except FileNotFoundError:
            continue
        except OSError as err:  # not ours (PermissionError): only a look, to warn
            _warn_if_dead(path, now, min_age_s, err)
            continue
        try:
            seen = os.fstat(fd)
            state = _state(os.pread(fd, 4, 0))
            if state == _SEGMENT_READY or now - seen.st_mtime <= min_age_s:
                continue
            os.pwrite(fd, _SEGMENT_CORRUPTED.to_bytes(4, sys.byteorder), 0)
        except OSError:
            continue
        finally:
            os.close(fd)
        try:
            if os.stat(path).st_ino != seen.st_ino:  # replaced meanwhile: a new port
                continue
            path.unlink()
        except FileNotFoundError:
            continue
        except OSError as err:
            log.warning("cannot remove the unfinished Fast DDS port %s (owner uid %d): %s; "
                        "marked corrupted, so nobody waits on it", path, seen.st_uid, err)
            continue
        removed.append(name)
        try:  # its mutex, maybe left locked by the same process
            (shm_dir / f"sem.{name}_mutex").unlink(missing_ok=True)
        except OSError as err:
            log.warning("cannot remove the mutex of the unfinished Fast DDS port %s: %s",
                        name, err)
    if removed:
        log.warning("removed %d unfinished Fast DDS shared-memory port(s) left by killed "
                    "processes (each would hang the participant that opens it): %s",
                    len(removed), ", ".join(sorted(removed)))
    return removed


def clear_dead_shm_segments(shm_dir: Path = SHM_DIR) -> int:
    """Remove the Fast DDS shared-memory data segments whose processes are gone; returns
    how many.

    Each participant's segment (``fastdds_<16 hex digits>``, half a megabyte or more)
    lives in RAM until removed, and only its process removes it — at a clean exit. Every
    killed or crashed process leaves its segment behind: a machine that runs the suite
    again and again filled ``/dev/shm`` with hundreds of megabytes. A live owner holds an
    exclusive ``flock`` on the segment's ``_el`` file for the segment's whole life, so an
    ``_el`` file we can lock has no owner (Fast DDS's own ``fastdds shm clean`` tells them
    apart the same way); we remove the segment, then the lock file, while holding it.
    A live participant is never touched: it takes its lock before it makes its segment,
    and removes the segment before it lets go. (A name the check holds for that moment
    is refused to a new participant, which draws another at random.)"""
    try:
        names = [n for n in os.listdir(shm_dir) if _SEGMENT_LOCK.fullmatch(n)]
    except OSError:
        return 0
    removed = 0
    for name in names:
        lock_path = shm_dir / name
        try:
            fd = os.open(lock_path, os.O_RDONLY)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # held: its process lives
            os.close(fd)
            continue
        try:
            (shm_dir / name[:-len("_el")]).unlink(missing_ok=True)
            lock_path.unlink(missing_ok=True)
            removed += 1
        except OSError as err:  # another user's (sticky /dev/shm): theirs to clear
            log.debug("cannot remove the dead Fast DDS segment %s: %s", name[:-3], err)
        finally:
            os.close(fd)
    if removed:
        log.info("removed %d Fast DDS shared-memory segment(s) left by processes that are "
                 "gone", removed)
    return removed


def _port_names(shm_dir: Path) -> list[str]:
    """The names of the ports in ``shm_dir`` (none without it: not Linux)."""
    try:
        return [n for n in os.listdir(shm_dir) if _PORT.fullmatch(n)]
    except OSError:
        return []


def _state(head: bytes) -> int | None:
    return int.from_bytes(head, sys.byteorder) if len(head) == 4 else None


def _warn_if_dead(path: Path, now: float, min_age_s: float, err: OSError) -> None:
    try:
        with open(path, "rb") as f:
            state = _state(f.read(4))
            age_s = now - os.fstat(f.fileno()).st_mtime
    except OSError:
        return
    if state != _SEGMENT_READY and age_s > min_age_s:
        log.warning("cannot release the unfinished Fast DDS port %s: %s; it will hang the "
                    "participant that opens it", path, err)


def await_unfinished_shm_ports(domain_id: int, *, poll_s: float = DEAD_PORT_POLL_S) -> None:
    """Clear dead segments and ports (:func:`clear_dead_shm_segments`,
    :func:`clear_dead_shm_ports`), then wait while a port of
    ``domain_id`` is still unfinished: until it is ready (its creator was at work) or old
    enough to clear (its creator was killed less than ``DEAD_PORT_AGE_S`` ago), at most
    ``DEAD_PORT_AGE_S``. Called before a context makes its participant: once it waits in
    ``rcl_node_init`` on such a port, it holds the interpreter's lock, and nothing in the
    process can release it any more."""
    clear_dead_shm_segments()
    deadline = time.monotonic() + DEAD_PORT_AGE_S + poll_s
    warned = False
    while True:
        clear_dead_shm_ports()
        young = _unfinished_ports(domain_id)
        if not young or time.monotonic() > deadline:
            return
        if not warned:
            log.warning("waiting up to %.0f s for unfinished Fast DDS port(s) of ROS domain "
                        "%d (%s): being set up, or left by a process killed just now; the "
                        "participant would wait on them for ever", DEAD_PORT_AGE_S,
                        domain_id, ", ".join(sorted(young)))
            warned = True
        time.sleep(poll_s)


def _unfinished_ports(domain_id: int, shm_dir: Path = SHM_DIR) -> list[str]:
    """The ports of ``domain_id`` that are not set up. (RTPS 9.6.1.1 gives each domain
    250 ports from 7400 + 250 * domain; a participant's shared-memory port is its user-data
    unicast port, + 11 + 2 * its participant id.)"""
    base = 7400 + 250 * domain_id
    unfinished: list[str] = []
    for name in _port_names(shm_dir):
        if not base <= int(name[len("fastdds_port"):]) < base + 250:
            continue
        try:
            with open(shm_dir / name, "rb") as f:
                if _state(f.read(4)) != _SEGMENT_READY:
                    unfinished.append(name)
        except OSError:
            continue
    return unfinished


def _domain_id() -> int:
    try:
        return int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    except ValueError:  # rclpy names the problem when it reads it
        return 0


EXIT_JOIN_S = 3.0
"""At the interpreter's exit, how long a context left running waits for its executor
thread to leave the callback it is in (wall time): one that blocks for ever must not turn
the exit into a hang."""


@atexit.register
def _shutdown_left_running() -> None:
    """At the interpreter's exit, shut down the contexts a program left running: their
    executor thread, back from rclpy's wait during the finalization, would be ended by
    ``pthread_exit``, whose unwinding through rclpy's C++ frames aborts the process
    (SIGABRT, and a core file, after an otherwise clean run). Not those a forked child
    inherited: they are its parent's."""
    for context in list(_owners.values()):
        if context._closed or context._pid != os.getpid():
            continue
        log.info("shutting down a RosContext left running at exit")
        try:
            context._shutdown(join_timeout_s=EXIT_JOIN_S)
        except Exception:  # the interpreter is ending: say so, and go on with the others
            log.exception("a RosContext's shutdown at exit failed")


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
    executor thread aborts the interpreter at exit: a context still running then is shut
    down by an ``atexit`` hook). Each context is independent, so tests
    and multi-robot programs can hold several.
    """

    def __init__(self, *, args: Sequence[str] | None = None, spin_timeout_s: float = 0.05) -> None:
        # Before this process's participant opens its shared-memory ports.
        await_unfinished_shm_ports(_domain_id())
        use_fastdds_profile()
        self.context = Context()
        rclpy.init(args=list(args) if args is not None else None, context=self.context)
        self.executor = EventsExecutor(context=self.context)
        self.spin_timeout_s = spin_timeout_s
        self._nodes: list[Node] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        # The one /clock subscription of this context (see create_node): its host node,
        # the ROS clocks of the nodes on sim time, and the listeners (SimClocks).
        self._clock_sub: Any = None
        self._clock_host: Node | None = None
        self._ros_clocks: dict[Node, Any] = {}
        self._clock_listeners: tuple[Callable[[float], None], ...] = ()
        _owners[id(self.context)] = self
        self._pid = os.getpid()  # a forked child's copy is not its to shut down at exit

    @staticmethod
    def of(node: Node) -> RosContext | None:
        """The :class:`RosContext` that created ``node``; None for a node made otherwise."""
        owner = _owners.get(id(node.context))
        return owner if owner is not None and owner.context is node.context else None

    def create_node(self, name: str, *, namespace: str = "", use_sim_time: bool = False,
                    parameters: dict[str, Any] | None = None) -> Node:
        """A node served by this context's executor; destroyed by :meth:`shutdown`.

        ``use_sim_time``: the node's ROS clock (``node.get_clock()``, its timers) follows
        ``/clock``. Every such node of the context shares one ``/clock`` subscription
        instead of one per node (rclpy's TimeSource makes its own for each): every message
        a process receives costs its executor thread, and ``/clock`` comes at 50-100 Hz."""
        overrides = [Parameter("use_sim_time", value=use_sim_time)]
        overrides += [Parameter(k, value=v) for k, v in (parameters or {}).items()]
        node = rclpy.create_node(name, namespace=namespace, context=self.context,
                                 parameter_overrides=overrides,
                                 automatically_declare_parameters_from_overrides=True)
        with self._lock:
            self._nodes.append(node)
            if use_sim_time:
                self._share_clock(node)
        self.executor.add_node(node)
        return node

    # ---- the shared /clock -----------------------------------------------------------------

    def _share_clock(self, node: Node) -> None:
        """Feed ``node``'s ROS clock from the context's /clock subscription, and take the
        one its TimeSource made away (under ``self._lock``)."""
        for sub in list(node.subscriptions):
            if sub.topic_name == CLOCK_TOPIC:
                node.destroy_subscription(sub)
        self._ros_clocks[node] = node.get_clock()
        if self._clock_sub is None:
            self._host_clock(node)

    def _host_clock(self, node: Node) -> None:
        from rosgraph_msgs.msg import Clock

        self._clock_sub = node.create_subscription(Clock, CLOCK_TOPIC, self._on_clock,
                                                   CLOCK_QOS)
        self._clock_host = node

    def _on_clock(self, msg: Any) -> None:  # in the executor thread
        from rclpy.time import Time

        stamp = msg.clock
        if self._ros_clocks:
            t = Time(seconds=stamp.sec, nanoseconds=stamp.nanosec,
                     clock_type=ClockType.ROS_TIME)
            for clock in list(self._ros_clocks.values()):
                clock.set_ros_time_override(t)
        t_s = stamp.sec + stamp.nanosec * 1e-9
        for listener in self._clock_listeners:
            listener(t_s)

    def on_clock(self, callback: Callable[[float], None], *, node: Node) -> Callable[[], None]:
        """Call ``callback(sim_time_s)`` for every ``/clock`` message, in the executor
        thread, from the context's one subscription (hosted on ``node`` when the context
        has none yet). Returns a function that removes it."""
        with self._lock:
            if self._clock_sub is None:
                self._host_clock(node)
            self._clock_listeners = (*self._clock_listeners, callback)

        def remove() -> None:
            with self._lock:
                self._clock_listeners = tuple(c for c in self._clock_listeners
                                              if c is not callback)

        return remove

    def _unhost_clock(self, node: Node) -> None:
        """``node`` goes away (under ``self._lock``): move the subscription to another."""
        self._ros_clocks.pop(node, None)
        if self._clock_host is not node:
            return
        node.destroy_subscription(self._clock_sub)
        self._clock_sub = self._clock_host = None
        others = [n for n in self._nodes if n is not node]
        if self._ros_clocks or self._clock_listeners:
            candidates = [n for n in others if n in self._ros_clocks] or others
            if candidates:
                self._host_clock(candidates[0])

    def destroy_node(self, node: Node) -> None:
        """Take ``node`` off the executor and destroy it (before :meth:`shutdown`)."""
        with self._lock:
            if node not in self._nodes:
                return
            self._unhost_clock(node)
            self._nodes.remove(node)
        self.executor.remove_node(node)
        destroy_node_action_clients(node)
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
        if not self._stop.is_set():
            log.warning("the ROS context was shut down from outside (rclpy.shutdown, a "
                        "signal): this process's subscriptions, timers and services stop")

    def shutdown(self) -> None:
        """Stop and join the executor thread, destroy the nodes, shut the context down."""
        self._shutdown(join_timeout_s=None)

    def _shutdown(self, *, join_timeout_s: float | None) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            thread, nodes = self._thread, list(self._nodes)
        self._stop.set()
        if thread is not None and thread is not threading.current_thread():
            thread.join(join_timeout_s)
            if thread.is_alive():  # only with a bound: at exit
                frame = sys._current_frames().get(thread.ident or -1)
                log.warning("the ROS executor thread is still in a callback %.1f s after "
                            "the stop; its executor and nodes are left as they are. It is "
                            "in:\n%s", join_timeout_s,
                            "".join(traceback.format_stack(frame)) if frame else "?")
                return
        self.executor.shutdown()
        for node in nodes:
            destroy_node_action_clients(node)
            node.destroy_node()
        if self.context.ok():
            rclpy.shutdown(context=self.context)

