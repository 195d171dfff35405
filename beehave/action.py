"""Action: one basic skill of a robot (drive somewhere, lift, play a sound).

Only one action of each ``action_type`` runs at a time across the whole manager (the type
lock); :meth:`Behavior.start_action` takes it and the action gives it back when it ends.
"""

from __future__ import annotations

import threading
import time
from typing import Any, ClassVar, Self

from beehave.errors import Interrupted
from beehave.events import Event, EventKind
from beehave.runnable import Runnable, _Pause
from beehave.status import Status


class Action(Runnable):
    """Subclass it and write :meth:`run`; optionally :meth:`safe_state`.

    Parameters go to your own ``__init__`` (no need to call ``super().__init__()``)::

        class Drive(Action):
            action_type = "driving"

            def __init__(self, speed_mps: float) -> None:
                self.speed_mps = speed_mps

            def run(self) -> float:
                travelled = 0.0
                while not self.interrupted and travelled < 1.0:
                    travelled += self.speed_mps * 0.1
                    self.sleep(0.1)
                return travelled

            def safe_state(self) -> None:
                robot.stop()

    The object is its own handle: ``.status``, ``.result``, ``.error``, ``.wait(timeout)``,
    ``.interrupt()``.
    """

    #: The lock domain ("driving", "lifting", "sound" …). Defaults to the class name and
    #: is inherited, so a subclass of a driving action is a driving action.
    action_type: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if not cls.action_type:
            cls.action_type = cls.__name__
        if not isinstance(cls.action_type, str):
            raise TypeError(f"{cls.__name__}.action_type must be a str, "
                            f"not {type(cls.action_type).__name__}")

    __safe_state_error: BaseException | None
    _HAS_SAFE_STATE: ClassVar[bool] = True

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        self = super().__new__(cls)
        self.__safe_state_error = None
        return self

    @property
    def safe_state_error(self) -> BaseException | None:
        """The exception ``safe_state()`` raised, if it did."""
        return self.__safe_state_error

    def safe_state(self) -> None:
        """Leave the hardware this action controls predictable (e.g. zero velocity).

        Called exactly once whenever the action ends without success: interrupted, failed,
        or STUCK (then in a thread of its own, while ``run`` may still be executing; the
        action keeps its type lock until both have returned). Not called after success.
        Keep it short and make it not depend on ``run``'s state.

        A pause (``hl.pause()``) of an action without an ``on_pause()`` hook calls it too,
        once ``run`` has wound down; the action then ends later without a second call
        unless it ran again after ``resume()``.
        """

    def on_pause(self) -> None:
        """Optional hook: the manager pauses (``hl.pause()``). Bring the hardware to a
        safe stop and return (within ``stop_timeout_s``, or the action becomes STUCK);
        ``run`` keeps its thread, and its ``sleep``s stand still until :meth:`on_resume`.
        Make ``run`` command no motion meanwhile (e.g. a flag it checks).

        Without this hook (the default), a pause interrupts the action: ``interrupted``
        turns true, ``run`` returns, ``safe_state()`` runs, and after ``resume()`` ``run``
        is called again from the start — in the same object, with its type lock kept all
        along. Write actions whose ``run`` can start again (drive *to* a goal, lift *to*
        a height), or write both hooks.
        """

    def on_resume(self) -> None:
        """Optional hook: the pause ended (``hl.resume()``); ``run`` goes on where it was.
        Called only when :meth:`on_pause` is overridden too."""

    # ------------------------------------------------------------------ driver
    @property
    def _has_pause_hooks(self) -> bool:
        return type(self).on_pause is not Action.on_pause

    def _request_pause(self, *, hooked: bool) -> threading.Event:
        """The manager pauses: ask this action to wind down (or mark it for its
        ``on_pause`` hook, which the manager calls); returns what is set once paused."""
        with self._cond_lock:
            done = self._paused_done = threading.Event()
            if self._decided.is_set() or self._status not in (Status.PENDING, Status.RUNNING):
                done.set()
                return done
            self._pause = _Pause.HOOKED if hooked else _Pause.WIND_DOWN
            self._cond.notify_all()  # (also for _await_pause)
        if not hooked and self._manager is not None:
            self._manager._locks.poke()
        return done

    def _await_pause(self, timeout_s: float) -> None:
        """In its own thread, before ``run``: a pause was just asked for (a breakpoint on
        its type). Wait until the pause has reached this action (or it is interrupted), at
        most ``timeout_s``: the pause is carried out in a manager thread, and ``run`` would
        otherwise begin, and move the robot, before it lands."""
        manager = self._manager
        assert manager is not None

        def reached() -> bool:
            return (self._pause is not _Pause.NONE or self._interrupt_requested
                    or self._status is not Status.RUNNING)

        with manager.clock.blocked(reached), self._cond_lock:
            self._cond.wait_for(reached, timeout_s)

    def _request_resume(self) -> None:
        """The pause ended: let ``run`` go again (it waits in ``_pause_point``)."""
        with self._cond_lock:
            self._pause = _Pause.NONE
            self._cond.notify_all()

    def _pause_point(self, error: BaseException | None, *, ran: bool) -> bool:
        if self._pause is not _Pause.WIND_DOWN:
            # The common case, read without the lock: a pause asked for just after this
            # look finds run() running and winds it down as usual.
            return not ran
        manager = self._manager
        assert manager is not None
        with self._cond_lock:
            if (self._pause is not _Pause.WIND_DOWN or self._interrupt_requested
                    or self._status is not Status.RUNNING):
                return not ran
            if ran and error is not None and not isinstance(error, Interrupted):
                return False  # a real failure ends it, pause or not
        if ran:
            # run() wound down for the pause: the hardware to its safe state, once.
            self._pause_safe = True
            with manager.run_clock.unfrozen():
                self._enter_safe_state(paused=True)
        done = self._paused_done
        if done is not None:
            done.set()

        def resumed() -> bool:
            return (self._pause is not _Pause.WIND_DOWN or self._interrupt_requested
                    or self._status is not Status.RUNNING)

        with manager.clock.blocked(resumed), self._cond_lock:
            self._cond.wait_for(resumed)  # a resume, a switch or a shutdown ends it
            if self._interrupt_requested or self._status is not Status.RUNNING:
                return False
        self._pause_safe = False
        manager.events.emit(Event(EventKind.STARTED, self.path, Status.RUNNING.name,
                                  detail={"resumed": True, "action_type": self.action_type}))
        return True

    def _enter_safe_state(self, *, paused: bool = False) -> None:
        # Called exactly once: the status transition to STUCK or to a final status (one
        # place, under the object's lock) decides who calls it.
        assert self._manager is not None
        began = time.monotonic()
        try:
            self.safe_state()
        except Exception as exc:  # recorded on the handle and reported as an event
            self.__safe_state_error = exc
            self._manager.events.emit(
                Event(EventKind.SAFE_STATE_FAILED, self.path, self.status.name, exc))
        else:
            events = self._manager.events
            if not events.wants(EventKind.SAFE_STATE_RAN):
                return
            events.emit(Event(
                EventKind.SAFE_STATE_RAN, self.path, self.status.name,
                detail={"took_s": round(time.monotonic() - began, 6),
                        "action_type": self.action_type,
                        **({"forced": True} if self.status.name == "STUCK" else {}),
                        **({"paused": True} if paused else {})}))

    def _release(self) -> None:
        assert self._manager is not None
        self._manager._locks.release(self)

    def _on_interrupt(self, deadline: float | None) -> None:
        if self._manager is not None:
            self._manager._locks.poke()

    def _snapshot(self) -> dict[str, Any]:
        snap = super()._snapshot()
        snap["kind"] = "action"
        snap["action_type"] = self.action_type
        if self.safe_state_error is not None:
            snap["safe_state_error"] = repr(self.safe_state_error)
        if self.safe_state_pending:
            snap["safe_state_pending"] = True
        if self._pause is not _Pause.NONE:
            snap["paused"] = True
        return snap
