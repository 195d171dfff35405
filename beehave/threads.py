"""The manager's worker threads: every behaviour and action runs in one of them.

Starting and ending an OS thread costs about 100 µs each here, and ten threads exiting
at once cost ~0.75 ms — more than a whole switch may take. So a behaviour or action gets
a thread of its own for as long as it runs, taken from this pool and handed back when
its ``run`` and clean-up are over. The pool grows when every thread is busy (a STUCK
action keeps its thread), lets idle threads go after ``idle_timeout_s``, and joins all of
them at :meth:`shutdown`: no thread outlives the manager that owns it.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from enum import Enum

log = logging.getLogger(__name__)

Job = Callable[[], None]


class _Worker:
    def __init__(self, pool: WorkerPool, number: int) -> None:
        self.pool = pool
        self.jobs: queue.SimpleQueue[tuple[str, Job] | None] = queue.SimpleQueue()
        self.thread = threading.Thread(target=self._loop, name=f"beehave:worker-{number}",
                                       daemon=True)
        self.idle_name = self.thread.name

    def _loop(self) -> None:
        pool = self.pool
        while True:
            try:
                job = self.jobs.get(timeout=pool.idle_timeout_s)
            except queue.Empty:
                if pool._retire(self):
                    return
                job = self.jobs.get()  # it was handed a job just as it timed out
            if job is None:
                return
            name, fn = job
            self.thread.name = name
            try:
                fn()
            except BaseException:  # the job records its own errors; this is a last resort
                log.exception("worker job %s raised", name)
            # An idle thread keeps nothing alive (the job is a behaviour's or an action's).
            del job, fn
            self.thread.name = self.idle_name
            if not pool._park(self):
                return


class WorkerState(Enum):
    """Where one of a :class:`WorkerPool`'s threads is."""

    PARKED = "parked"
    """Idle, waiting for a job."""
    HANDED = "handed"
    """A job was handed to it that it has not taken yet."""
    BUSY = "busy"
    """Running a job."""


class WorkerPool:
    """Threads for behaviours and actions. ``submit(name, fn)`` runs ``fn`` at once in a
    thread named ``name`` (an idle one if any, else a new one)."""

    def __init__(self, *, idle_timeout_s: float = 30.0,
                 track_job: Callable[[Job], Job] | None = None) -> None:
        self.idle_timeout_s = idle_timeout_s
        # The manager's clock counts the jobs in flight (a virtual clock jumps when all of
        # them wait): the count lives here, where the workers are made.
        self._track_job = track_job
        self._lock = threading.Lock()
        self._idle: list[_Worker] = []
        self._all: set[_Worker] = set()
        self._closed = False
        self._count = 0

    def submit(self, name: str, fn: Job) -> None:
        with self._lock:
            if self._closed:
                raise RuntimeError("worker pool is shut down")
            if self._track_job is not None:
                fn = self._track_job(fn)
            worker = self._idle.pop() if self._idle else None
            if worker is None:
                self._count += 1
                worker = _Worker(self, self._count)
                self._all.add(worker)
                fresh = True
            else:
                fresh = False
            # Under the lock: threads() must never see a worker taken from the idle list
            # without its job (neither parked nor handed: a replay took it as waiting).
            worker.jobs.put((name, fn))
        if fresh:
            worker.thread.start()

    def threads(self) -> list[tuple[threading.Thread, WorkerState]]:
        """Each worker's thread and its state: for a replay that waits until every thread
        waits."""
        with self._lock:
            return [(w.thread, WorkerState.HANDED if not w.jobs.empty()
                     else WorkerState.PARKED if w in self._idle else WorkerState.BUSY)
                    for w in self._all]

    def owns_current(self) -> bool:
        """True when the calling thread is one of this pool's."""
        me = threading.current_thread()
        with self._lock:
            return any(w.thread is me for w in self._all)

    def _park(self, worker: _Worker) -> bool:
        with self._lock:
            if self._closed:
                self._all.discard(worker)
                return False
            self._idle.append(worker)
            return True

    def _retire(self, worker: _Worker) -> bool:
        with self._lock:
            if worker in self._idle:
                self._idle.remove(worker)
                self._all.discard(worker)
                return True
            return False

    def shutdown(self, *, timeout_s: float | None = None) -> list[threading.Thread]:
        """Stop idle threads and join every thread; returns the ones still busy after
        ``timeout_s`` (running a STUCK action's ``run``)."""
        import time

        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
            workers = list(self._all)
        for worker in idle:
            worker.jobs.put(None)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        for worker in workers:
            if worker.thread.ident is None:
                continue
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            worker.thread.join(remaining)
        return [w.thread for w in workers if w.thread.is_alive()]
