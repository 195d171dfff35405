"""`make test-stress`: the suite, N times, on a clean clone of HEAD, beside a CPU hog.

A busy loop per core (a process each, killed by PID at the end) competes with the suite
for the whole run, as other work does on a shared CI machine. Each run is the exact command
`make test` runs. The report gives each run's wall time and counts, and every test that
failed or errored in any run, with how often. Exit status 0 only when every run passed.

    python scripts/test_stress.py [--runs 10] [--hogs N] [--no-clone] [--core-dumps]
                                  [-- PYTEST ARGS]

``--core-dumps`` lifts the core-file size limit for the suite and its processes and lists
the core files a run left where the robots and sims run (the clone, or this checkout with
``--no-clone``), for a native crash that faulthandler can only show from the Python side;
the clone is then kept. The kernel decides where a core goes
(``/proc/sys/kernel/core_pattern``: ``core.%p`` keeps one per process; a pattern starting
with ``|`` hands it to a program instead). ``test_agents`` sends one child SIGABRT on
purpose: its small core appears in every run.
"""

from __future__ import annotations

import argparse
import collections
import os
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# The same as the Makefile's `test` target (keep the two in step).
PYTEST = ["-m", "pytest", "-q", "-n", "6", "--dist", "loadgroup", "--no-loadscope-reorder",
          "--max-worker-restart", "0"]


def start_hogs(count: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                             stdin=subprocess.DEVNULL) for _ in range(count)]


def stop_hogs(hogs: list[subprocess.Popen[bytes]]) -> None:
    for hog in hogs:
        if hog.poll() is None:
            os.kill(hog.pid, signal.SIGKILL)
        hog.wait()


def _allow_cores() -> None:
    """In the suite's process, before it starts: core files of any size (inherited)."""
    _soft, hard = resource.getrlimit(resource.RLIMIT_CORE)
    resource.setrlimit(resource.RLIMIT_CORE, (hard, hard))


def _warn_if_no_core_files() -> None:
    if resource.getrlimit(resource.RLIMIT_CORE)[1] == 0:
        print("--core-dumps: the hard core-file limit is 0 here: no core files will appear")
    try:
        pattern = Path("/proc/sys/kernel/core_pattern").read_text().strip()
    except OSError:
        return
    if pattern.startswith("|"):
        print(f"--core-dumps: the kernel hands cores to a program ({pattern}), not to files")


def failures(junit: Path) -> tuple[int, list[str]]:
    """(tests run, ids of those that failed or errored) from a JUnit XML report."""
    if not junit.exists():
        return 0, ["<no report: pytest did not finish>"]
    root = ET.parse(junit).getroot()
    ran, bad = 0, []
    for case in root.iter("testcase"):
        ran += 1
        if case.find("failure") is not None or case.find("error") is not None:
            bad.append(f"{case.get('classname')}::{case.get('name')}")
    return ran, bad


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--hogs", type=int, default=os.cpu_count() or 2,
                        help="busy-loop processes beside the suite (default: one per core)")
    parser.add_argument("--no-clone", dest="clone", action="store_false",
                        help="run in this checkout instead of a clean clone of HEAD")
    parser.add_argument("--core-dumps", action="store_true",
                        help="allow core files and list those a run left (keeps the clone)")
    parser.add_argument("pytest_args", nargs="*")
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="beehave-stress-"))
    where = ROOT
    if args.clone:
        where = work / "clone"
        subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(ROOT), str(where)],
                       check=True)
        head = subprocess.check_output(["git", "-C", str(where), "rev-parse", "--short",
                                        "HEAD"], text=True).strip()
        print(f"clean clone of {head} in {where}")
    env = dict(os.environ, BEEHAVE_REQUIRE_EXTRAS="1")
    env.pop("ROS_DOMAIN_ID", None)
    # The clone's packages first (python -m puts the working directory on sys.path).
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(where), os.environ.get("PYTHONPATH", "")) if p)
    counts: collections.Counter[str] = collections.Counter()
    rows = []
    cores: list[Path] = []
    if args.core_dumps:
        _warn_if_no_core_files()
    hogs = start_hogs(args.hogs)
    print(f"{len(hogs)} busy-loop processes running beside the suite: "
          f"{[h.pid for h in hogs]}")
    try:
        for run in range(1, args.runs + 1):
            junit = work / f"run{run}.xml"
            start = time.monotonic()
            # Written as it comes (a run that hangs leaves its log), kept when it failed.
            log_path = work / f"run{run}.log"
            env["BEEHAVE_KEEP_DIR"] = str(work / f"run{run}-kept")  # a failure's recordings
            cores_before = set(where.glob("core*"))
            with open(log_path, "w") as log:
                done = subprocess.run([sys.executable, *PYTEST, "-p", "no:cacheprovider",
                                       f"--junitxml={junit}", *args.pytest_args],
                                      cwd=where, env=env, stdin=subprocess.DEVNULL,
                                      stdout=log, stderr=subprocess.STDOUT,
                                      preexec_fn=_allow_cores if args.core_dumps else None)
            wall = time.monotonic() - start
            ran, bad = failures(junit)
            counts.update(bad)
            output = log_path.read_text(errors="replace")
            summary = next((line for line in reversed(output.splitlines())
                            if " in " in line and ("passed" in line or "failed" in line)),
                           f"exit {done.returncode}")
            rows.append((run, wall, ran, len(bad), done.returncode))
            print(f"run {run:2d}: {wall:6.1f} s  exit {done.returncode}  {summary}", flush=True)
            for core in sorted(set(where.glob("core*")) - cores_before):
                cores.append(core)
                print(f"         core file: {core}")
            if bad or done.returncode != 0:
                for test in bad:
                    print(f"         failed: {test}")
            else:
                log_path.unlink()
    finally:
        stop_hogs(hogs)
    walls = sorted(r[1] for r in rows)
    green = sum(1 for r in rows if r[4] == 0)
    print(f"\n{green} of {len(rows)} runs green beside {len(hogs)} busy loops; wall time "
          f"median {statistics.median(walls):.1f} s, max {max(walls):.1f} s")
    if counts:
        print("tests that failed (times):")
        for test, n in counts.most_common():
            print(f"  {n}x  {test}")
        print(f"logs of the failed runs: {work}")
    if cores:
        print(f"{len(cores)} core file(s) kept in {where} (gdb {sys.executable} <core>)")
    elif not counts:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if green == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
