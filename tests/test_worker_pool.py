"""WorkerPool.threads(): where each of the pool's threads is (the replay settles on it)."""

from __future__ import annotations

import threading

from beehave.testing import WALL_TIMEOUT_S, wait_until
from beehave.threads import WorkerPool, WorkerState


def test_threads_says_which_worker_runs_a_job_and_which_is_parked() -> None:
    pool = WorkerPool()
    release = threading.Event()
    try:
        pool.submit("quick", lambda: None)
        assert wait_until(lambda: [s for _, s in pool.threads()] == [WorkerState.PARKED])
        pool.submit("long", release.wait)  # the parked thread takes it
        assert wait_until(lambda: [s for _, s in pool.threads()] == [WorkerState.BUSY])
        pool.submit("second", lambda: None)  # none parked: a new thread
        assert wait_until(lambda: sorted(s.value for _, s in pool.threads())
                          == ["busy", "parked"])
        assert all(isinstance(t, threading.Thread) for t, _ in pool.threads())
    finally:
        release.set()
        pool.shutdown(timeout_s=WALL_TIMEOUT_S)
