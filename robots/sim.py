"""The physics simulation: a world and its robots stepped by pybullet in a thread it owns.

::

    from robots.sim import Simulation

    with Simulation("warehouse", real_time_factor=1.0) as sim:   # starts the thread
        emili = sim.robot("emili1")
        emili.set_cmd_vel(0.5, 0.0)
        ...
        sim.render_topdown("warehouse.png")
    # leaving the block stops the thread (joined) and disconnects pybullet

Or step by hand, as tests do (no thread; as fast as the machine goes)::

    sim = Simulation(world, real_time_factor=None)
    sim.step(240)          # one second of sim time at 240 Hz
    sim.close()

Timing. Physics advances in fixed steps of ``1 / rate_hz`` seconds of sim time; ``time_s``
is the sim clock (``steps × step``, exact — publish it on ``/clock``). The thread paces
itself to ``real_time_factor`` × wall-clock speed (1.0: real time; None: as fast as
possible). When the machine cannot keep up it runs as fast as it can and does not try to
catch up later.

Per step, in the sim thread: queued pybullet actions (LED colours, lift targets) run, each
robot applies its drive command (watchdog included), pybullet steps, each robot reads its
pose and twist; every ``1 / sensor_rate_hz`` the robots update battery, path, lift and
contact sensors, and every ``1 / scan_rate_hz`` their laser scans (spread over the steps
so that the robots' scans do not all fall on one step); then the ``on_step`` callbacks due
run.

Threads. Every public method may be called from any thread. pybullet itself is only ever
called from the thread that steps (the sim thread, or the caller of :meth:`step` when no
thread runs); other threads' requests wait in a queue for the next step.
"""

from __future__ import annotations

import ctypes
import enum
import functools
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import pybullet  # type: ignore[import-not-found]  # no stubs
from pybullet_utils.bullet_client import BulletClient  # type: ignore[import-untyped]

from beehave.lifecycle import Running
from robots.emili import Emili
from robots.errors import SimulationError, UnknownRobot
from robots.kobuki import Kobuki
from robots.quad import Quad
from robots.render import RobotSketch
from robots.render import render_topdown as _render_topdown
from robots.robot import URDF_DIR, SimRobot
from robots.world import Box, Cylinder, Station, World, load_world

if TYPE_CHECKING:

    from beehave.planning import GridPlanner

log = logging.getLogger(__name__)

ROBOT_KINDS: dict[str, type[SimRobot]] = {"emili": Emili, "kobuki": Kobuki, "quad": Quad}
"""The robot classes by the ``kind`` a world names."""

StepCallback = Callable[[float], None]
T = TypeVar("T")

_FLOOR_THICKNESS_M = 0.1


class SimState(enum.Enum):
    """Where a :class:`Simulation` is in its life."""

    IDLE = "idle"
    """Built; not stepping by itself. ``step()`` works; ``start()`` starts the thread."""
    RUNNING = "running"
    """The sim thread steps."""
    FAILED = "failed"
    """An ``on_step`` callback raised; the thread ended. ``stop()`` raises the error."""
    CLOSED = "closed"
    """Disconnected from pybullet; nothing works any more."""


@contextmanager
def quiet_stdout() -> Iterator[None]:
    """Silence the C library's prints on file descriptor 1 (pybullet's connect prints
    ``argv[0]=``); Python's own stdout is untouched."""
    fd = 1  # the C library writes to fd 1, whatever sys.stdout is (pytest swaps it)
    sys.stdout.flush()
    saved = os.dup(fd)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), fd)
            try:
                yield
            finally:
                # The C library buffers what it printed; flush it into /dev/null first.
                _libc_fflush()
                os.dup2(saved, fd)
    finally:
        os.close(saved)


def _libc_fflush() -> None:
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):  # no C library to flush (not on POSIX)
        pass


class _OnStep:
    def __init__(self, callback: StepCallback, every: int) -> None:
        self.callback = callback
        self.every = every


class Simulation(Running):
    """A world with its robots in pybullet (DIRECT mode: no window), stepped at a fixed rate.

    ``world`` is a :class:`~robots.world.World`, a YAML path or a shipped world's name.
    Options (keyword-only):

    - ``rate_hz``: physics steps per sim second (240: pybullet's tuned default).
    - ``real_time_factor``: how much faster than wall-clock time the thread runs;
      None = as fast as possible.
    - ``cmd_timeout_s``: the drive watchdog — sim time without ``set_cmd_vel`` after which a
      robot stops.
    - ``sensor_rate_hz``: battery, lift, path, bumpers, cliffs, wheel drop.
    - ``scan_rate_hz``: laser scans.

    The simulation owns its pybullet connection and its thread: :meth:`start` /
    :meth:`stop` (joins), :meth:`close` (stops and disconnects). As a context manager it
    starts on entry and closes on exit.
    """

    def __init__(self, world: World | str | Path, *, rate_hz: float = 240.0,
                 real_time_factor: float | None = 1.0, cmd_timeout_s: float = 0.5,
                 sensor_rate_hz: float = 50.0, scan_rate_hz: float = 10.0) -> None:
        if rate_hz <= 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self.world = world if isinstance(world, World) else load_world(world)
        self.rate_hz = float(rate_hz)
        self.step_s = 1.0 / self.rate_hz
        self.real_time_factor = real_time_factor
        self.cmd_timeout_s = float(cmd_timeout_s)
        self.sensor_rate_hz = min(float(sensor_rate_hz), self.rate_hz)
        self.scan_rate_hz = min(float(scan_rate_hz), self.sensor_rate_hz)
        self._sensor_every = max(1, round(self.rate_hz / self.sensor_rate_hz))
        self._scan_every = max(1, round(self.sensor_rate_hz / self.scan_rate_hz))
        self._steps = 0
        self._state = SimState.IDLE
        self._state_lock = threading.Lock()
        # Re-entrant: an on_step callback may send commands that run pybullet at once.
        self._step_lock = threading.RLock()
        self._queue_lock = threading.Lock()
        self._queue: list[Callable[[BulletClient], None]] = []
        self._threaded = False  # the sim thread takes the queue (under _queue_lock)
        self._callbacks: list[_OnStep] = []
        self._gate: Callable[[float], bool] | None = None
        self._wake = threading.Event()
        self._stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._wall_started_s = 0.0
        self._steps_at_start = 0

        with quiet_stdout():
            self._client = BulletClient(connection_mode=pybullet.DIRECT)
        c = self._client
        c.setGravity(0, 0, -9.81)
        c.setTimeStep(self.step_s)
        if self.world.physics.solver_iterations is not None:
            c.setPhysicsEngineParameter(numSolverIterations=self.world.physics.solver_iterations)
        self._physics_step = functools.partial(pybullet.stepSimulation,
                                               physicsClientId=self._client._client)
        self._ground_ids: frozenset[int] = frozenset()
        self._charging_stations: tuple[Station, ...] = tuple(
            self.world.stations_of_kind("charging"))
        self._build_world()
        self._robots: dict[str, SimRobot] = {}
        for index, spec in enumerate(self.world.robots):
            cls = ROBOT_KINDS[spec.kind]
            start = spec.start
            body = c.loadURDF(str(URDF_DIR / cls.urdf),
                              [start.x_m, start.y_m, cls.limits.wheel_radius_m + 0.002],
                              c.getQuaternionFromEuler([0, 0, start.yaw_rad]))
            self._robots[spec.namespace] = cls(self, spec, body, index)
        self._run_queue()
        log.debug("simulation of world %r with %d robot(s) at %g Hz", self.world.name,
                  len(self._robots), self.rate_hz)

    # ---- lifecycle ------------------------------------------------------------------

    @property
    def state(self) -> SimState:
        return self._state

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the sim thread (from an ``on_step`` callback), if any."""
        return self._error

    def start(self) -> None:
        """Start the sim thread (named ``beehave-sim``); it steps until :meth:`stop`."""
        with self._state_lock:
            self._require_open("start")
            if self._state is SimState.RUNNING:
                raise SimulationError("simulation already running; stop() it first")
            self._stop_event.clear()
            self._error = None
            self._state = SimState.RUNNING
            self._wall_started_s = time.perf_counter()
            self._steps_at_start = self._steps
            with self._queue_lock:
                self._threaded = True
            self._thread = threading.Thread(target=self._run, name="beehave-sim", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the sim thread and wait for it to end. Raises :class:`SimulationError`
        (caused by the callback's exception) when an ``on_step`` callback had failed.
        Stopping a simulation that is not running does nothing."""
        thread = self._thread
        if thread is not None:
            self._stop_event.set()
            self._wake.set()
            if thread is not threading.current_thread():
                thread.join()
            self._thread = None
        with self._state_lock:
            if self._state in (SimState.RUNNING, SimState.FAILED):
                failed = self._state is SimState.FAILED
                self._state = SimState.IDLE
                if failed and self._error is not None:
                    raise SimulationError(
                        f"the simulation stopped at {self.time_s:.3f} s because a callback "
                        f"(on_step or gate) raised {self._error!r}") from self._error

    def close(self) -> None:
        """Stop (see :meth:`stop`) and disconnect from pybullet. Idempotent."""
        if self._state is SimState.CLOSED:
            return
        try:
            self.stop()
        finally:
            with self._state_lock:
                self._state = SimState.CLOSED
            self._client.disconnect()

    _stop_with = "close"

    # ---- time -----------------------------------------------------------------------

    @property
    def time_s(self) -> float:
        """The sim clock: seconds of simulated time since the start."""
        return self._steps * self.step_s

    @property
    def steps(self) -> int:
        """Physics steps taken so far."""
        return self._steps

    def measured_real_time_factor(self) -> float:
        """Sim seconds per wall-clock second since the last :meth:`start` (0 before)."""
        wall = time.perf_counter() - self._wall_started_s
        if self._wall_started_s == 0.0 or wall <= 0:
            return 0.0
        return (self._steps - self._steps_at_start) * self.step_s / wall

    # ---- robots ---------------------------------------------------------------------

    @property
    def robots(self) -> dict[str, SimRobot]:
        """The robots by namespace (a copy)."""
        return dict(self._robots)

    def robot(self, namespace: str) -> SimRobot:
        """The robot with ``namespace``; :class:`UnknownRobot` lists the namespaces."""
        try:
            return self._robots[namespace]
        except KeyError:
            raise UnknownRobot(namespace, self._robots) from None

    def emili(self, namespace: str) -> Emili:
        """The EMILI with ``namespace`` (typed, for EMILI-only methods)."""
        robot = self.robot(namespace)
        if not isinstance(robot, Emili):
            raise UnknownRobot(namespace, [n for n, r in self._robots.items()
                                           if isinstance(r, Emili)])
        return robot

    def kobuki(self, namespace: str) -> Kobuki:
        """The Kobuki with ``namespace`` (typed, for Kobuki-only methods)."""
        robot = self.robot(namespace)
        if not isinstance(robot, Kobuki):
            raise UnknownRobot(namespace, [n for n, r in self._robots.items()
                                           if isinstance(r, Kobuki)])
        return robot

    # ---- hooks ----------------------------------------------------------------------

    def on_step(self, callback: StepCallback, *, rate_hz: float | None = None
                ) -> Callable[[], None]:
        """Call ``callback(time_s)`` after physics steps, in the stepping thread — the
        place to publish ``/clock``, odometry and scans.

        ``rate_hz`` None: after every step; otherwise every ``round(rate_hz_sim / rate_hz)``
        steps (e.g. 50 Hz at 240 Hz: every 5th step, 48 Hz). The callback must be quick: it
        holds up the physics. If it raises, the thread ends (state FAILED) and
        :meth:`stop` raises :class:`SimulationError` with the exception as cause.
        Returns a function that removes the callback.
        """
        every = 1 if rate_hz is None else max(1, round(self.rate_hz / rate_hz))
        entry = _OnStep(callback, every)
        with self._queue_lock:
            self._callbacks = [*self._callbacks, entry]

        def remove() -> None:
            with self._queue_lock:
                self._callbacks = [e for e in self._callbacks if e is not entry]

        return remove

    def set_gate(self, gate: Callable[[float], bool] | None) -> Callable[[], None]:
        """Hold the sim thread while ``gate(time_s)`` is True (lockstep: the sim node holds
        it for controllers that have not answered yet). The thread asks the gate before
        every step, again after each :meth:`wake` and at least every 20 ms (wall) while it
        holds — so a gate may let go on a timeout — and runs queued requests (``call``,
        LED colours) meanwhile. The gate must be quick. A new gate replaces the old one;
        None removes it. Stepping by hand (:meth:`step`) ignores the gate.

        Returns ``remove()``, which removes this gate only if it is still the one set — so
        whoever set a gate can take it away without clearing someone else's."""
        with self._state_lock:
            self._gate = gate
        self._wake.set()

        def remove() -> None:
            with self._state_lock:
                if self._gate is not gate:
                    return
                self._gate = None
            self._wake.set()

        return remove

    @property
    def gate(self) -> Callable[[float], bool] | None:
        """The gate set now (:meth:`set_gate`), if any."""
        return self._gate

    def wake(self) -> None:
        """Tell a holding sim thread to ask its gate again (the gate's answer changed)."""
        self._wake.set()

    # ---- stepping -------------------------------------------------------------------

    def step(self, n: int = 1) -> None:
        """Step the physics ``n`` times in the calling thread (tests, scripted runs);
        not while the sim thread runs. An ``on_step`` callback's exception propagates."""
        if self._state is not SimState.IDLE:
            self._require_open("step")
            raise SimulationError(f"cannot step by hand while the simulation is "
                                  f"{self._state.value}; stop() it first")
        with self._step_lock:
            for _ in range(n):
                self._step_once()

    def run_for(self, duration_s: float) -> None:
        """Step by hand for ``duration_s`` of sim time (rounded to whole steps)."""
        self.step(max(0, round(duration_s * self.rate_hz)))

    def call(self, action: Callable[[BulletClient], T]) -> T:
        """Run ``action(client)`` with the pybullet client where it is safe — in the sim
        thread before its next step when it runs, else here — and return its result.
        For inspection and extras (camera images, debug queries)."""
        if self._threaded and threading.current_thread() is not self._thread:
            future: Future[T] = Future()

            def run(client: BulletClient) -> None:
                try:
                    future.set_result(action(client))
                except BaseException as exc:
                    future.set_exception(exc)

            self._post(run)
            return future.result()
        self._require_open("call")
        with self._step_lock:
            return action(self._client)

    def _post(self, action: Callable[[BulletClient], None]) -> None:
        """Run ``action(client)`` in the sim thread before its next step, or right here
        when no thread steps (so e.g. a new LED colour shows in the next picture)."""
        with self._queue_lock:
            if self._threaded:
                self._queue.append(action)
                return
        with self._step_lock:
            action(self._client)

    def _run_queue(self) -> None:
        with self._queue_lock:
            queue, self._queue = self._queue, []
        for action in queue:
            action(self._client)

    def _step_once(self) -> None:
        if self._queue:
            self._run_queue()
        now = self.time_s
        robots = list(self._robots.values())
        for robot in robots:
            robot._apply(now)
        self._physics_step()
        self._steps += 1
        now = self.time_s
        for robot in robots:
            robot._update_state(now)
        sensor_every = self._sensor_every
        for robot in robots:
            # Spread the robots over the steps so their sensor work does not pile up.
            tick, rest = divmod(self._steps + robot.index, sensor_every)
            if rest == 0:
                scan = (tick + robot.index) % self._scan_every == 0
                robot._sense(now, sensor_every * self.step_s, scan=scan)
        for entry in self._callbacks:
            if self._steps % entry.every == 0:
                entry.callback(now)

    def _run(self) -> None:
        period = self.step_s
        next_s = time.perf_counter()
        try:
            while not self._stop_event.is_set():
                if self._gate is not None and self._held():
                    break
                with self._step_lock:
                    self._step_once()
                factor = self.real_time_factor
                if factor is None or factor <= 0:
                    continue
                next_s += period / factor
                delay = next_s - time.perf_counter()
                if delay > 0:
                    self._stop_event.wait(delay)
                elif delay < -0.1:
                    next_s = time.perf_counter()  # fell behind: do not sprint to catch up
        except BaseException as exc:
            log.error("simulation thread ended at %.3f s: %r", self.time_s, exc)
            self._error = exc
            with self._state_lock:
                self._state = SimState.FAILED
        finally:
            with self._queue_lock:
                self._threaded = False
                pending, self._queue = self._queue, []
            # Requests that came in after the last step still run (and get their answer).
            with self._step_lock:
                for action in pending:
                    action(self._client)

    def _held(self) -> bool:
        """Wait while the gate holds; True when a stop came meanwhile."""
        while True:
            self._wake.clear()  # before asking: a wake() from now on is not lost
            gate = self._gate
            if gate is None or not gate(self.time_s):
                return False
            if self._queue:
                with self._step_lock:
                    self._run_queue()
            if self._stop_event.is_set():
                return True
            self._wake.wait(0.02)

    def _require_open(self, what: str) -> None:
        if self._state is SimState.CLOSED:
            raise SimulationError(f"cannot {what}: the simulation is closed")

    # ---- world building -------------------------------------------------------------

    def _static_box(self, center: tuple[float, float, float], half: tuple[float, float, float],
                    yaw_rad: float, rgba: list[float], *, collide: bool = True) -> int:
        c = self._client
        col = c.createCollisionShape(c.GEOM_BOX, halfExtents=half) if collide else -1
        vis = c.createVisualShape(c.GEOM_BOX, halfExtents=half, rgbaColor=rgba)
        body: int = c.createMultiBody(0.0, col, vis, list(center),
                                      c.getQuaternionFromEuler([0, 0, yaw_rad]))
        return body

    def _build_world(self) -> None:
        c = self._client
        w = self.world
        ground = []
        floor_rgba = [*w.floor.color, 1.0]
        for x0, y0, x1, y1 in w.floor_rects():
            body = self._static_box(((x0 + x1) / 2, (y0 + y1) / 2, -_FLOOR_THICKNESS_M / 2),
                                    ((x1 - x0) / 2, (y1 - y0) / 2, _FLOOR_THICKNESS_M / 2),
                                    0.0, floor_rgba)
            c.changeDynamics(body, -1, lateralFriction=1.0)
            ground.append(body)
        for lane in w.lanes:
            for (ax, ay), (bx, by) in zip(lane.points_m, lane.points_m[1:], strict=False):
                length = math.hypot(bx - ax, by - ay)
                self._static_box(((ax + bx) / 2, (ay + by) / 2, 0.0005),
                                 (length / 2 + lane.width_m / 2, lane.width_m / 2, 0.0005),
                                 math.atan2(by - ay, bx - ax), [*lane.color, 1.0],
                                 collide=False)
        station_rgba = {"charging": [0.3, 0.7, 0.35, 1.0], "pickup": [0.3, 0.45, 0.85, 1.0],
                        "dropoff": [0.9, 0.55, 0.2, 1.0]}
        for station in w.stations:
            self._static_box((*station.center_m, 0.0003),
                             (station.size_m[0] / 2, station.size_m[1] / 2, 0.0003),
                             math.radians(station.yaw_deg), station_rgba[station.kind],
                             collide=False)
        self._ground_ids = frozenset(ground)
        for wall in w.walls:
            (ax, ay), (bx, by) = wall.from_m, wall.to_m
            self._static_box(((ax + bx) / 2, (ay + by) / 2, wall.height_m / 2),
                             (math.hypot(bx - ax, by - ay) / 2, wall.thickness_m / 2,
                              wall.height_m / 2),
                             math.atan2(by - ay, bx - ax), [0.35, 0.35, 0.38, 1.0])
        for shelf in w.shelves:
            self._static_box((*shelf.center_m, shelf.height_m / 2),
                             (shelf.size_m[0] / 2, shelf.size_m[1] / 2, shelf.height_m / 2),
                             math.radians(shelf.yaw_deg),
                             [*(shelf.color or (0.45, 0.33, 0.22)), 1.0])
        # A factory's parts: machines block like shelves; their delivery areas and the
        # depots are flat paint (the physics of loading lives in robots.factory).
        for machine in w.machines:
            self._static_box((*machine.center_m, machine.height_m / 2),
                             (machine.size_m[0] / 2, machine.size_m[1] / 2,
                              machine.height_m / 2),
                             math.radians(machine.yaw_deg), [*machine.color, 1.0])
        flat = [(m.delivery, [0.85, 0.75, 0.30, 1.0]) for m in w.machines]
        flat += [(d.area, [0.55, 0.40, 0.20, 1.0]) for d in w.depots]
        for area, rgba in flat:
            self._static_box((*area.center_m, 0.0003),
                             (area.size_m[0] / 2, area.size_m[1] / 2, 0.0003),
                             math.radians(area.yaw_deg), rgba, collide=False)
        for obstacle in w.obstacles:
            rgba = [*(obstacle.color or (0.5, 0.5, 0.55)), 1.0]
            if isinstance(obstacle, Box):
                self._static_box((*obstacle.center_m, obstacle.height_m / 2),
                                 (obstacle.size_m[0] / 2, obstacle.size_m[1] / 2,
                                  obstacle.height_m / 2),
                                 math.radians(obstacle.yaw_deg), rgba)
            elif isinstance(obstacle, Cylinder):
                col = c.createCollisionShape(c.GEOM_CYLINDER, radius=obstacle.radius_m,
                                             height=obstacle.height_m)
                vis = c.createVisualShape(c.GEOM_CYLINDER, radius=obstacle.radius_m,
                                          length=obstacle.height_m, rgbaColor=rgba)
                c.createMultiBody(0.0, col, vis, [*obstacle.center_m, obstacle.height_m / 2])

    # ---- pictures -------------------------------------------------------------------

    def render_topdown(self, path: str | Path, *, scale_px_per_m: float = 40.0,
                       planned: Sequence[Sequence[tuple[float, float]]] = (),
                       planner: GridPlanner | None = None,
                       levels: Mapping[str, float] | None = None,
                       loads: Collection[str] = (), title: str | None = None) -> Path:
        """Write a top-down PNG of the world, the robots (EMILI in its LED colour, Kobuki
        with its LEDs) and their driven paths; drawn with PIL from known geometry and the
        robots' snapshots (no pybullet call), so safe while running. ``planned`` adds
        planned paths (waypoints), ``planner`` shades its inflated obstacles; ``levels``
        (machine name → level), ``loads`` (namespaces of loaded robots) and ``title`` are
        what :meth:`robots.factory.Factory.render_topdown` passes. Returns the path."""
        sketches = []
        for robot in self._robots.values():
            pose = robot.pose()
            leds: tuple[tuple[float, float, float], ...]
            if isinstance(robot, Emili):
                leds = (robot.leds(),)
            elif isinstance(robot, Kobuki):
                from robots.kobuki import LED_RGBA
                leds = tuple(LED_RGBA[name][:3] for name in robot.leds())
            else:
                leds = ()
            sketches.append(RobotSketch(robot.namespace, robot.kind, pose.x_m, pose.y_m,
                                        pose.yaw_rad, leds, robot.path(),
                                        loaded=robot.namespace in loads))
        return _render_topdown(self.world, sketches, path, scale_px_per_m=scale_px_per_m,
                               planned=planned, planner=planner, levels=levels, title=title)

    def camera_image(self, *, center_m: tuple[float, float] | None = None,
                     height_m: float = 15.0, width_px: int = 320, height_px: int = 192,
                     fov_deg: float = 60.0) -> Any:
        """A real rendered picture (pybullet's TinyRenderer, slow: ~0.1 s) looking straight
        down from ``height_m`` above ``center_m`` (default: the floor's centre), as an
        ``(height_px, width_px, 3)`` uint8 numpy array. Runs in the sim thread."""
        import numpy as np

        cx, cy = center_m or (self.world.floor.size_m[0] / 2, self.world.floor.size_m[1] / 2)

        def shoot(c: BulletClient) -> Any:
            view = c.computeViewMatrix([cx, cy, height_m], [cx, cy, 0.0], [0, 1, 0])
            proj = c.computeProjectionMatrixFOV(fov_deg, width_px / height_px, 0.1,
                                                height_m + 1)
            _, _, rgba, _, _ = c.getCameraImage(width_px, height_px, view, proj,
                                                renderer=c.ER_TINY_RENDERER)
            return np.reshape(np.asarray(rgba, dtype=np.uint8),
                              (height_px, width_px, 4))[:, :, :3].copy()

        return self.call(shoot)

    def __repr__(self) -> str:
        return (f"<Simulation {self.world.name!r} {self._state.value} t={self.time_s:.3f} s "
                f"robots={list(self._robots)}>")
