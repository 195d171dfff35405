"""``with`` for the framework's long-lived objects, written once.

:class:`Closing` closes what it owns at the end of the block (an agent, a link, a fleet);
:class:`Running` starts on entry and stops at the end (a manager, a robot, a simulation):
``_stop_with`` names the stopping method (``shutdown`` unless a class says otherwise).
"""

from __future__ import annotations

from types import TracebackType
from typing import ClassVar, Self


class Closing:
    """``with obj:`` ... ``obj.close()`` at the end of the block, however it ends."""

    def close(self) -> None:  # pragma: no cover - every user defines its own
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


class Running:
    """``with obj:`` starts it (``start()``) and stops it at the end of the block (the
    method ``_stop_with`` names), however the block ends."""

    _stop_with: ClassVar[str] = "shutdown"

    def start(self) -> None:  # pragma: no cover - every user defines its own
        raise NotImplementedError

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        getattr(self, self._stop_with)()
