"""Shared fixtures: a high-level manager that must leave no thread behind."""

from __future__ import annotations

import faulthandler
import importlib
import os
import random
import shutil
import signal
import sys
import tempfile
import time
import zlib
from collections.abc import Generator, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from beehave import Event, HighLevelBehaviorManager
from beehave.testing import no_thread_left

# ROS 2 isolation: only this machine, and a domain of our own for this test run and this
# pytest-xdist worker (child processes inherit both). The workers of one run share a seed
# (PYTEST_XDIST_TESTRUNUID), so they take consecutive domains and never the same one; the
# benchmarks use 101-200. BEEHAVE_TEST_DOMAINS=LO-HI moves a run into another range, so
# that two suites on one machine (e.g. `make test-stress` beside development) never meet.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
_SEED = os.environ.get("PYTEST_XDIST_TESTRUNUID", str(os.getpid()))
_LO, _HI = (int(n) for n in os.environ.get("BEEHAVE_TEST_DOMAINS", "1-100").split("-"))
_SPAN = min(16, _HI - _LO + 1)
_DOMAIN = str(random.Random(_SEED).randint(_LO, _HI - _SPAN + 1)
              + int(_WORKER.removeprefix("gw")) % _SPAN)
if "PYTEST_XDIST_WORKER" in os.environ:
    # A worker inherits the controller's environment: its own domain replaces that one.
    os.environ["ROS_DOMAIN_ID"] = _DOMAIN
else:
    os.environ.setdefault("ROS_DOMAIN_ID", _DOMAIN)

# Bytecode caches on, even where the environment turns them off (PYTHONDONTWRITEBYTECODE=1
# on CI machines): the suite starts hundreds of Python processes (robots, agents, the CLI)
# and each would compile beehave from source again, and each worker would rewrite every
# test module's asserts again. Child processes and xdist workers inherit this.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False
# Fast DDS's shared memory stays on: with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST the ROS 2
# middleware adds that transport itself, whatever FASTDDS_BUILTIN_TRANSPORTS says (this
# file set UDPv4 there, to no effect: the stress runs' hangs were still in
# SharedMemGlobal::open_port, read with gdb). A process the suite kills while it sets up a
# port leaves it unfinished, and every later participant that opens that port hangs;
# RosContext clears such ports before it starts (beehave.ros.context.clear_dead_shm_ports).
# Every process of the suite, the plain rclpy clients and probes included, uses beehave's
# Fast DDS profile (no TypeLookup service: Fast DDS 3.2 races in it, and a robot process of
# a stress run died of SIGSEGV there; beehave.fastdds). Set before
# any participant exists: Fast DDS reads it once per process.
from beehave.fastdds import use_fastdds_profile  # noqa: E402

use_fastdds_profile()
# Every Python child writes its threads' stacks to its stderr on a fatal signal: a harness
# that gives up on a hung child sends it SIGABRT and the test's failure shows where it hung.
os.environ["PYTHONFAULTHANDLER"] = "1"

if os.environ.get("BEEHAVE_REQUIRE_EXTRAS") == "1":
    # `make test` installs every extra: a missing rclpy or pybullet there is a broken
    # set-up, and a skipped ROS or physics test would hide it. Outside it (a bare checkout
    # without extras), those tests are skipped as usual.
    def _require(modname: str, *args: Any, **kwargs: Any) -> ModuleType:
        try:
            return importlib.import_module(modname)
        except ImportError as exc:
            pytest.fail(f"{modname} is not importable although `make test` installs every "
                        f"extra (BEEHAVE_REQUIRE_EXTRAS=1): {exc}", pytrace=False)

    pytest.importorskip = _require  # type: ignore[assignment]


# The files that start robots, agents or a simulation in processes of their own (several
# Python processes each, busy for a minute or more): they run in three lanes, each lane's
# files one after another on one worker, so that at most three of them run at once whatever
# the number of workers. Four or more at once (as when every worker began with one) put the
# load of a 2-core machine at 12-14 and starved their processes' real-time parts (MAVLink
# heartbeats, DDS discovery). Balanced by the seconds each file took in a run (comments);
# a lane's file with its own module fixtures keeps them, as the lane is one worker.
_LANES = {
    "lane-a": ("test_droid", "test_vda5050_sim", "test_three_terminals"),      # 115+27+9
    "lane-b": ("test_fleet", "test_fleet_figures", "test_http_cli"),           # 79+55+20
    "lane-c": ("test_replay_demo", "test_serve"),                              # 74+73
}
_LANE_OF = {name: lane for lane, names in _LANES.items() for name in names}
# The other files that take longest (seconds of a run, measured; longest first). They go
# first after the lanes, so that none starts late and ends the run alone on one worker.
_LONG_FILES = ("test_mavlink_ground_station", "test_mavlink", "test_http_timeline",
               "test_agents", "test_vda5050", "test_market", "test_agents_trust",
               "test_scenarios", "test_http_graph", "test_mavlink_signing",
               "test_loop_starvation", "test_http_browser")


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's, which reads the lanes' groups
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The order pytest-xdist hands tests out in (each worker applies the same one; ``make
    test`` passes ``--no-loadscope-reorder``, else xdist puts the largest groups first
    instead): the lanes (:data:`_LANES`, each one ``xdist_group``), then
    :data:`_LONG_FILES`, then the others in a fixed mix, not alphabetically, so that files
    that mostly wait (MAVLink links, VDA 5050 brokers) are not all running at once on every
    worker while the CPUs idle. A module's tests keep their order (an ``xdist_group`` goes
    to one worker whole; the others are handed out one by one)."""
    lanes = list(_LANES)

    def stem(item: pytest.Item) -> str:
        return Path(item.nodeid.split("::", 1)[0]).stem

    def place(item: pytest.Item) -> tuple[int, int, int]:
        name = stem(item)
        if name in _LANE_OF:
            lane = _LANE_OF[name]
            return 0, lanes.index(lane), _LANES[lane].index(name)
        if name in _LONG_FILES:
            return 1, _LONG_FILES.index(name), 0
        return 2, zlib.crc32(name.encode()), 0

    for item in items:
        lane = _LANE_OF.get(stem(item))
        if lane is not None:
            if any(item.iter_markers("xdist_group")):
                raise pytest.UsageError(
                    f"{item.nodeid}: a file in a lane ({lane}, tests/conftest.py) must not "
                    f"set an xdist_group of its own: the lane is its group")
            item.add_marker(pytest.mark.xdist_group(lane))
    items.sort(key=place)  # stable: a module's tests keep their order


@pytest.fixture
def hl(request: pytest.FixtureRequest) -> Iterator[HighLevelBehaviorManager]:
    """A started manager with a short stop timeout (a module's ``HL_STOP_TIMEOUT_S``, 0.3 s
    by default); checks that nothing leaks."""
    with no_thread_left("shutdown"):
        manager = HighLevelBehaviorManager(
            stop_timeout_s=getattr(request.module, "HL_STOP_TIMEOUT_S", 0.3))
        manager.start()
        try:
            yield manager
        finally:
            manager.shutdown()


@pytest.fixture
def events(hl: HighLevelBehaviorManager) -> list[Event]:
    received: list[Event] = []
    hl.subscribe(received.append)
    return received


# A stuck test must not stall the run until CI kills it. pytest-timeout (120 s, SIGALRM)
# cannot reach a main thread blocked in C that retries on EINTR, and nothing bounds the run
# when it hangs after its session (xdist ends hung workers then, nothing ends a hung
# controller). So each test, and the run after its session, is also bounded by faulthandler's
# own watchdog (a C thread, not seen by `threading`): past the bound it writes every thread's
# stack to a file and ends the process; xdist reports the test as crashed and starts a new
# worker, and the run's summary prints the stacks.
_GRACE_S = float(os.environ.get("BEEHAVE_HANG_GRACE_S", "60"))
_HANGS = "BEEHAVE_HANG_DIR"


@pytest.hookimpl(trylast=True)  # after pytest's faulthandler plugin: this one stays
def pytest_configure(config: pytest.Config) -> None:
    if "PYTEST_XDIST_WORKER" not in os.environ and _HANGS not in os.environ:
        _sweep_hang_dirs()
        os.environ[_HANGS] = tempfile.mkdtemp(prefix="beehave-hangs-")
    if "PYTEST_XDIST_WORKER" in os.environ and _HANGS in os.environ:
        # A worker that crashes (a segfault in a C extension) is only "node down" in the
        # run's output: its stacks go to a file that the summary prints.
        crash = Path(os.environ[_HANGS]) / f"crash-{_WORKER}-{os.getpid()}.txt"
        config._beehave_crash_file = crash.open("w")  # type: ignore[attr-defined]
        faulthandler.enable(file=config._beehave_crash_file, all_threads=True)  # type: ignore[attr-defined]
        # A worker ended by a signal that faulthandler does not watch (a stress run lost
        # one at the start of a test, with no trace) says which, and where it was. (It
        # then dies: rclpy's own SIGTERM handler passes the signal on, where before it
        # only shut rclpy down and left a worker without ROS.) Registered again before
        # each test: a test of `beehave run` in this process restores SIGTERM's default.
        config._beehave_signal_files = {  # type: ignore[attr-defined]
            signum: crash.with_name(f"{crash.stem}-{signum.name}.txt").open("w")
            for signum in _DUMP_SIGNALS}
        _register_dumps(config)


def _has_stacks(dump: Path) -> bool:
    text = dump.read_text(errors="replace")
    return "File " in text or "Fatal Python error" in text  # a watchdog fired, a crash


def _sweep_hang_dirs(min_age_s: float = 3600.0) -> None:
    """Remove the hang folders of earlier runs that hold no stacks (every run leaves one:
    its watchdogs' files, armed and never fired), once they are an hour old (a run beside
    this one may still use its own)."""
    for old in Path(tempfile.gettempdir()).glob("beehave-hangs-*"):
        try:
            dumps = list(old.glob("*.txt"))
            # A live run rewrites its files at each test (the folder's own time stays).
            touched = max([old.stat().st_mtime, *(d.stat().st_mtime for d in dumps)])
            if time.time() - touched < min_age_s or any(_has_stacks(d) for d in dumps):
                continue
        except OSError:
            continue
        shutil.rmtree(old, ignore_errors=True)


_DUMP_SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)


def _register_dumps(config: pytest.Config) -> None:
    for signum, out in getattr(config, "_beehave_signal_files", {}).items():
        if signal.getsignal(signum) in (signal.SIG_DFL, None):  # (None: not Python's)
            faulthandler.unregister(signum)  # it would not install itself again
        faulthandler.register(signum, file=out, all_threads=True, chain=True)


def _arm(seconds: float, why: str) -> None:
    path = Path(os.environ.get(_HANGS, tempfile.gettempdir())) / f"{_WORKER}-{os.getpid()}.txt"
    out = path.open("w")  # only the latest bound: a file with stacks is a watchdog that fired
    out.write(f"{why}: still running {seconds:.0f} s later; every thread's stack:\n")
    out.flush()
    faulthandler.dump_traceback_later(seconds, file=out, exit=True)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Generator[None, None, None]:
    marker = item.get_closest_marker("timeout")
    bound = float(marker.args[0]) if marker and marker.args else float(
        item.config.getini("timeout") or 120)
    if bound > 0:
        _arm(bound + _GRACE_S, f"test {item.nodeid} (timeout {bound:.0f} s)")
    _register_dumps(item.config)
    yield
    faulthandler.cancel_dump_traceback_later()


_KEEP = "BEEHAVE_KEEP_DIR"
"""Where a failed test's recordings (its ``.mcap`` arguments, e.g. the demo's) are copied,
so that a failure seen once under load can be replayed later (``make test-stress`` sets
it)."""


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: Any) -> Generator[None, Any, None]:
    outcome = yield
    where = os.environ.get(_KEEP)
    if not where or not outcome.get_result().failed:
        return
    for name, value in getattr(item, "funcargs", {}).items():
        if isinstance(value, Path) and value.suffix == ".mcap" and value.exists():
            keep = Path(where) / f"{item.name}-{name}.mcap"
            keep.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(value, keep)


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish() -> None:
    if "PYTEST_XDIST_WORKER" not in os.environ:  # a worker waits for the others legitimately
        _arm(_GRACE_S, "the session has finished but the process has not exited")


def pytest_terminal_summary(terminalreporter: Any) -> None:
    where = os.environ.get(_HANGS)
    if "PYTEST_XDIST_WORKER" in os.environ or not where:
        return
    for dump in sorted(Path(where).glob("*.txt")):
        if _has_stacks(dump):
            what = "crashed" if dump.name.startswith("crash-") else "stuck"
            terminalreporter.write_sep("=", f"{what}: {dump.name}")
            terminalreporter.write(dump.read_text(errors="replace")[-20000:] + "\n")
