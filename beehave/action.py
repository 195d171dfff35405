"""Action: one basic skill of a robot (drive somewhere, lift, play a sound).

Only one action of each ``action_type`` runs at a time across the whole manager (the type
lock); :meth:`Behavior.start_action` takes it and the action gives it back when it ends.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar, Self

from beehave.events import Event, EventKind
from beehave.runnable import Runnable


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

    #: The exception ``safe_state()`` raised, if it did.
    safe_state_error: BaseException | None

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        self = super().__new__(cls)
        object.__setattr__(self, "safe_state_error", None)
        return self

    def safe_state(self) -> None:
        """Leave the hardware this action controls predictable (e.g. zero velocity).

        Called exactly once whenever the action ends without success: interrupted, failed,
        or STUCK (then in a thread of its own, while ``run`` may still be executing; the
        action keeps its type lock until both have returned). Not called after success.
        Keep it short and make it not depend on ``run``'s state.
        """

    # ------------------------------------------------------------------ driver
    def _enter_safe_state(self) -> None:
        # Called exactly once: the status transition to STUCK or to a final status (one
        # place, under the object's lock) decides who calls it.
        assert self._manager is not None
        began = time.monotonic()
        try:
            self.safe_state()
        except Exception as exc:  # recorded on the handle and reported as an event
            object.__setattr__(self, "safe_state_error", exc)
            self._manager.events.emit(
                Event(EventKind.SAFE_STATE_FAILED, self.path, self.status.name, exc))
        else:
            self._manager.events.emit(Event(
                EventKind.SAFE_STATE_RAN, self.path, self.status.name,
                detail={"took_s": round(time.monotonic() - began, 6),
                        "action_type": self.action_type,
                        **({"forced": True} if self.status.name == "STUCK" else {})}))

    def _has_safe_state(self) -> bool:
        return True

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
        return snap
