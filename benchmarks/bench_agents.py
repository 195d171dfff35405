"""Agent layer over DDS, every peer in its own process (``python -m benchmarks agents``).

- ``rclpy_roundtrip``: the floor — a bare ``std_msgs/String`` ping echoed by another
  process (same QoS as an inbox), measured in the same run;
- ``agent_roundtrip``: an ACL message to an agent in another process and its reply
  (JSON, pydantic validation and routing on both sides), p50/p99 and ratio to the floor;
- ``agent_appear``: from a new agent taking its name (after its probe) to another agent's
  directory listing it; ``agent_disappear``: from ``kill -9`` to its removal (target
  ≤ lease + 0.5 s); ``agent_probe``: how long a new agent listens before it takes its name;
- ``contract_net_award``: one contract-net round, cfp → accept-proposal, with 1, 5 and 25
  responders, each in its own process (target at 5: p50 ≤ 5 ms, p99 ≤ 20 ms), also as a
  ratio to the floor. The 25 responders start in parallel (one by one, their imports and
  name probes alone would take about a minute on two cores).
- signed mode (docs/agents.md, "Trust model") in the same run: ``agent_roundtrip_signed``
  and ``contract_net_award_5_signed`` — every message signed with Ed25519 and checked
  (certificate, signature, window, replay) by the receiver; keys from ``beehave keys`` in a
  temporary folder; the children take them from ``BEEHAVE_AGENT_MODE``/``KEYS``
  (target: signed 5-responder p99 ≤ 20 ms).

``BENCH_AGENTS_RESPONDERS`` (default ``1,5,25``) picks the open contract-net sizes.

Children: ``python -m benchmarks.bench_agents floor-echo | echo NAME | responder NAME COST``.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(101, 200)))

from std_msgs.msg import String  # noqa: E402

from beehave import HighLevelBehaviorManager  # noqa: E402
from beehave.agents import Agent, Change, DirectoryEvent, Message, Performative  # noqa: E402
from beehave.agents.agent import inbox_qos  # noqa: E402
from beehave.agents.protocols import ContractNetResponder, contract_net  # noqa: E402
from beehave.ros.context import RosContext  # noqa: E402
from benchmarks._util import median, percentile, report  # noqa: E402

N_ROUNDTRIP = int(os.environ.get("BENCH_AGENTS_N", 500))
N_ROUNDS = int(os.environ.get("BENCH_AGENTS_ROUNDS", 100))
RESPONDERS = [int(n) for n in os.environ.get("BENCH_AGENTS_RESPONDERS", "1,5,25").split(",")]
LEASE_S = 1.0


# ---------------------------------------------------------------------- children
def _floor_echo() -> None:
    with RosContext() as ros:
        node = ros.create_node("agents_floor_echo")
        pub = node.create_publisher(String, "agents_floor_pong", inbox_qos(1000))
        node.create_subscription(String, "agents_floor_ping", pub.publish, inbox_qos(1000))
        print("ready", flush=True)  # the parent waits until both directions are matched
        sys.stdin.readline()


def _echo(name: str) -> None:
    with RosContext() as ros, Agent(name, ros=ros, lease_s=LEASE_S) as agent:
        print("ready", time.time(), flush=True)
        while True:
            message = agent.receive(timeout_s=None)
            if message.content == "stop":
                return
            agent.reply(message, Performative.INFORM, message.content)


class _Bid(ContractNetResponder):
    service = "bench_transport"

    def __init__(self, cost: float) -> None:
        self.price = cost

    def propose(self, cfp: Message) -> Any:
        return {"cost": self.price}

    def perform(self, task: Message) -> Any:
        return "done"  # at once: the round ends with the award and its inform


def _responder(name: str, cost: float) -> None:
    with RosContext() as ros:
        begun = time.time()
        with Agent(name, ros=ros, lease_s=LEASE_S,
                   services={"bench_transport": {}}) as agent, \
                HighLevelBehaviorManager(stop_timeout_s=0.5) as hl:
            agent.attach(hl)
            hl.register("bid", _Bid, cost=cost)
            hl.switch("bid")
            while not agent._mailboxes:  # the responder listens
                time.sleep(0.01)
            print("ready", begun, flush=True)
            sys.stdin.readline()


# ---------------------------------------------------------------------- parent
def _spawn(*args: str) -> subprocess.Popen[str]:
    return _spawn_ready(*args)[0]


def _spawn_ready(*args: str) -> tuple[subprocess.Popen[str], str]:
    proc = _start(*args)
    return proc, _await_ready(proc, args)


def _start(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "benchmarks.bench_agents", *args],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, **(env or {})})


def _await_ready(proc: subprocess.Popen[str], args: tuple[str, ...]) -> str:
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith("ready"):
        proc.kill()
        raise RuntimeError(f"benchmark child {args} did not start: {line!r}")
    return line


def _stop(procs: list[subprocess.Popen[str]]) -> None:
    for proc in procs:
        if proc.poll() is None:
            assert proc.stdin is not None
            try:
                proc.stdin.write("\n")
                proc.stdin.flush()
            except BrokenPipeError:
                pass
    for proc in procs:
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def floor_roundtrip(n: int) -> list[float]:
    echo = _spawn("floor-echo")
    samples: list[float] = []
    try:
        with RosContext() as ros:
            node = ros.create_node("agents_floor_ping")
            got = threading.Event()
            node.create_subscription(String, "agents_floor_pong", lambda _: got.set(),
                                     inbox_qos(1000))
            pub = node.create_publisher(String, "agents_floor_ping", inbox_qos(1000))
            while pub.get_subscription_count() == 0 or node.count_publishers(
                    "agents_floor_pong") == 0:
                time.sleep(0.01)
            time.sleep(0.3)  # the echo's writer has matched our reader too
            for i in range(n + 20):
                got.clear()
                start = time.perf_counter()
                pub.publish(String(data=str(i)))
                if not got.wait(2.0):
                    continue
                if i >= 20:  # warm-up
                    samples.append(time.perf_counter() - start)
    finally:
        _stop([echo])
    return samples


def agent_roundtrip(agent: Agent, n: int, *, name: str = "bench_echo",
                    env: dict[str, str] | None = None) -> list[float]:
    echo = _start("echo", name, env=env)
    _await_ready(echo, ("echo", name))
    samples: list[float] = []
    try:
        with agent.conversation() as conv:
            for i in range(n + 20):
                start = time.perf_counter()
                conv.send(Performative.REQUEST, [name], i, timeout_s=10.0)
                conv.receive(timeout_s=5.0)
                if i >= 20:
                    samples.append(time.perf_counter() - start)
            conv.send(Performative.INFORM, [name], "stop")
    finally:
        echo.wait(10)
    return samples


def appear_disappear(agent: Agent) -> tuple[float, float]:
    """Seconds from the newcomer being alive to being listed, and from kill to delisted."""
    cond = threading.Condition()
    seen: dict[str, float] = {}

    def note(event: DirectoryEvent) -> None:
        if event.agent.name == "bench_new":
            with cond:
                seen[event.change.value] = time.time()
                cond.notify_all()

    unsubscribe = agent.directory.subscribe("bench_transport", note)
    proc, ready = _spawn_ready("responder", "bench_new", "1.0")
    try:
        with cond:
            cond.wait_for(lambda: Change.APPEARED.value in seen, 30.0)
        # From the moment the child called Agent() (its probe included).
        appeared_after = seen[Change.APPEARED.value] - float(ready.split()[1])
        killed = time.time()
        proc.kill()
        with cond:
            cond.wait_for(lambda: Change.DISAPPEARED.value in seen, 30.0)
        return appeared_after, seen[Change.DISAPPEARED.value] - killed
    finally:
        unsubscribe()
        proc.wait(10)


def contract_rounds(agent: Agent, responders: int, rounds: int, *,
                    prefix: str = "bench_bidder_",
                    env: dict[str, str] | None = None) -> list[float]:
    names = [f"{prefix}{k}" for k in range(responders)]
    # All started at once, then awaited: the imports and name probes overlap.
    procs = [_start("responder", name, str(1.0 + k), env=env) for k, name in enumerate(names)]
    try:
        for proc, name in zip(procs, names, strict=True):
            _await_ready(proc, ("responder", name))
        deadline = time.monotonic() + 60.0
        while len([a for a in agent.directory.search("bench_transport")
                   if a.name in names]) < responders:
            if time.monotonic() > deadline:
                raise RuntimeError("bidders did not appear")
            time.sleep(0.02)
        samples = []
        for i in range(rounds + 5):
            award = contract_net(agent, "bench_transport", {"round": i}, candidates=names,
                                 reply_by_s=5.0, done_timeout_s=5.0)
            if i >= 5:
                samples.append(award.award_latency_s)
        return samples
    finally:
        _stop(procs)


def main() -> list[dict[str, Any]]:
    # As a HighLevelBehaviorManager does in every robot process (gil_switch_interval_s):
    # a thread woken by a message gets the interpreter within 1 ms, not Python's 5 ms.
    sys.setswitchinterval(0.001)
    rows = []
    floor = floor_roundtrip(N_ROUNDTRIP)
    floor_p50 = median(floor)
    rows.append(report("agents_rclpy_roundtrip_floor_p50", floor_p50 * 1e3, "ms", None, None,
                       p99_ms=round(percentile(floor, 99) * 1e3, 3), n=len(floor)))
    with RosContext() as ros:
        started = time.monotonic()
        agent = Agent("bench_initiator", ros=ros, lease_s=LEASE_S)
        rows.append(report("agent_probe", time.monotonic() - started, "s", None, None,
                           note="a new agent listens for a holder of its name first"))
        with agent:
            rt = agent_roundtrip(agent, N_ROUNDTRIP)
            rows.append(report("agent_roundtrip_p50", median(rt) * 1e3, "ms", None, None,
                               p99_ms=round(percentile(rt, 99) * 1e3, 3),
                               over_floor=round(median(rt) / floor_p50, 2)))
            appear, disappear = appear_disappear(agent)
            rows.append(report("agent_appear", appear, "s", None, None,
                               note="from Agent() in a new process (its probe included) "
                                    "to another agent's listing"))
            rows.append(report("agent_disappear_after_kill", disappear, "s",
                               f"<= {LEASE_S + 0.5} s (lease {LEASE_S} s + 0.5)",
                               disappear <= LEASE_S + 0.5))
            for responders in RESPONDERS:
                award = contract_rounds(agent, responders, N_ROUNDS)
                p50, p99 = median(award), percentile(award, 99)
                target = responders == 5
                rows.append(report(f"contract_net_award_{responders}_p50", p50 * 1e3, "ms",
                                   "<= 5 ms" if target else None,
                                   p50 <= 0.005 if target else None,
                                   over_floor=round(p50 / floor_p50, 1)))
                rows.append(report(f"contract_net_award_{responders}_p99", p99 * 1e3, "ms",
                                   "<= 20 ms" if target else None,
                                   p99 <= 0.020 if target else None,
                                   over_floor=round(p99 / floor_p50, 1)))
        rows += _signed(ros, floor_p50, rt)
    return rows


def _signed(ros: RosContext, floor_p50: float, open_rt: list[float]) -> list[dict[str, Any]]:
    """The same round trip and 5-responder contract net with every message signed and
    checked (keys made as a user makes them, `beehave keys`)."""
    from beehave.agents.trust import Trust, init_fleet, issue

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_keys_") as keys:
        init_fleet(keys)
        names = ["bench_initiator_s", "bench_echo_s", *(f"bench_sbidder_{k}" for k in range(5))]
        for name in names:
            issue(keys, name)
        env = {"BEEHAVE_AGENT_MODE": "signed", "BEEHAVE_AGENT_KEYS": keys}
        trust = Trust.load("bench_initiator_s", mode="signed", keys_dir=keys)
        with Agent("bench_initiator_s", ros=ros, lease_s=LEASE_S, trust=trust) as agent:
            rt = agent_roundtrip(agent, N_ROUNDTRIP, name="bench_echo_s", env=env)
            rows.append(report("agent_roundtrip_signed_p50", median(rt) * 1e3, "ms", None,
                               None, p99_ms=round(percentile(rt, 99) * 1e3, 3),
                               over_open=round(median(rt) / median(open_rt), 2),
                               over_floor=round(median(rt) / floor_p50, 2)))
            award = contract_rounds(agent, 5, N_ROUNDS, prefix="bench_sbidder_", env=env)
            p50, p99 = median(award), percentile(award, 99)
            rows.append(report("contract_net_award_5_signed_p50", p50 * 1e3, "ms", None,
                               None, over_floor=round(p50 / floor_p50, 1)))
            rows.append(report("contract_net_award_5_signed_p99", p99 * 1e3, "ms",
                               "<= 20 ms", p99 <= 0.020, over_floor=round(p99 / floor_p50, 1)))
    return rows


if __name__ == "__main__":
    mode = sys.argv[1] if len(sys.argv) > 1 else "main"
    if mode == "floor-echo":
        _floor_echo()
    elif mode == "echo":
        _echo(sys.argv[2])
    elif mode == "responder":
        _responder(sys.argv[2], float(sys.argv[3]))
    else:
        main()
