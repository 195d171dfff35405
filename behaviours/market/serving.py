"""Serving guests with a market (the ARCADE paper's SERVE task): the robots' side.

A serving role is a list of **steps**, each at a place of the world, that the role's
params carry (``role.params["steps"]``); :class:`ServeBroker` bids the drive through them
(:class:`~behaviours.market.TravelBroker`: planned paths around the obstacles inflated by
the robot's own radius) and :class:`ServeRole` performs them in the physics:

==========  ==========================================================================
step        what the robot does there
==========  ==========================================================================
``pick``    stand in a shelf station until the simulation says it holds an item
``give``    meet the partner role at the meeting point (both signal ``at_meeting`` and
            wait for the other's), offer the item to the partner's robot
            (:data:`HAND_OVER_TOPIC`) until it has left this robot, signal ``handed``
``take``    raise the lift (the item goes onto the plate), meet the partner, stand still
            until it holds the item and the partner signalled ``handed``; signal
            ``received``
``serve``   at a table: show the order on the display (EMILI), stand still until the
            guest took the item, clear the display, lower the lift; signal ``served``
==========  ==========================================================================

A step is ``[op, place name, [x_m, y_m]]``: the name is for people and reports, the point
is where the robot stands (the order source resolves station names against the world, so
a broker needs no names to bid). Whether a robot holds an item is decided by the
simulation, not by the robot: it publishes ``/serve/state`` (:data:`SERVE_STATE`, JSON of
schema :data:`STATE_SCHEMA`) and the action reads it.

**One robot at a time in a narrow zone.** The aisle is one lane: two Kobukis that meet in
it block each other for good (neither planner finds a way around). A zone keeper agent
(:class:`ZoneKeeper`, ``python -m behaviours.market.serving ZONE``; the charging stations'
leased reservations of :mod:`behaviours.fleet.station`, service :data:`ZONE_SERVICE`)
hands the zone to one robot at a time: before a leg that ends inside a kept zone the
role reserves it (waiting where it stands while another robot holds it), renews the lease
while inside, and releases it as soon as its odometry is out again. A robot that dies
leaves the directory, which frees its zone.

**An item belongs to an order.** The physics says *whether* a robot holds an item; only
the robot knows *for which order* it picked or took it (:class:`Hold`, one per broker,
kept across its roles). A role whose coalition was dissolved may leave the item on the
robot; when the order is awarded again, the robot that holds its item carries on with it
(its ``pick`` / ``take`` steps are skipped, and its bid is the cheaper for it) instead of
picking a second one, and a robot never starts a ``pick`` or ``take`` for another order
with a full plate: it refuses such a role in its bid until the order it carries is queued
ahead, and a role that finds it so anyway fails at once, naming the item.

The partner of ``give`` / ``take`` is ``role.params["partner"]``, else the plan's other
role. Waiting never blocks the control loop: under sim time the action keeps ticking (and
so keeps its lockstep with the simulator) while it waits — a blocking wait would hold the
simulation, and the partner could never arrive.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64, String

from beehave.action import Action
from beehave.agents import Agent
from beehave.agents.market import Job
from beehave.agents.protocols import request
from beehave.errors import (
    AgentError,
    BeehaveError,
    Interrupted,
    NoReply,
    ProtocolFailed,
    RendezvousTimeout,
)
from behaviours.actions import Goal, Navigation, SpeedLimit, first_message, world_planner
from behaviours.fleet.process import serve
from behaviours.fleet.site import site
from behaviours.fleet.station import Reservations
from behaviours.market.brokers import TravelBroker
from robots import topics

log = logging.getLogger(__name__)

__all__ = ["HAND_OVER_TOPIC", "OPS", "Hold", "SERVE_STATE", "STATE_QOS", "STATE_SCHEMA",
           "ZONE_PROTOCOL", "ZONE_SERVICE", "ServeBroker", "ServeError", "ServeRole", "Step",
           "ZoneKeeper", "parse_steps"]

SERVE_STATE = "/serve/state"
"""The simulation's word on who holds which item (std_msgs/String, JSON)."""
STATE_SCHEMA = "beehave/serve/state/1"
"""``{"schema", "time_s", "robots": {ns: {"item": str | None, "x_m", "y_m", "lift_m"}},
"events": [...]}``."""
HAND_OVER_TOPIC = "/serve/hand_over"
"""A giver's offer (std_msgs/String, JSON ``{"giver": ns, "taker": ns}``), repeated while
it stands at the meeting point: the simulation hands the item over only on an offer."""
STATE_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""Latched: an action that subscribes late gets the last state at once."""

OPS = ("pick", "give", "take", "serve")
"""The steps a serving role may have (see the module docstring)."""

ZONE_SERVICE = "zone"
"""The directory service of a :class:`ZoneKeeper`: ``{"station": zone, "holder": robot}``."""
ZONE_PROTOCOL = "zone"
"""Its requests: ``{"op": "reserve" | "renew" | "release", "lease_s": L}``."""
ZONE_LEASE_S = 30.0
"""Wall seconds a zone reservation lasts unless renewed (every third of it while inside)."""

Step = tuple[str, str, tuple[float, float]]


class ServeError(BeehaveError):
    """A serving step did not happen in time (no item at the shelf, no guest took it)."""


class Hold:
    """What one robot carries, and for which order (thread-safe: the broker reads it in its
    bids, the robot's roles write it). ``item`` is the physics' name of the item
    (``shelf_open#1``), ``task`` the id of the order this robot picked or took it for."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._item: str | None = None
        self._task: str | None = None

    def get(self) -> tuple[str | None, str | None]:
        """``(item, task)``; ``(None, None)`` when the robot carries nothing."""
        with self._lock:
            return self._item, self._task

    def set(self, item: str | None, task: str | None) -> None:
        with self._lock:
            self._item, self._task = item, (task if item is not None else None)

    def sync(self, physics_item: str | None) -> None:
        """Agree with the physics: an item it does not hold any more is forgotten, one it
        holds that was never recorded belongs to no known order."""
        with self._lock:
            if physics_item != self._item:
                self._item, self._task = physics_item, None

    def conflict(self, jobs: list[Job]) -> str | None:
        """Why this robot cannot do ``jobs`` in this order with what it carries now, or
        None: a role that picks or takes an item must not come while the robot still
        carries another order's item (every role that gets an item also puts it down, so
        the plate is free again after the carried order's role)."""
        item, task = self.get()
        for job in jobs:
            if item is None:
                return None
            if job.task.id == task:
                item = None  # this role carries on with it and puts it down
            elif any(op in ("pick", "take") for op, _, _ in parse_steps(job.role.params)):
                return (f"carries {item} of order {task!r}" if task is not None else
                        f"carries {item} of no known order") + \
                    f": it cannot {job.task.id}/{job.role.name} before that is put down"
        return None


def held_item(msg: String | None, robot: str) -> tuple[bool, str | None]:
    """(known, item) from a ``/serve/state`` message: whether it says anything about
    ``robot`` (no message or an unreadable one: not known), and the item it holds."""
    if msg is None:
        return False, None
    try:
        entry = json.loads(msg.data)["robots"][robot]
    except (ValueError, KeyError, TypeError):
        return False, None
    item = entry.get("item") if isinstance(entry, dict) else None
    return True, item if isinstance(item, str) else None


def parse_steps(params: Any, *, where: str = "role") -> list[Step]:
    """``params["steps"]`` as ``(op, place, (x_m, y_m))`` tuples; raises
    :class:`ValueError` naming the step, what is wrong and the valid ops."""
    steps = params.get("steps") if isinstance(params, dict) else None
    if not isinstance(steps, list) or not steps:
        raise ValueError(f"{where}: params.steps must be a non-empty list of "
                         f"[op, place, [x_m, y_m]] with op in {list(OPS)}, got {steps!r}")
    out: list[Step] = []
    for i, step in enumerate(steps):
        ok = isinstance(step, (list, tuple)) and len(step) == 3 and step[0] in OPS \
            and isinstance(step[1], str) and isinstance(step[2], (list, tuple)) \
            and len(step[2]) == 2 and all(isinstance(v, (int, float)) and not isinstance(
                v, bool) and math.isfinite(v) for v in step[2])
        if not ok:
            raise ValueError(f"{where}: params.steps[{i}] = {step!r} is not [op, place, "
                             f"[x_m, y_m]] with op in {list(OPS)} and two finite numbers")
        out.append((str(step[0]), str(step[1]), (float(step[2][0]), float(step[2][1]))))
    return out


class ZoneKeeper(Reservations):
    """Lets one robot at a time into a zone of the world (the narrow aisle): the charging
    stations' leased reservations (:class:`behaviours.fleet.station.Reservations`) under
    service and protocol ``zone``."""

    protocol = ZONE_PROTOCOL
    service = ZONE_SERVICE

    def _publish(self) -> None:
        self.agent.register(ZONE_SERVICE, **self.service_properties())


class ServeBroker(TravelBroker):
    """A robot's broker for serving roles: bids seconds as a
    :class:`~behaviours.market.TravelBroker` (the marginal sum of completion times of its
    queue, the role at its cheapest place after the one that runs) — the planned drive
    through the roles' steps, slower in speed zones, waiting for a kept zone another
    robot holds — refuses what its size cannot reach (EMILI has no path into the narrow
    aisle), and performs a role with :class:`ServeRole`.

    ``capabilities``: what it registers (EMILI: ``carry`` and ``serve`` — lift and display;
    a Kobuki: ``carry``). ``robot_radius_m`` and ``clearance_m`` inflate the obstacles for
    both the bid and the drive, so a bid is never made for a place the robot cannot go.
    ``has_lift`` / ``has_display``: the robot raises its lift to take an item and shows the
    order at the table. ``meet_timeout_s`` (sim time) bounds the wait for the partner at
    the meeting point — long enough for the partner's queued work; ``wait_timeout_s``
    bounds every wait on the physics (pick, hand-over, the guest)."""

    def __init__(self, world: str = "serve", *, capabilities: tuple[str, ...] = ("carry",),
                 robot_radius_m: float = 0.2, clearance_m: float = 0.1,
                 speed_mps: float = 0.4, handling_s: float = 4.0,
                 capacity_wh: float = 32.6, max_queue: int = 2, has_lift: bool = False,
                 has_display: bool = False, meet_timeout_s: float = 240.0,
                 wait_timeout_s: float = 60.0, stop_distance_m: float = 0.45) -> None:
        super().__init__(world_planner(world, robot_radius_m, clearance_m),
                         speed_mps=speed_mps, handling_s=handling_s,
                         capacity_wh=capacity_wh, max_queue=max_queue)
        self.capabilities = tuple(capabilities)
        self.world = world
        self.nav = {"world": world, "robot_radius_m": robot_radius_m,
                    "clearance_m": clearance_m, "speed_mps": speed_mps,
                    "stop_distance_m": stop_distance_m,
                    "slow_distance_m": stop_distance_m + 0.4}
        self.has_lift, self.has_display = has_lift, has_display
        self.meet_timeout_s, self.wait_timeout_s = meet_timeout_s, wait_timeout_s
        #: What this robot carries, for which order (shared by its roles).
        self.hold = Hold()
        self._state: Any = None  # the physics' word, for the bids (None without ROS)
        self._live = False  # started (it has an agent and its directory)

    def run(self) -> None:
        self._live = True
        if self.manager.node is not None:
            # Declared now, not at the first drive: the speed zones logic sets it from the
            # start (a robot entering the aisle on its first role is already limited).
            SpeedLimit.of(self.manager.node)
            self._state = self.ros.latest(String, SERVE_STATE, qos=STATE_QOS)
        super().run()

    def _physics_item(self) -> tuple[bool, str | None]:
        """(known, item): whether the simulation said yet, and what this robot holds."""
        if self._state is None or self.manager.node is None:
            return False, None
        return held_item(self._state.get(), self.manager.node.get_namespace().strip("/"))

    def stops(self, job: Job) -> list[tuple[float, float]]:
        # The robot that carries the order's item already skips its pick / take.
        carried = self.hold.get()[1] == job.task.id
        return [xy for op, _, xy in parse_steps(job.role.params)
                if not (carried and op in ("pick", "take"))]

    def schedule(self, jobs: list[Job]) -> list[float] | str:
        for job in jobs:
            try:
                parse_steps(job.role.params, where=f"task {job.task.id!r}, role "
                                                   f"{job.role.name!r}")
            except ValueError as exc:
                return str(exc)  # a malformed order is refused, saying why
        known, item = self._physics_item()
        if known and not getattr(self, "_jobs", None):
            # Nothing awarded that could change it: the physics' word is current (a role
            # interrupted right after its hand-over did not get to forget the item).
            self.hold.sync(item)
        conflict = self.hold.conflict(jobs)
        return conflict if conflict is not None else super().schedule(jobs)

    def zone_holders(self) -> dict[str, str]:
        """Optional hook: kept zone → the robot that holds it now (default: the zone
        keepers' directory entries; other robots only)."""
        if not self._live:
            return {}  # not started: no directory to read
        agent = self.agent
        held = {}
        for info in agent.directory.search(ZONE_SERVICE):
            props = info.properties(ZONE_SERVICE)
            holder = props.get("holder")
            if isinstance(holder, str) and holder != agent.name:
                held[str(props.get("station"))] = holder
        return held

    def _crossing_s(self, zone: Any) -> float:
        """What a robot that holds ``zone`` needs to get out of it, at worst: in to its
        far end and back at the zone's limit, plus handling there."""
        xs = [p[0] for p in zone.points_m]
        ys = [p[1] for p in zone.points_m]
        extent_m = math.hypot(max(xs) - min(xs), max(ys) - min(ys))
        speed_mps = float(min(zone.max_speed_mps, self.speed_mps))
        return 2.0 * extent_m / speed_mps + float(self.handling_s)

    def leg_s(self, start: tuple[float, float], stop: tuple[float, float], *,
              at_s: float) -> float:
        """The planned path at the robot's speed, slower where it crosses a speed zone
        (sampled every 0.1 m), plus the wait, before a leg that ends in a kept zone
        another robot holds, until that robot is out (at worst one crossing of the zone
        from now: :meth:`_crossing_s`)."""
        points = self.planner.plan(start, stop).waypoints_m
        zones = site(self.world).zones
        holders = self.zone_holders() if zones else {}
        waits = [z for z in zones if z.name in holders and z.contains(*stop)
                 and not z.contains(*start)]
        outside_s = inside_s = 0.0  # inside: in a zone it must wait for
        for a, b in zip(points, points[1:], strict=False):
            length_m = math.hypot(b[0] - a[0], b[1] - a[1])
            n = max(1, math.ceil(length_m / 0.1))
            for i in range(n):
                f = (i + 0.5) / n
                x, y = a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])
                speed = min([self.speed_mps, *(z.max_speed_mps for z in zones
                                               if z.contains(x, y))])
                if any(z.contains(x, y) for z in waits):
                    inside_s += length_m / n / speed
                else:
                    outside_s += length_m / n / speed
        # It stands at the zone's edge until the holder is out of the zone.
        free_at_s = max((self._crossing_s(z) for z in waits), default=0.0)
        return max(outside_s, free_at_s - at_s) + inside_s

    def perform_role(self, job: Job) -> Action:
        return ServeRole(job, agent=self.agent, hold=self.hold, has_lift=self.has_lift,
                         has_display=self.has_display,
                         meet_timeout_s=self.meet_timeout_s,
                         wait_timeout_s=self.wait_timeout_s, **self.nav)


class ServeRole(Navigation):
    """Performs one serving role step by step (see the module docstring); returns
    ``{"robot", "task", "role", "steps": [[op, place, sim time s], ...]}``.

    A Navigation under the ``driving`` lock: a robot's roles queue behind each other, and
    its safe state stops the base. Failures are typed: :class:`ServeError` when the
    physics did not do its part in ``wait_timeout_s``,
    :class:`~beehave.errors.RendezvousTimeout` when the partner did not come."""

    LIFT_UP_M = 0.2

    def __init__(self, job: Job, *, agent: Agent | None = None, hold: Hold | None = None,
                 has_lift: bool = False, has_display: bool = False,
                 meet_timeout_s: float = 240.0, wait_timeout_s: float = 60.0,
                 **nav: Any) -> None:
        self.job = job
        self.agent = agent
        self.hold = hold if hold is not None else Hold()
        self.world = nav.get("world")
        #: Zone keepers whose zone this robot holds now: keeper → (zone, last renewal).
        self.held: dict[str, tuple[Any, float]] = {}
        self.steps = parse_steps(job.role.params)
        first = self.steps[0]
        super().__init__(Goal(*first[2], name=first[1]), tolerance_m=0.12, **nav)
        self.name = f"Serve:{job.task.id}/{job.role.name}"
        self.has_lift, self.has_display = has_lift, has_display
        self.meet_timeout_s, self.wait_timeout_s = meet_timeout_s, wait_timeout_s
        others = [r.name for r in job.plan.roles if r.name != job.role.name]
        partner = job.role.params.get("partner")
        self.partner = partner if isinstance(partner, str) else (others[0] if others
                                                                  else None)
        self.phase = "planned"

    # ---- the physics' word ------------------------------------------------------------

    def _item(self) -> str | None:
        return held_item(self._state.get(), self._me)[1]

    def _until(self, done: Callable[[], bool], timeout_s: float, what: str,
               error: type[BeehaveError] = ServeError) -> None:
        """Stand still, ticking (lockstep), until ``done()``; ``error`` after
        ``timeout_s`` of the manager's clock (sim time under use_sim_time)."""
        clock = self.manager.clock
        deadline = clock.now() + timeout_s
        while not done():
            if self.interrupted:
                raise Interrupted(f"{self.name}: interrupted while waiting for {what}")
            if clock.now() > deadline:
                raise error(f"{self.name} ({self._me}): {what} did not happen within "
                            f"{timeout_s:g} s (events reached: "
                            f"{sorted(self.job.reached) or 'none'})")
            self.command(0.0, 0.0)
            self.tick()

    def _meet(self) -> None:
        if self.partner is None:
            raise ServeError(f"{self.name}: a hand-over needs a partner role; plan "
                             f"{self.job.plan.name!r} has only {self.job.role.name!r}")
        self.job.signal("at_meeting")
        event = f"{self.partner}:at_meeting"
        self._until(self._reached(event), self.meet_timeout_s,
                    f"{event!r} (the rendezvous)", RendezvousTimeout)

    def _offer(self) -> Callable[[], bool]:
        """The giver's side of a hand-over: offer the item to the partner's robot (on
        :data:`HAND_OVER_TOPIC`, at every control period) until it has left this robot.
        The simulation moves it only while both stand at the meeting point, the taker's
        lift up: a robot that merely passes by a waiting EMILI keeps its item."""
        taker = self.job.members.get(self.partner or "")
        pub = self.ros.publisher(String, HAND_OVER_TOPIC)
        offer = String(data=json.dumps({"giver": self._me, "taker": taker}))

        def handed() -> bool:
            if self._item() is None:
                return True
            pub.publish(offer)
            return False

        return handed

    def _reached(self, event: str) -> Callable[[], bool]:
        return lambda: event in self.job.reached

    def _lift(self, height_m: float) -> None:
        if not self.has_lift:
            return
        self._lift_cmd.publish(Float64(data=height_m))

        def there() -> bool:
            msg = self._lift_state.get()
            return msg is not None and abs(msg.data - height_m) <= 0.01

        self._until(there, 20.0, f"the lift at {height_m:g} m")

    def _show(self, text: str) -> None:
        if self.has_display:
            self._display.publish(String(data=text))

    # ---- one robot at a time in a kept zone ---------------------------------------------

    def _keepers_at(self, x: float, y: float) -> list[tuple[str, Any]]:
        """The zone keepers in the directory whose zone holds (x, y)."""
        if self.agent is None or self.world is None:
            return []
        zones = {z.name: z for z in site(self.world).zones}
        found = []
        for info in self.agent.directory.search(ZONE_SERVICE):
            zone = zones.get(str(info.properties(ZONE_SERVICE).get("station")))
            if zone is not None and zone.contains(x, y):
                found.append((info.name, zone))
        return found

    def _ask(self, keeper: str, op: str) -> None:
        assert self.agent is not None
        request(self.agent, keeper, {"op": op, "lease_s": ZONE_LEASE_S},
                protocol=ZONE_PROTOCOL, timeout_s=3.0)

    def _enter(self, x: float, y: float, place: str) -> None:
        """Reserve every kept zone (x, y) lies in, standing where it is while another robot
        holds one (up to ``meet_timeout_s``)."""
        for keeper, zone in self._keepers_at(x, y):
            if keeper in self.held:
                continue
            clock = self.manager.clock
            deadline, why = clock.now() + self.meet_timeout_s, ""
            retry_at = -math.inf
            while True:
                if clock.now() >= retry_at:
                    try:
                        self._ask(keeper, "reserve")
                        break
                    except (ProtocolFailed, NoReply, AgentError) as exc:
                        why, retry_at = str(exc), clock.now() + 1.0
                if self.interrupted:
                    raise Interrupted(f"{self.name}: interrupted waiting for {zone.name}")
                if clock.now() > deadline:
                    raise ServeError(f"{self.name} ({self._me}): could not enter {zone.name} "
                                     f"for {place} within {self.meet_timeout_s:g} s: {why}")
                self.phase = f"waiting for {zone.name}"
                self.command(0.0, 0.0)
                super().tick()
            self.held[keeper] = (zone, time.monotonic())
            log.info("%s: %s is ours", self.name, zone.name)

    def _leave(self, *, everything: bool = False) -> None:
        """Release the kept zones the robot is out of (``everything``: all of them)."""
        msg = self.odom.get() if getattr(self, "odom", None) is not None else None
        for keeper, (zone, renewed) in list(self.held.items()):
            out = msg is not None and not zone.contains(msg.pose.pose.position.x,
                                                        msg.pose.pose.position.y)
            goal_in = zone.contains(self.goal.x_m, self.goal.y_m)
            try:
                if everything:
                    del self.held[keeper]
                    self._release_uninterrupted(keeper)
                elif out and not goal_in:
                    del self.held[keeper]
                    self._ask(keeper, "release")
                    log.info("%s: left %s", self.name, zone.name)
                elif time.monotonic() - renewed > ZONE_LEASE_S / 3:
                    self.held[keeper] = (zone, time.monotonic())
                    self._ask(keeper, "renew")
            except (ProtocolFailed, NoReply, AgentError) as exc:  # its lease ends it
                log.warning("%s: %s of %s: %s", self.name, "release" if keeper not in
                            self.held else "renewal", zone.name, exc)

    def _release_uninterrupted(self, keeper: str) -> None:
        """Release a zone also when this action was interrupted (its coalition dissolved):
        asked from a helper thread, which the interrupt does not reach, joined here — else
        the zone would stay closed until the lease runs out."""
        def release() -> None:
            try:
                self._ask(keeper, "release")
            except (ProtocolFailed, NoReply, AgentError) as exc:
                log.warning("%s: release of %s: %s (its lease ends it)", self.name, keeper,
                            exc)

        helper = threading.Thread(target=release, name=f"{self.name}:release",
                                  daemon=True)
        helper.start()
        helper.join(5.0)

    def tick(self) -> bool:
        if self.held:
            self._leave()
        return super().tick()

    # ---- the role ---------------------------------------------------------------------

    def drive(self) -> dict[str, Any]:  # type: ignore[override]
        node = self.manager.node
        self._me = node.get_namespace().strip("/") if node is not None else "?"
        self._state = self.ros.latest(String, SERVE_STATE, qos=STATE_QOS)
        if self.has_lift:
            self._lift_cmd = self.ros.publisher(Float64, topics.LIFT_COMMAND)
            self._lift_state = self.ros.latest(Float64, topics.LIFT_STATE)
            first_message(self._lift_state)
        if self.has_display:
            self._display = self.ros.publisher(String, topics.DISPLAY)
        # What the robot carries now, in the physics' word (latched: here at once).
        first_message(self._state)
        self.hold.sync(self._item())
        try:
            return self._perform()
        finally:
            if self.held:
                self._leave(everything=True)

    def _carried(self, op: str, place: str) -> str | None:
        """Before a ``pick`` / ``take``: the item to carry on with when the robot already
        holds this order's item (an earlier round of it, dissolved, left it here), None
        when the plate is free; :class:`ServeError` when it holds another order's item —
        no second item onto a full plate, and no hand-over could ever happen."""
        item, task = self.hold.get()
        if item is None:
            return None
        if task == self.job.task.id:
            log.info("%s: carries on with %s (picked for this order in an earlier round); "
                     "no %s at %s", self.name, item, op, place)
            return item
        raise ServeError(f"{self.name} ({self._me}): cannot {op} at {place}: it carries "
                         f"{item} of " + (f"order {task!r}" if task is not None
                                          else "no known order") + " (put down first)")

    def _perform(self) -> dict[str, Any]:
        job, clock = self.job, self.manager.clock
        done: list[list[Any]] = []
        for op, place, (x, y) in self.steps:
            if op in ("pick", "take"):
                carried = self._carried(op, place)
                if carried is not None:
                    job.signal("picked" if op == "pick" else "received",
                               {"item": carried, "carried_over": True})
                    done.append([f"kept ({op})", place, round(clock.now(), 2)])
                    continue
            self._enter(x, y, place)
            self.phase = f"to {place}"
            self.goal = Goal(x, y, name=place)
            super().drive()
            if self.interrupted:
                raise Interrupted(f"{self.name}: interrupted on the way to {place}")
            self.phase = f"{op} at {place}"
            if op == "pick":
                self._until(lambda: self._item() is not None, self.wait_timeout_s,
                            f"an item picked at {place}")
                self.hold.set(self._item(), job.task.id)
                job.signal("picked", {"item": self._item()})
            elif op == "give":
                self._meet()
                self._until(self._offer(), self.wait_timeout_s,
                            "the hand-over (the item leaving this robot)")
                self.hold.set(None, None)
                job.signal("handed")
            elif op == "take":
                self._lift(self.LIFT_UP_M)  # the item goes onto the raised plate
                self._meet()
                self._until(lambda: self._item() is not None, self.wait_timeout_s,
                            "the hand-over (an item on this robot)")
                self.hold.set(self._item(), job.task.id)
                handed = f"{self.partner}:handed"
                self._until(self._reached(handed), self.wait_timeout_s,
                            f"{handed!r}", RendezvousTimeout)
                job.signal("received", {"item": self._item()})
            else:  # serve
                item = self._item()
                if item is None:
                    raise ServeError(f"{self.name} ({self._me}): at {place} with nothing "
                                     "to serve")
                table = job.task.params.get("table", place)
                self._show(f"{job.task.id}: {job.task.params.get('item', item)} for {table}")
                self._until(lambda: self._item() is None, self.wait_timeout_s,
                            f"the guest at {place} taking {item}")
                self.hold.set(None, None)
                self._show("")
                self._lift(0.0)
                job.signal("served")
            done.append([op, place, round(clock.now(), 2)])
        self.phase = "done"
        return {"robot": self._me, "task": job.task.id, "role": job.role.name,
                "steps": done}


def main(argv: list[str] | None = None) -> int:
    """``python -m behaviours.market.serving ZONE [--world serve] [--lease-s S]``: the
    zone keeper of ZONE (a speed zone of the world), as agent ``keeper_<ZONE>``."""
    parser = argparse.ArgumentParser(prog="python -m behaviours.market.serving",
                                     description=ZoneKeeper.__doc__)
    parser.add_argument("zone", help="the world's zone it keeps (one robot at a time)")
    parser.add_argument("--world", default="serve")
    parser.add_argument("--lease-s", type=float, default=3.0, help="its directory lease")
    args = parser.parse_args(argv)
    zones = sorted(z.name for z in site(args.world).zones)
    if args.zone not in zones:
        parser.error(f"no zone {args.zone!r} in world {args.world!r}; it has {zones}")
    return serve(f"keeper_{args.zone}", ZoneKeeper, {"station": args.zone},
                 lease_s=args.lease_s)


if __name__ == "__main__":
    raise SystemExit(main())
