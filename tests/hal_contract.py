"""The contract every HAL plugin keeps. Inherit it in the plugin's test module::

    from hal_contract import HALContract

    class TestMyHAL(HALContract):
        hal_cls = MyHAL
        expected_keys = ("battery/percentage",)

        def hal_params(self) -> dict[str, Any]:   # optional: constructor parameters
            return {"port": "/dev/null"}
"""

from __future__ import annotations

import asyncio
import importlib.metadata
import json
import time
from collections.abc import Awaitable, Callable
from typing import Any, ClassVar, TypeVar

from beehave.blackboard import Blackboard
from beehave.events import Event, EventBus, EventKind
from beehave.hal import ENTRY_POINT_GROUP, HAL, HALManager
from beehave.status import Status
from beehave.testing import WALL_TIMEOUT_S, wall_timeout

T = TypeVar("T")


class HALContract:
    """Contract tests for one HAL class; not collected by itself (no ``Test`` prefix)."""

    hal_cls: ClassVar[type[HAL]]
    expected_keys: ClassVar[tuple[str, ...]] = ()
    """Blackboard keys the HAL must publish once loaded (and keep fresh while it runs)."""
    entry_point: ClassVar[str | None] = None
    """The name under ``beehave.hals`` the HAL is published as, if any."""

    def hal_params(self) -> dict[str, Any]:
        return {}

    def configure(self, manager: HALManager) -> None:
        """Give the manager what the HAL needs besides its parameters (e.g. a ROS node in
        ``manager.node``); called before the HAL is registered."""

    # -- helpers ---------------------------------------------------------------------------

    def run_with_manager(self, body: Callable[[HALManager, list[Event]], Awaitable[T]]) -> T:
        """Run ``body`` with a manager that has the HAL registered, then close the manager
        and check what every HAL owes: no task left, and ``safe_state`` called exactly once
        for every instance that was loaded."""
        safe_states: dict[int, int] = {}
        loaded: list[HAL] = []
        counted = _counting_safe_states(self.hal_cls, loaded, safe_states)

        async def main() -> T:
            events: list[Event] = []
            bus = EventBus()
            bus.subscribe(events.append)
            manager = HALManager(Blackboard(), events=bus, backoff_initial_s=0.01,
                                 backoff_max_s=0.05, stop_timeout_s=2.0)
            self.configure(manager)
            manager.register(counted, name=self.hal_cls.name, **self.hal_params())
            try:
                # Twice the suite's bound: a body's own waits (each WALL_TIMEOUT_S) report
                # what they waited for before this one cuts the whole body short.
                return await asyncio.wait_for(body(manager, events), wall_timeout(2.0))
            finally:
                await manager.close()
                manager.blackboard.unbind()
                leftover = asyncio.all_tasks() - {asyncio.current_task()}
                assert not leftover, f"tasks left by HAL {self.hal_cls.name!r}: {leftover}"
                assert not any(e.kind is EventKind.STUCK for e in events), \
                    f"HAL {self.hal_cls.name!r} ignored its cancellation at unload"

        result = asyncio.run(main())
        for hal in loaded:
            calls = safe_states.get(id(hal), 0)
            assert calls == 1, (f"HAL {self.hal_cls.name!r}: safe_state() ran {calls} times "
                                "at unload, not once")
        return result

    @staticmethod
    async def settle(turns: int = 20) -> None:
        """Let the HAL's run() take a few steps."""
        for _ in range(turns):
            await asyncio.sleep(0)

    # -- the contract ----------------------------------------------------------------------

    def test_has_a_name(self) -> None:
        assert isinstance(self.hal_cls.name, str) and self.hal_cls.name
        assert issubclass(self.hal_cls, HAL)

    def test_loads_runs_and_reports_started(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            hal = await manager.load(self.hal_cls.name)
            await self.settle()
            assert isinstance(hal, self.hal_cls)
            assert hal.status is Status.RUNNING and hal.error is None
            assert manager.loaded == {self.hal_cls.name: hal}
            assert any(e.kind is EventKind.STARTED and e.subject == f"hal:{hal.name}"
                       for e in events)
        self.run_with_manager(body)

    def test_publishes_its_keys_fresh_and_as_its_writer(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            hal = await manager.load(self.hal_cls.name)
            await self.settle()
            # A HAL fed from outside (a MAVLink vehicle's telemetry) publishes when its
            # input arrives: on a loaded machine that is later than a few loop turns.
            deadline = time.monotonic() + WALL_TIMEOUT_S
            while time.monotonic() < deadline and any(
                    manager.blackboard.entry(key) is None for key in self.expected_keys):
                await asyncio.sleep(0.01)
            for key in self.expected_keys:
                entry = manager.blackboard.entry(key)
                assert entry is not None, f"HAL {hal.name!r} did not publish {key!r}"
                assert entry.writer == f"hal:{hal.name}" and not entry.stale
        self.run_with_manager(body)

    def test_one_shared_instance_stopped_with_its_safe_state_after_the_last_release(
            self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            owner_a, owner_b = object(), object()
            first = await manager.load(self.hal_cls.name, owner=owner_a)
            second = await manager.load(self.hal_cls.name, owner=owner_b)
            again = await manager.load(self.hal_cls.name, owner=owner_a)
            assert first is second is again
            assert manager.refs(self.hal_cls.name) == 2
            await manager.release(self.hal_cls.name, owner=owner_a)
            assert first.status is Status.RUNNING
            await manager.release(self.hal_cls.name, owner=owner_b)
            assert first.status is Status.INTERRUPTED
            assert manager.loaded == {}
            assert not any(e.kind is EventKind.SAFE_STATE_FAILED for e in events)
        self.run_with_manager(body)

    def test_entries_read_as_stale_after_unload(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            await manager.load(self.hal_cls.name)
            await self.settle()
            await manager.release(self.hal_cls.name)
            for key in self.expected_keys:
                assert manager.blackboard.is_stale(key), key
        self.run_with_manager(body)

    def test_can_be_loaded_again_after_unload(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            first = await manager.load(self.hal_cls.name)
            await manager.release(self.hal_cls.name)
            second = await manager.load(self.hal_cls.name)
            await self.settle()
            assert second is not first and second.status is Status.RUNNING
            for key in self.expected_keys:
                assert not manager.blackboard.is_stale(key), key
        self.run_with_manager(body)

    def test_a_load_right_after_a_release_waits_for_the_old_instance_to_stop(self) -> None:
        """A logic that ends does not wait for its HAL's unload; the next one asking for it
        must not see the new instance's on_load before the old one's safe_state (the
        hardware would be set up and then stopped)."""
        async def body(manager: HALManager, events: list[Event]) -> None:
            first = await manager.load(self.hal_cls.name)
            await self.settle()
            await manager.release(self.hal_cls.name, wait=False)
            second = await manager.load(self.hal_cls.name)
            assert second is not first
            assert first.status is Status.INTERRUPTED, \
                f"HAL {self.hal_cls.name!r} loaded again before its old instance stopped"
            await manager.release(self.hal_cls.name, wait=False)  # close() still waits
        self.run_with_manager(body)

    def test_snapshot_is_json_serialisable(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            await manager.load(self.hal_cls.name)
            await self.settle()
            json.dumps(manager.snapshot())
            json.dumps(manager.blackboard.snapshot())
            assert manager.snapshot()[self.hal_cls.name]["status"] == "RUNNING"
        self.run_with_manager(body)

    def test_safe_state_runs_once_when_the_manager_closes_with_the_hal_loaded(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> HAL:
            hal = await manager.load(self.hal_cls.name, owner=object())
            await self.settle()
            return hal  # still held: close() must unload it, safe state included

        hal = self.run_with_manager(body)
        assert hal.status is Status.INTERRUPTED

    def test_found_through_its_entry_point(self) -> None:
        if self.entry_point is None:
            return  # not published as a plugin: nothing to check
        eps = {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
        assert self.entry_point in eps, f"{self.entry_point!r} not in {sorted(eps)}"
        assert eps[self.entry_point].load() is self.hal_cls
        assert HALManager().resolve(self.entry_point)[0] is self.hal_cls


def _counting_safe_states(cls: type[HAL], loaded: list[HAL],
                          calls: dict[int, int]) -> type[HAL]:
    """``cls`` with its on_load and safe_state counted per instance (the plugin's own code
    runs unchanged)."""

    class Counted(cls):  # type: ignore[valid-type,misc]
        async def on_load(self) -> None:
            loaded.append(self)
            await super().on_load()

        def safe_state(self) -> Any:
            calls[id(self)] = calls.get(id(self), 0) + 1
            return super().safe_state()

    Counted.__name__ = Counted.__qualname__ = cls.__name__
    return Counted
